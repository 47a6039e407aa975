"""Plain pickles of numpy arrays (``pickle.dump`` of nested dicts / lists / tuples of arrays, as flax and JAX
projects ship their weights) read without running anything.

An ordinary ``pickle.load`` calls whatever the file names. Here a restricted unpickler allows exactly the names
numpy's own pickling uses, each replaced by a stand-in that only records its arguments:

- ``numpy.core.multiarray._reconstruct`` (``numpy._core`` in numpy 2) with ``numpy.ndarray`` and a BUILD state
  ``(version, shape, dtype, fortran_order, raw bytes)``;
- ``numpy._core.numeric._frombuffer`` (``(raw bytes, dtype, shape, order)``, protocol 5 pickles);
- ``numpy.core.multiarray.scalar`` (``(dtype, raw bytes)``: numpy scalars);
- ``_codecs.encode(text, "latin1")`` and ``bytes()`` (protocol 2's bytes; nothing else of either);
- ``numpy.dtype`` with a plain numeric type code (``f2 f4 f8 i1..i8 u1..u8 b1``; no object, string, structured or
  void dtypes, whose states could hold Python objects).

The array is then made by ``numpy.frombuffer`` from the raw bytes after its shape and dtype are checked against their
length, and copied. Any other name (``os.system``, ``builtins.eval``, ...) is refused before anything is called, with
one :class:`ProxycodecError` naming the file; so is a malformed or truncated pickle (``safe_pickle.restricted_load``:
the same opcode pre-scan, conversion and error handling as the PyTorch readers of ``torchscript``).
"""

from __future__ import annotations

import io
import math
import os
import pickle
import re
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ProxycodecError
from .safe_pickle import MAX_NDIM, ArrayHolder, Malformed, Part, int_tuple, restricted_load

__all__ = ["read_numpy_pickle", "MAX_NUMPY_PICKLE_BYTES"]

#: The largest weights file read this way (LPIPS's AlexNet checkpoint is 9.9 MB).
MAX_NUMPY_PICKLE_BYTES = 256 << 20
_TYPE_CODE = re.compile(r"[<>|=]?(f[248]|[iu][1248]|b1)")
_MODULES = ("numpy.core.multiarray", "numpy._core.multiarray")


class _NdarrayType(Part):
    """What ``numpy.ndarray`` unpickles to: a tag for ``_reconstruct`` (not callable)."""

    __slots__ = ()
    what = "numpy.ndarray type"


class _Dtype(Part):
    """What ``numpy.dtype(code, align, copy)`` unpickles to: the type code, and the byte order BUILD gives it."""

    __slots__ = ("code", "order")
    what = "numpy dtype"

    def __init__(self, code, align=False, copy=True):
        if not (isinstance(code, str) and _TYPE_CODE.fullmatch(code)):
            raise Malformed(f"refused numpy dtype {str(code)[:40]!r}: only plain numeric arrays are read")
        self.code, self.order = code, "="

    def __setstate__(self, state) -> None:
        # (version, byte order, subarray, names, fields, elsize, alignment, flags[, metadata])
        if not (isinstance(state, tuple) and len(state) in (8, 9) and state[0] in (3, 4)
                and state[1] in ("<", ">", "|", "=") and state[2:5] == (None, None, None)
                and (len(state) == 8 or state[8] is None)):
            raise Malformed(f"refused numpy dtype state {str(state)[:80]}")
        self.order = state[1]

    def dtype(self) -> np.dtype:
        code = self.code if self.code[0] in "<>|=" else self.order + self.code
        return np.dtype(code)


def _array(raw, dtype, shape, fortran: bool) -> np.ndarray:
    """The checked array: ``raw`` holds exactly ``shape`` elements of ``dtype``; a native-order copy."""
    if not isinstance(dtype, _Dtype):
        raise Malformed("an array without a numpy dtype")
    if not (int_tuple(shape) and len(shape) <= MAX_NDIM):
        raise Malformed(f"bad array shape {str(shape)[:80]}")
    if not isinstance(raw, (bytes, bytearray)):
        raise Malformed("array data is not raw bytes")
    dt = dtype.dtype()
    if len(raw) != math.prod(shape) * dt.itemsize:
        raise Malformed(f"array of shape {shape} and dtype {dt.str} needs {math.prod(shape) * dt.itemsize} B "
                         f"of data, the pickle holds {len(raw)} B")
    arr = np.frombuffer(raw, dtype=dt).reshape(shape, order="F" if fortran else "C")
    return np.array(arr, dtype=dt.newbyteorder("="), order="C", copy=True)


class _Array(ArrayHolder):
    """An array being rebuilt by ``_reconstruct`` + BUILD; replaced by its ``array`` in the result."""

    __slots__ = ()

    def __init__(self, array: np.ndarray | None = None):
        if array is not None:
            self.array = array

    def __setstate__(self, state) -> None:
        if hasattr(self, "array"):
            raise Malformed("an array built twice")
        if not (isinstance(state, tuple) and len(state) == 5 and state[0] == 1 and isinstance(state[3], bool)):
            raise Malformed(f"bad numpy array state {str(state)[:80]}")
        _, shape, dtype, fortran, raw = state
        self.array = _array(raw, dtype, shape, fortran)


def _reconstruct(cls, shape, typecode):
    if not isinstance(cls, _NdarrayType):
        raise Malformed("_reconstruct of something other than numpy.ndarray")
    return _Array()


def _frombuffer(raw, dtype, shape, order):
    if order not in ("C", "F"):
        raise Malformed(f"bad array order {str(order)[:8]!r}")
    return _Array(_array(raw, dtype, shape, order == "F"))


def _latin1(text="", encoding="latin1"):
    """``_codecs.encode(text, "latin1")`` and ``bytes()``: how protocol-2 pickles write bytes."""
    if not (isinstance(text, str) and encoding in ("latin1", "latin-1")):
        raise Malformed("refused bytes() or _codecs.encode() other than of a string to latin1")
    return text.encode("latin1")


def _scalar(dtype, raw=None):
    return _Array(_array(raw, dtype, (), False)[()])


class _Unpickler(pickle.Unpickler):
    """Rebuilds numpy arrays (and plain containers, strings, numbers) and nothing else (see the module docstring)."""

    def find_class(self, module: str, name: str):
        if module in _MODULES and name == "_reconstruct":
            return _reconstruct
        if module in _MODULES and name == "scalar":
            return _scalar
        if module in ("numpy._core.numeric", "numpy.core.numeric") and name == "_frombuffer":
            return _frombuffer
        if module == "numpy" and name == "ndarray":
            return _NdarrayType()
        if module == "numpy" and name == "dtype":
            return _Dtype
        if (module, name) in (("_codecs", "encode"), ("__builtin__", "bytes"), ("builtins", "bytes")):
            return _latin1
        raise Malformed(f"refused to load {module}.{name}: only numpy arrays are read")


def read_numpy_pickle(path: str | os.PathLike, max_bytes: int = MAX_NUMPY_PICKLE_BYTES) -> Any:
    """The pickled object at ``path`` (nested dicts / lists / tuples of numpy arrays, strings, numbers), nothing
    run; :class:`ProxycodecError` naming the file for anything else, a malformed or truncated file included."""
    path = Path(path)
    try:
        size = path.stat().st_size
        if size > max_bytes:
            raise ProxycodecError(f"{size:,} B is too large for a weights file (at most {max_bytes:,} B)", path)
        data = path.read_bytes()
    except FileNotFoundError:
        raise ProxycodecError("no such file", path) from None
    except IsADirectoryError:
        raise ProxycodecError("is a folder, not a weights file", path) from None
    except PermissionError:
        raise ProxycodecError("permission denied", path) from None
    return restricted_load(_Unpickler(io.BytesIO(data)), data, path)
