"""The fused numba projection (``render/project_cpu.py``) against the torch reference (``render/project.py``).

Same culling (identical ``index``), same outputs, same gradients. Tolerances: the fast path computes each forward
value with the reference's operations in the input dtype, so the outputs differ from the reference's only by the
last-ulp differences of sqrt/exp/log (torch's MKL/SLEEF vs numba's libm), amplified where the 2x2 inverse is
ill-conditioned: conics are compared relative to ``cond = a_d c_d / det`` of their row. Gradients are a float64
chain rule at the forward values; in float32 they are compared norm-wise (the float32 reference is itself only
float32-accurate: both are also compared against the float64 reference).

Culling: the two make the same decisions from the same values, except that a value computed through a
transcendental function (the gated opacity through exp, the footprint through log) may differ in its last ulp (numba's
libm vs torch's SLEEF, whose kernel depends on the machine's ISA), so a row within that of a threshold may be kept by
one and culled by the other (issue #14). Such rows are accepted (``flips.match_rows``: at most two, each within
``cull_rtol`` of its threshold) and left out of the comparison; every other row must be kept by both.
"""

from __future__ import annotations

import math

import flips
import numpy as np
import pytest
import torch

from proxycodec.camera import Camera
from proxycodec.render import GateConfig, project
from proxycodec.render.project import project_gaussians
from proxycodec.render.project_cpu import project_gaussians_cpu

OUTPUTS = ("means2d", "conics", "opacities", "colors", "depths")
PARAMS = ("means", "quats", "scales", "opacities", "colors")
F64_OUT = 1e-12
F64_GRAD = 1e-10


# ---------------------------------------------------------------------------------------------------- helpers
def camera(width=96, height=80, dist=3.0, fov=50.0):
    return Camera.look_at([dist, 0.4 * dist, 0.3 * dist], [0.0, 0.0, 0.0], fov_x_deg=fov, width=width, height=height)


def scene(n, seed=0, dtype=torch.float64, log_scale=math.log(0.02), spread=0.7, radius=1.0, center=(0.0, 0.0, 0.0),
          channels=3):
    g = torch.Generator().manual_seed(seed)
    means = torch.tensor(center, dtype=torch.float64) + radius * torch.randn(n, 3, generator=g, dtype=torch.float64)
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    scales = torch.exp(log_scale + spread * torch.randn(n, 3, generator=g, dtype=torch.float64))
    op = torch.sigmoid(2 * torch.randn(n, generator=g, dtype=torch.float64))
    colors = torch.rand(n, channels, generator=g, dtype=torch.float64)
    return [t.to(dtype) for t in (means, quats, scales, op, colors)]


def run(fn, params, cam, seed=1, skip=None, **kw):
    """Project, then backprop a random linear loss of every differentiable output -> (Projected, grads). The loss
    weights belong to the input rows (the same whichever rows survive culling); rows in ``skip`` get none."""
    leaves = [t.detach().clone().requires_grad_(True) for t in params]
    proj = fn(*leaves, cam, **kw)
    g = torch.Generator().manual_seed(seed)
    n = params[0].shape[0]
    loss = 0.0
    for name in OUTPUTS:
        x = getattr(proj, name)
        w = torch.rand((n,) + tuple(x.shape[1:]), generator=g, dtype=torch.float64) - 0.4
        if skip is not None:
            w[torch.as_tensor(skip, dtype=torch.long)] = 0.0
        loss = loss + (x * w[proj.index].to(x.dtype)).sum()
    if proj.count:
        loss.backward()
    return proj, [t.grad if t.grad is not None else torch.zeros_like(t) for t in leaves]


def cull_rtol(*projs):
    """How close to a threshold a value must lie for its cull to be allowed to differ: a few float32 ulps when either
    side is float32 (float32 vs float64 included), else a few float64 ulps."""
    return 1e-5 if any(p.means2d.dtype == torch.float32 for p in projs) else 1e-12


def matched(p, r):
    """(rows of p, rows of r) of the Gaussians both kept; the others must be flips within ``cull_rtol``."""
    return flips.match_rows(p.index.numpy(), r.index.numpy(), flips.cull_margins(p), flips.cull_margins(r),
                            cull_rtol(p, r), 2, "culling decisions")


def run_all(cases, cam, **kw):
    """``cases``: [(fn, params)] -> [(Projected, grads)] with one random loss; Gaussians whose cull differs between
    the first case and another (near a threshold, see ``matched``) are left out of every loss."""
    outs = [run(fn, ps, cam, **kw) for fn, ps in cases]
    for o in outs[1:]:
        matched(outs[0][0], o[0])
    flipped = np.unique(np.concatenate([np.setxor1d(outs[0][0].index.numpy(), o[0].index.numpy())
                                        for o in outs[1:]]))
    if flipped.size:
        outs = [run(fn, ps, cam, skip=flipped, **kw) for fn, ps in cases]
    return outs


def conic_cond(conics):
    """a_d c_d / det of the dilated covariance, from its inverse (ca cc - cb^2 = 1/det, ca cc = a_d c_d / det^2)."""
    c = conics.detach().double()
    ac = c[:, 0] * c[:, 2]
    return ac / (ac - c[:, 1] ** 2)


def assert_outputs_match(p, r, rtol, px_tol=0.0):
    assert p.width == r.width and p.height == r.height
    pi, ri = (torch.from_numpy(i) for i in matched(p, r))
    for name in ("means2d", "conics", "opacities", "colors", "depths", "extent", "gate"):
        x, y = getattr(p, name), getattr(r, name)
        assert x.dtype == y.dtype and x.shape[1:] == y.shape[1:], name
        assert torch.isfinite(x).all(), name
    p, r = _rows(p, pi), _rows(r, ri)

    def d(a, b):
        return (a.detach().double() - b.detach().double()).abs()

    m = r.means2d.detach().double()
    assert (d(p.means2d, r.means2d) <= px_tol + rtol * m.abs()).all()
    for name in ("opacities", "depths", "gate", "colors"):
        y = getattr(r, name).detach().double()
        assert (d(getattr(p, name), y) <= rtol * y.abs() + 1e-300).all(), name
    # extent = sqrt(m2 a_d), m2 = 2 ln(255 op): as op -> 1/255, m2 -> 0 and a last-ulp difference of op (or of log)
    # is a large relative one of m2. extent^2 = m2 a_d differs by about a_d d(m2) = 2 a_d d(op)/op.
    c = r.conics.detach().double()
    a_d = c[:, 2] / (c[:, 0] * c[:, 2] - c[:, 1] ** 2)
    e2 = r.extent.detach().double() ** 2
    assert (d(p.extent.double() ** 2, e2) <= rtol * (e2 + 2 * a_d[:, None])).all(), "extent"
    scale = r.conics.detach().double().abs().amax(1, keepdim=True) * conic_cond(r.conics)[:, None]
    assert (d(p.conics, r.conics) <= rtol * scale).all(), "conics"


def _rows(p, i):
    """``p`` (a Projected) restricted to its rows ``i``."""
    from dataclasses import replace

    return replace(p, **{k: getattr(p, k)[i] for k in ("means2d", "conics", "opacities", "colors", "depths", "extent",
                                                         "index", "gate")})


def assert_grads_match(ga, gr, rtol, elementwise=False):
    for name, x, y in zip(PARAMS, ga, gr):
        assert x.shape == y.shape and x.dtype == y.dtype, name
        assert torch.isfinite(x).all(), name
        x, y = x.double(), y.double()
        err, ref = (x - y).norm().item(), y.norm().item()
        assert err <= rtol * max(ref, 1e-300), f"{name}: |diff| {err:.3e} vs |ref| {ref:.3e}"
        if elementwise:
            tol = rtol * (y.abs() + 1e-6 * y.abs().max())
            assert ((x - y).abs() <= tol).all(), f"{name}: elementwise"


def compare(params, cam, out_rtol=F64_OUT, grad_rtol=F64_GRAD, px_tol=0.0, elementwise=False, **kw):
    (p, ga), (r, gr) = run_all([(project_gaussians_cpu, params), (project_gaussians, params)], cam, **kw)
    assert_outputs_match(p, r, out_rtol, px_tol)
    assert_grads_match(ga, gr, grad_rtol, elementwise)
    return p, r


# ---------------------------------------------------------------------------------------------------- tests
class TestAgainstReference:
    @pytest.mark.parametrize("seed", [0, 1, 2])
    def test_random_scene_float64(self, seed):
        params = scene(3000, seed=seed, channels=1 + seed)
        p, _ = compare(params, camera(), elementwise=True)
        assert 1000 < p.count < 3000  # culls something, keeps most

    def test_gradcheck_float64(self):
        cam = camera(40, 32)
        means, quats, scales, op, colors = scene(8, seed=3, log_scale=math.log(0.05), spread=0.3, radius=0.3)
        op = 0.3 + 0.5 * op
        assert project_gaussians(means, quats, scales, op, colors, cam).count == 8  # away from every cull

        def f(m, q, s, o, c):
            p = project_gaussians_cpu(m, q, s, o, c, cam)
            return p.means2d, p.conics, p.opacities, p.colors, p.depths

        leaves = [t.clone().requires_grad_(True) for t in (means, quats, scales, op, colors)]
        assert torch.autograd.gradcheck(f, leaves, eps=1e-6, atol=1e-6, rtol=1e-5)

    def test_float32_10k(self):
        cam = camera()
        params64 = scene(10_000, seed=5, log_scale=math.log(0.01))
        params = [t.float() for t in params64]
        # the float64 reference on the same (float32-representable) inputs: both float32 paths are compared to it
        (p, ga), (r, gr), (r64, g64) = run_all([(project_gaussians_cpu, params), (project_gaussians, params),
                                                (project_gaussians, [t.double() for t in params])], cam)
        assert p.count > 5_000
        assert_outputs_match(p, r, 1e-5, px_tol=1e-4)
        assert_grads_match(ga, gr, 1e-3)
        for name, x, y, z in zip(PARAMS, ga, gr, g64):
            e_fast = (x.double() - z).norm().item()
            e_ref = (y.double() - z).norm().item()
            assert e_fast <= 2 * e_ref + 1e-7 * z.norm().item(), name

    def test_float32_values_follow_the_reference_ops(self):
        """Positions, depths and 2D means are the reference's float32 values bit for bit (same ops, same order)."""
        cam = camera()
        params = scene(2000, seed=6, dtype=torch.float32)
        p = project_gaussians_cpu(*params, cam)
        r = project_gaussians(*params, cam)
        pi, ri = matched(p, r)
        assert len(pi) > 1000
        assert torch.equal(p.means2d[pi], r.means2d[ri]) and torch.equal(p.depths[pi], r.depths[ri])

    @pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
    def test_gate_disabled(self, dtype):
        cam = camera()
        params = scene(2000, seed=7, dtype=dtype, log_scale=math.log(0.003))
        kw = {"gate": GateConfig(enabled=False)}
        if dtype == torch.float64:
            p, _ = compare(params, cam, elementwise=True, **kw)
        else:
            (p, ga), (r, gr) = run_all([(project_gaussians_cpu, params), (project_gaussians, params)], cam, **kw)
            assert_outputs_match(p, r, 1e-5, 1e-4)
            assert_grads_match(ga, gr, 1e-3)
        assert torch.all(p.gate == 1)
        on = project_gaussians_cpu(*params, cam)
        assert on.gate.min() < 0.5  # the scene has sub-pixel Gaussians the gate dims

    @pytest.mark.parametrize("gate_on", [True, False])
    def test_antialiased(self, gate_on):
        """gsplat's antialiased mode (the opacity times sqrt(det_u / det)), with and without the gate: float64
        elementwise, float32 norm-wise, and the sub-pixel Gaussians it dims."""
        cam = camera()
        gate = GateConfig(enabled=gate_on, antialiased=True)
        params = scene(2000, seed=9, log_scale=math.log(0.004))
        p, _ = compare(params, cam, elementwise=True, gate=gate)
        plain = project_gaussians_cpu(*params, cam, gate=GateConfig(enabled=gate_on))
        common, ip, ia = np.intersect1d(plain.index.numpy(), p.index.numpy(), return_indices=True)
        assert len(common) > 500
        ratio = p.opacities[ia] / plain.opacities[ip]
        assert torch.allclose(p.gate[ia], plain.gate[ip] * ratio) and ratio.max() <= 1 and ratio.min() < 0.3
        params32 = [t.float() for t in params]
        (p, ga), (r, gr) = run_all([(project_gaussians_cpu, params32), (project_gaussians, params32)], cam, gate=gate)
        assert_outputs_match(p, r, 1e-5, 1e-4)
        assert_grads_match(ga, gr, 1e-3)

    def test_gradcheck_float64_antialiased(self):
        cam = camera(40, 32)
        gate = GateConfig(antialiased=True)
        means, quats, scales, op, colors = scene(8, seed=3, log_scale=math.log(0.05), spread=0.3, radius=0.3)
        op = 0.3 + 0.5 * op
        assert project_gaussians(means, quats, scales, op, colors, cam, gate=gate).count == 8

        def f(m, q, s, o, c):
            p = project_gaussians_cpu(m, q, s, o, c, cam, gate=gate)
            return p.means2d, p.conics, p.opacities, p.colors, p.depths

        leaves = [t.clone().requires_grad_(True) for t in (means, quats, scales, op, colors)]
        assert torch.autograd.gradcheck(f, leaves, eps=1e-6, atol=1e-6, rtol=1e-5)

    def test_other_gate_parameters(self):
        compare(scene(1500, seed=8, log_scale=math.log(0.005)), camera(), gate=GateConfig(True, 9.0, 1.5))

    def test_empty_input(self):
        for dtype in (torch.float64, torch.float32):
            params = [t[:0] for t in scene(4, dtype=dtype)]
            p, ga = run(project_gaussians_cpu, params, camera())
            r = project_gaussians(*params, camera())
            assert p.count == 0 and p.index.dtype == torch.long and p.colors.shape == (0, 3)
            assert p.means2d.dtype == dtype and p.extent.shape == (0, 2)
            assert_outputs_match(p, r, 0.0)
            assert all(g.shape == t.shape for g, t in zip(ga, params))

    def test_everything_culled_still_differentiable(self):
        params = scene(50, seed=9, center=(15.0, 6.0, 4.5), radius=0.1)  # behind the camera
        leaves = [t.clone().requires_grad_(True) for t in params]
        p = project_gaussians_cpu(*leaves, camera())
        assert p.count == 0
        (p.means2d.sum() + p.conics.sum() + p.opacities.sum() + p.colors.sum()).backward()
        assert all(t.grad is None or torch.all(t.grad == 0) for t in leaves)


class TestHardCases:
    def test_near_singular_covariances(self):
        """Needles, discs edge-on, points: det Sigma2D cancels, so last-ulp differences (sqrt in the quaternion norm)
        are amplified by the conditioning in both implementations. float64: agreement to 1e-7; float32 (where the
        reference itself is off by up to tens of percent in some gradients): no worse than the float32 reference,
        both measured against the float64 one."""
        n = 400
        g = torch.Generator().manual_seed(11)
        means = 0.5 * torch.randn(n, 3, generator=g, dtype=torch.float64)
        quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
        scales = torch.full((n, 3), 1e-6, dtype=torch.float64)
        scales[: n // 4, 0] = 1.0  # needles
        scales[n // 4: n // 2, :2] = 0.8  # flat discs, many nearly edge-on
        scales[n // 2: 3 * n // 4] = 0.0  # points: zero covariance, only the dilation
        scales[3 * n // 4:, 0] = 1e-12  # degenerate in one axis, tiny in all
        op = torch.full((n,), 0.9, dtype=torch.float64)
        colors = torch.rand(n, 3, generator=g, dtype=torch.float64)
        params = [means, quats, scales, op, colors]
        cam = camera(64, 48)
        p, r = compare(params, cam, out_rtol=1e-7, grad_rtol=1e-7)
        assert p.count > n // 2 and conic_cond(r.conics).max() > 100  # really near-singular
        assert (r.gate < 0.3).sum() > 10  # zero-area Gaussians at the gate's floor
        params32 = [t.float() for t in params]
        (r, g64), (p32, g32), (r32, gr32) = run_all([(project_gaussians, params), (project_gaussians_cpu, params32),
                                                     (project_gaussians, params32)], cam)
        matched(p32, r32)
        # the rows all three kept (the others: flips near a threshold, see ``matched``)
        keep = np.intersect1d(np.intersect1d(r.index.numpy(), p32.index.numpy()), r32.index.numpy())
        assert len(keep) > n // 2
        r, p32, r32 = (_rows(x, torch.from_numpy(np.searchsorted(x.index.numpy(), keep))) for x in (r, p32, r32))
        for name in OUTPUTS + ("extent", "gate"):
            z = getattr(r, name).detach()
            e_fast = (getattr(p32, name).detach().double() - z).norm().item()
            e_ref = (getattr(r32, name).detach().double() - z).norm().item()
            assert e_fast <= 2 * e_ref + 1e-6 * z.norm().item(), name
        for name, x, y, z in zip(PARAMS, g32, gr32, g64):
            e_fast = (x.double() - z).norm().item()
            e_ref = (y.double() - z).norm().item()
            assert e_fast <= 2 * e_ref + 1e-6 * z.norm().item(), name

    def test_huge_needles_float32_engage_the_det_floor(self):
        """Needles thousands of pixels long, seen from close by: in float32 the rounding of a_d c_d - b^2 exceeds
        0.3 (a + c), so ``det.clamp_min(0.09)`` engages (and the gate's ``clamp_min(0)`` on a negative det). The
        values there are float32 noise in both implementations; what must hold is the same culling and finite
        outputs and gradients."""
        import proxycodec.render.project_cpu as pc

        n = 2000
        g = torch.Generator().manual_seed(23)
        cam = camera(64, 48, dist=1.0)
        means = 0.05 * torch.randn(n, 3, generator=g)
        quats = torch.randn(n, 4, generator=g)
        scales = torch.full((n, 3), 1e-4)
        scales[:, 0] = torch.exp(2.0 + 2.0 * torch.randn(n, generator=g))
        params = [means, quats, scales, torch.full((n,), 0.9), torch.rand(n, 3, generator=g)]
        (p, ga), (r, _) = run_all([(project_gaussians_cpu, params), (project_gaussians, params)], cam)
        assert all(torch.isfinite(x).all() for x in ga)
        k = pc._constants(cam, GateConfig(), 0.01, 1e10, None, np.float32)
        from proxycodec.render import _project_kernels as pk

        w = np.zeros(pk.NW, np.float32)
        floored = negative = 0
        for i in range(n):
            pk.forward_one.py_func(*(t.numpy() for t in params[:4]), i, k, True, w)
            floored += bool(w[pk.W_DRAW] < k[pk.K_DD])
            negative += bool(w[pk.W_DETU] < 0)
        assert floored > 20 and negative > 100

    def test_zero_and_tiny_quaternions(self):
        params = scene(300, seed=12)
        params[1][:100] = 0.0
        params[1][100:150] = 1e-30
        params[1][150:200] *= 1e-4  # comparable to the smoothing epsilon
        p, _ = compare(params, camera(), elementwise=True)
        assert (p.index < 150).sum() > 50

    @pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
    def test_near_plane_and_image_borders(self, dtype):
        cam = camera(50, 40, dist=1.0)
        g = torch.Generator().manual_seed(13)
        n = 600
        R = torch.as_tensor(cam.rotation)
        t = torch.as_tensor(cam.translation)
        # depths across the near plane (behind, straddling, just in front) and far; directions up to 3x the FOV
        z = torch.cat([torch.rand(200, generator=g, dtype=torch.float64) * 0.06 - 0.02,
                       torch.rand(n - 200, generator=g, dtype=torch.float64) * 2 + 0.05])
        u = (torch.rand(n, generator=g, dtype=torch.float64) * 2 - 1) * 3.0
        v = (torch.rand(n, generator=g, dtype=torch.float64) * 2 - 1) * 3.0
        p_cam = torch.stack([u * z.abs() * cam.cx / cam.fx, v * z.abs() * cam.cy / cam.fy, z], -1)
        means = (p_cam - t) @ R  # camera -> world
        quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
        scales = torch.exp(math.log(0.03) + 0.8 * torch.randn(n, 3, generator=g, dtype=torch.float64))
        op = torch.sigmoid(2 * torch.randn(n, generator=g, dtype=torch.float64))
        colors = torch.rand(n, 3, generator=g, dtype=torch.float64)
        params = [x.to(dtype) for x in (means, quats, scales, op, colors)]
        if dtype == torch.float64:
            p, r = compare(params, cam, elementwise=True)
        else:
            (p, ga), (r, gr) = run_all([(project_gaussians_cpu, params), (project_gaussians, params)], cam)
            assert_outputs_match(p, r, 1e-5, 1e-4)
            assert_grads_match(ga, gr, 1e-3)
        # the cases are really there: near-plane survivors, footprints across the border, clamped tangents
        lo, hi = r.means2d - r.extent, r.means2d + r.extent
        straddle = (lo[:, 0] < 0) | (hi[:, 0] > cam.width) | (lo[:, 1] < 0) | (hi[:, 1] > cam.height)
        assert straddle.sum() > 20 and (r.depths < 0.03).sum() > 5
        tx = r.means2d[:, 0].double() - cam.cx
        lim = (cam.width - cam.cx) + 0.3 * 0.5 * cam.width
        assert (tx.abs() > lim).sum() > 5  # centres beyond the 1.3x clamp that still reach the image
        assert (z <= 0.01).sum() > 50 and not np.isin(p.index.numpy(), np.flatnonzero(z.numpy() <= 0.01)).any()

    @pytest.mark.parametrize("xi", [0.025, 2.0])
    def test_extreme_resolution_ratios(self, xi):
        cam = camera(400, 320).scaled(xi)
        params = scene(3000, seed=14, log_scale=math.log(0.005))
        p, _ = compare(params, cam, elementwise=True)
        assert p.count > 100
        params32 = [t.float() for t in params]
        (p32, g32), (r32, gr32) = run_all([(project_gaussians_cpu, params32), (project_gaussians, params32)], cam)
        assert_outputs_match(p32, r32, 1e-5, 1e-4)
        assert_grads_match(g32, gr32, 1e-3)

    def test_origin_given_vs_not(self):
        cam = camera()
        params = scene(1500, seed=15)
        origin = torch.tensor([0.3, -0.2, 0.1], dtype=torch.float64)
        rel = [params[0] - origin] + params[1:]
        p, _ = compare(rel, cam, origin=origin, elementwise=True)
        q = project_gaussians_cpu(*params, cam)
        assert torch.equal(p.index, q.index)
        assert (p.means2d - q.means2d).abs().max() < 1e-9

    def test_large_coordinates_float32(self):
        """Scene at 1e5 units, camera 3 units away: relative to an origin, float32 keeps full precision."""
        center = np.array([1e5, -2e5, 5e4])
        world = Camera.look_at(center + np.array([3.0, 1.2, 0.9]), center, width=96, height=80)
        params = scene(4000, seed=16, dtype=torch.float64)
        rel32 = [t.float() for t in params]
        (p, ga), (r, gr) = run_all([(project_gaussians_cpu, rel32), (project_gaussians, rel32)], world, origin=center)
        assert p.count > 2000
        assert_outputs_match(p, r, 1e-5, 1e-4)
        assert_grads_match(ga, gr, 1e-3)
        # absolute float32 coordinates (what the origin avoids): the same decisions as the reference's float32
        abs32 = [(params[0] + torch.as_tensor(center)).float()] + rel32[1:]
        pa = project_gaussians_cpu(*abs32, world)
        ra = project_gaussians(*abs32, world)
        pi, ri = matched(pa, ra)
        assert torch.equal(pa.means2d[pi], ra.means2d[ri])

    def test_non_finite_inputs_are_culled_like_the_reference(self):
        """Same culls. Gradients: culled Gaussians get exactly zero; the reference differs here in one way: a
        Gaussian with a non-finite quaternion or scale passes its depth cull, so autograd multiplies its zero
        upstream gradient by inf/NaN (0 * NaN) and hands NaN to its position (and scale) gradient."""
        params = scene(200, seed=17)
        params[0][0, 1] = float("nan")
        params[0][1, 2] = float("inf")
        params[1][2] = float("nan")
        params[2][3, 0] = float("inf")
        params[2][4, 1] = float("nan")
        params[3][5] = float("nan")
        params[2][6] = 1e200  # overflows to inf in the covariance
        p, ga = run(project_gaussians_cpu, params, camera())
        r, gr = run(project_gaussians, params, camera())
        assert_outputs_match(p, r, F64_OUT)
        assert not np.isin(p.index.numpy(), np.arange(7)).any()
        for x, y in zip(ga, gr):
            assert torch.isfinite(x).all() and torch.all(x[:7] == 0)
            assert (x[7:] - y[7:]).norm() <= F64_GRAD * y[7:].norm()
        assert not torch.isfinite(gr[0][:7]).all()  # the reference's NaN leak, see the docstring

    def test_non_contiguous_and_partial_requires_grad(self):
        cam = camera()
        params = scene(500, seed=18)
        wide = [torch.cat([t, t], 1)[:, : t.shape[1]] if t.dim() == 2 else t[::1] for t in params]
        assert not wide[0].is_contiguous()
        p = project_gaussians_cpu(*wide, cam)
        r = project_gaussians(*params, cam)
        assert_outputs_match(p, r, F64_OUT)
        means = params[0].clone().requires_grad_(True)
        p = project_gaussians_cpu(means, *params[1:], cam)
        p.means2d.sum().backward()
        means_r = params[0].clone().requires_grad_(True)
        project_gaussians(means_r, *params[1:], cam).means2d.sum().backward()
        assert (means.grad - means_r.grad).norm() <= F64_GRAD * means_r.grad.norm()

    def test_parallel_and_serial_paths_agree(self):
        """Above the small-work threshold the kernels run on the thread pool: same results, deterministic."""
        import proxycodec.render.project_cpu as pc

        params = scene(pc._SMALL_WORK + 1000, seed=19, dtype=torch.float32)
        cam = camera()
        a, ga = run(project_gaussians_cpu, params, cam)
        old = pc._SMALL_WORK
        pc._SMALL_WORK = 10**9
        try:
            b, gb = run(project_gaussians_cpu, params, cam)
        finally:
            pc._SMALL_WORK = old
        assert torch.equal(a.index, b.index) and torch.equal(a.conics, b.conics)
        assert all(torch.equal(x, y) for x, y in zip(ga, gb))


class TestDispatch:
    def test_project_picks_the_fused_path_on_cpu(self):
        params = [t.requires_grad_(True) for t in scene(100, seed=20)]
        cam = camera()
        fast = project(*params, cam, backend="cpu")
        auto = project(*params, cam)
        ref = project(*params, cam, backend="reference")
        assert "ProjectCPU" in type(fast.means2d.grad_fn).__name__
        assert "ProjectCPU" in type(auto.means2d.grad_fn).__name__
        assert "ProjectCPU" not in type(ref.means2d.grad_fn).__name__
        assert torch.equal(fast.index, ref.index)

    def test_unsupported_inputs_fall_back_to_the_reference(self):
        params = scene(100, seed=21)
        params[1] = params[1].float()  # mixed dtypes: the reference's promotion rules apply
        p = project_gaussians_cpu(*params, camera())
        r = project_gaussians(*params, camera())
        assert torch.equal(p.index, r.index) and torch.equal(p.conics, r.conics)

