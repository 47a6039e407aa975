"""The comparison helpers of tests/flips.py, tested: decisions forced across their thresholds by input changes of a
few ulps (what two float32 paths on two machines produce) are accepted; real differences are not, and the
explanation is needed (without it, the forced flips fail the comparison)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import flips
import numpy as np
import pytest

from proxycodec.render._raster_kernels import rasterize_forward
from proxycodec.render.project import ALPHA_MIN, T_MIN

W, H = 48, 40
BG = np.array([0.1, 0.6, 0.3])
ATOL = 1e-5
EPS = 2e-6  # the forced change: a few float32 ulps


def gaussians(n=150, seed=0, opacity=(0.05, 0.95), sigma=3.0):
    """Random 2D Gaussians (float32 arrays, as ``project`` hands them to the compositors)."""
    rng = np.random.default_rng(seed)
    means = rng.uniform(0, 1, (n, 2)) * [W, H] + rng.uniform(-2.0, 2.0, (n, 2))
    L = rng.normal(size=(n, 2, 2)) * sigma
    cov = L @ L.transpose(0, 2, 1) + 0.3 * np.eye(2)
    det = cov[:, 0, 0] * cov[:, 1, 1] - cov[:, 0, 1] ** 2
    g = SimpleNamespace(
        means2d=means, conics=np.stack([cov[:, 1, 1] / det, -cov[:, 0, 1] / det, cov[:, 0, 0] / det], -1),
        opacities=rng.uniform(*opacity, n), colors=rng.uniform(0, 1, (n, 3)), depths=rng.uniform(1.0, 2.0, n),
        width=W, height=H)
    m2 = 2 * np.log(np.maximum(255 * g.opacities, 1.0))
    g.extent = np.sqrt(m2[:, None] * np.stack([cov[:, 0, 0], cov[:, 1, 1]], -1)) + 1.0
    for k in ("means2d", "conics", "opacities", "colors", "depths", "extent"):
        setattr(g, k, np.ascontiguousarray(getattr(g, k), dtype=np.float32))
    return g


def render(g):
    img, alpha = rasterize_forward(g.means2d, g.conics, g.opacities, g.colors, g.depths, g.extent, W, H, BG)[:2]
    return img, alpha


def copy(g, **changes):
    out = SimpleNamespace(**{k: (v.copy() if isinstance(v, np.ndarray) else v) for k, v in vars(g).items()})
    for k, v in changes.items():
        setattr(out, k, v)
    return out


def alpha_at(g, i, x, y):
    """float64 alpha of Gaussian i at pixel (x, y) and its power."""
    a, b, c = g.conics[i].astype(np.float64)
    dx, dy = x + 0.5 - float(g.means2d[i, 0]), y + 0.5 - float(g.means2d[i, 1])
    power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
    return float(g.opacities[i]) * math.exp(power), power


def transmittance_before(g, i, x, y):
    """float64 T in front of Gaussian i at pixel (x, y) (the compositing rules), or None if the pixel ended."""
    T = 1.0
    for j in np.argsort(g.depths, kind="stable"):
        if j == i:
            return T
        al, power = alpha_at(g, j, x, y)
        al = min(0.99, al)
        if power > 0 or al < ALPHA_MIN:
            continue
        if T * (1 - al) < T_MIN:
            return None
        T *= 1 - al
    return None


def assert_agree(a, b, g_a, g_b, **kw):
    kw = {"atol": ATOL, "rtol": 1e-4, "dtol": 1e-5, "max_flips": 4, **kw}
    n = flips.assert_images_agree(a[0], b[0], g_a, g_b, **kw)
    flips.assert_images_agree(a[1], b[1], g_a, g_b, **kw)
    return n


# ---------------------------------------------------------------------------------------------- forced flips
def forced_alpha_flip(g):
    """(A, B, pixel): A and B differ by one Gaussian's opacity, by EPS relative, and that Gaussian's alpha at the
    pixel is above 1/255 in A and below in B, where it changes the image by more than ATOL."""
    for i in np.argsort(g.depths)[:40]:  # Gaussians near the front: T before them is large
        mx, my = g.means2d[i]
        for x in range(W):
            for y in range(H):
                al, power = alpha_at(g, i, x, y)
                if not (power <= 0 and ALPHA_MIN < al < 3 * ALPHA_MIN and al < 0.9):
                    continue
                T = transmittance_before(g, i, x, y)
                if T is None or T < 0.5:
                    continue
                op = np.float32(g.opacities[i] * (1 + EPS) * ALPHA_MIN / al)
                a_op, b_op = g.opacities.copy(), g.opacities.copy()
                a_op[i], b_op[i] = op, np.float32(op * (1 - 2 * EPS))
                A, B = copy(g, opacities=a_op), copy(g, opacities=b_op)
                ra, rb = render(A), render(B)
                if np.abs(ra[0][y, x] - rb[0][y, x]).max() > 10 * ATOL:
                    return A, B, (y, x), ra, rb
    raise AssertionError("no candidate")


def forced_stop_flip(g):
    """As ``forced_alpha_flip`` for the T >= 1e-4 rule: the Gaussian that ends a pixel in A does not in B."""
    for x in range(0, W, 3):
        for y in range(0, H, 3):
            T = 1.0
            for i in np.argsort(g.depths, kind="stable"):
                al, power = alpha_at(g, i, x, y)
                al = min(0.99, al)
                if power > 0 or al < ALPHA_MIN:
                    continue
                if T * (1 - al) < T_MIN:
                    # alpha that puts T after it at T_MIN (1 -+ EPS); possible when T is below 1e-2
                    want = 1.0 - T_MIN / T
                    if ALPHA_MIN * 2 < want < 0.9 * 0.99 and T * want > 10 * ATOL:
                        _, p = alpha_at(g, i, x, y)
                        op = want / math.exp(p)
                        a_op, b_op = g.opacities.copy(), g.opacities.copy()
                        a_op[i] = np.float32(op * (1 + EPS))  # T after < T_MIN: ends the pixel
                        b_op[i] = np.float32(op * (1 - EPS))  # composited
                        if a_op[i] < 0.99:
                            A, B = copy(g, opacities=a_op), copy(g, opacities=b_op)
                            ra, rb = render(A), render(B)
                            if np.abs(ra[0][y, x] - rb[0][y, x]).max() > 10 * ATOL:
                                return A, B, (y, x), ra, rb
                    break
                T *= 1 - al
    raise AssertionError("no candidate")


def test_a_forced_alpha_flip_is_explained_and_a_wrong_colour_is_not():
    g = gaussians()
    A, B, (y, x), ra, rb = forced_alpha_flip(g)
    assert assert_agree(ra, rb, A, B) == 1  # accepted, and it did change a pixel
    assert flips.pixel_margins(A, 1e-4)[y, x] < 1e-5  # the pixel is flagged ...
    quiet = flips.pixel_margins(A, 1e-4) > 1e-3
    assert quiet.mean() > 0.9  # ... and most are far from every threshold
    with pytest.raises(AssertionError, match="no decision within"):  # the explanation is what lets it pass
        assert_agree(ra, rb, A, B, rtol=1e-9)
    # a real difference: one Gaussian's colour, slightly
    col = B.colors.copy()
    col[np.argsort(B.depths)[0]] += np.float32(0.01)
    C = copy(B, colors=col)
    with pytest.raises(AssertionError, match="no decision within"):
        assert_agree(ra, render(C), A, C)
    # or its opacity by 1e-3: not a rounding-sized change
    op = A.opacities.copy()
    op[np.argsort(A.depths)[0]] *= np.float32(1 - 1e-3)
    D = copy(A, opacities=op)
    with pytest.raises(AssertionError, match="no decision within"):
        assert_agree(ra, render(D), A, D)


def test_a_forced_stop_flip_is_explained():
    g = gaussians(300, seed=3, opacity=(0.5, 0.99), sigma=5.0)
    A, B, (y, x), ra, rb = forced_stop_flip(g)
    assert assert_agree(ra, rb, A, B) >= 1
    with pytest.raises(AssertionError, match="no decision within"):
        assert_agree(ra, rb, A, B, rtol=1e-9)


def test_a_forced_depth_swap_is_explained_only_when_depths_may_differ():
    g = gaussians(60, seed=5, opacity=(0.6, 0.9))
    # the two front Gaussians, overlapping, made a near tie: A and B order them differently
    i, j = np.argsort(g.depths)[:2]
    g.means2d[j] = g.means2d[i] + np.float32(1.0)
    d = np.float32(0.5)
    da, db = g.depths.copy(), g.depths.copy()
    da[i], da[j] = d, np.nextafter(d, np.float32(1))
    db[i], db[j] = np.nextafter(d, np.float32(1)), d
    A, B = copy(g, depths=da), copy(g, depths=db)
    ra, rb = render(A), render(B)
    n = assert_agree(ra, rb, A, B, max_flips=W * H)
    assert n > 0
    with pytest.raises(AssertionError, match="no decision within"):
        assert_agree(ra, rb, A, B, dtol=None, max_flips=W * H)  # same-depths mode: not an allowed difference
    with pytest.raises(AssertionError, match="flipped"):
        assert_agree(ra, rb, A, B, max_flips=n - 1)  # and the count is bounded


def test_rows_in_one_set_only_must_be_near_a_threshold():
    g = gaussians()
    view = SimpleNamespace(**{**vars(g), "opacities": g.opacities.copy()})
    view.opacities[3] = np.float32(ALPHA_MIN * (1 + EPS))  # kept, near the 1/255 cull
    m = flips.cull_margins(view)
    keys = np.arange(len(m))
    ia, ib = flips.match_rows(keys, np.delete(keys, 3), m, np.delete(m, 3), 1e-4, 1, "rows")
    assert len(ia) == len(keys) - 1 and np.array_equal(keys[ia], np.delete(keys, 3)[ib])
    with pytest.raises(AssertionError, match="not near a threshold"):
        flips.match_rows(keys, np.delete(keys, 4), m, np.delete(m, 4), 1e-4, 1, "rows")
    with pytest.raises(AssertionError, match="flipped decisions"):
        flips.match_rows(keys, np.delete(keys, 3), m, np.delete(m, 3), 1e-4, 0, "rows")
    # a row present in one path only is an explanation wherever it reaches 1/255, and nowhere else
    pm = flips.pixel_margins(view, 1e-4, flagged=np.arange(len(m)) == 5)
    al = np.array([[alpha_at(view, 5, x, y)[0] for x in range(W)] for y in range(H)])
    assert np.all(pm[al >= ALPHA_MIN] == 0)
    assert np.all((pm < 1e-4) <= ((al >= ALPHA_MIN * (1 - 1e-4)) | (flips.pixel_margins(view, 1e-4) < 1e-4)))
