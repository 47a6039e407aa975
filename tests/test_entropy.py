"""The conditional entropy model (scene format 4): exact integer nets, fixed tables, lossless round trips through
both decoders, golden files of formats 1, 2, 4, 5 and 6, hostile entropy sections, and the rate term of training."""

from __future__ import annotations

import hashlib
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from proxycodec import codec, entropy, lite
from proxycodec.entropy_fit import RateModel, fit_nets, laplace_bits
from proxycodec.errors import ProxycodecError
from proxycodec.formats.container import ContainerError, write_container
from proxycodec.sections import read_scene_container, stored_anchors

pytestmark = pytest.mark.usefixtures("one_thread")

GOLDEN = Path(__file__).resolve().parent / "golden"
GOLDEN_KNOBS = dict(distill=False, predictor_iters=15, predictor_hidden=16, predictor_blocks=1, zstd_level=19,
                    entropy_iters=200, entropy_hidden=8, max_cameras=2, positions="delta")  # formats 2, 4, 5


def golden_scene():
    from test_codec import tiny_model

    return tiny_model(n=96, seed=3)


def golden_steps() -> dict:
    """Fixed learned grids with per-cell levels for the golden scene's format-5 file (every level in the table, so
    every multiplier is exercised)."""
    F, K = 32, 10
    lv = [((7 * i) % 17) - 8 for i in range(2 * 8)]  # G = 2: 2 x 8 cells
    return {"features": {"step": [0.02] * F, "origin": [0.01] * F, "levels": {"cells": 2, "table": lv}},
            "scalings": {"step": [0.01] * 6, "origin": [-2.0] * 6, "levels": {"cells": 2, "table": lv[::-1]}},
            "offsets": {"step": [0.01] * (3 * K), "origin": [0.0] * (3 * K),
                        "levels": {"cells": 2, "table": [v // 2 for v in lv]}}}


def golden_scene_levels():
    m = golden_scene()
    m.scene = replace(m.scene, metadata={**m.scene.metadata, "quant_steps": golden_steps()})
    return m


def stored_digest(path) -> str:
    """SHA-256 of what a scene container stores, dequantised (positions, proxy features, offsets, scalings, split):
    integer and IEEE basic arithmetic only, hence the same on every machine."""
    c = read_scene_container(path)

    def err(m):
        return ContainerError(m, path)

    a = stored_anchors(c.meta, dict(c.arrays), err)
    h = hashlib.sha256()
    for v in (a.positions, a.features, a.offsets, a.scalings, a.proxy_mask.astype(np.uint8)):
        h.update(np.ascontiguousarray(v).tobytes())
    return h.hexdigest()


def _err(m):
    return ProxycodecError(m)


# ------------------------------------------------------------------------------------------------ tables, nets
def test_tables_are_integer_laplace_rows_with_a_committed_hash():
    t = entropy.scale_tables()
    assert t.shape == (entropy.SCALE_LEVELS, entropy.ALPHABET)
    assert np.all(t == np.floor(t)) and np.all(t >= 1) and t.max() <= 2.0**32
    assert np.all(np.abs(t.sum(1) / 2.0**32 - 1) < 1e-6)  # bin masses of one distribution
    c = entropy.RESID
    assert np.array_equal(t[:, c - 1::-1][:, :-1], t[:, c + 1:-1])  # symmetric about residual 0
    assert np.all(np.diff(t[:, c:-1], axis=1) <= 0)  # non-increasing away from it
    wider = t[:, c + 1] / t[:, c]
    assert np.all(np.diff(wider) > 0)  # each level flatter than the last
    digest = hashlib.sha256(t.tobytes()).hexdigest()
    assert digest == json.loads((GOLDEN / "hashes.json").read_text())["tables"]


def test_level_multipliers_are_float32_powers_of_two_with_a_committed_hash():
    from proxycodec.sections import LEVEL_MAX, level_multipliers

    m = level_multipliers()
    assert m.shape == (2 * LEVEL_MAX + 1,) and m[LEVEL_MAX] == 1.0
    assert np.array_equal(m, m.astype(np.float32).astype(np.float64))  # float32 values
    want = 2.0 ** (np.arange(-LEVEL_MAX, LEVEL_MAX + 1) / 4)
    assert np.all(np.abs(m - want) <= np.spacing(want.astype(np.float32)))  # the nearest float32, within an ulp
    assert np.all(m[4::4] == 2.0 ** np.arange(-1, 3))  # whole octaves exact
    digest = hashlib.sha256(m.tobytes()).hexdigest()
    assert digest == json.loads((GOLDEN / "hashes.json").read_text())["level_multipliers"]


@pytest.mark.parametrize("G", [1, 3, 7])
def test_level_entries_hold_one_level_per_occupied_cell_and_kind_and_round_trip(G):
    from proxycodec.sections import anchor_levels, level_entries, levels_from_entries, position_cells

    rng = np.random.default_rng(G)
    pos = (rng.integers(-40, 40, (300, 3)) * 0.05).astype(np.float32)
    mask = rng.random(300) < 0.3
    table = rng.integers(-8, 9, 2 * G ** 3).tolist()
    info = {"cells": G, "table": table}
    cells = position_cells(pos, 0.05, G)
    assert cells.min() >= 0 and cells.max() < G ** 3
    for rows in (np.ones(300, bool), mask):  # every anchor's rows (scalings, offsets); the proxies' (features)
        lv = anchor_levels(info, pos, 0.05, ~mask, _err)[rows]
        e = level_entries(lv, cells, ~mask, rows)
        n_occupied = len(np.unique(cells[rows & mask])) + len(np.unique(cells[rows & ~mask]))
        assert e.dtype == np.int8 and e.size == n_occupied
        assert np.array_equal(levels_from_entries(e.astype(np.int64), cells, ~mask, rows, _err), lv)
        with pytest.raises(ProxycodecError):
            levels_from_entries(e[:-1].astype(np.int64), cells, ~mask, rows, _err)


def _random_net(rng, n_in, hidden, n_out, big=False) -> entropy.IntNet:
    sizes = [n_in, hidden, hidden, 2 * n_out]
    Ws = tuple((np.full((o, i), 127, np.int8) * rng.choice([-1, 1], (o, i)).astype(np.int8)) if big
               else rng.integers(-127, 128, (o, i)).astype(np.int8) for i, o in zip(sizes[:-1], sizes[1:]))
    bs = tuple(rng.integers(-5000, 5000, o).astype(np.int64) for o in sizes[1:])
    return entropy.IntNet(Ws, bs, (9, 10), 12, rng.integers(-4000, 4000, n_out).astype(np.int64))


def _reference(net: entropy.IntNet, x: np.ndarray, base: np.ndarray):
    """The integer MLP in int64 arithmetic only (numpy's integer matmul: no BLAS, no floats)."""
    h = x.astype(np.int64)
    for i, (W, b) in enumerate(zip(net.weights, net.biases)):
        acc = h @ W.astype(np.int64).T + b
        if i < len(net.shifts):
            h = np.clip(acc >> net.shifts[i], 0, 127)
    n = net.n_out
    m = (acc[:, :n] + net.gain * base + (1 << (net.out_exp - 1))) >> net.out_exp
    s = np.clip((acc[:, n:] + (1 << (net.out_exp - 1))) >> net.out_exp, 0, entropy.SCALE_LEVELS - 1)
    return m, s


@pytest.mark.parametrize("big", [False, True])
def test_integer_net_equals_the_int64_reference(big):
    """The float32 (BLAS) evaluation is exact: every partial sum is an integer below 2^24, whatever the order or
    FMA. ``big``: weights all +-127 and inputs all +-127 at the widest layer ``check`` allows."""
    rng = np.random.default_rng(1)
    n_in = 1000 if big else 75
    net = _random_net(rng, n_in, 16, 30, big=big)
    if big:
        net = replace(net, biases=tuple(np.zeros_like(b) for b in net.biases))
        net.check(_err)
        x = rng.choice([-127, 127], (257, n_in))
    else:
        net.check(_err)
        x = rng.integers(-127, 128, (257, n_in))
    base = rng.integers(-300, 300, (257, 30))
    m, s = net(x, base)
    rm, rs = _reference(net, x, base)
    assert np.array_equal(m, rm) and np.array_equal(s, rs)


def test_check_refuses_layers_that_could_leave_exact_float32():
    rng = np.random.default_rng(2)
    net = _random_net(rng, 1100, 8, 4, big=True)  # 1100 * 127 * 127 > 2^24
    with pytest.raises(ProxycodecError, match="overflow"):
        net.check(_err)
    with pytest.raises(ProxycodecError, match="shifts"):
        replace(_random_net(rng, 10, 8, 4), out_exp=0).check(_err)


# ------------------------------------------------------------------------------------------------ round trips
def _attributes(rng, M, F, K, spread, bits):
    half = 1 << (bits - 1)

    def draw(shape):
        return np.clip(np.rint(rng.laplace(0, spread, shape)), -half, half - 1).astype(np.int64)

    return entropy.Attributes(draw((M, F)), draw((M, 6)), draw((M, 3 * K)))


def test_direct_round_trip_with_escapes_and_wide_symbols():
    """12-bit symbols far from any centre the nets predict: escapes are used and everything comes back."""
    rng = np.random.default_rng(4)
    M, F, K = 150, 12, 3
    pos = rng.integers(-20, 20, (M, 3)).astype(np.float32) * np.float32(0.1)
    pos = np.unique(pos, axis=0)
    M = len(pos)
    mask = np.zeros(M, bool)
    mask[rng.choice(M, M // 3, replace=False)] = True
    ctx = entropy.Context.of(pos, 0.1, mask)
    a = _attributes(rng, M, F, K, 400.0, 12)
    a.features[~mask] = 0
    nets, est = fit_nets(ctx, a, hidden=8, iters=30)
    bits = {"features": 12, "scalings": 12, "offsets": 12}
    sections, meta, sizes = entropy.encode(ctx, nets, a, bits)
    assert meta["escapes"] > 0 and sections[entropy.ESCAPES].size == meta["escapes"]
    b = entropy.decode(meta, sections, entropy.Context.of(pos, 0.1, mask), F, K, bits, _err)
    for k in ("scalings", "offsets"):
        assert np.array_equal(getattr(a, k), getattr(b, k)), k
    assert np.array_equal(a.features[mask], b.features[mask])
    assert abs(sum(sizes.values()) - sections[entropy.STREAM].nbytes) <= 8
    # per-symbol code lengths add up to the stream (escapes: 32 bits each, stored beside it)
    lengths = entropy.code_lengths(ctx, nets, a)
    total = (lengths.features[mask].sum() + lengths.scalings.sum() + lengths.offsets.sum()) / 8
    assert total - 4 * meta["escapes"] == pytest.approx(sections[entropy.STREAM].nbytes, abs=16)


@pytest.fixture(scope="module")
def both(tmp_path_factory):
    from test_codec import FAST, tiny_model

    model = tiny_model()
    d = tmp_path_factory.mktemp("entropy")
    r4 = codec.encode(model, d / "m.pxc", **FAST, entropy_iters=300, entropy="model", positions="delta")
    r2 = codec.encode(model, d / "z.pxc", **FAST, entropy="zstd", positions="delta")
    return r4, r2


def test_format_4_decodes_to_exactly_the_zstd_containers_scene(both):
    r4, r2 = both
    assert r4.meta["scene_format"] == 4 and r2.meta["scene_format"] == 2
    names = {s["name"] for s in r4.sections}
    assert {entropy.STREAM, entropy.ESCAPES, entropy.NET_WEIGHTS, entropy.NET_INTS} <= names
    assert not names & {"anchors/offsets", "anchors/scalings", "proxy/features"}
    a, b = codec.decode(r4.path), codec.decode(r2.path)
    for k in ("positions", "features", "offsets", "scalings"):
        assert torch.equal(getattr(a.scene, k), getattr(b.scene, k)), k
    la, lb = lite.decode(r4.path), lite.decode(r2.path)
    assert np.array_equal(la.features, lb.features) and np.array_equal(la.offsets, lb.offsets)
    assert stored_digest(r4.path) == stored_digest(r2.path)
    st = codec.stats(r4.path)
    assert st["scene_format"] == 4


def test_the_float_rate_estimate_is_the_coded_size():
    """What the float model estimates while it fits (``fit_nets``' bytes per net) is what the integer nets' ANS
    stream takes: quantising the nets to integers loses almost nothing."""
    rng = np.random.default_rng(7)
    M, F, K = 600, 8, 2
    pos = np.unique(rng.integers(-12, 12, (M, 3)), axis=0).astype(np.float32) * np.float32(0.1)
    M = len(pos)
    mask = np.zeros(M, bool)
    mask[rng.choice(M, M // 3, replace=False)] = True
    ctx = entropy.Context.of(pos, 0.1, mask)
    a = _attributes(rng, M, F, K, 6.0, 8)  # narrow symbols: no escapes, every symbol under the tables
    a.features[~mask] = 0
    nets, est = fit_nets(ctx, a, hidden=8, iters=200)
    sections, meta, sizes = entropy.encode(ctx, nets, a, {"features": 8, "scalings": 8, "offsets": 8})
    assert meta["escapes"] == 0
    coded = sections[entropy.STREAM].nbytes
    print("estimate", {k: round(v) for k, v in est.items()}, "coded", sizes, coded)
    assert sum(est.values()) == pytest.approx(coded, rel=0.03)
    for k in est:  # and per net
        assert est[k] == pytest.approx(sizes[k], rel=0.05, abs=16), k


def test_laplace_bits_match_the_integer_tables():
    """The training rate (continuous Laplace) and the coder's tables give the same code length at integer
    centres and levels, to within the tables' floor rounding."""
    t = entropy.scale_tables()
    for s in (3, 10, 20, 30):
        p = t[s] / t[s].sum()
        r = np.arange(-20, 21)
        table_bits = -np.log2(p[r + entropy.RESID])
        got = laplace_bits(torch.tensor(r, dtype=torch.float64), torch.zeros(()), torch.tensor(float(s))).numpy()
        live = table_bits < 20  # well above the integer floor
        assert live.sum() >= 7
        assert np.allclose(got[live], table_bits[live], atol=1e-3), s


# ------------------------------------------------------------------------------------------------ golden files
@pytest.mark.parametrize("name", ["scene_v1.pxc", "scene_v2.pxc", "scene_v4.pxc", "scene_v5.pxc", "scene_v6.pxc"])
def test_golden_containers_decode_to_their_committed_hashes(name):
    """The cross-machine check: committed containers of scene formats 1, 2, 4, 5 and 6 decode to committed hashes of
    their stored arrays (formats 4 to 6 through the entropy model and the ANS coder; 5 with per-cell levels; 6 with
    octree-coded positions), in both decoders."""
    want = json.loads((GOLDEN / "hashes.json").read_text())
    path = GOLDEN / name
    assert stored_digest(path) == want[name]
    if name != "scene_v5.pxc":
        assert want[name] == want["scene_v2.pxc"]  # the same scene and symbols in every format
    else:
        c = read_scene_container(path)
        assert c.meta["scene_format"] == 5 and "entropy" in c.meta
        assert {k: q["levels"]["cells"] for k, q in c.meta["quant"].items()} == {k: 2 for k in golden_steps()}
        # the stored levels are the golden table's at the occupied cells
        from proxycodec.sections import LEVELS, anchor_levels, read_levels

        a = stored_anchors(c.meta, dict(c.arrays), _err)
        got = read_levels(c.meta["quant"], c.arrays, a.positions, a.voxel_size, a.proxy_mask, False, _err)
        for k, g in golden_steps().items():
            want = anchor_levels(g["levels"], a.positions, a.voxel_size, ~a.proxy_mask, _err)
            assert np.array_equal(got[k], want[a.proxy_mask] if k == "features" else want), k
        assert c.arrays[LEVELS].size == sum(q["levels"]["entries"] for q in c.meta["quant"].values())
    m, lt = codec.decode(path), lite.decode(path)
    assert torch.isfinite(m.scene.features).all()
    np.testing.assert_allclose(lt.features, m.scene.features.numpy(), atol=1e-5)


# ------------------------------------------------------------------------------------------------ hostile input
def _rewrite(src: Path, dst: Path, meta_fn=None, arrays_fn=None) -> Path:
    c = read_scene_container(src)
    meta, arrays = dict(c.meta), dict(c.arrays)
    if meta_fn:
        meta = meta_fn(meta)
    if arrays_fn:
        arrays = arrays_fn(arrays)
    from proxycodec.sections import pack_weights

    packed, meta["weights_layout"] = pack_weights(arrays)
    write_container(dst, meta, packed, level=3, raw_sections=frozenset({entropy.STREAM}))
    return dst


def _set(arrays, name, value):
    return {**arrays, name: value}


HOSTILE = {
    "stream_word_flipped": (None, lambda a: _set(a, entropy.STREAM, a[entropy.STREAM] ^ np.uint32(1 << 7))),
    "stream_truncated": (None, lambda a: _set(a, entropy.STREAM, a[entropy.STREAM][:-3])),
    "stream_empty": (None, lambda a: _set(a, entropy.STREAM, a[entropy.STREAM][:0])),
    "stream_garbage": (None, lambda a: _set(a, entropy.STREAM, np.random.default_rng(0).integers(
        1, 2**32, a[entropy.STREAM].size, dtype=np.uint64).astype(np.uint32))),
    "escapes_extra": (None, lambda a: _set(a, entropy.ESCAPES, np.array([5, 6], np.int32))),
    "escapes_negative": (None, lambda a: _set(a, entropy.ESCAPES, np.array([-1], np.int32))),
    "nets_short": (None, lambda a: _set(a, entropy.NET_WEIGHTS, a[entropy.NET_WEIGHTS][:-1])),
    "nets_long": (None, lambda a: _set(a, entropy.NET_INTS, np.concatenate([a[entropy.NET_INTS], [1]]).astype(
        np.int32))),
    "nets_overflow": (None, lambda a: _set(a, entropy.NET_INTS, np.full_like(a[entropy.NET_INTS], 1 << 30))),
    "layout_huge": (lambda m: {**m, "entropy": {**m["entropy"], "nets": {**m["entropy"]["nets"], "features": {
        **m["entropy"]["nets"]["features"], "layers": [[4096, 4096]] * 4}}}}, None),
    "tables_other": (lambda m: {**m, "entropy": {**m["entropy"], "tables": {**m["entropy"]["tables"],
                                                                           "levels": 64}}}, None),
    "shift_bad": (lambda m: {**m, "entropy": {**m["entropy"], "input_shift": {
        **m["entropy"]["input_shift"], "offsets": 99}}}, None),
    "no_entropy_meta": (lambda m: {k: v for k, v in m.items() if k != "entropy"}, None),
    "format_2_claimed": (lambda m: {**m, "scene_format": 2}, None),
    "bits_float": (lambda m: {**m, "quant": {**m["quant"], "offsets": {"bits": 32}}}, None),
    "entropy_bits_other": (lambda m: {**m, "entropy": {**m["entropy"], "bits": {
        **m["entropy"]["bits"], "offsets": m["entropy"]["bits"]["offsets"] - 2}}}, None),
    "entropy_bits_not_a_dict": (lambda m: {**m, "entropy": {**m["entropy"], "bits": [8, 8, 8]}}, None),
}


def _quant(m, attr, **kw):
    return {**m, "quant": {**m["quant"], attr: {**m["quant"][attr], **kw}}}


def _levels(m, attr, **kw):
    return _quant(m, attr, levels={**m["quant"][attr]["levels"], **kw})


def _level_section(fn):
    from proxycodec.sections import LEVELS

    return lambda a: _set(a, LEVELS, fn(a[LEVELS]))


HOSTILE_LEVELS = {
    "levels_format_4_claimed": (lambda m: {**m, "scene_format": 4}, None),
    "levels_dropped": (lambda m: {**m, "quant": {k: {f: v for f, v in q.items() if f != "levels"}
                                                 for k, q in m["quant"].items()}}, None),
    "levels_out_of_range": (None, _level_section(lambda x: np.full_like(x, 9))),
    "levels_min_int8": (None, _level_section(lambda x: np.full_like(x, -128))),
    "levels_section_short": (None, _level_section(lambda x: x[:-1])),
    "levels_section_long": (None, _level_section(lambda x: np.concatenate([x, x[:1]]))),
    "levels_section_int16": (None, _level_section(lambda x: x.astype(np.int16))),
    "levels_section_missing": (None, lambda a: {k: v for k, v in a.items() if k != "quant/levels"}),
    "levels_entries_wrong": (lambda m: _levels(m, "scalings", entries=m["quant"]["scalings"]["levels"]["entries"] + 1),
                             None),
    "levels_entries_huge": (lambda m: _levels(m, "scalings", entries=1 << 40), None),
    "levels_cells_zero": (lambda m: _levels(m, "features", cells=0), None),
    "levels_cells_huge": (lambda m: _levels(m, "features", cells=1 << 20), None),
    "levels_cells_other": (lambda m: _levels(m, "offsets", cells=3), None),
    "levels_not_a_dict": (lambda m: _quant(m, "offsets", levels=[1, 2]), None),
    "levels_zero_missing": (lambda m: {**m, "quant": {**m["quant"], "offsets": {
        f: v for f, v in m["quant"]["offsets"].items() if f != "zero"}}}, None),
    "levels_zero_wrong_length": (lambda m: _quant(m, "offsets", zero=[0]), None),
}


@pytest.mark.parametrize("case", sorted(HOSTILE) + sorted(HOSTILE_LEVELS))
def test_hostile_entropy_sections_give_one_line_errors(case, tmp_path):
    meta_fn, arrays_fn = HOSTILE.get(case) or HOSTILE_LEVELS[case]
    src = GOLDEN / ("scene_v5.pxc" if case in HOSTILE_LEVELS else "scene_v4.pxc")
    path = _rewrite(src, tmp_path / f"{case}.pxc", meta_fn, arrays_fn)
    for decode in (codec.decode, lite.decode):
        with pytest.raises(ProxycodecError) as e:
            decode(path)
        msg = str(e.value)
        assert "\n" not in msg and str(path) in msg


# ------------------------------------------------------------------------------------------------ rate training
def test_rate_model_gradients_and_coarser_steps_cost_fewer_bits():
    rng = np.random.default_rng(5)
    M, F, K = 200, 32, 10
    pos = np.unique(rng.integers(-30, 30, (M, 3)), axis=0).astype(np.float32) * np.float32(0.05)
    M = len(pos)
    mask = np.zeros(M, bool)
    mask[::3] = True
    f = torch.tensor(rng.normal(size=(M, F)), dtype=torch.float32, requires_grad=True)
    o = torch.tensor(rng.normal(size=(M, K, 3)) * 0.3, dtype=torch.float32, requires_grad=True)
    s = torch.tensor(rng.normal(size=(M, 6)) * 0.1 - 3, dtype=torch.float32, requires_grad=True)
    rate = RateModel(pos, 0.05, mask, f, o, s, sample=10_000)
    g = torch.Generator().manual_seed(0)
    fn, on, sn, bits = rate(f, o, s, generator=g)
    assert fn.shape == f.shape and on.shape == o.shape and sn.shape == s.shape
    assert (fn - f).abs().max() <= torch.exp(rate.log_step["features"]).max() / 2 + 1e-5
    step, mid = torch.exp(rate.log_step["offsets"]), rate.mid_offsets
    k = (on.reshape(M, -1) - mid) / step
    assert torch.allclose(k, torch.round(k), atol=1e-3)  # on the grid the container will store
    bits.backward()
    for t in (f, o, s, *rate.log_step.values()):
        assert t.grad is not None and torch.isfinite(t.grad).all()
    assert all((p.grad < 0).all() for p in rate.log_step.values())  # a coarser step always saves bits
    with torch.no_grad():
        for p in rate.log_step.values():
            p += 1.0
        coarse = rate(f, o, s, generator=torch.Generator().manual_seed(0))[3]
    assert coarse < bits - M * 10  # (the untrained nets still expect the old spread)


def test_learned_steps_reach_the_container(tmp_path):
    from test_codec import FAST, tiny_model

    model = tiny_model()
    steps = {"features": {"step": [0.05] * 32, "origin": [0.01] * 32},
             "scalings": {"step": [0.02] * 6, "origin": [0.0] * 6},
             "offsets": {"step": [0.03] * 30, "origin": [0.005] * 30}}
    model.scene = replace(model.scene, metadata={**model.scene.metadata, "quant_steps": steps})
    rep = codec.encode(model, tmp_path / "s.pxc", **FAST, entropy_iters=50, entropy="model")
    q = rep.meta["quant"]
    assert q["offsets"]["scale"] == pytest.approx(steps["offsets"]["step"]) and q["offsets"]["bits"] == 6  # 1/0.03
    # the stored values lie on the given grid, origin + k step
    k = (np.asarray(q["offsets"]["offset"]) - 0.005) / 0.03
    assert np.allclose(k, np.rint(k), atol=1e-6)
    assert "quant_steps" not in rep.meta["scene"]
    off = model.scene.offsets.numpy()
    dec = codec.decode(rep.path).scene.offsets.numpy()
    order = np.lexsort(model.scene.positions.numpy().T[::-1])
    back = np.lexsort(codec.decode(rep.path).scene.positions.numpy().T[::-1])
    assert np.abs(dec[back] - off[order]).max() <= 0.03 / 2 + 1e-6
    plain = codec.encode(model, tmp_path / "p.pxc", **FAST, entropy_iters=50, learned_steps=False)
    assert plain.meta["quant"]["offsets"]["bits"] == 8


def test_auto_keeps_zstd_where_the_nets_do_not_pay(both, tmp_path, monkeypatch):
    """Each of ``entropy="auto"``'s three exits, forced in turn: the nets too large to pay, zstd far below the
    model's starting point, and the fitted model against zstd (which wins decides the format, as its log says)."""
    from test_codec import FAST, tiny_model

    r4, r2 = both
    e = r4.meta["entropy"]
    model_bytes = r4.file_bytes - r2.file_bytes + e["zstd_bytes"]  # the rest of the two files is the same

    def auto(name, **limits):
        for k, v in limits.items():
            monkeypatch.setattr(codec, k, v)
        log = []
        rep = codec.encode(tiny_model(), tmp_path / f"{name}.pxc", **FAST, entropy_iters=300, progress=log.append,
                           positions="delta")  # as ``both``: formats 2 and 4
        return rep.meta["scene_format"], [s for s in log if s.startswith("entropy model:")]

    fmt, log = auto("big", AUTO_MAX_SAVING=0.0)
    assert fmt == 2 and len(log) == 1 and "would outweigh" in log[0], log
    fmt, log = auto("start", AUTO_MAX_SAVING=1e9, AUTO_MIN_START_RATIO=1e9)
    assert fmt == 2 and len(log) == 1 and "starting point" in log[0], log
    fmt, log = auto("fit", AUTO_MAX_SAVING=1e9, AUTO_MIN_START_RATIO=0.0)
    assert len(log) == 1, log
    if model_bytes < e["zstd_bytes"]:  # the model's fit (same seed and data as ``both``) wins: format 4
        assert fmt == 4 and "against zstd's" in log[0] and "zstd kept" not in log[0], log
    else:
        assert fmt == 2 and "zstd kept" in log[0], log


def _bits_pass_by_pass(rate: RateModel, y_f, y_s, y_o, P_rows, L_rows, wp, wl):
    """The reference of ``RateModel.symbol_bits``: one net call per coding pass (each feature group; proxies, then
    leaves), as the decoder makes the passes, and each pass's bits summed on its own."""

    def clip(v):
        return v.detach().clamp(-entropy.ACT_MAX, entropy.ACT_MAX)

    F = y_f.shape[1]
    G = -(-F // entropy.FEATURE_GROUP)
    total = 0.0
    yp = y_f[P_rows]
    for g in range(G):
        c0, c1 = g * entropy.FEATURE_GROUP, min(F, (g + 1) * entropy.FEATURE_GROUP)
        known = torch.zeros_like(yp)
        known[:, :c0] = clip(yp[:, :c0])
        onehot = yp.new_zeros(len(P_rows), G)
        onehot[:, g] = 64
        mu, lvl = rate.nets["features"](torch.cat([rate.posn[P_rows], known, onehot], 1))
        total = total + wp * laplace_bits(yp[:, c0:c1], mu[:, :c1 - c0], lvl[:, :c1 - c0]).sum()
    for rows, leaf, w in ((P_rows, False, wp), (L_rows, True, wl)):
        if not len(rows):
            continue
        src = rate.near[rows] if leaf else rows
        head = [clip(y_f)[src], rate.posn[rows], y_s.new_full((len(rows), 1), float(entropy.FLAG if leaf else 0)),
                rate.rel[rows]]
        ref_s = y_s[src].detach() if leaf else y_s.new_zeros(len(rows), y_s.shape[1])
        mu, lvl = rate.nets["scalings"](torch.cat(head + [clip(ref_s)], 1), ref_s)
        total = total + w * laplace_bits(y_s[rows], mu, lvl).sum()
        ref_o = y_o[src].detach() if leaf else y_o.new_zeros(len(rows), y_o.shape[1])
        mu, lvl = rate.nets["offsets"](torch.cat(head + [clip(y_s[rows]), clip(ref_o)], 1), ref_o)
        total = total + w * laplace_bits(y_o[rows], mu, lvl).sum()
    return total


@pytest.mark.parametrize("F", [32, 12])  # 12: a short last feature group (8 + 4)
def test_rate_bits_in_one_call_per_net_match_the_pass_by_pass_reference(F):
    """``symbol_bits`` stacks every pass of a net into one call: bits and gradients (symbols, nets, gains) are the
    reference's, in float64 so that only the order of the sums can differ."""
    rng = np.random.default_rng(11)
    M, K = 150, 10
    pos = np.unique(rng.integers(-30, 30, (M, 3)), axis=0).astype(np.float32) * np.float32(0.05)
    M = len(pos)
    mask = np.zeros(M, bool)
    mask[::3] = True
    f = torch.tensor(rng.normal(size=(M, F)), dtype=torch.float32)
    o = torch.tensor(rng.normal(size=(M, K, 3)) * 0.3, dtype=torch.float32)
    s = torch.tensor(rng.normal(size=(M, 6)) * 0.1 - 3, dtype=torch.float32)
    rate = RateModel(pos, 0.05, mask, f, o, s).double()
    with torch.no_grad():  # nets away from their start (zero gains, a uniform level) so that every input matters
        for p in rate.nets.parameters():
            p.add_(torch.from_numpy(rng.normal(size=tuple(p.shape)) * 0.1))
    ys = [torch.tensor(rng.normal(size=(M, c)) * 20, dtype=torch.float64, requires_grad=True) for c in (F, 6, 3 * K)]
    P_rows = torch.from_numpy(np.flatnonzero(mask)[::2].copy())
    L_rows = torch.from_numpy(np.flatnonzero(~mask)[1::2].copy())
    params = [p for p in rate.nets.parameters() if p.requires_grad]
    results = []
    for fn in (rate.symbol_bits, lambda *a: _bits_pass_by_pass(rate, *a)):
        bits = fn(*ys, P_rows, L_rows, 3.0, 2.5)
        grads = torch.autograd.grad(bits, ys + params)
        results.append((bits, grads))
    (b1, g1), (b2, g2) = results
    assert float(b1.detach()) == pytest.approx(float(b2.detach()), rel=1e-12) and float(b1.detach()) > 0
    for a, b in zip(g1, g2):
        assert torch.allclose(a, b, rtol=1e-9, atol=1e-12)
    assert g1[0].abs().sum() > 0 and g1[1].abs().sum() > 0 and g1[2].abs().sum() > 0
    # no leaves (a scene of proxies only): the proxies' passes alone
    none = torch.zeros(0, dtype=torch.int64)
    with torch.no_grad():
        assert float(rate.symbol_bits(*ys, P_rows, none)) == pytest.approx(
            float(_bits_pass_by_pass(rate, *ys, P_rows, none, 1.0, 1.0)), rel=1e-12)
