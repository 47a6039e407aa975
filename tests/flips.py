"""Comparing two renders that agree only to rounding, and where a threshold decision may flip (issue #14).

Two implementations of one float32 computation -- numpy vs torch MLPs, numba's libm vs torch's SLEEF ``exp``, OpenBLAS
vs MKL kernels, AVX2 vs AVX-512 -- agree to rounding, not bit for bit. A value that lies within that rounding of a
threshold can then be decided differently by the two: opacity > 0 (decoder), the frustum test (visible anchors),
the 1/255 opacity cull, the near plane and the footprint test (projection), then per pixel power <= 0,
alpha >= 1/255, T >= 1e-4 and the depth order (compositing). A whole Gaussian then shows in one render and not in the
other, and which values lie that close depends on the machine's kernels: a comparison with a plain tolerance passes
on one machine and fails on another.

The helpers here accept a difference only where such a decision explains it: a decision whose value lies within a
relative ``rtol`` of its threshold in one of the two paths (computed in float64 from that path's own values), and at
most ``max_flips`` of them. Everything else is compared as tightly as the continuous differences allow.
"""

from __future__ import annotations

import math

import numpy as np

from proxycodec.render.project import ALPHA_MAX, ALPHA_MIN, T_MIN

NEAR = 0.01  # ``project_gaussians``' near plane (its default)


def _np(x) -> np.ndarray:
    return (x.detach().cpu().numpy() if hasattr(x, "detach") else np.asarray(x)).astype(np.float64)


# ---------------------------------------------------------------------------------------------- sets of rows
def cull_margins(proj, near: float = NEAR) -> np.ndarray:
    """[N] relative distance of each kept projected row to the nearest of the culls it passed: gated opacity >= 1/255,
    depth > near, and its footprint box (means2d +- extent) reaching into the image on all four sides."""
    m, e = _np(proj.means2d).reshape(-1, 2), _np(proj.extent).reshape(-1, 2)
    op, z = _np(proj.opacities), _np(proj.depths)
    W, H = proj.width, proj.height
    out = [op / ALPHA_MIN - 1.0, (z - near) / near]
    for k, size in ((0, W), (1, H)):
        mag = np.abs(m[:, k]) + e[:, k] + size
        out += [(m[:, k] + e[:, k]) / mag, (size - m[:, k] + e[:, k]) / mag]
    return np.min(np.abs(np.stack(out)), axis=0) if len(op) else np.zeros(0)


def match_rows(keys_a, keys_b, margin_a, margin_b, rtol: float, max_flips: int, what: str):
    """Rows of two sets identified by unique integer keys -> (ia, ib), the positions of the common keys in each (in
    ascending key order). A key in one set only is a flipped decision: accepted when that set's row lies within
    ``rtol`` of its threshold (``margin_*``), at most ``max_flips`` of them."""
    keys_a, keys_b = np.asarray(keys_a), np.asarray(keys_b)
    assert len(np.unique(keys_a)) == len(keys_a) and len(np.unique(keys_b)) == len(keys_b), what
    _, ia, ib = np.intersect1d(keys_a, keys_b, assume_unique=True, return_indices=True)
    flips = 0
    for keys, other, margin, side in ((keys_a, keys_b, margin_a, "first"), (keys_b, keys_a, margin_b, "second")):
        only = np.flatnonzero(~np.isin(keys, other))
        bad = only[~(np.asarray(margin)[only] < rtol)]
        assert bad.size == 0, (f"{what}: {bad.size} row(s) only in the {side} set and not near a threshold: "
                               f"keys {keys[bad][:5]}, margins {np.asarray(margin)[bad][:5]}")
        flips += only.size
    assert flips <= max_flips, f"{what}: {flips} flipped decisions (at most {max_flips} expected)"
    return ia, ib


def frustum_margins(positions, radius, camera, near: float = NEAR) -> np.ndarray:
    """[M] relative distance of each anchor's bounding sphere to the decision of ``decoder.visible_anchors``
    (the sphere against the four side planes through the camera centre and the near plane), in float64."""
    p = _np(positions).reshape(-1, 3) @ np.asarray(camera.rotation, np.float64).T + np.asarray(camera.translation)
    r = _np(radius).reshape(-1)
    W, H, fx, fy, cx, cy = camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy
    planes = np.array([[fx, 0.0, cx], [-fx, 0.0, W - cx], [0.0, fy, cy], [0.0, -fy, H - cy]])
    planes /= np.linalg.norm(planes, axis=1, keepdims=True)
    mag = np.linalg.norm(p, axis=1) + r + near
    side = np.abs(p @ planes.T + r[:, None]).min(1)
    return np.minimum(side, np.abs(p[:, 2] + r - near)) / mag


# ---------------------------------------------------------------------------------------------- pixels
def pixel_margins(proj, rtol: float, dtol: float | None = None, flagged=None) -> np.ndarray:
    """[H, W]: per pixel centre, the smallest relative distance of any compositing decision to its threshold, as the
    compositors make them (``render/reference.py``'s rules), front to back: power <= 0 and alpha >= 1/255 for each
    Gaussian that might reach 1/255 there, T after it >= 1e-4 for each one composited (and the one that ends the
    pixel), and unless ``dtol`` is None the relative depth gap between consecutive ones, scaled by ``rtol / dtol``
    (an order two paths may resolve differently when their depths differ; with identical depths both sort alike).
    Rows in ``flagged`` (bool [N]: present in this path only) count as a decision at distance 0 wherever their alpha
    reaches (1 - rtol)/255. A pixel whose margin is below ``rtol`` may be decided differently; inf where nothing is
    decided. ``proj``: a ``Projected``, or any object with means2d, conics, opacities, depths, width and height
    (torch tensors or numpy arrays)."""
    W, H = proj.width, proj.height
    out = np.full((H, W), np.inf)
    m2d, con = _np(proj.means2d).reshape(-1, 2), _np(proj.conics).reshape(-1, 3)
    op, dep = _np(proj.opacities).reshape(-1), _np(proj.depths).reshape(-1)
    n = len(op)
    if n == 0:
        return out
    flagged = np.zeros(n, bool) if flagged is None else np.asarray(flagged, bool)
    T = np.ones((H, W))
    done = np.zeros((H, W), bool)
    last_d = np.full((H, W), np.nan)  # depth of the last Gaussian composited at each pixel
    floor = (1.0 - rtol) * ALPHA_MIN
    for g in np.argsort(dep, kind="stable"):  # the compositors' order: depth, ties by row
        o = op[g]
        if not o >= floor:  # alpha <= o everywhere: never near 1/255
            continue
        a, b, c = con[g]
        mx, my = m2d[g]
        det = a * c - b * b
        x0, x1, y0, y1 = 0, W, 0, H
        if a > 0 and c > 0 and det > 0 and math.isfinite(mx) and math.isfinite(my):
            thr = 2.0 * math.log(o / floor) + 1e-6  # q <= thr  <=>  o exp(-q/2) >= floor
            rx, ry = math.sqrt(thr * c / det) + 1.0, math.sqrt(thr * a / det) + 1.0
            x0, x1 = max(0, math.floor(mx - rx)), min(W, math.ceil(mx + rx) + 1)
            y0, y1 = max(0, math.floor(my - ry)), min(H, math.ceil(my + ry) + 1)
            if x1 <= x0 or y1 <= y0:
                continue
        dy = (np.arange(y0, y1) + 0.5 - my)[:, None]
        dx = (np.arange(x0, x1) + 0.5 - mx)[None, :]
        power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
        alpha = np.minimum(ALPHA_MAX, o * np.exp(np.minimum(power, 0.0)))
        live = ~done[y0:y1, x0:x1]
        reach = live & (alpha >= floor)
        if not reach.any():
            continue
        mg = out[y0:y1, x0:x1]
        scale = 0.5 * (abs(a) * dx * dx + abs(c) * dy * dy) + np.abs(b * dx * dy)
        with np.errstate(divide="ignore", invalid="ignore"):
            pm = np.where(scale > 0, np.abs(power) / scale, np.inf)
        np.minimum(mg, np.where(reach, pm, np.inf), out=mg)
        np.minimum(mg, np.where(reach, np.abs(alpha / ALPHA_MIN - 1.0), np.inf), out=mg)
        if flagged[g]:
            mg[reach] = 0.0
        comp = reach & (power <= 0) & (alpha >= ALPHA_MIN)
        if not comp.any():
            continue
        Tb = T[y0:y1, x0:x1]
        tn = Tb * (1.0 - alpha)
        np.minimum(mg, np.where(comp, np.abs(tn / T_MIN - 1.0), np.inf), out=mg)
        if dtol is not None:
            ld = last_d[y0:y1, x0:x1]
            d = dep[g]
            with np.errstate(invalid="ignore", divide="ignore"):
                gap = np.abs(d - ld) / np.maximum(np.abs(d), np.abs(ld))
            np.minimum(mg, np.where(comp & ~np.isnan(ld), gap * (rtol / dtol), np.inf), out=mg)
        stop = comp & (tn < T_MIN)
        go = comp & ~stop
        done[y0:y1, x0:x1] |= stop
        Tb[go] = tn[go]
        if dtol is not None:
            ld[go] = dep[g]
    return out


def assert_images_agree(a, b, proj_a, proj_b, *, atol: float, rtol: float, max_flips: int, dtol=None,
                        flagged_a=None, flagged_b=None, what: str = "image") -> int:
    """Images (or [H, W] alpha maps) ``a`` and ``b`` rendered from ``proj_a`` and ``proj_b``: equal to ``atol`` at
    every pixel, except at most ``max_flips`` pixels where a compositing decision lies within ``rtol`` of its threshold
    in one of the two paths (``pixel_margins``). Returns the number of such pixels that differ."""
    a, b = _np(a), _np(b)
    assert a.shape == b.shape, (what, a.shape, b.shape)
    diff = np.abs(a - b)
    diff = diff.max(-1) if diff.ndim == 3 else diff
    assert np.isfinite(diff).all(), what
    bad = np.argwhere(diff > atol)
    if len(bad) == 0:
        return 0
    near = np.minimum(pixel_margins(proj_a, rtol, dtol, flagged_a), pixel_margins(proj_b, rtol, dtol, flagged_b))
    unexplained = [(int(j), int(i), float(diff[j, i]), float(near[j, i])) for j, i in bad if not near[j, i] < rtol]
    assert not unexplained, (f"{what}: {len(unexplained)} pixel(s) differ by more than {atol:g} with no decision "
                             f"within {rtol:g} of its threshold (row, col, diff, margin): {unexplained[:5]}")
    assert len(bad) <= max_flips, f"{what}: {len(bad)} pixels flipped (at most {max_flips} expected)"
    return len(bad)


# ---------------------------------------------------------------------------------------------- whole renders
def _int(x) -> np.ndarray:
    return (x.detach().cpu().numpy() if hasattr(x, "detach") else np.asarray(x)).astype(np.int64)


def gaussian_keys(g, K: int) -> np.ndarray:
    """Neural Gaussians' identities: anchor index * K + slot (torch ``NeuralGaussians`` or ``lite.Gaussians``)."""
    return _int(g.anchor_index) * K + _int(g.slot)


def assert_renders_agree(r_a, r_b, K: int, *, otol: float, rtol: float, dtol, atol: float, max_flips: int,
                         param_rtol: float = 1e-5, param_atol: float = 1e-6, max_set_flips: int = 4,
                         what: str = "") -> int:
    """Two renders of one view (``SceneRender`` or ``lite.LiteRender``) by paths that agree to rounding, stage by
    stage: the same neural Gaussians but for opacities within ``otol`` of 0, with the same parameters (to
    ``param_rtol``, ``param_atol`` times the largest magnitude); the same projected rows but for culls within
    ``rtol`` of their thresholds; images and alpha equal to ``atol`` but where a compositing decision lies within
    ``rtol`` (depth gaps: ``dtol``) of its threshold (``assert_images_agree``). Returns the number of pixels whose
    image a flipped decision changed."""
    g_a, g_b = r_a.gaussians, r_b.gaussians
    k_a, k_b = gaussian_keys(g_a, K), gaussian_keys(g_b, K)
    ia, ib = match_rows(k_a, k_b, np.abs(_np(g_a.opacities)), np.abs(_np(g_b.opacities)), otol, max_set_flips,
                        f"{what}Gaussians (opacity > 0)")
    for name in ("means", "quats", "scales", "opacities", "colors"):
        x, y = _np(getattr(g_a, name))[ia], _np(getattr(g_b, name))[ib]
        scale = max(1.0, float(np.abs(x).max(initial=0.0)))
        np.testing.assert_allclose(y, x, rtol=param_rtol, atol=param_atol * scale, err_msg=f"{what}{name}")
    p_a, p_b = r_a.projected, r_b.projected
    q_a, q_b = k_a[_int(p_a.index)], k_b[_int(p_b.index)]
    match_rows(q_a, q_b, cull_margins(p_a), cull_margins(p_b), rtol, max_set_flips, f"{what}projection culls")
    kw = dict(atol=atol, rtol=rtol, dtol=dtol, max_flips=max_flips, flagged_a=~np.isin(q_a, q_b),
              flagged_b=~np.isin(q_b, q_a))
    n = assert_images_agree(r_a.image, r_b.image, p_a, p_b, what=f"{what}image", **kw)
    assert_images_agree(r_a.alpha, r_b.alpha, p_a, p_b, what=f"{what}alpha", **kw)
    return n
