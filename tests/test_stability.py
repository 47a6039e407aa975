"""Numerical stability of the hard cases, on every available compositing backend.

Finite outputs and bounded gradients for: the coverage gate near det Sigma2D = 0 (needle-thin and flat Gaussians,
anisotropy up to 1e6, gradient against finite differences), sub-pixel Gaussians at xi = 0.025 and huge ones at
xi = 2, Gaussians crossing the near plane or the image border, scenes seen from inside, zero/tiny quaternions,
log-scales of -20 and +10, saturated MLP outputs (+-1e4), coordinates of 1e5 and voxels of 1e-4, and a short
optimisation of a scene with such outliers. ``tests/test_render_reference.py`` and ``tests/test_gate_projection.py``
cover the reference backend on random Gaussians; this file adds the decoder path, the other backends and the
extremes.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from proxycodec.camera import Camera
from proxycodec.decoder import DecoderConfig, GaussianDecoder
from proxycodec.model import SceneModel, render_scene
from proxycodec.render import available_backends, project_gaussians, render_gaussians
from proxycodec.render.project import GATE_DET_FLOOR, GateConfig
from proxycodec.scene import AnchorScene

ALL_BACKENDS = ("reference", "cpu")


pytestmark = pytest.mark.usefixtures("one_thread")


def _backend(name: str) -> str:
    if name not in available_backends():
        assert name not in ("reference", "cpu"), f"backend {name!r} must always be available (numba is a dependency)"
        pytest.skip(f"backend {name!r} is not available here (available: {available_backends()})")
    return name


@pytest.fixture(params=ALL_BACKENDS)
def backend(request):
    return _backend(request.param)


def _finite_bounded(tensors, bound=1e8):
    for t in tensors:
        if t.grad is not None:
            assert torch.isfinite(t.grad).all(), "non-finite gradient"
            assert t.grad.abs().max() < bound, f"gradient {float(t.grad.abs().max()):.3g} exceeds {bound:g}"


def _check_image(r, bg_max=1.0):
    assert torch.isfinite(r.image).all() and torch.isfinite(r.alpha).all()
    assert r.image.min() >= -1e-6 and r.image.max() <= bg_max + 1e-5
    assert r.alpha.min() >= -1e-6 and r.alpha.max() <= 1 + 1e-6


# ================================================================================== explicit Gaussians, projection

CAM = Camera.look_at([0.0, -3.0, 0.0], [0, 0, 0], width=24, height=20, fov_x_deg=45)


def _rot_quat(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return [math.cos(angle / 2), *(math.sin(angle / 2) * axis)]


def _degenerate_gaussians(kind: str, dtype=torch.float64):
    """Eight Gaussians at the view centre with various orientations and a given degeneracy."""
    n = 8
    g = torch.Generator().manual_seed(1)
    means = (torch.rand(n, 3, generator=g, dtype=dtype) - 0.5) * 0.6
    quats = torch.tensor([_rot_quat(a, t) for a, t in zip(
        [(1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 0), (1, 2, 3), (0, 1, 1), (3, -1, 2), (1, 0, 1)],
        [0, 0.3, 1.1, 0.7, 2.0, 1e-4, math.pi / 2, 0.01])], dtype=dtype)
    base = 0.05
    if kind == "needle":  # anisotropy 1e6: one long axis, two degenerate
        scales = torch.tensor([base, base * 1e-6, base * 1e-6], dtype=dtype).expand(n, 3).clone()
    elif kind == "flat":  # a disc: one axis 1e-6 of the others
        scales = torch.tensor([base, base, base * 1e-6], dtype=dtype).expand(n, 3).clone()
    elif kind == "point":  # all three axes tiny: det -> 0 in every direction
        scales = torch.full((n, 3), 1e-9, dtype=dtype)
    elif kind == "aniso1e3":
        scales = torch.tensor([base, base * 1e-3, base * 1e-1], dtype=dtype).expand(n, 3).clone()
    else:
        raise ValueError(kind)
    opac = torch.linspace(0.2, 0.95, n, dtype=dtype)
    colors = torch.rand(n, 3, generator=g, dtype=dtype)
    return means, quats, scales, opac, colors


@pytest.mark.parametrize("kind", ["needle", "flat", "point", "aniso1e3"])
def test_gate_near_singular_covariance_is_finite_and_matches_finite_differences(kind):
    """The gated opacity as a function of the 3D parameters, float64 gradcheck, for det Sigma2D -> 0."""
    m, q, s, o, c = _degenerate_gaussians(kind)
    proj = project_gaussians(m, q, s, o, c, CAM)
    assert proj.count > 0
    assert torch.isfinite(proj.conics).all() and torch.isfinite(proj.opacities).all()
    # Undilated areas are tiny: the gate must sit in its flat low end (>= g(0) = 0.269), never NaN.
    assert (proj.gate >= 0.26).all() and (proj.gate <= 1).all()
    idx = proj.index

    def gated(means, quats, scales):
        p = project_gaussians(means, quats, scales, o, c, CAM)
        assert torch.equal(p.index, idx)  # the perturbation must not change what is culled
        return p.opacities, p.conics

    args = tuple(t.detach().clone().requires_grad_(True) for t in (m, q, s))
    # Scales of 5e-8 (needles) need a step below them; rtol covers the conic's 1/det(dilated) curvature.
    eps = 1e-10 if kind == "point" else 1e-9
    assert torch.autograd.gradcheck(gated, args, eps=eps, atol=1e-5, rtol=1e-3)
    # Bounded: the floor caps dA/dSigma at (pi/2) lambda_max / sqrt(floor).
    out = gated(*args)
    (out[0].sum() + out[1].sum()).backward()
    _finite_bounded(args, bound=1e9)


def test_gate_gradient_bound_is_the_documented_one():
    """d g / d Sigma2D <= kappa/4 * (pi/2) * lambda_max / sqrt(floor) for any det >= 0 (here: rank one, 1e6 aniso)."""
    gate = GateConfig()
    for lam in (1e-6, 1e-2, 1.0, 1e3):
        for v in ([1.0, 0.0], [0.6, 0.8]):
            u = torch.tensor(v, dtype=torch.float64)
            sigma = (lam * torch.outer(u, u) + 1e-6 * lam * torch.eye(2, dtype=torch.float64)).requires_grad_(True)
            det = sigma[0, 0] * sigma[1, 1] - sigma[0, 1] * sigma[1, 0]
            area = math.pi * torch.sqrt(det.clamp_min(0) + GATE_DET_FLOOR)
            g = torch.sigmoid(gate.kappa * (area - gate.eta))
            g.backward()
            bound = gate.kappa / 4 * (math.pi / 2) * lam * 1.000001 / math.sqrt(GATE_DET_FLOOR)
            assert torch.isfinite(sigma.grad).all() and sigma.grad.abs().max() <= bound + 1e-12


@pytest.mark.parametrize("kind", ["needle", "flat", "point"])
@pytest.mark.parametrize("xi", [0.025, 1.0, 2.0])
def test_degenerate_gaussians_render_on_every_backend(kind, xi, backend):
    m, q, s, o, c = _degenerate_gaussians(kind, torch.float32)
    leaves = [t.requires_grad_(True) for t in (m, q, s, o, c)]
    r = render_gaussians(m, q, s, o, c, CAM.scaled(xi), backend=backend)
    _check_image(r)
    (r.image.sum() + r.alpha.sum()).backward()
    _finite_bounded(leaves)


def _hard_scene(case: str, dtype=torch.float32):
    """Explicit Gaussians and a camera for one of the geometric hard cases."""
    g = torch.Generator().manual_seed(11)
    n = 40
    means = (torch.rand(n, 3, generator=g, dtype=dtype) - 0.5) * 1.2
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = torch.exp(torch.randn(n, 3, generator=g, dtype=dtype) * 0.5 - 2.5)
    opac = torch.rand(n, generator=g, dtype=dtype) * 0.9 + 0.05
    colors = torch.rand(n, 3, generator=g, dtype=dtype)
    cam = CAM
    if case == "subpixel":  # 1e-4-sized Gaussians seen at 2.5%: far below a pixel
        scales = torch.full_like(scales, 1e-4)
    elif case == "huge":  # Gaussians far larger than the view
        scales = torch.full_like(scales, math.exp(10.0))
    elif case == "near_plane":  # centres 0.5 to 3 cm in front of the camera, large enough to cross z = 0.01
        means = means * 0.02 + torch.tensor([0.0, -2.98, 0.0], dtype=dtype)
        scales = scales * 4
    elif case == "border":  # a row of Gaussians marching across all four borders
        t = torch.linspace(-2.0, 2.0, n, dtype=dtype)
        means = torch.stack([t, torch.zeros_like(t), t.flip(0) * 0.8], 1)
        scales = scales * 3
    elif case == "inside":  # the camera sits inside the cloud
        cam = Camera.look_at([0.0, 0.0, 0.0], [0, 1.0, 0.1], width=24, height=20, fov_x_deg=90)
        scales = scales * 2
    elif case == "behind":  # every centre behind the camera, some huge enough to reach in front
        means = means * 0.5 + torch.tensor([0.0, -4.0, 0.0], dtype=dtype)
        scales = scales * 20
    elif case == "grazing":  # seen edge-on at 89.99 degrees off the axis (tangent clamp)
        means = torch.tensor([[50.0, -2.999, 0.0]], dtype=dtype).expand(n, 3).clone() + means * 0.01
    else:
        raise ValueError(case)
    return (means, quats, scales, opac, colors), cam


HARD = ["subpixel", "huge", "near_plane", "border", "inside", "behind", "grazing"]


@pytest.mark.parametrize("case", HARD)
def test_geometric_hard_cases_on_every_backend(case, backend):
    (m, q, s, o, c), cam = _hard_scene(case)
    leaves = [t.requires_grad_(True) for t in (m, q, s, o, c)]
    for xi in (0.025, 2.0):
        r = render_gaussians(m, q, s, o, c, cam.scaled(xi), backend=backend)
        _check_image(r)
        (r.image.sum() + r.alpha.sum()).backward()
        _finite_bounded(leaves)
        for t in leaves:
            t.grad = None


@pytest.mark.parametrize("case", HARD)
def test_backends_agree_on_hard_cases(case):
    _backend("cpu")
    (m, q, s, o, c), cam = _hard_scene(case, torch.float64)
    for xi in (0.025, 1.0):
        a = render_gaussians(m, q, s, o, c, cam.scaled(xi), backend="reference")
        b = render_gaussians(m, q, s, o, c, cam.scaled(xi), backend="cpu")
        assert torch.allclose(a.image, b.image, atol=1e-9), float((a.image - b.image).abs().max())


def test_subpixel_is_dimmed_and_huge_is_not_at_the_extreme_resolutions():
    (m, q, s, o, c), cam = _hard_scene("subpixel", torch.float64)
    p = project_gaussians(m, q, s, o, c, cam.scaled(0.025))
    assert p.count == 0 or float(p.gate.max()) < 0.3  # the gate dims (and the 1/255 cull removes) sub-pixel ones
    (m, q, s, o, c), cam = _hard_scene("huge", torch.float64)
    p = project_gaussians(m, q, s, o, c, cam.scaled(2.0))
    assert p.count > 0 and float(p.gate.min()) > 0.999


# ================================================================================== the decoder path


def _scene(m=24, seed=0, log_scale=-2.5, spread=0.5, center=(0.0, 0.0, 0.0), voxel=0.05, K=10, F=32,
           dtype=torch.float32) -> AnchorScene:
    g = torch.Generator().manual_seed(seed)
    c = torch.tensor(center, dtype=torch.float64)
    rel = torch.round((torch.rand(m, 3, generator=g, dtype=torch.float64) - 0.5) * 2 * spread / voxel) * voxel
    return AnchorScene(
        positions=(rel + c).to(dtype),
        features=torch.randn(m, F, generator=g).to(dtype),
        offsets=(torch.randn(m, K, 3, generator=g) * 0.5).to(dtype),
        scalings=torch.full((m, 6), float(log_scale), dtype=dtype),
        voxel_size=voxel,
    ).validate()


def _decoder(seed=0, opacity_bias=1.0, **kw) -> GaussianDecoder:
    torch.manual_seed(seed)
    dec = GaussianDecoder(DecoderConfig(**kw))
    with torch.no_grad():
        dec.mlp_opacity[2].bias.fill_(opacity_bias)
    return dec


SCAM = Camera.look_at([0.0, -2.5, 0.8], [0, 0, 0], width=24, height=24, fov_x_deg=50)


def _render_and_backprop(scene, dec, cam, xi, backend):
    feats = scene.features.detach().clone().requires_grad_(True)
    offs = scene.offsets.detach().clone().requires_grad_(True)
    scal = scene.scalings.detach().clone().requires_grad_(True)
    s = AnchorScene(scene.positions, feats, offs, scal, scene.voxel_size)
    r = render_scene(s, dec, cam, xi, backend=backend)
    _check_image(r)
    dec.zero_grad()
    (r.image.mean() + r.alpha.mean()).backward()
    _finite_bounded([feats, offs, scal])
    _finite_bounded(list(dec.parameters()))
    return r


@pytest.mark.parametrize("log_scale", [-20.0, 10.0])
@pytest.mark.parametrize("xi", [0.025, 2.0])
def test_extreme_log_scales(log_scale, xi, backend):
    scene, dec = _scene(log_scale=log_scale), _decoder()
    r = _render_and_backprop(scene, dec, SCAM, xi, backend)
    if log_scale == 10.0:
        assert r.gaussians.count > 0 and float(r.alpha.detach().min()) > 0.5  # e^10-sized Gaussians cover the view


@pytest.mark.parametrize("saturation", [1e4, -1e4])
def test_saturated_mlp_outputs(saturation, backend):
    """Opacity/colour/scale logits of +-1e4: tanh and sigmoid saturate; scales of exactly 0 stay finite."""
    scene, dec = _scene(), _decoder(opacity_bias=0.0)
    with torch.no_grad():
        for mlp in (dec.mlp_opacity, dec.mlp_cov, dec.mlp_color):
            mlp[2].weight.zero_()
            mlp[2].bias.fill_(saturation)
        dec.mlp_opacity[2].bias.fill_(1e4)  # opacity tanh(1e4) = 1: every Gaussian alive
    for xi in (0.025, 1.0):
        r = _render_and_backprop(scene, dec, SCAM, xi, backend)
        assert r.gaussians.count == scene.num_anchors * 10


def test_zero_and_tiny_quaternions_from_the_decoder(backend):
    scene, dec = _scene(), _decoder()
    with torch.no_grad():
        w, b = dec.mlp_cov[2].weight.view(10, 7, -1), dec.mlp_cov[2].bias.view(10, 7)
        w[:5, 3:].zero_()
        b[:5, 3:].zero_()  # slots 0-4: exactly zero quaternions
        w[5:, 3:].mul_(1e-30)
        b[5:, 3:].fill_(1e-30)  # slots 5-9: norms around 1e-30
    r = _render_and_backprop(scene, dec, SCAM, 1.0, backend)
    assert r.gaussians.count > 0


def test_scene_seen_from_inside(backend):
    scene, dec = _scene(m=60, spread=1.0), _decoder()
    cam = Camera.look_at([0.0, 0.0, 0.0], [0.3, 1.0, 0.2], width=24, height=24, fov_x_deg=100)
    for xi in (0.025, 1.0, 2.0):
        _render_and_backprop(scene, dec, cam, xi, backend)


def test_far_from_the_origin_renders_like_near_the_origin(backend):
    """Coordinates of 1e5: the decoder outputs camera-relative means, so float32 loses nothing beyond its inputs.

    Anchors at 1e5 + k / 16 are exact in float32 (ulp 2^-7 there), so the far scene and its copy at the origin
    are the same scene; their renders from correspondingly shifted cameras must agree.
    """
    off = np.array([1e5, -1e5, 5e4])
    near = _scene(voxel=1 / 16, spread=0.5)
    far = AnchorScene(near.positions + torch.tensor(off, dtype=torch.float32), near.features, near.offsets,
                      near.scalings, near.voxel_size)
    assert torch.equal((far.positions.double() - torch.tensor(off)).float(), near.positions)
    dn = _decoder(embedding="none")
    df = _decoder(embedding="none")
    eye = np.array([0.25, -2.5, 0.75])  # multiples of 2^-7: the far camera centre is exact in float32 too
    cn = Camera.look_at(eye, [0, 0, 0], width=24, height=24, fov_x_deg=50)
    cf = Camera.look_at(eye + off, off, width=24, height=24, fov_x_deg=50)
    with torch.no_grad():
        a = render_scene(near, dn, cn, 1.0, backend=backend)
        b = render_scene(far, df, cf, 1.0, backend=backend)
    _check_image(b)
    assert a.gaussians.count == b.gaussians.count > 0
    assert float((a.image - b.image).abs().max()) < 2e-3
    # FiLM on: positions are normalised by the scene centre, which must follow the scene.
    dfilm = _decoder(embedding="film", scene_center=tuple(off), scene_radius=1.0)
    with torch.no_grad():
        dfilm.mlp_embed[2].weight.normal_(0, 0.1)
    _render_and_backprop(far, dfilm, cf, 0.5, backend)


def test_tiny_voxels(backend):
    """Voxels of 1e-4: a 2.4 mm scene seen from 2 cm (the near plane is 1 cm)."""
    scene = _scene(voxel=1e-4, spread=1.2e-3, log_scale=math.log(1e-4))
    dec = _decoder()
    cam = Camera.look_at([0.0, -0.02, 0.005], [0, 0, 0], width=24, height=24, fov_x_deg=20)
    for xi in (0.025, 1.0, 2.0):
        r = _render_and_backprop(scene, dec, cam, xi, backend)
    assert float(r.alpha.detach().max()) > 0.1  # the scene is actually seen


# ================================================================================== codec: positions at the extremes


def _codec():
    from proxycodec import codec  # an import error fails these tests: the codec is part of the product

    return codec


@pytest.mark.parametrize("where", ["far_1e5", "voxel_1e-4", "far_1e5_voxel_1e-4", "off_grid"])
def test_codec_position_round_trip_at_the_extremes(where, tmp_path):
    codec = _codec()
    if where == "far_1e5":
        scene = _scene(m=40, voxel=1 / 16, center=(1e5, -1e5, 5e4))
    elif where == "voxel_1e-4":
        scene = _scene(m=40, voxel=1e-4, spread=2e-3)
    elif where == "far_1e5_voxel_1e-4":
        # float32 cannot hold 1e-4 steps at 1e5 (ulp 2^-7): the grid collapses to float32's own; still exact.
        scene = _scene(m=40, voxel=1e-4, spread=2e-3, center=(1e5, 2.5e4, -3e4))
    else:
        s = _scene(m=40)
        g = torch.Generator().manual_seed(5)
        scene = AnchorScene(s.positions + torch.rand(40, 3, generator=g) * 1e-3, s.features, s.offsets, s.scalings,
                            s.voxel_size)
    model = SceneModel(scene, _decoder(scene_center=tuple(scene.positions.double().mean(0).tolist())).eval())
    rep = codec.encode(model, tmp_path / "x.pxc", distill=False, predictor_iters=3, zstd_level=3)
    back = codec.decode(tmp_path / "x.pxc")
    # Positions are stored exactly (grid indices or float32), in the codec's spatial order: compare as sets.
    key = lambda p: np.lexsort(p.numpy().T)
    a, b = scene.positions, back.scene.positions
    assert torch.equal(a[key(a)], b[key(b)])
    assert torch.isfinite(back.scene.features).all()
    assert torch.equal(back.scene.positions, rep.model.scene.positions)


# ================================================================================== a short optimisation with outliers


def _outlier_scene() -> AnchorScene:
    s = _scene(m=16, seed=3, spread=0.4)
    pos, scal, offs = s.positions.clone(), s.scalings.clone(), s.offsets.clone()
    scal[0] = -20.0  # vanishing
    scal[1, 3:] = 10.0  # enormous Gaussians
    scal[2, :3] = 10.0  # offsets thrown 1e4 away
    pos[3] = torch.tensor([1e5, 1e5, 1e5])  # far outlier
    pos[4] = torch.tensor([0.0, -2.495, 0.8])  # 5 mm from the camera (straddles the near plane)
    offs[5] = 0.0  # all ten Gaussians at the anchor
    return AnchorScene(pos, s.features, offs, scal, s.voxel_size).validate()


@pytest.mark.parametrize("backend_name", ALL_BACKENDS)
def test_training_with_outliers_stays_finite(backend_name):
    backend = _backend(backend_name)
    iters = 200 if backend == "cpu" else 120
    torch.manual_seed(0)
    target_scene = _outlier_scene()
    dec = _decoder(seed=1, opacity_bias=0.5)
    with torch.no_grad():  # a saturating opacity head on one slot and zero quaternions on another
        dec.mlp_opacity[2].bias[0] = 1e4
        dec.mlp_cov[2].bias.view(10, 7)[1, 3:] = 0.0
        dec.mlp_cov[2].weight.view(10, 7, -1)[1, 3:] = 0.0
        g = torch.Generator().manual_seed(2)
        pert = AnchorScene(target_scene.positions, target_scene.features + 0.3 * torch.randn(
            target_scene.features.shape, generator=g), target_scene.offsets, target_scene.scalings, 0.05)
        targets = {xi: render_scene(pert, dec, SCAM, xi, backend=backend).image for xi in (0.5, 1.0)}
    feats = target_scene.features.clone().requires_grad_(True)
    offs = target_scene.offsets.clone().requires_grad_(True)
    scal = target_scene.scalings.clone().requires_grad_(True)
    opt = torch.optim.Adam([{"params": [feats, offs, scal], "lr": 1e-2},
                            {"params": list(dec.parameters()), "lr": 1e-3}])
    losses = []
    for it in range(iters):
        xi = 0.5 if it % 2 else 1.0
        s = AnchorScene(target_scene.positions, feats, offs, scal, 0.05)
        r = render_scene(s, dec, SCAM, xi, backend=backend)
        loss = (r.image - targets[xi]).abs().mean()
        opt.zero_grad()
        loss.backward()
        for p in [feats, offs, scal, *dec.parameters()]:
            if p.grad is not None:
                assert torch.isfinite(p.grad).all(), f"non-finite gradient at iteration {it}"
        opt.step()
        losses.append(float(loss.detach()))
        assert math.isfinite(losses[-1])
    for p in [feats, offs, scal, *dec.parameters()]:
        assert torch.isfinite(p).all()
    assert min(losses[-10:]) < losses[0]  # it actually optimises
