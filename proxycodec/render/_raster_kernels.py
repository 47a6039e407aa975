"""The CPU compositor's numba kernels and their numpy driver, torch-free (``cpu.py`` documents the algorithm).

``cpu.py`` wraps the forward and the backward in a torch autograd Function; ``proxycodec.lite`` calls
``rasterize_forward`` on numpy arrays directly, so that decoding and rendering a view never imports torch.
Both go through the same functions here, so they give the same bits.
"""

from __future__ import annotations

import contextlib
import math

import numba
import numpy as np
from numba import njit, prange

from .project import ALPHA_MAX, ALPHA_MIN, T_MIN

TILE = 16
_TP = TILE * TILE
_PAR = {"parallel": True, "fastmath": False, "cache": True, "nogil": True}
_SER = {"fastmath": False, "cache": True, "nogil": True}

# geo columns (float64, per depth-sorted Gaussian): what binning and the scanlines need.
_MX, _MY, _A, _B, _C, _DET, _THR, _RX, _RY, _FULL = range(10)
_NGEO = 10
# gradient buffer columns: d mean x, d mean y, d conic a, b, c, d opacity, then d colour[C].
N_GRAD = 6


# ---------------------------------------------------------------------------------------------------- binning
@njit(**_SER)
def _tile_hit(geo, g, x0, x1, y0, y1):
    """Can a pixel centre of tile [x0, x1) x [y0, y1) lie inside Gaussian g's (margined) alpha >= 1/255 ellipse?"""
    if geo[g, _FULL] != 0.0:
        return True
    a = geo[g, _A]
    b = geo[g, _B]
    c = geo[g, _C]
    thr = geo[g, _THR]
    dxl = x0 + 0.5 - geo[g, _MX]
    dxh = x1 - 0.5 - geo[g, _MX]
    dyl = y0 + 0.5 - geo[g, _MY]
    dyh = y1 - 0.5 - geo[g, _MY]
    if dxl <= 0.0 <= dxh and dyl <= 0.0 <= dyh:
        return True
    # q is convex: its minimum over the rectangle lies on an edge, at the clamped 1D stationary point.
    best = np.inf
    for k in range(2):
        dx = dxl if k == 0 else dxh
        dy = min(max(-b * dx / c, dyl), dyh)
        q = a * dx * dx + 2.0 * b * dx * dy + c * dy * dy
        best = min(best, q)
        dy = dyl if k == 0 else dyh
        dx = min(max(-b * dy / a, dxl), dxh)
        q = a * dx * dx + 2.0 * b * dx * dy + c * dy * dy
        best = min(best, q)
    return best <= thr


@njit(**_PAR)
def _bin_count(means, conics, opac, colors, extent, order, width, height, tiles_x, tiles_y,
               mxy, con, op, col, geo, trange, count):
    """Gathers the inputs in depth order (mxy, con, op in the input dtype, col in float64), computes each Gaussian's
    ellipse (geo) and tile range, and counts the tiles it is listed in."""
    n = means.shape[0]
    nch = colors.shape[1]
    for g in prange(n):
        src = order[g]
        mxy[g, 0] = means[src, 0]
        mxy[g, 1] = means[src, 1]
        con[g, 0] = conics[src, 0]
        con[g, 1] = conics[src, 1]
        con[g, 2] = conics[src, 2]
        op[g] = opac[src]
        for ch in range(nch):
            col[g, ch] = colors[src, ch]
        count[g] = 0
        trange[g, 0] = 0
        trange[g, 1] = -1
        trange[g, 2] = 0
        trange[g, 3] = -1
        # the reference's box, in its dtype: lo = means2d - ext, hi = means2d + ext
        lx = float(means[src, 0] - extent[src, 0])
        hx = float(means[src, 0] + extent[src, 0])
        ly = float(means[src, 1] - extent[src, 1])
        hy = float(means[src, 1] + extent[src, 1])
        # the reference's tile test: hi > x0 and lo < x1 (x1 = min(x0 + 16, W)), same floats. NaN-safe.
        if not (lx < width and hx > 0.0 and ly < height and hy > 0.0):
            continue
        txa = int(max(0.0, np.floor(lx / TILE)))
        txb = int(min(tiles_x - 1.0, np.ceil(hx / TILE) - 1.0))
        tya = int(max(0.0, np.floor(ly / TILE)))
        tyb = int(min(tiles_y - 1.0, np.ceil(hy / TILE) - 1.0))
        mx = float(mxy[g, 0])
        my = float(mxy[g, 1])
        a = float(con[g, 0])
        b = float(con[g, 1])
        c = float(con[g, 2])
        o = float(op[g])
        det = a * c - b * b
        v = 255.0 * o
        m2 = 2.0 * math.log(v) if v > 1e-300 else -1e300
        # Safety margin on the ellipse: relative, plus a bound on the float32 rounding of the reference's power
        # (~ ulp times the magnitude of its terms over any pixel of a listed tile).
        ex = 0.5 * (hx - lx) + TILE
        ey = 0.5 * (hy - ly) + TILE
        s = (abs(a) + abs(b)) * ex * ex + (abs(c) + abs(b)) * ey * ey
        thr = m2 + 1e-4 * (1.0 + abs(m2)) + 4e-6 * s
        ok = a > 0.0 and c > 0.0 and det > 0.0 and thr < np.inf and math.isfinite(mx) and math.isfinite(my)
        geo[g, _MX] = mx
        geo[g, _MY] = my
        geo[g, _A] = a
        geo[g, _B] = b
        geo[g, _C] = c
        geo[g, _DET] = det
        geo[g, _THR] = thr
        geo[g, _FULL] = 0.0 if ok else 1.0
        if ok:
            if thr < 0.0:  # o < 1/255: alpha <= o never reaches the threshold
                continue
            rx = math.sqrt(thr * c / det)
            ry = math.sqrt(thr * a / det)
            geo[g, _RX] = rx
            geo[g, _RY] = ry
            # tiles holding a pixel centre within the ellipse's box (a necessary condition)
            txa = max(txa, int(max(-1.0, np.floor((mx - rx - 15.5) / TILE))))
            txb = min(txb, int(min(tiles_x + 0.0, np.floor((mx + rx - 0.5) / TILE))))
            tya = max(tya, int(max(-1.0, np.floor((my - ry - 15.5) / TILE))))
            tyb = min(tyb, int(min(tiles_y + 0.0, np.floor((my + ry - 0.5) / TILE))))
        else:
            geo[g, _RX] = np.inf
            geo[g, _RY] = np.inf
        if txb < txa or tyb < tya:
            continue
        trange[g, 0] = txa
        trange[g, 1] = txb
        trange[g, 2] = tya
        trange[g, 3] = tyb
        k = 0
        for ty in range(tya, tyb + 1):
            y0 = ty * TILE
            y1 = min(y0 + TILE, height)
            for tx in range(txa, txb + 1):
                x0 = tx * TILE
                if _tile_hit(geo, g, x0, min(x0 + TILE, width), y0, y1):
                    k += 1
        count[g] = k


@njit(**_PAR)
def _bin_fill(geo, trange, goff, width, height, tiles_x, gm_tile):
    n = geo.shape[0]
    for g in prange(n):
        k = goff[g]
        if goff[g + 1] == k:
            continue
        for ty in range(trange[g, 2], trange[g, 3] + 1):
            y0 = ty * TILE
            y1 = min(y0 + TILE, height)
            for tx in range(trange[g, 0], trange[g, 1] + 1):
                x0 = tx * TILE
                if _tile_hit(geo, g, x0, min(x0 + TILE, width), y0, y1):
                    gm_tile[k] = ty * tiles_x + tx
                    k += 1


@njit(**_PAR)
def _bin_sort(goff, gm_tile, n_tiles, n_chunks):
    """Stable counting sort of the Gaussian-major (depth-ordered) list by tile -> tile_off, isect_g, tm_gm.

    ``tm_gm[k]`` is the Gaussian-major index of tile-major entry k: the backward writes entry k's gradient to that
    row, so that each Gaussian's rows are contiguous for the reduction."""
    n_g = goff.shape[0] - 1
    n_isect = gm_tile.shape[0]
    # chunk by Gaussians (whole Gaussians per chunk keeps the isect -> Gaussian lookup trivial)
    bounds = np.empty(n_chunks + 1, np.int64)
    for ch in range(n_chunks + 1):
        bounds[ch] = (n_g * ch) // n_chunks
    hist = np.zeros((n_chunks, n_tiles), np.int64)
    for ch in prange(n_chunks):
        for k in range(goff[bounds[ch]], goff[bounds[ch + 1]]):
            hist[ch, gm_tile[k]] += 1
    tile_off = np.empty(n_tiles + 1, np.int64)
    run = 0
    for t in range(n_tiles):
        tile_off[t] = run
        for ch in range(n_chunks):
            cnt = hist[ch, t]
            hist[ch, t] = run  # becomes the chunk's write cursor for tile t
            run += cnt
    tile_off[n_tiles] = run
    isect_g = np.empty(n_isect, np.int32)
    tm_gm = np.empty(n_isect, np.int64)
    for ch in prange(n_chunks):
        for g in range(bounds[ch], bounds[ch + 1]):
            for k in range(goff[g], goff[g + 1]):
                t = gm_tile[k]
                pos = hist[ch, t]
                hist[ch, t] = pos + 1
                isect_g[pos] = g
                tm_gm[pos] = k
    return tile_off, isect_g, tm_gm


# ---------------------------------------------------------------------------------------------------- raster
@njit(**_SER)
def _row_span(geo, g, j, x0, x1):
    """Pixel columns [ia, ib] of row j within [x0, x1) that can lie inside Gaussian g's margined ellipse."""
    if geo[g, _FULL] != 0.0:
        return x0, x1 - 1
    a = geo[g, _A]
    dy = j + 0.5 - geo[g, _MY]
    disc = a * geo[g, _THR] - geo[g, _DET] * dy * dy
    if disc < 0.0:
        return 0, -1
    h = math.sqrt(disc) / a
    cx = geo[g, _MX] - geo[g, _B] * dy / a
    ia = max(float(x0), np.ceil(cx - h - 0.5))
    ib = min(float(x1 - 1), np.floor(cx + h - 0.5))
    if ib < ia:
        return 0, -1
    return int(ia), int(ib)


@njit(**_SER)
def _rows(geo, g, y0, y1):
    if geo[g, _FULL] != 0.0:
        return y0, y1 - 1
    my = geo[g, _MY]
    ry = geo[g, _RY]
    ja = max(float(y0), np.ceil(my - ry - 0.5))
    jb = min(float(y1 - 1), np.floor(my + ry - 0.5))
    if jb < ja:
        return 0, -1
    return int(ja), int(jb)


@njit(**_PAR)
def _forward(tile_off, tile_order, isect_g, geo, mxy, con, op, col, pcx, pcy, k_dt, t_stop, bg, width, height,
             tiles_x, img, alpha_out, t_out, nc_out):
    """k_dt = (0.5, 1/255, 0.99, 1) in the input dtype; t_stop: float64 T below which the reference stops.
    ``tile_order``: tiles by decreasing list length (dynamic scheduling balances the threads)."""
    n_tiles = tile_off.shape[0] - 1
    nch = col.shape[1]
    half, amin, amax, one = k_dt[0], k_dt[1], k_dt[2], k_dt[3]
    for q in prange(n_tiles):
        t = tile_order[q]
        tyi = t // tiles_x
        txi = t - tyi * tiles_x
        x0 = txi * TILE
        y0 = tyi * TILE
        x1 = min(x0 + TILE, width)
        y1 = min(y0 + TILE, height)
        s = tile_off[t]
        e = tile_off[t + 1]
        if s == e:
            for j in range(y0, y1):
                for i in range(x0, x1):
                    for ch in range(nch):
                        img[j, i, ch] = bg[ch]
                    alpha_out[j, i] = 0.0
                    t_out[j, i] = 1.0
                    nc_out[j, i] = 0
            continue
        T = np.ones(_TP)
        acc = np.zeros((_TP, nch))
        last = np.zeros(_TP, np.int32)
        done = np.zeros(_TP, np.bool_)
        n_live = (x1 - x0) * (y1 - y0)
        for k in range(s, e):
            g = isect_g[k]
            mxd = mxy[g, 0]
            myd = mxy[g, 1]
            ad = con[g, 0]
            bd = con[g, 1]
            cd = con[g, 2]
            od = op[g]
            ja, jb = _rows(geo, g, y0, y1)
            for j in range(ja, jb + 1):
                ia, ib = _row_span(geo, g, j, x0, x1)
                if ib < ia:
                    continue
                dy = pcy[j] - myd
                base = (j - y0) * TILE - x0
                for i in range(ia, ib + 1):
                    p = base + i
                    if done[p]:
                        continue
                    dx = pcx[i] - mxd
                    power = -half * (ad * dx * dx + cd * dy * dy) - bd * dx * dy
                    if not (power <= 0):
                        continue
                    v = od * np.exp(power)
                    alpha = min(amax, v)
                    if not (alpha >= amin):
                        continue
                    tn = T[p] * float(one - alpha)
                    if tn < t_stop:
                        done[p] = True
                        n_live -= 1
                        continue
                    w = float(alpha) * T[p]
                    for ch in range(nch):
                        acc[p, ch] += w * col[g, ch]
                    T[p] = tn
                    last[p] = k - s + 1
            if n_live == 0:
                break
        for j in range(y0, y1):
            for i in range(x0, x1):
                p = (j - y0) * TILE + i - x0
                for ch in range(nch):
                    img[j, i, ch] = acc[p, ch] + T[p] * bg[ch]
                alpha_out[j, i] = 1.0 - T[p]
                t_out[j, i] = T[p]
                nc_out[j, i] = last[p]


@njit(**_PAR)
def backward_tiles(tile_off, tile_order, isect_g, tm_gm, geo, mxy, con, op, col, pcx, pcy, k_dt, bg, width, height,
              tiles_x, t_fin, nc, g_img, g_alpha, gbuf):
    """Writes the gradient of tile-major entry k to gbuf row tm_gm[k] (Gaussian-major)."""
    n_tiles = tile_off.shape[0] - 1
    nch = col.shape[1]
    half, amin, amax, one = k_dt[0], k_dt[1], k_dt[2], k_dt[3]
    for q in prange(n_tiles):
        t = tile_order[q]
        s = tile_off[t]
        e = tile_off[t + 1]
        if s == e:
            continue
        tyi = t // tiles_x
        txi = t - tyi * tiles_x
        x0 = txi * TILE
        y0 = tyi * TILE
        x1 = min(x0 + TILE, width)
        y1 = min(y0 + TILE, height)
        T = np.ones(_TP)
        TN = np.ones(_TP)
        R = np.zeros((_TP, nch))
        gC = np.zeros((_TP, nch))
        gA = np.zeros(_TP)
        ncl = np.zeros(_TP, np.int64)
        d_col = np.zeros(nch)
        max_nc = 0
        for j in range(y0, y1):
            for i in range(x0, x1):
                p = (j - y0) * TILE + i - x0
                T[p] = t_fin[j, i]
                TN[p] = t_fin[j, i]
                gA[p] = g_alpha[j, i]
                ncl[p] = nc[j, i]
                max_nc = max(max_nc, nc[j, i])
                for ch in range(nch):
                    R[p, ch] = bg[ch]
                    gC[p, ch] = g_img[j, i, ch]
        for lk in range(max_nc - 1, -1, -1):
            k = s + lk
            g = isect_g[k]
            mxd = mxy[g, 0]
            myd = mxy[g, 1]
            ad = con[g, 0]
            bd = con[g, 1]
            cd = con[g, 2]
            od = op[g]
            d_mx = 0.0
            d_my = 0.0
            d_a = 0.0
            d_b = 0.0
            d_c = 0.0
            d_o = 0.0
            for ch in range(nch):
                d_col[ch] = 0.0
            ja, jb = _rows(geo, g, y0, y1)
            for j in range(ja, jb + 1):
                ia, ib = _row_span(geo, g, j, x0, x1)
                if ib < ia:
                    continue
                dy = pcy[j] - myd
                base = (j - y0) * TILE - x0
                for i in range(ia, ib + 1):
                    p = base + i
                    if lk >= ncl[p]:
                        continue
                    dx = pcx[i] - mxd
                    power = -half * (ad * dx * dx + cd * dy * dy) - bd * dx * dy
                    if not (power <= 0):
                        continue
                    ex = np.exp(power)
                    v = od * ex
                    alpha = min(amax, v)
                    if not (alpha >= amin):
                        continue
                    al = float(alpha)
                    om = float(one - alpha)
                    t_i = T[p] / om
                    dot = 0.0
                    w = al * t_i
                    for ch in range(nch):
                        cg = col[g, ch]
                        dot += (cg - R[p, ch]) * gC[p, ch]
                        d_col[ch] += w * gC[p, ch]
                        R[p, ch] = al * cg + om * R[p, ch]
                    T[p] = t_i
                    if v <= amax:  # clamp passes the gradient (torch.clamp: input <= max)
                        d_al = t_i * dot + gA[p] * TN[p] / om
                        d_o += d_al * float(ex)
                        d_p = d_al * al
                        fdx = float(dx)
                        fdy = float(dy)
                        d_mx += d_p * (float(ad) * fdx + float(bd) * fdy)
                        d_my += d_p * (float(bd) * fdx + float(cd) * fdy)
                        d_a += -0.5 * d_p * fdx * fdx
                        d_b += -d_p * fdx * fdy
                        d_c += -0.5 * d_p * fdy * fdy
            r = tm_gm[k]
            gbuf[r, 0] = d_mx
            gbuf[r, 1] = d_my
            gbuf[r, 2] = d_a
            gbuf[r, 3] = d_b
            gbuf[r, 4] = d_c
            gbuf[r, 5] = d_o
            for ch in range(nch):
                gbuf[r, N_GRAD + ch] = d_col[ch]


@njit(**_PAR)
def reduce_rows(goff, order, gbuf, out):
    """out[order[g]] = sum of Gaussian g's gradient rows (float64 sums, stored in out's dtype)."""
    n = goff.shape[0] - 1
    m = gbuf.shape[1]
    acc = np.zeros((n, m))
    for g in prange(n):
        for k in range(goff[g], goff[g + 1]):
            for c in range(m):
                acc[g, c] += gbuf[k, c]
        dst = order[g]
        for c in range(m):
            out[dst, c] = acc[g, c]


@njit(**_SER)
def _radix_argsort(keys, nbytes):
    """Stable LSD radix argsort of unsigned integer keys (the low ``nbytes`` bytes); skips uniform digits."""
    n = keys.shape[0]
    idx = np.arange(n).astype(np.int64)
    tmp = np.empty(n, np.int64)
    kcur = keys.copy()
    ktmp = np.empty_like(keys)
    cnt = np.empty(256, np.int64)
    for byte in range(nbytes):
        shift = np.uint64(8 * byte)
        cnt[:] = 0
        for i in range(n):
            cnt[(kcur[i] >> shift) & np.uint64(255)] += 1
        if cnt.max() == n:
            continue
        run = 0
        for d in range(256):
            c = cnt[d]
            cnt[d] = run
            run += c
        for i in range(n):
            d = (kcur[i] >> shift) & np.uint64(255)
            pos = cnt[d]
            cnt[d] = pos + 1
            tmp[pos] = idx[i]
            ktmp[pos] = kcur[i]
        idx, tmp = tmp, idx
        kcur, ktmp = ktmp, kcur
    return idx


# ---------------------------------------------------------------------------------------------------- driver
def _stop_threshold(np_dtype) -> float:
    """float64 T below which ``dtype(T) < dtype(T_MIN)``: the reference compares its float64-accumulated cumprod
    after rounding to the input dtype (round to nearest: the midpoint below dtype(T_MIN))."""
    t = np_dtype.type(T_MIN)
    below = np.nextafter(t, np_dtype.type(0))
    return float((float(t) + float(below)) / 2.0) if np_dtype != np.float64 else float(T_MIN)


#: Below this much work (Gaussians + pixels) the kernels run on the calling thread only: waking the pool and its
#: barriers would cost more than the work (and a lot more on a loaded machine).
_SMALL_WORK = 16_384


@contextlib.contextmanager
def threads_for(work: int, small: int = _SMALL_WORK):
    """Thread count for the next kernels (numba's setting is thread-local): one thread below ``small`` units of
    work, else the pool's. Yields the count in force."""
    prev = numba.get_num_threads()
    numba.set_num_threads(1 if work < small else prev)
    try:
        yield numba.get_num_threads()
    finally:
        numba.set_num_threads(prev)


def per_tile_threads():
    """Dynamic scheduling, one tile at a time: tiles differ wildly in cost. Per-Gaussian loops (binning, the
    gradient reduction) keep numba's default static chunks: handing out 100k tasks one by one cost 280 ms."""
    return numba.parallel_chunksize(1)


def _n_chunks() -> int:
    return max(1, 4 * numba.get_num_threads())


class Binned:
    """Depth-sorted inputs as numpy arrays plus the tile lists: everything the backward needs."""

    __slots__ = (
        "col",
        "con",
        "geo",
        "goff",
        "isect_g",
        "k_dt",
        "mxy",
        "n_isect",
        "op",
        "order",
        "pcx",
        "pcy",
        "tile_off",
        "tile_order",
        "tiles_x",
        "tiles_y",
        "tm_gm",
    )


def depth_order(depths: np.ndarray) -> np.ndarray:
    """``torch.sort(depths, stable=True).indices`` (the reference's order), by a radix sort of the float bits:
    sign-flipped bits order like the floats; -0.0 is folded into +0.0 and NaNs go last, as torch's sort does."""
    d = np.asarray(depths)
    if d.dtype == np.float32:
        ui, nbytes, top = np.uint32, 4, np.uint32(1 << 31)
    else:
        d = d.astype(np.float64, copy=False)
        ui, nbytes, top = np.uint64, 8, np.uint64(1 << 63)
    d = d + d.dtype.type(0.0)  # -0.0 -> +0.0
    u = d.view(ui)
    key = np.where(u & top, ~u, u | top)
    key[np.isnan(d)] = np.iinfo(ui).max
    return _radix_argsort(key.astype(np.uint64), nbytes)


def bin_gaussians(means2d, conics, opacities, colors, depths, extent, width, height) -> Binned:
    """Inputs: numpy arrays, means2d/conics/opacities/colors C-contiguous in one float dtype (the compute dtype)."""
    np_dt = means2d.dtype
    b = Binned()
    b.order = depth_order(depths)
    n = means2d.shape[0]
    nch = colors.shape[1]
    b.pcx = np.arange(width, dtype=np_dt) + np_dt.type(0.5)
    b.pcy = np.arange(height, dtype=np_dt) + np_dt.type(0.5)
    b.k_dt = np.array([0.5, ALPHA_MIN, ALPHA_MAX, 1.0], dtype=np_dt)
    b.tiles_x = (width + TILE - 1) // TILE
    b.tiles_y = (height + TILE - 1) // TILE
    b.mxy = np.empty((n, 2), np_dt)
    b.con = np.empty((n, 3), np_dt)
    b.op = np.empty(n, np_dt)
    b.col = np.empty((n, nch), np.float64)
    b.geo = np.empty((n, _NGEO), np.float64)
    trange = np.empty((n, 4), np.int64)
    count = np.empty(n, np.int64)
    _bin_count(means2d, conics, opacities, colors, np.ascontiguousarray(extent), b.order, width, height,
               b.tiles_x, b.tiles_y, b.mxy, b.con, b.op, b.col, b.geo, trange, count)
    b.goff = np.zeros(n + 1, np.int64)
    np.cumsum(count, out=b.goff[1:])
    b.n_isect = int(b.goff[-1])
    gm_tile = np.empty(b.n_isect, np.int64)
    _bin_fill(b.geo, trange, b.goff, width, height, b.tiles_x, gm_tile)
    b.tile_off, b.isect_g, b.tm_gm = _bin_sort(b.goff, gm_tile, b.tiles_x * b.tiles_y, _n_chunks())
    b.tile_order = np.argsort(-np.diff(b.tile_off), kind="stable")
    return b


def rasterize_forward(means2d, conics, opacities, colors, depths, extent, width: int, height: int, bg64):
    """Composite N >= 1 projected Gaussians (numpy arrays, as ``bin_gaussians`` takes them; ``bg64``: float64 [C]).

    Returns (image [H, W, C], alpha [H, W]) in the compute dtype, then what the backward needs: the final
    transmittance (float64 [H, W]), the per-pixel count of contributors (int32 [H, W]) and the binning.
    """
    n = means2d.shape[0]
    nch = colors.shape[1]
    with threads_for(n + width * height):
        b = bin_gaussians(means2d, conics, opacities, colors, depths, extent, width, height)
        np_dt = b.mxy.dtype
        img = np.empty((height, width, nch), np_dt)
        alpha = np.empty((height, width), np_dt)
        t_fin = np.empty((height, width), np.float64)
        nc = np.empty((height, width), np.int32)
        with per_tile_threads():
            _forward(b.tile_off, b.tile_order, b.isect_g, b.geo, b.mxy, b.con, b.op, b.col, b.pcx, b.pcy,
                     b.k_dt, _stop_threshold(np_dt), bg64, width, height, b.tiles_x, img, alpha, t_fin, nc)
    return img, alpha, t_fin, nc, b
