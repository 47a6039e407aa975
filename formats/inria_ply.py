"""INRIA 3D Gaussian Splatting PLY (``point_cloud.ply`` written by graphdeco-inria/gaussian-splatting).

Layout, all float32, in this order (``GaussianModel.construct_list_of_attributes`` of 3DGS)::

    x y z  nx ny nz                       position; normals (3DGS writes zeros)
    f_dc_0 f_dc_1 f_dc_2                  SH DC coefficient per colour channel
    f_rest_0 .. f_rest_{3(n-1)-1}         higher SH coefficients, CHANNEL-MAJOR: f_rest_{c*(n-1)+j} is
                                          coefficient j+1 of channel c, with n = (degree+1)^2
    opacity                               opacity logit (+-inf, a saturated alpha of 1 or 0, is read as
                                          +-SATURATED_LOGIT; NaN is refused)
    scale_0 scale_1 scale_2               log scales
    rot_0 .. rot_3                        rotation quaternion wxyz (not necessarily normalised)

The SH degree (0..3) follows from the number of f_rest properties (0, 9, 24, 45). Files without normals (some
exporters drop them) are read with ``normals=None`` and written back without them.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, fields

import numpy as np

from ..errors import ProxycodecError
from .ply import PlyHeader, columns, float32_records, indexed_names, read_ply, write_ply

__all__ = [
    "GaussianPly",
    "read_inria_ply",
    "write_inria_ply",
    "inria_attribute_names",
    "SH_C0",
    "SATURATED_LOGIT",
    "rgb_to_sh_dc",
    "sh_dc_to_rgb",
]

#: The degree-0 real spherical harmonic, 1 / (2 sqrt(pi)).
SH_C0 = 0.28209479177387814

#: An opacity logit of +-inf in a file (SPZ -> PLY converters such as splat-transform write +inf for an alpha byte of
#: 255, since logit(1) is infinite) is read as +-this: sigmoid(30) is 1.0 in float32, so the Gaussian renders as the
#: file says, and every value in memory stays finite. gsplat / 3DGS loaders read such files the same way
#: (sigmoid(inf) = 1).
SATURATED_LOGIT = 30.0

#: Number of f_rest properties -> SH degree.
_REST_TO_DEGREE = {0: 0, 9: 1, 24: 2, 45: 3}


def rgb_to_sh_dc(rgb):
    """Colour in [0, 1] -> DC SH coefficient (3DGS's ``RGB2SH``); numpy arrays, tensors or floats."""
    return (rgb - 0.5) / SH_C0


def sh_dc_to_rgb(sh):
    """DC SH coefficient -> colour (3DGS's ``SH2RGB``; not clamped)."""
    return sh * SH_C0 + 0.5


def inria_attribute_names(sh_degree: int = 3, normals: bool = True) -> list[str]:
    """PLY property names in 3DGS order."""
    n = (sh_degree + 1) ** 2
    return (
        ["x", "y", "z"]
        + (["nx", "ny", "nz"] if normals else [])
        + ["f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(3 * (n - 1))]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )


def _f32(name: str, a, shape: tuple[int | None, ...]) -> np.ndarray:
    arr = np.ascontiguousarray(a, dtype=np.float32)
    if arr.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, arr.shape)):
        want = "x".join("?" if s is None else str(s) for s in shape)
        raise ProxycodecError(f"GaussianPly.{name} must have shape [{want}], got {list(arr.shape)}")
    return arr


@dataclass(frozen=True, eq=False)
class GaussianPly:
    """A 3DGS scene as stored in its PLY (float32 numpy arrays, activations NOT applied).

    Equality (``==``) is bitwise equality of every array.
    """

    means: np.ndarray  # [N, 3]
    sh: np.ndarray  # [N, (degree+1)^2, 3]; sh[:, 0] is the DC term
    opacities: np.ndarray  # [N] opacity logits
    scales: np.ndarray  # [N, 3] log scales
    quats: np.ndarray  # [N, 4] wxyz
    normals: np.ndarray | None = None  # [N, 3]; None -> zeros written (as 3DGS does); see ``has_normals``
    has_normals: bool = True  # False: the file has no nx/ny/nz properties

    def __post_init__(self) -> None:
        means = _f32("means", self.means, (None, 3))
        n = means.shape[0]
        sh = _f32("sh", self.sh, (n, None, 3))
        if sh.shape[1] not in (1, 4, 9, 16):
            raise ProxycodecError(f"GaussianPly.sh must hold 1, 4, 9 or 16 coefficients, got {sh.shape[1]}")
        op = _f32("opacities", np.reshape(self.opacities, (-1,)), (n,))
        sc = _f32("scales", self.scales, (n, 3))
        q = _f32("quats", self.quats, (n, 4))
        nrm = np.zeros((n, 3), np.float32) if self.normals is None else _f32("normals", self.normals, (n, 3))
        for k, v in (
            ("means", means),
            ("sh", sh),
            ("opacities", op),
            ("scales", sc),
            ("quats", q),
            ("normals", nrm),
        ):
            object.__setattr__(self, k, v)
        object.__setattr__(self, "has_normals", bool(self.has_normals))
        self.validate()

    def validate(self) -> None:
        """Reject NaN/Inf in every field but the (unused) normals."""
        for k in ("means", "sh", "opacities", "scales", "quats"):
            if not np.isfinite(getattr(self, k)).all():
                raise ProxycodecError(f"GaussianPly.{k} holds NaN or Inf")

    @property
    def n_gaussians(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        return {1: 0, 4: 1, 9: 2, 16: 3}[int(self.sh.shape[1])]

    def attribute_matrix(self) -> np.ndarray:
        """All properties as one float32 matrix [N, P] in 3DGS file order."""
        n = self.n_gaussians
        rest = (
            self.sh[:, 1:, :].transpose(0, 2, 1).reshape(n, 3 * (self.sh.shape[1] - 1))
        )  # [N, 3*(n_coef-1)] channel-major
        parts = (
            [self.means]
            + ([self.normals] if self.has_normals else [])
            + [self.sh[:, 0, :], rest, self.opacities[:, None], self.scales, self.quats]
        )
        return np.concatenate(parts, axis=1)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, GaussianPly):
            return NotImplemented
        if self.has_normals != other.has_normals:
            return False
        return all(
            getattr(self, f.name).shape == getattr(other, f.name).shape
            and getattr(self, f.name).tobytes() == getattr(other, f.name).tobytes()
            for f in fields(self)
            if f.name != "has_normals"
        )

    __hash__ = None  # type: ignore[assignment]


def _check_layout(path, header: PlyHeader) -> tuple[int, bool, list[str], list[str]]:
    names = set(header.names)
    dc = indexed_names(path, header, "f_dc_")
    if not dc:
        hint = (
            " (it is a Scaffold-GS anchor PLY: `proxycodec encode`, `render` and `stats` take it)"
            if "f_anchor_feat_0" in names
            else ""
        )
        raise ProxycodecError("not an INRIA 3DGS PLY: no f_dc_* properties" + hint, path)
    if len(dc) != 3:
        raise ProxycodecError(f"INRIA 3DGS PLY must have 3 f_dc_* properties, found {len(dc)}", path)
    rest = indexed_names(path, header, "f_rest_")
    if len(rest) not in _REST_TO_DEGREE:
        raise ProxycodecError(
            f"INRIA 3DGS PLY has {len(rest)} f_rest_* properties; expected 0, 9, 24 or 45 (SH degree 0..3)",
            path,
        )
    has_normals = "nx" in names or "ny" in names or "nz" in names
    required = ["x", "y", "z", "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    if has_normals:
        required += ["nx", "ny", "nz"]
    missing = [n for n in required if n not in names]
    if missing:
        raise ProxycodecError(f"INRIA 3DGS PLY lacks properties {missing}", path)
    for prefix, want in (("scale_", 3), ("rot_", 4)):
        got = len(indexed_names(path, header, prefix))
        if got != want:
            raise ProxycodecError(f"INRIA 3DGS PLY must have {want} {prefix}* properties, found {got}", path)
    known = set(required) | set(dc) | set(rest)
    extra = [n for n in header.names if n not in known]
    if extra:
        raise ProxycodecError(f"INRIA 3DGS PLY has unexpected properties {extra[:5]}", path)
    for name, code in header.properties:
        if code[0] != "f":
            raise ProxycodecError(f"INRIA 3DGS PLY property {name!r} is not a float", path)
    return _REST_TO_DEGREE[len(rest)], has_normals, dc, rest


def read_inria_ply(path: str | os.PathLike) -> GaussianPly:
    """Read a 3DGS PLY. Raises :class:`ProxycodecError` (naming the file) on any problem."""
    header, data = read_ply(path)
    degree, has_normals, dc, rest = _check_layout(path, header)
    n = header.count
    n_coef = (degree + 1) ** 2
    means = columns(path, data, ["x", "y", "z"], field="means", finite=True)
    f_dc = columns(path, data, dc, field="f_dc", finite=True)
    f_rest = columns(path, data, rest, field="f_rest", finite=True)
    op = columns(path, data, ["opacity"], field="opacity", finite=False)[:, 0]
    if np.isnan(op).any():
        raise ProxycodecError(f"PLY field 'opacity' holds NaN (first at vertex {int(np.flatnonzero(np.isnan(op))[0])})",
                              path)
    op = np.where(np.isinf(op), np.copysign(np.float32(SATURATED_LOGIT), op), op).astype(np.float32)
    sc = columns(path, data, ["scale_0", "scale_1", "scale_2"], field="scales", finite=True)
    q = columns(path, data, ["rot_0", "rot_1", "rot_2", "rot_3"], field="quats", finite=True)
    nrm = columns(path, data, ["nx", "ny", "nz"], field="normals", finite=False) if has_normals else None
    sh = np.empty((n, n_coef, 3), np.float32)
    sh[:, 0, :] = f_dc
    sh[:, 1:, :] = f_rest.reshape(n, 3, n_coef - 1).transpose(0, 2, 1)
    try:
        return GaussianPly(means, sh, op, sc, q, nrm, has_normals)
    except ProxycodecError as e:
        raise ProxycodecError(e.reason, path) from None


def write_inria_ply(path: str | os.PathLike, ply: GaussianPly) -> None:
    """Write ``ply`` in 3DGS's exact layout (normals included, zeros unless given, when ``has_normals``)."""
    if not isinstance(ply, GaussianPly):
        raise ProxycodecError(f"write_inria_ply expects a GaussianPly, got {type(ply).__name__}")
    ply.validate()
    names = inria_attribute_names(ply.sh_degree, ply.has_normals)
    write_ply(path, float32_records(ply.attribute_matrix(), names))
