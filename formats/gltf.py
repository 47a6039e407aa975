"""glTF 2.0 binary (GLB) with the ``KHR_gaussian_splatting`` extension: a 3DGS scene as a point primitive.

Specification followed: ``extensions/2.0/Khronos/KHR_gaussian_splatting/README.md`` and
``schema/mesh.primitive.KHR_gaussian_splatting.schema.json`` of KhronosGroup/glTF at commit
``77b44be7bef26e01fb0b140e3d5bb1716421c5e9`` (2026-07-17). The extension's text was last changed by
``63770cc70a3709cf101a42cece0bdf602b37e2e7`` ("KHR_gaussian_splatting: Editorial review", #2567, 2026-04-15);
status there: Release Candidate (added by #2490, 2026-01-27).

File layout written by :func:`write_glb` (little-endian; every chunk starts and ends on a 4-byte boundary)::

    header   magic 'glTF' (0x46546C67) | version 2 | total length                      3 x uint32
    chunk 0  length | 'JSON' (0x4E4F534A) | UTF-8 JSON, padded with spaces (0x20) to a multiple of 4
    chunk 1  length | 'BIN\\0' (0x004E4942) | buffer 0, padded with zeros to a multiple of 4

The JSON has sorted keys and no whitespace: the same scene gives the same bytes. One scene, one node (no
transform), one mesh with one primitive of ``mode`` 0 (POINTS); per attribute one tightly packed bufferView
(target ARRAY_BUFFER, 4-byte aligned) and one accessor, in this order (``KHR:`` stands for
``KHR_gaussian_splatting:``)::

    POSITION                 VEC3   float   means; accessor min/max (glTF requires them)
    KHR:ROTATION             VEC4   float   quats wxyz -> xyzw ("the usual glTF order"), unit length
    KHR:SCALE                VEC3   float   exp(log scales): linear, never negative
    KHR:OPACITY              SCALAR float   sigmoid(logit), in [0, 1]
    KHR:SH_DEGREE_0_COEF_0   VEC3   float   sh[:, 0] as stored: the DC SH *coefficient* (RGB), not a colour
    KHR:SH_DEGREE_l_COEF_n   VEC3   float   sh[:, l*l + n] as stored; l = 1..degree, n = 0..2l (m = n - l)
    COLOR_0                  VEC4   ubyte normalized   optional fallback colour (``color_fallback``)

Conventions (from the spec text):

* The DC attribute holds the zeroth-order SH coefficient: diffuse colour = SH * 0.2820947917738781 + 0.5,
  exactly 3DGS's ``SH2RGB``. ``COLOR_0`` is only the optional point-cloud fallback (a "MAY"): clamp(SH * C0 +
  0.5) decoded from sRGB to linear (glTF colours are linear), opacity in alpha. The reader ignores it.
* SH ordering and normalisation equal the INRIA convention: degree l's coefficients are "packed from the
  lowest order (m) to highest"; real SH with the Condon-Shortley phase; the spec's constants and polynomials
  (-0.4886 y, 0.4886 z, -0.4886 x, 1.0925 xy, -1.0925 yz, ...) are those of 3DGS's ``eval_sh``, evaluated at
  the normalised direction from the camera to the splat. So ``SH_DEGREE_l_COEF_n`` is INRIA's coefficient l*l
  + n: no rescaling, no reordering (``f_rest_*`` is only INRIA's channel-major file layout of the same
  numbers; ``GaussianPly.sh`` is already [N, coefficient, RGB]).
* Quaternions: the spec's covariance factor C is 3DGS's R(q) S with q = (w, x, y, z) taken from xyzw, so only
  the storage order changes. Rotations must be unit quaternions: one whose norm is off 1 by more than 2**-20
  is divided by its norm (in float64); one unit to float32 precision is written unchanged (so read -> write is
  a fixed point); a zero quaternion (undefined in 3DGS) is written as the identity.
* Extension object (required: ``kernel``, ``colorSpace``): ``kernel`` "ellipse" (the only one defined: the
  original 3DGS shape, 3-sigma cut-off), ``colorSpace`` "srgb_rec709_display" (3DGS trains on sRGB images and
  blends in that space), and the optional ``projection`` "perspective" and ``sortingMethod`` "cameraDistance"
  (the defaults, written explicitly). The extension is in ``extensionsUsed`` only, not ``extensionsRequired``:
  a viewer without it draws points (the spec's fallback).
* Antialiasing: the extension cannot say that a scene was trained with the Mip-Splatting / gsplat
  "antialiased" screen-space filter (KhronosGroup/glTF issue #2564 proposes it; open). We record it in the
  extension object's ``extras`` as ``{"antialiased": true|false}``; other readers ignore it. :func:`read_glb`
  also accepts ``asset.extras.antialiased``.
* Coordinates: by default the numbers are the PLY's (no axis change, identity node), so files round-trip bit
  for bit where the conversions allow. glTF is +Y up while INRIA/COLMAP scenes are usually Y-down;
  ``write_glb(..., y_up=True)`` turns the scene 180 degrees about Z, as PlayCanvas splat-transform does for
  GLB (its ``Transform.PLY``): (x, y, z) -> (-x, -y, z), q -> (0, 0, 1, 0) * q, SH coefficient of order m
  times (-1)^|m|. Only sign flips and a permutation: exact. It is recorded as ``extras.proxycodecAxes =
  "ply-rotated-z180"``, and :func:`read_glb` undoes it (``y_up=None``: as recorded; ``y_up=True`` for
  splat-transform's files, which record nothing).
* Normals are not stored (3DGS writes zeros; a glTF ``NORMAL`` must be unit length): read scenes have zeros.

Conversions (float64, rounded once to float32) and their round-trip error:

* SCALE = exp(s), read back as log. Both values map to the same float32 linear scale, so |s' - s| <= 2**-23 +
  spacing(s). The reader picks, among the float32 neighbours of log(S), one whose exp rounds back to S
  exactly, so write(read(write(x))) gives the same bytes. Log scales above ~88.7 overflow float32 and are
  refused; a stored scale of 0 reads as log scale -104 (whose exp rounds to 0).
* OPACITY = sigmoid(x), read back as log(o) - log1p(-o) (again an exact inverse where one exists): |x' - x| <=
  2**-22 + 2**-23 (1 + e^max(x, 0)) + spacing(x): high opacities lose logit precision (inherent to storing
  alpha). o == 1.0 reads as +SATURATED_LOGIT, o == 0 as -SATURATED_LOGIT (as the PLY reader reads +-inf).

:func:`read_glb` reads any GLB (buffer 0 = the BIN chunk; no external or data URIs) with exactly one
``KHR_gaussian_splatting`` primitive of kernel "ellipse" and projection "perspective": float accessors and
every quantized form the spec allows (ROTATION signed byte/short normalized; SCALE unsigned byte/short,
normalized or not; OPACITY unsigned byte/short normalized; integer POSITION only with
``KHR_mesh_quantization``), interleaved (``byteStride``) or not. It refuses sparse accessors, accessors
without a bufferView and ``extensionsRequired`` beyond these two extensions. Data are returned in the
primitive's local space: a node transform is *not* applied (rotating SH needs Wigner-D matrices) but reported
in ``info["transform"]``. Every problem raises :class:`ProxycodecError` naming the file. Every accessor is
bounds-checked against the BIN chunk before anything is allocated: memory stays a small multiple of the file
size.
"""

from __future__ import annotations

import json
import math
import os
import re
import struct

import numpy as np

from ..errors import ProxycodecError
from ..fileio import write_bytes_atomic
from .inria_ply import SATURATED_LOGIT, SH_C0, GaussianPly

__all__ = [
    "EXTENSION",
    "SPEC_COMMIT",
    "encode_glb",
    "read_glb",
    "write_glb",
]

EXTENSION = "KHR_gaussian_splatting"
#: KhronosGroup/glTF commit whose extension text this module follows.
SPEC_COMMIT = "77b44be7bef26e01fb0b140e3d5bb1716421c5e9"

GLB_MAGIC = 0x46546C67  # b"glTF"
GLB_VERSION = 2
CHUNK_JSON = 0x4E4F534A  # b"JSON"
CHUNK_BIN = 0x004E4942  # b"BIN\0"
ARRAY_BUFFER = 34962
MODE_POINTS = 0

ROTATION = f"{EXTENSION}:ROTATION"
SCALE = f"{EXTENSION}:SCALE"
OPACITY = f"{EXTENSION}:OPACITY"
AXES_KEY = "proxycodecAxes"
AXES_Z180 = "ply-rotated-z180"

#: glTF componentType -> numpy dtype.
_DTYPES = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
_NCOMP = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}
_FLOAT, _BYTE, _UBYTE, _SHORT, _USHORT = 5126, 5120, 5121, 5122, 5123
#: (componentType, normalized) pairs the spec's attribute table allows.
_ALLOWED = {
    ROTATION: ("VEC4", {(_FLOAT, False), (_BYTE, True), (_SHORT, True)}),
    SCALE: ("VEC3", {(_FLOAT, False), (_UBYTE, False), (_UBYTE, True), (_USHORT, False), (_USHORT, True)}),
    OPACITY: ("SCALAR", {(_FLOAT, False), (_UBYTE, True), (_USHORT, True)}),
}
_QUANTIZED_POSITION = {(t, nm) for t in (_BYTE, _UBYTE, _SHORT, _USHORT) for nm in (False, True)}
_SH_RE = re.compile(rf"^{EXTENSION}:SH_DEGREE_(\d+)_COEF_(\d+)$")
#: Extensions a file may require and still be read here.
_READABLE_REQUIRED = {EXTENSION, "KHR_mesh_quantization"}

#: Log scale stored for a linear scale of exactly 0 (float32 exp(-104) rounds to 0, so it round-trips).
ZERO_SCALE_LOG = -104.0
_QUAT_UNIT_TOL = 2.0**-20


def _sh_name(degree: int, coef: int) -> str:
    return f"{EXTENSION}:SH_DEGREE_{degree}_COEF_{coef}"


def _sh_signs(n_coef: int) -> np.ndarray:
    """(-1)^|m| for each SH coefficient in 3DGS order (index l*l + l + m): a 180-degree turn about Z."""
    out = np.empty(n_coef, np.float32)
    for k in range(n_coef):
        deg = math.isqrt(k)
        out[k] = -1.0 if abs(k - deg * deg - deg) % 2 else 1.0
    return out


def _rotate_z180(means, quats_wxyz, sh, inverse: bool):
    """Exact 180-degree rotation about Z (or its inverse) of positions, wxyz quaternions and SH."""
    m = means.copy()
    m[:, :2] = -m[:, :2]
    w, x, y, z = (quats_wxyz[:, i] for i in range(4))
    # r * q with r = (w=0, x=0, y=0, z=1): (w, x, y, z) -> (-z, -y, x, w); r^-1 * q: -> (z, y, -x, -w)
    q = np.stack([z, y, -x, -w] if inverse else [-z, -y, x, w], axis=1)
    return m, np.ascontiguousarray(q, dtype=np.float32), sh * _sh_signs(sh.shape[1])[None, :, None]


def _srgb_to_linear(c: np.ndarray) -> np.ndarray:
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _unit_quats_xyzw(quats_wxyz: np.ndarray) -> np.ndarray:
    q64 = quats_wxyz.astype(np.float64)
    norm = np.sqrt((q64 * q64).sum(axis=1))
    keep = np.abs(norm - 1.0) <= _QUAT_UNIT_TOL
    zero = norm == 0.0
    unit = np.where(keep[:, None], q64, q64 / np.where(zero, 1.0, norm)[:, None])
    unit[zero] = (1.0, 0.0, 0.0, 0.0)
    out = np.where(keep[:, None], quats_wxyz, unit.astype(np.float32))
    return np.ascontiguousarray(out[:, [1, 2, 3, 0]], dtype=np.float32)


def _sigmoid64(x: np.ndarray) -> np.ndarray:
    x = x.astype(np.float64)
    e = np.exp(-np.abs(x))
    return np.where(x >= 0, 1.0 / (1.0 + e), e / (1.0 + e))


def encode_glb(
    ply: GaussianPly,
    *,
    antialiased: bool = False,
    generator: str = "proxycodec",
    y_up: bool = False,
    color_fallback: bool = True,
) -> bytes:
    """The GLB bytes :func:`write_glb` writes (see the module docstring for the layout and conversions)."""
    if not isinstance(ply, GaussianPly):
        raise ProxycodecError(f"write_glb expects a GaussianPly, got {type(ply).__name__}")
    if not isinstance(generator, str):
        raise ProxycodecError(f"write_glb: generator must be a string, got {type(generator).__name__}")
    ply.validate()
    n = ply.n_gaussians
    if n == 0:
        raise ProxycodecError("cannot write an empty scene as glTF: accessors need count >= 1")
    means, quats, sh = ply.means, ply.quats, ply.sh
    if y_up:
        means, quats, sh = _rotate_z180(means, quats, sh, inverse=False)
    with np.errstate(over="ignore"):
        scale = np.exp(ply.scales.astype(np.float64)).astype(np.float32)
    if not np.isfinite(scale).all():
        bad = int(np.flatnonzero(~np.isfinite(scale).all(axis=1))[0])
        raise ProxycodecError(f"log scale of Gaussian {bad} overflows float32 when exponentiated "
                              f"({float(ply.scales[bad].max())})")
    opacity = _sigmoid64(ply.opacities).astype(np.float32)
    attributes: list[tuple[str, np.ndarray, int, bool, str]] = [
        ("POSITION", means, _FLOAT, False, "VEC3"),
        (ROTATION, _unit_quats_xyzw(quats), _FLOAT, False, "VEC4"),
        (SCALE, scale, _FLOAT, False, "VEC3"),
        (OPACITY, opacity, _FLOAT, False, "SCALAR"),
    ]
    for k in range(sh.shape[1]):
        deg = math.isqrt(k)
        attributes.append((_sh_name(deg, k - deg * deg), sh[:, k, :], _FLOAT, False, "VEC3"))
    if color_fallback:
        rgb = np.clip(sh[:, 0, :].astype(np.float64) * SH_C0 + 0.5, 0.0, 1.0)
        rgba = np.concatenate([_srgb_to_linear(rgb), opacity[:, None].astype(np.float64)], axis=1)
        attributes.append(("COLOR_0", np.round(rgba * 255.0).astype(np.uint8), _UBYTE, True, "VEC4"))

    views, accessors, prim_attrs, blobs = [], [], {}, []
    offset = 0
    for i, (name, data, ctype, normalized, atype) in enumerate(attributes):
        raw = np.ascontiguousarray(data, dtype=np.dtype(_DTYPES[ctype]).newbyteorder("<")).tobytes()
        views.append({"buffer": 0, "byteLength": len(raw), "byteOffset": offset, "target": ARRAY_BUFFER})
        acc = {"bufferView": i, "componentType": ctype, "count": n, "type": atype}
        if normalized:
            acc["normalized"] = True
        if name == "POSITION":
            acc["min"] = [float(v) for v in data.min(axis=0)]
            acc["max"] = [float(v) for v in data.max(axis=0)]
        accessors.append(acc)
        prim_attrs[name] = i
        pad = -len(raw) % 4
        blobs.append(raw + b"\0" * pad)
        offset += len(raw) + pad
    bin_chunk = b"".join(blobs)
    extras: dict = {"antialiased": bool(antialiased)}
    if y_up:
        extras[AXES_KEY] = AXES_Z180
    gltf = {
        "accessors": accessors,
        "asset": {"generator": generator, "version": "2.0"},
        "bufferViews": views,
        "buffers": [{"byteLength": len(bin_chunk)}],
        "extensionsUsed": [EXTENSION],
        "meshes": [{"primitives": [{
            "attributes": prim_attrs,
            "extensions": {EXTENSION: {
                "colorSpace": "srgb_rec709_display",
                "extras": extras,
                "kernel": "ellipse",
                "projection": "perspective",
                "sortingMethod": "cameraDistance",
            }},
            "mode": MODE_POINTS,
        }]}],
        "nodes": [{"mesh": 0}],
        "scene": 0,
        "scenes": [{"nodes": [0]}],
    }
    js = json.dumps(gltf, sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=False).encode()
    js += b" " * (-len(js) % 4)
    total = 12 + 8 + len(js) + 8 + len(bin_chunk)
    if total > 0xFFFFFFFF:
        raise ProxycodecError(f"scene too large for GLB: {total} bytes, the format's limit is 4 GiB - 1 "
                              f"({n} Gaussians of SH degree {ply.sh_degree})")
    return b"".join([
        struct.pack("<III", GLB_MAGIC, GLB_VERSION, total),
        struct.pack("<II", len(js), CHUNK_JSON), js,
        struct.pack("<II", len(bin_chunk), CHUNK_BIN), bin_chunk,
    ])


def write_glb(
    path: str | os.PathLike,
    ply: GaussianPly,
    *,
    antialiased: bool = False,
    generator: str = "proxycodec",
    y_up: bool = False,
    color_fallback: bool = True,
) -> int:
    """Write ``ply`` as a ``KHR_gaussian_splatting`` GLB (atomically); returns the number of bytes written.

    ``antialiased`` goes to the extension object's ``extras`` (the extension has no property for it);
    ``y_up=True`` turns the scene 180 degrees about Z (PLY Y-down -> glTF Y-up, as splat-transform does);
    ``color_fallback`` adds ``COLOR_0`` for viewers without the extension. Same input, same bytes.
    """
    data = encode_glb(ply, antialiased=antialiased, generator=generator, y_up=y_up,
                      color_fallback=color_fallback)
    write_bytes_atomic(path, data)
    return len(data)


# ------------------------------------------------------------------------------------------------- reading


class _Bad(Exception):
    """Internal: a malformed file (turned into ProxycodecError with the path)."""


def _int(obj: dict, key: str, where: str, default: int | None = None, minimum: int = 0) -> int:
    v = obj.get(key, default)
    if v is None:
        raise _Bad(f"{where} lacks {key!r}")
    if isinstance(v, bool) or not isinstance(v, int) or v < minimum:
        raise _Bad(f"{where}.{key} must be an integer >= {minimum}, got {v!r}")
    return v


def _dict(v, where: str) -> dict:
    if not isinstance(v, dict):
        raise _Bad(f"{where} must be a JSON object")
    return v


def _list(gltf: dict, key: str) -> list:
    v = gltf.get(key, [])
    if not isinstance(v, list):
        raise _Bad(f"{key} must be a JSON array")
    return v


def _item(gltf: dict, key: str, index: int, where: str) -> dict:
    items = _list(gltf, key)
    if not 0 <= index < len(items):
        raise _Bad(f"{where} refers to {key}[{index}], but the file has {len(items)}")
    return _dict(items[index], f"{key}[{index}]")


def _split_glb(data: bytes) -> tuple[bytes, memoryview | None]:
    if len(data) < 12:
        raise _Bad(f"truncated: {len(data)} bytes, a GLB header alone is 12")
    magic, version, length = struct.unpack_from("<III", data, 0)
    if magic != GLB_MAGIC:
        raise _Bad(f"not a GLB file (magic {data[:4]!r}, expected b'glTF')")
    if version != GLB_VERSION:
        raise _Bad(f"GLB version {version} is not supported (expected 2)")
    if length != len(data):
        raise _Bad(f"GLB header declares {length} bytes but the file has {len(data)}"
                   + (" (truncated)" if length > len(data) else ""))
    chunks = []
    pos = 12
    while pos < length:
        if pos + 8 > length:
            raise _Bad(f"truncated chunk header at byte {pos}")
        clen, ctype = struct.unpack_from("<II", data, pos)
        if clen > length - pos - 8:
            raise _Bad(f"chunk at byte {pos} declares {clen} bytes, beyond the end of the file")
        if clen % 4:
            raise _Bad(f"chunk at byte {pos} has length {clen}, not a multiple of 4")
        chunks.append((ctype, pos + 8, clen))
        pos += 8 + clen
    if not chunks or chunks[0][0] != CHUNK_JSON:
        raise _Bad("the first GLB chunk must be JSON")
    _, js_at, js_len = chunks[0]
    bin_chunk = None
    if len(chunks) > 1 and chunks[1][0] == CHUNK_BIN:
        _, b_at, b_len = chunks[1]
        bin_chunk = memoryview(data)[b_at:b_at + b_len]
    later = [c[0] for c in chunks[1:]]
    if later.count(CHUNK_JSON) or later[1:].count(CHUNK_BIN):
        raise _Bad("a GLB holds one JSON chunk and at most one BIN chunk, right after it")
    return data[js_at:js_at + js_len], bin_chunk


def _parse_json(raw: bytes) -> dict:
    def no_constant(name):
        raise _Bad(f"JSON holds {name}, which is not valid JSON")

    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise _Bad(f"JSON chunk is not UTF-8 ({e.reason} at byte {e.start})") from None
    try:
        gltf = json.loads(text.lstrip("\ufeff"), parse_constant=no_constant)
    except json.JSONDecodeError as e:
        raise _Bad(f"JSON chunk does not parse: {e.msg} at line {e.lineno} column {e.colno}") from None
    except RecursionError:
        raise _Bad("JSON chunk is nested too deeply") from None
    return _dict(gltf, "the glTF JSON")


class _Accessors:
    def __init__(self, gltf: dict, bin_chunk: memoryview | None):
        self.gltf = gltf
        buffers = _list(gltf, "buffers")
        self.buffer0 = None
        if buffers:
            b0 = _dict(buffers[0], "buffers[0]")
            if "uri" in b0:
                raise _Bad("buffers[0] has a uri: only GLB-embedded data (the BIN chunk) is supported")
            if bin_chunk is None:
                raise _Bad("buffers[0] refers to the BIN chunk, but the file has none")
            blen = _int(b0, "byteLength", "buffers[0]", minimum=1)
            if blen > len(bin_chunk):
                raise _Bad(f"buffers[0].byteLength {blen} exceeds the BIN chunk ({len(bin_chunk)} bytes)")
            self.buffer0 = bin_chunk[:blen]

    def read(self, index, semantic: str) -> tuple[np.ndarray, dict]:
        """Accessor ``index`` as an array [count, ncomp] of its stored dtype (bounds-checked, then copied)."""
        if isinstance(index, bool) or not isinstance(index, int):
            raise _Bad(f"primitive attribute {semantic} must be an accessor index, got {index!r}")
        acc = _item(self.gltf, "accessors", index, f"attribute {semantic}")
        where = f"accessors[{index}] ({semantic})"
        if "sparse" in acc:
            raise _Bad(f"{where} is sparse; sparse accessors are not supported")
        if "bufferView" not in acc:
            raise _Bad(f"{where} has no bufferView (zero-filled accessors are not supported)")
        ctype = _int(acc, "componentType", where)
        if ctype not in _DTYPES:
            raise _Bad(f"{where}.componentType {ctype} is not a glTF component type")
        atype = acc.get("type")
        if atype not in _NCOMP:
            raise _Bad(f"{where}.type {atype!r} is not SCALAR/VEC2/VEC3/VEC4")
        count = _int(acc, "count", where, minimum=1)
        normalized = acc.get("normalized", False)
        if not isinstance(normalized, bool):
            raise _Bad(f"{where}.normalized must be a boolean")
        vi = _int(acc, "bufferView", where)
        view = _item(self.gltf, "bufferViews", vi, where)
        vwhere = f"bufferViews[{vi}]"
        if _int(view, "buffer", vwhere) != 0 or self.buffer0 is None:
            raise _Bad(f"{vwhere} does not refer to the GLB's BIN chunk (buffer 0)")
        v_off = _int(view, "byteOffset", vwhere, default=0)
        v_len = _int(view, "byteLength", vwhere, minimum=1)
        if v_off + v_len > len(self.buffer0):
            raise _Bad(f"{vwhere} spans bytes {v_off}..{v_off + v_len}, "
                       f"beyond buffer 0 ({len(self.buffer0)} bytes)")
        dtype = np.dtype(_DTYPES[ctype]).newbyteorder("<")
        ncomp = _NCOMP[atype]
        elem = dtype.itemsize * ncomp
        stride = _int(view, "byteStride", vwhere, default=elem, minimum=1)
        if stride < elem:
            raise _Bad(f"{vwhere}.byteStride {stride} is smaller than one {atype} element ({elem} bytes)")
        a_off = _int(acc, "byteOffset", where, default=0)
        need = a_off + stride * (count - 1) + elem
        if need > v_len:
            raise _Bad(f"{where} needs {need} bytes of {vwhere}, which has {v_len} (count {count}): "
                       "accessor beyond the buffer")
        region = self.buffer0[v_off + a_off: v_off + a_off + stride * (count - 1) + elem]
        arr = np.ndarray((count, ncomp), dtype=dtype, buffer=region, strides=(stride, dtype.itemsize))
        meta = {"componentType": ctype, "normalized": normalized, "type": atype, "count": count}
        return np.array(arr, dtype=dtype.newbyteorder("=")), meta


def _to_float(arr: np.ndarray, ctype: int, normalized: bool) -> np.ndarray:
    """glTF dequantization: signed normalized max(c / (2^(b-1) - 1), -1), unsigned c / (2^b - 1)."""
    if ctype == _FLOAT:
        return arr.astype(np.float32)
    if not normalized:
        return arr.astype(np.float32)
    info = np.iinfo(arr.dtype)
    out = arr.astype(np.float64) / info.max
    return np.maximum(out, -1.0).astype(np.float32)


def _finite(name: str, a: np.ndarray) -> None:
    bad = ~np.isfinite(a)
    if bad.any():
        row = int(np.flatnonzero(bad.reshape(a.shape[0], -1).any(axis=1))[0])
        raise _Bad(f"{name} holds NaN or Inf (first at splat {row})")


def _invert_f32(y: np.ndarray, forward, start: np.ndarray, steps: int = 3) -> np.ndarray:
    """Float32 x near ``start`` with forward(x) == y bit for bit where one lies within ``steps`` ulps."""
    x = start.astype(np.float32)
    ok = forward(x) == y
    for direction in (np.inf, -np.inf):
        cand = x.copy()
        for _ in range(steps):
            if ok.all():
                return x
            cand = np.nextafter(cand, np.float32(direction))
            hit = ~ok & (forward(cand) == y)
            x = np.where(hit, cand, x)
            ok |= hit
    return x


def _exp32(x: np.ndarray) -> np.ndarray:
    with np.errstate(over="ignore"):
        return np.exp(x.astype(np.float64)).astype(np.float32)


def _sigmoid32(x: np.ndarray) -> np.ndarray:
    return _sigmoid64(x).astype(np.float32)


def _log_scales(s: np.ndarray) -> np.ndarray:
    s64 = s.astype(np.float64)
    with np.errstate(divide="ignore"):
        start = np.where(s64 > 0, np.log(np.where(s64 > 0, s64, 1.0)), ZERO_SCALE_LOG)
    return _invert_f32(s, _exp32, start)


def _logits(o: np.ndarray) -> np.ndarray:
    o64 = o.astype(np.float64)
    inner = (o64 > 0) & (o64 < 1)
    safe = np.where(inner, o64, 0.5)
    edge = np.where(o64 >= 1, SATURATED_LOGIT, -SATURATED_LOGIT)
    start = np.where(inner, np.log(safe) - np.log1p(-safe), edge)
    return _invert_f32(o, _sigmoid32, start)


def _numbers(v, n: int) -> bool:
    return isinstance(v, list) and len(v) == n and all(
        isinstance(c, (int, float)) and not isinstance(c, bool) and math.isfinite(c) for c in v)


def _node_matrix(node: dict, where: str) -> np.ndarray:
    if "matrix" in node:
        m = node["matrix"]
        if not _numbers(m, 16):
            raise _Bad(f"{where}.matrix must be 16 numbers")
        return np.array(m, np.float64).reshape(4, 4).T  # glTF stores column-major

    def vec(key, n, default):
        v = node.get(key, default)
        if not _numbers(v, n):
            raise _Bad(f"{where}.{key} must be {n} numbers")
        return [float(c) for c in v]

    t, (x, y, z, w) = vec("translation", 3, [0, 0, 0]), vec("rotation", 4, [0, 0, 0, 1])
    s = vec("scale", 3, [1, 1, 1])
    r = np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])
    m = np.eye(4)
    m[:3, :3] = r * np.array(s)[None, :]
    m[:3, 3] = t
    return m


def _mesh_transforms(gltf: dict, mesh_index: int) -> list[np.ndarray]:
    """Global matrices of the nodes that instantiate ``mesh_index``."""
    nodes = [_dict(n, f"nodes[{i}]") for i, n in enumerate(_list(gltf, "nodes"))]
    parent: dict[int, int] = {}
    for i, node in enumerate(nodes):
        children = node.get("children", [])
        if not isinstance(children, list):
            raise _Bad(f"nodes[{i}].children must be an array")
        for c in children:
            if isinstance(c, bool) or not isinstance(c, int) or not 0 <= c < len(nodes) or c in parent:
                raise _Bad(f"nodes[{i}].children holds an invalid or shared node index {c!r}")
            parent[c] = i
    out = []
    for i, node in enumerate(nodes):
        if node.get("mesh") != mesh_index or isinstance(node.get("mesh"), bool):
            continue
        m, j, seen = np.eye(4), i, set()
        while True:
            if j in seen:
                raise _Bad(f"nodes[{i}] lies on a cycle of node children")
            seen.add(j)
            m = _node_matrix(nodes[j], f"nodes[{j}]") @ m
            if j not in parent:
                break
            j = parent[j]
        out.append(m)
    return out


def _parse(path, data: bytes, y_up: bool | None) -> tuple[GaussianPly, dict]:
    js, bin_chunk = _split_glb(data)
    gltf = _parse_json(js)
    asset = _dict(gltf.get("asset"), "asset") if "asset" in gltf else None
    if asset is None or asset.get("version") != "2.0":
        raise _Bad("asset.version must be \"2.0\"")
    required = _list(gltf, "extensionsRequired")
    unknown = [e for e in required if e not in _READABLE_REQUIRED]
    if unknown:
        raise _Bad(f"the file requires extensions this reader does not support: {unknown}")
    used = _list(gltf, "extensionsUsed")
    if EXTENSION not in used:
        raise _Bad(f"not a Gaussian splat glTF: {EXTENSION} is not in extensionsUsed")

    found = []
    for mi, mesh in enumerate(_list(gltf, "meshes")):
        prims = _dict(mesh, f"meshes[{mi}]").get("primitives", [])
        if not isinstance(prims, list):
            raise _Bad(f"meshes[{mi}].primitives must be an array")
        for pi, prim in enumerate(prims):
            ext = _dict(prim, f"meshes[{mi}].primitives[{pi}]").get("extensions", {})
            if EXTENSION in _dict(ext, f"meshes[{mi}].primitives[{pi}].extensions"):
                found.append((mi, pi, prim))
    if not found:
        raise _Bad(f"no mesh primitive carries the {EXTENSION} extension")
    if len(found) > 1:
        raise _Bad(f"{len(found)} primitives carry {EXTENSION}; reading more than one is not supported")
    mi, pi, prim = found[0]
    where = f"meshes[{mi}].primitives[{pi}]"
    ext = _dict(prim["extensions"][EXTENSION], f"{where}.extensions.{EXTENSION}")
    for key in ("kernel", "colorSpace"):
        if not isinstance(ext.get(key), str):
            raise _Bad(f"{where}: the {EXTENSION} object lacks its required string property {key!r}")
    if ext["kernel"] != "ellipse":
        raise _Bad(f"{where}: kernel {ext['kernel']!r} is not supported (only \"ellipse\")")
    projection = ext.get("projection", "perspective")
    if projection != "perspective":
        raise _Bad(f"{where}: projection {projection!r} is not supported (only \"perspective\")")
    sorting = ext.get("sortingMethod", "cameraDistance")
    mode = prim.get("mode", 4)
    if mode != MODE_POINTS:
        raise _Bad(f"{where}.mode is {mode!r}; a {EXTENSION} primitive must be POINTS (0)")
    attrs = _dict(prim.get("attributes"), f"{where}.attributes")

    acc = _Accessors(gltf, bin_chunk)
    quantized_pos = "KHR_mesh_quantization" in used

    def get(semantic: str, atype: str, allowed) -> np.ndarray:
        if semantic not in attrs:
            raise _Bad(f"{where} lacks the required attribute {semantic}")
        arr, meta = acc.read(attrs[semantic], semantic)
        if meta["type"] != atype:
            raise _Bad(f"attribute {semantic} must be {atype}, got {meta['type']}")
        if (meta["componentType"], meta["normalized"]) not in allowed:
            raise _Bad(f"attribute {semantic}: componentType {meta['componentType']}"
                       f"{' normalized' if meta['normalized'] else ''} is not allowed by {EXTENSION}")
        out = _to_float(arr, meta["componentType"], meta["normalized"])
        _finite(semantic, out)
        return out

    pos_allowed = {(_FLOAT, False)} | (_QUANTIZED_POSITION if quantized_pos else set())
    means = get("POSITION", "VEC3", pos_allowed)
    n = means.shape[0]
    quats_xyzw = get(ROTATION, *_ALLOWED[ROTATION])
    scale = get(SCALE, *_ALLOWED[SCALE])
    opacity = get(OPACITY, *_ALLOWED[OPACITY])[:, 0]

    degrees: dict[int, set[int]] = {}
    for name in attrs:
        m = _SH_RE.match(name) if isinstance(name, str) else None
        if m:
            degrees.setdefault(int(m.group(1)), set()).add(int(m.group(2)))
    if 0 not in degrees:
        raise _Bad(f"{where} lacks the required attribute {_sh_name(0, 0)}")
    degree = max(degrees)
    if degree > 3:
        raise _Bad(f"SH degree {degree} is not supported (0..3)")
    for deg in range(degree + 1):
        if degrees.get(deg) != set(range(2 * deg + 1)):
            have = sorted(degrees.get(deg, ()))
            raise _Bad(f"SH degree {deg} is partially defined (coefficients {have} of 0..{2 * deg}); "
                       "every degree up to the highest must be complete")
    sh = np.empty((n, (degree + 1) ** 2, 3), np.float32)
    for k in range(sh.shape[1]):
        deg = math.isqrt(k)
        name = _sh_name(deg, k - deg * deg)
        coef = get(name, "VEC3", {(_FLOAT, False)})
        if coef.shape[0] != n:
            raise _Bad(f"attribute {name} has {coef.shape[0]} elements, POSITION has {n}")
        sh[:, k, :] = coef
    for name, a in ((ROTATION, quats_xyzw), (SCALE, scale), (OPACITY, opacity)):
        if a.shape[0] != n:
            raise _Bad(f"attribute {name} has {a.shape[0]} elements, POSITION has {n}")
    if (scale < 0).any():
        first = int(np.flatnonzero((scale < 0).any(axis=1))[0])
        raise _Bad(f"{SCALE} holds negative values (first at splat {first})")
    if ((opacity < 0) | (opacity > 1)).any():
        first = int(np.flatnonzero((opacity < 0) | (opacity > 1))[0])
        raise _Bad(f"{OPACITY} holds values outside [0, 1] (first at splat {first}: {float(opacity[first])})")

    extras = ext.get("extras", {})
    extras = extras if isinstance(extras, dict) else {}
    asset_extras = asset.get("extras", {}) if isinstance(asset.get("extras", {}), dict) else {}
    aa = extras.get("antialiased", asset_extras.get("antialiased"))
    recorded_axes = extras.get(AXES_KEY)
    if y_up is None:
        y_up = recorded_axes == AXES_Z180

    quats = np.ascontiguousarray(quats_xyzw[:, [3, 0, 1, 2]])
    if y_up:
        means, quats, sh = _rotate_z180(means, quats, sh, inverse=True)
    ply = GaussianPly(means, sh, _logits(opacity), _log_scales(scale), quats)
    transforms = _mesh_transforms(gltf, mi)
    non_identity = [m for m in transforms if not np.allclose(m, np.eye(4), rtol=0, atol=1e-12)]
    generator = asset.get("generator")
    info = {
        "count": n,
        "sh_degree": degree,
        "antialiased": bool(aa) if isinstance(aa, bool) else False,
        "antialiased_recorded": isinstance(aa, bool),
        "generator": generator if isinstance(generator, str) else None,
        "kernel": ext["kernel"],
        "color_space": ext["colorSpace"],
        "projection": projection,
        "sorting_method": sorting,
        "y_up_undone": bool(y_up),
        "transform": non_identity[0].tolist() if non_identity else None,
        "instances": len(transforms),
        "spec_commit": SPEC_COMMIT,
    }
    return ply, info


def read_glb(path: str | os.PathLike, *, y_up: bool | None = None) -> tuple[GaussianPly, dict]:
    """Read a ``KHR_gaussian_splatting`` GLB -> (GaussianPly with log scales / logits / wxyz, info).

    ``info``: count, sh_degree, antialiased (False unless recorded; antialiased_recorded says whether it was),
    generator, kernel, color_space, projection, sorting_method, y_up_undone, transform (the global 4x4 matrix,
    row-major, of the node instantiating the mesh, when not identity; not applied), instances, spec_commit.
    ``y_up``: undo a 180-degree turn about Z (None: only when the file records that :func:`write_glb` did it).
    Raises :class:`ProxycodecError` naming the file on any problem.
    """
    try:
        with open(path, "rb") as fh:
            data = fh.read()
    except FileNotFoundError:
        raise ProxycodecError("file not found", path) from None
    except IsADirectoryError:
        raise ProxycodecError("is a directory, expected a GLB file", path) from None
    except PermissionError:
        raise ProxycodecError("permission denied", path) from None
    except OSError as e:
        raise ProxycodecError(f"cannot read: {e.strerror or e}", path) from None
    try:
        return _parse(path, data, y_up)
    except _Bad as e:
        raise ProxycodecError(str(e), path) from None
    except ProxycodecError as e:
        raise ProxycodecError(e.reason, path) from None
    except (ValueError, TypeError, KeyError, IndexError, OverflowError, struct.error) as e:
        raise ProxycodecError(f"malformed glTF: {type(e).__name__}: {e}", path) from None
