"""The numba CPU compositor against the reference oracle: images, alpha and gradients (issue #3)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import flips
import numpy as np
import pytest
import torch

from proxycodec.camera import Camera
from proxycodec.render import available_backends, project_gaussians, rasterize, render_gaussians
from proxycodec.render import cpu as cpu_backend
from proxycodec.render.cpu import rasterize_cpu
from proxycodec.render.reference import rasterize_reference

IMG_TOL = 1e-4
GRAD_TOL = 1e-3
LOG_001 = math.log(0.01)
LOG_002 = math.log(0.02)
GRAD_NAMES = ("means2d", "conics", "opacities", "colors", "background")


# ---------------------------------------------------------------------------------------------------- helpers
def random_2d(n, width, height, channels=3, dtype=torch.float64, seed=0, max_sigma=3.0, opacity=(0.05, 0.95),
              margin=0.15):
    """A random 2D interface (means2d, conics, opacities, colors, depths, extent) + background, as project makes."""
    g = torch.Generator().manual_seed(seed)
    wh = torch.tensor([width, height], dtype=torch.float64)
    means = (torch.rand(n, 2, generator=g, dtype=torch.float64) * (1 + 2 * margin) - margin) * wh
    L = torch.randn(n, 2, 2, generator=g, dtype=torch.float64) * max_sigma
    cov = L @ L.transpose(1, 2) + 0.3 * torch.eye(2, dtype=torch.float64)
    det = cov[:, 0, 0] * cov[:, 1, 1] - cov[:, 0, 1] ** 2
    conics = torch.stack([cov[:, 1, 1] / det, -cov[:, 0, 1] / det, cov[:, 0, 0] / det], -1)
    lo, hi = opacity
    op = lo + (hi - lo) * torch.rand(n, generator=g, dtype=torch.float64)
    colors = torch.rand(n, channels, generator=g, dtype=torch.float64)
    depths = torch.rand(n, generator=g, dtype=torch.float64) + 0.5
    m2 = 2 * torch.log((op * 255).clamp_min(1))
    extent = torch.stack([torch.sqrt(m2 * cov[:, 0, 0]), torch.sqrt(m2 * cov[:, 1, 1])], -1)
    bg = torch.rand(channels, generator=g, dtype=torch.float64)
    return [t.to(dtype) for t in (means, conics, op, colors, depths, extent, bg)]


def random_3d(n, seed=0, dtype=torch.float64, log_scale=LOG_002, spread=0.5, center=(0.0, 0.0, 0.0),
              radius=0.7, channels=3):
    g = torch.Generator().manual_seed(seed)
    means = torch.tensor(center, dtype=torch.float64) + radius * torch.randn(n, 3, generator=g, dtype=torch.float64)
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    scales = torch.exp(log_scale + spread * torch.randn(n, 3, generator=g, dtype=torch.float64))
    op = torch.sigmoid(2 * torch.randn(n, generator=g, dtype=torch.float64))
    colors = torch.rand(n, channels, generator=g, dtype=torch.float64)
    return [t.to(dtype) for t in (means, quats, scales, op, colors)]


def projected_inputs(proj, bg):
    return [proj.means2d.detach(), proj.conics.detach(), proj.opacities.detach(), proj.colors.detach(),
            proj.depths.detach(), proj.extent.detach(), bg]


def run(fn, inputs, width, height, seed=123, skip=None):
    """Render, then backprop a random linear loss of image and alpha -> (image, alpha, grads). ``skip``: bool [H, W],
    pixels left out of the loss."""
    means, conics, op, colors, depths, extent, bg = inputs
    leaves = [t.clone().requires_grad_(True) for t in (means, conics, op, colors, bg)]
    img, alpha = fn(leaves[0], leaves[1], leaves[2], leaves[3], depths, extent, width, height, leaves[4])
    g = torch.Generator().manual_seed(seed)
    wi = torch.rand(img.shape, generator=g, dtype=torch.float64).to(img.dtype) - 0.3
    wa = torch.rand(alpha.shape, generator=g, dtype=torch.float64).to(img.dtype) - 0.3
    if skip is not None:
        keep = torch.from_numpy(~skip).to(img.dtype)
        wi, wa = wi * keep[..., None], wa * keep
    ((img * wi).sum() + (alpha * wa).sum()).backward()
    return img.detach(), alpha.detach(), [t.grad for t in leaves]


def near_threshold_pixels(inputs, width, height):
    """bool [H, W]: pixels where a compositing decision (power <= 0, alpha >= 1/255, T >= 1e-4) lies within a
    few ulps of its threshold. The two compositors make them with the same operations on the same inputs but
    different ``exp`` (numba's libm, torch's SLEEF: which one depends on the machine), so only there can they differ
    (issue #14); the depth order is the same stable sort of the same depths in both."""
    means, conics, op, _, depths, _, _ = inputs
    view = SimpleNamespace(means2d=means, conics=conics, opacities=op, depths=depths, width=width, height=height)
    return flips.pixel_margins(view, _rtol(means.dtype)) < _rtol(means.dtype)


def _rtol(dtype):
    return 1e-5 if dtype == torch.float32 else 1e-12


def assert_matches_reference(inputs, width, height, img_tol=IMG_TOL, grad_tol=GRAD_TOL):
    """Images and alpha equal to ``img_tol`` but at pixels whose decisions lie within rounding of a threshold (at
    most a few: there the two may differ by a whole Gaussian); gradients of a loss that leaves those pixels out
    equal to ``grad_tol`` (norm-wise)."""
    near = near_threshold_pixels(inputs, width, height)
    assert near.sum() <= 4, f"{near.sum()} pixels near a threshold: the case is not a fair test"
    img, alpha, grads = run(rasterize_cpu, inputs, width, height, skip=near)
    img_r, alpha_r, grads_r = run(rasterize_reference, inputs, width, height, skip=near)
    assert img.shape == img_r.shape and alpha.shape == alpha_r.shape
    assert img.dtype == img_r.dtype and alpha.dtype == alpha_r.dtype
    assert torch.isfinite(img).all() and torch.isfinite(alpha).all()
    assert (img - img_r).abs().amax(-1).numpy()[~near].max(initial=0.0) < img_tol
    assert (alpha - alpha_r).abs().numpy()[~near].max(initial=0.0) < img_tol
    for name, g, gr in zip(GRAD_NAMES, grads, grads_r):
        assert g is not None and g.shape == gr.shape, name
        assert torch.isfinite(g).all(), name
        scale = gr.double().norm().item()
        err = (g.double() - gr.double()).norm().item()
        assert err <= grad_tol * max(scale, 1e-12), f"{name}: |diff| {err:.3e} vs |ref| {scale:.3e}"
    return img, alpha


def look_at_camera(width=96, height=80, dist=3.0, fov=50.0):
    return Camera.look_at([dist, 0.4 * dist, 0.3 * dist], [0.0, 0.0, 0.0], fov_x_deg=fov, width=width,
                          height=height)


# ---------------------------------------------------------------------------------------------------- tests
class TestAgainstReference:
    @pytest.mark.parametrize("channels", [1, 3])
    @pytest.mark.parametrize("seed", [0, 1])
    def test_random_tiny_float64(self, channels, seed):
        inputs = random_2d(80, 37, 29, channels=channels, seed=seed)
        assert_matches_reference(inputs, 37, 29, img_tol=1e-10, grad_tol=1e-8)

    def test_many_channels_and_odd_sizes(self):
        inputs = random_2d(120, 53, 17, channels=5, seed=4, max_sigma=6.0)
        assert_matches_reference(inputs, 53, 17, img_tol=1e-10, grad_tol=1e-8)

    def test_gradcheck_float64(self):
        means, conics, op, colors, depths, extent, bg = random_2d(7, 9, 7, channels=2, seed=3, opacity=(0.2, 0.8))

        def f(m, c, o, col, b):
            img, alpha = rasterize_cpu(m, c, o, col, depths, extent, 9, 7, b)
            return img, alpha

        leaves = [t.clone().requires_grad_(True) for t in (means, conics, op, colors, bg)]
        assert torch.autograd.gradcheck(f, leaves, eps=1e-6, atol=1e-7, rtol=1e-5)

    def test_float32_10k_scene(self):
        cam = look_at_camera(96, 80)
        params = random_3d(10_000, seed=5, dtype=torch.float32, log_scale=LOG_001, radius=1.0)
        proj = project_gaussians(*params, cam)
        assert proj.count > 6_000
        inputs = projected_inputs(proj, torch.tensor([0.2, 0.5, 1.0]))
        _, alpha = assert_matches_reference(inputs, cam.width, cam.height)
        assert alpha.max() > 0.9  # a real scene, not an empty one

    def test_equal_depths_resolve_by_row(self):
        inputs = random_2d(60, 33, 31, seed=7, opacity=(0.5, 0.99))
        inputs[4] = torch.full_like(inputs[4], 2.0)  # every tie broken by input row, as the stable sort does
        assert_matches_reference(inputs, 33, 31, img_tol=1e-10, grad_tol=1e-8)

    def test_float32_small(self):
        inputs = random_2d(200, 40, 40, seed=8, dtype=torch.float32)
        assert_matches_reference(inputs, 40, 40)


class TestHardCases:
    def test_near_singular_conics(self):
        n = 60
        g = torch.Generator().manual_seed(11)
        means = 0.5 * torch.randn(n, 3, generator=g, dtype=torch.float64)
        quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
        scales = torch.full((n, 3), 1e-6, dtype=torch.float64)
        scales[: n // 2, 0] = 1.0  # needles
        scales[n // 2:, :2] = 0.8  # flat discs, many seen nearly edge-on
        op = torch.full((n,), 0.9, dtype=torch.float64)
        colors = torch.rand(n, 3, generator=g, dtype=torch.float64)
        cam = look_at_camera(64, 48)
        proj = project_gaussians(means, quats, scales, op, colors, cam)
        assert proj.count > n // 2
        det = proj.conics[:, 0] * proj.conics[:, 2] - proj.conics[:, 1] ** 2
        ac = proj.conics[:, 0] * proj.conics[:, 2]
        assert (det / ac).min() < 1e-2  # really near-singular
        assert_matches_reference(projected_inputs(proj, torch.ones(3, dtype=torch.float64)), 64, 48,
                                 img_tol=1e-10, grad_tol=1e-8)

    def test_subpixel_xi_0025(self):
        cam = look_at_camera(400, 320).scaled(0.025)
        assert (cam.width, cam.height) == (10, 8)
        params = random_3d(3000, seed=12, log_scale=math.log(0.005))
        proj = project_gaussians(*params, cam)
        assert proj.count > 100
        inputs = projected_inputs(proj, torch.zeros(3, dtype=torch.float64))
        assert_matches_reference(inputs, cam.width, cam.height, img_tol=1e-10, grad_tol=1e-8)

    def test_image_borders_and_near_plane(self):
        cam = look_at_camera(50, 40, dist=1.0)
        g = torch.Generator().manual_seed(13)
        n = 150
        # points around the view frustum's edges, some just beyond the near plane
        R, t, _ = cam.torch_params(dtype=torch.float64)
        z = torch.cat([torch.rand(30, generator=g, dtype=torch.float64) * 0.05 + 0.011,
                       torch.rand(n - 30, generator=g, dtype=torch.float64) * 2 + 0.3])
        u = torch.where(torch.rand(n, generator=g) < 0.5, -1.0, 1.0).double() * (
            0.9 + 0.2 * torch.rand(n, generator=g, dtype=torch.float64))
        v = (torch.rand(n, generator=g, dtype=torch.float64) * 2 - 1) * 1.1
        swap = torch.rand(n, generator=g) < 0.5
        x_ndc, y_ndc = torch.where(swap, v, u), torch.where(swap, u, v)
        p_cam = torch.stack([x_ndc * z * cam.cx / cam.fx, y_ndc * z * cam.cy / cam.fy, z], -1)
        means = (p_cam - t) @ R  # camera -> world
        quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
        scales = torch.exp(math.log(0.02) + 0.5 * torch.randn(n, 3, generator=g, dtype=torch.float64))
        op = torch.sigmoid(2 * torch.randn(n, generator=g, dtype=torch.float64))
        colors = torch.rand(n, 3, generator=g, dtype=torch.float64)
        proj = project_gaussians(means, quats, scales, op, colors, cam)
        lo, hi = proj.means2d - proj.extent, proj.means2d + proj.extent
        straddle = (lo[:, 0] < 0) | (hi[:, 0] > cam.width) | (lo[:, 1] < 0) | (hi[:, 1] > cam.height)
        assert straddle.sum() > 20 and (proj.depths < 0.06).sum() > 5
        assert_matches_reference(projected_inputs(proj, torch.tensor([1.0, 0.0, 0.5], dtype=torch.float64)),
                                 cam.width, cam.height, img_tol=1e-10, grad_tol=1e-8)

    @pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
    def test_heavy_overlap_early_termination(self, dtype):
        inputs = random_2d(400, 40, 36, seed=14, max_sigma=8.0, opacity=(0.6, 1.0), dtype=dtype)
        _, alpha = assert_matches_reference(inputs, 40, 36)
        assert (alpha > 1 - 1e-3).float().mean() > 0.5  # most pixels ended by the 1e-4 rule
        b = cpu_backend._bin(*[t.to(dtype).contiguous() for t in inputs[:6]], 40, 36)
        assert int(np.diff(b.tile_off).max()) > 100

    def test_no_gaussians(self):
        inputs = [t[:0] for t in random_2d(5, 12, 10, seed=15)[:6]] + [torch.tensor([0.1, 0.2, 0.3],
                                                                                    dtype=torch.float64)]
        img, alpha, grads = run(rasterize_cpu, inputs, 12, 10)
        assert img.shape == (10, 12, 3) and alpha.shape == (10, 12)
        assert torch.equal(img, torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64).expand(10, 12, 3))
        assert torch.equal(alpha, torch.zeros(10, 12, dtype=torch.float64))
        assert grads[0].shape == (0, 2) and grads[3].shape == (0, 3)
        assert_matches_reference(inputs, 12, 10)

    @pytest.mark.parametrize("channels", [1, 3])
    def test_one_pixel_image(self, channels):
        inputs = random_2d(30, 1, 1, channels=channels, seed=16, max_sigma=1.0, margin=1.0)
        assert_matches_reference(inputs, 1, 1, img_tol=1e-10, grad_tol=1e-8)

    def test_all_outside_image(self):
        inputs = random_2d(20, 16, 16, seed=17)
        inputs[0] = inputs[0] + 1000.0
        _, alpha = assert_matches_reference(inputs, 16, 16)
        assert torch.equal(alpha, torch.zeros_like(alpha))


class TestBehaviour:
    def test_bins_follow_footprints(self):
        # one small Gaussian in a corner of a large image: one tile listed, the rest is background
        means = torch.tensor([[3.0, 4.0]], dtype=torch.float64)
        conics = torch.tensor([[1.0, 0.0, 1.0]], dtype=torch.float64)
        op = torch.tensor([0.9], dtype=torch.float64)
        colors = torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64)
        ext = torch.full((1, 2), math.sqrt(2 * math.log(255 * 0.9)), dtype=torch.float64)
        b = cpu_backend._bin(means, conics, op, colors, torch.ones(1, dtype=torch.float64), ext, 512, 512)
        assert b.n_isect == 1
        # a long thin diagonal Gaussian: the ellipse test lists fewer tiles than its bounding box covers
        cov = torch.tensor([[400.0, 399.0], [399.0, 400.0]], dtype=torch.float64)
        inv = torch.linalg.inv(cov)
        conics = torch.stack([inv[0, 0], inv[0, 1], inv[1, 1]])[None]
        m2 = 2 * math.log(255 * 0.9)
        ext = torch.sqrt(m2 * torch.diagonal(cov))[None]
        means = torch.tensor([[100.0, 100.0]], dtype=torch.float64)
        b = cpu_backend._bin(means, conics, op, colors, torch.ones(1, dtype=torch.float64), ext, 256, 256)
        lo, hi = (means - ext)[0], (means + ext)[0]
        bbox_tiles = (math.ceil(hi[0] / 16) - math.floor(lo[0] / 16)) * (math.ceil(hi[1] / 16) - math.floor(lo[1] / 16))
        assert b.n_isect < 0.5 * bbox_tiles
        assert_matches_reference([means, conics, op, colors, torch.ones(1, dtype=torch.float64), ext,
                                  torch.zeros(3, dtype=torch.float64)], 256, 256, img_tol=1e-10, grad_tol=1e-8)

    def test_deterministic(self):
        inputs = random_2d(300, 64, 48, seed=18, dtype=torch.float32)
        a = run(rasterize_cpu, inputs, 64, 48)
        b = run(rasterize_cpu, inputs, 64, 48)
        assert torch.equal(a[0], b[0]) and all(torch.equal(x, y) for x, y in zip(a[2], b[2]))

    def test_dispatch_and_end_to_end_gradients(self):
        assert "cpu" in available_backends()
        cam = look_at_camera(40, 32)
        params = random_3d(500, seed=19)
        outs = {}
        for backend in ("cpu", "reference"):
            leaves = [p.clone().requires_grad_(True) for p in params]
            res = render_gaussians(*leaves, cam, background=(0.3, 0.3, 0.3), backend=backend)
            (res.image.square().sum() + res.alpha.sum()).backward()
            outs[backend] = (res.image.detach(), [p.grad for p in leaves])
        assert (outs["cpu"][0] - outs["reference"][0]).abs().max() < 1e-10
        for g, gr in zip(outs["cpu"][1], outs["reference"][1]):
            assert (g - gr).norm() <= 1e-8 * gr.norm()
        proj = project_gaussians(*params, cam)
        bg = torch.ones(3, dtype=torch.float64)
        a = rasterize(proj, bg, backend="cpu")
        r = rasterize(proj, bg, backend="reference")
        assert (a[0] - r[0]).abs().max() < 1e-10

    def test_scalar_background_broadcasts(self):
        inputs = random_2d(40, 20, 20, seed=20)
        inputs[6] = torch.tensor(0.25, dtype=torch.float64)
        img, _, grads = run(rasterize_cpu, inputs, 20, 20)
        img_r, _, grads_r = run(rasterize_reference, inputs, 20, 20)
        assert (img - img_r).abs().max() < 1e-10
        assert grads[4].shape == () and abs(grads[4] - grads_r[4]) < 1e-8 * abs(grads_r[4])


class TestCudaBackendGuard:
    def test_import_guard(self):
        from proxycodec.render import cuda as cuda_backend

        if cuda_backend.gsplat_available() and torch.cuda.is_available():
            assert "cuda" in available_backends()
        if not cuda_backend.gsplat_available():
            assert "cuda" not in available_backends()
            with pytest.raises(Exception, match="gsplat"):
                cuda_backend.rasterize_cuda(*random_2d(3, 8, 8, dtype=torch.float32)[:6], 8, 8, torch.zeros(3))
