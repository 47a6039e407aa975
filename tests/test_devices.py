"""Devices: the CUDA compositor against the reference, ``--device`` on a machine without a GPU, and no hard-coded
device in the library.

* The alpha clamp (``proxycodec/render/cuda.py``'s docstring has the analysis): gsplat up to 1.5.x composites with
  ``min(0.999, o e)``, the reference with ``min(0.99, o e)``. The CPU tests emulate gsplat's rule with the reference
  compositor itself (its ``ALPHA_MAX`` set to gsplat's value) and check, in float64 and on the same code path (so
  bit-for-bit, whatever the machine's ``exp``): equality where no opacity exceeds 0.99; above 0.99 a difference
  confined to the cores (o e > 0.99) and within the stated bound; and why passing ``opacities.clamp(max=0.99)`` to
  gsplat was rejected.
* ``cuda``-marked tests (conftest skips them, with ``proxycodec.devices.cuda_unavailable_reason()``, where torch sees
  no GPU or gsplat does not import): the gsplat backend against the reference on CUDA tensors, projected with the
  coverage gate, images and gradients, float32 against a float64 oracle. Pixels where a compositing decision lies
  within rounding of its threshold (1/255, T = 1e-4, power = 0: ``flips.pixel_margins``) are left out, as in
  ``test_raster_cpu.py`` (issue #14): there ``__expf`` and torch's ``exp`` may decide differently. The same
  comparison runs on the CPU with the float32 emulation standing in for gsplat, so its code is exercised everywhere.
* The static check: no module of the library names a device but ``proxycodec/devices.py``.
"""

from __future__ import annotations

import ast
import contextlib
import math
import os
import subprocess
import sys
from pathlib import Path

import flips
import numpy as np
import pytest
import torch

import proxycodec.render.reference as reference_module
from proxycodec import devices
from proxycodec.camera import Camera
from proxycodec.errors import ProxycodecError
from proxycodec.render.project import ALPHA_MAX, ALPHA_MIN, T_MIN, GateConfig, project_gaussians
from proxycodec.render.reference import rasterize_reference

REPO_ROOT = Path(__file__).resolve().parents[1]
GSPLAT_15_ALPHA_MAX = 0.999  # what gsplat 1.5.x compiles
GRAD_NAMES = ("means2d", "conics", "opacities", "colors")


# ============================================================================================ the alpha clamp
@contextlib.contextmanager
def alpha_clamp(amax: float):
    """The reference compositor (and ``flips``' model of it) with its alpha clamp at ``amax``: gsplat's rule when
    ``amax`` is gsplat's value. Restored on exit."""
    old = reference_module.ALPHA_MAX, flips.ALPHA_MAX
    reference_module.ALPHA_MAX = flips.ALPHA_MAX = amax
    try:
        yield
    finally:
        reference_module.ALPHA_MAX, flips.ALPHA_MAX = old


def emulated(amax: float, clamp_opacities: bool = False):
    """A compositor with ``rasterize_reference``'s interface that applies ``min(amax, o e)``; with
    ``clamp_opacities`` it first clamps the opacities at ``ALPHA_MAX`` (the rejected alternative)."""

    def fn(means2d, conics, opacities, colors, depths, extent, width, height, background):
        if clamp_opacities:
            opacities = opacities.clamp(max=ALPHA_MAX)
        with alpha_clamp(amax):
            return rasterize_reference(means2d, conics, opacities, colors, depths, extent, width, height, background)

    return fn


def random_2d(n, width, height, seed, opacity, sigma=(1.5, 6.0), dtype=torch.float64):
    """A 2D interface (means2d, conics, opacities, colors, depths, extent) + background, opacities uniform in
    ``opacity`` (lo, hi), axis lengths uniform in ``sigma`` pixels; colours and background in [0, 1]."""
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.rand(*s, generator=g, dtype=torch.float64)
    means = r(n, 2) * torch.tensor([width, height], dtype=torch.float64)
    theta = r(n) * math.pi
    s1, s2 = (sigma[0] + (sigma[1] - sigma[0]) * r(n) for _ in range(2))
    c, s = torch.cos(theta), torch.sin(theta)
    sxx, syy, sxy = c * c * s1**2 + s * s * s2**2, s * s * s1**2 + c * c * s2**2, c * s * (s1**2 - s2**2)
    det = sxx * syy - sxy * sxy
    conics = torch.stack([syy / det, -sxy / det, sxx / det], -1)
    op = opacity[0] + (opacity[1] - opacity[0]) * r(n)
    colors, depths, bg = r(n, 3), 1.0 + r(n), r(3)
    m2 = 2 * torch.log((op * 255).clamp_min(1))
    extent = torch.stack([torch.sqrt(m2 * sxx), torch.sqrt(m2 * syy)], -1)
    return [t.to(dtype) for t in (means, conics, op, colors, depths, extent, bg)]


def render_and_grad(fn, inputs, width, height, skip=None, dtype=None, seed=7):
    """Render with ``fn`` (inputs cast to ``dtype``), backprop a fixed random linear loss of image and alpha over
    the pixels not in ``skip`` (bool [H, W]) -> (image, alpha, grads of means2d, conics, opacities, colors), all
    float64 on the CPU."""
    means, conics, op, colors, depths, extent, bg = inputs
    dtype = dtype or means.dtype
    leaves = [t.detach().to(dtype).clone().requires_grad_(True) for t in (means, conics, op, colors)]
    img, alpha = fn(*leaves, depths.to(dtype), extent.to(dtype), width, height, bg.to(dtype))
    g = torch.Generator().manual_seed(seed)
    wi = torch.rand(img.shape, generator=g, dtype=torch.float64) - 0.3
    wa = torch.rand(alpha.shape, generator=g, dtype=torch.float64) - 0.3
    if skip is not None:
        keep = torch.from_numpy(~np.asarray(skip)).double()
        wi, wa = wi * keep[..., None], wa * keep
    dev = img.device
    ((img * wi.to(dev, img.dtype)).sum() + (alpha * wa.to(dev, img.dtype)).sum()).backward()
    host = lambda t: t.detach().cpu().double()
    return host(img), host(alpha), [host(t.grad) for t in leaves]


def core_pixels(means2d, conics, opacities, width, height, limit=ALPHA_MAX, rtol=1e-5) -> np.ndarray:
    """bool [H, W]: pixel centres in the core of some Gaussian, o exp(power) > limit (1 - rtol): where gsplat's
    0.999 clamp can differ from the reference's 0.99 (a superset: whether the pixel reaches it is not asked)."""
    m2d, con, op = (flips._np(t) for t in (means2d, conics, opacities))
    m2d, con, op = m2d.reshape(-1, 2), con.reshape(-1, 3), op.reshape(-1)
    out = np.zeros((height, width), bool)
    lim = limit * (1 - rtol)
    for g in np.flatnonzero(op > lim):
        a, b, c = con[g]
        det = a * c - b * b
        q = 2.0 * math.log(op[g] / lim)  # o exp(-m^2/2) > lim  <=>  m^2 < q
        rx, ry = math.sqrt(q * c / det) + 1.0, math.sqrt(q * a / det) + 1.0
        mx, my = m2d[g]
        x0, x1 = max(0, math.floor(mx - rx)), min(width, math.ceil(mx + rx) + 1)
        y0, y1 = max(0, math.floor(my - ry)), min(height, math.ceil(my + ry) + 1)
        if x1 <= x0 or y1 <= y0:
            continue
        dx = np.arange(x0, x1)[None, :] + 0.5 - mx
        dy = np.arange(y0, y1)[:, None] + 0.5 - my
        power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
        out[y0:y1, x0:x1] |= op[g] * np.exp(np.minimum(power, 0.0)) > lim
    return out


def core_bound(means2d, conics, opacities, depths, pixels, amax=GSPLAT_15_ALPHA_MAX, slack=1e-6) -> np.ndarray:
    """[len(pixels)] the bound of ``render/cuda.py`` on |gsplat - reference| (colour and alpha) at the given pixels
    ([P, 2] integer (x, y)): with T_k the reference's transmittance in front of the first Gaussian it reaches with
    o e > 0.99 there, 0.01 T_k, or T_k where gsplat may end the pixel at it (T_k (1 - amax) <= 1e-4); 0 where no
    core is reached. Float64, the reference's rules, Gaussians in ascending depth (ties by row); ``slack``: relative,
    on gsplat's stop test (a float32 path decides it within rounding)."""
    m2d, con, op, dep = (flips._np(t) for t in (means2d, conics, opacities, depths))
    m2d, con, op, dep = m2d.reshape(-1, 2), con.reshape(-1, 3), op.reshape(-1), dep.reshape(-1)
    px = np.asarray(pixels, np.float64) + 0.5
    T = np.ones(len(px))
    Tk = np.full(len(px), np.nan)
    done = np.zeros(len(px), bool)
    for g in np.argsort(dep, kind="stable"):
        a, b, c = con[g]
        dx, dy = px[:, 0] - m2d[g, 0], px[:, 1] - m2d[g, 1]
        power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
        raw = op[g] * np.exp(np.minimum(power, 0.0))
        alpha = np.minimum(ALPHA_MAX, raw)
        live = ~done & (power <= 0) & (alpha >= ALPHA_MIN)
        first = live & (raw > ALPHA_MAX) & np.isnan(Tk)
        Tk[first] = T[first]
        nxt = T * (1.0 - alpha)
        stop = live & (nxt < T_MIN)
        done |= stop
        T = np.where(live & ~stop, nxt, T)
    may_stop = Tk * (1.0 - amax) <= T_MIN * (1 + slack)
    return np.where(np.isnan(Tk), 0.0, np.where(may_stop, Tk, 0.01 * Tk))


def test_the_emulation_changes_the_clamp():
    """Not vacuous: the emulated rule gives alpha 0.999 where the reference gives 0.99, and is undone on exit."""
    one = [torch.tensor([[4.5, 4.5]]), torch.tensor([[0.5, 0.0, 0.5]]), torch.tensor([1.0]), torch.zeros(1, 3),
           torch.ones(1), torch.tensor([[8.0, 8.0]])]
    args = (*[t.double() for t in one], 9, 9, torch.ones(3, dtype=torch.float64))
    _, a_ref = rasterize_reference(*args)
    _, a_emu = emulated(GSPLAT_15_ALPHA_MAX)(*args)
    assert a_ref[4, 4].item() == pytest.approx(0.99, abs=1e-15)
    assert a_emu[4, 4].item() == pytest.approx(0.999, abs=1e-15)
    assert reference_module.ALPHA_MAX == ALPHA_MAX == 0.99 and flips.ALPHA_MAX == ALPHA_MAX


def test_gsplat_rule_is_the_reference_below_the_cap():
    """No gated opacity above 0.99 (here at most 0.98): the 0.999 clamp never engages, so gsplat's rule gives the
    reference's images, alpha and gradients bit for bit (the same operations on the same values)."""
    inputs = random_2d(150, 48, 40, seed=3, opacity=(0.3, 0.98))
    img, alpha, grads = render_and_grad(emulated(GSPLAT_15_ALPHA_MAX), inputs, 48, 40)
    img_r, alpha_r, grads_r = render_and_grad(rasterize_reference, inputs, 48, 40)
    assert alpha_r.max() > 0.999  # opaque stacks: early termination is exercised
    assert torch.equal(img, img_r) and torch.equal(alpha, alpha_r)
    for name, g, gr in zip(GRAD_NAMES, grads, grads_r):
        assert torch.equal(g, gr), name


@pytest.fixture(scope="module")
def above_the_cap():
    """A scene whose front layers are ordinary and half of whose Gaussians have opacity in (0.995, 0.9999)."""
    W, H = 48, 40
    lo = random_2d(90, W, H, seed=11, opacity=(0.2, 0.9))
    hi = random_2d(90, W, H, seed=12, opacity=(0.995, 0.9999), sigma=(3.0, 8.0))
    inputs = [torch.cat([a, b]) for a, b in zip(lo[:6], hi[:6])] + [lo[6]]
    core = core_pixels(inputs[0], inputs[1], inputs[2], W, H)
    return inputs, W, H, core


def test_gsplat_rule_above_the_cap_differs_only_in_the_cores(above_the_cap):
    """Opacities above 0.99: outside the cores (o e > 0.99) images, alpha and the gradients of a loss over those
    pixels are the reference's bit for bit; in the cores the difference keeps to ``render/cuda.py``'s bound."""
    inputs, W, H, core = above_the_cap
    assert 20 <= core.sum() <= 0.5 * core.size, core.sum()  # the case is a test: cores exist, the rest dominates
    emu = emulated(GSPLAT_15_ALPHA_MAX)
    img, alpha, grads = render_and_grad(emu, inputs, W, H, skip=core)
    img_r, alpha_r, grads_r = render_and_grad(rasterize_reference, inputs, W, H, skip=core)
    diff = (img - img_r).abs().amax(-1).numpy()
    dal = (alpha - alpha_r).abs().numpy()
    assert diff[~core].max() <= 1e-12 and dal[~core].max() <= 1e-12
    for name, g, gr in zip(GRAD_NAMES, grads, grads_r):
        assert (g - gr).norm() <= 1e-12 * gr.norm(), name
    assert diff[core].max() > 1e-4  # the cores do differ (else the bound below proves nothing)
    ys, xs = np.nonzero(core)
    bound = core_bound(inputs[0], inputs[1], inputs[2], inputs[4], np.stack([xs, ys], 1))
    assert (diff[ys, xs] <= bound + 1e-12).all() and (dal[ys, xs] <= bound + 1e-12).all()
    assert bound.max() <= 0.1 + 1e-12
    assert max(diff.max(), dal.max()) <= 0.1


def test_gsplat_rule_stop_flip_is_the_worst_case():
    """Where gsplat ends a pixel at a core that the reference composites (T in front in [0.01, 0.1]), the whole
    remaining transmittance differs: a Gaussian of opacity 0.999 behind one of 0.95, colour 0 on white: 0.0495."""
    W = H = 9
    means = torch.tensor([[4.5, 4.5], [4.5, 4.5]], dtype=torch.float64)  # centred on pixel (4, 4): power = 0
    conics = torch.tensor([[0.5, 0.0, 0.5]] * 2, dtype=torch.float64)
    op = torch.tensor([0.95, 0.999], dtype=torch.float64)
    colors = torch.tensor([[1.0, 1.0, 1.0], [0.0, 0.0, 0.0]], dtype=torch.float64)
    inputs = [means, conics, op, colors, torch.tensor([1.0, 2.0], dtype=torch.float64),
              torch.full((2, 2), 8.0, dtype=torch.float64), torch.ones(3, dtype=torch.float64)]
    img, _, _ = render_and_grad(emulated(GSPLAT_15_ALPHA_MAX), inputs, W, H)
    img_r, _, _ = render_and_grad(rasterize_reference, inputs, W, H)
    d = (img - img_r).abs()[4, 4].max().item()
    assert d == pytest.approx(0.05 * 0.99, rel=1e-9)
    bound = core_bound(means, conics, op, inputs[4], [[4, 4]])
    assert bound[0] == pytest.approx(0.05, rel=1e-9) and d <= bound[0]


def test_clamping_the_opacities_instead_was_rejected(above_the_cap):
    """The alternative, ``opacities.clamp(max=0.99)`` into gsplat: alpha = 0.99 e over the whole footprint of a
    Gaussian above 0.99, so pixels outside the cores differ too, and such a Gaussian gets no opacity gradient."""
    inputs, W, H, core = above_the_cap
    img, _, grads = render_and_grad(emulated(GSPLAT_15_ALPHA_MAX, clamp_opacities=True), inputs, W, H, skip=core)
    img_r, _, grads_r = render_and_grad(rasterize_reference, inputs, W, H, skip=core)
    diff = (img - img_r).abs().amax(-1).numpy()
    assert diff[~core].max() > 1e-3  # unclamped: 0 there (the test above)
    assert (diff[~core] > 1e-4).mean() > 3 * core.mean()  # ... and on more pixels than the cores hold
    above = inputs[2] > ALPHA_MAX
    assert (grads[2][above] == 0).all() and (grads_r[2][above] != 0).sum() >= 0.9 * above.sum()


# ============================================================================== the cuda backend (GPU machine)
RTOL_F32 = 1e-4  # decisions within this relative distance of a threshold may flip between float32 paths
IMG_TOL = 1e-3
GRAD_RTOL = 1e-2


def gated_scene(n, size, seed, device, *, opacity=(0.02, 0.98), hi_share=0.0, hi=(0.995, 0.9999)):
    """``n`` random 3D Gaussians projected with the coverage gate at ``size`` px on ``device`` (float32): the
    ``Projected`` and a background. A share ``hi_share`` gets opacity in ``hi`` and larger scales (so its gate is
    near 1 and its gated opacity above 0.99); the rest ``opacity`` (gated: at most its upper end)."""
    g = torch.Generator().manual_seed(seed)
    means = 0.6 * torch.randn(n, 3, generator=g)
    quats = torch.randn(n, 4, generator=g)
    log_scale = torch.full((n,), math.log(0.02))
    op = opacity[0] + (opacity[1] - opacity[0]) * torch.rand(n, generator=g)
    k = round(hi_share * n)
    if k:
        log_scale[:k] = math.log(0.06)
        op[:k] = hi[0] + (hi[1] - hi[0]) * torch.rand(k, generator=g)
    scales = torch.exp(log_scale[:, None] + 0.4 * torch.randn(n, 3, generator=g))
    colors = torch.rand(n, 3, generator=g)
    bg = torch.rand(3, generator=g)
    cam = Camera.look_at([2.6, 1.0, 0.9], [0.0, 0.0, 0.0], fov_x_deg=50.0, width=size, height=size)
    to = lambda t: t.to(device)
    proj = project_gaussians(to(means), to(quats), to(scales), to(op), to(colors), cam, gate=GateConfig())
    return proj, to(bg)


def proj_inputs(proj, bg):
    return [proj.means2d.detach(), proj.conics.detach(), proj.opacities.detach(), proj.colors.detach(),
            proj.depths.detach(), proj.extent.detach(), bg]


def compare(candidate, oracle, proj, bg, skip=None):
    """``candidate`` in float32 against ``oracle`` in float64 on the same (float32) values, on their device: the
    largest image and alpha difference and the relative gradient errors (norm-wise), over the pixels that are not
    near a threshold (``flips.pixel_margins`` at ``RTOL_F32``, with ``flips.ALPHA_MAX`` as it is) nor in ``skip``.
    Returns (image error, alpha error, {name: relative gradient error}, near-threshold pixel count)."""
    inputs = proj_inputs(proj, bg)
    W, H = proj.width, proj.height
    near = flips.pixel_margins(proj, RTOL_F32) < RTOL_F32
    assert near.sum() <= 0.01 * near.size, f"{near.sum()} pixels near a threshold: the case is not a fair test"
    out = near if skip is None else near | skip
    img, alpha, grads = render_and_grad(candidate, inputs, W, H, skip=out, dtype=torch.float32)
    img_o, alpha_o, grads_o = render_and_grad(oracle, inputs, W, H, skip=out, dtype=torch.float64)
    assert img.shape == img_o.shape == (H, W, 3) and alpha.shape == alpha_o.shape == (H, W)
    assert torch.isfinite(img).all() and torch.isfinite(alpha).all()
    keep = torch.from_numpy(~out)
    img_err = (img - img_o).abs().amax(-1)[keep].max().item()
    alpha_err = (alpha - alpha_o).abs()[keep].max().item()
    errs = {}
    for name, g, go in zip(GRAD_NAMES, grads, grads_o):
        assert torch.isfinite(g).all(), name
        errs[name] = ((g - go).norm() / go.norm().clamp_min(1e-30)).item()
    return img_err, alpha_err, errs, int(near.sum())


def check_below_the_cap(candidate, proj, bg):
    assert proj.count >= 100 and proj.opacities.max() <= 0.98 + 1e-6
    assert proj.gate.min() < 0.9  # the gate dims some: it is on
    img_err, alpha_err, errs, _ = compare(candidate, rasterize_reference, proj, bg)
    assert img_err <= IMG_TOL and alpha_err <= IMG_TOL, (img_err, alpha_err)
    assert max(errs.values()) <= GRAD_RTOL, errs


def check_above_the_cap(candidate, amax, proj, bg):
    """(a) ``candidate`` is gsplat's rule with clamp ``amax`` (the emulation, in float64); (b) outside the cores it is
    the reference; (c) in the cores it keeps to the bound of ``render/cuda.py``."""
    above = int((proj.opacities > ALPHA_MAX).sum())
    assert above >= 20, f"only {above} gated opacities above 0.99: the case is not a test"
    with alpha_clamp(amax):
        img_err, alpha_err, errs, _ = compare(candidate, emulated(amax), proj, bg)
    assert img_err <= IMG_TOL and alpha_err <= IMG_TOL, ("against the emulation", img_err, alpha_err)
    assert max(errs.values()) <= 2 * GRAD_RTOL, ("against the emulation", errs)
    W, H = proj.width, proj.height
    core = core_pixels(proj.means2d, proj.conics, proj.opacities, W, H)
    assert core.sum() > 0
    img_err, alpha_err, errs, _ = compare(candidate, rasterize_reference, proj, bg, skip=core)
    assert img_err <= IMG_TOL and alpha_err <= IMG_TOL, ("outside the cores", img_err, alpha_err)
    assert max(errs.values()) <= 2 * GRAD_RTOL, ("outside the cores", errs)
    inputs = proj_inputs(proj, bg)
    with torch.no_grad():
        img, alpha = candidate(*[t.float() for t in inputs[:6]], W, H, bg.float())
        img_r, alpha_r = rasterize_reference(*[t.double() for t in inputs[:6]], W, H, bg.double())
    ys, xs = np.nonzero(core)
    bound = core_bound(proj.means2d, proj.conics, proj.opacities, proj.depths, np.stack([xs, ys], 1), amax=amax,
                       slack=RTOL_F32)
    if amax <= ALPHA_MAX:
        bound[:] = 0.0
    diff = (img.double() - img_r).abs().amax(-1).cpu().numpy()[ys, xs]
    dal = (alpha.double() - alpha_r).abs().cpu().numpy()[ys, xs]
    near = flips.pixel_margins(proj, RTOL_F32) < RTOL_F32  # a decision may flip there, under either rule
    with alpha_clamp(amax):
        near |= flips.pixel_margins(proj, RTOL_F32) < RTOL_F32
    worse = ((diff > bound + IMG_TOL) | (dal > bound + IMG_TOL)) & ~near[ys, xs]  # IMG_TOL: float32 slack
    assert not worse.any(), list(zip(xs[worse][:5], ys[worse][:5], diff[worse][:5], bound[worse][:5]))
    assert (diff <= bound + IMG_TOL).mean() >= 0.99


def test_comparison_on_the_cpu():
    """The GPU checks' code, run here with the float32 emulation of gsplat's rule standing in for gsplat."""
    cpu = devices.resolve("cpu")
    proj, bg = gated_scene(2000, 64, seed=0, device=cpu)
    check_below_the_cap(rasterize_reference, proj, bg)
    proj, bg = gated_scene(2000, 64, seed=1, device=cpu, hi_share=0.3)
    check_above_the_cap(emulated(GSPLAT_15_ALPHA_MAX), GSPLAT_15_ALPHA_MAX, proj, bg)


@pytest.fixture(scope="module")
def cuda():
    return devices.resolve(devices.CUDA)


@pytest.mark.cuda
@pytest.mark.parametrize("n, size", [(2000, 64), (20000, 128)])
def test_cuda_backend_matches_the_reference(cuda, n, size):
    from proxycodec.render.cuda import rasterize_cuda

    proj, bg = gated_scene(n, size, seed=n, device=cuda)
    assert proj.means2d.is_cuda
    check_below_the_cap(rasterize_cuda, proj, bg)


@pytest.mark.cuda
@pytest.mark.parametrize("n, size", [(2000, 64), (20000, 128)])
def test_cuda_backend_above_the_alpha_cap(cuda, n, size):
    from proxycodec.render.cuda import gsplat_alpha_max, rasterize_cuda

    amax = gsplat_alpha_max()
    assert amax is not None, "the alpha clamp of the installed gsplat was not found in its sources"
    proj, bg = gated_scene(n, size, seed=n + 1, device=cuda, hi_share=0.3)
    check_above_the_cap(rasterize_cuda, amax, proj, bg)


@pytest.mark.cuda
def test_cuda_backend_stop_flip(cuda):
    """The worst case of ``render/cuda.py``'s bound, on gsplat: 0.0495 with a 0.999 clamp, 0 with 0.99."""
    from proxycodec.render.cuda import gsplat_alpha_max, rasterize_cuda

    f32 = {"device": cuda, "dtype": torch.float32}
    args = (torch.tensor([[4.5, 4.5], [4.5, 4.5]], **f32), torch.tensor([[0.5, 0.0, 0.5]] * 2, **f32),
            torch.tensor([0.95, 0.999], **f32), torch.tensor([[1.0, 1.0, 1.0], [0.0, 0.0, 0.0]], **f32),
            torch.tensor([1.0, 2.0], **f32), torch.full((2, 2), 8.0, **f32), 9, 9, torch.ones(3, **f32))
    img, _ = rasterize_cuda(*args)
    img_r, _ = rasterize_reference(*args)
    d = (img - img_r).abs()[4, 4].max().item()
    expected = 0.05 * 0.99 if gsplat_alpha_max() > ALPHA_MAX else 0.0
    assert d == pytest.approx(expected, abs=1e-5)


# ================================================================================== --device without a GPU
@pytest.fixture
def no_cuda():
    why = devices.cuda_unavailable_reason()
    if why is None:
        pytest.skip("this machine can run CUDA work")
    return why


def run_cli(*args, env_extra=None):
    env = {k: v for k, v in os.environ.items() if k != devices.ENV}
    env.update(PROXYCODEC_THREADS="1", **(env_extra or {}))
    return subprocess.run([sys.executable, "-c", "from proxycodec.cli.main import main; main()", *args],
                          check=False, capture_output=True, text=True, timeout=300, env=env)


def one_error_line(r) -> str:
    assert r.returncode == 2, (r.returncode, r.stderr)
    assert "Traceback" not in r.stderr, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, r.stderr
    return lines[0]


@pytest.mark.parametrize("command", [["sample", "{tmp}/x.ply"], ["render", "{tmp}/missing.ply"],
                                     ["fit", "{tmp}/no-dataset"]])
def test_device_cuda_without_a_gpu_is_one_line(no_cuda, tmp_path, command):
    r = run_cli("--device", "cuda", *[a.format(tmp=tmp_path) for a in command])
    line = one_error_line(r)
    assert line.startswith("error:") and "cuda" in line.lower(), line
    assert not (tmp_path / "x.ply").exists()  # nothing ran


def test_bogus_device_in_the_environment_is_one_line(tmp_path):
    r = run_cli("sample", str(tmp_path / "x.ply"), env_extra={devices.ENV: "bogus"})
    line = one_error_line(r)
    assert line.lower().startswith("error:") and "bogus" in line, line
    assert not (tmp_path / "x.ply").exists()


def test_resolve_without_a_gpu(no_cuda, monkeypatch):
    monkeypatch.delenv(devices.ENV, raising=False)
    assert devices.resolve("auto") == torch.device("cpu")
    assert devices.resolve() == torch.device("cpu")
    assert devices.resolve("cpu") == torch.device("cpu")
    with pytest.raises(ProxycodecError, match="cuda"):
        devices.resolve("cuda")
    monkeypatch.setenv(devices.ENV, "cuda")
    with pytest.raises(ProxycodecError):
        devices.resolve()
    monkeypatch.setenv(devices.ENV, "bogus")
    with pytest.raises(ProxycodecError, match="bogus"):
        devices.resolve()


# ====================================================================================== no hard-coded device
#: Folders of the package (pyproject's package-dir) and the one module allowed to name a device.
LIBRARY_FOLDERS = ("proxycodec", "formats", "cli")
ALLOWED = {"proxycodec/devices.py"}
DEVICE_LITERAL = ("cpu", "cuda")


def _is_device_literal(node) -> bool:
    if not (isinstance(node, ast.Constant) and isinstance(node.value, str)):
        return False
    v = node.value.strip().lower()
    return v in DEVICE_LITERAL or (v.startswith("cuda:") and v[5:].isdigit())


def _is_torch_device(func) -> bool:
    return isinstance(func, ast.Attribute) and func.attr == "device" and isinstance(func.value, ast.Name) \
        and func.value.id == "torch"


def hard_coded_devices(source: str, name: str = "<source>") -> list[str]:
    """``name:line: what`` for each place ``source`` names a device: a literal "cpu"/"cuda"/"cuda:N" as a
    ``device=`` keyword, as the first argument of ``torch.device(...)`` or as an argument of ``.to(...)``; any
    ``.cuda(...)`` call; ``torch.set_default_device(...)``. ``.cpu()`` (to host memory, for numpy or files) is fine."""
    out = []
    for node in ast.walk(ast.parse(source)):
        if not isinstance(node, ast.Call):
            continue
        f = node.func
        for kw in node.keywords:
            if kw.arg == "device" and _is_device_literal(kw.value):
                out.append((node.lineno, f"device={kw.value.value!r}"))
        if _is_torch_device(f) and node.args and _is_device_literal(node.args[0]):
            out.append((node.lineno, f"torch.device({node.args[0].value!r})"))
        if isinstance(f, ast.Attribute):
            if f.attr == "to" and any(_is_device_literal(a) for a in node.args):
                lit = next(a for a in node.args if _is_device_literal(a))
                out.append((node.lineno, f".to({lit.value!r})"))
            elif f.attr == "cuda":
                out.append((node.lineno, ".cuda()"))
            elif f.attr == "set_default_device":
                out.append((node.lineno, "set_default_device()"))
    return [f"{name}:{line}: {what}" for line, what in sorted(set(out))]


def library_sources(root: Path = REPO_ROOT) -> list[Path]:
    return [p for folder in LIBRARY_FOLDERS for p in sorted((root / folder).rglob("*.py"))
            if "__pycache__" not in p.parts]


def test_the_device_check_catches_each_pattern():
    bad = """import torch
a = torch.zeros(3, device="cuda")
b = torch.ones(2, device='cpu')
c = torch.device("cuda:1")
d = x.to("cuda")
e = x.to("cpu", non_blocking=True)
f = x.cuda()
torch.set_default_device(dev)
g = torch.Generator(device="cuda:0")
h = x.to(dtype=torch.float32, device="cpu")
i = torch.device('cpu', 0)
"""
    found = hard_coded_devices(bad, "m.py")
    assert [int(f.split(":")[1]) for f in found] == list(range(2, 12)), found
    ok = """import torch
a = torch.zeros(3, device=x.device)
b = x.cpu().numpy()
c = torch.device(devices.CPU)
d = x.to(device)
e = x.to(torch.float32)
f = torch.cuda.is_available()
g = torch.load(p, map_location=devices.CPU)
h = x.to(other.device, dtype=torch.float64)
if d.type == "cuda":
    torch.cuda.synchronize(d)
s = "cuda"
"""
    assert hard_coded_devices(ok) == []


def test_the_device_check_walks_the_library():
    files = {p.relative_to(REPO_ROOT).as_posix() for p in library_sources()}
    for f in ("proxycodec/devices.py", "proxycodec/render/cuda.py", "formats/container.py", "cli/main.py"):
        assert f in files, f
    assert not any("__pycache__" in f for f in files)


def test_no_hard_coded_device():
    bad = []
    for path in library_sources():
        rel = path.relative_to(REPO_ROOT).as_posix()
        if rel not in ALLOWED:
            bad += hard_coded_devices(path.read_text(encoding="utf-8"), rel)
    assert not bad, "devices named outside proxycodec/devices.py:\n" + "\n".join(bad)


def test_upload_gives_the_values_of_a_blocking_copy():
    """``devices.upload``: the dtype asked for, the values torch.as_tensor gives, on the device asked for."""
    from proxycodec.devices import upload

    a = np.array([[0.1, 2.0], [3.0, -4.5]])
    t = upload(a, torch.device("cpu"), torch.float32)
    assert t.dtype == torch.float32 and t.device.type == "cpu"
    assert torch.equal(t, torch.as_tensor(a, dtype=torch.float32))
    assert torch.equal(upload([1, 2, 3], torch.device("cpu")), torch.tensor([1, 2, 3]))
    m = upload(np.array([True, False]), torch.device("cpu"))
    assert m.dtype == torch.bool and m.tolist() == [True, False]
    if torch.cuda.is_available():
        g = upload(a, torch.device("cuda"), torch.float64)
        a[0, 0] = 99.0  # staged before the call returned
        assert g.cpu()[0, 0].item() == 0.1
