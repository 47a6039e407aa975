"""Image quality metrics: PSNR, SSIM (scikit-image for evaluation, a differentiable torch SSIM for the loss), D-SSIM.

Images are float RGB in [0, 1], shaped [H, W, 3] (numpy or torch). Evaluation numbers use scikit-image's
``structural_similarity(channel_axis=-1, data_range=1.0)`` with its defaults (7x7 uniform window), the loss uses the
3DGS/Scaffold-GS SSIM (11x11 Gaussian window, sigma 1.5, zero padding) so that training matches those papers.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

__all__ = ["dssim", "l1", "mse_to_psnr", "psnr", "ssim", "ssim_torch"]


def _np(img) -> np.ndarray:
    if isinstance(img, torch.Tensor):
        img = img.detach().cpu().numpy()
    return np.asarray(img, dtype=np.float64)


def mse_to_psnr(mse: float, data_range: float = 1.0) -> float:
    """PSNR in dB of a mean squared error; ``inf`` for a perfect match."""
    mse = float(mse)
    if mse <= 0.0:
        return math.inf
    return 10.0 * math.log10(data_range * data_range / mse)


def psnr(a, b, data_range: float = 1.0) -> float:
    """PSNR (dB) between two images of the same shape (values are not clipped)."""
    a, b = _np(a), _np(b)
    if a.shape != b.shape:
        raise ValueError(f"psnr: shapes differ {a.shape} vs {b.shape}")
    return mse_to_psnr(float(np.mean((a - b) ** 2)), data_range)


def ssim(a, b, data_range: float = 1.0) -> float | None:
    """Mean SSIM of two [H, W, 3] images via ``skimage.metrics.structural_similarity``.

    scikit-image needs a window of at least 3 pixels no larger than the image: for images smaller than its default
    7x7 window the largest odd window that fits is used; below 3x3 SSIM is undefined and ``None`` is returned.
    """
    from skimage.metrics import structural_similarity

    a, b = _np(a), _np(b)
    if a.shape != b.shape:
        raise ValueError(f"ssim: shapes differ {a.shape} vs {b.shape}")
    side = min(a.shape[0], a.shape[1])
    if side < 3:
        return None
    win = min(7, side if side % 2 == 1 else side - 1)
    return float(structural_similarity(a, b, channel_axis=-1, data_range=data_range, win_size=win))


_WINDOWS: dict[tuple, torch.Tensor] = {}


def _gauss_1d(size: int, sigma: float, dtype, device) -> torch.Tensor:
    key = (size, sigma, dtype, str(device))
    w = _WINDOWS.get(key)
    if w is None:
        x = torch.arange(size, dtype=torch.float64) - size // 2
        g = torch.exp(-(x * x) / (2 * sigma * sigma))
        w = (g / g.sum()).to(dtype=dtype, device=device)
        _WINDOWS[key] = w
    return w


def _blur(x: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """Separable Gaussian filter of [1, C, H, W] with zero padding (= the 2D window g g^T)."""
    C, k = x.shape[1], g.numel()
    x = F.conv2d(x, g.reshape(1, 1, k, 1).expand(C, 1, k, 1), padding=(k // 2, 0), groups=C)
    return F.conv2d(x, g.reshape(1, 1, 1, k).expand(C, 1, 1, k), padding=(0, k // 2), groups=C)


def ssim_torch(a: torch.Tensor, b: torch.Tensor, window: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Differentiable mean SSIM of [H, W, C] images (3DGS's ``ssim``: 11x11 Gaussian window, zero padding)."""
    x = a.permute(2, 0, 1)[None]
    y = b.permute(2, 0, 1)[None]
    C = x.shape[1]
    g = _gauss_1d(window, sigma, x.dtype, x.device)
    stats = _blur(torch.cat([x, y, x * x, y * y, x * y], 1), g)
    mu_x, mu_y, e_xx, e_yy, e_xy = stats.split(C, 1)
    mu_x2, mu_y2, mu_xy = mu_x * mu_x, mu_y * mu_y, mu_x * mu_y
    s_x, s_y, s_xy = e_xx - mu_x2, e_yy - mu_y2, e_xy - mu_xy
    C1, C2 = 0.01**2, 0.03**2
    m = ((2 * mu_xy + C1) * (2 * s_xy + C2)) / ((mu_x2 + mu_y2 + C1) * (s_x + s_y + C2))
    return m.mean()


def dssim(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """D-SSIM as 3DGS and Scaffold-GS use it in the loss: 1 - SSIM."""
    return 1.0 - ssim_torch(a, b)


def l1(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return (a - b).abs().mean()
