"""Hostile files: every reader refuses malformed input with ``ProxycodecError`` and nothing else, in bounded memory.

Seed files are generated here (small valid files of every format we read), then mutated: truncations, bit flips,
huge declared counts and sizes, NaN/Inf payloads, wrong magic/version, spliced garbage. The only exception a reader
may let escape is ``ProxycodecError`` (or a subclass such as ``ContainerError``); IndexError, struct.error,
MemoryError, UnicodeDecodeError, OverflowError or numpy errors are bugs in the reader.

``benchmarks/fuzz_long.py`` reuses :data:`READERS`, :func:`make_seeds` and :func:`mutate` for a longer run; the
regression corpus in ``tests/corpus/`` holds the inputs that once broke a reader (and the classic attacks).
"""

from __future__ import annotations

import json
import os
import random
import struct
import subprocess
import sys
import tempfile
import zlib
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from conftest import read_until, signal_when_ready
from PIL import Image
from proxycodec import lite
from proxycodec.formats import colmap, container
from proxycodec.formats.blender import load_blender
from proxycodec.formats.inria_ply import GaussianPly, read_inria_ply, write_inria_ply
from proxycodec.formats.ply import encode_ply, read_ply, read_ply_header
from proxycodec.formats.scaffold_ply import ScaffoldPly, read_scaffold_ply, write_scaffold_ply
from proxycodec.formats.torchscript import read_torch_checkpoint, read_torchscript

from proxycodec.errors import ProxycodecError
from proxycodec.scaffold_gs import read_cfg_args, read_scaffold_cameras

CORPUS = Path(__file__).resolve().parent / "corpus"

# ================================================================================================= seed files


def _scaffold_seed() -> bytes:
    rng = np.random.default_rng(0)
    m, k, f = 3, 2, 4
    ply = ScaffoldPly(positions=rng.normal(size=(m, 3)), offsets=rng.normal(size=(m, k, 3)),
                      features=rng.normal(size=(m, f)), scalings=rng.normal(size=(m, 6)) - 3)
    with tempfile.TemporaryDirectory() as d:
        write_scaffold_ply(Path(d) / "s.ply", ply)
        return (Path(d) / "s.ply").read_bytes()


def _inria_seed() -> bytes:
    rng = np.random.default_rng(1)
    n = 3
    g = GaussianPly(means=rng.normal(size=(n, 3)), sh=rng.normal(size=(n, 4, 3)), opacities=rng.normal(size=n),
                    scales=rng.normal(size=(n, 3)) - 3, quats=rng.normal(size=(n, 4)))
    with tempfile.TemporaryDirectory() as d:
        write_inria_ply(Path(d) / "g.ply", g)
        return (Path(d) / "g.ply").read_bytes()


def _generic_ply_seeds() -> dict[str, bytes]:
    dt = np.dtype([("x", "<f4"), ("y", "<f8"), ("red", "u1"), ("i", "<i4"), ("s", "<u2")])
    a = np.zeros(3, dt)
    a["x"], a["y"], a["red"], a["i"], a["s"] = [1.5, -2, 0], [3, 4e10, -1e-5], [0, 128, 255], [-7, 0, 2**30], [1, 2, 3]
    le = encode_ply(a, comments=["made by test_fuzz_readers"])
    head = le[: le.index(b"end_header\n") + 11]
    body = a.astype(dt.newbyteorder(">")).tobytes()
    be = head.replace(b"binary_little_endian", b"binary_big_endian") + body
    rows = "\n".join(" ".join(str(v) for v in r) for r in a.tolist())
    asc = head.replace(b"binary_little_endian", b"ascii") + rows.encode() + b"\n"
    return {"ply_le": le, "ply_be": be, "ply_ascii": asc}


_MODEL_IDS = {name: mid for mid, (name, _) in colmap.CAMERA_MODELS.items()}


def _colmap_bin_seeds() -> dict[str, bytes]:
    cams = [(1, "PINHOLE", 16, 12, [14.0, 15.0, 8.0, 6.0]), (2, "SIMPLE_RADIAL", 16, 12, [13.0, 8.0, 6.0, 0.0])]
    b = struct.pack("<Q", len(cams))
    for cid, model, w, h, params in cams:
        b += struct.pack("<iiQQ", cid, _MODEL_IDS[model], w, h) + struct.pack(f"<{len(params)}d", *params)
    cameras = b
    b = struct.pack("<Q", 2)
    for iid, name in ((10, "a.png"), (20, "b.png")):
        b += struct.pack("<i4d3di", iid, 1.0, 0.0, 0.0, 0.0, 0.1, 0.2, 3.0, 1) + name.encode() + b"\0"
        b += struct.pack("<Q", 2) + struct.pack("<ddq", 1.0, 2.0, 100) + struct.pack("<ddq", 3.0, 4.0, -1)
    images = b
    b = struct.pack("<Q", 3)
    for pid, tl in ((100, 2), (101, 0), (102, 1)):
        b += struct.pack("<Q3d3BdQ", pid, 0.1 * pid, -0.2, 0.3, 10, 20, 30, 0.5, tl)
        b += b"".join(struct.pack("<ii", 10 + j, j) for j in range(tl))
    points = b
    return {"cameras_bin": cameras, "images_bin": images, "points3d_bin": points}


def _colmap_txt_seeds() -> dict[str, bytes]:
    cams = "# cameras\n1 PINHOLE 16 12 14.0 15.0 8.0 6.0\n2 SIMPLE_RADIAL 16 12 13.0 8.0 6.0 0.0\n"
    imgs = ("# images\n10 1.0 0.0 0.0 0.0 0.1 0.2 3.0 1 a.png\n1.0 2.0 100 3.0 4.0 -1\n"
            "20 0.9 0.1 0.0 0.0 0.0 0.0 2.0 2 b c.png\n\n")
    pts = "# points\n100 0.1 -0.2 0.3 10 20 30 0.5 10 0 20 1\n101 1 2 3 0 0 0 0.0\n"
    return {"cameras_txt": cams.encode(), "images_txt": imgs.encode(), "points3d_txt": pts.encode()}


def _blender_seed() -> bytes:
    meta = {"camera_angle_x": 0.69, "frames": [
        {"file_path": "./r_0", "rotation": 0.0,
         "transform_matrix": [[1, 0, 0, 0], [0, 0, -1, -4], [0, 1, 0, 0.5], [0, 0, 0, 1]]},
        {"file_path": "./r_0.png", "transform_matrix": [[0, 0, 1, 4], [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]]}]}
    return json.dumps(meta, indent=1).encode()


def _container_seed() -> bytes:
    arrays = {"a/f32": np.linspace(-1, 1, 24, dtype=np.float32).reshape(2, 3, 4),
              "b_u8": np.arange(40, dtype=np.uint8), "c.i64": np.array([-5, 7, 2**40], dtype=np.int64),
              "d_f16": np.array([0.5, 1.5], dtype=np.float16)}
    with tempfile.TemporaryDirectory() as d:
        container.write_container(Path(d) / "c.pxc", {"kind": "fuzz", "x": [1, 2.5, "s"]}, arrays,
                                  level=3, raw_sections=frozenset({"b_u8"}))
        return (Path(d) / "c.pxc").read_bytes()


def _torch_seeds() -> dict[str, bytes]:
    """What Scaffold-GS writes beside its PLY: a TorchScript archive (``torch.jit.trace(mlp, x).save``), a
    ``torch.save`` of state dicts, ``cfg_args`` (``str(Namespace(...))``) and 3DGS's ``cameras.json``."""
    import warnings
    from argparse import Namespace

    import torch
    from torch import nn

    with torch.random.fork_rng(), tempfile.TemporaryDirectory() as d, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.manual_seed(0)
        m = nn.Sequential(nn.Linear(5, 4), nn.ReLU(True), nn.Linear(4, 2), nn.Tanh()).eval()
        torch.jit.trace(m, (torch.rand(1, 5),)).save(str(Path(d) / "m.pt"))
        torch.save({"opacity_mlp": m.state_dict()}, Path(d) / "c.pth")
        out = {"torchscript": (Path(d) / "m.pt").read_bytes(), "torch_checkpoint": (Path(d) / "c.pth").read_bytes()}
    out["cfg_args"] = str(Namespace(sh_degree=3, feat_dim=32, n_offsets=10, voxel_size=0.001, use_feat_bank=False,
                                    source_path="/data/x", model_path="out/x", white_background=True, eval=True,
                                    appearance_dim=0, add_opacity_dist=False, ratio=1)).encode()
    out["scaffold_cameras"] = json.dumps([
        {"id": 0, "img_name": "r_0", "width": 16, "height": 12, "position": [0.0, -4.0, 0.5],
         "rotation": [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]], "fy": 14.0, "fx": 14.5},
        {"id": 1, "img_name": "r_1", "width": 16, "height": 12, "position": [4.0, 0.0, 0.0],
         "rotation": [[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]], "fy": 14.0, "fx": 14.0}]).encode()
    return out


def make_seeds() -> dict[str, bytes]:
    """Valid seed files, keyed by the name of the reader that reads them (see :data:`READERS`)."""
    s = {**_generic_ply_seeds(), "scaffold_ply": _scaffold_seed(), "inria_ply": _inria_seed(),
         **_colmap_bin_seeds(), **_colmap_txt_seeds(), "blender_json": _blender_seed(),
         "container": _container_seed(), **_torch_seeds()}
    s["container_header"] = s["container"]
    s["scene"] = (Path(__file__).resolve().parent / "golden" / "scene_v4.pxc").read_bytes()
    s["inria_convert"] = s["inria_ply"]
    s["ply_header"] = s["ply_le"]
    return s


# ================================================================================================= readers


def _blender_reader(path: Path):
    """A Blender dataset folder whose transforms_train.json is the fuzzed file (one 2x2 PNG beside it)."""
    root = path.parent / (path.name + ".d")
    root.mkdir(exist_ok=True)
    png = root / "r_0.png"
    if not png.exists():
        Image.fromarray(np.zeros((2, 2, 4), np.uint8)).save(png)
    os.replace(path, root / "transforms_train.json")
    return load_blender(root)


def _ascii_ply(p):
    return read_ply(p)


def _inria_convert(p):
    """What ``proxycodec convert`` builds from a PLY before training: Gaussians made safe, the voxel, the anchors and
    their fitted start (a few regression steps). Anything non-finite in the result is a bug."""
    from proxycodec.convert import ConvertConfig, anchors_from_gaussians, choose_voxel, fit_attributes, load_gaussians
    from proxycodec.decoder import GaussianDecoder
    from proxycodec.netconfig import DecoderConfig

    g = load_gaussians(read_inria_ply(p))
    choice = choose_voxel(g, 10, ConvertConfig(max_anchors=2000))
    scene, targets = anchors_from_gaussians(g, choice.voxel, 10, 32)
    scene = fit_attributes(scene, GaussianDecoder(DecoderConfig()), targets, g.degree, 1.0, 3)
    for name in ("positions", "features", "offsets", "scalings"):
        if not torch.isfinite(getattr(scene, name)).all():
            raise AssertionError(f"non-finite {name} from a converted PLY")
    return scene


READERS: dict[str, Callable[[Path], object]] = {
    "ply_le": read_ply, "ply_be": read_ply, "ply_ascii": _ascii_ply, "ply_header": read_ply_header,
    "scaffold_ply": read_scaffold_ply, "inria_ply": read_inria_ply, "inria_convert": _inria_convert,
    "cameras_bin": colmap.read_cameras_bin, "images_bin": lambda p: colmap.read_images_bin(p, keypoints=True),
    "points3d_bin": colmap.read_points3d_bin,
    "cameras_txt": colmap.read_cameras_txt, "images_txt": lambda p: colmap.read_images_txt(p, keypoints=True),
    "points3d_txt": colmap.read_points3d_txt,
    "blender_json": _blender_reader,
    "container": container.read_container, "container_header": container.read_header,
    "scene": lambda p: lite.decode(p),  # a scene container (format 4: the entropy-coded sections)
    "torchscript": read_torchscript, "torch_checkpoint": read_torch_checkpoint,
    "cfg_args": read_cfg_args, "scaffold_cameras": read_scaffold_cameras,
}

OK, OURS, BUG = "accepted", "our_error", "bug"


def run_reader(name: str, data: bytes, workdir: Path) -> tuple[str, BaseException | None]:
    """Write ``data`` to a fresh file in ``workdir`` and read it -> (outcome, exception)."""
    path = Path(tempfile.mkdtemp(dir=workdir)) / f"input.{name}"
    path.write_bytes(data)
    try:
        READERS[name](path)
    except ProxycodecError as e:
        msg = str(e)
        if "\n" in msg or not msg:
            return BUG, AssertionError(f"error message is not one non-empty line: {msg!r}")
        return OURS, e
    except Exception as e:  # noqa: BLE001 - anything else is a bug in the reader
        return BUG, e
    return OK, None


# ================================================================================================= mutations

#: Values that make declared counts/sizes absurd.
HUGE = (2**31 - 1, 2**31, 2**32 - 1, 2**32, 2**63 - 1, 2**63, 2**64 - 1, 10**9, 10**12, 1 << 30)


def _flip(data: bytearray, rng: random.Random) -> None:
    for _ in range(rng.randint(1, 4)):
        i = rng.randrange(len(data))
        data[i] ^= 1 << rng.randrange(8)


def _overwrite_int(data: bytearray, rng: random.Random) -> None:
    """Overwrite an aligned 4- or 8-byte slot with a huge or negative value (counts, sizes, offsets)."""
    width = rng.choice((4, 8))
    if len(data) < width:
        return
    i = rng.randrange(0, len(data) - width + 1)
    v = rng.choice(HUGE + (0, 1, 2**width * 8 - 1 if width == 4 else 2**64 - 1))
    data[i:i + width] = (v % (1 << (8 * width))).to_bytes(width, "little")


def _text_number(data: bytearray, rng: random.Random) -> bytearray:
    """Replace one decimal number in a text file by a huge/NaN/negative token."""
    text = bytes(data)
    import re

    nums = list(re.finditer(rb"-?[0-9]+(?:\.[0-9]+)?(?:e-?[0-9]+)?", text))
    if not nums:
        return data
    m = rng.choice(nums)
    tok = rng.choice([b"1000000000000", b"-1", b"nan", b"inf", b"-inf", b"1e308", b"99999999999999999999999",
                      b"0", b"1e-320", b"0x10", b"\xff\xfe"])
    return bytearray(text[:m.start()] + tok + text[m.end():])


def _nan_payload(data: bytearray, rng: random.Random) -> None:
    """Write a float32 or float64 NaN/Inf at a 4-aligned offset in the second half (where payloads live)."""
    if len(data) < 16:
        return
    kind = rng.choice(("<f", "<d"))
    w = struct.calcsize(kind)
    i = rng.randrange(len(data) // 2, len(data) - w + 1)
    data[i:i + w] = struct.pack(kind, rng.choice((float("nan"), float("inf"), -float("inf"), 1e38, -3.4e38)))


def mutate(data: bytes, rng: random.Random, seeds: list[bytes] | None = None) -> bytes:
    """One to three random structural mutations of ``data``."""
    out = bytearray(data)
    for _ in range(rng.randint(1, 3)):
        op = rng.randrange(9)
        if not out:
            out = bytearray(rng.randbytes(rng.randint(0, 64)))
            continue
        if op == 0:  # truncate
            del out[rng.randrange(len(out)):]
        elif op == 1:
            _flip(out, rng)
        elif op == 2:
            _overwrite_int(out, rng)
        elif op == 3:
            out = _text_number(out, rng)
        elif op == 4:
            _nan_payload(out, rng)
        elif op == 5:  # splice a piece of another seed (or itself)
            other = rng.choice(seeds) if seeds else bytes(out)
            i, j = rng.randrange(len(out) + 1), rng.randrange(len(other) + 1)
            out = out[:i] + other[j:j + rng.randint(1, 256)] + out[i + rng.randint(0, 64):]
        elif op == 6:  # insert random bytes
            i = rng.randrange(len(out) + 1)
            out[i:i] = rng.randbytes(rng.randint(1, 32))
        elif op == 7:  # delete a chunk
            i = rng.randrange(len(out))
            del out[i:i + rng.randint(1, 64)]
        else:  # duplicate a chunk (repeated records / lines)
            i = rng.randrange(len(out))
            chunk = out[i:i + rng.randint(1, 128)]
            out[i:i] = chunk * rng.randint(1, 4)
    return bytes(out)


# ================================================================================================= tests

SEEDS = make_seeds()


@pytest.fixture(scope="module")
def workdir():
    with tempfile.TemporaryDirectory(prefix="pxc-fuzz-") as d:
        yield Path(d)


@pytest.mark.parametrize("name", sorted(READERS))
def test_seed_files_are_accepted(name, workdir):
    outcome, exc = run_reader(name, SEEDS[name], workdir)
    assert outcome == OK, repr(exc)


def _assert_clean(name, data, workdir):
    outcome, exc = run_reader(name, data, workdir)
    if outcome == BUG:
        raise AssertionError(f"{name}: {type(exc).__name__}: {exc} on input {data[:200]!r}...") from exc


FUZZ = settings(max_examples=120, deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])


@FUZZ
@given(name=st.sampled_from(sorted(READERS)), seed=st.integers(0, 2**32 - 1))
def test_mutated_seed_files_are_refused_cleanly(name, seed, workdir):
    data = mutate(SEEDS[name], random.Random(seed), list(SEEDS.values()))
    _assert_clean(name, data, workdir)


@FUZZ
@given(name=st.sampled_from(sorted(READERS)), cut=st.floats(0, 1))
def test_truncations(name, cut, workdir):
    data = SEEDS[name]
    _assert_clean(name, data[: int(cut * len(data))], workdir)


@settings(max_examples=80, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(name=st.sampled_from(sorted(READERS)), data=st.binary(max_size=300))
def test_random_bytes(name, data, workdir):
    _assert_clean(name, data, workdir)


@settings(max_examples=100, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(name=st.sampled_from(sorted(READERS)), pos=st.floats(0, 1), value=st.sampled_from(HUGE),
       width=st.sampled_from([4, 8]))
def test_huge_values_at_every_offset(name, pos, value, width, workdir):
    data = bytearray(SEEDS[name])
    i = min(int(pos * len(data)), len(data) - width)
    data[i:i + width] = (value % (1 << (8 * width))).to_bytes(width, "little")
    _assert_clean(name, bytes(data), workdir)


# ------------------------------------------------------------------------------------------ the regression corpus


def corpus_files() -> list[Path]:
    return sorted(p for p in CORPUS.glob("*/*") if p.is_file() and p.parent.name in READERS)


@pytest.mark.parametrize("path", corpus_files(), ids=lambda p: f"{p.parent.name}/{p.name}")
def test_regression_corpus(path, workdir):
    """Every committed hostile file is refused with our error (or, where the name says ``ok_``, accepted)."""
    outcome, exc = run_reader(path.parent.name, path.read_bytes(), workdir)
    want = OK if path.name.startswith("ok_") else OURS
    assert outcome == want, f"{path.name}: {type(exc).__name__}: {exc}"


def test_corpus_is_small_and_covers_every_reader():
    files = corpus_files()
    assert sum(p.stat().st_size for p in files) < 300_000  # ~100 KB of it: hostile entropy-coded scenes
    assert {p.parent.name for p in files} >= {"ply_le", "scaffold_ply", "inria_ply", "cameras_bin", "images_bin",
                                               "points3d_bin", "cameras_txt", "images_txt", "points3d_txt",
                                               "blender_json", "container", "torchscript", "torch_checkpoint",
                                               "cfg_args", "scaffold_cameras", "scene"}


# ------------------------------------------------------------------------------ structure-aware container forging
# Random bit flips mostly stop at the CRCs. These forge headers and tables of contents with hostile fields and
# *valid* checksums, so that every check behind the CRCs is exercised.


def forge_container(entries: list[dict], payload: bytes, *, version: int = container.FORMAT_VERSION,
                    flags: int = 0, n_sections: int | None = None, magic: bytes = container.MAGIC) -> bytes:
    """Header + table of contents (fields exactly as given, CRCs made valid) + ``payload``."""
    toc = bytearray()
    for e in entries:
        nb = e["name"] if isinstance(e["name"], bytes) else e["name"].encode()
        shape = e["shape"]
        toc += struct.pack("<H", len(nb)) + nb + struct.pack("<BBBB", e["codec"], e["dtype"], len(shape), 0)
        toc += struct.pack(f"<{len(shape)}Q", *shape)
        toc += struct.pack("<QQQI", e["offset"], e["stored"], e["raw"], e["crc"])
    n = len(entries) if n_sections is None else n_sections
    head = container.HEADER.pack(magic, version, flags, n, len(toc), zlib.crc32(toc), 0)
    head = head[:-4] + struct.pack("<I", zlib.crc32(head[:-4]))
    return head + bytes(toc) + payload


def _meta_entry(meta: bytes, offset: int, codec: int = container.CODEC_RAW) -> tuple[dict, bytes]:
    stored = meta if codec == container.CODEC_RAW else __import__("zstandard").ZstdCompressor().compress(meta)
    return ({"name": "meta", "codec": codec, "dtype": 1, "shape": (len(meta),), "offset": offset,
             "stored": len(stored), "raw": len(meta), "crc": zlib.crc32(meta)}, stored)


def _toc_size(entries) -> int:
    return sum(2 + len(e["name"]) + 4 + 8 * len(e["shape"]) + 28 for e in entries)


U64 = st.one_of(st.integers(0, 64), st.sampled_from([2**63 - 1, 2**63, 2**64 - 1, 1 << 30, 1 << 40]),
                st.integers(0, 2**64 - 1))


@FUZZ
@given(codec=st.integers(0, 3), dtype=st.integers(0, 12), shape=st.lists(U64, max_size=9), offset=U64, stored=U64,
       raw=U64, crc=st.integers(0, 2**32 - 1), body=st.binary(max_size=64), version=st.sampled_from([0, 1, 1, 2, 65535]),
       extra_n=st.sampled_from([0, 0, 1, 5000]))
def test_forged_table_of_contents(codec, dtype, shape, offset, stored, raw, crc, body, version, extra_n, workdir):
    meta = b'{"kind":"x"}'
    e = {"name": "s", "codec": codec, "dtype": dtype, "shape": tuple(shape), "offset": offset, "stored": stored,
         "raw": raw, "crc": crc}
    m, m_stored = _meta_entry(meta, 0)
    m["offset"] = 32 + _toc_size([m, e])
    data = forge_container([m, e], m_stored + body, version=version, n_sections=2 + extra_n)
    _assert_clean("container", data, workdir)


@settings(max_examples=60, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(meta=st.one_of(st.binary(max_size=40),
                      st.sampled_from([b'{"a": 1' + b"0" * 5000 + b"}", b"NaN",
                                       b'{"a": NaN}', b'{"a": Infinity}', b"[]", b"null", b'"\xff"', b'{"a":1}{}',
                                       b'{"a": 1e999}', b"\xef\xbb\xbf{}"])),
       codec=st.sampled_from([container.CODEC_RAW, container.CODEC_ZSTD]))
def test_forged_metadata(meta, codec, workdir):
    m, stored = _meta_entry(meta, 0, codec)
    m["offset"] = 32 + _toc_size([m])
    _assert_clean("container", forge_container([m], stored), workdir)


def test_deeply_nested_metadata(workdir):
    meta = b"[" * 100_000 + b"]" * 100_000
    m, stored = _meta_entry(meta, 0, container.CODEC_ZSTD)
    m["offset"] = 32 + _toc_size([m])
    outcome, exc = run_reader("container", forge_container([m], stored), workdir)
    assert outcome == OURS, f"{type(exc).__name__}: {str(exc)[:100]}"


JSON = st.recursive(st.none() | st.booleans() | st.floats() | st.integers() | st.text(max_size=8),
                    lambda ch: st.lists(ch, max_size=5) | st.dictionaries(st.text(max_size=6), ch, max_size=5),
                    max_leaves=20)


@settings(max_examples=150, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(angle=JSON, frames=JSON, frame=st.dictionaries(st.sampled_from(["file_path", "transform_matrix", "x"]), JSON),
       which=st.integers(0, 3))
def test_blender_transforms_with_hostile_json_values(angle, frames, frame, which, workdir):
    meta = json.loads(SEEDS["blender_json"])
    if which == 0:
        meta["camera_angle_x"] = angle
    elif which == 1:
        meta["frames"] = frames
    elif which == 2:
        meta["frames"][0] = frame
    else:
        meta["frames"][1]["transform_matrix"] = frames
    _assert_clean("blender_json", json.dumps(meta).encode(), workdir)


@pytest.mark.parametrize("doc", [
    b"[" * 100_000 + b"]" * 100_000,  # RecursionError in json
    b'{"camera_angle_x": 1' + b"0" * 5000 + b', "frames": []}',
    (b'{"camera_angle_x": 0.5, "frames": [{"file_path": "r_0", "transform_matrix": [[1e999, 0, 0, 0], [0, 1, 0, 0], '
     b'[0, 0, 1, 0], [0, 0, 0, 1]]}]}'),
    (b'{"camera_angle_x": 0.5, "frames": [{"file_path": "r_0", "transform_matrix": [[0, 0, 0, 0], [0, 0, 0, 0], '
     b'[0, 0, 0, 0], [0, 0, 0, 0]]}]}'),
    b'{"camera_angle_x": 0.5, "frames": [{"file_path": "../../../../etc/passwd", "transform_matrix": []}]}',
    b'{"camera_angle_x": 0.5, "frames": [{"file_path": "r_0\\u0000x", "transform_matrix": []}]}',
], ids=["deep_nesting", "int_of_5000_digits", "inf_in_matrix", "zero_matrix", "path_outside_root", "nul_in_path"])
def test_blender_classic_attacks(doc, workdir):
    outcome, exc = run_reader("blender_json", doc, workdir)
    assert outcome == OURS, repr(exc)


# ------------------------------------------------------------------------------------------ bounded memory

_MEMORY_PROBE = r"""
import json, resource, struct, sys, zlib
from pathlib import Path
from proxycodec.errors import ProxycodecError
from proxycodec import lite
from proxycodec.formats import colmap, container
from proxycodec.formats.ply import read_ply
sys.path.insert(0, sys.argv[2])
from test_fuzz_readers import forge_container, _meta_entry, _toc_size
d = Path(sys.argv[1])

def rss():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # Linux: KiB

def probe(name, path, reader):
    before = rss()
    try:
        reader(path)
        out = "accepted"
    except ProxycodecError as e:
        out = "our_error"
    except BaseException as e:
        out = f"{type(e).__name__}: {e}"
    print(json.dumps({"case": name, "outcome": out, "extra_rss": rss() - before, "bytes": path.stat().st_size}))

# 1. a container whose single section declares 1 GiB (zstd) in a ~1 KB file
m, stored = _meta_entry(b'{"kind":"bomb"}', 0)
e = {"name": "big", "codec": 1, "dtype": 1, "shape": (1 << 30,), "offset": 0, "stored": 900, "raw": 1 << 30, "crc": 0}
m["offset"] = 32 + _toc_size([m, e]); e["offset"] = m["offset"] + len(stored)
frame = b"\x28\xb5\x2f\xfd" + bytes(896)
(d / "bomb.pxc").write_bytes(forge_container([m, e], stored + frame))
probe("container_1GiB_section", d / "bomb.pxc", container.read_container)
# 1b. the same as a raw section (stored == raw == 1 GiB declared, file ~1 KB)
e.update(codec=0, stored=1 << 30)
(d / "bomb_raw.pxc").write_bytes(forge_container([m, e], stored + frame))
probe("container_1GiB_raw_section", d / "bomb_raw.pxc", container.read_container)
# 2. a PLY header declaring 1e12 vertices (binary and ascii)
for fmt in ("binary_little_endian", "ascii"):
    p = d / f"huge_{fmt}.ply"
    p.write_bytes(f"ply\nformat {fmt} 1.0\nelement vertex 1000000000000\nproperty float x\nend_header\n".encode()
                  + bytes(900))
    probe(f"ply_1e12_vertices_{fmt}", p, read_ply)
# 3. COLMAP files declaring 1e9 points / images / cameras
for name, reader in (("points3D.bin", colmap.read_points3d_bin), ("images.bin", colmap.read_images_bin),
                     ("cameras.bin", colmap.read_cameras_bin)):
    p = d / name
    p.write_bytes(struct.pack("<Q", 10**9) + bytes(1000))
    probe(f"colmap_1e9_{name}", p, reader)
# 3b. one point whose track declares 1e9 observations
p = d / "track.bin"
p.write_bytes(struct.pack("<Q", 1) + struct.pack("<Q3d3BdQ", 1, 0, 0, 0, 1, 2, 3, 0.5, 10**9) + bytes(900))
probe("colmap_1e9_track", p, colmap.read_points3d_bin)
# 4. PyTorch archives whose pickle declares a 1e12-element storage, or a 1e12-element view of 4 floats
import zipfile
from conftest import forged_tensor_pickle
from proxycodec.formats.torchscript import read_torch_checkpoint, read_torchscript
for name, shape, stride, numel, reader in (
        ("torchscript_storage_1e12", (2, 2), (2, 1), 10**12, read_torchscript),
        ("torchscript_view_1e12", (10**6, 10**6), (0, 0), 4, read_torchscript),
        ("checkpoint_view_1e12", (10**6, 10**6), (0, 0), 4, read_torch_checkpoint)):
    p = d / f"{name}.pt"
    with zipfile.ZipFile(p, "w") as z:
        z.writestr("m/data.pkl", forged_tensor_pickle(shape, stride, numel))
        z.writestr("m/data/0", bytes(16))
    probe(name, p, reader)
# 5. a pickle putting one object at memo index 2^27 (CPython's unpickler would size its memo table for it: 1 GB)
p = d / "memo.pt"
with zipfile.ZipFile(p, "w") as z:
    z.writestr("m/data.pkl", b"\x80\x02Nr" + struct.pack("<I", 1 << 27) + b".")
probe("torchscript_memo_index_2pow27", p, read_torchscript)
"""


def test_declared_sizes_cannot_make_readers_allocate(tmp_path):
    """1 GiB-declared sections, 1e12-vertex PLYs, 1e9-point COLMAP files and 1e12-element tensors in PyTorch
    archives, all of ~1 KB: our error, < 100 MB RSS."""
    r = subprocess.run([sys.executable, "-c", _MEMORY_PROBE, str(tmp_path), str(Path(__file__).parent)],
                       capture_output=True, text=True, timeout=120, check=False)
    assert r.returncode == 0, r.stderr
    rows = [json.loads(line) for line in r.stdout.splitlines()]
    assert len(rows) == 12
    for row in rows:
        assert row["outcome"] == "our_error", row
        assert row["bytes"] < 2048, row
        assert row["extra_rss"] < 100 * 2**20, row


# ------------------------------------------------------------------------------------------ nothing half-written


class _FailingFile:
    """Wraps the temporary file of ``atomic_write``: the second write raises (a full disk, midway)."""

    def __init__(self, fh):
        self._fh, self._writes = fh, 0

    def write(self, b):
        self._writes += 1
        if self._writes >= 2:
            self._fh.write(bytes(memoryview(b)[: max(1, len(memoryview(b)) // 2)]))
            raise OSError(28, "No space left on device (simulated)")
        return self._fh.write(b)

    def __getattr__(self, k):
        return getattr(self._fh, k)

    def __enter__(self):
        return self

    def __exit__(self, *a):
        return self._fh.__exit__(*a)


def _writers(tmp: Path):
    rng = np.random.default_rng(3)
    sply = ScaffoldPly(positions=rng.normal(size=(4, 3)), offsets=rng.normal(size=(4, 2, 3)),
                       features=rng.normal(size=(4, 5)), scalings=rng.normal(size=(4, 6)))
    gply = GaussianPly(means=rng.normal(size=(4, 3)), sh=rng.normal(size=(4, 1, 3)), opacities=rng.normal(size=4),
                       scales=rng.normal(size=(4, 3)), quats=rng.normal(size=(4, 4)))
    from proxycodec.formats.ply import write_ply

    arr = np.zeros(5, np.dtype([("x", "<f4"), ("y", "<f4")]))
    return {
        "ply": (tmp / "a.ply", lambda p: write_ply(p, arr)),
        "scaffold": (tmp / "s.ply", lambda p: write_scaffold_ply(p, sply)),
        "inria": (tmp / "g.ply", lambda p: write_inria_ply(p, gply)),
        "container": (tmp / "c.pxc", lambda p: container.write_container(p, {"k": 1}, {"a": np.arange(9.0)})),
    }


@pytest.mark.parametrize("writer", ["ply", "scaffold", "inria", "container"])
@pytest.mark.parametrize("failure", ["write", "fsync", "interrupt"])
def test_writers_leave_nothing_on_failure(writer, failure, tmp_path, monkeypatch):
    """A failing write (full disk midway), fsync or a KeyboardInterrupt: the old file stays, no temp file."""
    from proxycodec import fileio

    path, write = _writers(tmp_path)[writer]
    path.write_bytes(b"previous content")
    real_fdopen = os.fdopen
    if failure == "write":
        monkeypatch.setattr(fileio.os, "fdopen", lambda fd, mode: _FailingFile(real_fdopen(fd, mode)))
        exc = OSError
    else:
        exc = OSError if failure == "fsync" else KeyboardInterrupt

        def boom(fd):
            raise exc("simulated") if exc is OSError else KeyboardInterrupt()

        monkeypatch.setattr(fileio.os, "fsync", boom)
    with pytest.raises(exc):
        write(path)
    monkeypatch.undo()
    assert path.read_bytes() == b"previous content"
    assert sorted(os.listdir(tmp_path)) == [path.name]
    write(path)  # and the real thing works afterwards
    assert sorted(os.listdir(tmp_path)) == [path.name] and path.stat().st_size > 16


# A child that blocks inside the writer (in fsync, after all data went to the temporary file) until SIGINT.
_SLOW_WRITER = r"""
import os, sys, time
import proxycodec.fileio as fileio
real_fsync = os.fsync
calls = {"n": 0}
AT = int(sys.argv[2])
def slow_fsync(fd):
    calls["n"] += 1
    if calls["n"] == AT:
        print("WRITING", flush=True)
        time.sleep(60)
    real_fsync(fd)
fileio.os.fsync = slow_fsync
what = sys.argv[1]
if what == "ply":
    import numpy as np
    from proxycodec.formats.ply import write_ply
    arr = np.zeros(2_000_000, np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4")]))  # 24 MB
    write_ply(sys.argv[3], arr)
else:  # the CLI
    sys.argv = ["proxycodec"] + sys.argv[3:]
    from proxycodec.cli.main import main
    main()
"""


def _interrupt(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    import signal

    # SIGINT back to its default in the child: a test run started as a background job (``cmd &`` in a script)
    # inherits SIGINT ignored, and a Python started with SIGINT ignored never raises KeyboardInterrupt.
    p = subprocess.Popen([sys.executable, "-c", _SLOW_WRITER, *args], cwd=cwd, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    out, err = signal_when_ready(p, signal.SIGINT, lambda: read_until(p.stdout, "WRITING"), timeout=60)
    return subprocess.CompletedProcess(p.args, p.returncode, out, err)


def test_sigint_during_a_large_ply_write_leaves_nothing(tmp_path):
    r = _interrupt(["ply", "1", str(tmp_path / "big.ply")], tmp_path)
    assert r.returncode != 0 and "KeyboardInterrupt" in r.stderr
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("which_fsync", [
    1, 2], ids=["during_ply", "during_weights"])
def test_sigint_during_cli_sample_leaves_no_partial_output(tmp_path, which_fsync):
    r = _interrupt(["cli", str(which_fsync), "sample", str(tmp_path / "s.ply")], tmp_path)
    assert r.returncode == 130, r.stderr
    assert "Traceback" not in r.stderr
    left = sorted(os.listdir(tmp_path))
    assert not [n for n in left if n.endswith(".tmp")], left
    # No half-written file, and never a PLY without the weights it needs.
    assert left == [], left


def test_sigint_during_cli_render_leaves_no_partial_png(tmp_path):
    from proxycodec.cli.main import cli  # noqa: F401  (import check: the CLI exists)

    ok = subprocess.run([sys.executable, "-c", "from proxycodec.cli.main import main; main()", "sample",
                         str(tmp_path / "s.ply")], capture_output=True, text=True, timeout=300, check=False)
    assert ok.returncode == 0, ok.stderr
    out = tmp_path / "r"
    # fsync 1 is the first PNG: one complete PNG would be there after it; we interrupt the second.
    r = _interrupt(["cli", "2", "render", str(tmp_path / "s.ply"), "--res", "0.05", "--view", "0", "--view", "1",
                    "--backend", "reference", "-o", str(out)], tmp_path)
    assert r.returncode == 130, r.stderr
    pngs = sorted(os.listdir(out))
    assert pngs == ["view000_res0.050.png"], pngs  # the finished one, nothing partial, no temp file
    Image.open(out / pngs[0]).verify()


# ------------------------------------------------------------------------------------------ the weights sidecar


@pytest.mark.parametrize("field,value", [("pe_pos_freqs", 2**31), ("pe_res_freqs", -1), ("scene_center", []),
                                         ("scene_center", [1, "a", 3]), ("feat_dim", 10**9), ("scene_radius", -1),
                                         ("embedding", "eval"), ("gate", [])])
def test_hostile_decoder_configuration_in_a_weights_file(field, value, tmp_path):
    """A weights sidecar whose decoder configuration would allocate without bound or crash: our error."""
    import torch

    from proxycodec.decoder import DecoderConfig, GaussianDecoder
    from proxycodec.model import SceneModel
    from proxycodec.scene import AnchorScene

    scene = AnchorScene(torch.zeros(2, 3), torch.zeros(2, 32), torch.zeros(2, 10, 3), torch.zeros(2, 6), 0.1)
    ply, w = SceneModel(scene, GaussianDecoder(DecoderConfig())).save(tmp_path / "s.ply")
    c = container.read_container(w)
    meta = json.loads(json.dumps(c.meta))
    meta["decoder"][field] = value
    container.write_container(w, meta, c.arrays)
    with pytest.raises(ProxycodecError):
        SceneModel.load(ply)
