"""Anchor scene validation, the neural Gaussian decoder, frustum culling and model persistence."""

import math
import subprocess
import sys
from dataclasses import replace
from types import SimpleNamespace

import flips
import numpy as np
import pytest
import torch

import proxycodec.model as model_mod
from proxycodec import ProxycodecError
from proxycodec.camera import Camera
from proxycodec.decoder import DecoderConfig, GaussianDecoder
from proxycodec.model import SceneModel, render_scene
from proxycodec.scene import AnchorScene


def tiny_scene(m=200, seed=0, K=10, F=32):
    g = torch.Generator().manual_seed(seed)
    pos = torch.round((torch.rand(m, 3, generator=g) - 0.5) * 2 / 0.05) * 0.05
    return AnchorScene(
        positions=pos,
        features=torch.randn(m, F, generator=g),
        offsets=torch.randn(m, K, 3, generator=g) * 0.5,
        scalings=torch.log(torch.full((m, 6), 0.05)),
        voxel_size=0.05,
    ).validate()


def tiny_decoder(seed=0, **kw):
    torch.manual_seed(seed)
    dec = GaussianDecoder(DecoderConfig(**kw))
    with torch.no_grad():  # make most Gaussians visible
        dec.mlp_opacity[2].bias.fill_(1.0)
    return dec.eval()


CAM = Camera.look_at([0.0, -3.0, 1.0], [0, 0, 0], width=40, height=32)


def test_validate_rejects_bad_scenes():
    s = tiny_scene(5)
    with pytest.raises(ProxycodecError, match="NaN"):
        replace(s, features=s.features.clone().fill_(float("nan"))).validate()
    with pytest.raises(ProxycodecError, match="shape"):
        replace(s, scalings=s.scalings[:, :5]).validate()
    with pytest.raises(ProxycodecError, match="voxel"):
        replace(s, voxel_size=0.0).validate()
    assert tiny_scene(0).validate().num_anchors == 0


def test_film_starts_as_identity_and_depends_on_resolution_once_trained():
    s = tiny_scene(30)
    dec = tiny_decoder()
    assert torch.equal(dec.embed(s.positions, s.features, 0.1), s.features)
    with torch.no_grad():
        dec.mlp_embed[2].weight.normal_()
    a, b = dec.embed(s.positions, s.features, 0.1), dec.embed(s.positions, s.features, 1.0)
    assert not torch.allclose(a, b)
    none = tiny_decoder(embedding="none")
    assert not hasattr(none, "mlp_embed")
    add = tiny_decoder(embedding="additive")
    assert add.mlp_embed[2].out_features == 32


def test_frustum_culling_changes_nothing_but_the_work(monkeypatch):
    s, dec = tiny_scene(300), tiny_decoder()
    cam = Camera.look_at([0.4, -1.5, 0.3], [0.4, 0, 0.3], width=40, height=32, fov_x_deg=30)
    with torch.no_grad():
        culled = render_scene(s, dec, cam, 1.0, backend="reference")
        monkeypatch.setattr(model_mod, "visible_anchors", lambda pos, r, c, near=0.01: torch.arange(pos.shape[0]))
        full = render_scene(s, dec, cam, 1.0, backend="reference")
    assert culled.visible_anchor_index.numel() < s.num_anchors // 2  # most anchors never reach the MLPs
    # The Gaussians of the anchors culled never survive projection (but for a cull within rounding of its threshold)
    vis = culled.visible_anchor_index.numpy()
    rows = np.flatnonzero(np.isin(full.gaussians.anchor_index.numpy(), vis))
    outside = ~np.isin(full.projected.index.numpy(), rows)
    assert (flips.cull_margins(full.projected)[outside] < 1e-4).all(), "culled anchors' Gaussians are drawn"
    # and the others are the same Gaussians, rendered alike. Not bit for bit: the decoder ran on 98 anchors in one
    # render and 300 in the other, and a BLAS kernel may round a row differently with the batch size (MKL's AVX2 code
    # path does), so a decision within rounding of its threshold may flip (issue #14, tests/flips.py).
    g = full.gaussians
    g = replace(g, **{k: getattr(g, k)[rows] for k in ("means", "quats", "scales", "opacities", "colors",
                                                       "anchor_index", "slot")})
    keep = ~outside
    p = replace(full.projected, **{k: getattr(full.projected, k)[keep] for k in (
        "means2d", "conics", "opacities", "colors", "depths", "extent", "gate")},
        index=torch.from_numpy(np.searchsorted(rows, full.projected.index.numpy()[keep])))
    full_visible = SimpleNamespace(gaussians=g, projected=p, image=full.image, alpha=full.alpha)
    flips.assert_renders_agree(culled, full_visible, dec.config.n_offsets, otol=1e-5, rtol=1e-4, dtol=1e-5,
                               atol=1e-6, max_flips=8)


def test_anchors_with_no_visible_gaussians_and_empty_scene():
    s, dec = tiny_scene(50), tiny_decoder()
    with torch.no_grad():
        dec.mlp_opacity[2].bias.fill_(-10.0)  # every opacity <= 0: all Gaussians dropped
    r = render_scene(s, dec, CAM, 1.0, background=(0.0, 0.5, 1.0), backend="reference")
    assert r.gaussians.count == 0 and torch.allclose(r.image, torch.tensor([0.0, 0.5, 1.0]).expand_as(r.image))
    e = render_scene(tiny_scene(0), tiny_decoder(), CAM, 0.5, backend="reference")
    assert torch.isfinite(e.image).all() and e.gaussians.count == 0


@pytest.mark.parametrize("xi", [0.025, 0.1, 1.0, 2.0])
def test_render_any_resolution_is_finite_with_gradients(xi):
    s, dec = tiny_scene(120), tiny_decoder()
    feats = s.features.clone().requires_grad_(True)
    r = render_scene(s, dec, CAM, xi, features=feats, backend="reference")
    assert r.image.shape[:2] == (max(1, round(32 * xi)), max(1, round(40 * xi)))
    assert torch.isfinite(r.image).all()
    r.image.mean().backward()
    assert torch.isfinite(feats.grad).all()
    grads = {n: p.grad for n, p in dec.named_parameters() if p.grad is not None}
    assert grads and all(torch.isfinite(g).all() for g in grads.values()), [n for n, g in grads.items()
                                                                             if not torch.isfinite(g).all()]
    if feats.grad.abs().sum() > 0:  # something is drawn: the colour MLP's gradient reaches its first layer too
        assert any(n.startswith("mlp_color") and g.abs().sum() > 0 for n, g in grads.items()), sorted(grads)


def test_resolution_outside_range_is_a_user_error():
    with pytest.raises(ProxycodecError, match="outside"):
        render_scene(tiny_scene(3), tiny_decoder(), CAM, 3.0)


def test_save_load_round_trip_in_a_fresh_process(tmp_path):
    m = SceneModel(tiny_scene(80), tiny_decoder(), [CAM], (0.0, 0.0, 0.0))
    ply, w = m.save(tmp_path / "s.ply")
    back = SceneModel.load(ply)
    for k in ("positions", "features", "offsets", "scalings"):
        assert torch.equal(getattr(back.scene, k), getattr(m.scene, k))
    for (k, a), (_, b) in zip(m.decoder.state_dict().items(), back.decoder.state_dict().items()):
        assert torch.equal(a, b), k
    assert back.cameras[0] == CAM and back.background == (0.0, 0.0, 0.0)
    img = m.render(CAM, 0.5, backend="reference").image
    np.save(tmp_path / "expected.npy", img.numpy())
    code = (  # bit for bit: the same machine, the same kernels, the same thread count (BLAS may split sums by it)
        f"import numpy as np, sys, torch; torch.set_num_threads({torch.get_num_threads()}); "
        "from proxycodec.model import SceneModel; "
        f"m = SceneModel.load({str(ply)!r}); img = m.render(m.cameras[0], 0.5, backend='reference').image.numpy(); "
        f"sys.exit(0 if np.array_equal(img, np.load({str(tmp_path / 'expected.npy')!r})) else 1)"
    )
    assert subprocess.run([sys.executable, "-c", code]).returncode == 0


def test_missing_weights_sidecar_is_a_clear_error(tmp_path):
    ply, w = SceneModel(tiny_scene(4), tiny_decoder()).save(tmp_path / "a.ply")
    w.unlink()
    with pytest.raises(ProxycodecError, match="weights"):
        SceneModel.load(ply)


def test_a_ply_and_weights_that_do_not_belong_together_are_refused(tmp_path):
    a_ply, _ = SceneModel(tiny_scene(6, seed=1), tiny_decoder()).save(tmp_path / "a.ply")
    b_ply, _ = SceneModel(tiny_scene(6, seed=2), tiny_decoder()).save(tmp_path / "b.ply")
    b_ply.replace(a_ply)  # same anchor count and shapes, other anchors: a silent mismatch without the check
    with pytest.raises(ProxycodecError, match="different anchor PLY"):
        SceneModel.load(a_ply)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.ply", "a.weights.pxc", "b.weights.pxc"]


def test_film_does_not_extrapolate_outside_its_training_band():
    s = tiny_scene(20)
    dec = tiny_decoder(film_xi_range=(0.1, 1.0))
    with torch.no_grad():
        dec.mlp_embed[2].weight.normal_()
    e = lambda xi: dec.embed(s.positions, s.features, xi)  # noqa: E731
    assert torch.equal(e(0.025), e(0.1)) and torch.equal(e(2.0), e(1.0))
    assert not torch.equal(e(0.1), e(0.5))
    cfg = DecoderConfig.from_json(DecoderConfig(film_xi_range=(0.2, 0.9)).to_json())
    assert cfg.film_xi_range == (0.2, 0.9)
    assert DecoderConfig.from_json({k: v for k, v in DecoderConfig().to_json().items()
                                    if k != "film_xi_range"}).film_xi_range == (0.1, 1.0)
    with pytest.raises(ProxycodecError, match="film_xi_range"):
        DecoderConfig(film_xi_range=(1.0, 0.1))


def test_the_sample_scene_is_the_same_bytes_for_a_seed_whatever_torch_drew_before(tmp_path):
    """``proxycodec sample`` is deterministic: its decoder's randomly initialised layers (the FiLM MLP's first
    layer) are drawn from the scene's seed, not from torch's global stream (which the caller may have advanced)."""
    from proxycodec.sample import sample_model

    torch.manual_seed(123)
    a = sample_model(0)
    torch.rand(1000)  # the global stream moved on
    b = sample_model(0)
    wa, wb = a.decoder.state_arrays(), b.decoder.state_arrays()
    assert sorted(wa) == sorted(wb)
    for k in wa:
        assert wa[k].tobytes() == wb[k].tobytes(), k
    after = torch.rand(1)
    torch.manual_seed(123)
    torch.rand(1000)
    assert torch.equal(after, torch.rand(1)), "sampling must not consume the caller's torch random stream"
    pa, pb = a.save(tmp_path / "a.ply"), b.save(tmp_path / "b.ply")
    assert [p.read_bytes() for p in pa] == [p.read_bytes() for p in pb]


def test_the_sample_decoder_survives_the_container_and_its_stripes_are_steps_off_the_grid_values(tmp_path):
    """The built-in scene's decoder is on the storage grid (int8 rows, float16 vectors): the default weight
    quantisation stores it unchanged. Its stripes are steps of a phase's sine whose ramps lie between the values the
    sine takes on the voxel grid, far enough from them that a predicted phase a little off changes no colour."""
    from proxycodec import codec
    from proxycodec.sample import PATTERNS, _ramp, sample_model

    m = sample_model(0)
    rep = codec.encode(m, tmp_path / "s.pxc", distill=False, predictor_iters=1, zstd_level=3)
    wa, wb = m.decoder.state_arrays(), rep.model.decoder.state_arrays()
    for k in wa:
        np.testing.assert_allclose(wb[k], wa[k], rtol=1e-6, atol=1e-7, err_msg=k)
    f = m.scene.features.numpy()
    for j, (_, _, period, target, _) in enumerate(PATTERNS):
        assert 0 < period and -1 < target < 1
        lo, hi = _ramp(period, target)
        s = f[:, 3 + 2 * j]
        on = s[s > -1.5]  # the pattern's part
        assert len(on) > 50
        assert np.minimum(np.abs(on - lo), np.abs(on - hi)).min() > 0.05, j
        assert not ((on > lo) & (on < hi)).any(), j
        assert (on >= hi).any() and (on <= lo).any(), j  # stripes on and off


def test_positional_encoding_frequencies_are_cached_safely():
    """The cached 2^k pi table gives NeRF's encoding, and a table first made under inference mode still serves
    autograd (an inference tensor could not be saved for backward)."""
    from proxycodec.decoder import _frequencies, positional_encoding

    _frequencies.cache_clear()
    x = torch.tensor([[0.25, -0.5]], dtype=torch.float64)
    with torch.inference_mode():
        positional_encoding(x, 3)
    k = torch.arange(3, dtype=torch.float64)
    want = torch.cat([x, torch.sin(x[..., None] * 2.0**k * math.pi).flatten(-2),
                      torch.cos(x[..., None] * 2.0**k * math.pi).flatten(-2)], -1)
    xg = x.clone().requires_grad_(True)
    got = positional_encoding(xg, 3)
    assert torch.equal(got.detach(), want)
    got.sum().backward()
    assert torch.isfinite(xg.grad).all() and xg.grad.abs().sum() > 0
