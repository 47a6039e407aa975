"""Fast CPU compositor: a numba tile rasterizer with an analytic backward (issue #3).

Same 2D interface and exactly the same compositing semantics as ``reference.rasterize_reference`` (its docstring is
the spec): pixel centres at (i + 0.5, j + 0.5); Gaussians in ascending depth, ties by input row (a stable sort);
power > 0 or alpha = min(0.99, o exp(power)) < 1/255 skips; the Gaussian that would push the transmittance below
1e-4 ends the pixel uncounted; background * final T; output alpha = 1 - T.

Pipeline (all numba, parallel over Gaussians or over 16x16 tiles):

1. binning: a Gaussian is listed in a tile when the tile passes the reference's own test on the ``extent`` box
   (same comparisons, same floats, so exactly the reference's tile lists) AND the tile holds a pixel centre inside
   the Gaussian's alpha >= 1/255 ellipse, evaluated from the conic with a safety margin (a tighter, still
   conservative, list: a Gaussian it drops contributes nothing to any pixel of that tile). Counting sort: count per
   Gaussian, prefix sum, fill, then a stable parallel counting sort by tile of the Gaussian-major list. Gaussians
   are visited in (depth, row) order, so each tile's list comes out already sorted like the reference's.
2. forward, parallel over tiles: each Gaussian of the tile list (front to back) visits only the pixels of its
   ellipse's scanlines inside the tile; per-pixel state (T, colour, done) lives in tile-local buffers. The decisive
   quantities (power, alpha, the 1/255 and 1e-4 tests) are computed with the reference's operations in the input
   dtype; transmittance and colour accumulate in float64 (as torch's CPU cumprod does), so float32 inputs make the
   same skip/stop decisions as the float32 reference up to 1-ulp differences of exp.
3. backward, parallel over tiles: the 3DGS back-to-front walk from the final T and the last contributor, per-pixel
   suffix colour R; each (tile, Gaussian) pair owns one row of a gradient buffer (no races, deterministic), then a
   parallel per-Gaussian reduction.

Work follows what a view needs: tiles nobody touches only get the background written.
"""

from __future__ import annotations

import numpy as np
import torch

# The kernels and their numpy driver live in a torch-free module (the torch-free decode path calls them directly).
from ._raster_kernels import (
    N_GRAD,
    backward_tiles,
    Binned,
    per_tile_threads,
    reduce_rows,
    bin_gaussians,
    depth_order,
    rasterize_forward,
    threads_for,
)


def _depth_order(depths: torch.Tensor) -> torch.Tensor:
    """``torch.sort(depths, stable=True).indices`` (the reference's order): ``_raster_kernels.depth_order``."""
    return torch.from_numpy(depth_order(depths.detach().numpy()))


def _bin(means2d, conics, opacities, colors, depths, extent, width, height) -> Binned:
    """Inputs: CPU tensors, means2d/conics/opacities/colors contiguous in one float dtype (the compute dtype)."""
    return bin_gaussians(means2d.detach().numpy(), conics.detach().numpy(), opacities.detach().numpy(),
                         colors.detach().numpy(), depths.detach().numpy(), extent.detach().contiguous().numpy(),
                         width, height)


class _RasterizeCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, depths, extent, width, height, background):
        n, nch = colors.shape
        dt = means2d.dtype
        bg64 = background.detach().to(torch.float64).reshape(-1).expand(nch).contiguous().numpy()
        ctx.width, ctx.height, ctx.n, ctx.nch = width, height, n, nch
        ctx.bg_shape = background.shape
        ctx.bg64 = bg64
        if n == 0:
            ctx.binned = None
            img = torch.from_numpy(np.broadcast_to(bg64, (height, width, nch)).copy()).to(dt)
            return img, torch.zeros(height, width, dtype=dt)
        img, alpha, t_fin, nc, b = rasterize_forward(
            means2d.detach().numpy(), conics.detach().numpy(), opacities.detach().numpy(), colors.detach().numpy(),
            depths.detach().numpy(), extent.detach().contiguous().numpy(), width, height, bg64)
        ctx.binned, ctx.t_fin, ctx.nc = b, t_fin, nc
        return torch.from_numpy(img), torch.from_numpy(alpha)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_img, grad_alpha):
        width, height, n, nch = ctx.width, ctx.height, ctx.n, ctx.nch
        b = ctx.binned
        dt = grad_img.dtype if grad_img is not None else grad_alpha.dtype
        g_img = (np.zeros((height, width, nch)) if grad_img is None
                 else np.ascontiguousarray(grad_img.to(torch.float64).numpy()))
        g_alpha = (np.zeros((height, width)) if grad_alpha is None
                   else np.ascontiguousarray(grad_alpha.to(torch.float64).numpy()))
        g_bg = None
        if ctx.needs_input_grad[8]:
            t_fin = ctx.t_fin if b is not None else np.ones((height, width))
            gb = torch.from_numpy(np.einsum("hwc,hw->c", g_img, t_fin))
            shape = ctx.bg_shape
            g_bg = (gb.sum() if gb.numel() != 1 and int(np.prod(shape)) == 1 else gb).reshape(shape).to(dt)
        if b is None:
            return (torch.zeros(0, 2, dtype=dt), torch.zeros(0, 3, dtype=dt), torch.zeros(0, dtype=dt),
                    torch.zeros(0, nch, dtype=dt), None, None, None, None, g_bg)
        gbuf = np.zeros((b.n_isect, N_GRAD + nch), np.float64)
        out = np.empty((n, N_GRAD + nch), b.mxy.dtype)
        with threads_for(n + width * height):
            with per_tile_threads():
                backward_tiles(b.tile_off, b.tile_order, b.isect_g, b.tm_gm, b.geo, b.mxy, b.con, b.op, b.col, b.pcx,
                          b.pcy, b.k_dt, ctx.bg64, width, height, b.tiles_x, ctx.t_fin, ctx.nc, g_img, g_alpha, gbuf)
            reduce_rows(b.goff, b.order, gbuf, out)
        grads = torch.from_numpy(out)
        return (grads[:, 0:2], grads[:, 2:5], grads[:, 5], grads[:, N_GRAD:], None, None, None, None, g_bg)


def rasterize_cpu(
    means2d: torch.Tensor,  # [N, 2]
    conics: torch.Tensor,  # [N, 3]
    opacities: torch.Tensor,  # [N]
    colors: torch.Tensor,  # [N, C]
    depths: torch.Tensor,  # [N]
    extent: torch.Tensor,  # [N, 2]
    width: int,
    height: int,
    background: torch.Tensor,  # [C] (or one value for all channels)
) -> tuple[torch.Tensor, torch.Tensor]:
    """-> (image [H, W, C], alpha [H, W]), differentiable in means2d, conics, opacities, colors and background.

    Computes in float64 when means2d is float64, else in float32. Runs on the CPU; tensors on another device are
    copied here and the results go back there.
    """
    dev = means2d.device
    dt = torch.float64 if means2d.dtype == torch.float64 else torch.float32

    def prep(x):  # the kernels' explicit transfer: a no-op for CPU tensors
        return x.cpu().to(dtype=dt).contiguous()

    if colors.dim() != 2 or means2d.shape != (colors.shape[0], 2):
        raise ValueError(f"rasterize_cpu: means2d {tuple(means2d.shape)} / colors {tuple(colors.shape)} mismatch")
    background = torch.as_tensor(background, device=means2d.device)
    img, alpha = _RasterizeCPU.apply(prep(means2d), prep(conics), prep(opacities), prep(colors),
                                     depths.detach().cpu(), extent.detach().cpu(), int(width), int(height),
                                     prep(background))
    return img.to(dev), alpha.to(dev)
