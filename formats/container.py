"""The proxycodec container (``.pxc``): a header, a table of contents, and one stream per section.

Byte layout: ``formats/CONTAINER.md``. This module is the generic layer (named arrays + JSON metadata, each section
zstd-compressed or raw, CRC32-checked); what the sections mean for a compressed scene is ``proxycodec.codec``'s.

The reader is strict: every length is bounded by the file size and by caps before anything is allocated, a
decompressed stream may not exceed its declared raw size (it is decompressed in chunks, so a forged size cannot make
us allocate), and every failure raises ``ContainerError`` (a ``ProxycodecError``) naming the file.
"""

from __future__ import annotations

import json
import os
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import zstandard

from ..errors import ProxycodecError
from ..fileio import atomic_write

MAGIC = b"\x89PXC\r\n\x1a\n"
FORMAT_VERSION = 1
SUPPORTED_VERSIONS = (1,)
HEADER = struct.Struct("<8sHHIQII")  # magic, version, flags, n_sections, toc_len, toc_crc, header_crc
assert HEADER.size == 32
ENTRY_FIXED = struct.Struct("<BBBB")  # codec, dtype, ndim, reserved
ENTRY_TAIL = struct.Struct("<QQQI")  # offset, stored size, raw size, crc32 of raw bytes

CODEC_RAW, CODEC_ZSTD = 0, 1
DTYPES = {1: "u1", 2: "i1", 3: "<u2", 4: "<i2", 5: "<u4", 6: "<i4", 7: "<u8", 8: "<i8", 9: "<f2", 10: "<f4", 11: "<f8"}
DTYPE_CODES = {np.dtype(v).str: k for k, v in DTYPES.items()}

MAX_SECTIONS = 4096
MAX_TOC_BYTES = 1 << 20
MAX_NAME = 64
MAX_NDIM = 8
MAX_RAW_BYTES = 8 << 30  # 8 GiB: no real section comes near
#: zstd's largest expansion per input byte: a 4-byte block (3-byte header + 1 RLE byte) yields up to 128 KiB.
ZSTD_BLOCK_RATIO = 1 << 15
#: A section claiming more than twice that expansion is forged (refused before any decompression).
MAX_ZSTD_RATIO = 2 * ZSTD_BLOCK_RATIO
#: How far past the declared raw size decompression may run before it stops (plus one 128 KiB block): the input is
#: fed in pieces no larger than (room + slack) / ZSTD_BLOCK_RATIO bytes, so no piece can expand past it.
DECOMPRESS_SLACK = 1 << 26
META_SECTION = "meta"


class ContainerError(ProxycodecError):
    """A container file is malformed, corrupt, truncated or of an unsupported version."""


@dataclass(frozen=True)
class SectionInfo:
    name: str
    codec: int
    dtype: np.dtype
    shape: tuple[int, ...]
    offset: int
    stored_size: int
    raw_size: int
    crc32: int

    def to_json(self) -> dict:
        return {"name": self.name, "codec": "zstd" if self.codec == CODEC_ZSTD else "raw", "dtype": self.dtype.str,
                "shape": list(self.shape), "stored_bytes": self.stored_size, "raw_bytes": self.raw_size}


@dataclass(frozen=True)
class Container:
    version: int
    flags: int
    meta: dict[str, Any]
    arrays: dict[str, np.ndarray]
    sections: tuple[SectionInfo, ...]
    file_size: int


def _encode_name(name: str) -> bytes:
    b = name.encode("utf-8")
    if not (0 < len(b) <= MAX_NAME) or not all((c.isascii() and c.isalnum()) or c in "_./-" for c in name):
        raise ProxycodecError(f"bad section name {name!r}")
    return b


def write_container(
    path: str | os.PathLike,
    meta: Mapping[str, Any],
    arrays: Mapping[str, np.ndarray],
    *,
    level: int = 19,
    flags: int = 0,
    raw_sections: frozenset[str] = frozenset(),
) -> int:
    """Write ``meta`` (JSON) and ``arrays`` atomically; returns the file size. Deterministic: same input, same bytes."""
    meta_bytes = json.dumps(meta, sort_keys=True, separators=(",", ":"), allow_nan=False).encode("utf-8")
    items = [(META_SECTION, np.frombuffer(meta_bytes, dtype=np.uint8))]
    for name, a in arrays.items():
        if name == META_SECTION:
            raise ProxycodecError(f"section name {META_SECTION!r} is reserved")
        items.append((name, np.asarray(a)))
    cctx = zstandard.ZstdCompressor(level=level, write_checksum=False, write_content_size=True)
    payloads, entries = [], []
    for name, a in items:
        dt = a.dtype.newbyteorder("<") if a.dtype.byteorder == ">" else a.dtype
        code = DTYPE_CODES.get(np.dtype(dt).str)
        if code is None:
            raise ProxycodecError(f"section {name!r}: dtype {a.dtype} is not storable")
        if a.ndim > MAX_NDIM:
            raise ProxycodecError(f"section {name!r}: too many dimensions")
        raw = np.ascontiguousarray(a, dtype=np.dtype(DTYPES[code])).tobytes()
        codec = CODEC_RAW if name in raw_sections else CODEC_ZSTD
        stored = raw if codec == CODEC_RAW else cctx.compress(raw)
        payloads.append(stored)
        entries.append((_encode_name(name), codec, code, a.shape, len(stored), len(raw), zlib.crc32(raw)))
    toc_len = sum(2 + len(n) + ENTRY_FIXED.size + 8 * len(s) + ENTRY_TAIL.size for n, _, _, s, _, _, _ in entries)
    offset = HEADER.size + toc_len
    toc = bytearray()
    for (nb, codec, code, shape, stored, raw, crc) in entries:
        toc += struct.pack("<H", len(nb)) + nb + ENTRY_FIXED.pack(codec, code, len(shape), 0)
        toc += struct.pack(f"<{len(shape)}Q", *shape)
        toc += ENTRY_TAIL.pack(offset, stored, raw, crc)
        offset += stored
    head = HEADER.pack(MAGIC, FORMAT_VERSION, flags, len(entries), len(toc), zlib.crc32(toc), 0)
    head = head[:-4] + struct.pack("<I", zlib.crc32(head[:-4]))
    with atomic_write(path) as fh:
        fh.write(head)
        fh.write(toc)
        for p in payloads:
            fh.write(p)
    return offset


def _parse_toc(toc: bytes, n: int, file_size: int, err) -> list[SectionInfo]:
    pos, out, expect_offset = 0, [], None
    for i in range(n):
        try:
            (nlen,) = struct.unpack_from("<H", toc, pos)
            pos += 2
            if not 0 < nlen <= MAX_NAME:
                raise err(f"section {i}: bad name length {nlen}")
            name = toc[pos:pos + nlen].decode("utf-8")
            pos += nlen
            codec, code, ndim, _ = ENTRY_FIXED.unpack_from(toc, pos)
            pos += ENTRY_FIXED.size
            if ndim > MAX_NDIM:
                raise err(f"section {name!r}: {ndim} dimensions")
            shape = struct.unpack_from(f"<{ndim}Q", toc, pos)
            pos += 8 * ndim
            offset, stored, raw, crc = ENTRY_TAIL.unpack_from(toc, pos)
            pos += ENTRY_TAIL.size
        except (struct.error, UnicodeDecodeError) as e:
            raise err(f"table of contents is malformed ({e})") from None
        if code not in DTYPES:
            raise err(f"section {name!r}: unknown dtype code {code}")
        if codec not in (CODEC_RAW, CODEC_ZSTD):
            raise err(f"section {name!r}: unknown codec {codec}")
        dtype = np.dtype(DTYPES[code])
        count = 1
        for s in shape:
            count *= s
            if count * dtype.itemsize > MAX_RAW_BYTES:
                raise err(f"section {name!r}: declared shape {shape} is too large")
        if raw != count * dtype.itemsize:
            raise err(f"section {name!r}: raw size {raw} does not match shape {shape} of {dtype}")
        if expect_offset is not None and offset != expect_offset:
            raise err(f"section {name!r}: offset {offset} is not where the previous section ends")
        if offset + stored > file_size:
            raise err(f"section {name!r} runs past the end of the file (truncated?)")
        if codec == CODEC_RAW and stored != raw:
            raise err(f"section {name!r}: stored size {stored} != raw size {raw}")
        if codec == CODEC_ZSTD and raw > stored * MAX_ZSTD_RATIO + 4096:
            raise err(f"section {name!r}: declared raw size {raw} is impossible for {stored} compressed bytes")
        expect_offset = offset + stored
        out.append(SectionInfo(name, codec, dtype, tuple(int(s) for s in shape), offset, stored, raw, crc))
    if pos != len(toc):
        raise err("table of contents has trailing bytes")
    if len({s.name for s in out}) != len(out):
        raise err("duplicate section names")
    return out


def read_header(path: str | os.PathLike) -> tuple[int, int, list[SectionInfo], int]:
    """(version, flags, sections, file size) without reading any payload."""
    path = Path(path)

    def err(msg: str) -> ContainerError:
        return ContainerError(msg, path)

    try:
        file_size = path.stat().st_size
        with open(path, "rb") as fh:
            head = fh.read(HEADER.size)
            if len(head) < HEADER.size:
                raise err("file is too short to be a proxycodec container")
            magic, version, flags, n, toc_len, toc_crc, head_crc = HEADER.unpack(head)
            if magic != MAGIC:
                raise err("not a proxycodec container (wrong magic bytes)")
            if zlib.crc32(head[:-4]) != head_crc:
                raise err("header checksum mismatch (corrupt file)")
            if version not in SUPPORTED_VERSIONS:
                raise err(f"container format version {version} is not supported by this proxycodec "
                          f"(supports {', '.join(map(str, SUPPORTED_VERSIONS))}); upgrade proxycodec")
            if n > MAX_SECTIONS or toc_len > MAX_TOC_BYTES or HEADER.size + toc_len > file_size:
                raise err("table of contents is larger than allowed or than the file (truncated?)")
            toc = fh.read(toc_len)
    except FileNotFoundError:
        raise err("no such file") from None
    except IsADirectoryError:
        raise err("is a directory, not a container file") from None
    if zlib.crc32(toc) != toc_crc:
        raise err("table of contents checksum mismatch (corrupt file)")
    sections = _parse_toc(toc, n, file_size, err)
    if sections and sections[0].offset != HEADER.size + toc_len:
        raise err("first section does not follow the table of contents")
    end = sections[-1].offset + sections[-1].stored_size if sections else HEADER.size + toc_len
    if end != file_size:
        raise err(f"file has {file_size - end} unexpected trailing bytes" if end < file_size else "truncated")
    return version, flags, sections, file_size


def _decompress(stored: bytes, raw_size: int, err) -> bytearray:
    """Chunked decompression that never produces (or allocates for) more than ``raw_size`` bytes."""
    dctx = zstandard.ZstdDecompressor()
    try:
        params = zstandard.get_frame_parameters(stored)
    except zstandard.ZstdError as e:
        raise err(f"bad compressed stream ({e})") from None
    if params.content_size not in (zstandard.CONTENTSIZE_UNKNOWN, raw_size):
        raise err(f"compressed stream declares {params.content_size} bytes, table of contents {raw_size}")
    out = bytearray()
    dobj = dctx.decompressobj()
    view = memoryview(stored)
    try:
        i = 0
        while i < len(stored):
            # a piece of n input bytes yields at most n / 4 + 1 blocks of 128 KiB: never more than the room left
            # plus the slack (and one block), whatever the stream
            n = min(1 << 16, max(4, (raw_size - len(out) + DECOMPRESS_SLACK) // ZSTD_BLOCK_RATIO))
            out += dobj.decompress(view[i:i + n])
            i += n
            if len(out) > raw_size:
                raise err("compressed stream is longer than declared")
    except zstandard.ZstdError as e:
        raise err(f"corrupt compressed stream ({e})") from None
    if not dobj.eof or dobj.unused_data:
        raise err("compressed stream is truncated or has trailing data")
    if len(out) != raw_size:
        raise err(f"compressed stream holds {len(out)} bytes, expected {raw_size}")
    return out  # no bytes() copy: peak memory stays at one raw-size buffer


def read_container(path: str | os.PathLike, *, sections: set[str] | None = None) -> Container:
    """Read and verify a container (all sections, or only ``sections`` plus the metadata)."""
    path = Path(path)

    def err(msg: str) -> ContainerError:
        return ContainerError(msg, path)

    version, flags, infos, file_size = read_header(path)
    arrays: dict[str, np.ndarray] = {}
    meta: dict[str, Any] | None = None
    with open(path, "rb") as fh:
        for s in infos:
            if sections is not None and s.name != META_SECTION and s.name not in sections:
                continue
            fh.seek(s.offset)
            stored = fh.read(s.stored_size)
            if len(stored) != s.stored_size:
                raise err(f"section {s.name!r} is truncated")
            raw = stored if s.codec == CODEC_RAW else _decompress(stored, s.raw_size, lambda m, n=s.name: err(f"section {n!r}: {m}"))
            if zlib.crc32(raw) != s.crc32:
                raise err(f"section {s.name!r}: checksum mismatch (corrupt file)")
            a = np.frombuffer(raw, dtype=s.dtype).reshape(s.shape)
            if s.name == META_SECTION:
                if s.dtype != np.uint8 or len(s.shape) != 1:
                    raise err("metadata section must be 1-D bytes")
                try:
                    meta = json.loads(raw.decode("utf-8"), parse_constant=lambda c: (_ for _ in ()).throw(ValueError(c)))
                except (UnicodeDecodeError, ValueError, RecursionError) as e:
                    raise err(f"metadata is not valid JSON ({type(e).__name__})") from None
                if not isinstance(meta, dict):
                    raise err("metadata must be a JSON object")
            else:
                arrays[s.name] = a
    if meta is None:
        raise err("no metadata section")
    return Container(version, flags, meta, arrays, tuple(infos), file_size)
