"""Exports of a decoded scene as plain 3DGS (``proxycodec.export``): what ``decode --ply/--spz/--glb/--lod`` write."""

import json

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from proxycodec import codec
from proxycodec.cli.main import cli
from proxycodec.errors import ProxycodecError
from proxycodec.explicit import ExplicitModel
from proxycodec.export import (
    BakeConfig,
    bake,
    export_psnr,
    held_out_cameras,
    parse_levels,
    sphere_cameras,
    write_gaussians,
    write_lod,
)
from proxycodec.formats.inria_ply import read_inria_ply
from proxycodec.model import apply_gate_mode
from tests.test_codec import tiny_model


def view_independent(model):
    """The model with its MLPs blind to the view: direction and distance inputs zeroed, gate off."""
    dec = model.decoder
    with torch.no_grad():
        for mlp in (dec.mlp_opacity, dec.mlp_cov, dec.mlp_color):
            mlp[0].weight[:, -4:] = 0.0
    apply_gate_mode(model, "off")
    return model


def test_a_view_independent_scene_exports_exactly():
    """With nothing depending on the view, the exported set rendered as plain 3DGS is the scene's own render."""
    m = view_independent(tiny_model(120))
    b = bake(m, BakeConfig(xi=1.0, sh_degree=0, directions=6))
    assert b.ply.n_gaussians > 100
    ex = ExplicitModel(b.ply, m.background)
    import flips

    for cam in m.cameras + sphere_cameras(m, 3, offset=0.3):
        a = m.render(cam, 1.0, backend="reference")
        e = ex.render(cam, 1.0, backend="reference")
        # the baked opacities go through logit and sigmoid: an alpha at 1/255 may flip by an ulp on another CPU
        flips.assert_images_agree(a.image, e.image, a.projected, e.projected, atol=2e-4, rtol=1e-5,
                                  max_flips=4)


def test_centres_are_exact_and_single_view_opacity_is_the_gated_one():
    m = tiny_model(80)
    cam = m.cameras[0]
    b = bake(m, BakeConfig(xi=0.5, sh_degree=0), cameras=[cam])
    s = m.scene
    K = s.n_offsets
    full = (s.positions.double()[:, None] + s.offsets.double() * torch.exp(s.scalings.double()[:, None, :3]))
    full = full.reshape(-1, 3).float().numpy()
    # Every exported centre is one of the slots' exact centres.
    d = np.abs(b.ply.means[:, None, :] - full[None]).max(-1).min(1)
    assert d.max() == 0.0
    # One view: the stored opacity is that view's gated opacity o * g.
    r = m.render(cam, 0.5)
    g, proj = r.gaussians, r.projected
    want = {int(g.anchor_index[i] * K + g.slot[i]): float(o) for i, o in zip(proj.index.tolist(),
                                                                            proj.opacities.tolist())}
    slot_of = {tuple(full[k]): k for k in want}
    got = 1.0 / (1.0 + np.exp(-b.ply.opacities.astype(np.float64)))
    for mean, o in zip(b.ply.means, got):
        k = slot_of[tuple(mean)]
        assert abs(o - want[k]) < 1e-5


def test_a_lower_resolution_keeps_fewer_gaussians():
    m = tiny_model(150)
    counts = [bake(m, BakeConfig(xi=xi, directions=8)).ply.n_gaussians for xi in (1.0, 0.25, 0.05)]
    assert counts[0] >= counts[1] > counts[2] > 0


def test_sh_fits_view_dependent_colour_better_than_one_baked_view():
    """Geometry blind to the view, colour strongly dependent on it: held-out PSNR orders view < SH0 < SH1."""
    m = view_independent(tiny_model(150))
    gen = torch.Generator().manual_seed(0)
    with torch.no_grad():
        w = m.decoder.mlp_color[0].weight
        w[:, -4:-1] = 2.0 * torch.randn(w.shape[0], 3, generator=gen)
    ho = held_out_cameras(m, 4)
    p = {c: float(np.mean(export_psnr(m, bake(m, BakeConfig(directions=24, **kw)).ply, 1.0, ho)))
         for c, kw in (("view", {"view": 0}), ("sh0", {"sh_degree": 0}), ("sh1", {"sh_degree": 1}))}
    assert p["view"] + 2.0 < p["sh0"] and p["sh0"] + 4.0 < p["sh1"], p


def test_bake_is_deterministic_and_finite(tmp_path):
    m = tiny_model(60)
    a = write_gaussians(tmp_path / "a.ply", bake(m, BakeConfig(sh_degree=3, directions=4)).ply)
    b = write_gaussians(tmp_path / "b.ply", bake(m, BakeConfig(sh_degree=3, directions=4)).ply)
    assert a == b and (tmp_path / "a.ply").read_bytes() == (tmp_path / "b.ply").read_bytes()
    g = read_inria_ply(tmp_path / "a.ply")
    assert g.sh_degree == 3 and all(np.isfinite(x).all() for x in (g.means, g.sh, g.opacities, g.scales, g.quats))


def test_an_extreme_resolution_bakes_without_nan():
    m = tiny_model(40)
    for xi in (0.025, 2.0):
        p = bake(m, BakeConfig(xi=xi, directions=2)).ply
        assert all(np.isfinite(x).all() for x in (p.means, p.sh, p.opacities, p.scales, p.quats))


def test_lod_set_manifest(tmp_path):
    m = tiny_model(100)
    man = write_lod(m, tmp_path / "lod", (1.0, 0.25, 0.05), fmt="ply", directions=4, source="t.pxc")
    on_disk = json.loads((tmp_path / "lod" / "lod.json").read_text())
    assert on_disk == man and man["lodLevels"] == 3 and man["filenames"] == ["lod0.ply", "lod1.ply", "lod2.ply"]
    for e in man["levels"]:
        g = read_inria_ply(tmp_path / "lod" / e["file"])
        assert g.n_gaussians == e["count"] and (tmp_path / "lod" / e["file"]).stat().st_size == e["bytes"]
        assert e["distance_scale"] == pytest.approx(1.0 / e["resolution"])
    assert man["counts"][0] > man["counts"][2] and man["count"] == sum(man["counts"])


def test_levels_and_formats_are_checked():
    assert parse_levels("0.25,1,0.5") == (1.0, 0.5, 0.25)
    for bad in ("", "1,1", "a", "3"):
        with pytest.raises(ProxycodecError):
            parse_levels(bad)
    with pytest.raises(ProxycodecError, match="unknown export format"):
        write_gaussians("x.obj", bake(tiny_model(20), BakeConfig(directions=0)).ply)
    with pytest.raises(ProxycodecError, match="view 7 does not exist"):
        bake(tiny_model(20), BakeConfig(view=7))


def test_decode_cli_exports_and_lod(tmp_path):
    m = tiny_model(80)
    pxc = tmp_path / "s.pxc"
    codec.encode(m, pxc, distill=False, predictor_iters=10, zstd_level=3)
    run = CliRunner().invoke
    r = run(cli, ["decode", str(pxc), "--res", "0.5", "--ply", str(tmp_path / "e.ply"), "--sh-degree", "2"])
    assert r.exit_code == 0, r.output
    assert read_inria_ply(tmp_path / "e.ply").sh_degree == 2
    r = run(cli, ["decode", str(pxc), "--lod", str(tmp_path / "lod"), "--levels", "1,0.1", "--lod-format", "ply"])
    assert r.exit_code == 0, r.output
    man = json.loads((tmp_path / "lod" / "lod.json").read_text())
    assert [e["resolution"] for e in man["levels"]] == [1.0, 0.1] and man["source"] == "s.pxc"
    r = run(cli, ["decode", str(pxc), "--lod", str(tmp_path / "x"), "--bake-view", "0"])
    assert r.exit_code == 2 and r.output.startswith("error: ")


def test_spz_and_glb_exports_read_back_and_render_like_the_ply(tmp_path):
    """Each format read back by our readers (through the one entry point every command uses) renders within its
    quantisation of the PLY export, which renders within the bake's own error of the scene."""
    from proxycodec.formats.splats import read_splats, splat_kind
    from proxycodec.scenes import load_any

    m = tiny_model(120)
    baked = bake(m, BakeConfig(xi=0.5, sh_degree=1, directions=4))
    cams = m.cameras
    ref = np.mean(export_psnr(m, baked.ply, 0.5, cams))
    assert ref > 35.0, ref  # the PLY export against the container's own render at the same resolution
    for fmt in ("ply", "spz", "glb"):
        path = tmp_path / f"e.{fmt}"
        n = write_gaussians(path, baked.ply)
        assert n == path.stat().st_size and splat_kind(path) == fmt
        ply, info = read_splats(path)
        assert ply.n_gaussians == baked.ply.n_gaussians and ply.sh_degree == 1 and info["kind"] == fmt
        if fmt != "spz":  # PLY and GLB hold float32: the same Gaussians
            np.testing.assert_allclose(ply.means, baked.ply.means, atol=1e-6)
        else:
            assert np.abs(ply.means - baked.ply.means).max() <= 2.0 ** -12
        loaded = load_any(path)
        assert isinstance(loaded, ExplicitModel)
        p = np.mean(export_psnr(m, loaded.ply, 0.5, cams))
        assert p > ref - (0.5 if fmt == "spz" else 0.01), (fmt, p, ref)
        s = codec.stats(path)
        assert s["type"] == ("inria-3dgs-ply" if fmt == "ply" else fmt) and s["gaussians"] == ply.n_gaussians
    r = CliRunner().invoke(cli, ["stats", str(tmp_path / "e.spz")])
    assert r.exit_code == 0 and "SPZ" in r.output and "Gaussians" in r.output
    r = CliRunner().invoke(cli, ["render", str(tmp_path / "e.glb"), "--res", "0.5", "-o", str(tmp_path / "r")])
    assert r.exit_code == 0, r.output
