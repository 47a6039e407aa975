"""Conditional entropy coding of the stored anchor attributes (scene format 4), torch-free.

What it codes: the quantised symbols of the proxies' features, every anchor's scalings and every anchor's offsets
(the arrays ``sections.quantize_anchors`` makes; unsigned, ``bits`` per channel). Dequantisation is untouched, so a
format-4 container decodes to exactly the arrays of the format-2 container with the same symbols.

How (SPEC section 4, "Entropy coding"):

- Each symbol ``q`` gets a discrete Laplace distribution ``p(q) ~ rho_s^|q - m|`` whose integer centre ``m`` and scale
  index ``s`` (one of ``SCALE_LEVELS``) a small **integer MLP** predicts from what the decoder already holds: the
  integer grid position of the anchor, its own feature (a proxy) or its nearest proxy's (a leaf), the leaf's offset
  from that proxy, the proxy's scalings and offsets, the anchor's already-decoded scalings and, for features,
  the already-decoded channel groups of the same proxy. A leaf's predicted feature is a function of exactly these
  inputs (its proxy's feature and its position relative to it); the MLP sees them directly, in integers.
- **Bit-exact on every x86 machine.** Every value that selects a probability is an integer computed exactly: inputs
  are integers clipped to [-127, 127], weights int8, so every product and partial sum of a layer is an integer below
  2^24 and float32 matrix products (BLAS, any summation order, FMA or not) give the same exact result; activations
  are re-quantised by arithmetic shifts. The probability tables are integers: Laplace masses computed in 50-digit decimal
  arithmetic (correctly rounded, software: no libm) and truncated to Q32 (formats/CONTAINER.md, Appendix A.3). The coder (``constriction``'s ANS, Rust) normalises those integer-valued tables itself, in IEEE
  arithmetic without platform-dependent reductions.
- Residuals ``q - m`` in [-254, 254] are coded directly; larger ones as an escape symbol plus their excess in
  ``entropy/escapes``.

Decode order (the encoder codes the same, in reverse): proxy features in groups of ``FEATURE_GROUP`` channels;
scalings, proxies then leaves; offsets, proxies then leaves. Within a pass symbols are coded grouped by scale index,
each group in anchor-major order, so every group is one ``decode`` call.
"""

from __future__ import annotations

import decimal
import functools
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .errors import ProxycodecError
from .nearest import nearest_proxy

SCALE_LEVELS = 48
LN_B0, LN_STEP = -2, 5  # b_s = exp(LN_B0 + s / LN_STEP) symbols: 0.135 .. 1636
RESID = 255  # residuals -(RESID - 1)..RESID - 1 coded directly; indices 0 and 2 RESID are the escapes
ALPHABET = 2 * RESID + 1
ACT_MAX = 127  # inputs and hidden activations are integers in [-127, 127] / [0, 127]
EXACT_F32 = 1 << 24  # every partial sum of a layer stays below this: float32 products are exact
FEATURE_GROUP = 8
REL_CLIP, REL_GAIN = 15, 8  # a leaf's grid offset from its proxy: clipped to +-15 voxels, times 8
FLAG = 127  # the "leaf" input
MAX_SHIFT = 40
NETS = ("features", "scalings", "offsets")
STREAM = "entropy/stream"  # u4: the ANS words (stored raw: they do not compress)
ESCAPES = "entropy/escapes"  # i4: excess magnitudes of escaped residuals, in decode order
NET_WEIGHTS = "entropy/nets.i1"  # every net's int8 matrices, concatenated
NET_INTS = "entropy/nets.i4"  # every net's int32 biases and gains, concatenated
SECTIONS = (STREAM, ESCAPES, NET_WEIGHTS, NET_INTS)
TABLES = {"levels": SCALE_LEVELS, "ln_b0": LN_B0, "ln_step": LN_STEP, "resid": RESID,
          "family": "discrete Laplace, Q32 integer powers"}


# ---------------------------------------------------------------------------------------------- tables
@functools.lru_cache(maxsize=1)
def scale_tables() -> np.ndarray:
    """[SCALE_LEVELS, ALPHABET] float64 holding integers: 2^32 times the probability of each residual index
    (residual = index - RESID) under a Laplace of scale ``b_s`` integrated over the residual's unit bin (what the
    training rate assumes: ``entropy_fit.laplace_bits``), floored, at least 1. Computed in decimal arithmetic (50
    digits, correctly rounded, no libm), so the integers are the same everywhere. The escapes carry the tail
    beyond the direct range."""
    ctx = decimal.Context(prec=50, rounding=decimal.ROUND_HALF_EVEN)  # whatever the host's DefaultContext
    D = decimal.Decimal
    one = D(1 << 32)
    out = np.zeros((SCALE_LEVELS, ALPHABET), np.float64)
    for s in range(SCALE_LEVELS):
        b = ctx.exp(ctx.add(D(LN_B0), ctx.divide(D(s), D(LN_STEP))))
        rho = ctx.exp(ctx.minus(ctx.divide(D(1), b)))  # e^(-1/b): one residual further
        sigma = ctx.exp(ctx.minus(ctx.divide(D(1), ctx.multiply(D(2), b))))  # e^(-1/2b)
        w = [int(ctx.multiply(ctx.subtract(D(1), sigma), one))]  # P(0) = 1 - e^(-1/2b)
        p = ctx.divide(ctx.subtract(ctx.divide(D(1), sigma), sigma), D(2))  # P(1) / rho
        for _ in range(1, RESID + 1):
            p = ctx.multiply(p, rho)  # P(k) = rho^k (e^(1/2b) - e^(-1/2b)) / 2, one side
            w.append(int(ctx.multiply(p, one)))
        tail = int(ctx.multiply(ctx.divide(ctx.multiply(p, D(1)), ctx.subtract(D(1), rho)), one))  # P(>= RESID)
        row = np.array([max(1, w[abs(k)]) for k in range(-RESID, RESID + 1)], np.float64)
        row[0] = row[-1] = max(1, tail)
        out[s] = row
    return out


def scale_of_level(s):
    """The Laplace scale b (in symbols) of level ``s`` (float, for training only: coding uses the tables)."""
    return np.exp(LN_B0 + np.asarray(s, np.float64) / LN_STEP)


@functools.lru_cache(maxsize=1)
def _models():
    import constriction  # noqa: PLC0415  (a few ms; only containers with entropy-coded sections need it)

    return [constriction.stream.model.Categorical(t, perfect=False) for t in scale_tables()]


# ---------------------------------------------------------------------------------------------- integer MLP
def _shift_floor(a: np.ndarray, t: int) -> np.ndarray:
    return a >> t if t >= 0 else a << (-t)


def _shift_round(a: np.ndarray, t: int) -> np.ndarray:
    return (a + (1 << (t - 1))) >> t


@dataclass(frozen=True)
class IntNet:
    """Integer MLP: ``h = clip((W h + b) >> shift, 0, 127)`` per hidden layer (W int8, b integer), then an output
    layer in fixed point with ``out_exp`` fractional bits: ``n_out`` centres (plus ``gain * base``, the base being a
    reference symbol such as the proxy's value of the same channel) and ``n_out`` scale levels."""

    weights: tuple[np.ndarray, ...]  # int8 [out, in]
    biases: tuple[np.ndarray, ...]  # int64 [out]
    shifts: tuple[int, ...]  # one per hidden layer
    out_exp: int
    gain: np.ndarray  # int64 [n_out] (zeros: no base)

    @property
    def n_in(self) -> int:
        return int(self.weights[0].shape[1])

    @property
    def n_out(self) -> int:
        return int(self.weights[-1].shape[0]) // 2

    def check(self, err: Callable[[str], Exception]) -> None:
        """Shapes chain, and no partial sum can leave float32's exact integers (a hostile file could ask for it)."""
        if not (len(self.weights) == len(self.biases) == len(self.shifts) + 1 and 1 <= len(self.weights) <= 4):
            raise err("entropy model: bad layer count")
        n = self.n_in
        for W, b in zip(self.weights, self.biases):
            if W.ndim != 2 or W.shape[1] != n or b.shape != (W.shape[0],) or not 0 < W.shape[0] <= 4096:
                raise err("entropy model: layer shapes do not chain")
            bound = ACT_MAX * np.abs(W.astype(np.int64)).sum(1) + np.abs(b)
            if bound.max(initial=0) >= EXACT_F32:
                raise err("entropy model: a layer can overflow exact integer arithmetic")
            n = W.shape[0]
        if n % 2 or self.gain.shape != (n // 2,) or np.abs(self.gain).max(initial=0) >= 1 << 30:
            raise err("entropy model: bad output layer")
        if not all(0 <= t <= MAX_SHIFT for t in self.shifts) or not 1 <= self.out_exp <= MAX_SHIFT:
            raise err("entropy model: bad shifts")

    def __call__(self, x: np.ndarray, base: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """[N, n_in] integers in [-127, 127] -> (centres [N, n_out] int64, scale levels [N, n_out] int64)."""
        h = x.astype(np.float32)
        for i, (W, b) in enumerate(zip(self.weights, self.biases)):
            acc = (h @ W.astype(np.float32).T).astype(np.int64) + b  # exact: |partial sums| < 2^24
            if i < len(self.shifts):
                h = np.clip(_shift_floor(acc, self.shifts[i]), 0, ACT_MAX).astype(np.float32)
        n = self.n_out
        centre = acc[:, :n]
        if base is not None:
            centre = centre + self.gain * base
        m = _shift_round(centre, self.out_exp)
        s = np.clip(_shift_round(acc[:, n:], self.out_exp), 0, SCALE_LEVELS - 1)
        return m, s

    def to_json(self) -> dict:
        return {"layers": [[int(v) for v in W.shape] for W in self.weights], "shifts": list(self.shifts),
                "out_exp": self.out_exp}


def pack_nets(nets: dict[str, IntNet]) -> tuple[dict[str, np.ndarray], dict]:
    """The nets as two sections (int8 matrices; int32 biases and gains) and their layout for the metadata."""
    i1, i4 = [], []
    for name in NETS:
        net = nets[name]
        i1 += [W.ravel() for W in net.weights]
        i4 += [b.astype(np.int32) for b in net.biases] + [net.gain.astype(np.int32)]
    return ({NET_WEIGHTS: np.concatenate(i1).astype(np.int8), NET_INTS: np.concatenate(i4).astype(np.int32)},
            {name: nets[name].to_json() for name in NETS})


def unpack_nets(layout, sections: dict[str, np.ndarray], err) -> dict[str, IntNet]:
    if not isinstance(layout, dict) or set(layout) != set(NETS):
        raise err("entropy model: bad net layout")
    w8, w32 = sections.get(NET_WEIGHTS), sections.get(NET_INTS)
    if w8 is None or w32 is None or w8.dtype != np.int8 or w32.dtype != np.int32 or w8.ndim != 1 or w32.ndim != 1:
        raise err(f"missing or malformed sections {NET_WEIGHTS!r} / {NET_INTS!r}")
    p8 = p32 = 0
    nets = {}
    for name in NETS:
        spec = layout[name]
        layers, shifts, out_exp = spec["layers"], spec["shifts"], spec["out_exp"]
        if not (isinstance(layers, list) and 1 <= len(layers) <= 4 and isinstance(shifts, list)
                and all(isinstance(t, int) for t in shifts) and isinstance(out_exp, int)):
            raise err(f"entropy model {name!r}: bad layout")
        Ws, bs = [], []
        for shape in layers:
            if not (isinstance(shape, list) and len(shape) == 2 and all(isinstance(v, int) and 0 < v <= 4096
                                                                        for v in shape)):
                raise err(f"entropy model {name!r}: bad layer shape")
            o, i = shape
            if p8 + o * i > w8.size or p32 + o > w32.size:
                raise err(f"entropy model {name!r}: sections shorter than its layout")
            Ws.append(w8[p8:p8 + o * i].reshape(o, i))
            bs.append(w32[p32:p32 + o].astype(np.int64))
            p8, p32 = p8 + o * i, p32 + o
        n_out = layers[-1][0] // 2
        if p32 + n_out > w32.size:
            raise err(f"entropy model {name!r}: sections shorter than its layout")
        gain = w32[p32:p32 + n_out].astype(np.int64)
        p32 += n_out
        net = IntNet(tuple(Ws), tuple(bs), tuple(shifts), out_exp, gain)
        net.check(err)
        nets[name] = net
    if p8 != w8.size or p32 != w32.size:
        raise err("entropy model: sections longer than its layout")
    return nets


# ---------------------------------------------------------------------------------------------- contexts
@dataclass(frozen=True)
class Context:
    """What the decoder knows before the attributes: integer positions, the split and each anchor's nearest proxy."""

    posn: np.ndarray  # [M, 3] int64 in [-127, 127]: grid position scaled to the anchors' bounding box
    rel: np.ndarray  # [M, 3] int64: clipped grid offset from the nearest proxy, times REL_GAIN (0 for proxies)
    near: np.ndarray  # [M] int64: nearest proxy (itself for a proxy)
    proxies: np.ndarray  # [P] indices
    leaves: np.ndarray  # [L] indices

    @staticmethod
    def of(positions: np.ndarray, voxel: float, mask: np.ndarray) -> "Context":
        c = np.floor(positions.astype(np.float64) / float(voxel)).astype(np.int64)  # IEEE division: exact rule
        lo = c.min(0) if len(c) else np.zeros(3, np.int64)
        span = max(1, int((c.max(0) - lo).max(initial=0))) if len(c) else 1
        posn = (c - lo) * (2 * ACT_MAX) // span - ACT_MAX
        near = nearest_proxy(positions, mask, ties="index")  # format 4's rule (encoder and decoder: Morton order)
        rel = np.clip(c - c[near], -REL_CLIP, REL_CLIP) * REL_GAIN
        return Context(posn, rel, near, np.flatnonzero(mask), np.flatnonzero(~mask))


def squash(v: np.ndarray, u: int) -> np.ndarray:
    """Centred symbols -> net inputs: arithmetic shift by ``u``, clipped to [-127, 127]."""
    return np.clip(v >> u, -ACT_MAX, ACT_MAX)


def feature_inputs(ctx: Context, f_sq: np.ndarray, group: int, n_groups: int) -> np.ndarray:
    """[P, 3 + F + n_groups]: proxy position, the proxy's feature groups before ``group`` (zeros after), one-hot."""
    P, F = f_sq.shape
    known = np.zeros_like(f_sq)
    known[:, :group * FEATURE_GROUP] = f_sq[:, :group * FEATURE_GROUP]
    onehot = np.zeros((P, n_groups), np.int64)
    onehot[:, group] = 64
    return np.concatenate([ctx.posn[ctx.proxies], known, onehot], 1)


def anchor_inputs(ctx: Context, rows: np.ndarray, leaf: bool, f_sq_all: np.ndarray, *extra: np.ndarray
                  ) -> np.ndarray:
    """[len(rows), F + 7 + ...]: the anchor's feature (a proxy) or its nearest proxy's (a leaf), position, leaf flag,
    offset from the proxy, then ``extra`` blocks (already indexed by row)."""
    src = ctx.near[rows] if leaf else rows
    flag = np.full((len(rows), 1), FLAG if leaf else 0, np.int64)
    return np.concatenate([f_sq_all[src], ctx.posn[rows], flag, ctx.rel[rows], *extra], 1)


# ---------------------------------------------------------------------------------------------- passes
@dataclass
class Attributes:
    """Centred symbols (``q - 2^(bits-1)``), anchor-major: features [M, F] (proxies' rows), scalings [M, 6],
    offsets [M, 3K]."""

    features: np.ndarray
    scalings: np.ndarray
    offsets: np.ndarray


def passes(ctx: Context, predict, shifts: dict[str, int], a: Attributes, code) -> None:
    """Run every coding pass in decode order. ``predict(net, inputs, base)`` gives the centres and scale levels
    (``IntNet`` calls; the encoder's training collects the inputs instead). ``code(attribute, rows, columns, m, s)`` returns the [len(rows), C] centred symbols
    of the pass (the encoder: the known ones, recorded; the decoder: decoded), which later passes then see in ``a``.
    """
    F = a.features.shape[1]
    n_groups = -(-F // FEATURE_GROUP)
    P = len(ctx.proxies)
    f_sq = np.zeros((P, F), np.int64)
    for g in range(n_groups):
        cols = slice(g * FEATURE_GROUP, min(F, (g + 1) * FEATURE_GROUP))
        m, s = predict("features", feature_inputs(ctx, f_sq, g, n_groups), None)
        n = cols.stop - cols.start
        vals = code("features", ctx.proxies, cols, m[:, :n], s[:, :n])
        a.features[ctx.proxies, cols] = vals
        f_sq[:, cols] = squash(vals, shifts["features"])
    f_all = np.zeros((len(ctx.posn), F), np.int64)
    f_all[ctx.proxies] = f_sq
    for leaf, rows in ((False, ctx.proxies), (True, ctx.leaves)):
        ref = a.scalings[ctx.near[rows]] if leaf else np.zeros((len(rows), a.scalings.shape[1]), np.int64)
        m, s = predict("scalings", anchor_inputs(ctx, rows, leaf, f_all, squash(ref, shifts["scalings"])), ref)
        a.scalings[rows] = code("scalings", rows, slice(None), m, s)
    for leaf, rows in ((False, ctx.proxies), (True, ctx.leaves)):
        ref = a.offsets[ctx.near[rows]] if leaf else np.zeros((len(rows), a.offsets.shape[1]), np.int64)
        x = anchor_inputs(ctx, rows, leaf, f_all, squash(a.scalings[rows], shifts["scalings"]),
                          squash(ref, shifts["offsets"]))
        m, s = predict("offsets", x, ref)
        a.offsets[rows] = code("offsets", rows, slice(None), m, s)


def _caller(nets: dict[str, IntNet]):
    return lambda name, x, base: nets[name](x, base)


def net_inputs(F: int, K: int) -> dict[str, tuple[int, int]]:
    """(inputs, outputs) of each net for feature size F and K offsets."""
    n_groups = -(-F // FEATURE_GROUP)
    return {"features": (3 + F + n_groups, FEATURE_GROUP), "scalings": (F + 7 + 6, 6),
            "offsets": (F + 7 + 6 + 3 * K, 3 * K)}


def _order(s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Symbols of a pass (flattened, anchor-major) grouped by scale level: (order, count per level)."""
    flat = s.ravel()
    return np.argsort(flat, kind="stable"), np.bincount(flat, minlength=SCALE_LEVELS)


# ---------------------------------------------------------------------------------------------- encode / decode
def input_shifts(a: Attributes) -> dict[str, int]:
    """Per attribute: the shift that brings its centred symbols into [-127, 127] (0 for 8-bit symbols)."""
    return {k: max(0, int(np.abs(getattr(a, k)).max(initial=0)).bit_length() - 7) for k in NETS}


def centred(q: np.ndarray, bits: int) -> np.ndarray:
    return q.astype(np.int64) - (1 << (bits - 1))


def encode(ctx: Context, nets: dict[str, IntNet], a: Attributes, bits: dict[str, int]
           ) -> tuple[dict[str, np.ndarray], dict, dict[str, float]]:
    """Code ``a`` (centred symbols) -> (sections, meta["entropy"], coded bytes per attribute)."""
    import constriction  # noqa: PLC0415

    shifts = input_shifts(a)
    groups: list[tuple[np.ndarray, np.ndarray]] = []  # (indices, levels) per pass, decode order
    escapes: list[np.ndarray] = []
    names: list[str] = []
    known = Attributes(a.features.copy(), a.scalings.copy(), a.offsets.copy())

    def code(attr, rows, cols, m, s):
        vals = getattr(known, attr)[rows][:, cols]
        r = (vals - m).ravel()
        idx = np.clip(r, -(RESID - 1), RESID - 1) + RESID
        idx[r <= -RESID] = 0
        idx[r >= RESID] = 2 * RESID
        escapes.append(np.abs(r[(r <= -RESID) | (r >= RESID)]) - RESID)
        groups.append((idx.astype(np.int32), s.ravel()))
        names.append(attr)
        return vals

    passes(ctx, _caller(nets), shifts, Attributes(np.zeros_like(a.features), np.zeros_like(a.scalings),
                                         np.zeros_like(a.offsets)), code)
    coder = constriction.stream.stack.AnsCoder()
    models = _models()
    sizes = {}
    for (idx, s), name in zip(reversed(groups), reversed(names)):
        before = coder.num_bits()
        order, counts = _order(s)
        ends = np.cumsum(counts)
        for lvl in range(SCALE_LEVELS - 1, -1, -1):  # reverse of the decoder's ascending levels
            if counts[lvl]:
                coder.encode_reverse(idx[order[ends[lvl] - counts[lvl]:ends[lvl]]], models[lvl])
        sizes[name] = sizes.get(name, 0.0) + (coder.num_bits() - before) / 8
    esc = np.concatenate(escapes).astype(np.int64) if escapes else np.zeros(0, np.int64)
    if esc.size and esc.max() >= 1 << 31:
        raise ProxycodecError("entropy coding: residual out of range")
    sections, layout = pack_nets(nets)
    sections[STREAM] = coder.get_compressed().astype(np.uint32)
    sections[ESCAPES] = esc.astype(np.int32)
    meta = {"version": 1, "coder": "constriction 0.5 stack.AnsCoder, Categorical(perfect=False)",
            "tables": dict(TABLES), "nets": layout, "input_shift": shifts, "bits": dict(bits),
            "symbols": int(sum(len(i) for i, _ in groups)), "escapes": int(esc.size)}
    return sections, meta, sizes


def code_lengths(ctx: Context, nets: dict[str, IntNet], a: Attributes) -> Attributes:
    """Bits each symbol of ``a`` costs under the integer model and tables (an escape: its index's bits + 32 for the
    excess word): where the stream's bytes go, symbol by symbol (e.g. the offsets of never-drawn slots)."""
    t = scale_tables()
    logp = np.log2(t) - np.log2(t.sum(1, keepdims=True))
    out = Attributes(np.zeros(a.features.shape), np.zeros(a.scalings.shape), np.zeros(a.offsets.shape))

    def code(attr, rows, cols, m, s):
        vals = getattr(a, attr)[rows][:, cols]
        r = vals - m
        idx = np.clip(r, -(RESID - 1), RESID - 1) + RESID
        idx[r <= -RESID] = 0
        idx[r >= RESID] = 2 * RESID
        b = -logp[s, idx] + 32.0 * ((idx == 0) | (idx == 2 * RESID))
        getattr(out, attr)[np.ix_(rows, np.arange(getattr(a, attr).shape[1])[cols])] = b
        return vals

    passes(ctx, _caller(nets), input_shifts(a), Attributes(np.zeros_like(a.features), np.zeros_like(a.scalings),
                                                            np.zeros_like(a.offsets)), code)
    return out


def decode(meta: dict, sections: dict[str, np.ndarray], ctx: Context, F: int, K: int, bits: dict[str, int], err
           ) -> Attributes:
    """Inverse of ``encode``: the centred symbols, every count bounded by the declared shapes and sections."""
    import constriction  # noqa: PLC0415

    if not isinstance(meta, dict) or meta.get("version") != 1:
        raise err("unsupported entropy coding version")
    if meta.get("tables") != TABLES:
        raise err("entropy coding: unknown probability tables")
    shifts = meta.get("input_shift")
    if not (isinstance(shifts, dict) and set(shifts) == set(NETS)
            and all(isinstance(v, int) and 0 <= v <= 16 for v in shifts.values())):
        raise err("entropy coding: bad input shifts")
    for k in NETS:
        if not (isinstance(bits.get(k), int) and 1 <= bits[k] <= 16):
            raise err(f"entropy coding needs integer symbols for {k!r} (1..16 bits)")
    nets = unpack_nets(meta.get("nets"), sections, err)
    for name, (n_in, n_out) in net_inputs(F, K).items():
        if nets[name].n_in != n_in or nets[name].n_out != n_out:
            raise err(f"entropy model {name!r} does not match the scene's sizes")
    stream, esc = sections.get(STREAM), sections.get(ESCAPES)
    if stream is None or stream.dtype != np.uint32 or stream.ndim != 1:
        raise err(f"missing or malformed section {STREAM!r}")
    if esc is None or esc.dtype != np.int32 or esc.ndim != 1 or (esc.size and esc.min() < 0):
        raise err(f"missing or malformed section {ESCAPES!r}")
    coder = constriction.stream.stack.AnsCoder(np.ascontiguousarray(stream))
    models = _models()
    used = [0]

    def code(attr, rows, cols, m, s):
        order, counts = _order(s)
        idx = np.empty(s.size, np.int64)
        ends = np.cumsum(counts)
        for lvl in range(SCALE_LEVELS):
            if counts[lvl]:
                idx[order[ends[lvl] - counts[lvl]:ends[lvl]]] = coder.decode(models[lvl], int(counts[lvl]))
        r = idx - RESID
        lo, hi = idx == 0, idx == 2 * RESID
        n_esc = int(lo.sum() + hi.sum())
        if used[0] + n_esc > esc.size:
            raise err("entropy stream is corrupt (more escapes than stored)")
        e = np.zeros(s.size, np.int64)
        e[lo | hi] = esc[used[0]:used[0] + n_esc].astype(np.int64) + RESID
        used[0] += n_esc
        r = np.where(lo, -e, np.where(hi, e, r))
        vals = m.ravel() + r
        half = 1 << (bits[attr] - 1)
        if vals.size and (vals.min() < -half or vals.max() >= half):
            raise err(f"entropy stream is corrupt ({attr} decode out of range)")
        return vals.reshape(m.shape)

    M = len(ctx.posn)
    a = Attributes(np.zeros((M, F), np.int64), np.zeros((M, 6), np.int64), np.zeros((M, 3 * K), np.int64))
    passes(ctx, _caller(nets), shifts, a, code)
    if used[0] != esc.size or not coder.is_empty():
        raise err("entropy stream is corrupt (data left over)")
    return a
