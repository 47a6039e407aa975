"""Plain 3DGS files in any format we read: an INRIA 3DGS PLY, an SPZ (v2-v4) or a glTF GLB with
``KHR_gaussian_splatting``, recognised by their first bytes (never by the suffix), read as one ``GaussianPly``."""

from __future__ import annotations

import gzip
import os

from ..errors import ProxycodecError
from .inria_ply import GaussianPly

__all__ = ["SPLAT_KINDS", "is_inria_ply", "read_splats", "splat_kind"]

#: What ``splat_kind`` can answer, with the name a user reads.
SPLAT_KINDS = {"ply": "INRIA 3DGS PLY", "spz": "SPZ", "glb": "glTF GLB (KHR_gaussian_splatting)"}


def splat_kind(path: str | os.PathLike) -> str | None:
    """"ply", "spz" or "glb" when ``path`` is a plain 3DGS file of that kind, else None (any other file, a folder,
    a missing path). Reads the PLY header, or the first bytes (SPZ v4 ``NGSP``; older SPZ: gzip whose stream starts
    with ``NGSP``; GLB ``glTF``)."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(4)
    except OSError:
        return None
    if head == b"NGSP":
        return "spz"
    if head == b"glTF":
        return "glb"
    if head[:2] == b"\x1f\x8b":
        try:
            with gzip.open(path, "rb") as g:
                return "spz" if g.read(4) == b"NGSP" else None
        except (OSError, EOFError):
            return None
    if head[:3] == b"ply":
        return "ply" if is_inria_ply(path) else None
    return None


def is_inria_ply(path: str | os.PathLike) -> bool:
    """True when ``path`` is a PLY whose header has INRIA 3DGS fields (f_dc_0, opacity, rot_0, no anchor features)."""
    from .ply import read_ply_header

    try:
        names = set(read_ply_header(path).names)
    except (ProxycodecError, OSError):
        return False
    return "f_dc_0" in names and "opacity" in names and "rot_0" in names and "f_anchor_feat_0" not in names


def _starts_with(path, magic: bytes) -> bool:
    try:
        with open(path, "rb") as fh:
            return fh.read(len(magic)) == magic
    except OSError:
        return False


def read_splats(path: str | os.PathLike) -> tuple[GaussianPly, dict]:
    """(Gaussians, what the file says of itself: ``kind`` and the reader's fields) of a plain 3DGS file."""
    kind = splat_kind(path)
    if kind == "ply" or (kind is None and _starts_with(path, b"ply")):  # another PLY: its reader says what it is
        from .inria_ply import read_inria_ply

        return read_inria_ply(path), {"kind": "ply"}
    if kind == "spz":
        from .spz import read_spz

        ply, info = read_spz(path)
        return ply, {"kind": "spz", **info}
    if kind == "glb":
        from .gltf import read_glb

        ply, info = read_glb(path)
        return ply, {"kind": "glb", **info}
    raise ProxycodecError("is not a 3DGS file (an INRIA 3DGS PLY, an SPZ or a KHR_gaussian_splatting GLB)", path)
