"""The scene format in one place, torch-free: numpy arrays <-> a scene container's sections and metadata (every
section: ``formats/CONTAINER.md``).

Write half (``codec.encode``): positions as Morton-ordered grid deltas (``encode_positions``), uniform per-channel
quantisation of the stored attributes (``quantize_anchors``), MLP weights as sections (``weights_to_sections``,
``pack_weights``), and the sections and metadata a container holds (``scene_sections``, ``scene_metadata``).

Read half: ``codec.py`` decodes a container to a ``SceneModel`` (torch); ``proxycodec.lite`` decodes and renders one
view without importing torch. Both read the container through the functions here (dequantisation, grid positions,
the proxy split, weights with their int8 row scales, cameras), so the stored arrays come out bit for bit the same
and a malformed file fails the same way, with one ``ContainerError``.
"""

from __future__ import annotations

import decimal
import functools
import math
import os
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from . import octree
from .camera import Camera
from .errors import ProxycodecError
from .formats.container import Container, ContainerError, read_container
from .netconfig import DecoderConfig, PredictorConfig

SCENE_KIND = "proxycodec.scene"
SCENE_FORMAT = 2  # version of the scene sections (inside container format 1); 2: weights packed per group and dtype
#: 3: format 2 with a Scaffold-GS decoder variant (``DecoderConfig.variant()``: no distance input, feature bank).
#: Written only for such decoders, so that a reader that predates the variants refuses the file ("upgrade") instead
#: of ignoring the fields it does not know and rendering wrongly.
SCENE_FORMAT_VARIANT = 3
#: 4: the stored attributes (proxy features, scalings, offsets) arithmetic-coded under the conditional entropy
#: model (``proxycodec.entropy``; ``meta["entropy"]``); weights and variants as in formats 2 and 3.
SCENE_FORMAT_ENTROPY = 4
#: 5: any of formats 2-4 with per-cell quantisation levels (``meta["quant"][attribute]["levels"]``: the step of an
#: anchor's values is the channel's step times ``2^(level / 4)``, the level looked up by the anchor's position cell
#: and whether it is a proxy). Written only when a scene has learned levels (``fit --quant-cells``).
SCENE_FORMAT_LEVELS = 5
#: 6: lists what the file uses in ``meta["features"]`` (sorted, from ``SCENE_FEATURES``): "octree" (grid positions
#: octree-coded, ``proxycodec.octree``), "entropy" (format 4's coding), "levels" (format 5's), "variant" (format
#: 3's). A reader refuses a feature it does not know ("upgrade"), so later features need no new number. Written only
#: for files that use a feature formats 2-5 cannot say (octree positions: ``encode --positions octree``).
#: "shift" (a later feature): the octree's grid passes through ``meta["positions"]["shift"]`` (float64 xyz) instead of
#: the origin: x = f32(shift + i x step), the grid of a scene trained in another frame (``convert``'s canonical one).
SCENE_FORMAT_OCTREE = 6
SCENE_FEATURES = ("entropy", "levels", "octree", "shift", "variant")
SUPPORTED_SCENE_FORMATS = (1, 2, 3, 4, 5, 6)
POSITION_CODINGS = ("delta", "octree")
FLOAT_BITS = 32  # "bits" value meaning: store float32, no quantisation
PREDICT_CHUNK = 65536  # leaves per predictor batch (fixed: the same batches in encoder and decoder)
MAX_ANCHORS = 1 << 28
QSCALE = ".qscale"  # suffix of the per-row scale section of an int8 ("q8") weight matrix
# MLP weight precisions: float32, float16, or int8 matrices on a grid of 2^(N-1) - 1 levels each side (qN)
WEIGHT_DTYPES = ("f32", "f16", "q8", "q7", "q6", "q5", "q4")
DEFAULT_WEIGHTS_DTYPE = "q7"  # encode's (``EncodeConfig.weights_dtype``); the built-in scene's decoder sits on its grid

LEVEL_MAX = 8  # per-cell quantisation levels are integers in [-LEVEL_MAX, LEVEL_MAX]: steps x 2^(level / 4)
LEVEL_DIVISOR = 4
MAX_LEVEL_CELLS = 32  # cells per axis of a level table

GRID_SUBDIVISIONS = 4  # positions may sit on voxel / 2^j for j <= this (Scaffold-GS grows anchors on finer grids)

# Section names (one place for the writer and both readers).
GRID = "anchors/grid"  # int [3, M]: Morton-ordered grid coordinates, delta-coded per axis
XYZ = "anchors/xyz"  # float32 [3, M]: positions that lie on no grid
PROXY_MASK = "anchors/proxy_mask"  # uint8 [ceil(M / 8)]: packed bits, little bit order
SCALINGS = "anchors/scalings"  # [6, M] quantised
OFFSETS = "anchors/offsets"  # [3K, M] quantised: every anchor's offsets ("stored" mode)
PROXY_FEATURES = "proxy/features"  # [F, P] quantised
PROXY_OFFSETS = "proxy/offsets"  # [3K, P] quantised: the proxies' offsets only ("predicted" mode)
LEVELS = "quant/levels"  # int8 [n]: scene format 5's per-cell levels of the occupied cells (``level_entries``)
LEVEL_ATTRS = ("features", "scalings", "offsets")  # the order of their entries in LEVELS

ErrorFactory = Callable[[str], ProxycodecError]


# ---------------------------------------------------------------------------------------------- primitives
@functools.lru_cache(maxsize=1)
def level_multipliers() -> np.ndarray:
    """[2 LEVEL_MAX + 1] float64, each a float32 value: ``2^(level / 4)`` for level -LEVEL_MAX..LEVEL_MAX, computed
    in decimal arithmetic (correctly rounded, software: no libm), so every machine has the same numbers."""
    ctx = decimal.Context(prec=50)
    D = decimal.Decimal
    ln2 = ctx.ln(D(2))
    return np.array([float(np.float32(float(ctx.exp(ctx.multiply(ln2, ctx.divide(D(v), D(LEVEL_DIVISOR)))))))
                     for v in range(-LEVEL_MAX, LEVEL_MAX + 1)], np.float64)


def position_cells(positions: np.ndarray, voxel: float, cells: int) -> np.ndarray:
    """[M] int64: each anchor's cell of a ``cells``^3 grid over the anchors' voxel bounding box (integer arithmetic
    on ``floor(position / voxel)``, IEEE division: the same cells in the trainer, the encoder and every decoder)."""
    c = np.floor(np.asarray(positions, np.float64) / float(voxel)).astype(np.int64)
    if not len(c):
        return np.zeros(0, np.int64)
    lo = c.min(0)
    span = int((c.max(0) - lo).max()) + 1
    ijk = (c - lo) * cells // span
    return (ijk[:, 0] * cells + ijk[:, 1]) * cells + ijk[:, 2]


def level_table(info, err) -> tuple[int, np.ndarray]:
    """A full level table (``quant_steps[attribute]["levels"]`` in a fitted scene's metadata), checked: (cells per
    axis G, table [2, G^3] int64: row 0 the proxies' levels, row 1 the leaves', by cell)."""
    if not isinstance(info, dict):
        raise err("bad quantisation levels")
    G, table = info.get("cells"), info.get("table")
    if not (isinstance(G, int) and not isinstance(G, bool) and 1 <= G <= MAX_LEVEL_CELLS):
        raise err(f"bad quantisation level cells {G!r}")
    if not (isinstance(table, list) and len(table) == 2 * G ** 3
            and all(isinstance(v, int) and not isinstance(v, bool) and -LEVEL_MAX <= v <= LEVEL_MAX for v in table)):
        raise err("bad quantisation level table")
    return G, np.asarray(table, np.int64).reshape(2, G ** 3)


def anchor_levels(info, positions: np.ndarray, voxel: float, leaf: np.ndarray, err) -> np.ndarray:
    """[N] int64: the quantisation level of each anchor under a full table (``positions`` [N, 3] of the whole
    scene; ``leaf`` [N])."""
    G, table = level_table(info, err)
    return table[np.asarray(leaf, np.int64), position_cells(positions, voxel, G)]


def _occupied(cells: np.ndarray, leaf: np.ndarray, rows: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """For the stored ``rows`` of an attribute: per kind (proxies, then leaves) present among them, (the rows'
    positions among the stored ones, the ascending occupied cells)."""
    out = []
    stored_leaf = leaf[rows]
    stored_cells = cells[rows]
    for kind in (False, True):
        where = np.flatnonzero(stored_leaf == kind)
        if len(where):
            out.append((where, np.unique(stored_cells[where])))
    return out


def level_entries(levels: np.ndarray, cells: np.ndarray, leaf: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """int8 entries of one attribute in ``LEVELS``: for each kind (proxies, then leaves) among the stored ``rows``,
    the level of each occupied cell in ascending cell order (empty cells cost nothing). ``levels``: the stored rows'
    levels (equal within a cell and kind)."""
    parts = []
    for where, occ in _occupied(cells, leaf, rows):
        first = np.zeros(len(occ), np.int64)
        idx = np.searchsorted(occ, cells[rows][where])
        first[idx] = where  # a row of each cell (any: they share its level)
        parts.append(levels[first])
    return np.concatenate(parts).astype(np.int8) if parts else np.zeros(0, np.int8)


def levels_from_entries(entries: np.ndarray, cells: np.ndarray, leaf: np.ndarray, rows: np.ndarray, err
                        ) -> np.ndarray:
    """Inverse of ``level_entries``: the stored rows' levels [len(rows)] (``entries`` exactly as many as needed)."""
    out = np.zeros(int(rows.sum()), np.int64)
    used = 0
    for where, occ in _occupied(cells, leaf, rows):
        if used + len(occ) > len(entries):
            raise err(f"section {LEVELS!r} is shorter than the occupied cells need")
        out[where] = entries[used:used + len(occ)][np.searchsorted(occ, cells[rows][where])]
        used += len(occ)
    if used != len(entries):
        raise err(f"section {LEVELS!r} does not match the occupied cells")
    return out


def stored_rows(name: str, mask: np.ndarray, predict_offsets: bool) -> np.ndarray:
    """[M] bool: the anchors whose rows attribute ``name`` stores."""
    return mask if name == "features" or (name == "offsets" and predict_offsets) else np.ones(len(mask), bool)


def read_levels(quant: dict, sections: dict[str, np.ndarray], positions: np.ndarray, voxel: float, mask: np.ndarray,
                predict_offsets: bool, err) -> dict[str, np.ndarray]:
    """Scene format 5: per attribute with ``levels``, the stored rows' levels, from ``LEVELS`` (checked: cells per
    axis, levels in range, entries consumed exactly)."""
    names = [k for k in LEVEL_ATTRS if isinstance(quant.get(k), dict) and "levels" in quant[k]]
    if not names:
        return {}
    sec = sections.get(LEVELS)
    if sec is None or sec.dtype != np.int8 or sec.ndim != 1:
        raise err(f"missing or malformed section {LEVELS!r}")
    if sec.size and np.abs(sec.astype(np.int64)).max() > LEVEL_MAX:
        raise err(f"section {LEVELS!r}: a level outside [-{LEVEL_MAX}, {LEVEL_MAX}]")
    out, used, cells = {}, 0, {}
    for k in names:
        info = quant[k]["levels"]
        G, n = (info.get("cells"), info.get("entries")) if isinstance(info, dict) else (None, None)
        if not (isinstance(G, int) and not isinstance(G, bool) and 1 <= G <= MAX_LEVEL_CELLS):
            raise err(f"bad quantisation level cells {G!r}")
        if not (isinstance(n, int) and not isinstance(n, bool) and 0 <= n <= sec.size - used):
            raise err(f"bad quantisation level entries {n!r} for {k}")
        if G not in cells:  # the attributes usually share one grid
            cells[G] = position_cells(positions, voxel, G)
        out[k] = levels_from_entries(sec[used:used + n].astype(np.int64), cells[G], ~mask,
                                     stored_rows(k, mask, predict_offsets), err)
        used += n
    if used != sec.size:
        raise err(f"section {LEVELS!r} is longer than its levels")
    return out


def dequantize(q: np.ndarray, params: dict, name: str, err, levels: np.ndarray | None = None) -> np.ndarray:
    """Inverse of ``quantize``: offset + q * scale in float64, rounded once to float32. With per-cell levels
    (``params["levels"]``; ``levels`` [N]: each column's level), ``offset + (q - zero) * (scale * 2^(level / 4))``."""
    bits = params["bits"]
    if bits == FLOAT_BITS:
        if q.dtype != np.float32:
            raise err(f"section {name!r} must be float32")
        if not np.all(np.isfinite(q)):
            raise err(f"section {name!r} contains NaN or Inf")
        return np.array(q, dtype=np.float32)
    if not (isinstance(bits, int) and 1 <= bits <= 16):
        raise err(f"section {name!r}: bad bit depth {bits!r}")
    want = np.uint8 if bits <= 8 else np.uint16
    if q.dtype != want:
        raise err(f"section {name!r} has dtype {q.dtype}, expected {np.dtype(want)} for {bits} bits")
    off = np.asarray(params["offset"], dtype=np.float64)
    sc = np.asarray(params["scale"], dtype=np.float64)
    if off.shape != (q.shape[0],) or sc.shape != (q.shape[0],):
        raise err(f"section {name!r}: quantisation parameters do not match its {q.shape[0]} channels")
    if not (np.all(np.isfinite(off)) and np.all(np.isfinite(sc)) and np.all(sc >= 0)):
        raise err(f"section {name!r}: quantisation parameters are not finite")
    if int(q.max(initial=0)) > (1 << bits) - 1:
        raise err(f"section {name!r}: value exceeds {bits} bits")
    if "levels" in params:
        zero = np.asarray(params["zero"], dtype=np.int64)
        if zero.shape != (q.shape[0],) or np.abs(zero).max(initial=0) > 1 << 20:
            raise err(f"section {name!r}: bad quantisation zero points")
        if levels is None or levels.shape != (q.shape[1],):
            raise err(f"section {name!r}: quantisation levels do not match its {q.shape[1]} anchors")
        mult = level_multipliers()[levels + LEVEL_MAX]
        x = (off[:, None] + (q.astype(np.float64) - zero[:, None]) * (sc[:, None] * mult[None, :])).astype(np.float32)
    else:
        x = (off[:, None] + q.astype(np.float64) * sc[:, None]).astype(np.float32)
    if not np.all(np.isfinite(x)):
        raise err(f"section {name!r} dequantises to NaN or Inf")
    return x


def quantize(x: np.ndarray, bits: int) -> tuple[np.ndarray, dict]:
    """[C, N] float -> (stored array, parameters). Uniform per channel; bits == 32 stores float32 unchanged."""
    x = np.asarray(x, dtype=np.float32)
    if bits == FLOAT_BITS:
        return np.ascontiguousarray(x), {"bits": FLOAT_BITS}
    levels = (1 << bits) - 1
    xd = x.astype(np.float64)
    if xd.shape[1]:
        lo, hi = xd.min(1), xd.max(1)
    else:
        lo = hi = np.zeros(xd.shape[0])
    scale = np.where(hi > lo, (hi - lo) / levels, 0.0)
    q = np.zeros(xd.shape, dtype=np.float64)
    nz = scale > 0
    q[nz] = np.rint((xd[nz] - lo[nz, None]) / scale[nz, None])
    q = np.clip(q, 0, levels).astype(np.uint8 if bits <= 8 else np.uint16)
    return q, {"bits": int(bits), "offset": [float(v) for v in lo], "scale": [float(v) for v in scale]}


def quantize_step(x: np.ndarray, step: np.ndarray, origin: np.ndarray, levels: np.ndarray | None = None
                  ) -> tuple[np.ndarray, dict]:
    """[C, N] float -> (stored array, parameters) on a given grid per channel, ``origin + k step`` (learned by rate
    training): stored levels ``k - min k``, as many bits as the largest needs. At most 16: a grid too fine for that
    is replaced by the channel's range in 2^16 levels. ``levels`` [N]: per-cell levels (scene format 5), each
    column's grid ``origin + k step 2^(level / 4)``; the parameters then hold ``origin`` and ``zero = -min k``."""
    xd = np.asarray(x, dtype=np.float64)
    step = np.asarray(step, dtype=np.float64)
    origin = np.asarray(origin, dtype=np.float64)
    C = xd.shape[0]
    if step.shape != (C,) or origin.shape != (C,) or not np.all(np.isfinite(step) & (step > 0) & np.isfinite(origin)):
        raise ProxycodecError("quantisation grids must be finite with positive steps, one per channel")
    col = step[:, None] if levels is None else step[:, None] * level_multipliers()[levels + LEVEL_MAX][None, :]
    k = np.rint((xd - origin[:, None]) / col) if xd.shape[1] else np.zeros(xd.shape)
    lo = k.min(1) if xd.shape[1] else np.zeros(C)
    q = k - lo[:, None]
    bits = max(1, int(q.max(initial=0)).bit_length())
    if bits > 16:
        return quantize(x, 16)
    q = q.astype(np.uint8 if bits <= 8 else np.uint16)
    if levels is not None:
        return q, {"bits": bits, "offset": [float(v) for v in origin], "zero": [int(-v) for v in lo],
                   "scale": [float(v) for v in step]}
    return q, {"bits": bits, "offset": [float(v) for v in origin + lo * step], "scale": [float(v) for v in step]}


def grid_to_xyz(ii: np.ndarray, step: float, rule: str, shift=None) -> np.ndarray:
    """Grid coordinates -> float32 positions under ``rule`` ("f64", "f32"); ``shift`` (float64 xyz, "f64" only):
    the grid's node 0."""
    if shift is not None:
        return (np.asarray(shift, dtype=np.float64) + ii.astype(np.float64) * step).astype(np.float32)
    if rule == "f64":
        return (ii.astype(np.float64) * step).astype(np.float32)
    return ii.astype(np.float32) * np.float32(step)


def _section(sections, name, err, shape=None, kinds="f") -> np.ndarray:
    if name not in sections:
        raise err(f"missing section {name!r}")
    a = sections[name]
    if shape is not None and tuple(a.shape) != tuple(shape):
        raise err(f"section {name!r} has shape {tuple(a.shape)}, expected {tuple(shape)}")
    if a.dtype.kind not in kinds:
        raise err(f"section {name!r} has unexpected dtype {a.dtype}")
    return a


def weights_from_sections(prefix, sections, err) -> dict[str, np.ndarray]:
    """The ``prefix/*`` weight arrays as float32 (int8 matrices times their per-row scales)."""
    out = {}
    for k, v in sections.items():
        if not k.startswith(prefix + "/") or k.endswith(QSCALE):
            continue
        if v.dtype == np.int8:
            scale = sections.get(k + QSCALE)
            if scale is None or scale.dtype != np.float32 or v.ndim != 2 or scale.shape != (v.shape[0],):
                raise err(f"section {k!r}: int8 weights need a float32 per-row scale section")
            if not np.all(np.isfinite(scale)):
                raise err(f"section {k!r}: weight scales are not finite")
            out[k[len(prefix) + 1:]] = (v.astype(np.float32) * scale[:, None]).astype(np.float32)
        elif v.dtype in (np.float16, np.float32):
            out[k[len(prefix) + 1:]] = v.astype(np.float32)
        else:
            raise err(f"section {k!r}: weights must be float16, float32 or int8 (with scales)")
    return out


# ---------------------------------------------------------------------------------------------- writing
def grid_positions(pos: np.ndarray, voxel: float, shift=None) -> tuple[np.ndarray, dict] | None:
    """Integer grid coordinates reproducing ``pos`` (float32) exactly, or None when the anchors are off-grid.

    Tries steps voxel / 2^j and two reconstruction rules: "f64" x = f32(i * step) computed in float64 (numpy),
    "f32" x = f32(i) * f32(step) in float32 (what Scaffold-GS's torch code does); then, given a ``shift`` (float64
    xyz: where a scene trained in another frame has its grid's node 0), "f64" x = f32(shift + i * step).
    """
    p64 = pos.astype(np.float64)
    shifts: list = [None]
    try:  # a scene's own metadata: anything but three finite numbers is no shift
        sh = [float(v) for v in shift] if shift is not None else []
        if len(sh) == 3 and all(math.isfinite(v) for v in sh):
            shifts.append(sh)
    except (TypeError, ValueError):
        pass
    for sh in shifts:
        for j in range(GRID_SUBDIVISIONS + 1):
            step = voxel / (1 << j)
            i = np.rint((p64 if sh is None else p64 - np.asarray(sh)) / step)
            if len(i) and np.abs(i).max() >= 2**31 - 1:
                break
            ii = i.astype(np.int64)
            for rule in ("f64", "f32") if sh is None else ("f64",):
                if np.array_equal(grid_to_xyz(ii, step, rule, sh), pos):
                    return ii, {"mode": "grid", "step": step, "rule": rule, **({} if sh is None else {"shift": sh})}
    return None


def morton_order(keys: np.ndarray, *ties: np.ndarray) -> np.ndarray:
    """Stable z-order of [M, 3] non-negative int64 keys (21 bits per axis after a shift), ties by ``ties``."""
    k = keys.astype(np.int64)
    span = int(k.max(initial=0))
    shift = max(0, span.bit_length() - 21)
    k = (k >> shift).astype(np.uint64)
    code = np.zeros(len(k), dtype=np.uint64)
    for b in range(21):
        for a in range(3):
            code |= ((k[:, a] >> np.uint64(b)) & np.uint64(1)) << np.uint64(3 * b + a)
    return np.lexsort(tuple(reversed(ties)) + (code,))


def small_int(a: np.ndarray) -> np.ndarray:
    """``a`` in the smallest signed integer type that holds it."""
    lo, hi = int(a.min(initial=0)), int(a.max(initial=0))
    for dt in (np.int8, np.int16, np.int32, np.int64):
        if np.iinfo(dt).min <= lo and hi <= np.iinfo(dt).max:
            return a.astype(dt)
    raise ProxycodecError("grid coordinates out of range")  # unreachable: |i| < 2^31


@dataclass(frozen=True)
class PositionCoding:
    """How the anchor positions are stored: the stored (Morton) order, the position section, its metadata."""

    order: np.ndarray  # [M] stored order: stored row r is input row order[r]
    sections: dict[str, np.ndarray]
    info: dict  # meta["positions"]


def encode_positions(pos: np.ndarray, voxel: float, coding: str = "delta", shift=None) -> PositionCoding:
    """Exact grid coordinates when a rule reproduces every float32 position, in Morton order: per-axis deltas in the
    smallest integer type ("delta"), or ``coding="octree"`` an octree of them (``proxycodec.octree``; distinct
    positions only, else deltas); off-grid, the float32 positions themselves (lossless) in the Morton order of their
    voxels. One order serves every per-anchor section. ``shift``: the node 0 of a grid the positions may sit on
    instead of the origin's (the scene's ``grid_shift``); used with the octree only (format 6 lists it)."""
    if coding not in POSITION_CODINGS:
        raise ProxycodecError(f"position coding {coding!r}: must be one of {', '.join(POSITION_CODINGS)}")
    grid = grid_positions(pos, voxel, shift if coding == "octree" else None)
    if grid is not None:
        ii, pinfo = grid
        origin = ii.min(0)
        rel = ii - origin
        order = morton_order(rel, rel[:, 0], rel[:, 1], rel[:, 2])
        rel = rel[order]
        base = {**pinfo, "origin": [int(v) for v in origin], "order": "morton"}
        if coding == "octree" and octree.can_code(rel):
            secs, depth = octree.encode(rel)
            return PositionCoding(order, secs, {**base, "coding": "octree", "depth": depth, "coder": octree.CODER})
        if "shift" not in pinfo:  # a shifted grid only as an octree (format 6; the delta files predate it): float32
            deltas = np.diff(rel, axis=0, prepend=np.zeros((1, 3), np.int64)).T  # [3, M]
            return PositionCoding(order, {GRID: small_int(np.ascontiguousarray(deltas))}, {**base, "coding": "delta"})
    lo = pos.astype(np.float64).min(0)
    cell = np.floor((pos.astype(np.float64) - lo) / voxel).astype(np.int64)
    order = morton_order(cell, pos[:, 0], pos[:, 1], pos[:, 2])
    return PositionCoding(order, {XYZ: np.ascontiguousarray(pos[order].T)},
                          {"mode": "float32", "order": "morton", "coding": "plain"})


@dataclass(frozen=True)
class QuantizedAnchors:
    """The stored per-anchor attributes, quantised, and what the decoder will see after dequantisation."""

    sections: dict[str, np.ndarray]  # SCALINGS, PROXY_FEATURES, OFFSETS or PROXY_OFFSETS
    quant: dict  # meta["quant"]: per attribute, bits and per-channel offset/scale
    features: np.ndarray  # [M, F]: the proxies' rows dequantised, the leaves' rows as given
    offsets: np.ndarray  # [M, K, 3]: the stored rows dequantised (the leaves' as given when predicted)
    levels: dict[str, np.ndarray] = field(default_factory=dict)  # format 5: the stored rows' levels, per attribute


def quantize_anchors(features: np.ndarray, offsets: np.ndarray, scalings: np.ndarray, proxy_mask: np.ndarray, *,
                     feature_bits: int, offset_bits: int, scaling_bits: int, predict_offsets: bool,
                     steps: dict | None = None, positions: np.ndarray | None = None,
                     voxel: float | None = None) -> QuantizedAnchors:
    """Arrays in the stored order -> their quantised sections (channel-major: one row per channel). Stored: every
    anchor's scalings, the proxies' features, every anchor's offsets (the proxies' only when ``predict_offsets``).
    ``steps``: per attribute ("features", "scalings", "offsets"), a grid per channel, ``(step, origin)``
    (``quantize_step``), used instead of that attribute's bit depth; or ``(step, origin, levels)`` with a per-cell
    level table (``level_table``; scene format 5), which needs the anchors' ``positions`` and ``voxel``."""
    err = ProxycodecError
    M, K = offsets.shape[:2]
    mask = proxy_mask
    steps = steps or {}
    lv: dict[str, np.ndarray] = {}
    for name, g in steps.items():
        if len(g) > 2:
            lv[name] = anchor_levels(g[2], positions, voxel, ~mask, err)[stored_rows(name, mask, predict_offsets)]

    def quant(x, bits, name):
        if name not in steps:
            return quantize(x, bits)
        q, params = quantize_step(x, steps[name][0], steps[name][1], lv.get(name))
        if "zero" not in params:
            lv.pop(name, None)  # too fine for 16 bits: the channel's range instead (``quantize_step``)
        return q, params

    q_scal, qp_scal = quant(scalings.T, scaling_bits, "scalings")
    q_feat, qp_feat = quant(features[mask].T, feature_bits, "features")
    off_rows = offsets if not predict_offsets else offsets[mask]
    q_off, qp_off = quant(off_rows.reshape(len(off_rows), 3 * K).T, offset_bits, "offsets")
    feat_dq = features.copy()
    feat_dq[mask] = dequantize(q_feat, qp_feat, PROXY_FEATURES, err, lv.get("features")).T
    off_dq = offsets.copy()
    od = dequantize(q_off, qp_off, OFFSETS, err, lv.get("offsets")).T.reshape(-1, K, 3)
    if predict_offsets:
        off_dq[mask] = od
    else:
        off_dq = od
    sections = {SCALINGS: q_scal, PROXY_FEATURES: q_feat, (PROXY_OFFSETS if predict_offsets else OFFSETS): q_off}
    quant = {"scalings": qp_scal, "features": qp_feat, "offsets": qp_off}
    if lv:  # scene format 5: the occupied cells' levels, one section
        entries = []
        for name in (k for k in LEVEL_ATTRS if k in lv):
            G = int(steps[name][2]["cells"])
            e = level_entries(lv[name], position_cells(positions, voxel, G), ~mask,
                              stored_rows(name, mask, predict_offsets))
            quant[name]["levels"] = {"cells": G, "entries": int(e.size)}
            entries.append(e)
        sections[LEVELS] = np.concatenate(entries)
    return QuantizedAnchors(sections, quant, feat_dq, off_dq, lv)


def weight_levels(dtype: str) -> int | None:
    """The largest integer of a ``qN`` weights dtype's grid, ``2^(N-1) - 1`` (q8: 127, q6: 31); None for f16/f32."""
    return (1 << (int(dtype[1:]) - 1)) - 1 if dtype in WEIGHT_DTYPES and dtype.startswith("q") else None


def weights_to_sections(prefix: str, arrays: dict[str, np.ndarray], dtype: str) -> dict[str, np.ndarray]:
    """f32; f16 (where representable); or qN (N = 4..8): matrices as int8 on the grid -L..L, L = 2^(N-1) - 1, with
    a float32 scale per output row (symmetric, ``w = q * scale``, scale = max |w| / L), vectors (biases) as f16.
    Every qN is stored (and read) as q8 is: N < 8 only leaves fewer distinct values for zstd."""
    out = {}
    levels = weight_levels(dtype)
    for k, v in arrays.items():
        v = np.asarray(v, dtype=np.float32)
        if levels and v.ndim == 2:
            scale = (np.abs(v).max(axis=1) / np.float32(levels)).astype(np.float32)
            safe = np.where(scale > 0, scale, 1.0).astype(np.float32)
            out[f"{prefix}/{k}"] = np.clip(np.rint(v / safe[:, None]), -levels, levels).astype(np.int8)
            out[f"{prefix}/{k}{QSCALE}"] = scale
        elif (dtype == "f16" or levels) and np.all(np.abs(v) <= 65504.0):
            out[f"{prefix}/{k}"] = v.astype(np.float16)
        else:
            out[f"{prefix}/{k}"] = v
    return out


def scene_sections(positions: PositionCoding, proxy_mask: np.ndarray, quantized: QuantizedAnchors,
                   decoder_arrays: dict[str, np.ndarray], predictor_arrays: dict[str, np.ndarray],
                   weights_dtype: str) -> dict[str, np.ndarray]:
    """Every section of a scene container, in file order (scene format 1 names: ``pack_weights`` packs them)."""
    sections: dict[str, np.ndarray] = dict(positions.sections)
    sections[PROXY_MASK] = np.packbits(proxy_mask, bitorder="little")
    sections.update(quantized.sections)
    sections.update(weights_to_sections("decoder", decoder_arrays, weights_dtype))
    sections.update(weights_to_sections("predictor", predictor_arrays, weights_dtype))
    return sections


def scene_features(meta: dict) -> list[str]:
    """The sorted ``SCENE_FEATURES`` a scene container's metadata uses (what format 6 lists in ``features``): the
    writer records them, the reader checks a file's list against them."""
    used = {"entropy": "entropy" in meta,
            "levels": any(isinstance(v, dict) and "levels" in v for v in meta["quant"].values()),
            "octree": meta["positions"].get("coding") == "octree",
            "shift": "shift" in meta["positions"],
            "variant": bool(DecoderConfig.from_json(meta["decoder"]).variant())}
    return sorted(k for k, v in used.items() if v)


def scene_metadata(positions: PositionCoding, proxy_mask: np.ndarray, quantized: QuantizedAnchors, *,
                   feat_dim: int, n_offsets: int, voxel_size: float, bounds: np.ndarray, predict_offsets: bool,
                   weights_dtype: str, decoder_config: DecoderConfig, predictor_config: PredictorConfig,
                   cameras: list[Camera], background, **provenance) -> dict:
    """The ``meta`` section of a scene container: what the readers need (counts, voxel size, position coding,
    quantisation, offsets mode, network configurations, cameras, background) plus ``provenance`` (how the encoder
    made it: training, proxy selection, source, encoder; JSON values, stored as given)."""
    M, P = int(len(proxy_mask)), int(proxy_mask.sum())
    meta = {
        "kind": SCENE_KIND,
        "scene_format": (SCENE_FORMAT_OCTREE if positions.info.get("coding") == "octree"
                         else SCENE_FORMAT_LEVELS if any("levels" in v for v in quantized.quant.values())
                         else SCENE_FORMAT_VARIANT if decoder_config.variant() else SCENE_FORMAT),
        "anchors": {"count": M, "proxies": P, "leaves": M - P, "feat_dim": feat_dim, "n_offsets": n_offsets},
        "voxel_size": voxel_size,
        "bounds": np.asarray(bounds, dtype=np.float64).tolist(),
        "positions": positions.info,
        "quant": quantized.quant,
        "offsets": "predicted" if predict_offsets else "stored",
        "weights_dtype": weights_dtype,
        "decoder": decoder_config.to_json(),
        "predictor": predictor_config.to_json(),
        "cameras": [c.to_json() for c in cameras],
        "background": [float(x) for x in background],
        **provenance,
    }
    if meta["scene_format"] == SCENE_FORMAT_OCTREE:
        meta["features"] = scene_features(meta)
    return meta


def zero_dead_offsets(q_off: np.ndarray, qp: dict, dead: np.ndarray, levels: np.ndarray | None = None
                      ) -> np.ndarray:
    """Stored offsets [3K, M] with the dead slots' three channels set to each channel's level nearest 0
    (``levels`` [M]: each anchor's per-cell level, with scene format 5's grids)."""
    q = q_off.copy()
    if qp.get("bits") == FLOAT_BITS:
        zero = np.zeros(q.shape, q.dtype)
    else:
        off = np.asarray(qp["offset"], np.float64)[:, None]
        scale = np.asarray(qp["scale"], np.float64)[:, None]
        z0 = np.zeros_like(off)
        if "levels" in qp:
            scale = scale * level_multipliers()[levels + LEVEL_MAX][None, :]
            z0 = np.asarray(qp["zero"], np.float64)[:, None]
        with np.errstate(divide="ignore", invalid="ignore"):
            zero = np.where(scale > 0, np.round(-off / np.where(scale > 0, scale, 1)) + z0, z0)
        zero = np.clip(np.broadcast_to(zero, q.shape), 0, (1 << int(qp["bits"])) - 1).astype(q.dtype)
    rows = np.repeat(dead.T, 3, axis=0)  # [3K, M]: channel k*3 + c belongs to slot k
    q[rows] = zero[rows]
    return q


# ---------------------------------------------------------------------------------------------- weight packing
WEIGHT_GROUPS = ("decoder", "predictor")
PACKED_DTYPES = ("i1", "f2", "f4")  # int8 matrices, float16 vectors (or f16 weights), float32 row scales/weights
MAX_WEIGHT_VALUES = 1 << 26


def _packed_name(group: str, code: str) -> str:
    return f"{group}/packed.{code}"


def pack_weights(sections: dict[str, np.ndarray]) -> tuple[dict[str, np.ndarray], list]:
    """Scene format 2: the weight sections (``decoder/*``, ``predictor/*``, int8 row scales included) concatenated
    per group and dtype into 1-D sections ``<group>/packed.<i1|f2|f4>``, in their order; returns the new sections
    and the layout ``[[name, dtype code, shape], ...]`` the metadata keeps (``weights_layout``). Fifty-odd small
    sections cost ~80 B of table entry and ~10 B of zstd frame each; six cost a tenth of that."""
    out: dict[str, np.ndarray] = {}
    layout: list = []
    parts: dict[str, list[np.ndarray]] = {}
    for k, v in sections.items():
        group = k.split("/")[0]
        if group not in WEIGHT_GROUPS:
            out[k] = v
            continue
        code = np.dtype(v.dtype).str[1:]
        if code not in PACKED_DTYPES:
            raise ProxycodecError(f"weight section {k!r} has dtype {v.dtype}, which cannot be packed")
        layout.append([k, code, [int(n) for n in v.shape]])
        parts.setdefault(_packed_name(group, code), []).append(np.ascontiguousarray(v).ravel())
    for name, ps in parts.items():
        out[name] = np.concatenate(ps)
    return out, layout


def unpack_weights(meta: dict, arrays: dict[str, np.ndarray], err: ErrorFactory) -> dict[str, np.ndarray]:
    """Inverse of ``pack_weights`` for a scene-format-2 container (format 1 is returned as it is). Every entry of
    the layout is checked (name, dtype, shape) and the packed sections must be consumed exactly."""
    if meta.get("scene_format") == 1:
        return dict(arrays)
    layout = meta.get("weights_layout")
    if not isinstance(layout, list) or len(layout) > 4096:
        raise err("weights_layout is missing or not a list")
    out = {k: v for k, v in arrays.items() if k.split("/")[0] not in WEIGHT_GROUPS}
    used: dict[str, int] = {}
    for entry in layout:
        if not (isinstance(entry, list) and len(entry) == 3 and isinstance(entry[0], str)
                and entry[1] in PACKED_DTYPES and isinstance(entry[2], list) and len(entry[2]) <= 2
                and all(isinstance(n, int) and not isinstance(n, bool) and 0 <= n <= MAX_WEIGHT_VALUES
                        for n in entry[2])):
            raise err(f"bad weights_layout entry {str(entry)[:80]!r}")
        name, code, shape = entry
        group = name.split("/")[0]
        if group not in WEIGHT_GROUPS or name in out:
            raise err(f"bad or repeated weight name {name[:80]!r} in weights_layout")
        src = _packed_name(group, code)
        packed = arrays.get(src)
        if packed is None or packed.ndim != 1 or packed.dtype != np.dtype("<" + code):
            raise err(f"missing or malformed section {src!r}")
        n = math.prod(shape)
        start = used.get(src, 0)
        if start + n > packed.size:
            raise err(f"section {src!r} is shorter than weights_layout says")
        out[name] = packed[start:start + n].reshape(shape)
        used[src] = start + n
    for k, v in arrays.items():
        if k.split("/")[0] in WEIGHT_GROUPS and used.get(k) != v.size:
            raise err(f"section {k!r} does not match weights_layout")
    return out


# ---------------------------------------------------------------------------------------------- reading
def read_scene_container(path: str | os.PathLike) -> Container:
    """Read and verify a scene container (raises ``ContainerError``): CRCs, kind and scene format. The arrays come
    back as scene format 1 names them (format 2's packed weights unpacked)."""
    path = Path(path)
    c = read_container(path)
    if c.meta.get("kind") != SCENE_KIND:
        raise ContainerError(f"not a compressed scene (kind {c.meta.get('kind')!r})", path)
    fmt = c.meta.get("scene_format")
    if fmt not in SUPPORTED_SCENE_FORMATS:
        raise ContainerError(f"scene format {fmt!r} is not supported by this proxycodec (supports "
                             f"{', '.join(map(str, SUPPORTED_SCENE_FORMATS))}); upgrade proxycodec", path)

    def err(m: str) -> ContainerError:
        return ContainerError(m, path)

    return replace(c, arrays=unpack_weights(c.meta, c.arrays, err))


def guarded(fn, err: ErrorFactory, *args):
    """``fn(*args)``, with malformed metadata (a missing key, a wrong type...) and a ``ProxycodecError`` raised
    while building the scene turned into one ``err`` error (a ``ContainerError`` naming the file, when reading)."""
    try:
        return fn(*args)
    except (KeyError, TypeError, ValueError, IndexError, AttributeError, OverflowError) as e:
        if isinstance(e, ProxycodecError):
            if isinstance(e, ContainerError) or not isinstance(err(""), ContainerError):
                raise
            raise err(e.reason) from None
        raise err(f"bad scene metadata ({type(e).__name__}: {e})") from None


@dataclass
class StoredAnchors:
    """What a scene container stores, dequantised, in the stored (Morton) order; leaves not yet regenerated."""

    positions: np.ndarray  # [M, 3] float32
    features: np.ndarray  # [M, F] float32: the proxies' rows; the leaves' rows are zero
    offsets: np.ndarray  # [M, K, 3] float32 (leaves' rows zero when they are predicted)
    scalings: np.ndarray  # [M, 6] float32, log space
    proxy_mask: np.ndarray  # [M] bool
    voxel_size: float
    decoder_config: DecoderConfig
    predictor_config: PredictorConfig


def stored_anchors(meta: dict, sections: dict[str, np.ndarray], err: ErrorFactory) -> StoredAnchors:
    """The stored arrays and the network configurations, checked against each other (no ``guarded`` here)."""
    a = meta["anchors"]
    M, P, Fd, K = (int(a[k]) for k in ("count", "proxies", "feat_dim", "n_offsets"))
    if not (0 < M <= MAX_ANCHORS and 0 < P <= M and a["leaves"] == M - P and 0 < Fd <= 4096 and 0 < K <= 4096):
        raise err(f"bad anchor counts {a}")
    voxel = float(meta["voxel_size"])
    if not (math.isfinite(voxel) and voxel > 0):
        raise err(f"bad voxel size {voxel}")
    # positions
    pinfo = meta["positions"]
    fmt = meta.get("scene_format")
    features = meta.get("features") if fmt == SCENE_FORMAT_OCTREE else None
    if fmt == SCENE_FORMAT_OCTREE:
        if not (isinstance(features, list) and all(isinstance(f, str) for f in features)):
            raise err("scene format 6 needs its list of 'features'")
        unknown = sorted(set(features) - set(SCENE_FEATURES))
        if unknown:
            raise err(f"scene feature(s) {', '.join(map(repr, unknown))} not supported by this proxycodec (supports "
                      f"{', '.join(SCENE_FEATURES)}); upgrade proxycodec")
    coding = pinfo.get("coding")  # absent in files written before codings were named: delta / plain
    if coding not in {"grid": (None, "delta", "octree"), "float32": (None, "plain")}.get(pinfo.get("mode"), (coding,)):
        raise err(f"unknown position coding {coding!r} for mode {pinfo.get('mode')!r}")
    octree_coded = coding == "octree"
    if octree_coded and fmt != SCENE_FORMAT_OCTREE:
        raise err("octree-coded positions need scene format 6")
    if pinfo["mode"] == "grid":
        if octree_coded:
            rel = octree.decode(sections, pinfo["depth"], M, err)
        else:
            d = _section(sections, GRID, err, (3, M), "i").astype(np.int64)
            rel = np.cumsum(d, axis=1).T
        origin = np.asarray([int(v) for v in pinfo["origin"]], dtype=np.int64)
        if origin.shape != (3,):
            raise err("bad grid origin")
        ii = rel + origin
        if len(ii) and np.abs(ii).max() >= 2**31:
            raise err("grid coordinates out of range")
        step = float(pinfo["step"])
        if not (math.isfinite(step) and step > 0) or pinfo["rule"] not in ("f64", "f32"):
            raise err("bad grid step or rule")
        shift = pinfo.get("shift")
        if "shift" in pinfo:
            if not (octree_coded and "shift" in features):
                raise err("a shifted grid needs octree positions and the 'shift' feature")
            if not (isinstance(shift, list) and len(shift) == 3 and pinfo["rule"] == "f64"
                    and all(isinstance(v, (int, float)) and abs(v) < 1e38 for v in shift)):  # NaN fails too
                raise err("bad grid shift")
        pos = grid_to_xyz(ii, step, pinfo["rule"], shift)
    elif pinfo["mode"] == "float32":
        pos = np.ascontiguousarray(_section(sections, XYZ, err, (3, M)).T)
        if pos.dtype != np.float32 or not np.all(np.isfinite(pos)):
            raise err("section 'anchors/xyz' must hold finite float32 values")
    else:
        raise err(f"unknown position mode {pinfo['mode']!r}")
    if not np.all(np.isfinite(pos)):
        raise err("positions are not finite")
    # split
    bits = _section(sections, PROXY_MASK, err, ((M + 7) // 8,), "u")
    mask = np.unpackbits(bits, count=M, bitorder="little").astype(bool)
    if int(mask.sum()) != P:
        raise err(f"proxy mask marks {int(mask.sum())} proxies, metadata says {P}")
    q = meta["quant"]
    if ("entropy" in meta and fmt not in (SCENE_FORMAT_ENTROPY, SCENE_FORMAT_LEVELS, SCENE_FORMAT_OCTREE)) or \
            (fmt == SCENE_FORMAT_ENTROPY and "entropy" not in meta):
        raise err("entropy-coded sections need scene format 4, 5 or 6 and its 'entropy' metadata")
    levels = any(isinstance(v, dict) and "levels" in v for v in q.values())
    if (levels and fmt not in (SCENE_FORMAT_LEVELS, SCENE_FORMAT_OCTREE)) or \
            (fmt == SCENE_FORMAT_LEVELS and not levels):
        raise err("per-cell quantisation levels need scene format 5 or 6, and format 5 needs them")
    if "entropy" in meta:
        if meta["offsets"] != "stored":
            raise err("entropy coding covers stored offsets only")
        sections = {**sections, **entropy_sections(meta["entropy"], sections, pos, voxel, mask, Fd, K, q, err)}

    offsets_mode = meta["offsets"]
    lv = read_levels(q, sections, pos, voxel, mask, offsets_mode == "predicted", err)
    scal = dequantize(_section(sections, SCALINGS, err, (6, M), "uf"), q["scalings"],
                      SCALINGS, err, lv.get("scalings")).T
    feats = np.zeros((M, Fd), dtype=np.float32)
    feats[mask] = dequantize(_section(sections, PROXY_FEATURES, err, (Fd, P), "uf"), q["features"],
                             PROXY_FEATURES, err, lv.get("features")).T
    if offsets_mode == "stored":
        offs = dequantize(_section(sections, OFFSETS, err, (3 * K, M), "uf"), q["offsets"],
                          OFFSETS, err, lv.get("offsets")).T.reshape(M, K, 3)
    elif offsets_mode == "predicted":
        offs = np.zeros((M, K, 3), dtype=np.float32)
        offs[mask] = dequantize(_section(sections, PROXY_OFFSETS, err, (3 * K, P), "uf"), q["offsets"],
                                PROXY_OFFSETS, err, lv.get("offsets")).T.reshape(P, K, 3)
    else:
        raise err(f"unknown offsets mode {offsets_mode!r}")
    # networks
    dcfg = DecoderConfig.from_json(meta["decoder"])
    pcfg = PredictorConfig.from_json(meta["predictor"])
    if (dcfg.feat_dim, dcfg.n_offsets, pcfg.feat_dim, pcfg.n_offsets) != (Fd, K, Fd, K):
        raise err("network configurations do not match the anchors' feature/offset sizes")
    if pcfg.predict_offsets != (offsets_mode == "predicted"):
        raise err("predictor configuration disagrees with the offsets mode")
    if features is not None and set(features) != set(used := scene_features(meta)):
        raise err(f"scene features {sorted(features)} do not match what the file uses ({used})")
    # [D] row-major, as a PLY-loaded scene is: the section layouts are channel-major, and transposed views made every
    # render gather anchors across strides (measured on bonsai: +30 ms per view at any resolution)
    c = np.ascontiguousarray
    return StoredAnchors(c(pos), feats, c(offs), c(scal), mask, voxel, dcfg, pcfg)


def entropy_sections(emeta: dict, sections: dict[str, np.ndarray], pos: np.ndarray, voxel: float,
                     mask: np.ndarray, Fd: int, K: int, quant: dict, err) -> dict[str, np.ndarray]:
    """Scene format 4: the attribute sections (as format 2 stores them, unsigned symbols) from the entropy stream."""
    from . import entropy  # noqa: PLC0415  (constriction is imported only for such files)

    bits = {k: quant[k]["bits"] for k in entropy.NETS}
    coded = emeta.get("bits", bits)  # the depths the stream was coded at (written since format 4): must be the quant's
    if not isinstance(coded, dict) or any(coded.get(k) != b for k, b in bits.items()):
        raise err(f"the entropy stream's bit depths {coded} differ from the quantisation's {bits}")
    a = entropy.decode(emeta, sections, entropy.Context.of(pos, voxel, mask), Fd, K, bits, err)
    P = int(mask.sum())

    def stored(v: np.ndarray, b: int) -> np.ndarray:
        return np.ascontiguousarray((v + (1 << (b - 1))).T).astype(np.uint8 if b <= 8 else np.uint16)

    return {PROXY_FEATURES: stored(a.features[mask], bits["features"]).reshape(Fd, P),
            SCALINGS: stored(a.scalings, bits["scalings"]), OFFSETS: stored(a.offsets, bits["offsets"])}


def scene_extras(meta: dict, proxy_mask: np.ndarray, err: ErrorFactory) -> tuple[list[Camera], tuple, dict]:
    """(stored cameras, background, the scene's metadata with ``proxy_mask`` added)."""
    cams = [Camera.from_json(c) for c in meta.get("cameras", [])]
    bg = tuple(float(x) for x in meta.get("background", (1.0, 1.0, 1.0)))
    if len(bg) != 3:
        raise err("background must have 3 components")
    scene_meta = dict(meta.get("scene", {})) if isinstance(meta.get("scene", {}), dict) else {}
    scene_meta["proxy_mask"] = proxy_mask  # which anchors were proxies (in the stored order)
    return cams, bg, scene_meta
