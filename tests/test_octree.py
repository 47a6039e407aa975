"""Octree-coded grid positions (``proxycodec.octree``; ``encode --positions octree``, scene format 6)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import zstandard
from click.testing import CliRunner
from test_codec import FAST, tiny_model

from proxycodec import codec, lite, octree
from proxycodec.cli.main import cli
from proxycodec.errors import ProxycodecError
from proxycodec.formats.container import ContainerError, read_container, write_container
from proxycodec.sections import morton_order

pytestmark = pytest.mark.usefixtures("one_thread")


def _sorted(rel: np.ndarray) -> np.ndarray:
    rel = np.unique(np.asarray(rel, dtype=np.int64), axis=0)
    return rel[morton_order(rel, rel[:, 0], rel[:, 1], rel[:, 2])]


def _shell(n=4000, radius=60, seed=0) -> np.ndarray:
    """Voxelised points on a sphere: a surface, as anchors are."""
    d = np.random.default_rng(seed).normal(size=(n, 3))
    return _sorted(np.rint(radius * d / np.linalg.norm(d, axis=1, keepdims=True)) + radius)


CASES = {
    "one point": np.array([[5, 0, 9]]),
    "origin only": np.zeros((1, 3), np.int64),
    "two points far apart": np.array([[0, 0, 0], [2**21 - 1, 2**21 - 1, 2**21 - 1]]),
    "dense cube": np.stack(np.meshgrid(*[np.arange(6)] * 3, indexing="ij"), -1).reshape(-1, 3),
    "a line": np.stack([np.arange(0, 3000, 7), np.zeros(429, np.int64), np.full(429, 3)], 1),
    "random sparse": np.random.default_rng(1).integers(0, 5000, (3000, 3)),
    "sphere shell": _shell(),
}


@pytest.mark.parametrize("name", list(CASES))
def test_round_trip_gives_the_morton_order(name):
    rel = _sorted(CASES[name])
    assert octree.can_code(rel)
    secs, depth = octree.encode(rel)
    assert depth == max(1, int(rel.max()).bit_length()) and secs[octree.TABLE].shape == (depth, octree.CONTEXTS)
    back = octree.decode(secs, depth, len(rel), ProxycodecError)
    np.testing.assert_array_equal(back, rel)
    again, _ = octree.encode(rel)  # same input, same words
    assert all(np.array_equal(secs[k], again[k]) for k in secs)


def test_what_it_cannot_code():
    assert not octree.can_code(np.zeros((0, 3), np.int64))
    assert not octree.can_code(np.array([[1, 2, 3], [1, 2, 3]]))  # duplicates: the tree has one leaf for both
    assert not octree.can_code(np.array([[0, 0, 0], [2**21, 0, 0]]))  # beyond 21 bits per axis
    assert octree.can_code(np.array([[0, 0, 0], [2**21 - 1, 0, 0]]))


def test_a_surface_costs_fewer_bytes_than_zstd_deltas():
    rel = _shell(20000, 120)
    secs, _ = octree.encode(rel)
    z = zstandard.ZstdCompressor(level=19)
    deltas = np.diff(rel, axis=0, prepend=np.zeros((1, 3), np.int64)).T.astype(np.int16)
    coded = secs[octree.STREAM].nbytes + len(z.compress(secs[octree.TABLE].tobytes()))
    assert coded < 0.75 * len(z.compress(deltas.tobytes())), coded


def test_corrupt_streams_are_refused_and_bounded():
    rel = _shell(3000, 40)
    secs, depth = octree.encode(rel)
    s, t = secs[octree.STREAM], secs[octree.TABLE]
    bad = {
        "truncated stream": ({octree.STREAM: s[: len(s) // 2], octree.TABLE: t}, depth, len(rel)),
        "a word more": ({octree.STREAM: np.append(s, np.uint32(12345)), octree.TABLE: t}, depth, len(rel)),
        "fewer anchors declared": (secs, depth, len(rel) - 1),
        "more anchors declared": (secs, depth, len(rel) + 1),
        "deeper tree declared": (secs, depth + 1, len(rel)),
        "depth beyond 21": (secs, 22, len(rel)),
        "probabilities lost": ({octree.STREAM: s, octree.TABLE: np.zeros_like(t)}, depth, len(rel)),
        "table of the wrong shape": ({octree.STREAM: s, octree.TABLE: t[:-1]}, depth, len(rel)),
        "stream of the wrong type": ({octree.STREAM: s.astype(np.int64), octree.TABLE: t}, depth, len(rel)),
        "no stream": ({octree.TABLE: t}, depth, len(rel)),
        "garbage, and a count that allows a blow-up": (
            {octree.STREAM: np.random.default_rng(0).integers(0, 2**32, 4000, dtype=np.uint32),
             octree.TABLE: np.full((21, octree.CONTEXTS), 250, np.uint8)}, 21, 50),
    }
    for name, (sections, d, count) in bad.items():
        try:
            octree.decode(sections, d, count, ProxycodecError)
        except ProxycodecError as e:
            assert "octree" in str(e), (name, str(e))
        else:
            pytest.fail(f"{name}: decoded without an error")


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    d = tmp_path_factory.mktemp("octree")
    m = tiny_model(300)
    codec.encode(m, d / "delta.pxc", **FAST, positions="delta")
    codec.encode(m, d / "octree.pxc", **FAST)  # the default
    return m, d / "delta.pxc", d / "octree.pxc"


def test_an_octree_container_decodes_to_the_delta_containers_scene(pair):
    _, delta, oct_ = pair
    a, b = codec.decode(delta), codec.decode(oct_)
    for k in ("positions", "features", "offsets", "scalings"):
        assert torch.equal(getattr(a.scene, k), getattr(b.scene, k)), k
    ca, cb = read_container(delta), read_container(oct_)
    assert ca.meta["scene_format"] == 2 and cb.meta["scene_format"] == 6
    assert cb.meta["positions"]["coding"] == "octree" and "anchors/grid" not in cb.arrays
    assert cb.meta["features"] == ["octree"] and "features" not in ca.meta
    assert {octree.STREAM, octree.TABLE} <= set(cb.arrays)
    L = lite.decode(oct_)  # the torch-free reader shares the format code: the same arrays
    np.testing.assert_array_equal(L.positions, b.scene.positions.numpy())
    from test_decode_lite import assert_renders_agree  # float32 paths: decisions may flip on another CPU

    assert_renders_agree(b, L, b.cameras[0], 0.5)


def test_same_scene_same_bytes(pair, tmp_path):
    m, _, oct_ = pair
    codec.encode(m, tmp_path / "again.pxc", **FAST)
    assert (tmp_path / "again.pxc").read_bytes() == oct_.read_bytes()


def test_format_and_coding_must_agree(pair, tmp_path):
    _, delta, oct_ = pair
    cd, co = read_container(delta), read_container(oct_)
    cases = {
        "octree positions claimed as format 5": ({**co.meta, "scene_format": 5}, co.arrays),
        "octree positions claimed as format 2": ({**co.meta, "scene_format": 2}, co.arrays),
        "format 6 without its features": ({**cd.meta, "scene_format": 6}, cd.arrays),
        "a feature from the future": ({**co.meta, "features": ["octree", "splines"]}, co.arrays),
        "features of the wrong type": ({**co.meta, "features": "octree"}, co.arrays),
        "octree left out of the features": ({**co.meta, "features": []}, co.arrays),
        "a feature the file does not use": ({**co.meta, "features": ["levels", "octree"]}, co.arrays),
        "octree depth missing": ({**co.meta, "positions": {k: v for k, v in co.meta["positions"].items()
                                                             if k != "depth"}}, co.arrays),
        "octree stream missing": (co.meta, {k: v for k, v in co.arrays.items() if k != octree.STREAM}),
        "a coding from the future": ({**cd.meta, "positions": {**cd.meta["positions"], "coding": "kd"}}, cd.arrays),
    }
    for name, (meta, arrays) in cases.items():
        p = tmp_path / "bad.pxc"
        write_container(p, meta, arrays, level=1)
        with pytest.raises(ContainerError) as e:
            codec.decode(p)
        with pytest.raises(ContainerError):
            lite.decode(p)
        if name == "a feature from the future":
            assert "'splines'" in str(e.value) and "upgrade proxycodec" in str(e.value)
        if name == "a coding from the future":
            assert "unknown position coding 'kd'" in str(e.value)
    # a format-6 file without octree positions, its features saying so, reads (features, not numbers, say what it is)
    p = tmp_path / "delta6.pxc"
    write_container(p, {**cd.meta, "scene_format": 6, "features": []}, cd.arrays, level=1)
    assert torch.equal(codec.decode(p).scene.positions, codec.decode(delta).scene.positions)


def test_bad_coding_name_and_cli(tmp_path):
    m = tiny_model(80)
    with pytest.raises(ProxycodecError, match="position coding"):
        codec.encode(m, tmp_path / "x.pxc", positions="kd")
    assert not (tmp_path / "x.pxc").exists()
    ply, _ = m.save(tmp_path / "s.ply")
    r = CliRunner().invoke(cli, ["encode", str(ply), "-o", str(tmp_path / "s.pxc"), "--predictor-iters", "10"])
    assert r.exit_code == 0, r.output
    assert read_container(tmp_path / "s.pxc").meta["scene_format"] == 6  # octree positions: the default
    r = CliRunner().invoke(cli, ["encode", str(ply), "-o", str(tmp_path / "d.pxc"), "--positions", "delta",
                                 "--predictor-iters", "10"])
    assert r.exit_code == 0, r.output
    assert read_container(tmp_path / "d.pxc").meta["scene_format"] == 2  # deltas: the formats older readers read
    r = CliRunner().invoke(cli, ["stats", str(tmp_path / "s.pxc")])
    assert r.exit_code == 0 and "anchors/octree" in r.output and "positions grid octree" in r.output, r.output
    assert "(scene format 6: octree)" in r.output


def test_flipped_bytes_fail_alike_in_both_decoders(pair, tmp_path):
    """Every byte flip of an octree container is refused (our error), or decodes, the same way in both readers."""
    from test_decode_lite import assert_flips_agree

    assert_flips_agree(pair[2], tmp_path, 60)


def test_positions_the_octree_cannot_hold_fall_back_to_deltas():
    from proxycodec.sections import encode_positions

    voxel = 0.05
    pos = (np.array([[0, 0, 0], [3, 1, 2], [3, 1, 2], [7, 0, 1]]) * voxel).astype(np.float32)  # a duplicate
    pc = encode_positions(pos, voxel, "octree")
    assert pc.info["coding"] == "delta" and octree.STREAM not in pc.sections
    pc = encode_positions(np.unique(pos, axis=0), voxel, "octree")
    assert pc.info["coding"] == "octree" and pc.info["depth"] == 3
    off = pos + np.float32(0.013)  # on no grid: float32 positions whatever the coding
    assert encode_positions(off, voxel, "octree").info["mode"] == "float32"
    with pytest.raises(ProxycodecError, match="position coding"):
        encode_positions(pos, voxel, "kd")
