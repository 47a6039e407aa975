"""Posed image sets: cameras plus lazily loaded, resolution-scaled ground-truth images.

:class:`PosedImages` is what :func:`~proxycodec.formats.blender.load_blender` and
:func:`~proxycodec.formats.colmap.load_colmap` return. Images never sit in RAM as a whole: ``load_image``
decodes one file per call (a small LRU cache, bounded in bytes, keeps recent results), composites alpha onto
the dataset background, undistorts it at full resolution when the dataset has an undistorter for that image
(COLMAP radial cameras, :mod:`.undistort`) and resizes with an area filter to exactly ``camera.scaled(xi)``'s size.
"""

from __future__ import annotations

import math
import os
import threading
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
from PIL import Image, UnidentifiedImageError

from ..camera import Camera
from ..errors import ProxycodecError

__all__ = [
    "PosedImages",
    "image_file_size",
    "decode_image",
    "multiscale_target",
    "read_image_rgb",
    "resize_image",
    "look_at_bounds",
    "DEFAULT_CACHE_BYTES",
]

#: Default byte budget of a dataset's decoded-image cache.
DEFAULT_CACHE_BYTES = 256 * 1024 * 1024

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def image_file_size(path: str | os.PathLike) -> tuple[int, int]:
    """(width, height) of an image file, read from its header without decoding pixels."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(24)
            if head[:8] == _PNG_SIGNATURE and head[12:16] == b"IHDR":
                w, h = int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
                if w < 1 or h < 1:
                    raise ProxycodecError("PNG header declares an empty image", path)
                return w, h
            fh.seek(0)
            with Image.open(fh) as im:  # lazy: parses the header only
                return int(im.size[0]), int(im.size[1])
    except FileNotFoundError:
        raise ProxycodecError("image file not found", path) from None
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as e:  # ValueError: NUL in the path
        raise ProxycodecError(f"cannot read image header: {e}", path) from None


def decode_image(path: str | os.PathLike, expect_size: tuple[int, int] | None = None) -> np.ndarray:
    """Decode an image as stored: uint8 [H, W, 3] RGB or [H, W, 4] RGBA (straight alpha), or float32 [H, W, 3] in
    [0, 1] for 16-bit and 32-bit greyscale (read at full depth)."""
    try:
        with Image.open(path) as im:
            if expect_size is not None and tuple(im.size) != tuple(expect_size):
                raise ProxycodecError(
                    f"image is {im.size[0]}x{im.size[1]} but the dataset expects "
                    f"{expect_size[0]}x{expect_size[1]}",
                    path,
                )
            mode = im.mode
            if mode.startswith("I;16") or mode == "I":
                arr = np.asarray(im, dtype=np.float32)
                arr = arr / (65535.0 if mode.startswith("I;16") or arr.max() > 255 else 255.0)
                return np.repeat(arr[:, :, None], 3, axis=2)
            has_alpha = mode in ("RGBA", "LA", "PA", "RGBa", "La") or (
                mode == "P" and "transparency" in im.info
            )
            im = im.convert("RGBA" if has_alpha else "RGB")
            return np.asarray(im, dtype=np.uint8)
    except FileNotFoundError:
        raise ProxycodecError("image file not found", path) from None
    except ProxycodecError:
        raise
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as e:
        raise ProxycodecError(f"cannot decode image: {e}", path) from None


def read_image_rgb(
    path: str | os.PathLike, background: Sequence[float], expect_size: tuple[int, int] | None = None
) -> np.ndarray:
    """Decode an image to float32 RGB [H, W, 3] in [0, 1], compositing any alpha onto ``background``."""
    arr = decode_image(path, expect_size)
    if arr.dtype != np.uint8:
        return arr
    rgb = arr[:, :, :3].astype(np.float32) * np.float32(1 / 255)
    if arr.shape[2] == 4:
        a = arr[:, :, 3:4].astype(np.float32) * np.float32(1 / 255)
        bg = np.asarray(background, dtype=np.float32).reshape(1, 1, 3)
        rgb = rgb * a + bg * (1.0 - a)
    return rgb


def multiscale_target(arr: np.ndarray, levels: int, background: Sequence[float]) -> np.ndarray:
    """The ground truth of Mip-Splatting's multi-scale protocol, in its arithmetic, from a decoded file ``arr``
    (``decode_image``) -> float32 RGB [H / 2^levels, W / 2^levels, 3].

    Mip-NeRF's ``scripts/convert_blender_data.py`` makes the multi-scale data: the file / 255 in float32, halved
    ``levels`` times by 2x2 means of the straight RGBA, saved as PNG with ``np.uint8(img * 255)`` (truncation).
    Mip-Splatting's loader composites it onto the background in float64 and truncates to 8 bits again
    (``np.array(arr * 255.0, dtype=np.byte)``); the image is then that / 255. Averaging colour and alpha separately
    before compositing is not box-filtering the composited image (``resize_image``, our own targets) at silhouettes:
    this is the protocol's ground truth, kept as it is so that figures compare with the field's."""
    img = arr.astype(np.float32) / 255.0 if arr.dtype == np.uint8 else np.asarray(arr, np.float32)
    for _ in range(levels):
        h, w = img.shape[:2]
        if h % 2 or w % 2:
            raise ProxycodecError(f"a {w}x{h} image cannot be halved by 2x2 means")
        img = np.mean(np.reshape(img, [h // 2, 2, w // 2, 2, -1]), (1, 3))
    norm = np.uint8(img * 255) / 255.0  # the PNG, read back in float64
    rgb = norm[:, :, :3]
    if norm.shape[2] == 4:
        rgb = rgb * norm[:, :, 3:4] + np.asarray(background, np.float64) * (1 - norm[:, :, 3:4])
    return (np.uint8(rgb * 255.0) / 255.0).astype(np.float32)


def resize_image(rgb: np.ndarray, width: int, height: int) -> np.ndarray:
    """Resize float RGB [H, W, 3] to [height, width, 3].

    Downscaling uses PIL's BOX filter on float data: every output pixel is the exact area average of the input
    pixels it covers (proper anti-aliasing, no ringing, values stay in range). Upscaling uses bicubic
    interpolation, clipped to [0, 1].
    """
    h0, w0 = rgb.shape[:2]
    if (w0, h0) == (width, height):
        return np.ascontiguousarray(rgb, dtype=np.float32)
    down = width <= w0 and height <= h0
    resample = Image.Resampling.BOX if down else Image.Resampling.BICUBIC
    out = np.empty((height, width, 3), np.float32)
    for c in range(3):  # PIL's float mode "F" is single-channel
        ch = Image.fromarray(np.ascontiguousarray(rgb[:, :, c], dtype=np.float32))  # mode "F"
        out[:, :, c] = np.asarray(ch.resize((width, height), resample=resample), dtype=np.float32)
    if not down:
        np.clip(out, 0.0, 1.0, out=out)
    return out


def check_background(values: Sequence[float]) -> tuple[float, float, float]:
    """A background colour as three floats in [0, 1] (NaN fails the range test); ProxycodecError otherwise."""
    try:
        bg = tuple(float(v) for v in values)
    except (TypeError, ValueError):
        bg = ()
    if len(bg) != 3 or not all(0.0 <= v <= 1.0 for v in bg):
        raise ProxycodecError(f"background must be 3 numbers in [0, 1], got {values!r}")
    return bg  # type: ignore[return-value]


def look_at_bounds(cameras: Sequence[Camera]) -> np.ndarray:
    """A bounding-box estimate [2, 3] of the region a set of inward-looking cameras observes.

    Centre: the least-squares point closest to all optical axes (the point the cameras look at; the centroid
    of the camera centres when the axes are nearly parallel). Half-size: the median over cameras of
    ``distance_to_centre * sin(half of the narrower field of view)``, the radius of the largest sphere around
    the centre that the camera sees whole. For NeRF-Synthetic (cameras at distance 4.03, 39.6 deg field of
    view) this gives the cube [-1.37, 1.37]^3 around the origin, close to the [-1.3, 1.3]^3 that 3DGS samples
    its random initial points from for those scenes.
    """
    if not cameras:
        raise ProxycodecError("cannot estimate bounds without cameras")
    centers = np.stack([c.center for c in cameras])  # [N, 3]
    dirs = np.stack([c.rotation[2] for c in cameras])  # [N, 3] optical axes in world coordinates
    proj = np.eye(3)[None] - dirs[:, :, None] * dirs[:, None, :]  # [N, 3, 3]
    A = proj.sum(0)
    b = np.einsum("nij,nj->i", proj, centers)
    if np.linalg.cond(A) < 1e6:
        center = np.linalg.solve(A, b)
    else:
        center = centers.mean(0)
    dist = np.linalg.norm(centers - center, axis=1)
    half_fov = np.array(
        [min(math.atan(0.5 * c.width / c.fx), math.atan(0.5 * c.height / c.fy)) for c in cameras]
    )
    r = float(np.median(dist * np.sin(half_fov)))
    if not math.isfinite(r) or r <= 0:
        r = float(max(np.median(dist), 1e-3))
    return np.stack([center - r, center + r]).astype(np.float64)


class _ImageCache:
    """A thread-safe LRU cache of tensors bounded by total bytes."""

    def __init__(self, max_bytes: int):
        self.max_bytes = int(max_bytes)
        self._items: OrderedDict[tuple, torch.Tensor] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()

    def get(self, key: tuple) -> torch.Tensor | None:
        with self._lock:
            t = self._items.get(key)
            if t is not None:
                self._items.move_to_end(key)
            return t

    def put(self, key: tuple, t: torch.Tensor) -> None:
        size = t.numel() * t.element_size()
        if size > self.max_bytes:
            return
        with self._lock:
            if key in self._items:
                return
            self._items[key] = t
            self._bytes += size
            while self._bytes > self.max_bytes:
                _, old = self._items.popitem(last=False)
                self._bytes -= old.numel() * old.element_size()

    def clear(self) -> None:
        with self._lock:
            self._items.clear()
            self._bytes = 0

    @property
    def nbytes(self) -> int:
        return self._bytes


@dataclass(frozen=True, eq=False)
class PosedImages:
    """Cameras at the 100% reference resolution, their image files, train/test split, optional SfM points."""

    cameras: list[Camera]  # each with image_path set
    train_indices: list[int]
    test_indices: list[int]
    points: np.ndarray | None  # [P, 3] float32 SfM points (COLMAP), None for Blender
    point_colors: np.ndarray | None  # [P, 3] uint8 or None
    bounds: np.ndarray  # [2, 3] float64: (min corner, max corner) scene box estimate
    background: tuple[float, float, float]  # RGB in [0, 1] that alpha is composited onto (and renders use)
    file_sizes: list[tuple[int, int]]  # (width, height) of each image file on disk
    root: str = ""
    kind: str = ""  # "blender" | "colmap"
    cache_bytes: int = DEFAULT_CACHE_BYTES
    #: per camera, None or a function float32 [H, W, 3] -> [H, W, 3] applied to the decoded file before resizing
    #: (undistortion to the pinhole ``cameras[i]``); None: no image needs one
    undistorters: Sequence[Callable[[np.ndarray], np.ndarray] | None] | None = None
    _cache: _ImageCache = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        n = len(self.cameras)
        if len(self.file_sizes) != n:
            raise ProxycodecError("PosedImages: one file size per camera is required")
        split = list(self.train_indices) + list(self.test_indices)
        if any(not (0 <= i < n) for i in split) or len(set(split)) != len(split):
            raise ProxycodecError(
                "PosedImages: train/test indices must be distinct and within the camera list"
            )
        if self.undistorters is not None:
            if len(self.undistorters) != n:
                raise ProxycodecError("PosedImages: one undistorter (or None) per camera is required")
            object.__setattr__(self, "undistorters", list(self.undistorters))
        if any(c.image_path is None for c in self.cameras):
            raise ProxycodecError("PosedImages: every camera needs an image_path")
        bounds = np.asarray(self.bounds, dtype=np.float64)
        if bounds.shape != (2, 3) or not np.isfinite(bounds).all() or (bounds[0] > bounds[1]).any():
            raise ProxycodecError(f"PosedImages: bounds must be a finite [2, 3] box, got {bounds.tolist()}")
        bg = check_background(self.background)
        object.__setattr__(self, "bounds", bounds)
        object.__setattr__(self, "background", bg)
        object.__setattr__(self, "train_indices", [int(i) for i in self.train_indices])
        object.__setattr__(self, "test_indices", [int(i) for i in self.test_indices])
        object.__setattr__(self, "_cache", _ImageCache(self.cache_bytes))

    def __len__(self) -> int:
        return len(self.cameras)

    @property
    def train_cameras(self) -> list[Camera]:
        return [self.cameras[i] for i in self.train_indices]

    @property
    def test_cameras(self) -> list[Camera]:
        return [self.cameras[i] for i in self.test_indices]

    def image_size(self, i: int, xi: float = 1.0) -> tuple[int, int]:
        """(width, height) that ``load_image(i, xi)`` returns: the size of ``cameras[i].scaled(xi)``."""
        cam = self.cameras[i].scaled(xi)
        return cam.width, cam.height

    def load_image(self, i: int, xi: float = 1.0) -> torch.Tensor:
        """Image ``i`` at resolution ratio ``xi``: float32 tensor [h, w, 3] in [0, 1] with h, w from
        ``cameras[i].scaled(xi)``. Decoded from disk on each call (unless in the small LRU cache); the result
        is a fresh tensor the caller may modify."""
        if not (0 <= int(i) < len(self.cameras)):
            raise ProxycodecError(f"image index {i} out of range (dataset has {len(self.cameras)} images)")
        i = int(i)
        w, h = self.image_size(i, xi)
        key = (i, w, h)
        hit = self._cache.get(key)
        if hit is not None:
            return hit.clone()
        path = self.cameras[i].image_path
        rgb = read_image_rgb(path, self.background, expect_size=self.file_sizes[i])
        if self.undistorters is not None and self.undistorters[i] is not None:
            rgb = self.undistorters[i](rgb)
        t = torch.from_numpy(resize_image(rgb, w, h))
        self._cache.put(key, t)
        return t.clone()

    def load_multiscale_target(self, i: int, xi: float) -> torch.Tensor:
        """Image ``i`` at ``camera.scaled(xi)``'s size as Mip-Splatting's multi-scale protocol builds its ground
        truth (``multiscale_target``): that size must be the file's size divided by a power of two."""
        i = int(i)
        (fw, fh), (w, h) = self.file_sizes[i], self.image_size(i, xi)
        k = round(math.log2(fw / w)) if w > 0 and fw >= w else -1
        if k < 0 or (fw, fh) != (w << k, h << k):
            raise ProxycodecError(f"the multi-scale protocol needs each test size to be the image size / 2^k; "
                                  f"{fw}x{fh} at {xi:g} of the reference is {w}x{h}", self.cameras[i].image_path)
        if self.undistorters is not None and self.undistorters[i] is not None:
            raise ProxycodecError("the multi-scale protocol needs undistorted images (give --no-undistort or an "
                                  "undistorted dataset)", self.cameras[i].image_path)
        arr = decode_image(self.cameras[i].image_path, expect_size=self.file_sizes[i])
        return torch.from_numpy(multiscale_target(arr, k, self.background))

    def clear_cache(self) -> None:
        self._cache.clear()
