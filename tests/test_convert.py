"""`proxycodec convert`: an INRIA 3DGS PLY -> an anchor scene without images (issue 16), and the commands that
now take a 3DGS PLY (stats, render, encode)."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from proxycodec.camera import Camera
from proxycodec.cli.main import cli
from proxycodec.convert import (ConvertConfig, anchors_from_gaussians, auto_views, choose_voxel, convert,
                                fit_attributes, initial_model, load_gaussians, replace_fit)
from proxycodec.decoder import GaussianDecoder
from proxycodec.errors import ProxycodecError
from proxycodec.explicit import ExplicitModel, eval_sh
from proxycodec.formats.inria_ply import GaussianPly, read_inria_ply, rgb_to_sh_dc, write_inria_ply
from proxycodec.netconfig import DecoderConfig
from proxycodec.scaffold_gs import find_cameras_json, read_scaffold_cameras, write_cameras_json

pytestmark = pytest.mark.usefixtures("one_thread")


def _ball(n=400, seed=0, degree=1, radius=0.5) -> GaussianPly:
    """Gaussians on a sphere, two colour bands, random rotations (SH ``degree``)."""
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    col = np.where((v[:, 2] > 0)[:, None], [0.9, 0.2, 0.1], [0.1, 0.3, 0.9])
    c = (degree + 1) ** 2
    sh = np.zeros((n, c, 3))
    sh[:, 0] = rgb_to_sh_dc(col)
    sh[:, 1:] = 0.05 * rng.normal(size=(n, c - 1, 3))
    return GaussianPly(radius * v, sh, np.full(n, 2.0), np.full((n, 3), math.log(0.06)), rng.normal(size=(n, 4)))


def _tiny_config(**fit) -> ConvertConfig:
    return replace_fit(ConvertConfig(init_iters=60, views=12, view_size=32),
                       **{"iters": 24, "log_every": 1e9, "checkpoint_every": 0.0, "predictor_warmup": 10, **fit})


# ---------------------------------------------------------------------------------------------- building blocks
def test_every_kept_gaussian_is_an_offset_of_its_anchor_exactly_where_it_was():
    g = load_gaussians(_ball())
    choice = choose_voxel(g, 10, ConvertConfig(voxel_size=0.1))
    scene, t = anchors_from_gaussians(g, choice.voxel, 10, 32)
    world = scene.positions[:, None, :] + scene.offsets * torch.exp(scene.scalings[:, None, :3])
    got = world[t.used].double().numpy()
    # every used slot is one of the source's centres, and there are as many as the cells keep
    d = np.linalg.norm(got[:, None, :] - g.means[None], axis=-1).min(1)
    assert d.max() < 1e-6
    assert t.used.sum().item() == choice.kept_gaussians
    counts = np.unique(np.round(g.means / 0.1).astype(np.int64), axis=0, return_counts=True)[1]
    assert choice.kept_gaussians == int(np.minimum(counts, 10).sum())
    assert scene.num_anchors == len(counts) == choice.anchors
    # the offsets' scale is the voxel; the base scale bounds every kept Gaussian (sigmoid < 1)
    assert torch.allclose(torch.exp(scene.scalings[:, :3]), torch.full((scene.num_anchors, 3), 0.1))
    assert (t.log_scale[t.used] < scene.scalings[:, None, 3:].expand_as(t.log_scale)[t.used]).all()


def test_the_automatic_voxel_keeps_the_weight_it_promises_and_is_the_largest_that_does():
    g = load_gaussians(_ball(20000))  # dense: the coarsest voxel (extent / 16) keeps too little
    cfg = ConvertConfig(keep=0.9)
    c = choose_voxel(g, 10, cfg)
    assert c.automatic and c.kept_weight >= 0.9 and c.voxel < g.extent / 16
    coarser = choose_voxel(g, 10, ConvertConfig(voxel_size=c.voxel * 2 ** 0.125))
    assert coarser.kept_weight < 0.9
    # the anchors follow the scene: no cap by default (the same sphere twice as dense asks for more anchors)
    denser = choose_voxel(load_gaussians(_ball(80000)), 10, cfg)
    assert denser.kept_weight >= 0.9 and denser.anchors > c.anchors
    capped = choose_voxel(g, 10, ConvertConfig(keep=1.0, max_anchors=2000))  # the budget binds first
    assert capped.anchors <= 2000 and capped.kept_weight < 1.0
    assert choose_voxel(g, 10, ConvertConfig(voxel_size=capped.voxel / 2 ** 0.125)).anchors > 2000
    from proxycodec.convert import CONTAINER_ANCHOR_BYTES, CONTAINER_BASE_BYTES, anchors_for_size

    size = int(CONTAINER_BASE_BYTES + 1500 * CONTAINER_ANCHOR_BYTES) + 1
    assert anchors_for_size(size) == 1500
    sized = choose_voxel(g, 10, ConvertConfig(keep=1.0, target_size=size))
    assert sized.anchors <= 1500 and choose_voxel(g, 10, ConvertConfig(voxel_size=sized.voxel / 2 ** 0.125)).anchors \
        > 1500
    with pytest.raises(ProxycodecError, match="holds no anchor"):
        ConvertConfig(target_size=1000)


@pytest.mark.parametrize("bad, match", [({"background": (2.0, 0.0, 0.0)}, "background"),
                                        ({"background": (0.0, 0.0)}, "background"),
                                        ({"background": (float("nan"), 0.0, 0.0)}, "background"),
                                        ({"background": ("white", 0.0, 0.0)}, "background"),
                                        ({"lr_scale": -1.0}, "learning-rate scale"),
                                        ({"lr_scale": float("inf")}, "learning-rate scale")])
def test_config_refuses_bad_background_and_lr_scale(bad, match):
    with pytest.raises(ProxycodecError, match=match):
        ConvertConfig(**bad)
    cfg = ConvertConfig(background=[1, 0.5, 0], lr_scale=0.5)  # in range: accepted, held as a tuple of floats
    assert cfg.background == (1.0, 0.5, 0.0) and all(type(b) is float for b in cfg.background)


def test_voxel_hashing_equals_row_wise_unique():
    from proxycodec.convert import _cells

    rng = np.random.default_rng(3)
    pts = np.concatenate([rng.normal(size=(5000, 3)), [[1e6, -1e6, 3.0]]])  # a far floater: a wide key range
    for v, p in ((0.05, pts[:-1]), (0.05, pts), (1e-9, pts)):  # the last one overflows 63 bits: row-wise
        u, inv = _cells(p, v)
        u2, inv2 = np.unique(np.round(p / v).astype(np.int64), axis=0, return_inverse=True)
        assert np.array_equal(u, u2) and np.array_equal(inv, inv2.reshape(-1))


def test_the_fitted_start_decodes_near_the_source_gaussians():
    g = load_gaussians(_ball())
    scene, t = anchors_from_gaussians(g, 0.1, 10, 32)
    torch.manual_seed(0)
    dec = GaussianDecoder(DecoderConfig(scene_center=(0, 0, 0), scene_radius=1.0))
    fitted = fit_attributes(scene, dec, t, g.degree, 2.0, iters=300)
    cam = torch.tensor([0.0, -2.0, 0.3])
    with torch.no_grad():
        out = dec(fitted.positions, fitted.features, fitted.offsets, fitted.scalings, cam, 1.0)
    used = t.used[out.anchor_index, out.slot]
    assert used.float().mean() > 0.98  # free slots stay invisible
    a, s = out.anchor_index[used], out.slot[used]
    assert (out.opacities[used] - t.alpha[a, s]).abs().mean() < 0.05
    d = out.world_means()[used] - cam
    rgb = (eval_sh(g.degree, t.sh[a, s], d / d.norm(dim=1, keepdim=True)) + 0.5).clamp(0, 1)
    assert (out.colors[used] - rgb).abs().mean() < 0.05
    assert (torch.log(out.scales[used]) - t.log_scale[a, s]).abs().mean() < 0.2
    q = out.quats[used] / out.quats[used].norm(dim=1, keepdim=True)
    assert ((q * t.quat[a, s]).sum(1).abs() > 0.95).float().mean() > 0.9


def test_auto_views_look_at_an_object_from_outside_and_around_a_room_from_inside():
    obj = load_gaussians(_ball(500))
    cams, layout = auto_views(obj, 16, 32)
    assert layout == "outside-in" and len(cams) == 16
    for c in cams:
        assert np.linalg.norm(c.center) > 0.5  # outside the ball, looking at it
        assert (c.world_to_camera[:3, :3] @ -c.center)[2] > 0
    rng = np.random.default_rng(1)
    walls = rng.normal(size=(1500, 3))
    walls = 10.0 * walls / np.linalg.norm(walls, axis=1, keepdims=True)  # a room's walls (or the background)
    table = 0.3 * rng.normal(size=(3000, 3))  # what the capture looked at, in the middle
    m = np.concatenate([walls, table])
    room = load_gaussians(GaussianPly(m, np.zeros((len(m), 1, 3)), np.zeros(len(m)), np.full((len(m), 3), -3.0),
                                      np.tile([1.0, 0, 0, 0], (len(m), 1))))
    cams, layout = auto_views(room, 16, 32)
    assert layout == "inside-out"
    assert max(np.linalg.norm(c.center) for c in cams) < 10.0  # inside the walls


def test_cameras_json_round_trips_and_is_found_where_3dgs_puts_it(tmp_path):
    cams = [Camera.look_at((2.0, 0.5 * i, 1.0), (0, 0, 0), fov_x_deg=40 + i, width=64 + i, height=48, name=f"c{i}")
            for i in range(3)]
    out = tmp_path / "output"
    (out / "point_cloud" / "iteration_7000").mkdir(parents=True)
    write_cameras_json(out / "cameras.json", cams)
    ply = out / "point_cloud" / "iteration_7000" / "point_cloud.ply"
    write_inria_ply(ply, _ball(50))
    assert find_cameras_json(ply) == out / "cameras.json"
    back = read_scaffold_cameras(find_cameras_json(ply))
    for a, b in zip(cams, back):
        assert np.allclose(a.world_to_camera, b.world_to_camera, atol=1e-9)
        assert (a.width, a.height, a.fx, a.fy, a.cx, a.cy, a.name) == (b.width, b.height, b.fx, b.fy, b.cx, b.cy,
                                                                        b.name)
    assert len(ExplicitModel.load(ply).cameras) == 3  # render / eval use them
    # a link to the PLY in a folder with its own cameras.json (benchmarks/convert.py --input): the link's folder wins
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    write_cameras_json(elsewhere / "cameras.json", cams[:2])
    (elsewhere / "linked.ply").symlink_to(ply)
    assert find_cameras_json(elsewhere / "linked.ply") == elsewhere / "cameras.json"
    (elsewhere / "cameras.json").unlink()
    assert find_cameras_json(elsewhere / "linked.ply") == out / "cameras.json"  # then around the target


# ---------------------------------------------------------------------------------------------- the run
def test_convert_writes_a_stage_2_anchor_scene_and_reports_on_held_out_views(tmp_path):
    src = tmp_path / "splats.ply"
    write_inria_ply(src, _ball(300))
    log = []
    r = convert(src, tmp_path / "scene.ply", _tiny_config(), log=log.append)
    from proxycodec.model import SceneModel, weights_path_for
    from proxycodec.proxy import load_fitted_predictor

    m = SceneModel.load(tmp_path / "scene.ply")
    pred, mask = load_fitted_predictor(weights_path_for(tmp_path / "scene.ply"))
    assert pred is not None and mask.shape == (m.scene.num_anchors,) and 0 < mask.sum() < len(mask)
    assert r.layout == "outside-in" and r.iterations == 24
    rows = r.report["converted"]["per_resolution"]
    assert [x["xi"] for x in rows] == [round(0.1 * k, 1) for k in range(1, 11)]
    assert all(math.isfinite(x["psnr"]) for x in rows)
    assert min(x["psnr"] for x in rows) > 15  # 24 iterations on a 300-Gaussian ball: 17.4-19.1 dB measured
    assert r.report["converted"]["held_out"] and r.report["converted"]["views"] == [0]  # every 8th of 12 views
    direct = [x["psnr"] for x in r.report["source_direct"]["per_resolution"]]
    assert direct[-1] is None  # at 100% the reference is the source's own render: identical (infinite PSNR)
    assert all(math.isfinite(v) and v < 60 for v in direct[:-1])  # below it, the plain render aliases
    assert any("initial fit" in s for s in log) and any(s.startswith("it ") for s in log)
    json.dumps(r.to_json())  # JSON-able


def test_an_anchor_budget_also_caps_the_training_s_growth(tmp_path):
    src = tmp_path / "splats.ply"
    write_inria_ply(src, _ball(300))
    # 266 anchors from the voxel rule (the coarsest voxel already has them), growth beyond them capped at 275
    cfg = replace(_tiny_config(iters=12, update_interval=3, grad_threshold=1e-9, min_opacity=0.0), max_anchors=275)
    r = convert(src, tmp_path / "scene.ply", cfg, log=lambda s: None)
    assert r.voxel.anchors == 266 and 266 < r.model.scene.num_anchors <= 275
    free = convert(src, tmp_path / "free.ply", replace(cfg, max_anchors=None), log=lambda s: None)
    assert free.voxel.anchors == 266 and free.model.scene.num_anchors > 275  # growth without a cap


def test_convert_is_deterministic(tmp_path):
    src = tmp_path / "splats.ply"
    write_inria_ply(src, _ball(200))
    cfg = _tiny_config(iters=8)
    convert(src, tmp_path / "a.ply", cfg, log=lambda s: None)
    convert(src, tmp_path / "b.ply", cfg, log=lambda s: None)
    assert (tmp_path / "a.ply").read_bytes() == (tmp_path / "b.ply").read_bytes()


def test_encode_of_a_3dgs_ply_writes_the_same_bytes_twice(tmp_path):
    from proxycodec.convert import convert_and_encode

    src = tmp_path / "splats.ply"
    write_inria_ply(src, _ball(200))
    knobs = dict(entropy="zstd", zstd_level=3)
    _, a = convert_and_encode(src, tmp_path / "a.pxc", _tiny_config(iters=6), log=lambda s: None, **knobs)
    _, b = convert_and_encode(src, tmp_path / "b.pxc", _tiny_config(iters=6), log=lambda s: None, **knobs)
    assert (tmp_path / "a.pxc").read_bytes() == (tmp_path / "b.pxc").read_bytes()
    assert "seconds" not in a.meta["convert"] and a.meta["convert"]["iterations"] == 6


def test_an_interrupted_conversion_resumes_to_the_same_scene(tmp_path):
    from proxycodec.model import SceneModel

    src = tmp_path / "splats.ply"
    write_inria_ply(src, _ball(200))
    cfg = _tiny_config(iters=16, predictor_warmup=5)
    convert(src, tmp_path / "a.ply", cfg, log=lambda s: None)
    with pytest.raises(KeyboardInterrupt):
        convert(src, tmp_path / "b.ply", cfg, log=lambda s: None, stop_after=11)  # in stage 2
    assert not (tmp_path / "b.ply").exists() and (tmp_path / "b.ckpt.pxc").exists()
    log = []
    convert(src, tmp_path / "b.ply", cfg, resume=True, log=log.append)
    assert any("resumed" in s and "iteration 11" in s for s in log)
    a, b = SceneModel.load(tmp_path / "a.ply").scene, SceneModel.load(tmp_path / "b.ply").scene
    assert a.num_anchors == b.num_anchors
    for name in ("positions", "features", "offsets", "scalings"):  # bit for bit: every state is checkpointed
        assert torch.equal(getattr(a, name), getattr(b, name)), name


@pytest.mark.parametrize("case, message", [
    ("empty", "holds no Gaussians"),
    ("one_point", "sit in one point"),
])
def test_plys_with_nothing_to_convert_are_refused(tmp_path, case, message):
    g = _ball(30)
    if case == "empty":
        g = GaussianPly(np.zeros((0, 3)), np.zeros((0, 4, 3)), np.zeros(0), np.zeros((0, 3)), np.zeros((0, 4)))
    else:
        g = GaussianPly(np.ones((30, 3)), g.sh, g.opacities, g.scales, g.quats)
    write_inria_ply(tmp_path / "g.ply", g)
    with pytest.raises(ProxycodecError, match=message):
        convert(tmp_path / "g.ply", tmp_path / "out.ply", _tiny_config())
    assert not (tmp_path / "out.ply").exists()


def test_extreme_scales_and_zero_quaternions_convert_to_a_finite_scene(tmp_path):
    g = _ball(120)
    sc = g.scales.copy()
    sc[:40] = 20.0
    sc[40:80] = -20.0
    q = g.quats.copy()
    q[::3] = 0.0
    write_inria_ply(tmp_path / "g.ply", GaussianPly(g.means, g.sh, g.opacities, sc, q))
    src = ExplicitModel.load(tmp_path / "g.ply")
    img = src.render(src.cameras[0], 0.5).image
    assert torch.isfinite(img).all()  # the source itself renders
    start, _ = initial_model(load_gaussians(read_inria_ply(tmp_path / "g.ply")), _tiny_config(),
                             src.cameras, lambda s: None)
    for name in ("features", "offsets", "scalings"):
        assert torch.isfinite(getattr(start.scene, name)).all()
    assert torch.isfinite(start.render(src.cameras[0], 0.3).image).all()


# ---------------------------------------------------------------------------------------------- the commands
def test_stats_names_a_3dgs_ply_and_its_bytes_add_up(tmp_path):
    src = tmp_path / "splats.ply"
    write_inria_ply(src, _ball(100, degree=3))
    res = CliRunner().invoke(cli, ["stats", str(src), "--json"])
    assert res.exit_code == 0, res.output
    s = json.loads(res.output)
    assert s["type"] == "inria-3dgs-ply" and s["gaussians"] == 100 and s["sh_degree"] == 3
    assert s["header_bytes"] + sum(s["bytes_by_group"].values()) + s["trailing_bytes"] == src.stat().st_size
    assert s["bytes_by_group"]["sh_rest"] == 100 * 45 * 4 and s["trailing_bytes"] == 0
    text = CliRunner().invoke(cli, ["stats", str(src)]).output
    assert "INRIA 3DGS PLY, 100 Gaussians, SH degree 3" in text and "proxycodec convert" in text
    assert "Scaffold-GS" not in text


def test_render_takes_a_3dgs_ply(tmp_path):
    src = tmp_path / "splats.ply"
    write_inria_ply(src, _ball(100))
    res = CliRunner().invoke(cli, ["--threads", "1", "render", str(src), "--res", "0.25", "--view", "1", "-o", str(tmp_path / "r")])
    assert res.exit_code == 0, res.output
    assert len(list((tmp_path / "r").glob("*.png"))) == 1


def test_encode_of_a_3dgs_ply_trains_conversion_s_own_length_unless_told(tmp_path, monkeypatch):
    """Encode's default --distill-iters is the distillation's (measured for anchor scenes); a 3DGS PLY's conversion
    keeps ConvertConfig's length unless --distill-iters is given."""
    import proxycodec.convert as convert_module

    seen = []

    def spy(ply, out, cfg, **kw):
        seen.append(cfg.fit.iters)
        raise ProxycodecError("stop here")

    monkeypatch.setattr(convert_module, "convert_and_encode", spy)
    src = tmp_path / "splats.ply"
    write_inria_ply(src, _ball(20))
    for extra in ([], ["--distill-iters", "12"]):
        res = CliRunner().invoke(cli, ["encode", str(src), "-o", str(tmp_path / "s.pxc"), *extra])
        assert res.exit_code == 2 and "stop here" in res.output
    assert seen == [ConvertConfig().fit.iters, 12] and ConvertConfig().fit.iters == 4000


def test_encode_converts_a_3dgs_ply_and_keeps_the_anchor_scene_when_asked(tmp_path):
    src = tmp_path / "splats.ply"
    write_inria_ply(src, _ball(200))
    keep = tmp_path / "kept" / "anchors.ply"
    res = CliRunner().invoke(cli, ["--threads", "1", "encode", str(src), "-o", str(tmp_path / "s.pxc"), "--distill-iters", "12",
                                   "--views", "10", "--view-size", "32", "--keep-anchor-scene", str(keep)])
    assert res.exit_code == 0, res.output
    from proxycodec.model import weights_path_for

    assert keep.exists() and weights_path_for(keep).exists()
    s = json.loads(CliRunner().invoke(cli, ["stats", str(tmp_path / "s.pxc"), "--json"]).output)
    conv = s["metadata"]["convert"]
    assert conv["source"]["name"] == "splats.ply" and conv["iterations"] == 12
    assert s["source_bytes"] == src.stat().st_size  # the ratio is against the 3DGS PLY
    assert "smaller than the 3DGS PLY" in res.output
    text = CliRunner().invoke(cli, ["stats", str(tmp_path / "s.pxc")]).output
    assert "smaller than the 3DGS PLY" in text and "converted from the 3DGS PLY splats.ply: 12 iterations" in text
    assert s["metadata"]["proxy"]["source"].startswith("fit")  # the conversion's stage-2 predictor, as fitted
    res = CliRunner().invoke(cli, ["--threads", "1", "decode", str(tmp_path / "s.pxc"), "--res", "0.3", "--view", "0",
                                   "-o", str(tmp_path / "d")])
    assert res.exit_code == 0, res.output
    # without --keep-anchor-scene nothing but the container is left behind
    res = CliRunner().invoke(cli, ["--threads", "1", "encode", str(src), "-o", str(tmp_path / "t" / "t.pxc"), "--distill-iters", "6",
                                   "--views", "10", "--view-size", "32"])
    assert res.exit_code == 0, res.output
    assert sorted(p.name for p in (tmp_path / "t").iterdir()) == ["t.pxc"]


@pytest.mark.parametrize("args, message", [
    (["encode", "{src}", "--images", "{tmp}"], "do not apply to a 3DGS PLY"),
    (["encode", "{src}", "--distill-targets", "whole"], "--distill-targets do not apply to a 3DGS PLY"),
    (["convert", "{tmp}/missing.ply", "-o", "{tmp}/o.ply"], "missing.ply"),
    (["convert", "{anchor}", "-o", "{tmp}/o.ply"], "`proxycodec encode`, `render` and `stats` take it"),
])
def test_command_line_errors_are_one_line_and_name_a_command(tmp_path, args, message):
    src = tmp_path / "splats.ply"
    write_inria_ply(src, _ball(50))
    from proxycodec.sample import sample_model

    anchor = tmp_path / "anchor.ply"
    sample_model().save(anchor)
    argv = [a.format(src=src, tmp=tmp_path, anchor=anchor) for a in args]
    res = CliRunner().invoke(cli, argv)
    assert res.exit_code == 2, res.output
    lines = res.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and message in lines[0], res.output


def test_the_library_encode_points_a_3dgs_ply_to_the_conversion(tmp_path):
    from proxycodec import codec

    write_inria_ply(tmp_path / "g.ply", _ball(50))
    with pytest.raises(ProxycodecError, match="`proxycodec encode` converts it first"):
        codec.encode(tmp_path / "g.ply", tmp_path / "g.pxc")


def test_the_benchmark_converts_with_conversion_s_own_fit_settings_like_the_cli():
    """benchmarks/convert.py passes a few fit fields; the rest must be conversion's own (uniform resolutions, the
    rate term), as `proxycodec encode PLY` uses, not FitConfig's defaults."""
    from proxycodec.bench.steps import convert_config
    from proxycodec.cli.convert import make_config
    from proxycodec.train import FitConfig

    cli_cfg = make_config(300, None, 0, 0.0, 64, 400, (1.0, 1.0, 1.0), 100)
    bench = convert_config({"background": [1.0, 1.0, 1.0], "fit": {"iters": 300, "max_width": 100, "seed": 0}})
    assert bench == cli_cfg
    assert (bench.fit.lr_warmup, bench.fit.xi_full_share, bench.fit.lambda_rate) == (0.0, 0.0, 1e-4)
    assert (bench.fit.proxy_selection, bench.fit.predictor_context) == ("spread", 4)
    assert bench.fit.xi_full_share != FitConfig().xi_full_share
    old = convert_config({"fit": {"proxy_selection": "random", "predictor_context": 1, "lr_warmup": 0.05}})
    assert (old.fit.proxy_selection, old.fit.predictor_context, old.fit.lr_warmup, old.fit.iters) == ("random", 1, 0.05,
                                                                                                      4000)


@pytest.mark.parametrize("given, expected", [([], ConvertConfig().fit.lambda_rate), (["--lambda-rate", "0"], 0.0),
                                             (["--lambda-rate", "3e-4"], 3e-4)])
def test_convert_s_lambda_rate_reaches_the_conversion_s_fit(tmp_path, monkeypatch, given, expected):
    """`convert --lambda-rate` sets the rate term of conversion's own fit; left out, conversion's default stays; the
    other fields of conversion's fit stay either way."""
    import proxycodec.convert as convert_module

    seen = []

    def spy(ply, out, cfg, **kw):
        seen.append(cfg.fit)
        raise ProxycodecError("stop here")

    monkeypatch.setattr(convert_module, "convert", spy)
    write_inria_ply(tmp_path / "g.ply", _ball(20))
    res = CliRunner().invoke(cli, ["convert", str(tmp_path / "g.ply"), "-o", str(tmp_path / "a.ply"), *given])
    assert res.exit_code == 2 and "stop here" in res.output
    assert seen[0].lambda_rate == expected and seen[0].iters == ConvertConfig().fit.iters
    assert seen[0].checkpoint_every == ConvertConfig().fit.checkpoint_every
    res = CliRunner().invoke(cli, ["convert", str(tmp_path / "g.ply"), "-o", str(tmp_path / "a.ply"), *given,
                                   "--checkpoint-every", "30"])
    assert res.exit_code == 2 and seen[1].checkpoint_every == 30.0 and seen[1].lambda_rate == expected


def test_convert_s_lambda_rate_refuses_a_negative_weight(tmp_path):
    write_inria_ply(tmp_path / "g.ply", _ball(20))
    res = CliRunner().invoke(cli, ["convert", str(tmp_path / "g.ply"), "-o", str(tmp_path / "a.ply"),
                                   "--lambda-rate", "-1"])
    assert res.exit_code == 2 and "--lambda-rate" in res.output
    assert not (tmp_path / "a.ply").exists()


# ---------------------------------------------------------------------------------------------- background
def _trainer_output(tmp_path, white: bool | None):
    """A 3DGS trainer's output folder: OUT/cameras.json, OUT/cfg_args (``white`` None: none) and the PLY in
    OUT/point_cloud/iteration_30000/; a half-transparent ball, so the background shows through it."""
    out = tmp_path / ("white" if white else "black" if white is False else "none")
    ply = out / "point_cloud" / "iteration_30000" / "point_cloud.ply"
    ply.parent.mkdir(parents=True)
    g = _ball(200)
    write_inria_ply(ply, GaussianPly(g.means, g.sh, np.full(len(g.means), -1.0), g.scales, g.quats))
    write_cameras_json(out / "cameras.json", [Camera.look_at((0.0, -2.0, 0.3), (0, 0, 0), fov_x_deg=50, width=24,
                                                             height=18, name="v0")])
    if white is not None:
        (out / "cfg_args").write_text(f"Namespace(sh_degree=3, source_path='/data/x', model_path='{out}', "
                                      f"white_background={white}, eval=True)")
    return ply


def test_a_3dgs_ply_renders_on_the_background_it_was_trained_on(tmp_path):
    """Black unless the trainer's cfg_args says white_background=True (the reference trainer's, gsplat's and
    nerfstudio's default); `render --background` overrides it, and the default render is the black one exactly."""
    from PIL import Image

    from proxycodec.explicit import ply_background

    none, black, white = (_trainer_output(tmp_path, w) for w in (None, False, True))
    assert ply_background(none)[0] == (0.0, 0.0, 0.0) and "default" in ply_background(none)[1]
    assert ply_background(black)[0] == (0.0, 0.0, 0.0) and "cfg_args" in ply_background(black)[1]
    assert ply_background(white)[0] == (1.0, 1.0, 1.0)
    assert ExplicitModel.load(white).background == (1.0, 1.0, 1.0)
    assert ExplicitModel.load(white, background=(0, 0, 0)).background == (0.0, 0.0, 0.0)

    def render(ply, *extra):
        d = tmp_path / f"r{len(list(tmp_path.glob('r*')))}"
        r = CliRunner().invoke(cli, ["render", str(ply), "--res", "1", "-o", str(d), *extra])
        assert r.exit_code == 0, r.output
        return np.asarray(Image.open(next(d.glob("*.png"))), np.float64)

    default, on_black, on_white = render(none), render(none, "--background", "black"), render(none, "--background",
                                                                                               "white")
    assert np.array_equal(default, on_black) and on_black[0, 0].sum() == 0
    assert (on_white - on_black).mean() > 20  # the haze a black-trained PLY shows on white
    assert np.array_equal(render(white), on_white)
    grey = render(none, "--background", "0.5,0.5,0.5")
    assert np.allclose(grey[0, 0], 128, atol=1)
    for bad in ("2,0,0", "red", "0.1,0.2"):
        r = CliRunner().invoke(cli, ["render", str(none), "--background", bad])
        assert r.exit_code == 2 and "--background" in r.output and "Traceback" not in r.output
    (white.parents[2] / "cfg_args").write_text("Namespace(white_background=")
    r = CliRunner().invoke(cli, ["render", str(white)])
    assert r.exit_code == 2 and "cfg_args" in r.output and r.output.count("\n") == 1, r.output


def test_conversion_and_its_container_keep_the_sources_background(tmp_path):
    from proxycodec import codec
    from proxycodec.model import SceneModel

    ply = _trainer_output(tmp_path, None)
    log = []
    r = convert(ply, tmp_path / "a.ply", _tiny_config(iters=4), log=log.append)
    assert r.model.background == (0.0, 0.0, 0.0) and any(s.startswith("background: 0 0 0 (default") for s in log)
    assert SceneModel.load(tmp_path / "a.ply").background == (0.0, 0.0, 0.0)
    rep = codec.encode(tmp_path / "a.ply", tmp_path / "a.pxc", predictor_iters=5, entropy="zstd")
    assert rep.meta["background"] == [0.0, 0.0, 0.0] and codec.decode(tmp_path / "a.pxc").background == (0, 0, 0)
    white = _trainer_output(tmp_path, True)
    assert convert(white, tmp_path / "w.ply", _tiny_config(iters=2), log=lambda s: None).model.background == \
        (1.0, 1.0, 1.0)
    given = replace(_tiny_config(iters=2), background=(0.2, 0.4, 0.6))
    assert convert(white, tmp_path / "g.ply", given, log=lambda s: None).model.background == (0.2, 0.4, 0.6)
    # an anchor scene keeps the background it was trained on: encode refuses to change it
    res = CliRunner().invoke(cli, ["encode", str(tmp_path / "a.ply"), "--background", "white"])
    assert res.exit_code == 2 and "--background applies to a 3DGS PLY" in res.output


def _scaled(ply: GaussianPly, k: float, shift=(0.0, 0.0, 0.0)) -> GaussianPly:
    return GaussianPly(ply.means.astype(np.float64) * k + np.asarray(shift), ply.sh, ply.opacities,
                       ply.scales.astype(np.float64) + math.log(k), ply.quats)


def _decoded_leaf_error(tmp_path, scene_ply, log):
    """Max |feature| difference between the anchor scene at ``scene_ply`` and its container decoded (every attribute
    stored as float, float32 MLP weights: what is left is the leaves' regeneration)."""
    from scipy.spatial import cKDTree

    from proxycodec.codec import EncodeConfig, decode, encode
    from proxycodec.model import SceneModel

    encode(scene_ply, tmp_path / "c.pxc", EncodeConfig(entropy="zstd", feature_bits=32, offset_bits=32,
                                                        scaling_bits=32, weights_dtype="f32"), progress=log.append)
    a, b = SceneModel.load(scene_ply).scene, decode(tmp_path / "c.pxc").scene
    _, j = cKDTree(b.positions.double().numpy()).query(a.positions.double().numpy())
    return float((b.features[j] - a.features).abs().max())


def test_the_container_decodes_the_leaves_the_conversion_trained(tmp_path):
    """A conversion trains in a canonical frame and stores world coordinates: the container's decoder finds, for
    every leaf, the proxies training predicted it from (the predictor's "grid" tie rule), so the decoded leaves are
    the anchor scene's (under "position", float32 world coordinates broke the grid's ties otherwise: 1.29 here)."""
    write_inria_ply(tmp_path / "s.ply", _scaled(_ball(300), 10.0, (3.0, 1.0, 2.0)))
    convert(tmp_path / "s.ply", tmp_path / "a.ply", _tiny_config(), log=lambda s: None)
    log = []
    assert _decoded_leaf_error(tmp_path, tmp_path / "a.ply", log) < 1e-5
    assert not any("tie rule" in s for s in log)


def test_a_conversion_s_anchors_are_stored_as_integers_of_its_grid(tmp_path):
    """Converted anchors come out on the world grid through the canonical frame's centre (the scene's
    ``grid_shift``), near the frame's map of the trained positions; encode stores that grid's integers as an octree
    (scene format 6, feature "shift"), not float32 xyz, and both readers give the positions back bit for bit."""
    from proxycodec import lite
    from proxycodec.codec import EncodeConfig, decode, encode
    from proxycodec.formats.container import read_container
    from proxycodec.model import SceneModel
    from proxycodec.sections import grid_positions

    write_inria_ply(tmp_path / "s.ply", _scaled(_ball(300), 10.0, (3.0, 1.0, 2.0)))
    r = convert(tmp_path / "s.ply", tmp_path / "a.ply", _tiny_config(), log=lambda s: None)
    m = SceneModel.load(tmp_path / "a.ply")
    shift = m.scene.metadata["grid_shift"]
    assert shift == r.model.scene.metadata["grid_shift"] and grid_positions(m.scene.positions.numpy(),
                                                                            m.scene.voxel_size) is None
    ii, info = grid_positions(m.scene.positions.numpy(), m.scene.voxel_size, shift)
    assert info["shift"] == shift and info["rule"] == "f64"
    encode(tmp_path / "a.ply", tmp_path / "c.pxc", EncodeConfig(predictor_iters=10))
    pinfo = read_container(tmp_path / "c.pxc").meta["positions"]
    assert pinfo["coding"] == "octree" and pinfo["shift"] == shift
    out = decode(tmp_path / "c.pxc").scene.positions
    assert torch.equal(out.sort(0).values, m.scene.positions.sort(0).values)
    np.testing.assert_array_equal(lite.decode(tmp_path / "c.pxc").positions, out.numpy())


def test_encode_finds_the_tie_rule_of_a_conversion_written_before_the_grid_rule(tmp_path, monkeypatch):
    """A conversion whose predictor says "position" (written before "grid"): encode sees that the rule does not
    reproduce the scene's leaves, says so, and encodes under the rule that does."""
    import proxycodec.train as train

    made = train.Trainer._predictor_config
    monkeypatch.setattr(train.Trainer, "_predictor_config", lambda self: replace(made(self), ties="position"))
    write_inria_ply(tmp_path / "s.ply", _scaled(_ball(300), 10.0, (3.0, 1.0, 2.0)))
    convert(tmp_path / "s.ply", tmp_path / "a.ply", _tiny_config(), log=lambda s: None)
    from proxycodec.model import weights_path_for
    from proxycodec.proxy import load_fitted_predictor

    assert load_fitted_predictor(weights_path_for(tmp_path / "a.ply"))[0].config.ties == "position"
    log = []
    assert _decoded_leaf_error(tmp_path, tmp_path / "a.ply", log) < 1e-5
    assert any("tie rule 'position' does not reproduce the scene's leaves" in s and "'grid' does" in s for s in log)


@pytest.mark.parametrize("k", [1000.0, 0.001])
def test_results_do_not_depend_on_the_scene_s_units(tmp_path, k):
    """The same PLY in other units (x1000 / x0.001, moved away from the origin) converts to the same scene: the
    conversion works in a canonical frame, so its losses, report and decoded images are those of the original, and
    the result, written back in the PLY's units, renders from the world cameras what the original's renders."""
    base = _ball(300)
    write_inria_ply(tmp_path / "a.ply", base)
    write_inria_ply(tmp_path / "b.ply", _scaled(base, k, (3.0 * k, -2.0 * k, 5.0 * k)))
    logs = {"a": [], "b": []}
    cfg = _tiny_config(iters=24)
    ra = convert(tmp_path / "a.ply", tmp_path / "sa.ply", cfg, log=logs["a"].append)
    rb = convert(tmp_path / "b.ply", tmp_path / "sb.ply", cfg, log=logs["b"].append)
    pa = [x["psnr"] for x in ra.report["converted"]["per_resolution"]]
    pb = [x["psnr"] for x in rb.report["converted"]["per_resolution"]]
    assert all(math.isfinite(p) for p in pa) and np.allclose(pa, pb, atol=0.01), (pa, pb)
    assert ra.voxel.anchors == rb.voxel.anchors
    from proxycodec.model import SceneModel

    ma, mb = SceneModel.load(tmp_path / "sa.ply"), SceneModel.load(tmp_path / "sb.ply")
    assert mb.decoder.config.length_unit == pytest.approx(k * ma.decoder.config.length_unit)
    np.testing.assert_allclose(mb.scene.positions.double().numpy(),
                               ma.scene.positions.double().numpy() * k + np.array([3.0, -2.0, 5.0]) * k,
                               rtol=0, atol=1e-3 * k)
    for ca, cb in zip(ma.cameras[:3], mb.cameras[:3]):
        np.testing.assert_allclose(cb.center, ca.center * k + np.array([3.0, -2.0, 5.0]) * k, rtol=1e-6)
        ia, ib = ma.render(ca, 0.5).image, mb.render(cb, 0.5).image
        assert float((ia - ib).abs().mean()) < 0.01 and float(ia.std()) > 0.01


# ---------------------------------------------------------------------------------------------- antialiased sources
def test_render_and_convert_take_the_antialiased_filter_for_a_plain_ply(tmp_path, monkeypatch):
    """An INRIA PLY has no antialiased flag: `render --antialiased on` renders it with the compensation (as the
    flagged SPZ of the same Gaussians renders by itself), `--antialiased off` renders the SPZ without it;
    `convert --source-antialiased` reaches conversion's config (scene: None, the file decides), and `encode` refuses
    it for an anchor scene."""
    import proxycodec.convert as convert_module
    from PIL import Image

    from proxycodec.formats.spz import read_spz, write_spz

    ply = _trainer_output(tmp_path, False)
    spz_path = ply.with_name("aa.spz")  # beside the PLY: the same cameras.json, two folders up
    write_spz(spz_path, read_inria_ply(ply), antialiased=True)
    write_inria_ply(ply, read_spz(spz_path)[0])  # the SPZ's own (quantised) Gaussians, as a PLY

    def render(src, *extra):
        d = tmp_path / f"r{len(list(tmp_path.glob('r*')))}"
        r = CliRunner().invoke(cli, ["render", str(src), "--res", "1", "-o", str(d), "--background", "black", *extra])
        assert r.exit_code == 0, r.output
        return np.asarray(Image.open(next(d.glob("*.png"))), np.float64)

    plain, ply_on, spz, spz_off = (render(ply), render(ply, "--antialiased", "on"), render(spz_path),
                                   render(spz_path, "--antialiased", "off"))
    assert np.array_equal(ply_on, spz) and np.array_equal(plain, spz_off)
    assert plain.sum() > ply_on.sum() > 0  # the compensation only ever dims

    seen = []

    def spy(src, out, cfg, **kw):
        seen.append(cfg.source_antialiased)
        raise ProxycodecError("stop here")

    monkeypatch.setattr(convert_module, "convert", spy)
    for mode in ("scene", "on", "off"):
        res = CliRunner().invoke(cli, ["convert", str(ply), "-o", str(tmp_path / "a.ply"),
                                       "--source-antialiased", mode])
        assert res.exit_code == 2 and "stop here" in res.output
    assert seen == [None, True, False]
    other = tmp_path / "anchors.ply"  # not a plain 3DGS file: refused before it is read
    other.write_text("ply\n")
    res = CliRunner().invoke(cli, ["encode", str(other), "--source-antialiased", "on"])
    assert res.exit_code == 2 and "--source-antialiased applies to a 3DGS" in res.output, res.output


def test_a_flagged_spz_converts_against_its_antialiased_renders(tmp_path):
    """The teacher of a conversion renders a flagged SPZ with the compensation (its report measures the source that
    way), unless ``source_antialiased`` says otherwise."""
    from dataclasses import replace as dc_replace

    from proxycodec.convert import convert
    from proxycodec.formats.spz import write_spz

    write_spz(tmp_path / "g.spz", _ball(200), antialiased=True)
    reports = {}
    for told in (None, False):
        lines = []
        r = convert(tmp_path / "g.spz", tmp_path / f"a_{told}.ply", dc_replace(_tiny_config(iters=2),
                                                                              source_antialiased=told),
                    log=lines.append)
        said = [s for s in lines if "renders antialiased" in s]
        assert said == (["the source renders antialiased (the filter's opacity compensation): its file says it was "
                         "trained so"] if told is None else [])
        reports[told] = r.report["source_direct"]["per_resolution"]
    # the source rendered directly, scored against its own supersampled renders: both change with the compensation
    assert reports[None] != reports[False]
