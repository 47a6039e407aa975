"""Posed-image datasets: one front door over the Blender and COLMAP loaders.

The loaders live in :mod:`.blender` and :mod:`.colmap`; the shared result type, :class:`PosedImages`, in
:mod:`.images`.
"""

from __future__ import annotations

import os
from pathlib import Path

from ..errors import ProxycodecError
from .blender import load_blender
from .colmap import find_sparse_dir, load_colmap
from .images import PosedImages

__all__ = ["PosedImages", "load_blender", "load_colmap", "load_dataset", "dataset_kind"]


def dataset_kind(root: str | os.PathLike) -> str:
    """``"blender"`` (``transforms_train.json`` present) or ``"colmap"`` (a sparse model present)."""
    root = Path(root)
    if not root.is_dir():
        raise ProxycodecError("dataset folder not found", root)
    if (root / "transforms_train.json").is_file():
        return "blender"
    try:
        find_sparse_dir(root)
    except ProxycodecError:
        raise ProxycodecError(
            "not a dataset: neither transforms_train.json nor a COLMAP sparse model "
            "(sparse/0/cameras.bin) was found",
            root,
        ) from None
    return "colmap"


def load_dataset(root: str | os.PathLike, *, max_width: int | None = None, images: str = "images",
                 test_every: int = 8, undistort: bool = True, **kwargs) -> PosedImages:
    """Load a Blender or COLMAP scene folder (see :func:`dataset_kind`). ``images``, ``test_every`` and
    ``undistort`` are COLMAP's (a Blender scene has its own split and pinhole cameras); ``kwargs`` go to either
    loader."""
    if dataset_kind(root) == "blender":
        return load_blender(root, max_width=max_width, **kwargs)
    return load_colmap(root, max_width=max_width, images=images, test_every=test_every, undistort=undistort,
                       **kwargs)
