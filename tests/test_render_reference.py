"""The reference compositor against a per-pixel loop written from the 3DGS rules, and the hard cases."""

import math

import flips
import numpy as np
import pytest
import torch

from proxycodec.camera import Camera
from proxycodec.render import project_gaussians, rasterize_reference, render_gaussians
from proxycodec.render.project import ALPHA_MAX, ALPHA_MIN, T_MIN


def loop_composite(p, bg):
    """Independent oracle: 3DGS's forward, one pixel at a time, in float64 Python."""
    H, W = p.height, p.width
    order = sorted(range(p.count), key=lambda i: (float(p.depths[i]), i))
    img = np.zeros((H, W, p.colors.shape[1]))
    for y in range(H):
        for x in range(W):
            T, c = 1.0, np.zeros(p.colors.shape[1])
            for i in order:
                dx, dy = x + 0.5 - float(p.means2d[i, 0]), y + 0.5 - float(p.means2d[i, 1])
                a, b, cc = (float(v) for v in p.conics[i])
                power = -0.5 * (a * dx * dx + cc * dy * dy) - b * dx * dy
                if power > 0:
                    continue
                alpha = min(ALPHA_MAX, float(p.opacities[i]) * math.exp(power))
                if alpha < ALPHA_MIN:
                    continue
                if T * (1 - alpha) < T_MIN:
                    break
                c += T * alpha * p.colors[i].double().numpy()
                T *= 1 - alpha
            img[y, x] = c + T * np.asarray(bg)
    return img


def random_gaussians(n, seed=0, spread=0.6, log_scale=-2.5, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=dtype) - 0.5) * 2 * spread
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = torch.exp(torch.randn(n, 3, generator=g, dtype=dtype) * 0.6 + log_scale)
    opac = torch.rand(n, generator=g, dtype=dtype)
    colors = torch.rand(n, 3, generator=g, dtype=dtype)
    return means, quats, scales, opac, colors


CAM = Camera.look_at([0.0, -3.0, 0.8], [0, 0, 0], width=23, height=17, fov_x_deg=40)


@pytest.mark.parametrize("seed", [0, 1])
def test_reference_matches_per_pixel_loop(seed):
    m, q, s, o, c = random_gaussians(60, seed, log_scale=-2.0)
    o = o * 0 + 0.95 if seed else o  # seed 1: opaque, reaches early termination
    p = project_gaussians(m, q, s, o, c, CAM)
    bg = (0.2, 0.4, 0.6)
    img, _ = rasterize_reference(p.means2d, p.conics, p.opacities, p.colors, p.depths, p.extent, p.width, p.height,
                                 torch.tensor(bg, dtype=torch.float64))
    assert np.abs(img.numpy() - loop_composite(p, bg)).max() < 1e-12


def test_reference_gradcheck_float64():
    m, q, s, o, c = random_gaussians(12, 3, log_scale=-1.7)
    p = project_gaussians(m, q, s, o, c, CAM.scaled(0.5))
    args = [t.detach().clone().requires_grad_(True) for t in (p.means2d, p.conics, p.opacities, p.colors)]
    bg = torch.tensor([1.0, 1.0, 1.0], dtype=torch.float64)

    def f(m2, con, op, col):
        return rasterize_reference(m2, con, op, col, p.depths, p.extent, p.width, p.height, bg)[0]

    assert torch.autograd.gradcheck(f, args, eps=1e-6, atol=1e-6, rtol=1e-4)


def _grads_ok(tensors, bound=1e8):
    for t in tensors:
        assert t.grad is None or (torch.isfinite(t.grad).all() and t.grad.abs().max() < bound)


@pytest.mark.parametrize("case", ["needle", "flat", "near_plane", "border", "inside", "zero_quat", "huge"])
def test_hard_cases_finite_with_bounded_gradients(case):
    m, q, s, o, c = random_gaussians(40, 7, dtype=torch.float32)
    cam = Camera.look_at([0.0, -3.0, 0.0], [0, 0, 0], width=48, height=40)
    if case == "needle":
        s = s * torch.tensor([1e-6, 1e-6, 1.0])
    elif case == "flat":
        s = s * torch.tensor([1.0, 1.0, 1e-7])
    elif case == "near_plane":
        m = m * 0.1 + torch.tensor([0.0, -2.99, 0.0])  # 1 cm in front of the camera
        s = s * 5
    elif case == "border":
        m[:, 0] = torch.linspace(-1.5, 1.5, m.shape[0])  # marching across the left/right image borders
    elif case == "inside":
        cam = Camera.look_at([0.0, 0.0, 0.0], [0, 1.0, 0], width=48, height=40)
    elif case == "zero_quat":
        q = q * 0
    elif case == "huge":
        s = torch.full_like(s, math.exp(10))
    leaves = [t.requires_grad_(True) for t in (m, q, s, o, c)]
    for xi in (0.025, 1.0, 2.0):
        r = render_gaussians(m, q, s, o, c, cam.scaled(xi), backend="reference")
        assert torch.isfinite(r.image).all() and torch.isfinite(r.alpha).all()
        assert r.image.min() >= 0 and r.image.max() <= 1 + 1e-6
        (r.image.sum() + r.alpha.sum()).backward()
        _grads_ok(leaves)


def test_one_pixel_image_and_empty_scene():
    cam = Camera.look_at([0.0, -3.0, 0.0], [0, 0, 0], width=1, height=1)
    m, q, s, o, c = random_gaussians(10, 2, dtype=torch.float32)
    r = render_gaussians(m, q, s, o, c, cam, backend="reference", background=(0.0, 0.0, 0.0))
    assert r.image.shape == (1, 1, 3) and torch.isfinite(r.image).all()
    e = render_gaussians(m[:0], q[:0], s[:0], o[:0], c[:0], cam.scaled(2.0), backend="reference",
                         background=(0.1, 0.2, 0.3))
    assert e.image.shape == (2, 2, 3) and torch.allclose(e.image, torch.tensor([0.1, 0.2, 0.3]).expand(2, 2, 3))
    assert e.projected.count == 0


def test_gate_dims_sub_pixel_gaussians_at_low_resolution():
    """The same small Gaussian is fainter (gated) when it covers less than a pixel."""
    m = torch.zeros(1, 3)
    q = torch.tensor([[1.0, 0, 0, 0]])
    s = torch.full((1, 3), 0.01)
    cam = Camera.look_at([0.0, -3.0, 0.0], [0, 0, 0], width=400, height=400)
    hi = project_gaussians(m, q, s, torch.ones(1), torch.ones(1, 3), cam)
    lo = project_gaussians(m, q, s, torch.ones(1), torch.ones(1, 3), cam.scaled(0.05))
    assert float(hi.gate[0]) > 0.99 and float(lo.gate[0]) < 0.3


def test_far_from_the_origin_float32_matches_float64():
    """Coordinates of 1e5 with centimetre Gaussians: camera-relative projection keeps float32 exact enough."""
    off = torch.tensor([1e5, -2e5, 3e4], dtype=torch.float64)
    m, q, s, o, c = random_gaussians(200, 5, spread=0.3, log_scale=-4.0)
    cam = Camera.look_at((off + torch.tensor([0.0, -2.0, 0.5])).numpy(), off.numpy(), width=48, height=40)
    m32 = (m + off).float()
    ref = project_gaussians(m32.double(), q, s, o, c, cam)
    p32 = project_gaussians(m32, q.float(), s.float(), o.float(), c.float(), cam)
    # the same culls but for values within float32 rounding of a threshold (float32 vs float64: issue #14)
    ia, ib = flips.match_rows(p32.index.numpy(), ref.index.numpy(), flips.cull_margins(p32), flips.cull_margins(ref),
                              1e-5, 2, "culling decisions")
    assert len(ia) > 100
    assert (p32.means2d[ia].double() - ref.means2d[ib]).abs().max() < 1e-3  # pixels


def test_a_camera_sized_to_whole_pixels_sees_the_same_field_of_view():
    """``Camera.sized`` (``scaled`` with the size given): the image corners map to the same rays at any size, and
    ``scaled(xi)`` is ``sized`` of its rounded size."""
    for w, h in ((46, 34), (7, 5), (23, 17), (30, 11)):
        c = CAM.sized(w, h)
        assert (c.width, c.height) == (w, h)
        for u, v in ((0.0, 0.0), (1.0, 1.0), (0.25, 0.75)):  # image fractions -> normalised rays
            ray = ((u * w - c.cx) / c.fx, (v * h - c.cy) / c.fy)
            ref = ((u * CAM.width - CAM.cx) / CAM.fx, (v * CAM.height - CAM.cy) / CAM.fy)
            np.testing.assert_allclose(ray, ref, rtol=0, atol=1e-12)
    assert CAM.scaled(0.3) == CAM.sized(round(0.3 * 23), round(0.3 * 17))
    with pytest.raises(Exception, match="at least 1 x 1"):
        CAM.sized(0, 4)
