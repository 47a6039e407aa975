"""CUDA compositor through gsplat's tile rasterizer (``isect_tiles`` -> ``isect_offset_encode`` ->
``rasterize_to_pixels``), for CUDA tensors when gsplat is installed. Import-guarded: importing this module never
needs gsplat or a GPU.

Projection (EWA, dilation, gate, culling) stays in ``project.py``; gsplat only composites, so the gate is already in
``opacities``. gsplat's 3DGS kernel uses our semantics: pixel centres at (i + 0.5, j + 0.5), a Gaussian is skipped
where sigma = -power < 0 or alpha < 1/255, the pixel ends (uncounted) at the Gaussian that would take T to 1e-4,
background * final T, alpha = 1 - T, depth order by a stable radix sort on float32 depth bits (ties by row).
Known differences, all float32-level except the first:

* **the alpha clamp.** gsplat up to 1.5.x compiles ``alpha = min(0.999f, o * exp(power))``, newer releases
  ``MAX_ALPHA`` = 0.99f; the reference takes ``min(0.99, o e)`` (``ALPHA_MAX``), e = exp(power) in (0, 1].
  ``gsplat_alpha_max`` reads the installed value; with 0.99 there is no difference. With 0.999 the opacities are
  passed **as they are**, and the difference is exactly this:

  - where o e <= 0.99, alpha and its partial derivatives are the reference's (gsplat's backward passes them where
    ``o e <= 0.999``), so a pixel that no *core* reaches is composited exactly as the reference does, gradients
    included: every pixel, when no gated opacity exceeds 0.99;
  - the core of a Gaussian with o > 0.99 is the set of pixels where o e > 0.99 (Mahalanobis m^2 < 2 ln(o / 0.99)
    <= 0.0201: within 0.142 sigma of its centre). There alpha is min(0.999, o e) instead of 0.99: larger by at most
    min(o, 0.999) - 0.99 <= 0.009, the transmittance behind it up to 10x smaller, and where o e <= 0.999 it passes
    gradients to o, the mean and the conic that the reference's clamp stops. With T_k the transmittance in front of
    the first core a pixel reaches, its colour and alpha differ by at most 0.01 T_k (colours and background in
    [0, 1]: behind the core both are 0.99 or more of that core's colour), except where gsplat ends the pixel at that
    Gaussian, T_k (1 - alpha) <= 1e-4, while the reference composites it, T_k >= 0.01: there by at most T_k <= 0.1
    (a Gaussian of opacity 0.999 behind one of 0.95, colour 0 on a white background: 0.0495).

  Passing ``opacities.clamp(max=0.99)`` instead was measured and rejected: alpha = min(0.99, o) e equals the
  reference's where o <= 0.99 -- as the unclamped one does -- and for o > 0.99 it is 0.99 e instead of min(0.99, o e)
  over the Gaussian's *whole* footprint (smaller by (o - 0.99) e outside the core, 0.99 (1 - e) inside, at most
  0.99 (o - 0.99) / o < 0.01), and d alpha / d o = 0 at every pixel: such a Gaussian gets no opacity gradient at
  all (the reference gives e at every pixel outside its core), a trap for tanh/sigmoid opacities that saturate.
  On the built-in sample scene at 128 x 96 (opacity tanh(3) = 0.995, 6.9 % of the gated opacities above 0.99;
  float64 emulation of both rules) the image differs from the reference by 3.5e-6 at most as gsplat clamps, by
  6.1e-3 (PSNR 76 dB) with clamped opacities, whose opacity gradient is then 58 % off (relative norm).
  ``tests/test_devices.py`` emulates both rules with the reference compositor and checks these statements; the
  warning (once per process, ``_check_semantics``) stays because the core difference remains;
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
    """The alpha clamp compiled into the installed gsplat, read from its CUDA sources; None when not found.

    A ``#define MAX_ALPHA`` in its ``Common.h`` (newer releases) wins; else the ``min(<value>f, opac`` of the 3DGS
    forward kernel (``RasterizeToPixels3DGSFwd.cu`` in 1.5.x), then of any ``RasterizeToPixels`` source."""
    import gsplat

    return alpha_max_in_sources(Path(gsplat.__file__).parent / "cuda")


def alpha_max_in_sources(root: Path) -> float | None:
    """``gsplat_alpha_max`` for a gsplat ``cuda`` source folder ``root``."""
    for header in (root / "include" / "Common.h", root / "csrc" / "Common.h"):
        if header.is_file():
            m = re.search(r"#define\s+MAX_ALPHA\s+([0-9.]+)f?", header.read_text(errors="replace"))
            if m:
                return float(m.group(1))
    sources = [p for p in sorted(root.rglob("*.cu"))
               if "RasterizeToPixels" in p.name or "rasterize_to_pixels" in p.name]
    sources.sort(key=lambda p: ("3DGS" not in p.name and "3dgs" not in p.name, "Fwd" not in p.name
                                and "fwd" not in p.name, "World" in p.name, p.name))
    for src in sources:
        m = re.search(r"min\(\s*([0-9.]+)f\s*,\s*opac", src.read_text(errors="replace"))
        if m:
            return float(m.group(1))
    return None


@functools.lru_cache(maxsize=1)
def _check_semantics() -> None:
    """Warn once when the installed gsplat's alpha clamp is not ``ALPHA_MAX`` (the module docstring: the difference
    is confined to the cores of Gaussians with opacity above 0.99, but there it can reach 0.1 in a pixel)."""
    amax = gsplat_alpha_max()
    if amax is None or abs(amax - ALPHA_MAX) > 1e-9:
        what = f"at {amax}" if amax is not None else "at a value not found in its sources"
        warnings.warn(f"gsplat clamps alpha {what}, proxycodec at {ALPHA_MAX}: pixels where a Gaussian's "
                      f"opacity * G > {ALPHA_MAX} (only Gaussians of opacity > {ALPHA_MAX}, within 0.14 sigma of "
                      f"their centre) differ from the reference backend (see proxycodec.render.cuda)",
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
