"""Open any scene file a user may hand us, whatever its format (``eval``, ``bench``, ``view``, ``decode``)."""

from __future__ import annotations

import os


def decode_torch_free(path: str | os.PathLike):
    """The container at ``path`` decoded by the torch-free path (a ``lite.LiteScene``), or None where that path
    does not apply (no numba; a leaf predictor it does not implement): the caller then takes the torch path.
    Malformed files raise as they do there."""
    try:
        from . import lite
    except ImportError:  # numba missing: the torch path renders with the reference backend
        return None
    try:
        return lite.decode(path)
    except lite.Unsupported:
        return None


def load_any(path: str | os.PathLike, *, torch_free: bool = False):
    """An anchor PLY (+ weights sidecar) as a ``SceneModel``, a trained Scaffold-GS output (its folder, or its PLY
    with the MLP files beside it: ``scaffold_gs.load_scaffold_output``) as a ``SceneModel``, an INRIA 3DGS PLY
    (``fit --explicit``, other 3DGS trainers), an SPZ or a KHR_gaussian_splatting GLB as an ``ExplicitModel``
    (rendered as plain 3DGS) or a proxycodec container decoded to a ``SceneModel`` (leaves regenerated).

    ``torch_free``: a container by ``decode_torch_free`` where that applies (a ``lite.LiteScene``; torch is never
    imported), ``view``'s choice: ~1.5 s less to start."""
    from .formats.container import MAGIC
    from .formats.splats import splat_kind
    from .scaffold_gs import is_scaffold_output, load_scaffold_output

    if is_scaffold_output(path):
        return load_scaffold_output(path)
    try:
        with open(path, "rb") as fh:
            head = fh.read(len(MAGIC))
    except OSError:
        head = b""
    if head == MAGIC:
        scene = decode_torch_free(path) if torch_free else None
        if scene is not None:
            return scene
        from .codec import decode

        return decode(path)
    if splat_kind(path):
        from .explicit import ExplicitModel

        return ExplicitModel.load(path)
    from .model import SceneModel

    return SceneModel.load(path)
