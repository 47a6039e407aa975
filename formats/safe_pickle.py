"""What the restricted unpicklers share (``torchscript`` for PyTorch files, ``numpy_pickle`` for plain pickles of
numpy arrays): the opcode pre-scan, the conversion of the unpickled graph, the one error path.

A restricted unpickler's ``find_class`` hands the pickle stand-ins instead of the names it asks for: :class:`Part`
(building blocks valid only inside a tensor or array: storages, dtype specs) and :class:`Holder` (objects replaced
in the result, e.g. :class:`ArrayHolder` by its numpy array). :func:`restricted_load` scans the pickle, runs the
unpickler and converts the graph; every problem becomes one :class:`ProxycodecError` naming the file.
"""

from __future__ import annotations

import pickle
import pickletools
import zipfile
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ProxycodecError

__all__ = ["MAX_NDIM", "ArrayHolder", "Holder", "Malformed", "Part", "convert", "int_tuple", "restricted_load",
           "scan", "short_error"]

MAX_NDIM = 16


class Malformed(Exception):
    """Raised inside an unpickler; turned into a ``ProxycodecError`` naming the file."""


class Part:
    """Base of the building blocks an unpickler hands to the pickle (storage tags, storages, numpy dtype specs):
    valid only inside a tensor or array, refused when one is left over in the result (:func:`convert`)."""

    __slots__ = ()
    what = "storage"


class Holder:
    """Base of the objects :func:`convert` replaces by what :meth:`result` makes of them."""

    __slots__ = ()

    def result(self, memo: dict[int, Any], depth: int) -> Any:  # pragma: no cover - every holder overrides it
        raise NotImplementedError


class ArrayHolder(Holder):
    """A rebuilt tensor or array while unpickling (replaced by its ``array``): no ``__setstate__``, no ``__dict__``,
    so the pickle cannot BUILD, SETITEM or APPEND into the numpy array."""

    __slots__ = ("array",)

    def __init__(self, array: np.ndarray):
        self.array = array

    def result(self, memo: dict[int, Any], depth: int) -> np.ndarray:
        return self.array


def int_tuple(t) -> bool:
    return isinstance(t, tuple) and all(isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in t)


def short_error(e: BaseException) -> str:
    return f"{type(e).__name__}: {str(e).splitlines()[0][:120] if str(e) else ''}".rstrip(": ")


def convert(obj, memo: dict[int, Any] | None = None, depth: int = 0):
    """The unpickled graph with holders replaced (:meth:`Holder.result`); a shared object is converted once (so a
    pickle that references one list many times at many levels cannot make this exponential)."""
    memo = {} if memo is None else memo
    if depth > 64:
        raise Malformed("module state nested too deeply")
    if id(obj) in memo:
        return memo[id(obj)]
    if isinstance(obj, Holder):
        out = obj.result(memo, depth)
    elif isinstance(obj, dict):
        out = memo[id(obj)] = {}
        out.update((k, convert(v, memo, depth + 1)) for k, v in obj.items())
    elif isinstance(obj, list):
        out = memo[id(obj)] = []
        out.extend(convert(v, memo, depth + 1) for v in obj)
    elif isinstance(obj, tuple):
        out = memo[id(obj)] = tuple(convert(v, memo, depth + 1) for v in obj)
    elif isinstance(obj, Part):
        raise Malformed(f"a bare {obj.what} outside a tensor")
    else:
        out = obj
    return out


def scan(data: bytes) -> None:
    """Parse the pickle's opcodes without building anything (``pickletools.genops``) before the unpickler runs:
    CPython's unpickler sizes its memo table by the largest index a PUT names, so a 10-byte pickle naming index 2^32
    would make it allocate 32 GB. Memo indices must come in order (each PUT at most one past the previous ones), as
    every pickler writes them."""
    puts = 0
    for op, arg, _ in pickletools.genops(data):
        if op.name in ("PUT", "BINPUT", "LONG_BINPUT"):
            if not isinstance(arg, int) or not 0 <= arg <= puts:
                raise Malformed(f"memo index {str(arg)[:20]} out of order")
            puts = max(puts, arg + 1)
        elif op.name == "MEMOIZE":
            puts += 1
        elif op.name == "STOP":
            return


def restricted_load(unpickler: pickle.Unpickler, data: bytes, path: Path, where: str = "") -> Any:
    """Run a restricted ``unpickler`` over ``data`` (scanned first, see :func:`scan`) and return the converted
    result; every problem becomes one :class:`ProxycodecError` naming ``path`` (``where``: the pickle's place in it)."""
    try:
        scan(data)
        return convert(unpickler.load())
    except ProxycodecError:
        raise
    except Malformed as e:
        raise ProxycodecError(str(e), path) from None
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError, KeyError, IndexError, AttributeError,
            OverflowError, RecursionError, UnicodeDecodeError, zipfile.BadZipFile, zlib.error) as e:
        raise ProxycodecError(f"malformed pickle{where} ({short_error(e)})", path) from None
