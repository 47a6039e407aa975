"""Niantic SPZ (compressed 3D Gaussian splats): our own writer and reader, byte-compatible with the reference.

Source read: github.com/nianticlabs/spz (HEAD 21715c3b, July 2026): ``README.md`` (the format section),
``src/cc/load-spz.cc`` (``packGaussians``, ``saveSpz``, ``loadSpzPacked``, ``unpackGaussians``,
``deserializePackedGaussians``, ``loadSplatFromPly``), ``src/cc/load-spz.h``, ``src/cc/splat-utils.h``
(``colorScale``, ``unquantizeSH``, ``unpackQuaternion*``), ``src/cc/splat-types.h`` (``CoordinateSystem``,
``coordinateConverter``) and ``extensions/README.md``. Cross-checked against PlayCanvas splat-transform 2.7.1,
which runs that library compiled to WebAssembly (tests/test_formats_spz.py).

Containers (all integers little-endian)
---------------------------------------
Version 4 (the default; not compressed as a whole)::

    0   u32 magic 0x5053474E ("NGSP")     4  u32 version (4)        8  u32 numPoints
    12  u8 shDegree   13 u8 fractionalBits   14 u8 flags   15 u8 numStreams
    16  u32 tocByteOffset (32 unless extension records sit in [32, tocByteOffset))
    20  12 reserved zero bytes
    tocByteOffset: numStreams x (u64 compressedSize, u64 uncompressedSize)
    then the numStreams zstd frames back to back, to the end of the file.

The streams are, in this order, positions, alphas, colors, scales, rotations, SH, empty ones left out (so 5
streams at SH degree 0, else 6). Each is one zstd frame at level 12 (the reference's ``compressZstd``), content
size in the frame header, no checksum.

Versions 2 and 3 (legacy): one gzip stream (zlib level 6, memLevel 9, mtime 0, OS byte 3: what the reference's
``compressGzipped`` writes) of a 16-byte header ``u32 magic, u32 version, u32 numPoints, u8 shDegree,
u8 fractionalBits, u8 flags, u8 reserved`` followed by the six attribute arrays above, concatenated.

Flags: 0x1 antialiased (trained with Mip-Splatting's filter), 0x2 extension records present (``[u32 type]
[u32 byteLength][payload]``; in v4 between the header and the TOC, in v2/v3 after the SH array). The only record
that changes the data, ``SPZ_ADOBE_coordinate_system`` (0xADBE0003, payload u32 ``CoordinateSystem``), is honoured
for the unrotated family (LDB..RUF); other record types are skipped, as the reference does.

Attributes, per Gaussian, and the round-trip error of each (``write`` then ``read``)
-----------------------------------------------------------------------------------
* positions, 9 bytes: each coordinate ``round(x * 2^fractionalBits)`` as a 24-bit two's-complement integer
  (fractionalBits 12 by default: 1/4096 steps, range +-2048). Error <= 2^-fractionalBits / 2. A coordinate out
  of range is refused (the reference silently wraps it).
* alphas, 1 byte: ``round(sigmoid(opacity_logit) * 255)``. Error <= 0.5/255 on the activated alpha. Bytes 0 and
  255 decode to a logit of -inf/+inf; we return -+``SATURATED_LOGIT`` (30), which re-encodes to the same byte.
* colors, 3 bytes: the DC SH coefficient, ``round(f_dc * 0.15 * 255 + 127.5)`` (colour scale 0.15: a "wide"
  range, f_dc in [-3.33, 3.33], not 1/255 steps of the rendered colour). Error <= 0.5 / 38.25 = 0.0131 in
  f_dc units inside that range, values beyond it clamp.
* scales, 3 bytes: ``round((log_scale + 10) * 16)``. Error <= 1/32 in log units inside [-10, 5.9375].
* rotations, v3 and v4, 4 bytes, "smallest three": the quaternion is normalised and negated if needed so its
  largest-magnitude component is positive; a u32 holds that component's index (xyzw order, 0..3) in bits 30-31
  and, for the other three in increasing index order from bit 20 down to bit 0, 10 bits each: a sign bit (bit 9)
  and ``mag = floor(511 * |q_i| / sqrt(1/2) + 0.5)`` (9 bits). Decoding rebuilds the largest one as
  ``sqrt(1 - sum of squares)``. Error, up to the sign of q (the same rotation): each stored component
  <= eps = sqrt(1/2) / 1022 = 6.9e-4, any component <= 3 eps (the rebuilt one inherits the others' errors,
  |q_max| >= 1/2). The reference's decode is not always re-encodable to the same bytes: a stored -0 loses its
  sign, and near a tie of the two largest components the rebuilt one can come out below a stored one, so the
  encoder picks another index (~0.25% of random rotations). Our reader returns the reference's values except
  for those rotations, where it returns the nearest value that re-encodes to the same bytes (``_settle``: stored
  components moved toward zero inside their bins, so within 2 eps).
  v2 (read only here): 3 bytes, x, y, z of the normalised quaternion with w >= 0, ``round(q * 127.5 + 127.5)``.
* SH (degree >= 1), (degree+1)^2 - 1 coefficients x 3 channels bytes, coefficient-major, channel fastest:
  ``q = round(x * 128) + 128``, snapped to a multiple of ``2^(8-bits)`` (half up) and clamped to [0, 255];
  decoded as ``(q - 128) / 128``. bits = 5 for the 3 degree-1 coefficients, 4 for degree 2 and 3 (the
  reference's defaults ``sh1Bits``/``shRestBits``). Error <= 4.5/128 (degree 1) and <= 8.5/128 (degree 2, 3)
  inside [-1, 127/128]; values beyond clamp.

All encoding arithmetic is float32 in the reference's order, with C ``std::round`` (half away from zero), so our
bytes equal the reference's for the same input (sigmoid's exp is evaluated correctly rounded; libm's ``expf`` may
differ by an ulp, which changes an alpha byte only at an exact rounding tie). Decoded values equal the reference's
``loadSpz`` (bar the rotations above and the +-inf alphas) and are exactly re-encodable:
``write(read(write(x))) == write(x)``.

Coordinate convention
---------------------
SPZ stores RUB (x right, y up, z back: OpenGL / three.js). A 3DGS PLY is RDF (x right, y down, z forward:
COLMAP / OpenCV), the reference's ``CoordinateSystem::RDF``, "PLY coordinate system". :func:`write_spz` takes a
:class:`GaussianPly` as in its PLY (RDF) and converts as the reference's ``saveSpz`` does with
``PackOptions.from = RDF`` (what splat-transform does; the reference CLI ``ply_to_spz`` leaves both systems
UNSPECIFIED and so stores the PLY's axes unconverted, which the spec warns against): a 180 degree rotation about
x, i.e. ``y -> -y, z -> -z`` for positions, quaternion ``(w, x, y, z) -> (w, x, -y, -z)`` and sign flips of the
SH coefficients odd in y*z (band 1: -,-,+; band 2: -,+,+,-,+; band 3: -,+,-,-,+,-,+). :func:`read_spz` undoes it
and returns RDF again, like ``loadSpz`` with ``UnpackOptions.to = RDF``.
"""

from __future__ import annotations

import os
import struct
import zlib

import numpy as np
import zstandard

from ..errors import ProxycodecError
from ..fileio import write_bytes_atomic
from .inria_ply import SATURATED_LOGIT, GaussianPly

__all__ = [
    "COLOR_SCALE",
    "FLAG_ANTIALIASED",
    "FLAG_HAS_EXTENSIONS",
    "SH1_BITS",
    "SH_REST_BITS",
    "SPZ_MAGIC",
    "ZSTD_LEVEL",
    "decode_spz",
    "encode_spz",
    "read_spz",
    "write_spz",
]

SPZ_MAGIC = 0x5053474E  # b"NGSP"
FLAG_ANTIALIASED = 0x1
FLAG_HAS_EXTENSIONS = 0x2
COLOR_SCALE = 0.15
SH1_BITS = 5
SH_REST_BITS = 4
ZSTD_LEVEL = 12
GZIP_LEVEL = 6
GZIP_MEM_LEVEL = 9
WRITE_VERSIONS = (3, 4)
READ_VERSIONS = (2, 3, 4)
_MAX_DEGREE = 3  # GaussianPly holds SH degree 0..3; SPZ allows 4
_MAX_FILE_DEGREE = 4
# The reference's sanity bound on numPoints vs file size for v4 (kMaxCompressionRatio / kMinBytesPerPoint).
_MAX_ZSTD_RATIO = 1024
_MIN_BYTES_PER_POINT = 9
_MAX_DEFLATE_RATIO = 1032  # deflate cannot expand more than ~1032:1
_MAX_LEGACY_EXTENSION_BYTES = 1 << 20
_INT32_MAX = 2**31 - 1

_NGSP = struct.Struct("<IIIBBBBI12x")  # 32 bytes
_LEGACY = struct.Struct("<IIIBBBB")  # 16 bytes
_TOC_ENTRY = struct.Struct("<QQ")
_STREAMS = ("positions", "alphas", "colors", "scales", "rotations", "sh")

_F32 = np.float32
_SQRT1_2 = _F32(0.707106781186547524401)
_COLOR_MUL = _F32(_F32(COLOR_SCALE) * _F32(255.0))  # the reference's (colorScale * 255.0f), folded in float32

# CoordinateSystem enum values of the reference (unrotated family only).
_COORDS = {1: "LDB", 2: "RDB", 3: "LUB", 4: "RUB", 5: "LDF", 6: "RDF", 7: "LUF", 8: "RUF"}
_COORDS_ROTATED = {9: "LFD", 10: "RFD", 11: "LFU", 12: "RFU", 13: "LBD", 14: "RBD", 15: "LBU", 16: "RBU"}
_RUB, _RDF = 4, 6
_EXT_COORDINATE_SYSTEM = 0xADBE0003


def _flips(frm: int, to: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The reference's ``coordinateConverter`` for two systems of the unrotated family: sign flips of the
    position axes, of the quaternion's x, y, z, and of the 15 SH coefficients of degree 1..3."""
    a, b = frm - 1, to - 1
    x, y, z = (1.0 if ((a >> k) & 1) == ((b >> k) & 1) else -1.0 for k in range(3))
    flip_p = np.array([x, y, z], np.float32)
    flip_q = np.array([y * z, x * z, x * y], np.float32)
    flip_sh = np.array(
        [y, z, x, x * y, y * z, 1, x * z, 1, y, x * y * z, y, z, x, z, x], np.float32
    )
    return flip_p, flip_q, flip_sh


def _round_away(x: np.ndarray) -> np.ndarray:
    """C ``std::round`` (half away from zero) of float32 values, exactly, as float64."""
    x64 = np.asarray(x, np.float64)
    return np.copysign(np.floor(np.abs(x64) + 0.5), x64)


def _to_u8(x: np.ndarray) -> np.ndarray:
    """The reference's ``toUint8``: clamp(round(x), 0, 255)."""
    return np.clip(_round_away(x), 0, 255).astype(np.uint8)


# ----------------------------------------------------------------------------------------------------------- writing


def _pack_positions(means: np.ndarray, fractional_bits: int, flip_p: np.ndarray) -> bytes:
    fixed = _round_away((means * _F32(1 << fractional_bits)) * flip_p)
    lim = 1 << 23
    bad = (fixed < -lim) | (fixed >= lim)
    if bad.any():
        worst = float(np.abs(means).max())
        raise ProxycodecError(
            f"SPZ positions are 24-bit fixed point with {fractional_bits} fractional bits (range +-"
            f"{lim / (1 << fractional_bits):g}); the scene reaches {worst:g}: lower fractional_bits"
        )
    u = (fixed.astype(np.int64) & 0xFFFFFF).astype("<u4").view(np.uint8).reshape(-1, 4)[:, :3]
    return np.ascontiguousarray(u).tobytes()


def _pack_alphas(logits: np.ndarray) -> bytes:
    with np.errstate(over="ignore"):
        e = np.exp(-logits.astype(np.float64)).astype(np.float32)  # correctly rounded expf(-x)
    sig = _F32(1.0) / (_F32(1.0) + e)
    return _to_u8(sig * _F32(255.0)).tobytes()


def _pack_colors(dc: np.ndarray) -> bytes:
    return _to_u8(dc * _COLOR_MUL + _F32(127.5)).tobytes()


def _pack_scales(log_scales: np.ndarray) -> bytes:
    return _to_u8((log_scales + _F32(10.0)) * _F32(16.0)).tobytes()


def _normalized_xyzw(quats_wxyz: np.ndarray) -> np.ndarray:
    q = np.ascontiguousarray(quats_wxyz[:, [1, 2, 3, 0]], np.float32)
    norm = np.sqrt(((q[:, 0] * q[:, 0] + q[:, 1] * q[:, 1]) + q[:, 2] * q[:, 2]) + q[:, 3] * q[:, 3])
    zero = norm == 0
    with np.errstate(invalid="ignore", divide="ignore"):
        q = q / norm[:, None]
    q[zero] = (0.0, 0.0, 0.0, 1.0)  # a zero quaternion (no rotation defined): identity
    return q


def _smallest_three(q: np.ndarray) -> np.ndarray:
    """The reference's ``packQuaternionSmallestThree`` of normalised xyzw rows (in the stored frame) -> u32."""
    n = q.shape[0]
    largest = np.argmax(np.abs(q), axis=1)  # first of equals, as the reference's strict '>' scan
    negate = q[np.arange(n), largest] < 0
    mag = (_F32(511.0) * (np.abs(q) / _SQRT1_2) + _F32(0.5)).astype(np.uint32)
    neg = ((q < 0) ^ negate[:, None]).astype(np.uint32)
    comp = largest.astype(np.uint32)
    for i in range(4):
        comp = np.where(largest != i, (comp << 10) | (neg[:, i] << 9) | mag[:, i], comp)
    return comp


def _pack_rotations(quats_wxyz: np.ndarray, flip_q: np.ndarray) -> bytes:
    q = _normalized_xyzw(quats_wxyz)
    q[:, :3] *= flip_q
    return _smallest_three(q).astype("<u4").tobytes()


def _pack_sh(rest: np.ndarray, flip_sh: np.ndarray) -> bytes:
    """rest: [N, D, 3] SH coefficients 1..D (D = 3, 8 or 15), already in GaussianPly order."""
    d = rest.shape[1]
    x = rest * flip_sh[:d, None]
    q = _round_away(np.clip(x * _F32(128.0), -4096, 4096)).astype(np.int64) + 128
    bucket = np.where(np.arange(d) < 3, 1 << (8 - SH1_BITS), 1 << (8 - SH_REST_BITS))[None, :, None]
    q = (q + bucket // 2) // bucket * bucket  # negative sums clamp to 0 below either way (C truncates)
    return np.clip(q, 0, 255).astype(np.uint8).tobytes()


def _pack(ply: GaussianPly, fractional_bits: int) -> list[bytes]:
    flip_p, flip_q, flip_sh = _flips(_RDF, _RUB)
    streams = [
        _pack_positions(ply.means, fractional_bits, flip_p),
        _pack_alphas(ply.opacities),
        _pack_colors(ply.sh[:, 0, :]),
        _pack_scales(ply.scales),
        _pack_rotations(ply.quats, flip_q),
        _pack_sh(ply.sh[:, 1:, :], flip_sh) if ply.sh_degree > 0 else b"",
    ]
    return streams


def encode_spz(
    ply: GaussianPly, *, antialiased: bool = False, version: int = 4, fractional_bits: int = 12
) -> bytes:
    """The SPZ bytes of ``ply`` (RDF, as in its PLY); see :func:`write_spz`."""
    if not isinstance(ply, GaussianPly):
        raise ProxycodecError(f"SPZ export expects a GaussianPly, got {type(ply).__name__}")
    if isinstance(version, bool) or not isinstance(version, (int, np.integer)) or version not in WRITE_VERSIONS:
        raise ProxycodecError(f"SPZ version {version!r} cannot be written; choose one of {WRITE_VERSIONS}")
    if isinstance(fractional_bits, bool) or not isinstance(fractional_bits, (int, np.integer)) or not (
        0 <= fractional_bits <= 23
    ):
        raise ProxycodecError(f"SPZ fractional_bits must be an integer in 0..23, got {fractional_bits!r}")
    ply.validate()
    n = ply.n_gaussians
    if n == 0:
        raise ProxycodecError("SPZ cannot hold an empty scene (readers refuse numPoints 0)")
    if n > _INT32_MAX:
        raise ProxycodecError(f"SPZ holds at most {_INT32_MAX} Gaussians, got {n}")
    fractional_bits, version = int(fractional_bits), int(version)
    streams = _pack(ply, fractional_bits)
    flags = FLAG_ANTIALIASED if antialiased else 0
    degree = ply.sh_degree
    if version >= 4:
        present = [s for s in streams if s]
        cctx = zstandard.ZstdCompressor(level=ZSTD_LEVEL)
        chunks = [cctx.compress(s) for s in present]
        toc_offset = _NGSP.size
        head = _NGSP.pack(SPZ_MAGIC, version, n, degree, fractional_bits, flags, len(present), toc_offset)
        toc = b"".join(_TOC_ENTRY.pack(len(c), len(s)) for c, s in zip(chunks, present))
        return head + toc + b"".join(chunks)
    raw = _LEGACY.pack(SPZ_MAGIC, version, n, degree, fractional_bits, flags, 0) + b"".join(streams)
    z = zlib.compressobj(GZIP_LEVEL, zlib.DEFLATED, 16 + zlib.MAX_WBITS, GZIP_MEM_LEVEL)
    return z.compress(raw) + z.flush()


def write_spz(
    path: str | os.PathLike,
    ply: GaussianPly,
    *,
    antialiased: bool = False,
    version: int = 4,
    fractional_bits: int = 12,
) -> int:
    """Write ``ply`` (a 3DGS scene as in its PLY: RDF axes) as SPZ at ``path``, atomically; returns the bytes
    written.

    ``version`` 4 (zstd streams; current viewers) or 3 (gzip; older viewers). ``fractional_bits`` sets the position
    step 2^-fractional_bits and range +-2^(23-fractional_bits). Same input, same bytes. Raises
    :class:`ProxycodecError` on an empty scene or positions out of range.
    """
    data = encode_spz(ply, antialiased=antialiased, version=version, fractional_bits=fractional_bits)
    write_bytes_atomic(path, data)
    return len(data)


# ----------------------------------------------------------------------------------------------------------- reading


def _bytes_per_point(version: int, degree: int) -> list[int]:
    d = (degree + 1) ** 2 - 1
    return [9, 1, 3, 3, 4 if version >= 3 else 3, 3 * d]


def _parse_extensions(blob: bytes, path) -> tuple[list[int], int]:
    """ILV records -> (types, stored coordinate system)."""
    types, coord, off = [], _RUB, 0
    while off < len(blob):
        if len(blob) - off < 8:
            raise ProxycodecError(f"SPZ extension record at byte {off} of its block is truncated", path)
        kind, length = struct.unpack_from("<II", blob, off)
        off += 8
        if length > len(blob) - off:
            raise ProxycodecError(
                f"SPZ extension 0x{kind:08x} claims {length} bytes, {len(blob) - off} remain", path
            )
        payload = blob[off:off + length]
        off += length
        types.append(kind)
        if kind == _EXT_COORDINATE_SYSTEM:
            if length < 4:
                raise ProxycodecError("SPZ coordinate-system extension is truncated", path)
            value = struct.unpack_from("<I", payload)[0]
            if value in _COORDS:
                coord = value
            elif value in _COORDS_ROTATED:
                raise ProxycodecError(
                    f"SPZ stored in coordinate system {_COORDS_ROTATED[value]} (a 90-degree-rotated frame) is "
                    "not supported", path)
            elif value != 0:  # 0 (UNSPECIFIED) counts as absent, as in the reference
                raise ProxycodecError(f"SPZ coordinate-system extension has unknown value {value}", path)
    return types, coord


def _check_count(count: int, bound: int, size: int, path) -> None:
    if count == 0:
        raise ProxycodecError("SPZ header says 0 Gaussians", path)
    if count > _INT32_MAX or count > bound:
        raise ProxycodecError(
            f"SPZ header claims {count} Gaussians, more than a file of {size} bytes can hold", path
        )


def _check_degree(degree: int, path) -> None:
    if degree > _MAX_FILE_DEGREE:
        raise ProxycodecError(f"SPZ SH degree {degree} is invalid (0..4)", path)
    if degree > _MAX_DEGREE:
        raise ProxycodecError(f"SPZ SH degree {degree} is not supported (GaussianPly holds degree 0..3)", path)


def _check_fractional_bits(fb: int, path) -> None:
    if fb > 30:
        raise ProxycodecError(f"SPZ fractional bits {fb} is invalid (0..30)", path)


def _zstd_stream(chunk: bytes, expected: int, name: str, path) -> bytes:
    """Decompress one stream (one or more zstd frames) to exactly ``expected`` bytes, never more in memory."""
    try:
        reader = zstandard.ZstdDecompressor().stream_reader(chunk, read_across_frames=True, read_size=1 << 16)
        parts, got = [], 0
        while got <= expected:
            part = reader.read(min(expected + 1 - got, 1 << 24))
            if not part:
                break
            parts.append(part)
            got += len(part)
    except zstandard.ZstdError as e:
        raise ProxycodecError(f"SPZ {name} stream is corrupt ({e})", path) from None
    if got != expected:
        raise ProxycodecError(
            f"SPZ {name} stream decompresses to {'more than ' if got > expected else ''}{got} bytes, "
            f"expected {expected}", path)
    return b"".join(parts)


def _read_ngsp(data: bytes, path) -> tuple[dict, list[bytes], bytes]:
    size = len(data)
    if size < _NGSP.size:
        raise ProxycodecError(f"SPZ file is truncated: {size} bytes, the header alone is {_NGSP.size}", path)
    _, version, count, degree, fb, flags, n_streams, toc = _NGSP.unpack_from(data)
    if version != 4:
        raise ProxycodecError(f"SPZ version {version} is not supported (an NGSP-header file is version 4)", path)
    _check_count(count, size * _MAX_ZSTD_RATIO // _MIN_BYTES_PER_POINT, size, path)
    _check_degree(degree, path)
    _check_fractional_bits(fb, path)
    if not _NGSP.size <= toc <= size:
        raise ProxycodecError(f"SPZ table of contents offset {toc} is outside the file ({size} bytes)", path)
    ext = data[_NGSP.size:toc] if flags & FLAG_HAS_EXTENSIONS else b""
    sizes = [count * b for b in _bytes_per_point(version, degree)]
    present = [(name, s) for name, s in zip(_STREAMS, sizes) if s]
    if n_streams != len(present):
        raise ProxycodecError(
            f"SPZ header lists {n_streams} streams; SH degree {degree} needs {len(present)}", path
        )
    toc_end = toc + n_streams * _TOC_ENTRY.size
    if toc_end > size:
        raise ProxycodecError("SPZ file is truncated inside its table of contents", path)
    offset, spans = toc_end, []
    for i, (name, want) in enumerate(present):
        csize, usize = _TOC_ENTRY.unpack_from(data, toc + i * _TOC_ENTRY.size)
        if usize != want:
            raise ProxycodecError(
                f"SPZ {name} stream holds {usize} bytes; {count} Gaussians need {want}", path
            )
        if csize > size - offset:
            raise ProxycodecError(f"SPZ file is truncated: the {name} stream runs past its end", path)
        spans.append((offset, csize))
        offset += csize
    if offset != size:
        raise ProxycodecError(f"SPZ file has {size - offset} bytes after its last stream", path)
    raw = {name: _zstd_stream(data[o:o + c], want, name, path) for (name, want), (o, c) in zip(present, spans)}
    streams = [raw.get(name, b"") for name in _STREAMS]
    info = {"version": version, "count": count, "sh_degree": degree, "fractional_bits": fb, "flags": flags}
    return info, streams, ext


def _read_legacy(data: bytes, path) -> tuple[dict, list[bytes], bytes]:
    size = len(data)
    d = zlib.decompressobj(16 + zlib.MAX_WBITS)
    try:
        head = d.decompress(data, _LEGACY.size)
        if len(head) < _LEGACY.size:
            raise ProxycodecError("SPZ file is truncated: its gzip stream ends inside the header", path)
        magic, version, count, degree, fb, flags, _ = _LEGACY.unpack(head)
        if magic != SPZ_MAGIC:
            raise ProxycodecError(f"not an SPZ file: gzip payload starts with 0x{magic:08x}, not NGSP", path)
        if version not in READ_VERSIONS:
            raise ProxycodecError(
                f"SPZ version {version} is not supported (readable: {', '.join(map(str, READ_VERSIONS))})", path
            )
        payload = count * sum(_bytes_per_point(version, degree))
        _check_count(count, ((size * _MAX_DEFLATE_RATIO) // _MIN_BYTES_PER_POINT), size, path)
        _check_degree(degree, path)
        _check_fractional_bits(fb, path)
        if payload + _LEGACY.size > size * _MAX_DEFLATE_RATIO:
            raise ProxycodecError(
                f"SPZ header claims {count} Gaussians, more than a file of {size} bytes can hold", path
            )
        extra = _MAX_LEGACY_EXTENSION_BYTES if flags & FLAG_HAS_EXTENSIONS else 0
        body = d.decompress(d.unconsumed_tail, payload + extra + 1)
    except zlib.error as e:
        raise ProxycodecError(f"SPZ gzip stream is corrupt ({e})", path) from None
    if len(body) < payload:
        raise ProxycodecError(
            f"SPZ file is truncated: {count} Gaussians need {payload} bytes after the header, it holds {len(body)}",
            path)
    if not d.eof:
        raise ProxycodecError(
            "SPZ gzip stream is truncated or longer than its header says"
            if len(body) <= payload + extra else "SPZ extension records are too large", path)
    if d.unused_data:
        raise ProxycodecError(f"SPZ file has {len(d.unused_data)} bytes after its gzip stream", path)
    if len(body) > payload and not flags & FLAG_HAS_EXTENSIONS:
        raise ProxycodecError(
            f"SPZ payload is {len(body) - payload} bytes longer than {count} Gaussians need", path
        )
    streams, off = [], 0
    for b in _bytes_per_point(version, degree):
        streams.append(body[off:off + count * b])
        off += count * b
    info = {"version": version, "count": count, "sh_degree": degree, "fractional_bits": fb, "flags": flags}
    return info, streams, body[payload:]


def _unpack_smallest_three(comp: np.ndarray) -> np.ndarray:
    """The reference's ``unpackQuaternionSmallestThree`` (float32, same order of operations) -> xyzw."""
    n = comp.shape[0]
    largest = (comp >> 30).astype(np.int64)
    q = np.zeros((n, 4), np.float32)
    sum_sq = np.zeros(n, np.float32)
    for i in (3, 2, 1, 0):
        keep = largest != i
        v = _SQRT1_2 * (comp & 511).astype(np.float32) / _F32(511.0)
        v = np.where(((comp >> 9) & 1) == 1, -v, v)
        q[:, i] = np.where(keep, v, q[:, i])
        sum_sq = np.where(keep, sum_sq + v * v, sum_sq)
        comp = np.where(keep, comp >> 10, comp)
    q[np.arange(n), largest] = np.sqrt(np.maximum(_F32(0.0), _F32(1.0) - sum_sq))
    return q


def _settle(q: np.ndarray, comp: np.ndarray) -> np.ndarray:
    """Make every decoded rotation re-encode to its own bytes (the reference's decode does not, for ~0.25% of
    random rotations): a stored -0 (magnitude 0, sign bit set) becomes -1e-30, whose sign survives; and where
    the rebuilt largest component came out below a stored one (a near tie of the two largest), the three stored
    components move toward zero inside their quantisation bins (by fractions of half a bin, the least that
    works), which raises the rebuilt one above them. Every other rotation is left exactly as the reference's."""
    largest = (comp >> 30).astype(np.int64)
    stored = np.arange(4)[None, :] != largest[:, None]
    q = np.where(stored & (q == 0) & np.signbit(q), _F32(-1e-30), q).astype(np.float32)
    todo = np.flatnonzero(_smallest_three(_normalized_xyzw(q[:, [3, 0, 1, 2]])) != comp)
    half_bin = _F32(0.5 - 1e-3) * _SQRT1_2 / _F32(511.0)
    for t in np.arange(1, 17, dtype=np.float32) / _F32(16.0):
        if not todo.size:
            break
        sub, st = q[todo].copy(), stored[todo]
        shrunk = np.copysign(np.maximum(np.abs(sub) - t * half_bin, _F32(0.0)), sub)
        shrunk = np.where((sub != 0) & (shrunk == 0), np.copysign(_F32(1e-30), sub), shrunk)
        sub = np.where(st, shrunk, sub).astype(np.float32)
        rows = np.arange(len(todo))
        sub[rows, largest[todo]] = np.sqrt(np.maximum(_F32(0.0), _F32(1.0) - (np.where(st, sub, 0) ** 2).sum(1)))
        ok = _smallest_three(_normalized_xyzw(sub[:, [3, 0, 1, 2]])) == comp[todo]
        q[todo[ok]] = sub[ok]
        todo = todo[~ok]
    return q


def _unpack_rotations(raw: bytes, n: int, version: int) -> np.ndarray:
    """-> [N, 4] xyzw in the stored frame."""
    if version < 3:
        r = np.frombuffer(raw, np.uint8).reshape(n, 3).astype(np.float32)
        xyz = r * _F32(1.0 / 127.5) + _F32(-1.0)
        w = np.sqrt(np.maximum(_F32(0.0), _F32(1.0) - (xyz * xyz).sum(axis=1, dtype=np.float32)))
        return np.concatenate([xyz, w[:, None]], axis=1)
    comp = np.frombuffer(raw, "<u4").astype(np.uint32)
    return _settle(_unpack_smallest_three(comp), comp)


def decode_spz(data: bytes, path: str | os.PathLike | None = None) -> tuple[GaussianPly, dict]:
    """Parse SPZ bytes; see :func:`read_spz`. ``path`` only names the source in errors."""
    data = bytes(data)
    if len(data) >= 4 and struct.unpack_from("<I", data)[0] == SPZ_MAGIC:
        info, streams, ext = _read_ngsp(data, path)
    elif data[:2] == b"\x1f\x8b":
        info, streams, ext = _read_legacy(data, path)
    else:
        raise ProxycodecError("not an SPZ file (neither an NGSP header nor a gzip stream)", path)
    n, degree, version = info["count"], info["sh_degree"], info["version"]
    ext_types, coord = _parse_extensions(ext, path)
    flip_p, flip_q, flip_sh = _flips(coord, _RDF)

    b = np.frombuffer(streams[0], np.uint8).reshape(n, 3, 3).astype(np.int32)
    fixed = b[..., 0] | (b[..., 1] << 8) | (b[..., 2] << 16)
    fixed = np.where(fixed & 0x800000, fixed - (1 << 24), fixed)
    means = (fixed.astype(np.float32) * _F32(1.0 / (1 << info["fractional_bits"]))) * flip_p

    a = np.frombuffer(streams[1], np.uint8).astype(np.float32) / _F32(255.0)
    with np.errstate(divide="ignore"):
        logit = np.log((a / (_F32(1.0) - a)).astype(np.float64)).astype(np.float32)
    opacities = np.clip(logit, -SATURATED_LOGIT, SATURATED_LOGIT).astype(np.float32)  # bytes 0 / 255: -+inf

    colors = (np.frombuffer(streams[2], np.uint8).reshape(n, 3).astype(np.float32) / _F32(255.0) - _F32(0.5)) \
        / _F32(COLOR_SCALE)
    scales = np.frombuffer(streams[3], np.uint8).reshape(n, 3).astype(np.float32) / _F32(16.0) - _F32(10.0)

    q = _unpack_rotations(streams[4], n, version)
    q[:, :3] *= flip_q
    quats = q[:, [3, 0, 1, 2]]

    d = (degree + 1) ** 2 - 1
    sh = np.empty((n, d + 1, 3), np.float32)
    sh[:, 0, :] = colors
    if d:
        rest = (np.frombuffer(streams[5], np.uint8).reshape(n, d, 3).astype(np.float32) - _F32(128.0)) \
            / _F32(128.0)
        sh[:, 1:, :] = rest * flip_sh[:d, None]
    try:
        ply = GaussianPly(means, sh, opacities, scales, quats)
    except ProxycodecError as e:
        raise ProxycodecError(e.reason, path) from None
    flags = info["flags"]
    meta = {
        "version": version,
        "count": n,
        "sh_degree": degree,
        "fractional_bits": info["fractional_bits"],
        "flags": flags,
        "antialiased": bool(flags & FLAG_ANTIALIASED),
        "extensions": ext_types,
        "coordinate_system": _COORDS[coord],
    }
    return ply, meta


def read_spz(path: str | os.PathLike) -> tuple[GaussianPly, dict]:
    """Read an SPZ file (version 2, 3 or 4) into a :class:`GaussianPly` in PLY axes (RDF), plus a dict with
    ``version``, ``count``, ``sh_degree`` (0..3; degree 4 is refused), ``fractional_bits``, ``flags``,
    ``antialiased``, ``extensions`` (record types, skipped) and ``coordinate_system`` (as stored, normally RUB).

    Every malformed file raises :class:`ProxycodecError` naming it; memory is bounded by the file size before
    anything is allocated.
    """
    try:
        with open(path, "rb") as fh:
            data = fh.read()
    except OSError as e:
        raise ProxycodecError(f"cannot read SPZ file ({e.strerror or e})", path) from None
    return decode_spz(data, path)
