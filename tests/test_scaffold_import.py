"""Importing a trained Scaffold-GS output (``proxycodec.scaffold_gs``, ``formats/torchscript.py``).

The output folders are made here with the torch calls Scaffold-GS makes (``GaussianModel``'s ``nn.Sequential`` MLPs,
``torch.jit.trace(mlp, example).save(path)`` in mode "split", ``torch.save({name: state_dict})`` in mode "unite",
``save_ply``'s layout, ``camera_to_JSON``, ``str(Namespace(...))``), so the bytes are real TorchScript and real
``torch.save``. The reference decoder below is Scaffold-GS's ``generate_neural_gaussians`` written again in torch from
its source, run on the same in-memory modules.
"""

from __future__ import annotations

import json
import os
import pickle
import zipfile
from argparse import Namespace
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from conftest import forged_tensor_pickle, os_system_pickle, replace_zip_record
from torch import nn

from proxycodec.camera import Camera
from proxycodec.errors import ProxycodecError
from proxycodec.formats.scaffold_ply import ScaffoldPly, write_scaffold_ply
from proxycodec.formats.torchscript import read_torch_checkpoint, read_torchscript
from proxycodec.model import render_scene
from proxycodec.netconfig import DecoderConfig
from proxycodec.render import GateConfig, project, rasterize
from proxycodec.scaffold_gs import find_scaffold_files, is_scaffold_output, load_scaffold_output

F, K, VOXEL = 32, 10, 0.05
pytestmark = pytest.mark.filterwarnings("ignore:`torch.jit.trace:DeprecationWarning")


# ================================================================================================ making outputs
class FieldComponent(nn.Module):  # scene/embedding.py of Scaffold-GS
    def __init__(self, in_dim=None, out_dim=None):
        super().__init__()
        self.in_dim, self.out_dim = in_dim, out_dim


class Embedding(FieldComponent):
    def __init__(self, in_dim, out_dim):
        super().__init__()
        self.in_dim, self.out_dim = in_dim, out_dim
        self.embedding = torch.nn.Embedding(in_dim, out_dim)

    def forward(self, in_tensor):
        return self.embedding(in_tensor)


def scaffold_mlps(*, opacity_dist=False, cov_dist=False, color_dist=False, bank=False, appearance_dim=0,
                  n_cameras=3, seed=0) -> dict[str, nn.Module]:
    """``GaussianModel.__init__``'s networks (+ ``set_appearance``), in eval mode."""
    torch.manual_seed(seed)
    m = {}
    if bank:
        m["bank"] = nn.Sequential(nn.Linear(3 + 1, F), nn.ReLU(True), nn.Linear(F, 3), nn.Softmax(dim=1))
    m["opacity"] = nn.Sequential(nn.Linear(F + 3 + opacity_dist, F), nn.ReLU(True), nn.Linear(F, K), nn.Tanh())
    m["cov"] = nn.Sequential(nn.Linear(F + 3 + cov_dist, F), nn.ReLU(True), nn.Linear(F, 7 * K))
    m["color"] = nn.Sequential(nn.Linear(F + 3 + color_dist + appearance_dim, F), nn.ReLU(True),
                               nn.Linear(F, 3 * K), nn.Sigmoid())
    with torch.no_grad():
        m["opacity"][2].bias.add_(0.3)  # more visible Gaussians than at init
        if bank:
            m["bank"][2].weight.mul_(4.0)  # far from uniform blend weights
    if appearance_dim:
        m["appearance"] = Embedding(n_cameras, appearance_dim)
    return {k: v.eval() for k, v in m.items()}


def scene_arrays(seed=0, m=150):
    rng = np.random.default_rng(seed)
    grid = rng.choice(8 ** 3, size=m, replace=False)
    idx = np.stack(np.unravel_index(grid, (8, 8, 8)), 1).astype(np.float64)
    pos = (idx * VOXEL - 0.2).astype(np.float32)
    return ScaffoldPly(positions=pos, offsets=rng.normal(0, 0.6, (m, K, 3)), features=rng.normal(0, 0.7, (m, F)),
                       scalings=np.log(np.full((m, 6), VOXEL)) + rng.normal(0, 0.2, (m, 6)),
                       opacity=rng.normal(size=m), rotations=rng.normal(size=(m, 4)))


def view_cameras(n=3, w=40, h=30) -> list[Camera]:
    return [Camera.look_at((1.3 * np.cos(a), 1.3 * np.sin(a), 0.5), (0, 0, 0), fov_x_deg=55, width=w, height=h,
                           name=f"r_{i}") for i, a in enumerate(np.linspace(0.3, 2.0, n))]


def camera_json(i: int, cam: Camera) -> dict:
    """3DGS's ``camera_to_JSON``: centre and camera-to-world rotation."""
    return {"id": i, "img_name": cam.name, "width": cam.width, "height": cam.height,
            "position": cam.center.tolist(), "rotation": cam.rotation.T.tolist(),
            "fy": cam.fy, "fx": cam.fx}


def write_output(root: Path, mlps: dict[str, nn.Module], mode="split", *, iteration=30000, ply=None,
                 cfg: dict | None = None, white=True, seed=0) -> Path:
    """A Scaffold-GS output folder: cfg_args, cameras.json, point_cloud/iteration_N/{point_cloud.ply, MLPs}."""
    it = root / "point_cloud" / f"iteration_{iteration}"
    it.mkdir(parents=True)
    write_scaffold_ply(it / "point_cloud.ply", ply or scene_arrays(seed))
    if mode == "split":  # save_mlp_checkpoints(path, mode='split')
        for name, file in (("opacity", "opacity_mlp.pt"), ("cov", "cov_mlp.pt"), ("color", "color_mlp.pt"),
                           ("bank", "feature_bank_mlp.pt")):
            if name in mlps:
                net = mlps[name]
                torch.jit.trace(net, (torch.rand(1, net[0].in_features),)).save(str(it / file))
        if "appearance" in mlps:
            torch.jit.trace(mlps["appearance"], (torch.zeros((1,), dtype=torch.long),)).save(
                str(it / "embedding_appearance.pt"))
    else:
        d = {"opacity_mlp": mlps["opacity"].state_dict(), "cov_mlp": mlps["cov"].state_dict(),
             "color_mlp": mlps["color"].state_dict()}
        if "bank" in mlps:
            d["feature_bank_mlp"] = mlps["bank"].state_dict()
        if "appearance" in mlps:
            d["appearance"] = mlps["appearance"].state_dict()
        torch.save(d, it / "checkpoints.pth")
    args = {"sh_degree": 3, "feat_dim": F, "n_offsets": K, "voxel_size": VOXEL, "update_depth": 3,
            "update_init_factor": 16, "update_hierachy_factor": 4, "use_feat_bank": "bank" in mlps,
            "source_path": "/data/scene", "model_path": str(root), "images": "images", "resolution": -1,
            "white_background": white, "data_device": "cuda", "eval": True, "lod": 0,
            "appearance_dim": int(mlps["appearance"].out_dim) if "appearance" in mlps else 0,
            "add_opacity_dist": mlps["opacity"][0].in_features == F + 4,
            "add_cov_dist": mlps["cov"][0].in_features == F + 4,
            "add_color_dist": mlps["color"][0].in_features - (mlps["appearance"].out_dim if "appearance" in mlps
                                                              else 0) == F + 4,
            "ratio": 1, **(cfg or {})}
    (root / "cfg_args").write_text(str(Namespace(**args)))
    (root / "cameras.json").write_text(json.dumps([camera_json(i, c) for i, c in enumerate(view_cameras())]))
    return root


# ================================================================================================ the reference
@torch.no_grad()
def generate_neural_gaussians(ply: ScaffoldPly, mlps: dict[str, nn.Module], camera_center, uid=0,
                              add_opacity_dist=False, add_cov_dist=False, add_color_dist=False):
    """Scaffold-GS's ``gaussian_renderer.generate_neural_gaussians`` (all anchors visible), from its source."""
    feat = torch.tensor(ply.features)
    anchor = torch.tensor(ply.positions)
    grid_offsets = torch.tensor(ply.offsets)
    grid_scaling = torch.exp(torch.tensor(ply.scalings))
    n_offsets = grid_offsets.shape[1]
    ob_view = anchor - camera_center
    ob_dist = ob_view.norm(dim=1, keepdim=True)
    ob_view = ob_view / ob_dist
    if "bank" in mlps:
        cat_view = torch.cat([ob_view, ob_dist], dim=1)
        bank_weight = mlps["bank"](cat_view).unsqueeze(dim=1)  # [n, 1, 3]
        feat = feat.unsqueeze(dim=-1)
        feat = feat[:, ::4, :1].repeat([1, 4, 1]) * bank_weight[:, :, :1] + \
            feat[:, ::2, :1].repeat([1, 2, 1]) * bank_weight[:, :, 1:2] + \
            feat[:, ::1, :1] * bank_weight[:, :, 2:]
        feat = feat.squeeze(dim=-1)
    cat_local_view = torch.cat([feat, ob_view, ob_dist], dim=1)
    cat_local_view_wodist = torch.cat([feat, ob_view], dim=1)
    if "appearance" in mlps:
        camera_indicies = torch.ones_like(cat_local_view[:, 0], dtype=torch.long) * uid
        appearance = mlps["appearance"](camera_indicies)
    neural_opacity = mlps["opacity"](cat_local_view if add_opacity_dist else cat_local_view_wodist)
    neural_opacity = neural_opacity.reshape([-1, 1])
    mask = (neural_opacity > 0.0).view(-1)
    opacity = neural_opacity[mask]
    base = cat_local_view if add_color_dist else cat_local_view_wodist
    color = mlps["color"](torch.cat([base, appearance], dim=1) if "appearance" in mlps else base)
    color = color.reshape([anchor.shape[0] * n_offsets, 3])
    scale_rot = mlps["cov"](cat_local_view if add_cov_dist else cat_local_view_wodist)
    scale_rot = scale_rot.reshape([anchor.shape[0] * n_offsets, 7])
    offsets = grid_offsets.view([-1, 3])
    concatenated = torch.cat([grid_scaling, anchor], dim=-1)
    concatenated_repeated = concatenated.repeat_interleave(n_offsets, dim=0)  # einops 'n (c) -> (n k) (c)'
    concatenated_all = torch.cat([concatenated_repeated, color, scale_rot, offsets], dim=-1)
    masked = concatenated_all[mask]
    scaling_repeat, repeat_anchor, color, scale_rot, offsets = masked.split([6, 3, 3, 7, 3], dim=-1)
    scaling = scaling_repeat[:, 3:] * torch.sigmoid(scale_rot[:, :3])
    rot = torch.nn.functional.normalize(scale_rot[:, 3:7])
    offsets = offsets * scaling_repeat[:, :3]
    xyz = repeat_anchor + offsets
    return xyz, color, opacity[:, 0], scaling, rot


VARIANTS = {
    # name: (mode, scaffold_mlps kwargs)
    "split_default": ("split", {}),
    "split_all_dist": ("split", {"opacity_dist": True, "cov_dist": True, "color_dist": True}),
    "split_bank_mixed_dist": ("split", {"bank": True, "opacity_dist": True, "color_dist": True}),
    "split_appearance": ("split", {"appearance_dim": 8, "cov_dist": True}),
    "unite_default": ("unite", {}),
    "unite_bank_appearance": ("unite", {"bank": True, "appearance_dim": 4, "opacity_dist": True,
                                        "color_dist": True}),
}


def _dists(kw):
    return {f"add_{k}_dist": kw.get(f"{k}_dist", False) for k in ("opacity", "cov", "color")}


@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_import_decodes_and_renders_as_scaffold_gs(variant, tmp_path):
    mode, kw = VARIANTS[variant]
    mlps = scaffold_mlps(**kw)
    root = write_output(tmp_path / "out", mlps, mode)
    ply = scene_arrays(0)
    model = load_scaffold_output(root)
    cfg = model.decoder.config
    assert (cfg.opacity_dist, cfg.cov_dist, cfg.color_dist) == tuple(kw.get(f"{k}_dist", False)
                                                                     for k in ("opacity", "cov", "color"))
    assert cfg.feature_bank == (F if kw.get("bank") else 0)
    assert cfg.embedding == "film" and cfg.film_xi_range == (0.1, 1.0) and cfg.gate == GateConfig()
    assert model.background == (1.0, 1.0, 1.0) and model.scene.voxel_size == VOXEL
    assert len(model.cameras) == 3 and model.meta["scaffold_gs"]["mode"] == mode
    for cam in model.cameras:
        center = torch.tensor(cam.center, dtype=torch.float32)
        xyz, color, opacity, scaling, rot = generate_neural_gaussians(ply, mlps, center, 0, **_dists(kw))
        s = model.scene
        with torch.no_grad():
            g = model.decoder(s.positions, s.features, s.offsets, s.scalings, center, 1.0)
        assert g.count == xyz.shape[0] > 50
        torch.testing.assert_close(g.world_means(), xyz, rtol=0, atol=2e-6)
        torch.testing.assert_close(g.colors, color, rtol=0, atol=2e-6)
        torch.testing.assert_close(g.opacities, opacity, rtol=0, atol=2e-6)
        torch.testing.assert_close(g.scales, scaling, rtol=1e-5, atol=1e-7)
        torch.testing.assert_close(torch.nn.functional.normalize(g.quats), rot, rtol=0, atol=2e-6)
        # the images: ours at xi = 1 with the gate off against the reference's Gaussians through the same rasterizer
        bg = torch.tensor(model.background)
        off = GateConfig(enabled=False)
        with torch.no_grad():
            ours = render_scene(s, model.decoder, cam, 1.0, background=model.background, backend="reference",
                                gate=off)
            ref = rasterize(project(xyz, rot, scaling, opacity, color, cam, gate=off, backend="reference"), bg,
                            "reference")[0]
        assert float((ours.image - ref).abs().max()) < 1e-5
        assert float((ours.image - bg).abs().max()) > 0.1  # something was drawn


def test_appearance_row_is_the_fixed_embedding(tmp_path):
    mlps = scaffold_mlps(appearance_dim=6, n_cameras=4, seed=3)
    root = write_output(tmp_path / "out", mlps)
    cam = view_cameras()[1]
    center = torch.tensor(cam.center, dtype=torch.float32)
    for row in (0, 3):
        model = load_scaffold_output(root, appearance_row=row)
        s = model.scene
        with torch.no_grad():
            g = model.decoder(s.positions, s.features, s.offsets, s.scalings, center, 1.0)
        _, color, *_ = generate_neural_gaussians(scene_arrays(0), mlps, center, row)
        torch.testing.assert_close(g.colors, color, rtol=0, atol=2e-6)
        assert model.meta["scaffold_gs"]["appearance"] == {"width": 6, "rows": 4, "row": row}
    with pytest.raises(ProxycodecError, match="appearance row 4 does not exist"):
        load_scaffold_output(root, appearance_row=4)


def test_film_is_the_identity_at_import_and_xi_changes_nothing_but_the_camera(tmp_path):
    root = write_output(tmp_path / "out", scaffold_mlps(bank=True, opacity_dist=True))
    model = load_scaffold_output(root)
    s, cam = model.scene, model.cameras[0]
    center = torch.tensor(cam.center, dtype=torch.float32)
    with torch.no_grad():
        a = model.decoder(s.positions, s.features, s.offsets, s.scalings, center, 1.0)
        b = model.decoder(s.positions, s.features, s.offsets, s.scalings, center, 0.1)
    assert torch.equal(a.opacities, b.opacities) and torch.equal(a.colors, b.colors)
    assert not model.decoder.mlp_embed[2].weight.any()


# ================================================================================================ finding the files
def test_paths_that_name_an_output(tmp_path):
    root = write_output(tmp_path / "out", scaffold_mlps())
    (root / "point_cloud" / "iteration_7000").mkdir()  # an earlier iteration without a PLY: not chosen
    it = root / "point_cloud" / "iteration_30000"
    for p in (root, it, it / "point_cloud.ply"):
        f = find_scaffold_files(p)
        assert f is not None and f.ply == it / "point_cloud.ply" and f.output_dir == root and f.mode == "split"
        assert f.iteration == 30000 and f.cameras_json == root / "cameras.json"
    # the largest iteration wins
    write_output(tmp_path / "out2", scaffold_mlps(), iteration=500)
    it2 = tmp_path / "out2" / "point_cloud" / "iteration_30000"
    it2.mkdir()
    for n in os.listdir(tmp_path / "out2" / "point_cloud" / "iteration_500"):
        (it2 / n).write_bytes((tmp_path / "out2" / "point_cloud" / "iteration_500" / n).read_bytes())
    assert find_scaffold_files(tmp_path / "out2").iteration == 30000
    # a PLY of ours (weights sidecar beside it) is not a Scaffold-GS output, nor is a folder without point_cloud
    (it / "point_cloud.weights.pxc").write_bytes(b"x")
    assert not is_scaffold_output(it / "point_cloud.ply")
    assert not is_scaffold_output(tmp_path) and not is_scaffold_output(tmp_path / "missing")


def test_output_without_cameras_or_cfg_args(tmp_path):
    root = write_output(tmp_path / "out", scaffold_mlps(opacity_dist=True), white=False)
    model = load_scaffold_output(root)
    assert model.background == (0.0, 0.0, 0.0)
    (root / "cfg_args").unlink()
    (root / "cameras.json").unlink()
    model = load_scaffold_output(root / "point_cloud" / "iteration_30000" / "point_cloud.ply")
    assert model.cameras is None and model.background == (0.0, 0.0, 0.0)
    assert abs(model.scene.voxel_size - VOXEL) < 1e-6  # inferred from the anchors' grid


def test_cfg_args_is_parsed_without_eval(tmp_path):
    from proxycodec.scaffold_gs import read_cfg_args

    marker = tmp_path / "marker"
    p = tmp_path / "cfg_args"
    p.write_text(f"Namespace(voxel_size=0.01, white_background=True, evil=__import__('os').system('touch {marker}'),"
                 " lod=0)")
    assert read_cfg_args(p) == {"voxel_size": 0.01, "white_background": True, "lod": 0}
    assert not marker.exists()
    for bad in ("__import__('os').system('x')", "Namespace(**{'a': 1})", "Namespace(", "x" * 10, ""):
        p.write_text(bad)
        with pytest.raises(ProxycodecError, match="cfg_args"):
            read_cfg_args(p)


# ================================================================================================ refusals
def _replace_record(path: Path, suffix: str, data: bytes) -> None:
    path.write_bytes(replace_zip_record(path.read_bytes(), suffix, data))


def test_malicious_pickles_are_refused_and_never_run(tmp_path):
    marker = tmp_path / "marker"
    # 1. a TorchScript archive whose data.pkl calls os.system
    root = write_output(tmp_path / "a", scaffold_mlps())
    it = root / "point_cloud" / "iteration_30000"
    _replace_record(it / "opacity_mlp.pt", "/data.pkl", os_system_pickle(f"touch {marker}"))
    with pytest.raises(ProxycodecError, match=r"opacity_mlp\.pt: refused to load (posix|os)\.system"):
        load_scaffold_output(root)
    # the same through the CLI: one line, exit 2
    r = CliRunner().invoke(_cli(), ["encode", str(root), "-o", str(tmp_path / "x.pxc")])
    assert r.exit_code == 2 and "refused to load" in r.output and "Traceback" not in r.output
    # 2. a checkpoints.pth holding one
    root = write_output(tmp_path / "b", scaffold_mlps(), "unite")
    ck = root / "point_cloud" / "iteration_30000" / "checkpoints.pth"
    ck.write_bytes(replace_zip_record(ck.read_bytes(), "/data.pkl", os_system_pickle(f"touch {marker}")))
    with pytest.raises(ProxycodecError, match=r"checkpoints\.pth: refused to load"):
        load_scaffold_output(root)
    # 3. a __torch__ class called with arguments, a TorchScript pickle of a bare storage
    bad = os_system_pickle(f"touch {marker}").replace(b"cposix\nsystem\n", b"c__torch__\nX\n")
    _replace_record(it / "opacity_mlp.pt", "/data.pkl", bad)
    with pytest.raises(ProxycodecError, match="malformed pickle"):
        read_torchscript(it / "opacity_mlp.pt")
    assert not marker.exists()
    # and torch.load itself refuses the checkpoint (our check comes first; theirs would too)
    with pytest.raises(pickle.UnpicklingError):
        torch.load(ck, weights_only=True)
    assert not marker.exists()


@pytest.mark.parametrize("shape,stride,numel,match", [
    ((10 ** 6, 10 ** 6), (10 ** 6, 1), 1120, "runs past its storage"),
    ((10 ** 6, 10 ** 6), (0, 0), 1120, "runs past its storage"),  # a broadcast view would allocate 4 TB
    ((32, 35), (35, 1), 10 ** 12, "record holds"),  # a storage larger than its record
])
def test_forged_shapes_do_not_allocate(shape, stride, numel, match, tmp_path):
    root = write_output(tmp_path / "out", scaffold_mlps())
    p = root / "point_cloud" / "iteration_30000" / "cov_mlp.pt"
    _replace_record(p, "/data.pkl", forged_tensor_pickle(shape, stride, numel))
    with pytest.raises(ProxycodecError, match=match):
        read_torchscript(p)
    # the same forged pickle inside a torch.save file
    ck = tmp_path / "checkpoints.pth"
    torch.save({"0.weight": torch.zeros(32, 35)}, ck)
    _replace_record(ck, "/data.pkl", forged_tensor_pickle(shape, stride, numel))
    with pytest.raises(ProxycodecError, match=match):
        read_torch_checkpoint(ck)


def test_broken_files_are_refused_naming_them(tmp_path):
    root = write_output(tmp_path / "a", scaffold_mlps())
    it = root / "point_cloud" / "iteration_30000"
    (it / "cov_mlp.pt").unlink()
    with pytest.raises(ProxycodecError, match=r"cov_mlp\.pt: missing"):
        load_scaffold_output(root)
    root = write_output(tmp_path / "b", scaffold_mlps())
    it = root / "point_cloud" / "iteration_30000"
    data = (it / "color_mlp.pt").read_bytes()
    (it / "color_mlp.pt").write_bytes(data[: len(data) // 2])
    with pytest.raises(ProxycodecError, match=r"color_mlp\.pt: not a PyTorch zip archive"):
        load_scaffold_output(root)
    root = write_output(tmp_path / "c", scaffold_mlps(), "unite")
    ck = root / "point_cloud" / "iteration_30000" / "checkpoints.pth"
    ck.write_bytes(ck.read_bytes()[:-30])
    with pytest.raises(ProxycodecError, match=r"checkpoints\.pth: not a PyTorch zip archive"):
        load_scaffold_output(root)
    root = write_output(tmp_path / "d", scaffold_mlps())
    for n in ("opacity_mlp.pt", "cov_mlp.pt", "color_mlp.pt"):
        (root / "point_cloud" / "iteration_30000" / n).unlink()
    with pytest.raises(ProxycodecError, match="no Scaffold-GS MLP files"):
        load_scaffold_output(root)
    (root / "cameras.json").write_text("[{}]")
    with pytest.raises(ProxycodecError, match=r"cameras\.json: view 0 lacks"):
        from proxycodec.scaffold_gs import read_scaffold_cameras

        read_scaffold_cameras(root / "cameras.json")


def test_variants_that_cannot_be_represented_are_refused(tmp_path):
    # an appearance embedding without its file: the colour MLP's input does not add up
    mlps = scaffold_mlps(appearance_dim=8)
    root = write_output(tmp_path / "a", mlps)
    (root / "point_cloud" / "iteration_30000" / "embedding_appearance.pt").unlink()
    with pytest.raises(ProxycodecError, match=r"color_mlp\.pt: the color network takes 43 inputs.*without "
                                              "embedding_appearance"):
        load_scaffold_output(root)
    # hidden widths that differ
    mlps = scaffold_mlps()
    mlps["cov"] = nn.Sequential(nn.Linear(F + 3, 16), nn.ReLU(True), nn.Linear(16, 7 * K)).eval()
    with pytest.raises(ProxycodecError, match="hidden widths differ"):
        load_scaffold_output(write_output(tmp_path / "b", mlps))
    # a deeper network
    mlps = scaffold_mlps()
    mlps["opacity"] = nn.Sequential(nn.Linear(F + 3, F), nn.ReLU(True), nn.Linear(F, F), nn.ReLU(True),
                                    nn.Linear(F, K), nn.Tanh()).eval()
    with pytest.raises(ProxycodecError, match="cannot be represented"):
        load_scaffold_output(write_output(tmp_path / "c", mlps))
    # cfg_args that disagree with the files
    with pytest.raises(ProxycodecError, match="cfg_args says add_cov_dist=True"):
        load_scaffold_output(write_output(tmp_path / "d", scaffold_mlps(), cfg={"add_cov_dist": True}))
    # outputs that do not match the anchors
    with pytest.raises(ProxycodecError, match="the opacity network has 10 outputs; the anchors need 20"):
        load_scaffold_output(write_output(tmp_path / "e", scaffold_mlps(), ply=_ply_with_k(20)))
    # a feature bank needs F divisible by 4 (Scaffold-GS's blend)
    with pytest.raises(ProxycodecError, match="feature bank needs a feature width divisible by 4"):
        DecoderConfig(feat_dim=30, feature_bank=30)


def _ply_with_k(k):
    p = scene_arrays(0)
    return ScaffoldPly(positions=p.positions, offsets=np.zeros((p.n_anchors, k, 3)), features=p.features,
                       scalings=p.scalings)


# ================================================================================================ configuration
OLD_DECODER_KEYS = {"feat_dim", "n_offsets", "hidden", "embedding", "film_hidden", "pe_pos_freqs", "pe_res_freqs",
                    "scene_center", "scene_radius", "film_xi_range", "gate"}


def test_decoder_config_json_is_unchanged_for_our_decoders_and_carries_the_variant():
    assert set(DecoderConfig().to_json()) == OLD_DECODER_KEYS  # our containers keep their bytes
    assert DecoderConfig.from_json(DecoderConfig().to_json()) == DecoderConfig()
    v = DecoderConfig(opacity_dist=False, color_dist=False, feature_bank=32)
    d = v.to_json()
    assert set(d) - OLD_DECODER_KEYS == {"opacity_dist", "color_dist", "feature_bank"}
    assert DecoderConfig.from_json(json.loads(json.dumps(d))) == v
    for bad in ({"cov_dist": 1}, {"feature_bank": -1}, {"feature_bank": "32"}, {"feature_bank": True}):
        with pytest.raises(ProxycodecError):
            DecoderConfig.from_json({**DecoderConfig().to_json(), **bad})


# ================================================================================================ end to end
def _cli():
    from proxycodec.cli.main import cli

    return cli


def test_cli_encode_decode_render_stats_on_an_output_folder(tmp_path):
    """The output folder through the CLI: encode (predictor refitted), stats, decode --res 0.3 (torch-free path),
    render; the container's decoder configuration carries the variant, and the torch-free decoder renders it as the
    torch path does."""
    from proxycodec import codec, lite
    from proxycodec.formats.container import read_container

    kw = {"bank": True, "opacity_dist": True, "color_dist": True}
    root = write_output(tmp_path / "scaffold_out", scaffold_mlps(**kw), "split")
    run = CliRunner()
    out = tmp_path / "scene.pxc"
    r = run.invoke(_cli(), ["encode", str(root), "-o", str(out), "--predictor-iters", "30", "--distill-iters", "3",
                                 "--distill-views", "8", "--positions", "delta"])
    assert r.exit_code == 0, r.output
    meta = read_container(out).meta
    dec = meta["decoder"]
    assert (dec["cov_dist"], dec["feature_bank"]) == (False, F)  # Scaffold-GS's default: no distance
    assert "opacity_dist" not in dec and "color_dist" not in dec  # at our default (with distance): omitted
    # a reader that predates the variants refuses the file instead of ignoring the fields it does not know
    assert meta["scene_format"] == 3
    # the Python API renders the output folder too
    assert len(codec.render(root, xi=0.2)) >= 1
    assert meta["source"]["bytes"] == sum(p.stat().st_size for p in (root / "point_cloud" / "iteration_30000")
                                          .iterdir())
    # the default output name for a folder
    r = run.invoke(_cli(), ["encode", str(root), "--predictor-iters", "0", "--distill-iters", "2", "--distill-views", "4"])
    assert r.exit_code == 0 and (tmp_path / "scaffold_out.pxc").is_file(), r.output
    r = run.invoke(_cli(), ["stats", str(root)])
    assert r.exit_code == 0 and "Scaffold-GS output (split MLP files" in r.output and "150 anchors" in r.output
    r = run.invoke(_cli(), ["stats", str(out)])
    assert r.exit_code == 0 and "150 anchors" in r.output, r.output
    r = run.invoke(_cli(), ["decode", str(out), "--res", "0.3", "--view", "0", "-o", str(tmp_path / "dec")])
    assert r.exit_code == 0 and (tmp_path / "dec" / "view000_res0.300.png").is_file(), r.output
    r = run.invoke(_cli(), ["render", str(root), "--res", "0.3", "--view", "0", "--backend", "cpu",
                            "-o", str(tmp_path / "ren")])
    assert r.exit_code == 0 and (tmp_path / "ren" / "view000_res0.300.png").is_file(), r.output
    # the torch-free decoder implements the variant: same leaves, same image as the torch path
    torch_model, lite_scene = codec.decode(out), lite.decode(out)
    np.testing.assert_allclose(lite_scene.features, torch_model.scene.features.numpy(), rtol=1e-5, atol=1e-5)
    from test_decode_lite import assert_renders_agree  # float32 paths: decisions may flip on another CPU

    for xi in (0.3, 1.0):
        assert_renders_agree(torch_model, lite_scene, torch_model.cameras[1], xi)


def test_load_any_and_source_bytes(tmp_path):
    from proxycodec.scenes import load_any

    root = write_output(tmp_path / "out", scaffold_mlps(), "unite")
    model = load_any(root)
    it = root / "point_cloud" / "iteration_30000"
    assert model.meta["scaffold_gs"]["files"] == ["point_cloud.ply", "checkpoints.pth"]
    assert model.meta["scaffold_gs"]["bytes"] == sum(p.stat().st_size for p in it.iterdir())
    assert load_any(it / "point_cloud.ply").decoder.config == model.decoder.config


def test_cli_eval_on_an_output_folder(tmp_path):
    """``eval`` takes the folder: a dataset rendered from the imported scene itself scores high at 100%."""
    from conftest import write_blender

    root = write_output(tmp_path / "out", scaffold_mlps(color_dist=True))
    model = load_scaffold_output(root)
    cams = model.cameras
    data = write_blender(tmp_path / "data", {"train": cams[:2], "test": cams[2:]},
                         lambda cam: model.render(cam, 1.0, backend="cpu").image)
    r = CliRunner().invoke(_cli(), ["eval", str(root), str(data), "--res", "1.0", "--backend", "cpu",
                                    "-o", str(tmp_path / "ev")])
    assert r.exit_code == 0, r.output
    summary = json.loads((tmp_path / "ev" / "eval.json").read_text())["summary"]
    assert summary["anchors"] == 150 and summary["psnr_100"] > 40.0  # 8-bit PNG targets of its own render


@pytest.mark.parametrize("kw", [{"bank": True, "opacity_dist": True}, {}], ids=["bank", "no_dist"])
def test_live_slots_follow_the_variant(kw, tmp_path):
    """``decoder.live_slots`` (encode --drop-dead-offsets) with a feature bank / without distance inputs: exactly the
    slots the decoder draws from the same viewpoints and resolutions."""
    from proxycodec.decoder import live_slots

    model = load_scaffold_output(write_output(tmp_path / "out", scaffold_mlps(**kw)))
    s, dec = model.scene, model.decoder
    with torch.no_grad():
        dec.mlp_embed[2].weight.normal_(0, 0.3)  # a FiLM that depends on xi
    vps = torch.tensor(np.stack([c.center for c in model.cameras] + [[0.0, 0.0, 3.0]]), dtype=torch.float32)
    xis = (0.1, 1.0)
    want = torch.zeros(s.num_anchors, K, dtype=torch.bool)
    with torch.no_grad():
        for vp in vps:
            for xi in xis:
                g = dec(s.positions, s.features, s.offsets, s.scalings, vp, xi)
                want[g.anchor_index, g.slot] = True
    got = live_slots(dec, s.positions, s.features, vps, xis, chunk=2)
    assert 0 < int(want.sum()) < want.numel()
    assert torch.equal(got, want)


@pytest.mark.parametrize("mode", ["split", "unite"])
def test_files_saved_from_a_gpu(mode, tmp_path):
    """Scaffold-GS traces and saves its MLPs on CUDA: storages located at "cuda:0" load on a CPU-only machine."""
    root = write_output(tmp_path / "out", scaffold_mlps(bank=True, appearance_dim=4), mode)
    want = load_scaffold_output(root).decoder.state_arrays()
    it = root / "point_cloud" / "iteration_30000"
    for p in it.iterdir():
        if p.suffix in (".pt", ".pth"):
            with zipfile.ZipFile(p) as z:
                pkl = z.read(next(n for n in z.namelist() if n.endswith("/data.pkl")))
            assert b"X\x03\x00\x00\x00cpu" in pkl
            _replace_record(p, "/data.pkl", pkl.replace(b"X\x03\x00\x00\x00cpu", b"X\x06\x00\x00\x00cuda:0"))
    got = load_scaffold_output(root).decoder.state_arrays()
    assert want.keys() == got.keys() and all(np.array_equal(want[k], got[k]) for k in want)
