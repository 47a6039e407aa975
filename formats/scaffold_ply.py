"""Scaffold-GS anchor PLY (``point_cloud/iteration_*/point_cloud.ply`` of a Scaffold-GS run).

Layout, all float32, in this order (``GaussianModel.construct_list_of_attributes`` of Scaffold-GS)::

    x y z                      anchor position
    nx ny nz                   zeros (unused)
    f_offset_0 .. f_offset_{3K-1}        the K offsets, TRANSPOSED: first the K x components, then y, then z
    f_anchor_feat_0 .. f_anchor_feat_{F-1}
    opacity                    anchor-level opacity logit (unused by rendering)
    scale_0 .. scale_5         log scaling: [0:3] scale the offsets, [3:6] base scale of the neural Gaussians
    rot_0 .. rot_3             anchor rotation, wxyz (unused by rendering)

K (default 10) and F (default 32) are inferred from the header. The neural-Gaussian MLPs live in separate
TorchScript files that this module does not read (never unpickle user files).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, fields

import numpy as np

from ..errors import ProxycodecError
from .ply import PlyHeader, columns, float32_records, indexed_names, read_ply, write_ply

__all__ = ["ScaffoldPly", "read_scaffold_ply", "write_scaffold_ply", "scaffold_attribute_names"]

#: Scaffold-GS's initial anchor opacity logit, inverse_sigmoid(0.1).
DEFAULT_OPACITY_LOGIT = math.log(0.1 / 0.9)


def scaffold_attribute_names(n_offsets: int = 10, feature_dim: int = 32) -> list[str]:
    """PLY property names in Scaffold-GS order for K offsets and F feature channels."""
    return (
        ["x", "y", "z", "nx", "ny", "nz"]
        + [f"f_offset_{i}" for i in range(3 * n_offsets)]
        + [f"f_anchor_feat_{i}" for i in range(feature_dim)]
        + ["opacity"]
        + [f"scale_{i}" for i in range(6)]
        + [f"rot_{i}" for i in range(4)]
    )


def _f32(name: str, a, shape: tuple[int | None, ...]) -> np.ndarray:
    arr = np.ascontiguousarray(a, dtype=np.float32)
    if arr.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, arr.shape)):
        want = "x".join("?" if s is None else str(s) for s in shape)
        raise ProxycodecError(f"ScaffoldPly.{name} must have shape [{want}], got {list(arr.shape)}")
    return arr


@dataclass(frozen=True, eq=False)
class ScaffoldPly:
    """The anchors of a Scaffold-GS scene exactly as stored in its PLY (float32 numpy arrays).

    Equality (``==``) is bitwise equality of every array, so ``read(write(x)) == x`` is meaningful.
    """

    positions: np.ndarray  # [M, 3] anchor positions x_v
    offsets: np.ndarray  # [M, K, 3] offsets O_v (before scaling by exp(scalings[:, :3]))
    features: np.ndarray  # [M, F] anchor features f_v
    scalings: np.ndarray  # [M, 6] log-space scaling l_v as stored
    normals: np.ndarray | None = None  # [M, 3]; None -> zeros, as Scaffold-GS writes
    opacity: np.ndarray | None = None  # [M] anchor opacity logit (unused); None -> inverse_sigmoid(0.1)
    rotations: np.ndarray | None = None  # [M, 4] wxyz (unused); None -> identity (1, 0, 0, 0)

    def __post_init__(self) -> None:
        pos = _f32("positions", self.positions, (None, 3))
        m = pos.shape[0]
        off = _f32("offsets", self.offsets, (m, None, 3))
        feat = _f32("features", self.features, (m, None))
        sc = _f32("scalings", self.scalings, (m, 6))
        if off.shape[1] < 1 or feat.shape[1] < 1:
            raise ProxycodecError("ScaffoldPly needs at least one offset and one feature channel per anchor")
        nrm = np.zeros((m, 3), np.float32) if self.normals is None else _f32("normals", self.normals, (m, 3))
        op = (
            np.full(m, DEFAULT_OPACITY_LOGIT, np.float32)
            if self.opacity is None
            else _f32("opacity", np.reshape(self.opacity, (-1,)), (m,))
        )
        if self.rotations is None:
            rot = np.zeros((m, 4), np.float32)
            rot[:, 0] = 1.0
        else:
            rot = _f32("rotations", self.rotations, (m, 4))
        for k, v in (
            ("positions", pos),
            ("offsets", off),
            ("features", feat),
            ("scalings", sc),
            ("normals", nrm),
            ("opacity", op),
            ("rotations", rot),
        ):
            object.__setattr__(self, k, v)
        self.validate()

    def validate(self) -> None:
        """Reject NaN/Inf in the fields rendering uses (unused normals/opacity/rotations may be anything)."""
        for k in ("positions", "offsets", "features", "scalings"):
            a = getattr(self, k)
            if not np.isfinite(a).all():
                raise ProxycodecError(f"ScaffoldPly.{k} holds NaN or Inf")

    @property
    def n_anchors(self) -> int:
        return int(self.positions.shape[0])

    @property
    def n_offsets(self) -> int:
        return int(self.offsets.shape[1])

    @property
    def feature_dim(self) -> int:
        return int(self.features.shape[1])

    def attribute_matrix(self) -> np.ndarray:
        """All properties as one float32 matrix [M, P] in Scaffold-GS file order."""
        m = self.n_anchors
        off_t = self.offsets.transpose(0, 2, 1).reshape(
            m, 3 * self.n_offsets
        )  # [M, 3K]: x components, then y, then z
        return np.concatenate(
            [
                self.positions,
                self.normals,
                off_t,
                self.features,
                self.opacity[:, None],
                self.scalings,
                self.rotations,
            ],
            axis=1,
        )

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, ScaffoldPly):
            return NotImplemented
        return all(
            getattr(self, f.name).shape == getattr(other, f.name).shape
            and getattr(self, f.name).tobytes() == getattr(other, f.name).tobytes()
            for f in fields(self)
        )

    __hash__ = None  # type: ignore[assignment]


_REQUIRED = ("x", "y", "z", "nx", "ny", "nz", "opacity")


def _check_layout(path, header: PlyHeader) -> tuple[list[str], list[str], list[str], list[str]]:
    names = set(header.names)
    offs = indexed_names(path, header, "f_offset_")
    feats = indexed_names(path, header, "f_anchor_feat_")
    if not offs or not feats:
        hint = (" (it is an INRIA 3DGS PLY: `proxycodec render` and `eval` take it as it is, `proxycodec convert` "
                "makes an anchor scene of it, `proxycodec encode` converts and compresses it)"
                if "f_dc_0" in names else "")
        raise ProxycodecError(
            "not a Scaffold-GS anchor PLY: no f_offset_* / f_anchor_feat_* properties" + hint, path
        )
    missing = [n for n in _REQUIRED if n not in names]
    if missing:
        raise ProxycodecError(f"Scaffold-GS anchor PLY lacks properties {missing}", path)
    if len(offs) % 3:
        raise ProxycodecError(
            f"Scaffold-GS anchor PLY has {len(offs)} f_offset_* properties, not a multiple of 3", path
        )
    scales = indexed_names(path, header, "scale_")
    if len(scales) != 6:
        raise ProxycodecError(
            f"Scaffold-GS anchor PLY must have 6 scale_* properties, found {len(scales)}", path
        )
    rots = indexed_names(path, header, "rot_")
    if len(rots) != 4:
        raise ProxycodecError(f"Scaffold-GS anchor PLY must have 4 rot_* properties, found {len(rots)}", path)
    known = set(_REQUIRED) | set(offs) | set(feats) | set(scales) | set(rots)
    extra = [n for n in header.names if n not in known]
    if extra:
        raise ProxycodecError(f"Scaffold-GS anchor PLY has unexpected properties {extra[:5]}", path)
    for name, code in header.properties:
        if code[0] != "f":
            raise ProxycodecError(f"Scaffold-GS anchor PLY property {name!r} is not a float", path)
    return offs, feats, scales, rots


def read_scaffold_ply(path: str | os.PathLike) -> ScaffoldPly:
    """Read a Scaffold-GS anchor PLY. Raises :class:`ProxycodecError` (naming the file) on any problem."""
    header, data = read_ply(path)
    offs, feats, scales, rots = _check_layout(path, header)
    m = header.count
    k = len(offs) // 3
    pos = columns(path, data, ["x", "y", "z"], field="positions", finite=True)
    off = columns(path, data, offs, field="offsets", finite=True)
    feat = columns(path, data, feats, field="features", finite=True)
    sc = columns(path, data, scales, field="scalings", finite=True)
    nrm = columns(path, data, ["nx", "ny", "nz"], field="normals", finite=False)
    op = columns(path, data, ["opacity"], field="opacity", finite=False)[:, 0]
    rot = columns(path, data, rots, field="rotations", finite=False)
    offsets = np.ascontiguousarray(off.reshape(m, 3, k).transpose(0, 2, 1))  # [M, K, 3]
    try:
        return ScaffoldPly(pos, offsets, feat, sc, nrm, op, rot)
    except ProxycodecError as e:
        raise ProxycodecError(e.reason, path) from None


def write_scaffold_ply(path: str | os.PathLike, ply: ScaffoldPly) -> None:
    """Write ``ply`` atomically in Scaffold-GS's exact layout (the bytes its ``save_ply`` produces)."""
    if not isinstance(ply, ScaffoldPly):
        raise ProxycodecError(f"write_scaffold_ply expects a ScaffoldPly, got {type(ply).__name__}")
    ply.validate()
    names = scaffold_attribute_names(ply.n_offsets, ply.feature_dim)
    write_ply(path, float32_records(ply.attribute_matrix(), names))
