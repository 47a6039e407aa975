"""Reference compositor in pure PyTorch: the oracle every faster backend is tested against.

Clarity over speed. Differentiable through autograd, device-agnostic. The semantics (shared by all backends):
for each pixel centre p, Gaussians in ascending depth order (ties by input row), alpha_i = min(0.99, o_i exp(power_i))
with power_i = -0.5 (a dx^2 + c dy^2) - b dx dy; a Gaussian is skipped where power > 0 or alpha_i < 1/255; it is
composited while the transmittance after it stays >= 1e-4 (the first one that would push it lower ends the pixel,
uncounted, as in 3DGS); the background fills the remaining transmittance.
"""

from __future__ import annotations

import torch

from .project import ALPHA_MAX, ALPHA_MIN, T_MIN

TILE = 16


def composite_pixels(
    pix: torch.Tensor,  # [P, 2] pixel centres
    means2d: torch.Tensor,  # [n, 2] depth-sorted
    conics: torch.Tensor,  # [n, 3]
    opacities: torch.Tensor,  # [n]
    colors: torch.Tensor,  # [n, C]
    background: torch.Tensor,  # [C]
) -> tuple[torch.Tensor, torch.Tensor]:
    """Composite depth-sorted Gaussians over a set of pixels -> (color [P, C], transmittance [P])."""
    d = pix[:, None, :] - means2d[None, :, :]  # [P, n, 2]
    dx, dy = d[..., 0], d[..., 1]
    power = -0.5 * (conics[:, 0] * dx * dx + conics[:, 2] * dy * dy) - conics[:, 1] * dx * dy
    alpha = torch.clamp(opacities * torch.exp(torch.clamp(power, max=0.0)), max=ALPHA_MAX)
    alpha = torch.where((power <= 0) & (alpha >= ALPHA_MIN), alpha, torch.zeros_like(alpha))
    with torch.no_grad():  # early termination: transmittance is non-increasing, so this keeps a prefix
        include = torch.cumprod(1.0 - alpha, dim=1) >= T_MIN
    alpha = alpha * include
    one_minus = 1.0 - alpha
    T_before = torch.cumprod(torch.cat([torch.ones_like(one_minus[:, :1]), one_minus[:, :-1]], 1), 1)
    weights = alpha * T_before  # [P, n]
    T_final = T_before[:, -1] * one_minus[:, -1] if alpha.shape[1] else torch.ones_like(pix[:, 0])
    color = weights @ colors + T_final[:, None] * background
    return color, T_final


def rasterize_reference(
    means2d: torch.Tensor,
    conics: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    depths: torch.Tensor,
    extent: torch.Tensor,
    width: int,
    height: int,
    background: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """-> (image [H, W, C], alpha [H, W]). Tiled only to bound memory; tiles do not change the result."""
    dev, dt = means2d.device, means2d.dtype
    C = colors.shape[1]
    order = torch.sort(depths, stable=True).indices
    means2d, conics, opacities, colors = means2d[order], conics[order], opacities[order], colors[order]
    ext = extent[order]
    lo, hi = means2d.detach() - ext, means2d.detach() + ext
    rows = []
    for y0 in range(0, height, TILE):
        y1 = min(y0 + TILE, height)
        row = []
        for x0 in range(0, width, TILE):
            x1 = min(x0 + TILE, width)
            hit = (hi[:, 0] > x0) & (lo[:, 0] < x1) & (hi[:, 1] > y0) & (lo[:, 1] < y1)
            ids = hit.nonzero().squeeze(1)
            ys, xs = torch.meshgrid(
                torch.arange(y0, y1, device=dev, dtype=dt) + 0.5,
                torch.arange(x0, x1, device=dev, dtype=dt) + 0.5,
                indexing="ij",
            )
            pix = torch.stack([xs.reshape(-1), ys.reshape(-1)], -1)
            col, T = composite_pixels(pix, means2d[ids], conics[ids], opacities[ids], colors[ids], background)
            row.append(torch.cat([col, (1 - T)[:, None]], 1).reshape(y1 - y0, x1 - x0, C + 1))
        rows.append(torch.cat(row, 1))
    out = torch.cat(rows, 0)
    return out[..., :C], out[..., C]
