"""Open any scene file a user may hand us, whatever its format (``eval``, ``bench``)."""

from __future__ import annotations

import os


def load_any(path: str | os.PathLike):
    """An anchor PLY (+ weights sidecar) as a ``SceneModel``, a trained Scaffold-GS output (its folder, or its PLY
    with the MLP files beside it: ``scaffold_gs.load_scaffold_output``) as a ``SceneModel``, an INRIA 3DGS PLY
    (``fit --explicit``, other 3DGS trainers), an SPZ or a KHR_gaussian_splatting GLB as an ``ExplicitModel`` (rendered as plain 3DGS) or a proxycodec
    container decoded to a ``SceneModel`` (leaves regenerated)."""
    from .explicit import ExplicitModel
    from .formats.splats import splat_kind
    from .formats.container import MAGIC
    from .model import SceneModel
    from .scaffold_gs import is_scaffold_output, load_scaffold_output

    if is_scaffold_output(path):
        return load_scaffold_output(path)
    try:
        with open(path, "rb") as fh:
            head = fh.read(len(MAGIC))
    except OSError:
        head = b""
    if head == MAGIC:
        from .codec import decode

        return decode(path)
    if splat_kind(path):
        return ExplicitModel.load(path)
    return SceneModel.load(path)
