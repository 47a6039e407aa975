"""PyTorch files read without running anything: TorchScript archives (``torch.jit.save``) and ``torch.save`` files.

Both are zip archives holding a pickle (``<archive>/data.pkl``) whose tensors live in raw records
(``<archive>/data/<key>``). Loading them the PyTorch way runs code from the file: ``torch.jit.load`` compiles the
archive's ``code/`` folder, and an unrestricted unpickler calls whatever the pickle names. Here:

- ``read_torchscript``: a restricted unpickler over ``data.pkl`` only (``code/`` is never opened). It allows
  exactly the names a saved module's state uses: ``torch._utils._rebuild_tensor_v2`` (re-implemented with numpy:
  tensors come back as numpy arrays), ``collections.OrderedDict``, the ``torch.*Storage`` type tags of the storages
  (``persistent_load``), and ``__torch__.*`` module classes, which become :class:`ScriptObject` state holders (the
  class's qualified name and a dict of attributes: parameters, buffers, submodules, plain values). Any other name
  (``os.system``, ``builtins.eval``, ...) is refused before anything is called.
- ``read_torch_checkpoint``: a ``torch.save`` file of (nested dicts of) tensors. The same restricted unpickler reads
  it first (no ``__torch__`` classes allowed), which checks every storage against its record and every tensor against
  its storage, then ``torch.load(weights_only=True)`` loads it.

Every size is bounded before it is allocated: records by the archive's size, a storage's element count by its record
(exactly, as PyTorch writes them), a tensor by its storage, and all tensors together by twice the file size. Any
problem raises one :class:`ProxycodecError` naming the file.
"""

from __future__ import annotations

import collections
import io
import math
import os
import pickle
import re
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ProxycodecError
from .safe_pickle import MAX_NDIM, ArrayHolder, Holder, Malformed, Part, convert, int_tuple, restricted_load, \
    short_error

__all__ = ["ScriptObject", "read_torchscript", "read_torch_checkpoint", "MAX_ARCHIVE_BYTES"]

#: Scaffold-GS's MLP files are a few KB; nothing of this kind comes near.
MAX_ARCHIVE_BYTES = 256 << 20
MAX_PICKLE_BYTES = 16 << 20
MAX_RECORDS = 65536
#: Tensors rebuilt from one file may hold at most this many bytes per byte of file (views of one storage repeat it).
TENSOR_BUDGET_RATIO = 2
TENSOR_BUDGET_MIN = 1 << 16

#: ``torch.<Name>Storage`` -> numpy dtype (little endian; swapped for a ``byteorder`` record saying "big").
STORAGE_DTYPES = {
    "FloatStorage": "f4", "DoubleStorage": "f8", "HalfStorage": "f2", "LongStorage": "i8", "IntStorage": "i4",
    "ShortStorage": "i2", "CharStorage": "i1", "ByteStorage": "u1", "BoolStorage": "b1",
}
_KEY = re.compile(r"[0-9A-Za-z_]{1,64}")


@dataclass
class ScriptObject:
    """The pickled state of one TorchScript module: its class (``__torch__.`` qualified name, as saved, mangling
    included) and its attributes (submodules as ``ScriptObject``, tensors as numpy arrays, plain values)."""

    qualname: str
    attributes: dict[str, Any] = field(default_factory=dict)

    @property
    def kind(self) -> str:
        """The class name without TorchScript's ``___torch_mangle_N`` parts, e.g. ``torch.nn.modules.linear.Linear``
        for ``__torch__.torch.nn.modules.linear.___torch_mangle_0.Linear``."""
        parts = [p for p in self.qualname.split(".") if p != "__torch__" and not p.startswith("___torch_mangle")]
        return ".".join(parts)


class _StorageType(Part):
    """What ``torch.FloatStorage`` & co. unpickle to: a tag naming the storage's dtype (not callable)."""

    __slots__ = ("name", "dtype")

    def __init__(self, name: str, dtype: np.dtype):
        self.name, self.dtype = name, dtype


class _ScriptState(Holder):
    """Base of the classes ``__torch__.*`` names unpickle to: instances only collect the state BUILD gives them, and
    become :class:`ScriptObject` in the result."""

    qualname = ""

    def __init__(self) -> None:  # REDUCE with arguments -> TypeError -> refused
        self.state: dict = {}

    def __setstate__(self, state) -> None:
        if not isinstance(state, dict):
            raise Malformed(f"state of {self.qualname} is not a dict")
        self.state = state

    def result(self, memo: dict[int, Any], depth: int) -> ScriptObject:
        out = memo[id(self)] = ScriptObject(type(self).qualname)
        if not isinstance(self.state, dict):
            raise Malformed(f"{type(self).qualname} has no state")
        out.attributes = {str(k): convert(v, memo, depth + 1) for k, v in self.state.items()}
        return out


class _Storage(Part):
    __slots__ = ("array",)

    def __init__(self, array: np.ndarray):
        self.array = array


class _Archive:
    """A zip archive as PyTorch writes it: one top-level folder holding ``data.pkl`` and ``data/<key>`` records."""

    def __init__(self, path: Path):
        self.path = path
        try:
            self.size = path.stat().st_size
        except FileNotFoundError:
            raise ProxycodecError("no such file", path) from None
        if self.size > MAX_ARCHIVE_BYTES:
            raise ProxycodecError(f"{self.size:,} B is too large for a network file "
                                  f"(at most {MAX_ARCHIVE_BYTES:,} B)", path)
        try:
            self.zip = zipfile.ZipFile(path)
            infos = self.zip.infolist()
        except (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError, IndexError, OverflowError,
                UnicodeDecodeError, NotImplementedError, RuntimeError) as e:
            raise ProxycodecError(f"not a PyTorch zip archive ({short_error(e)})", path) from None
        if len(infos) > MAX_RECORDS:
            raise ProxycodecError(f"archive holds {len(infos)} records, more than {MAX_RECORDS}", path)
        self.infos = {i.filename: i for i in infos}
        pickles = [n for n in self.infos if n.endswith("/data.pkl") and n.count("/") == 1]
        if len(pickles) != 1:
            raise ProxycodecError("not a PyTorch archive: expected one <name>/data.pkl record"
                                  + (f", found {len(pickles)}" if pickles else ""), path)
        self.prefix = pickles[0][: -len("data.pkl")]
        order = self.read(self.prefix + "byteorder", 16) if self.prefix + "byteorder" in self.infos else b"little"
        if order not in (b"little", b"big"):
            raise ProxycodecError(f"unknown byte order {order[:16]!r}", path)
        self.endian = "<" if order == b"little" else ">"

    def read(self, name: str, limit: int) -> bytes:
        info = self.infos.get(name)
        if info is None:
            raise ProxycodecError(f"archive record {name!r} is missing", self.path)
        if info.file_size > min(limit, self.size) or info.compress_size > self.size:
            raise ProxycodecError(f"archive record {name!r} declares {info.file_size:,} B, more than the file "
                                  "can hold", self.path)
        try:
            data = self.zip.read(info)
        except (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError, NotImplementedError, RuntimeError,
                OverflowError, IndexError) as e:
            raise ProxycodecError(f"archive record {name!r} is corrupt ({short_error(e)})", self.path) from None
        if len(data) != info.file_size:
            raise ProxycodecError(f"archive record {name!r} is truncated", self.path)
        return data

    def close(self) -> None:
        self.zip.close()


class _Unpickler(pickle.Unpickler):
    """Rebuilds a saved module's state and nothing else (see the module docstring)."""

    def __init__(self, archive: _Archive, data: bytes, allow_script: bool):
        super().__init__(io.BytesIO(data))
        self.archive = archive
        self.allow_script = allow_script
        self.storages: dict[str, _Storage] = {}
        self.classes: dict[str, type] = {}
        self.budget = max(TENSOR_BUDGET_MIN, TENSOR_BUDGET_RATIO * archive.size)

    def find_class(self, module: str, name: str):
        if self.allow_script and (module == "__torch__" or module.startswith("__torch__.")):
            qual = f"{module}.{name}"
            if len(qual) > 512 or not all(p.isidentifier() for p in qual.split(".")):
                raise Malformed(f"bad class name {qual[:80]!r}")
            if qual not in self.classes:
                if len(self.classes) > 4096:
                    raise Malformed("too many module classes")
                self.classes[qual] = type("ScriptState", (_ScriptState,), {"qualname": qual, "__slots__": ()})
            return self.classes[qual]
        if module == "torch._utils" and name == "_rebuild_tensor_v2":
            return self.rebuild_tensor
        if module == "torch._utils" and name == "_rebuild_parameter":
            return _rebuild_parameter
        if module == "collections" and name == "OrderedDict":
            return collections.OrderedDict
        if module == "torch" and name in STORAGE_DTYPES:
            return _StorageType(name, np.dtype(self.archive.endian + STORAGE_DTYPES[name]))
        raise Malformed(f"refused to load {module}.{name}: only tensors and module state are read")

    def persistent_load(self, pid):
        if not (isinstance(pid, tuple) and len(pid) == 5 and pid[0] == "storage"):
            raise Malformed(f"unknown persistent id {str(pid)[:80]!r}")
        _, stype, key, _location, numel = pid
        if not isinstance(stype, _StorageType):
            raise Malformed("storage without a storage type")
        if not (isinstance(key, str) and _KEY.fullmatch(key)):
            raise Malformed(f"bad storage key {str(key)[:80]!r}")
        if not (isinstance(numel, int) and not isinstance(numel, bool) and numel >= 0):
            raise Malformed(f"bad storage size {str(numel)[:40]!r}")
        if key in self.storages:
            st = self.storages[key]
            if st.array.dtype != stype.dtype or st.array.size != numel:
                raise Malformed(f"storage {key} is declared twice with different types or sizes")
            return st
        nbytes = numel * stype.dtype.itemsize
        name = f"{self.archive.prefix}data/{key}"
        info = self.archive.infos.get(name)
        if info is None:
            raise Malformed(f"storage record {name!r} is missing")
        if info.file_size != nbytes:
            raise Malformed(f"storage {key} declares {numel} x {stype.dtype.itemsize} B but its record holds "
                             f"{info.file_size} B")
        raw = self.archive.read(name, nbytes)
        arr = np.frombuffer(raw, dtype=stype.dtype)
        self.storages[key] = _Storage(arr)
        return self.storages[key]

    def rebuild_tensor(self, storage, offset, size, stride, requires_grad=False, hooks=None, metadata=None):
        """``torch._utils._rebuild_tensor_v2`` with numpy: a copy of the strided view, bounds checked first."""
        if not isinstance(storage, _Storage):
            raise Malformed("a tensor without a storage")
        if not (int_tuple(size) and int_tuple(stride) and len(size) == len(stride) <= MAX_NDIM):
            raise Malformed(f"bad tensor shape {str(size)[:80]} / stride {str(stride)[:80]}")
        if not (isinstance(offset, int) and not isinstance(offset, bool) and offset >= 0):
            raise Malformed(f"bad storage offset {str(offset)[:40]!r}")
        arr = storage.array
        numel = math.prod(size)
        if numel == 0:
            if any(s > arr.size + 1 for s in size):
                raise Malformed(f"empty tensor of shape {size} is implausible")
            return ArrayHolder(np.zeros(size, dtype=arr.dtype.newbyteorder("=")))
        last = offset + sum((s - 1) * st for s, st in zip(size, stride))
        if last >= arr.size or numel > arr.size:
            raise Malformed(f"tensor of shape {tuple(size)} (offset {offset}, stride {tuple(stride)}) runs past "
                             f"its storage of {arr.size} elements")
        self.budget -= numel * arr.dtype.itemsize
        if self.budget < 0:
            raise Malformed("the tensors add up to far more than the file holds")
        view = np.lib.stride_tricks.as_strided(arr[offset:], shape=size,
                                               strides=tuple(st * arr.dtype.itemsize for st in stride))
        return ArrayHolder(np.array(view, dtype=arr.dtype.newbyteorder("="), copy=True))


def _rebuild_parameter(data, requires_grad=False, hooks=None):
    if not isinstance(data, ArrayHolder):
        raise Malformed("a parameter that is not a tensor")
    return data


def _load(path: str | os.PathLike, allow_script: bool):
    path = Path(path)
    archive = _Archive(path)
    try:
        data = archive.read(archive.prefix + "data.pkl", MAX_PICKLE_BYTES)
        return restricted_load(_Unpickler(archive, data, allow_script), data, path, " in data.pkl")
    finally:
        archive.close()


def read_torchscript(path: str | os.PathLike) -> ScriptObject:
    """The state of the module saved by ``torch.jit.save`` / ``ScriptModule.save`` at ``path`` (nothing is run)."""
    root = _load(path, allow_script=True)
    if not isinstance(root, ScriptObject):
        raise ProxycodecError("not a TorchScript module archive (data.pkl holds no module)", path)
    return root


def read_torch_checkpoint(path: str | os.PathLike) -> dict:
    """A ``torch.save`` file of (nested) dicts of tensors, as numpy arrays.

    The restricted unpickler reads it first (bounds and allowed names, see the module docstring); then
    ``torch.load(weights_only=True, map_location="cpu")`` loads it, and its tensors are returned as numpy arrays.
    """
    path = Path(path)
    checked = _load(path, allow_script=False)
    if not isinstance(checked, dict):
        raise ProxycodecError("checkpoint does not hold a dict", path)
    import torch  # a checkpoint is only ever read to build a torch model

    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, EOFError, ValueError, TypeError, KeyError, IndexError,
            AttributeError, OverflowError, zipfile.BadZipFile) as e:
        raise ProxycodecError(f"torch.load(weights_only=True) refused it ({short_error(e)})", path) from None

    def to_numpy(o, depth=0):
        if depth > 64:
            raise ProxycodecError("checkpoint nested too deeply", path)
        if isinstance(o, torch.Tensor):
            return o.detach().cpu().numpy().copy()
        if isinstance(o, dict):
            return {k: to_numpy(v, depth + 1) for k, v in o.items()}
        return o

    return to_numpy(obj)
