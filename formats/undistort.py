"""Undistortion of COLMAP's radial camera models to a pinhole camera, as ``colmap image_undistorter`` does.

Models: ``SIMPLE_RADIAL``, ``RADIAL``, ``OPENCV``, ``FULL_OPENCV`` (the non-fisheye ones). The distortion
functions are COLMAP's (``src/colmap/sensor/models.h``): a point ``(u, v)`` on the normalised image plane
(``z = 1``) is distorted to ``(u + du, v + dv)`` and then mapped to pixels with ``f * . + c``, pixel centres at
``+0.5`` (COLMAP's, and :class:`~proxycodec.camera.Camera`'s, convention).

**Output camera** (:meth:`DistortedCamera.pinhole`): same width, height and principal point; focal lengths
``s * fx``, ``s * fy`` with one scale ``s`` (square pixels stay square), the smallest for which every output pixel
centre maps inside the source image's pixel-centre rectangle ``[0.5, W - 0.5] x [0.5, H - 0.5]`` (where bilinear
interpolation needs no extrapolation). That is COLMAP's default ``blank_pixels = 0``: no black border, as little
field of view cropped as possible. COLMAP keeps ``f`` and changes the image size by per-axis scales; keeping the
size instead (so datasets keep their file sizes and ``images_N`` folders) with one scale crops at most a few pixels
more along one axis. ``s`` is found by sampling every output border pixel centre: a geometric scan down from
``s = 4`` to the first invalid scale, then bisection; a sample only counts as inside where the distortion is locally
invertible (positive Jacobian determinant), so a distortion that folds back on itself cannot fake validity.

**Remapping** (:class:`Undistorter`): the source position of every output pixel centre is computed once per
distinct camera in float64 and kept (as a flat int32 index plus float32 bilinear weights, 12 bytes per pixel) in
a byte-bounded LRU :class:`RemapCache`; images are then resampled bilinearly in vectorised numpy. Everything is
deterministic.
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from ..errors import ProxycodecError

__all__ = [
    "UNDISTORTABLE_MODELS",
    "DistortedCamera",
    "RemapCache",
    "Undistorter",
    "distortion",
    "distort",
    "undistort",
]

#: model -> (number of parameters, indices of fx, fy, cx, cy; the rest are distortion coefficients).
UNDISTORTABLE_MODELS: dict[str, tuple[int, tuple[int, int, int, int]]] = {
    "SIMPLE_RADIAL": (4, (0, 0, 1, 2)),  # f, cx, cy, k
    "RADIAL": (5, (0, 0, 1, 2)),  # f, cx, cy, k1, k2
    "OPENCV": (8, (0, 1, 2, 3)),  # fx, fy, cx, cy, k1, k2, p1, p2
    "FULL_OPENCV": (12, (0, 1, 2, 3)),  # fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6
}
_N_EXTRA = {m: n - len(set(idx)) for m, (n, idx) in UNDISTORTABLE_MODELS.items()}

#: Default byte budget of a dataset's remap cache (a 720x1280 map takes 11 MB).
DEFAULT_REMAP_CACHE_BYTES = 64 * 1024 * 1024

_S_MAX = 4.0  # largest focal scale considered (COLMAP clamps its size scale to [0.2, 2])
_S_MIN = 0.25
_SCAN = 2.0 ** (1.0 / 8.0)  # geometric scan step


def _check_extra(model: str, extra) -> np.ndarray:
    if model not in _N_EXTRA:
        raise ProxycodecError(
            f"cannot undistort the {model} model (only {', '.join(UNDISTORTABLE_MODELS)})"
        )
    e = np.asarray(extra, dtype=np.float64).reshape(-1)
    if e.shape[0] != _N_EXTRA[model] or not np.isfinite(e).all():
        raise ProxycodecError(f"the {model} model needs {_N_EXTRA[model]} finite distortion coefficients")
    return e


def distortion(model: str, extra, u, v) -> tuple[np.ndarray, np.ndarray]:
    """COLMAP's ``Distortion(extra_params, u, v, &du, &dv)``: the offset that distortion adds to a point of the
    normalised image plane (float64 arrays broadcast together)."""
    e = _check_extra(model, extra)
    u = np.asarray(u, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    u2 = u * u
    v2 = v * v
    r2 = u2 + v2
    if model == "SIMPLE_RADIAL":
        radial = e[0] * r2
        return u * radial, v * radial
    if model == "RADIAL":
        radial = e[0] * r2 + e[1] * r2 * r2
        return u * radial, v * radial
    uv = u * v
    if model == "OPENCV":
        k1, k2, p1, p2 = e
        radial = k1 * r2 + k2 * r2 * r2
        du = u * radial + 2.0 * p1 * uv + p2 * (r2 + 2.0 * u2)
        dv = v * radial + 2.0 * p2 * uv + p1 * (r2 + 2.0 * v2)
        return du, dv
    # FULL_OPENCV
    k1, k2, p1, p2, k3, k4, k5, k6 = e
    r4 = r2 * r2
    r6 = r4 * r2
    radial = (1.0 + k1 * r2 + k2 * r4 + k3 * r6) / (1.0 + k4 * r2 + k5 * r4 + k6 * r6)
    du = u * radial + 2.0 * p1 * uv + p2 * (r2 + 2.0 * u2) - u
    dv = v * radial + 2.0 * p2 * uv + p1 * (r2 + 2.0 * v2) - v
    return du, dv


def distort(model: str, extra, u, v) -> tuple[np.ndarray, np.ndarray]:
    """Undistorted normalised coordinates -> distorted ones: ``(u + du, v + dv)``."""
    du, dv = distortion(model, extra, u, v)
    return np.asarray(u, dtype=np.float64) + du, np.asarray(v, dtype=np.float64) + dv


def _jacobian(model: str, e: np.ndarray, u: np.ndarray, v: np.ndarray):
    """Analytic Jacobian of :func:`distort`: (d xd/du, d xd/dv (= d yd/du), d yd/dv).

    Every model is ``xd = u (1 + g(r2)) + 2 p1 u v + p2 (r2 + 2 u^2)`` (and alike for ``yd``) for some radial
    ``g`` and tangential ``p1, p2`` (zero for the radial-only models)."""
    r2 = u * u + v * v
    if model == "SIMPLE_RADIAL":
        g, dg, p1, p2 = e[0] * r2, e[0], 0.0, 0.0
    elif model == "RADIAL":
        g, dg, p1, p2 = e[0] * r2 + e[1] * r2 * r2, e[0] + 2.0 * e[1] * r2, 0.0, 0.0
    elif model == "OPENCV":
        k1, k2, p1, p2 = e
        g, dg = k1 * r2 + k2 * r2 * r2, k1 + 2.0 * k2 * r2
    else:
        k1, k2, p1, p2, k3, k4, k5, k6 = e
        num = 1.0 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
        den = 1.0 + k4 * r2 + k5 * r2 * r2 + k6 * r2 * r2 * r2
        dnum = k1 + 2.0 * k2 * r2 + 3.0 * k3 * r2 * r2
        dden = k4 + 2.0 * k5 * r2 + 3.0 * k6 * r2 * r2
        g = num / den - 1.0
        dg = (dnum * den - num * dden) / (den * den)
    a = 1.0 + g + 2.0 * u * u * dg + 2.0 * p1 * v + 6.0 * p2 * u
    b = 2.0 * u * v * dg + 2.0 * p1 * u + 2.0 * p2 * v
    d = 1.0 + g + 2.0 * v * v * dg + 2.0 * p2 * u + 6.0 * p1 * v
    return a, b, d


def undistort(model: str, extra, ud, vd, *, iterations: int = 100) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`distort` by Newton's method (COLMAP's ``IterativeUndistortion``, with the analytic
    Jacobian instead of central differences), vectorised; starts at the distorted point. Where the distortion is
    not invertible (outside its monotone region) the result is whatever Newton reaches."""
    e = _check_extra(model, extra)
    xd = np.asarray(ud, dtype=np.float64)
    yd = np.asarray(vd, dtype=np.float64)
    xd, yd = np.broadcast_arrays(xd, yd)
    u, v = xd.copy(), yd.copy()
    with np.errstate(all="ignore"):
        for _ in range(int(iterations)):
            fu, fv = distort(model, e, u, v)
            ru, rv = fu - xd, fv - yd
            a, b, d = _jacobian(model, e, u, v)
            det = a * d - b * b
            su = (d * ru - b * rv) / det
            sv = (a * rv - b * ru) / det
            ok = np.isfinite(su) & np.isfinite(sv)
            u = np.where(ok, u - su, u)
            v = np.where(ok, v - sv, v)
            step = np.where(ok, np.abs(su) + np.abs(sv), 0.0)
            if not step.size or float(step.max()) <= 1e-15 * max(1.0, float(np.abs(u).max() + np.abs(v).max())):
                break
    return u, v


@dataclass(frozen=True)
class DistortedCamera:
    """A COLMAP radial camera at the size of its image files (hashable: equal cameras share a pixel map)."""

    model: str
    fx: float
    fy: float
    cx: float
    cy: float
    extra: tuple[float, ...]
    width: int
    height: int

    @staticmethod
    def from_colmap(model: str, params, width: int, height: int, size: tuple[int, int] | None = None):
        """From COLMAP's parameter vector; ``size`` (the image files' width, height) scales the intrinsics per
        axis (distortion acts on normalised coordinates, so its coefficients do not change)."""
        if model not in UNDISTORTABLE_MODELS:
            raise ProxycodecError(f"cannot undistort the {model} model (only {', '.join(UNDISTORTABLE_MODELS)})")
        n, (ifx, ify, icx, icy) = UNDISTORTABLE_MODELS[model]
        p = np.asarray(params, dtype=np.float64)
        if p.shape != (n,):
            raise ProxycodecError(f"the {model} model needs {n} parameters, got {p.shape[0]}")
        w, h = (int(width), int(height)) if size is None else (int(size[0]), int(size[1]))
        sx, sy = w / int(width), h / int(height)
        extra = tuple(float(x) for x in p[len({ifx, ify, icx, icy}) :])
        return DistortedCamera(model, float(p[ifx]) * sx, float(p[ify]) * sy, float(p[icx]) * sx,
                               float(p[icy]) * sy, extra, w, h)

    def __post_init__(self) -> None:
        _check_extra(self.model, self.extra)
        if not all(math.isfinite(x) for x in (self.fx, self.fy, self.cx, self.cy)) or self.fx <= 0 or self.fy <= 0:
            raise ProxycodecError(f"{self.model} camera has invalid intrinsics")
        if self.width < 2 or self.height < 2:
            raise ProxycodecError(f"cannot undistort a {self.width}x{self.height} image (needs at least 2x2)")

    # ------------------------------------------------------------------ geometry
    def source_pixels(self, x, y, scale: float) -> tuple[np.ndarray, np.ndarray]:
        """Pixel positions (+0.5 convention) ``x, y`` of the output camera with focal scale ``scale`` -> their
        positions in the distorted source image."""
        u = (np.asarray(x, dtype=np.float64) - self.cx) / (scale * self.fx)
        v = (np.asarray(y, dtype=np.float64) - self.cy) / (scale * self.fy)
        ud, vd = distort(self.model, self.extra, u, v)
        return self.fx * ud + self.cx, self.fy * vd + self.cy

    def _border_valid(self, scale: float) -> bool:
        w, h = self.width, self.height
        xs = np.arange(w, dtype=np.float64) + 0.5
        ys = np.arange(h, dtype=np.float64) + 0.5
        bx = np.concatenate([xs, xs, np.full(h, 0.5), np.full(h, w - 0.5)])
        by = np.concatenate([np.full(w, 0.5), np.full(w, h - 0.5), ys, ys])
        with np.errstate(all="ignore"):
            sx, sy = self.source_pixels(bx, by, scale)
            a, b, d = _jacobian(self.model, np.asarray(self.extra), (bx - self.cx) / (scale * self.fx),
                                (by - self.cy) / (scale * self.fy))
            ok = (sx >= 0.5) & (sx <= w - 0.5) & (sy >= 0.5) & (sy <= h - 0.5) & (a * d - b * b > 0)
        return bool(ok.all())

    @cached_property
    def scale(self) -> float:
        """The output focal scale ``s`` (see the module docstring)."""
        if not self._border_valid(_S_MAX):
            raise ProxycodecError(
                f"cannot undistort the {self.model} camera (distortion {list(self.extra)}): even a {_S_MAX:g}x "
                "zoom leaves output pixels outside the image"
            )
        hi = _S_MAX
        lo = hi / _SCAN
        while lo > _S_MIN and self._border_valid(lo):
            hi, lo = lo, lo / _SCAN
        if lo <= _S_MIN:
            return _S_MIN if self._border_valid(_S_MIN) else hi
        while hi > lo * (1.0 + 1e-12):  # lo invalid, hi valid; ~37 halvings (1e-9 px at 1000 px)
            mid = math.sqrt(lo * hi)
            if mid <= lo or mid >= hi:
                break
            if self._border_valid(mid):
                hi = mid
            else:
                lo = mid
        return hi

    def pinhole(self) -> tuple[float, float, float, float]:
        """(fx, fy, cx, cy) of the undistorted pinhole camera (same width and height)."""
        s = self.scale
        return self.fx * s, self.fy * s, self.cx, self.cy

    def source_map(self) -> tuple[np.ndarray, np.ndarray]:
        """float64 [H, W] source pixel positions (+0.5 convention) of every output pixel centre."""
        x = np.arange(self.width, dtype=np.float64) + 0.5
        y = np.arange(self.height, dtype=np.float64) + 0.5
        return self.source_pixels(x[None, :], y[:, None], self.scale)


class RemapCache:
    """A thread-safe LRU of bilinear remap tables, bounded by total bytes."""

    def __init__(self, max_bytes: int = DEFAULT_REMAP_CACHE_BYTES):
        self.max_bytes = int(max_bytes)
        self._items: OrderedDict[DistortedCamera, tuple[np.ndarray, ...]] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()

    def get(self, cam: DistortedCamera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        with self._lock:
            hit = self._items.get(cam)
            if hit is not None:
                self._items.move_to_end(cam)
                return hit  # type: ignore[return-value]
        table = _remap_table(cam)  # outside the lock: deterministic, so a duplicate computation is harmless
        size = sum(a.nbytes for a in table)
        if size <= self.max_bytes:
            with self._lock:
                if cam not in self._items:
                    self._items[cam] = table
                    self._bytes += size
                    while self._bytes > self.max_bytes:
                        _, old = self._items.popitem(last=False)
                        self._bytes -= sum(a.nbytes for a in old)
        return table

    @property
    def nbytes(self) -> int:
        return self._bytes


def _remap_table(cam: DistortedCamera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(flat index of the top-left neighbour int32, x weight float32, y weight float32), each [H*W]."""
    w, h = cam.width, cam.height
    sx, sy = cam.source_map()
    # array index coordinates; clipping only guards rounding at the border (the scale keeps every centre inside)
    xi = np.clip(sx.reshape(-1) - 0.5, 0.0, w - 1.0)
    yi = np.clip(sy.reshape(-1) - 0.5, 0.0, h - 1.0)
    x0 = np.minimum(np.floor(xi), w - 2).astype(np.int64)
    y0 = np.minimum(np.floor(yi), h - 2).astype(np.int64)
    idx = (y0 * w + x0).astype(np.int32)
    return idx, (xi - x0).astype(np.float32), (yi - y0).astype(np.float32)


class Undistorter:
    """Resamples images of one distorted camera onto its pinhole output camera (:meth:`DistortedCamera.pinhole`)."""

    def __init__(self, camera: DistortedCamera, cache: RemapCache | None = None):
        self.camera = camera
        self.cache = cache if cache is not None else RemapCache()

    def __call__(self, rgb: np.ndarray) -> np.ndarray:
        """float32 [H, W, C] image of the distorted camera -> float32 [H, W, C] undistorted (bilinear)."""
        c = self.camera
        if rgb.ndim != 3 or rgb.shape[:2] != (c.height, c.width):
            raise ProxycodecError(
                f"image is {rgb.shape[1] if rgb.ndim > 1 else '?'}x{rgb.shape[0]} but its camera is "
                f"{c.width}x{c.height}"
            )
        idx, wx, wy = self.cache.get(c)
        nc = rgb.shape[2]
        # one pixel (all channels) as one opaque item: np.take gathers whole pixels ~5x faster than fancy indexing
        px = np.ascontiguousarray(rgb, dtype=np.float32).view(np.dtype((np.void, 4 * nc))).reshape(-1)

        def gather(i: np.ndarray) -> np.ndarray:
            return np.take(px, i).view(np.float32).reshape(-1, nc)

        wx = wx[:, None]
        wy = wy[:, None]
        top = gather(idx)
        d = gather(idx + 1)
        np.subtract(d, top, out=d)
        d *= wx
        top += d  # (1 - wx) a + wx b, as a + wx (b - a)
        bot = gather(idx + c.width)
        d = gather(idx + (c.width + 1))
        np.subtract(d, bot, out=d)
        d *= wx
        bot += d
        np.subtract(bot, top, out=bot)
        bot *= wy
        top += bot
        return top.reshape(c.height, c.width, nc)
