"""NeRF-Synthetic ("Blender") datasets: ``transforms_{train,test}.json`` plus RGBA PNG frames."""

from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..camera import Camera
from ..errors import ProxycodecError
from .images import DEFAULT_CACHE_BYTES, PosedImages, image_file_size, look_at_bounds

__all__ = ["load_blender"]

#: A transforms file larger than this is not a transforms file.
_MAX_JSON_BYTES = 64 * 1024 * 1024


def _read_json(path: Path) -> dict:
    try:
        size = path.stat().st_size
        if size > _MAX_JSON_BYTES:
            raise ProxycodecError(f"transforms file is {size} bytes, larger than {_MAX_JSON_BYTES}", path)
        with open(path, "rb") as fh:
            meta = json.loads(fh.read().decode("utf-8"))
    except FileNotFoundError:
        raise ProxycodecError("file not found", path) from None
    except (UnicodeDecodeError, ValueError) as e:  # ValueError: JSONDecodeError, integers of > 4300 digits
        raise ProxycodecError(f"invalid JSON: {e}", path) from None
    except RecursionError:
        raise ProxycodecError("invalid JSON: nested too deeply", path) from None
    if not isinstance(meta, dict):
        raise ProxycodecError("transforms file must hold a JSON object", path)
    return meta


def _frames(
    path: Path, root: Path, meta: dict, max_width: int | None
) -> tuple[list[Camera], list[tuple[int, int]]]:
    angle = meta.get("camera_angle_x")
    if isinstance(angle, bool) or not isinstance(angle, (int, float)) or not (0 < float(angle) < math.pi):
        raise ProxycodecError(f"camera_angle_x must be a number in (0, pi), got {angle!r}", path)
    frames = meta.get("frames")
    if not isinstance(frames, list):
        raise ProxycodecError("'frames' must be a list", path)
    cams: list[Camera] = []
    sizes: list[tuple[int, int]] = []
    for k, fr in enumerate(frames):
        if (
            not isinstance(fr, dict)
            or not isinstance(fr.get("file_path"), str)
            or "transform_matrix" not in fr
        ):
            raise ProxycodecError(f"frame {k} needs a 'file_path' string and a 'transform_matrix'", path)
        rel = fr["file_path"]
        img = root / rel
        if not Path(rel).suffix:
            img = img.with_name(img.name + ".png")
        w, h = image_file_size(img)
        try:
            c2w = np.asarray(fr["transform_matrix"], dtype=np.float64)
        except (TypeError, ValueError):
            raise ProxycodecError(f"frame {k}: transform_matrix is not a numeric 4x4 matrix", path) from None
        if c2w.shape != (4, 4) or not np.isfinite(c2w).all():
            raise ProxycodecError(f"frame {k}: transform_matrix must be a finite 4x4 matrix", path)
        focal = 0.5 * w / math.tan(0.5 * float(angle))
        name = rel[2:] if rel.startswith("./") else rel
        try:
            cam = Camera.from_opengl_c2w(
                c2w, focal, focal, w / 2, h / 2, w, h, name=name, image_path=str(img)
            )
        except ProxycodecError as e:
            raise ProxycodecError(f"frame {k}: {e.reason}", path) from None
        if max_width is not None:
            cam = cam.with_max_width(max_width)
        cams.append(cam)
        sizes.append((w, h))
    return cams, sizes


def load_blender(
    root: str | os.PathLike,
    *,
    background: Sequence[float] = (1.0, 1.0, 1.0),
    max_width: int | None = None,
    cache_bytes: int = DEFAULT_CACHE_BYTES,
) -> PosedImages:
    """Load a NeRF-Synthetic scene folder.

    Cameras are the frames of ``transforms_train.json`` followed by those of ``transforms_test.json``
    (absent file: no test split). Intrinsics: ``fx = fy = 0.5 * W / tan(0.5 * camera_angle_x)`` with W the
    real PNG width (read from the PNG header), principal point at the image centre. ``file_path`` entries
    without an extension get ``.png``. ``max_width`` applies 3DGS's rule (:meth:`Camera.with_max_width`) to
    get the 100% reference resolution. RGBA frames are composited onto ``background`` when loaded. ``bounds``
    is :func:`~proxycodec.formats.images.look_at_bounds` of all cameras.
    """
    root = Path(root)
    if not root.is_dir():
        raise ProxycodecError("Blender dataset folder not found", root)
    if max_width is not None and (isinstance(max_width, bool) or int(max_width) < 1):
        raise ProxycodecError(f"max_width must be a positive integer, got {max_width!r}")
    train_json = root / "transforms_train.json"
    if not train_json.is_file():
        raise ProxycodecError("not a Blender dataset: transforms_train.json is missing", root)
    train, train_sizes = _frames(train_json, root, _read_json(train_json), max_width)
    test_json = root / "transforms_test.json"
    test, test_sizes = ([], [])
    if test_json.is_file():
        test, test_sizes = _frames(test_json, root, _read_json(test_json), max_width)
    cams = train + test
    if not cams:
        raise ProxycodecError("Blender dataset has no frames", root)
    return PosedImages(
        cameras=cams,
        train_indices=list(range(len(train))),
        test_indices=list(range(len(train), len(cams))),
        points=None,
        point_colors=None,
        bounds=look_at_bounds(cams),
        background=tuple(float(v) for v in background),  # type: ignore[arg-type]
        file_sizes=train_sizes + test_sizes,
        root=str(root),
        kind="blender",
        cache_bytes=cache_bytes,
    )
