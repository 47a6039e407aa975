"""A strict reader and a plyfile-compatible writer for point-cloud PLY files.

Scope: one ``vertex`` element of scalar properties, stored as ``binary_little_endian 1.0`` (read and written),
``binary_big_endian 1.0`` or ``ascii 1.0`` (read only). That is every PLY that 3DGS, Scaffold-GS and their
descendants write. List properties (meshes' ``vertex_indices``) are rejected, as are elements other than
``vertex`` unless they are empty (``element face 0``, as some exporters add).

The reader trusts nothing in the file: the header is capped at :data:`MAX_HEADER_BYTES`, the declared vertex
count times the row size must equal the payload size *before* anything is allocated, and every problem raises
:class:`~proxycodec.errors.ProxycodecError` with a one-line message prefixed by the file name. Data are read
with one ``np.fromfile`` call into a structured array (no per-vertex Python work).

The writer produces exactly the bytes that ``plyfile`` (>= 0.6, the version every 3DGS code base pins) writes
for ``PlyData([PlyElement.describe(arr, 'vertex')]).write(path)``::

    ply\\n
    format binary_little_endian 1.0\\n
    element vertex N\\n
    property float x\\n
    ...
    end_header\\n
    <N rows of packed little-endian values>
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from ..errors import ProxycodecError
from ..fileio import atomic_write

#: A header longer than this is not a header (3DGS headers are ~2 KB, Scaffold-GS ~1.5 KB).
MAX_HEADER_BYTES = 64 * 1024

#: PLY scalar type names (both the classic and the sized spelling) -> numpy type code without byte order.
PLY_TO_NUMPY: dict[str, str] = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}

#: numpy type code -> the PLY name plyfile writes.
NUMPY_TO_PLY: dict[str, str] = {
    "i1": "char",
    "u1": "uchar",
    "b1": "uchar",
    "i2": "short",
    "u2": "ushort",
    "i4": "int",
    "u4": "uint",
    "f4": "float",
    "f8": "double",
}

_FORMATS = {"binary_little_endian": "<", "binary_big_endian": ">", "ascii": "<"}
_NAME_RE = re.compile(r"^[!-~]+$")  # printable ASCII without spaces


@dataclass(frozen=True)
class PlyHeader:
    """What a PLY header declares about its single vertex element."""

    format: str  # "binary_little_endian" | "binary_big_endian" | "ascii"
    count: int  # number of vertices
    properties: tuple[tuple[str, str], ...]  # (name, numpy type code such as "f4"), in file order
    comments: tuple[str, ...]
    header_size: int  # bytes up to and including the newline after ``end_header``

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(name for name, _ in self.properties)

    def dtype(self, byte_order: str | None = None) -> np.dtype:
        """The packed structured dtype of one row (file byte order unless ``byte_order`` is given)."""
        bo = _FORMATS[self.format] if byte_order is None else byte_order
        return np.dtype([(name, bo + code) for name, code in self.properties])


def _fail(path, message: str) -> ProxycodecError:
    return ProxycodecError(message, path)


def _read_header_bytes(path: str | os.PathLike, fh) -> bytes:
    head = fh.read(MAX_HEADER_BYTES + 2)
    if not (head.startswith(b"ply\n") or head.startswith(b"ply\r\n")):
        raise _fail(path, "not a PLY file (it does not start with the line 'ply')")
    m = re.search(rb"(?:^|\n)end_header\r?\n", head)
    if m is None:
        if len(head) > MAX_HEADER_BYTES:
            raise _fail(path, f"PLY header has no 'end_header' line within {MAX_HEADER_BYTES} bytes")
        raise _fail(path, "PLY header is truncated: no 'end_header' line (ending with a newline)")
    end = m.end()
    if end > MAX_HEADER_BYTES:
        raise _fail(path, f"PLY header is longer than {MAX_HEADER_BYTES} bytes")
    return head[:end]


def parse_ply_header(path: str | os.PathLike, raw: bytes) -> PlyHeader:
    """Parse header bytes (ending with the ``end_header`` line); ``path`` is only used in error messages."""
    try:
        text = raw.decode("ascii")
    except UnicodeDecodeError:
        raise _fail(path, "PLY header contains non-ASCII bytes") from None
    lines = [ln.rstrip("\r") for ln in text.split("\n")]
    if lines and lines[-1] == "":
        lines.pop()
    if not lines or lines[0] != "ply" or lines[-1] != "end_header":
        raise _fail(path, "malformed PLY header")
    fmt: str | None = None
    comments: list[str] = []
    elements: list[tuple[str, int, list[tuple[str, str]], bool]] = []  # name, count, props, has_list
    for lineno, line in enumerate(lines[1:-1], start=2):
        words = line.split()
        if not words:
            raise _fail(path, f"PLY header line {lineno} is empty")
        key = words[0]
        if key == "comment":
            comments.append(line[len("comment") :].lstrip(" "))
        elif key == "obj_info":
            continue
        elif key == "format":
            if fmt is not None or elements:
                raise _fail(path, f"PLY header line {lineno}: unexpected 'format' line")
            if len(words) != 3 or words[1] not in _FORMATS or words[2] != "1.0":
                raise _fail(
                    path,
                    f"unsupported PLY format {line[7:].strip()!r} "
                    "(expected binary_little_endian, binary_big_endian or ascii, version 1.0)",
                )
            fmt = words[1]
        elif key == "element":
            if fmt is None:
                raise _fail(path, "PLY header has an 'element' line before its 'format' line")
            if len(words) != 3 or not re.fullmatch(r"[0-9]{1,19}", words[2]):
                raise _fail(path, f"PLY header line {lineno}: malformed element declaration {line!r}")
            elements.append((words[1], int(words[2]), [], False))
        elif key == "property":
            if not elements:
                raise _fail(path, f"PLY header line {lineno}: property declared before any element")
            name, count, props, has_list = elements[-1]
            if len(words) >= 2 and words[1] == "list":
                elements[-1] = (name, count, props, True)
                if name == "vertex":
                    raise _fail(
                        path,
                        f"PLY property {words[-1]!r} of element 'vertex' is a list property; "
                        "only scalar properties are supported",
                    )
                continue
            if len(words) != 3:
                raise _fail(path, f"PLY header line {lineno}: malformed property declaration {line!r}")
            if words[1] not in PLY_TO_NUMPY:
                raise _fail(path, f"PLY property {words[2]!r} has unknown type {words[1]!r}")
            if not _NAME_RE.match(words[2]):
                raise _fail(path, f"PLY property name {words[2]!r} is invalid")
            props.append((words[2], PLY_TO_NUMPY[words[1]]))
        else:
            raise _fail(path, f"PLY header line {lineno}: unknown keyword {key!r}")
    if fmt is None:
        raise _fail(path, "PLY header has no 'format' line")
    vertex = [e for e in elements if e[0] == "vertex"]
    if len(vertex) != 1:
        raise _fail(path, f"expected exactly one 'vertex' element, found {len(vertex)}")
    others = [e for e in elements if e[0] != "vertex"]
    nonempty = [e[0] for e in others if e[1] != 0]
    if nonempty:
        raise _fail(path, f"PLY element(s) {nonempty} are not supported (only a single 'vertex' element)")
    _, count, props, _ = vertex[0]
    if not props:
        raise _fail(path, "PLY 'vertex' element has no properties")
    names = [n for n, _ in props]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise _fail(path, f"PLY property names repeat: {dup}")
    return PlyHeader(fmt, count, tuple(props), tuple(comments), len(raw))


def _open(path):
    """Open a PLY for reading; OS errors become our one-line error naming the file."""
    try:
        return open(path, "rb")
    except FileNotFoundError:
        raise _fail(path, "file not found") from None
    except IsADirectoryError:
        raise _fail(path, "is a directory, expected a PLY file") from None
    except PermissionError:
        raise _fail(path, "permission denied") from None


def read_ply_header(path: str | os.PathLike) -> PlyHeader:
    """Read and validate only the header of a PLY file."""
    with _open(path) as fh:
        return parse_ply_header(path, _read_header_bytes(path, fh))


def read_ply(path: str | os.PathLike) -> tuple[PlyHeader, np.ndarray]:
    """Read a PLY point cloud: (header, structured array [N] in little-endian packed layout).

    Raises :class:`ProxycodecError` for any malformed input, before allocating anything proportional to the
    declared vertex count.
    """
    with _open(path) as fh:
        file_size = os.fstat(fh.fileno()).st_size
        header = parse_ply_header(path, _read_header_bytes(path, fh))
        payload = file_size - header.header_size
        dtype = header.dtype()
        if header.format == "ascii":
            data = _read_ascii(path, fh, header, payload)
        else:
            need = header.count * dtype.itemsize
            if need > payload:
                raise _fail(
                    path,
                    f"PLY file is truncated: header declares {header.count} vertices of "
                    f"{dtype.itemsize} bytes ({need} bytes) but only {payload} bytes follow",
                )
            if need < payload:
                raise _fail(
                    path, f"PLY file has {payload - need} unexpected bytes after its {header.count} vertices"
                )
            fh.seek(header.header_size)
            data = np.fromfile(fh, dtype=dtype, count=header.count)
            if data.shape[0] != header.count:
                raise _fail(path, "PLY file is truncated (it changed while being read)")
    little = header.dtype("<")
    if data.dtype != little:
        data = data.astype(little)
    return header, data


def _read_ascii(path, fh, header: PlyHeader, payload: int) -> np.ndarray:
    nprop = len(header.properties)
    # every value needs at least one character and one separator
    if header.count * nprop * 2 > payload + 1:
        raise _fail(
            path,
            f"PLY file is truncated: header declares {header.count} vertices but only "
            f"{payload} bytes of text follow",
        )
    fh.seek(header.header_size)
    text = fh.read(payload)
    try:
        values = np.array(text.split(), dtype=np.float64)
    except ValueError:
        raise _fail(path, "ASCII PLY data contains a token that is not a number") from None
    if values.size != header.count * nprop:
        raise _fail(path, f"ASCII PLY data holds {values.size} values, expected {header.count} x {nprop}")
    values = values.reshape(header.count, nprop)
    out = np.empty(header.count, dtype=header.dtype("<"))
    for j, (name, code) in enumerate(header.properties):
        col = values[:, j]
        if code[0] in "iu":
            info = np.iinfo(np.dtype(code))
            if not np.all((col == np.round(col)) & (col >= info.min) & (col <= info.max)):
                raise _fail(
                    path, f"ASCII PLY property {name!r} has values that are not {np.dtype(code).name}"
                )
        out[name] = col
    return out


def ply_header_bytes(count: int, dtype: np.dtype, comments: Sequence[str] = ()) -> bytes:
    """The header plyfile writes for ``count`` rows of ``dtype`` (binary_little_endian)."""
    lines = ["ply", "format binary_little_endian 1.0"]
    for c in comments:
        if "\n" in c or "\r" in c:
            raise ProxycodecError("PLY comments must be single lines")
        lines.append("comment " + c)
    lines.append(f"element vertex {int(count)}")
    for name in dtype.names or ():
        sub = dtype.fields[name][0]
        if sub.shape != () or sub.names is not None:
            raise ProxycodecError(f"PLY field {name!r} is not a scalar")
        code = sub.str[1:]
        if code not in NUMPY_TO_PLY:
            raise ProxycodecError(f"PLY field {name!r} has unsupported type {sub}")
        if not _NAME_RE.match(name):
            raise ProxycodecError(f"PLY field name {name!r} is invalid")
        lines.append(f"property {NUMPY_TO_PLY[code]} {name}")
    lines.append("end_header")
    return ("\n".join(lines) + "\n").encode("ascii")


def _little_packed(data: np.ndarray) -> np.ndarray:
    if data.ndim != 1 or data.dtype.names is None:
        raise ProxycodecError("PLY data must be a one-dimensional structured array")
    fields = []
    for name in data.dtype.names:
        sub = data.dtype.fields[name][0]
        if sub.shape != () or sub.names is not None or sub.str[1:] not in NUMPY_TO_PLY:
            raise ProxycodecError(f"PLY field {name!r} has unsupported type {sub}")
        code = "u1" if sub.str[1:] == "b1" else sub.str[1:]
        fields.append((name, "<" + code))
    dt = np.dtype(fields)  # packed, little-endian
    if data.dtype == dt and data.flags.c_contiguous:
        return data
    out = np.empty(data.shape[0], dtype=dt)
    for name in data.dtype.names:
        out[name] = data[name]
    return out


def encode_ply(data: np.ndarray, comments: Sequence[str] = ()) -> bytes:
    """The bytes :func:`write_ply` would write (for small data and tests)."""
    arr = _little_packed(data)
    return ply_header_bytes(arr.shape[0], arr.dtype, comments) + arr.tobytes()


def write_ply(path: str | os.PathLike, data: np.ndarray, comments: Sequence[str] = ()) -> None:
    """Write a structured array [N] as a binary_little_endian PLY vertex element, atomically.

    Byte for byte what ``plyfile`` writes for ``PlyData([PlyElement.describe(data, 'vertex')])``
    on a little-endian machine.
    """
    arr = _little_packed(data)
    header = ply_header_bytes(arr.shape[0], arr.dtype, comments)
    with atomic_write(path, "wb") as fh:
        fh.write(header)
        if arr.shape[0]:
            fh.write(arr.view(np.uint8).data)


# ---------------------------------------------------------------------------------------------------- helpers
def indexed_names(path, header: PlyHeader, prefix: str) -> list[str]:
    """``prefix0, prefix1, ...`` present in the header, checked to be exactly 0..n-1 (``[]`` when none)."""
    pat = re.compile(re.escape(prefix) + r"([0-9]+)")
    idx = []
    for n in header.names:
        m = pat.fullmatch(n)
        if m:
            if m.group(1) != str(int(m.group(1))):
                raise _fail(path, f"PLY property name {n!r} has a malformed index")
            idx.append(int(m.group(1)))
    idx.sort()
    if idx != list(range(len(idx))):
        # The first gap; never materialise range(max(idx)): a hostile name like f_rest_99999999999 must not
        # make us allocate.
        present = set(idx)
        first_missing = next(i for i in range(len(idx) + 1) if i not in present)
        raise _fail(
            path,
            f"PLY properties {prefix}* are not numbered 0..{len(idx) - 1}: {prefix}{first_missing} is missing",
        )
    return [f"{prefix}{i}" for i in range(len(idx))]


def columns(path, data: np.ndarray, names: Iterable[str], *, field: str, finite: bool) -> np.ndarray:
    """Stack PLY properties into a float32 matrix [N, len(names)]; reject NaN/Inf when ``finite``.

    Float32 properties are copied exactly (bit for bit, NaN payloads included); double properties must be
    representable in float32 without overflow.
    """
    names = list(names)
    out = _contiguous_f4_block(data, names)
    if out is None:
        out = _gather_columns(path, data, names, field=field, finite=finite)
    if finite and out.size and not np.isfinite(out).all():
        bad = np.argwhere(~np.isfinite(out))[0]
        raise _fail(
            path,
            f"PLY field {field!r} holds NaN or Inf (first at vertex {int(bad[0])}, "
            f"property {names[int(bad[1])]})",
        )
    return out


def _contiguous_f4_block(data: np.ndarray, names: list[str]) -> np.ndarray | None:
    """Fast path: ``names`` are consecutive little-endian float32 fields -> one strided copy."""
    if not names or data.dtype.names is None:
        return None
    fields = data.dtype.fields
    off0 = fields[names[0]][1]
    for j, name in enumerate(names):
        dt, off = fields[name][:2]
        if dt != np.dtype("<f4") or off != off0 + 4 * j:
            return None
    if data.shape[0] == 0:
        return np.empty((0, len(names)), dtype=np.float32)
    view = np.ndarray(
        (data.shape[0], len(names)), dtype="<f4", buffer=data, offset=off0, strides=(data.dtype.itemsize, 4)
    )
    return np.array(view, dtype=np.float32, order="C")


def _gather_columns(path, data: np.ndarray, names: list[str], *, field: str, finite: bool) -> np.ndarray:
    out = np.empty((data.shape[0], len(names)), dtype=np.float32)
    for j, name in enumerate(names):
        col = data[name]
        if col.dtype.kind == "f" and col.dtype.itemsize == 8:
            with np.errstate(over="ignore", invalid="ignore"):
                out[:, j] = col.astype(np.float32)
            if finite and np.isfinite(col).all() and not np.isfinite(out[:, j]).all():
                raise _fail(path, f"PLY field {field!r} ({name}) has values beyond the float32 range")
        else:
            out[:, j] = col
    return out


def float32_records(matrix: np.ndarray, names: Sequence[str]) -> np.ndarray:
    """View a float32 matrix [N, P] as a structured array [N] of P little-endian float fields (no copy
    when ``matrix`` already is C-contiguous little-endian float32)."""
    names = list(names)
    mat = np.ascontiguousarray(matrix, dtype="<f4")
    if mat.ndim != 2 or mat.shape[1] != len(names):
        raise ProxycodecError(f"expected a matrix with {len(names)} columns, got shape {mat.shape}")
    dt = np.dtype([(n, "<f4") for n in names])
    return mat.view(dt).reshape(mat.shape[0])
