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


def _shifted(m, shift):
    """``m`` with its anchors moved onto the grid through ``shift`` (as a conversion writes its scene)."""
    from dataclasses import replace

    from proxycodec.sections import grid_positions, grid_to_xyz

    ii, _ = grid_positions(m.scene.positions.numpy(), m.scene.voxel_size)
    pos = torch.from_numpy(grid_to_xyz(ii, m.scene.voxel_size, "f64", shift))
    return replace(m, scene=replace(m.scene, positions=pos, metadata={**m.scene.metadata, "grid_shift": shift}))


SHIFT = [0.012345678901234, -0.0071, 0.0033]  # a sub-voxel move: on no grid through the origin


def test_a_grid_through_the_scene_s_shift_is_stored_as_an_octree(tmp_path):
    """A scene on the grid through its ``grid_shift`` (``convert``'s canonical frame) keeps octree positions (format 6,
    feature "shift"), decoded bit for bit by both readers; without the shift, or as deltas (formats older readers
    read, which predate it), it is on no grid and stores float32 positions."""
    m = _shifted(tiny_model(300), SHIFT)
    codec.encode(m, tmp_path / "s.pxc", **FAST)
    c = read_container(tmp_path / "s.pxc")
    assert c.meta["scene_format"] == 6 and c.meta["features"] == ["octree", "shift"]
    assert c.meta["positions"]["shift"] == SHIFT and c.meta["positions"]["coding"] == "octree"
    out = codec.decode(tmp_path / "s.pxc").scene.positions
    assert torch.equal(torch.sort(out, 0).values, torch.sort(m.scene.positions, 0).values)
    np.testing.assert_array_equal(lite.decode(tmp_path / "s.pxc").positions, out.numpy())
    from dataclasses import replace

    plain = replace(m, scene=replace(m.scene, metadata={"name": "tiny"}))
    codec.encode(plain, tmp_path / "p.pxc", **FAST)
    codec.encode(m, tmp_path / "d.pxc", **FAST, positions="delta")
    for name in ("p.pxc", "d.pxc"):
        meta = read_container(tmp_path / name).meta
        assert meta["positions"]["mode"] == "float32" and "shift" not in meta["positions"], name
        assert torch.equal(codec.decode(tmp_path / name).scene.positions.sort(0).values, out.sort(0).values)
    sizes = {n: sum(x.stored_size for x in read_container(tmp_path / n).sections
                    if x.name.startswith("anchors/") and x.name != "anchors/proxy_mask") for n in ("s.pxc", "p.pxc")}
    assert sizes["s.pxc"] < sizes["p.pxc"], sizes  # an octree of the cells against their float32 xyz (zstd)
    # a shift the positions do not sit on is not used
    other = replace(m, scene=replace(m.scene, metadata={**m.scene.metadata, "grid_shift": [0.0, 0.0, 0.001]}))
    codec.encode(other, tmp_path / "w.pxc", **FAST)
    assert read_container(tmp_path / "w.pxc").meta["positions"]["mode"] == "float32"
    from proxycodec.sections import grid_positions

    pos = m.scene.positions.numpy()
    assert grid_positions(pos, m.scene.voxel_size, SHIFT)[1]["shift"] == SHIFT
    for bad in ("abc", SHIFT[:2], ["x", 0, 0], [float("nan")] * 3, {"a": 1}):  # a sidecar's junk: no shift
        assert grid_positions(pos, m.scene.voxel_size, bad) is None, bad
    from proxycodec.sections import encode_positions

    twice = np.concatenate([pos, pos[:1]])  # a duplicate: no octree, and deltas cannot say the shift
    assert encode_positions(twice, m.scene.voxel_size, "octree", SHIFT).info["mode"] == "float32"


def test_a_shifted_grid_must_say_so(tmp_path):
    m = _shifted(tiny_model(200), SHIFT)
    codec.encode(m, tmp_path / "s.pxc", **FAST)
    c = read_container(tmp_path / "s.pxc")
    pos = c.meta["positions"]
    cases = {
        "shift left out of the features": {**c.meta, "features": ["octree"]},
        "a shift a format-6 reader without it would ignore": {**c.meta, "positions": {**pos, "shift": None}},
        "a shift of two numbers": {**c.meta, "positions": {**pos, "shift": SHIFT[:2]}},
        "a shift that is not a number": {**c.meta, "positions": {**pos, "shift": ["0", 0.0, 0.0]}},
        "a shift beyond float32": {**c.meta, "positions": {**pos, "shift": [1e300, 0.0, 0.0]}},
        "a shift under the f32 rule": {**c.meta, "positions": {**pos, "rule": "f32"}},
    }
    for name, meta in cases.items():
        p = tmp_path / "bad.pxc"
        write_container(p, meta, c.arrays, level=1)
        with pytest.raises(ContainerError):
            codec.decode(p)
        with pytest.raises(ContainerError):
            lite.decode(p)
