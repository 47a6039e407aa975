"""The torch-free decode + render path (``proxycodec.lite``) against the torch one (``codec.decode`` +
``SceneModel.render`` on the cpu backend): same arrays, same images, same errors, and no torch in the CLI's decode."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from proxycodec.cli.main import cli
from proxycodec.formats.container import ContainerError, read_container, write_container
from test_codec import FAST, tiny_model

from proxycodec import codec, lite
from proxycodec.camera import orbit_cameras
from proxycodec.decoder import DecoderConfig, GaussianDecoder
from proxycodec.model import SceneModel, image_to_uint8
from proxycodec.netconfig import PredictorConfig
from proxycodec.proxy import ResidualPredictor
from proxycodec.render.project import GateConfig
from proxycodec.sections import pack_weights, read_scene_container

pytestmark = pytest.mark.usefixtures("one_thread")

CORPUS = Path(__file__).parent / "corpus" / "container"
XIS = (0.025, 0.3, 1.0, 2.0)


def _model(n=200, seed=0, **decoder_kw) -> SceneModel:
    """``test_codec.tiny_model`` with a decoder whose resolution embedding is not the identity (so FiLM matters)
    and cameras big enough to see something at xi = 0.025."""
    m = tiny_model(n, seed)
    torch.manual_seed(seed + 1)
    cfg = DecoderConfig(scene_center=(0.0, 0.0, 0.1), scene_radius=0.6, **decoder_kw)
    dec = GaussianDecoder(cfg).eval()
    if cfg.embedding != "none":
        with torch.no_grad():
            dec.mlp_embed[2].weight.normal_(0.0, 0.3)
            dec.mlp_embed[2].bias.normal_(0.0, 0.1)
    cams = orbit_cameras((0.0, 0.0, 0.1), 1.4, 3, width=64, height=48)
    return SceneModel(m.scene, dec, cams, (0.2, 0.4, 0.9))


VARIANTS = {
    "film_q8": ({}, {}),
    "film_q8_context3": ({}, {"predictor_context": 3}),
    "additive_f32_predicted_offsets": ({"embedding": "additive"}, {"weights_dtype": "f32", "predict_offsets": True}),
    "none_f16_no_gate_float_bits": ({"embedding": "none", "gate": GateConfig(enabled=False)},
                                    {"weights_dtype": "f16", "feature_bits": 32, "scaling_bits": 12}),
}


@pytest.fixture(scope="module", params=sorted(VARIANTS))
def encoded(request, tmp_path_factory):
    dec_kw, enc_kw = VARIANTS[request.param]
    path = tmp_path_factory.mktemp("lite") / f"{request.param}.pxc"
    codec.encode(_model(**dec_kw), path, **{**FAST, **enc_kw})
    return path, codec.decode(path), lite.decode(path)


def test_arrays_are_the_torch_decoders(encoded):
    _, want, got = encoded
    s = want.scene
    mask = s.metadata["proxy_mask"]
    assert np.array_equal(got.metadata["proxy_mask"], mask) and mask.any() and not mask.all()
    for k in ("positions", "scalings"):
        a, b = getattr(s, k).numpy(), getattr(got, k)
        assert a.dtype == b.dtype == np.float32 and a.shape == b.shape and a.tobytes() == b.tobytes(), k
    # stored rows bit for bit; predicted rows (leaf features, and leaf offsets when predicted) to float32 rounding
    f_want, f_got = s.features.numpy(), got.features
    assert f_got.dtype == np.float32 and f_want[mask].tobytes() == f_got[mask].tobytes()
    o_want, o_got = s.offsets.numpy(), got.offsets
    stored_rows = mask if read_container(encoded[0]).meta["offsets"] == "predicted" else slice(None)
    assert o_got.dtype == np.float32 and o_want[stored_rows].tobytes() == o_got[stored_rows].tobytes()
    for w, g in ((f_want[~mask], f_got[~mask]), (o_want[~mask].reshape(-1, 30), o_got[~mask].reshape(-1, 30))):
        np.testing.assert_allclose(g, w, rtol=1e-5, atol=1e-5 * float(np.abs(w).max()))
        rel = np.linalg.norm(g - w, axis=1) / np.maximum(np.linalg.norm(w, axis=1), 1e-30)
        assert rel.max() < 1e-5
    assert got.voxel_size == s.voxel_size and got.background == want.background
    assert [c.to_json() for c in got.cameras] == [c.to_json() for c in want.cameras]
    assert got.num_anchors == s.num_anchors and np.array_equal(got.bounds(), s.bounds())
    np.testing.assert_allclose(got.extent_radius(), s.extent_radius().numpy(), rtol=1e-6)  # exp, norm: to 1 ulp


def test_images_match_the_cpu_backend(encoded):
    _, want, got = encoded
    for cam in want.cameras[:2]:
        for xi in XIS:
            r_t = want.render(cam, xi, backend="cpu")
            r_l = got.render(cam, xi)
            a, b = r_t.image.numpy(), r_l.image
            assert a.shape == b.shape and b.dtype == np.float32, (xi, a.shape, b.shape)
            assert np.abs(a - b).max() < 1e-4, (xi, float(np.abs(a - b).max()))
            assert np.abs(r_t.alpha.numpy() - r_l.alpha).max() < 1e-4
            assert abs(r_t.projected.count - r_l.projected.count) <= 1
            assert r_l.projected.count > 0 or xi == 0.025
            assert np.array_equal(r_t.visible_anchor_index.numpy(), r_l.visible_anchor_index)


def test_same_decoder_inputs_give_the_same_gaussians_and_bits_from_projection_on(encoded):
    """Given the torch decoder's own Gaussians, the lite projection + compositing reproduce the cpu backend bit for
    bit (they are the same numba kernels); the numpy decoder matches torch's to float32 rounding."""
    _, want, got = encoded
    from proxycodec.model import decode_view

    cam = want.cameras[0].scaled(0.3)
    with torch.no_grad():
        g_t, vis = decode_view(want.scene, want.decoder, cam, 0.3)
    s, v = want.scene, vis.numpy()
    center = np.asarray(cam.center, np.float32)
    g_l = got.decoder(*(getattr(s, k).numpy()[v] for k in ("positions", "features", "offsets", "scalings")),
                      center, 0.3)
    assert np.array_equal(v[g_l.anchor_index], g_t.anchor_index.numpy())
    for k in ("means", "quats", "scales", "opacities", "colors"):
        np.testing.assert_allclose(getattr(g_l, k), getattr(g_t, k).numpy(), rtol=1e-5, atol=1e-6, err_msg=k)
    from proxycodec.render import project, rasterize
    from proxycodec.render._project_kernels import constants, project_forward
    from proxycodec.render._raster_kernels import rasterize_forward

    gate = want.decoder.config.gate
    with torch.no_grad():
        proj = project(g_t.means, g_t.quats, g_t.scales, g_t.opacities, g_t.colors, cam, gate=gate,
                       origin=g_t.origin, backend="cpu")
        img, _ = rasterize(proj, torch.tensor(want.background, dtype=torch.float32), "cpu")
    k = constants(cam, gate, 0.01, 1e10, g_t.origin.double().numpy(), np.float32)
    m2d, con, op, dep, ext, _, idx = project_forward(*(getattr(g_t, n).numpy() for n in
                                                       ("means", "quats", "scales", "opacities")), k, gate.enabled)
    assert np.array_equal(idx, proj.index.numpy()) and m2d.tobytes() == proj.means2d.numpy().tobytes()
    bg64 = np.asarray(want.background, np.float32).astype(np.float64)
    img_l = rasterize_forward(m2d, con, op, g_t.colors.numpy()[idx], dep, ext, cam.width, cam.height, bg64)[0]
    assert img_l.tobytes() == img.numpy().tobytes()


def test_default_cameras_without_stored_ones(tmp_path):
    m = _model(120)
    p = tmp_path / "nocam.pxc"
    codec.encode(m, p, **{**FAST, "max_cameras": 0})
    want, got = codec.decode(p), lite.decode(p)
    assert got.cameras is None and want.cameras is None
    a, b = codec.default_cameras(want), lite.default_cameras(got)
    assert [c.to_json() for c in a] == [c.to_json() for c in b] and len(a) == 8
    ia = want.render(a[1], 0.2, backend="cpu").image.numpy()
    assert np.abs(ia - got.render(b[1], 0.2).image).max() < 1e-4


def test_network_layouts_are_the_torch_modules():
    for cfg in (DecoderConfig(), DecoderConfig(embedding="additive", hidden=16, film_hidden=8, pe_pos_freqs=2),
                DecoderConfig(embedding="none", feat_dim=8, n_offsets=3)):
        assert lite.decoder_shapes(cfg) == {k: tuple(v.shape) for k, v in GaussianDecoder(cfg).state_dict().items()}
    for cfg in (PredictorConfig(), PredictorConfig(n_blocks=0, hidden=8, predict_offsets=True, pe_dir_freqs=0)):
        want = {k: tuple(v.shape) for k, v in ResidualPredictor(cfg).state_dict().items()}
        assert lite.predictor_shapes(cfg) == want


# ---------------------------------------------------------------------------------------------- errors
def _outcome(fn, path):
    try:
        fn(path)
    except ContainerError as e:
        return "ContainerError", str(e)
    return "ok", ""


def test_hostile_containers_fail_as_in_the_torch_path(encoded, tmp_path):
    path = encoded[0]
    c = read_scene_container(path)  # weights unpacked: the cases below edit them by name, then pack again
    lay = pack_weights(c.arrays)[1]
    cases = {
        "wrong count": ({**c.meta, "anchors": {**c.meta["anchors"], "count": c.meta["anchors"]["count"] + 1}},
                        c.arrays),
        "missing section": (c.meta, {k: v for k, v in c.arrays.items() if k != "anchors/scalings"}),
        "wrong dtype": (c.meta, {**c.arrays, "anchors/scalings": c.arrays["anchors/scalings"].astype(np.int16)}),
        "bad quant": ({**c.meta, "quant": {**c.meta["quant"], "scalings": {"bits": 8, "offset": [0.0]}}}, c.arrays),
        "future scene format": ({**c.meta, "scene_format": 99}, c.arrays),
        "not a scene": ({**c.meta, "kind": "proxycodec.weights"}, c.arrays),
        "garbage metadata": ({**c.meta, "positions": "grid"}, c.arrays),
        "metadata of the wrong type": ({**c.meta, "anchors": []}, c.arrays),
        "missing weights": (c.meta, {k: v for k, v in c.arrays.items() if not k.startswith("predictor/")}),
        "weights of the wrong shape": (c.meta, {**c.arrays, "decoder/mlp_cov.2.bias":
                                                c.arrays["decoder/mlp_cov.2.bias"][:3]}),
        "nan weights": (c.meta, {**c.arrays, "predictor/head.bias":
                                 np.full_like(c.arrays["predictor/head.bias"], np.nan)}),
        "bad predictor config": ({**c.meta, "predictor": {**c.meta["predictor"], "dist_ref": 1e308}}, c.arrays),
        "bad camera": ({**c.meta, "cameras": [{"fx": 1}]}, c.arrays),
        "bad background": ({**c.meta, "background": [1, 2]}, c.arrays),
        "weights layout longer than its section": ({**c.meta, "weights_layout": lay + [lay[0]]}, c.arrays),
        "weights layout shorter than its section": ({**c.meta, "weights_layout": lay[1:]}, c.arrays),
        "weights layout entry malformed": ({**c.meta, "weights_layout": [[lay[0][0], "f8", [2]]] + lay[1:]}, c.arrays),
        "weights layout shape of the wrong type": ({**c.meta, "weights_layout": [[lay[0][0], lay[0][1], "32"]]
                                                    + lay[1:]}, c.arrays),
        "weights layout missing": ({k: v for k, v in c.meta.items() if k != "weights_layout"}, c.arrays),
    }
    for name, (meta, arrays) in cases.items():
        p = tmp_path / "bad.pxc"
        packed, layout = pack_weights(arrays)
        write_container(p, meta if name.startswith("weights layout") else {**meta, "weights_layout": layout},
                        packed, level=1)
        want = _outcome(codec.decode, p)
        assert want[0] == "ContainerError", name
        assert _outcome(lite.decode, p) == want, name
    data = path.read_bytes()
    for i, pos in enumerate(list(range(0, len(data), max(1, len(data) // 40))) + [len(data) - 1]):
        flipped = bytearray(data)
        flipped[pos] ^= 1 << (i % 8)
        p = tmp_path / f"flip{i}.pxc"
        p.write_bytes(bytes(flipped))
        assert _outcome(lite.decode, p) == _outcome(codec.decode, p), pos
    for cut in (0, 7, 40, len(data) // 2, len(data) - 1):
        p = tmp_path / "cut.pxc"
        p.write_bytes(data[:cut])
        got = _outcome(lite.decode, p)
        assert got == _outcome(codec.decode, p) and got[0] == "ContainerError", cut


def test_corpus_containers_fail_as_in_the_torch_path():
    files = sorted(CORPUS.glob("*.pxc"))
    assert files
    for p in files:
        assert _outcome(lite.decode, p) == _outcome(codec.decode, p), p.name


def test_cli_decode_uses_the_lite_path_and_its_errors_are_one_line(encoded, tmp_path):
    path = encoded[0]
    runner = CliRunner()
    out = tmp_path / "r"
    r = runner.invoke(cli, ["decode", str(path), "--res", "0.3,1", "--view", "1", "-o", str(out)])
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in out.iterdir()) == ["view001_res0.300.png", "view001_res1.000.png"]
    from PIL import Image

    model = codec.decode(path)
    for xi in (0.3, 1.0):
        png = np.asarray(Image.open(out / f"view001_res{xi:.3f}.png"))
        want = image_to_uint8(model.render(model.cameras[1], xi, backend="cpu").image)
        assert png.shape == want.shape and np.abs(png.astype(int) - want).max() <= 1
    bad = tmp_path / "bad.pxc"
    bad.write_bytes(path.read_bytes()[:-5])
    for backend in ("auto", "cpu", "reference"):
        r = runner.invoke(cli, ["decode", str(bad), "-o", str(tmp_path / "x"), "--backend", backend])
        assert r.exit_code == 2 and r.output.startswith("error: ") and r.output.count("\n") == 1, r.output
        assert str(bad) in r.output
    r = runner.invoke(cli, ["decode", str(path), "--view", "7", "-o", str(tmp_path / "y")])
    assert r.exit_code == 2 and "view 7 does not exist" in r.output


def test_cli_decode_on_the_cpu_never_imports_torch(encoded, tmp_path):
    path = encoded[0]
    script = f"""
import json, sys
from click.testing import CliRunner
from proxycodec.cli.main import cli
runs = []
for extra in ([], ["--backend", "cpu"], ["--no-render"]):
    r = CliRunner().invoke(cli, ["decode", {str(path)!r}, "--res", "0.3", "--view", "0", "-o", {str(tmp_path)!r}]
                           + extra)
    runs.append([r.exit_code, r.output])
print(json.dumps({{"runs": runs, "torch": "torch" in sys.modules, "lite": "proxycodec.lite" in sys.modules}}))
"""
    res = subprocess.run([sys.executable, "-c", script], check=False, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    got = json.loads(res.stdout.strip().splitlines()[-1])
    assert all(code == 0 for code, _ in got["runs"]), got["runs"]
    assert got["lite"] and not got["torch"], got
    assert (tmp_path / "view000_res0.300.png").exists()
