"""The generic container layer (formats/container.py) and hostile input, through the library and the CLI."""

from __future__ import annotations

import struct
import zlib

import numpy as np
import pytest
import torch
import zstandard
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from proxycodec import codec
from proxycodec.cli.main import cli
from proxycodec.errors import ProxycodecError
from proxycodec.formats.container import (
    ENTRY_FIXED, ENTRY_TAIL, FORMAT_VERSION, HEADER, MAGIC, ContainerError, read_container, read_header,
    write_container,
)

META = {"kind": "test", "n": 3, "nested": {"a": [1.5, -2.0]}, "text": "é"}


def arrays() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    return {
        "a/u8": rng.integers(0, 255, (3, 7), dtype=np.uint8),
        "b/i16": rng.integers(-300, 300, 11).astype(np.int16),
        "c/f16": rng.normal(size=(2, 2, 2)).astype(np.float16),
        "d/f32": rng.normal(size=5).astype(np.float32),
        "e/f64": rng.normal(size=(1, 4)),
        "f/empty": np.zeros((0, 3), np.float32),
        "g/big": np.arange(5000, dtype=np.int64) // 7,
        "h/be": np.arange(4, dtype=">i4"),
    }


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    p = tmp_path_factory.mktemp("c") / "small.pxc"
    write_container(p, META, arrays(), raw_sections=frozenset({"d/f32"}))
    return p


class TestRoundTrip:
    def test_arrays_meta_and_dtypes(self, small):
        c = read_container(small)
        assert c.meta == META and c.version == FORMAT_VERSION
        want = arrays()
        assert list(c.arrays) == list(want)
        for k, v in want.items():
            assert c.arrays[k].shape == v.shape and np.array_equal(c.arrays[k], v), k
            assert c.arrays[k].dtype == v.dtype.newbyteorder("<"), k
        info = {s.name: s for s in c.sections}
        assert info["d/f32"].codec == 0 and info["d/f32"].stored_size == 20
        assert info["g/big"].codec == 1 and info["g/big"].stored_size < info["g/big"].raw_size

    def test_layout_is_as_documented(self, small):
        data = small.read_bytes()
        magic, version, flags, n, toc_len, toc_crc, head_crc = HEADER.unpack_from(data)
        assert magic == MAGIC and version == 1 and flags == 0 and n == 1 + len(arrays())
        assert head_crc == zlib.crc32(data[:28]) and toc_crc == zlib.crc32(data[32:32 + toc_len])
        pos, offset = 32, 32 + toc_len
        for _ in range(n):
            (nlen,) = struct.unpack_from("<H", data, pos)
            pos += 2 + nlen
            codec_id, dtype, ndim, reserved = ENTRY_FIXED.unpack_from(data, pos)
            assert reserved == 0
            pos += 4 + 8 * ndim
            off, stored, raw, crc = ENTRY_TAIL.unpack_from(data, pos)
            pos += ENTRY_TAIL.size
            assert off == offset
            payload = data[off:off + stored]
            rawb = payload if codec_id == 0 else zstandard.ZstdDecompressor().decompress(payload)
            assert len(rawb) == raw and zlib.crc32(rawb) == crc
            offset += stored
        assert pos == 32 + toc_len and offset == len(data)
        first = data[32 + 2:32 + 2 + 4]
        assert first == b"meta"

    def test_deterministic(self, tmp_path):
        write_container(tmp_path / "a", META, arrays())
        write_container(tmp_path / "b", META, arrays())
        assert (tmp_path / "a").read_bytes() == (tmp_path / "b").read_bytes()

    def test_partial_read(self, small):
        c = read_container(small, sections={"b/i16"})
        assert list(c.arrays) == ["b/i16"] and c.meta == META

    def test_writer_rejects_bad_input(self, tmp_path):
        for name, arrs in (("reserved", {"meta": np.zeros(1)}), ("bad name", {"a b": np.zeros(1)}),
                           ("long", {"x" * 65: np.zeros(1)}), ("object", {"o": np.array([object()])}),
                           ("complex", {"c": np.zeros(2, np.complex64)})):
            with pytest.raises(ProxycodecError):
                write_container(tmp_path / "x", {}, arrs)
        with pytest.raises(ValueError):
            write_container(tmp_path / "x", {"nan": float("nan")}, {})
        assert not (tmp_path / "x").exists()


def _forge(data: bytes, *, version=None, toc: bytes | None = None, n=None) -> bytes:
    """Rewrite header fields (and the TOC) with valid checksums, so only the intended field is wrong."""
    magic, v, flags, n0, toc_len, toc_crc, _ = HEADER.unpack_from(data)
    old_toc = data[32:32 + toc_len]
    new_toc = old_toc if toc is None else toc
    head = HEADER.pack(magic, v if version is None else version, flags, n0 if n is None else n, len(new_toc),
                       zlib.crc32(new_toc), 0)
    head = head[:-4] + struct.pack("<I", zlib.crc32(head[:-4]))
    return head + new_toc + data[32 + toc_len:]


class TestHostile:
    def test_wrong_magic_empty_short_missing_directory(self, small, tmp_path):
        data = small.read_bytes()
        cases = {"magic": b"PLY\n" + data[4:], "empty": b"", "short": data[:20]}
        for name, blob in cases.items():
            p = tmp_path / name
            p.write_bytes(blob)
            with pytest.raises(ContainerError):
                read_container(p)
        with pytest.raises(ContainerError, match="no such file"):
            read_container(tmp_path / "missing")
        with pytest.raises(ContainerError):
            read_container(tmp_path)

    def test_future_version(self, small, tmp_path):
        p = tmp_path / "v2"
        p.write_bytes(_forge(small.read_bytes(), version=FORMAT_VERSION + 1))
        with pytest.raises(ContainerError, match="version 2 is not supported"):
            read_container(p)

    def test_one_gigabyte_declared_section_in_a_tiny_file(self, tmp_path):
        p = tmp_path / "bomb"
        write_container(p, {}, {"x": np.zeros(16, np.uint8)})
        data = p.read_bytes()
        toc_len = HEADER.unpack_from(data)[4]
        toc = bytearray(data[32:32 + toc_len])
        # the second entry ("x", ndim 1): patch its shape to 1 GiB and its raw size to match
        meta_len = 2 + 4 + 4 + 8 + ENTRY_TAIL.size
        pos = meta_len + 2 + 1 + 4
        struct.pack_into("<Q", toc, pos, 1 << 30)
        off, stored, raw, crc = ENTRY_TAIL.unpack_from(toc, pos + 8)
        ENTRY_TAIL.pack_into(toc, pos + 8, off, stored, 1 << 30, crc)
        p.write_bytes(_forge(data, toc=bytes(toc)))
        with pytest.raises(ContainerError, match="impossible|too large"):
            read_container(p)
        # ... and a forged zstd frame that does expand, but to more than declared, is stopped while decompressing
        bomb = zstandard.ZstdCompressor(level=1, write_content_size=False).compress(b"\0" * (1 << 22))
        p2 = tmp_path / "bomb2"
        write_container(p2, {}, {"x": np.zeros(16, np.uint8)})
        d2 = bytearray(p2.read_bytes())
        toc_len = HEADER.unpack_from(d2)[4]
        toc = bytearray(d2[32:32 + toc_len])
        off, stored, raw, crc = ENTRY_TAIL.unpack_from(toc, pos + 8)
        ENTRY_TAIL.pack_into(toc, pos + 8, off, len(bomb), raw, crc)
        out = _forge(bytes(d2[:off]), toc=bytes(toc)) + bomb
        p2.write_bytes(out)
        with pytest.raises(ContainerError, match="longer than declared|holds|content"):
            read_container(p2)

    def test_a_bomb_stops_within_a_block_of_the_declared_size(self, tmp_path, monkeypatch):
        """64 MiB of zeros in ~2 KB, declared as 16 bytes: decompression stops before it has made 1 MiB (without the
        slack: the room left plus one 128 KiB block), where one 64 KiB input chunk would have made all 64 MiB."""
        import tracemalloc

        import proxycodec.formats.container as C

        monkeypatch.setattr(C, "DECOMPRESS_SLACK", 0)
        bomb = zstandard.ZstdCompressor(level=1, write_content_size=False).compress(b"\0" * (64 << 20))
        assert len(bomb) < (1 << 16)
        tracemalloc.start()
        try:
            with pytest.raises(ContainerError, match="longer than declared"):
                C._decompress(bomb, 16, lambda m: ContainerError(m, "bomb"))
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        assert peak < (1 << 20), peak
        # the default slack decodes a legitimate stream whatever its ratio
        data = np.arange(1 << 20, dtype=np.uint32).tobytes() + bytes(8 << 20)
        z = zstandard.ZstdCompressor(level=3, write_content_size=False).compress(data)
        monkeypatch.setattr(C, "DECOMPRESS_SLACK", 1 << 26)
        assert bytes(C._decompress(z, len(data), lambda m: ContainerError(m, "z"))) == data

    def test_trailing_bytes_and_too_many_sections(self, small, tmp_path):
        p = tmp_path / "t"
        p.write_bytes(small.read_bytes() + b"\0")
        with pytest.raises(ContainerError, match="trailing"):
            read_container(p)
        p.write_bytes(_forge(small.read_bytes(), n=10_000))
        with pytest.raises(ContainerError):
            read_container(p)

    @settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
    @given(cut=st.integers(min_value=0, max_value=10_000))
    def test_any_truncation(self, small, tmp_path, cut):
        data = small.read_bytes()
        p = tmp_path / "trunc"
        p.write_bytes(data[:cut % len(data)])
        with pytest.raises(ContainerError):
            read_container(p)

    @settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
    @given(pos=st.integers(min_value=0, max_value=1 << 20), bit=st.integers(min_value=0, max_value=7))
    def test_any_single_bit_flip(self, small, tmp_path, pos, bit):
        data = bytearray(small.read_bytes())
        data[pos % len(data)] ^= 1 << bit
        p = tmp_path / "flip"
        p.write_bytes(bytes(data))
        # Either a ContainerError, or (a flip in bits a zstd frame never reads) exactly the original content:
        # the CRC32 of every section's raw bytes makes anything else impossible.
        try:
            c = read_container(p)
        except ContainerError:
            return
        want = read_container(small)
        assert c.meta == want.meta and all(np.array_equal(c.arrays[k], v) for k, v in want.arrays.items())


@pytest.fixture(scope="module")
def scene_file(tmp_path_factory):
    from test_codec import FAST, tiny_model

    p = tmp_path_factory.mktemp("s") / "scene.pxc"
    codec.encode(tiny_model(80), p, **FAST)
    return p


class TestHostileScene:
    @settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
    @given(pos=st.integers(min_value=0, max_value=1 << 20), bit=st.integers(min_value=0, max_value=7))
    def test_bit_flip_anywhere_in_a_scene(self, scene_file, tmp_path, pos, bit):
        data = bytearray(scene_file.read_bytes())
        data[pos % len(data)] ^= 1 << bit
        p = tmp_path / "flip.pxc"
        p.write_bytes(bytes(data))
        try:
            got = codec.decode(p)
        except ContainerError:
            return
        # a flip in bits zstd never reads: the content is intact (CRC32-verified), so is the decoded scene
        want = codec.decode(scene_file)
        assert all(torch.equal(getattr(got.scene, k), getattr(want.scene, k))
                   for k in ("positions", "features", "offsets", "scalings"))

    def test_truncated_scene_and_stats(self, scene_file, tmp_path):
        p = tmp_path / "t.pxc"
        p.write_bytes(scene_file.read_bytes()[:-7])
        with pytest.raises(ContainerError, match="truncated|past the end"):
            codec.decode(p)
        with pytest.raises(ContainerError):
            codec.stats(p)

    def test_cli_exits_nonzero_with_one_line(self, scene_file, tmp_path):
        data = scene_file.read_bytes()
        bad = {"trunc.pxc": data[:len(data) // 2], "magic.pxc": b"XXXXXXXX" + data[8:],
               "future.pxc": _forge(data, version=9), "flip.pxc": data[:-3] + bytes([data[-3] ^ 0x10]) + data[-2:]}
        runner = CliRunner()
        for name, blob in bad.items():
            p = tmp_path / name
            p.write_bytes(blob)
            for args in (["decode", str(p), "--no-render"], ["stats", str(p)], ["stats", str(p), "--json"]):
                r = runner.invoke(cli, args)
                assert r.exit_code == 2, (name, args, r.output)
                assert r.output.startswith("error: ") and r.output.count("\n") == 1, r.output
                assert "Traceback" not in r.output and str(p) in r.output
        read_header(scene_file)  # the original is fine
