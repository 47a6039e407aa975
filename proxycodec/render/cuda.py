"""CUDA compositor through gsplat's tile rasterizer (``isect_tiles`` -> ``isect_offset_encode`` ->
``rasterize_to_pixels``), for CUDA tensors when gsplat is installed. Import-guarded: importing this module never
needs gsplat or a GPU.

Projection (EWA, dilation, gate, culling) stays in ``project.py``; gsplat only composites, so the gate is already in
``opacities``. gsplat's 3DGS kernel uses our semantics: pixel centres at (i + 0.5, j + 0.5), a Gaussian is skipped
where sigma = -power < 0 or alpha < 1/255, the pixel ends (uncounted) at the Gaussian that would take T to 1e-4,
background * final T, alpha = 1 - T, depth order by a stable radix sort on float32 depth bits (ties by row).
Known differences, all float32-level except the first:

* the alpha clamp: gsplat releases up to 1.5.x compile ``min(0.999f, ...)``, newer ones ``MAX_ALPHA 0.99f``; with
  0.999, pixels where opacity * G > 0.99 differ (they can only occur for gated opacity > 0.99). We read the value
  from the installed sources (``gsplat_alpha_max``) and warn once when it is not 0.99;
* the stop test is ``next_T <= 1e-4`` (ours ``< 1e-4``): only exact equality differs;
* float32 throughout with ``__expf``; float64 inputs are rendered in float32 and cast back; depths that differ only
  beyond float32 precision tie (and go by row).
"""

from __future__ import annotations

import functools
import re
import warnings
from pathlib import Path

import torch

from ..errors import ProxycodecError
from .project import ALPHA_MAX

TILE = 16


def gsplat_available() -> bool:
    """True when gsplat imports and a CUDA device is present."""
    try:
        import gsplat  # noqa: F401
    except ImportError:
        return False
    return torch.cuda.is_available()


@functools.lru_cache(maxsize=1)
def gsplat_alpha_max() -> float | None:
    """The alpha clamp compiled into the installed gsplat, read from its CUDA sources; None when not found."""
    import gsplat

    root = Path(gsplat.__file__).parent / "cuda"
    for header in (root / "include" / "Common.h", root / "csrc" / "Common.h"):
        if header.is_file():
            m = re.search(r"#define\s+MAX_ALPHA\s+([0-9.]+)f?", header.read_text(errors="replace"))
            if m:
                return float(m.group(1))
    for src in sorted(root.rglob("*.cu")):
        if "RasterizeToPixels" in src.name or "rasterize_to_pixels" in src.name:
            m = re.search(r"min\(\s*([0-9.]+)f\s*,\s*opac", src.read_text(errors="replace"))
            if m:
                return float(m.group(1))
    return None


@functools.lru_cache(maxsize=1)
def _check_semantics() -> None:
    amax = gsplat_alpha_max()
    if amax is None or abs(amax - ALPHA_MAX) > 1e-9:
        warnings.warn(f"gsplat clamps alpha at {amax if amax is not None else 'an unknown value'}, proxycodec at "
                      f"{ALPHA_MAX}: pixels where opacity * G > {ALPHA_MAX} differ from the reference backend",
                      RuntimeWarning, stacklevel=3)


def _isect(means2d, radii, depths, tiles_x, tiles_y):
    """gsplat.isect_tiles across its API versions: radii [C, N, 2] (gsplat >= 1.5) or [C, N] (earlier)."""
    from gsplat import isect_tiles

    try:
        return isect_tiles(means2d, radii, depths, TILE, tiles_x, tiles_y)
    except (AssertionError, RuntimeError, TypeError, ValueError):
        return isect_tiles(means2d, radii.amax(-1), depths, TILE, tiles_x, tiles_y)


def rasterize_cuda(
    means2d: torch.Tensor,  # [N, 2]
    conics: torch.Tensor,  # [N, 3]
    opacities: torch.Tensor,  # [N]
    colors: torch.Tensor,  # [N, C]
    depths: torch.Tensor,  # [N]
    extent: torch.Tensor,  # [N, 2]
    width: int,
    height: int,
    background: torch.Tensor,  # [C]
) -> tuple[torch.Tensor, torch.Tensor]:
    """-> (image [H, W, C], alpha [H, W]) on the CUDA device; gradients through gsplat's backward."""
    if not gsplat_available():
        raise ProxycodecError("the cuda backend needs gsplat (pip install gsplat) and a CUDA device")
    if means2d.device.type != "cuda":
        raise ProxycodecError(f"the cuda backend renders CUDA tensors, got {means2d.device}")
    from gsplat import isect_offset_encode, rasterize_to_pixels

    _check_semantics()
    dt = means2d.dtype
    n, nch = colors.shape
    bg = background.to(device=means2d.device, dtype=torch.float32).reshape(-1).expand(nch)
    if n == 0:
        img = bg.expand(height, width, nch).clone()
        return img.to(dt), torch.zeros(height, width, dtype=dt, device=means2d.device)
    tiles_x, tiles_y = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
    m = means2d.float().contiguous()[None]  # [1, N, 2]
    # integer radii >= our conservative extent: gsplat lists tiles floor((m - r)/16) .. ceil((m + r)/16) - 1
    radii = torch.ceil(extent.detach().float()).clamp(1, 1 << 20).to(torch.int32)[None]  # [1, N, 2]
    _, isect_ids, flatten_ids = _isect(m.detach(), radii.contiguous(), depths.detach().float()[None].contiguous(),
                                       tiles_x, tiles_y)
    offsets = isect_offset_encode(isect_ids, 1, tiles_x, tiles_y)  # [1, tiles_y, tiles_x]
    img, alpha = rasterize_to_pixels(
        m, conics.float().contiguous()[None], colors.float().contiguous()[None], opacities.float().contiguous()[None],
        width, height, TILE, offsets, flatten_ids, backgrounds=bg.contiguous()[None],
    )  # [1, H, W, C], [1, H, W, 1]
    return img[0].to(dt), alpha[0, ..., 0].to(dt)
