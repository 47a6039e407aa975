"""Each anchor's nearest proxy (numpy, torch-free): shared by the encoder, the torch decoder and ``proxycodec.lite``."""

from __future__ import annotations

import numpy as np

from .errors import ProxycodecError

#: Below this many (leaf, proxy) pairs the nearest proxy is found by exhaustive search (no scipy import, which
#: costs 0.3-0.8 s in a fresh process on the 2-core machine); above it by a kd-tree. Both give identical results
#: (same formula, same exact tie-breaking). The exhaustive search does ~100M pairs/s (lego's 2.5M: 25 ms).
BRUTE_FORCE_PAIRS = 16_000_000


#: How equidistant proxies are ordered. "index": the smaller index in the given array first (files written before
#: the "ties" field existed; the order then depends on how the anchors are stored, and a trainer's order is not the
#: container's Morton order). "position": the lexicographically smaller (x, y, z) first, whatever the storage order
#: (the index only between proxies at the same position). Anchors sit on a voxel grid, so exact ties are common:
#: on lego (context 4) 9% of the leaves' rows changed with the storage order under "index". "grid": "position", with
#: distances measured on the lattice of 1/GRID_STEPS of ``unit`` (the predictor's ``dist_ref``, the voxel size) from
#: the proxies' lowest corner: positions are rounded to it, so the squared distances are exact integers and a tie
#: stays a tie when the positions are moved and scaled (a conversion trains in a canonical frame and stores world
#: coordinates: under "position" float32 rounding broke the grid's ties differently, and 100% of a 20k-anchor
#: conversion's leaves decoded from other neighbours than they were trained with; 27.07 -> 23.89 dB).
TIES = ("index", "position", "grid")
GRID_STEPS = 16


def _split(positions, proxy_mask, ties: str = "position", unit: float | None = None
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(float64 positions, proxy indices in tie-break order, leaf indices); a leaf without any proxy is an error.
    Every search below prefers the earlier of two equidistant proxies in the returned proxy order. Under "grid" the
    positions returned are lattice coordinates (integers in float64)."""
    if ties not in TIES:
        raise ProxycodecError(f"unknown tie rule {ties!r}; choose from {', '.join(TIES)}")
    p = np.asarray(positions, dtype=np.float64)
    mask = np.asarray(proxy_mask, dtype=bool)
    pidx, leaves = np.flatnonzero(mask), np.flatnonzero(~mask)
    if len(leaves) and not len(pidx):
        raise ProxycodecError("no proxy anchors: every leaf needs a proxy")
    if ties == "grid":
        if unit is None or not (np.isfinite(unit) and unit > 0):
            raise ProxycodecError(f"the grid tie rule needs a positive length unit, got {unit!r}")
        if len(pidx):  # no proxy: no leaf either (else the error above), nothing to measure
            p = np.round((p - p[pidx].min(0)) * (GRID_STEPS / float(unit)))
    if ties in ("position", "grid") and len(pidx) > 1:
        q = p[pidx]
        pidx = pidx[np.lexsort((q[:, 2], q[:, 1], q[:, 0]))]  # stable: the same position keeps index order
    return p, pidx, leaves


def nearest_proxy(positions, proxy_mask, ties: str = "position", *, unit: float | None = None,
                  brute_force_pairs: int = BRUTE_FORCE_PAIRS) -> np.ndarray:
    """[M] int64: index (into ``positions``) of each anchor's nearest proxy; proxies map to themselves.

    Distances are squared Euclidean, computed in float64 as ((a - b)^2).sum() on the given coordinates (under "grid":
    on their lattice coordinates); ties go to the first proxy in ``ties`` order (``TIES``). Encoder and decoder call
    this on the same stored positions with the container's rule, so they always agree; with "position" a trainer's
    anchor order agrees with them too, and with "grid" also a trainer's frame.
    ``positions``: [M, 3] array-like (numpy; ``proxy.nearest_proxy`` also takes tensors). ``unit``: the lattice's
    length unit under "grid".
    """
    p, pidx, leaves = _split(positions, proxy_mask, ties, unit)
    out = np.arange(len(p), dtype=np.int64)
    if len(leaves) == 0:
        return out
    pp = p[pidx]
    if len(leaves) * len(pidx) <= brute_force_pairs:
        cols = [np.ascontiguousarray(pp[:, a]) for a in range(3)]
        rows = max(1, (4 << 20) // len(pidx))  # ~4M pairs per block
        for s in range(0, len(leaves), rows):
            lv = leaves[s:s + rows]
            q = p[lv]
            # ((a - b)^2).sum(-1) one axis at a time: the same float64 operations in the same order, 7x faster
            d = cols[0][None, :] - q[:, 0:1]
            d2 = d * d  # [l, P]
            for a in (1, 2):
                np.subtract(cols[a][None, :], q[:, a:a + 1], out=d)
                d *= d
                d2 += d
            out[lv] = pidx[np.argmin(d2, axis=1)]  # argmin: first (= smallest index) of the minima
        return out
    from scipy.spatial import cKDTree

    tree = cKDTree(pp)
    k = min(16, len(pidx))
    _, cand = tree.query(p[leaves], k=k)
    cand = np.sort(cand.reshape(len(leaves), k), axis=1)  # ascending in the tie-break order
    d2 = ((pp[cand] - p[leaves][:, None, :]) ** 2).sum(-1)  # [L, k], the same formula as above
    best = pidx[cand[np.arange(len(leaves)), np.argmin(d2, axis=1)]]
    # When even the k-th candidate ties with the best, more ties may exist beyond it: resolve those exhaustively.
    for r in np.flatnonzero(d2.max(1) <= d2.min(1)):
        d = ((pp - p[leaves[r]]) ** 2).sum(-1)
        best[r] = pidx[np.argmin(d)]
    out[leaves] = best
    return out


def nearest_proxies(positions, proxy_mask, k: int, ties: str = "position", *, unit: float | None = None,
                    brute_force_pairs: int = BRUTE_FORCE_PAIRS) -> np.ndarray:
    """[M, k] int64: each leaf's ``k`` nearest proxies, nearest first (column 0 is ``nearest_proxy``); a proxy's
    row holds itself k times. Order: squared float64 distance as in ``nearest_proxy``, ties by ``ties``
    (``TIES``); ``k`` larger than the number of proxies repeats the farthest one."""
    if k == 1:
        return nearest_proxy(positions, proxy_mask, ties, unit=unit, brute_force_pairs=brute_force_pairs)[:, None]
    p, pidx, leaves = _split(positions, proxy_mask, ties, unit)
    out = np.repeat(np.arange(len(p), dtype=np.int64)[:, None], k, axis=1)
    if len(leaves) == 0:
        return out
    pp = p[pidx]
    kk = min(k, len(pidx))

    def pick(cand: np.ndarray, d2: np.ndarray) -> np.ndarray:  # cand [l, c] places in pidx, ascending
        order = np.argsort(d2, axis=1, kind="stable")[:, :kk]  # stable: equal distances keep the tie-break order
        sel = pidx[np.take_along_axis(cand, order, 1)]
        return np.concatenate([sel, np.repeat(sel[:, -1:], k - kk, 1)], 1) if kk < k else sel

    if len(leaves) * len(pidx) <= brute_force_pairs:
        rows = max(1, (4 << 20) // len(pidx))
        allc = np.arange(len(pidx))
        for s in range(0, len(leaves), rows):
            lv = leaves[s:s + rows]
            d2 = ((pp[None, :, :] - p[lv][:, None, :]) ** 2).sum(-1)
            out[lv] = pick(np.broadcast_to(allc, d2.shape), d2)
        return out
    from scipy.spatial import cKDTree

    c = min(kk + 16, len(pidx))
    _, cand = cKDTree(pp).query(p[leaves], k=c)
    cand = np.sort(cand.reshape(len(leaves), c), axis=1)
    d2 = ((pp[cand] - p[leaves][:, None, :]) ** 2).sum(-1)
    res = pick(cand, d2)
    # a tie between the k-th nearest and the farthest candidate may hide equal ones beyond: resolve exhaustively
    kth = np.sort(d2, axis=1)[:, kk - 1]
    for r in np.flatnonzero(d2.max(1) <= kth):
        dr = ((pp - p[leaves[r]]) ** 2).sum(-1)
        res[r] = pick(np.arange(len(pidx))[None, :], dr[None, :])[0]
    out[leaves] = res
    return out


def predictor_neighbours(positions, proxy_mask, config, *, brute_force_pairs: int = BRUTE_FORCE_PAIRS) -> np.ndarray:
    """[M, context] the proxies a predictor of ``config`` (``PredictorConfig`` or ``ProxyLeafConfig``) sees per
    anchor, under its tie rule (the lattice unit of "grid": its ``dist_ref``)."""
    return nearest_proxies(positions, proxy_mask, int(getattr(config, "context", 1)), getattr(config, "ties", "index"),
                           unit=getattr(config, "dist_ref", None), brute_force_pairs=brute_force_pairs)
