"""Fused CPU projection: ``project.project_gaussians`` as one numba kernel per direction, with analytic backward.

Exactly the reference's semantics (``project.py`` is the spec and stays the oracle): the same culls (depth, opacity,
footprint, non-finite), the same rows in the same order, the same ``index``, ``extent`` and ``gate``.

Forward (parallel over Gaussians): each Gaussian is computed with the reference's own operations, in its order and
in the input dtype (constants cast to that dtype as torch casts Python scalars; sums left to right as torch's
reductions over 3 and 4 elements do), so float32 inputs give the float32 reference's values: positions, depths and
2D means bit-identical; the rest within the last-ulp differences of ``sqrt``/``exp``/``log`` (torch's CPU kernels,
MKL VML and SLEEF, are not correctly rounded; numba's are libm's), amplified only where det Sigma2D cancels. The
culling decisions therefore agree except for a Gaussian within an ulp of a threshold. Then one compaction
(``np.flatnonzero`` of the visibility mask, a parallel gather).

Backward (parallel over the surviving rows): recomputes the row's forward in the input dtype (so every branch:
the tangent clamp, ``clamp_min`` of det Sigma2D inside the gate's sqrt, ``det.clamp_min(0.09)``, is decided
exactly as in the forward), then the chain rule in float64 at those values: means2d, conics, gated opacities and
depths -> means, quaternions (through the smoothed normalisation), scales and opacities. Masks follow torch's
``clamp`` backward (gradient passes where ``min <= x <= max``). Colours are not touched: ``colors[index]`` is a torch
index, so autograd handles them. Depths are differentiable as in the reference (``z[sel]``), although no rasterizer
gives them a gradient. Culled Gaussians get zero gradient.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit, prange

from .cpu import threads_for
from .project import ALPHA_MIN, DILATION, GATE_DET_FLOOR, QUAT_EPS, GateConfig, Projected, project_gaussians

_PAR = {"parallel": True, "fastmath": False, "cache": True, "nogil": True}
_SER = {"fastmath": False, "cache": True, "nogil": True}

# Constants, in the input dtype (index into ``k``).
(_NEAR, _FAR, _AMIN, _LXN, _LXP, _LYN, _LYP, _FX, _FY, _CX, _CY, _QEPS2, _ONE, _TWO, _DIL, _DD, _PI, _FLOOR,
 _KAPPA, _ETA, _ZERO, _C255, _W, _H) = range(24)
_R = 24  # camera rotation, 9 entries (row-major)
_SH = 33  # shift, 3 entries
_NK = 36

# Per-Gaussian forward values (scratch row, input dtype), what the backward needs.
(_PX, _PY, _PZ, _IZ, _RX, _RY, _TX, _TY, _FXZ, _FYZ, _NRM, _QN, _RQ, _T0, _T1, _U0, _U1, _A, _B, _C, _DETU,
 _AD, _CD, _DRAW, _DET, _IDET, _G, _OP, _SQ, _MX, _MY, _E0, _E1, _CA, _CB, _CC) = (
    0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 15, 24, 27, 30, 33, 36, 37, 38, 39, 40, 41, 42, 43, 44, 45, 46, 47, 48,
    49, 50, 51, 52, 53, 54)
_NW = 55

# Output columns of the forward's full-size buffer.
_NOUT = 10  # mx, my, conic a, b, c, op, z, ext x, ext y, g


@njit(**_SER)
def _isfinite(x):
    return x - x == x - x  # False for inf and NaN, in any float dtype


@njit(**_SER)
def _fwd_one(means, quats, scales, opac, i, k, gate_on, w):
    """The reference's forward for Gaussian i, in k's dtype. Fills w; returns (kept by the cheap culls, visible)."""
    d0 = means[i, 0] - k[_SH]
    d1 = means[i, 1] - k[_SH + 1]
    d2 = means[i, 2] - k[_SH + 2]
    # p_cam = d @ R^T: element j = (d0 R[j,0] + d1 R[j,1]) + d2 R[j,2]
    px = d0 * k[_R + 0] + d1 * k[_R + 1] + d2 * k[_R + 2]
    py = d0 * k[_R + 3] + d1 * k[_R + 4] + d2 * k[_R + 5]
    pz = d0 * k[_R + 6] + d1 * k[_R + 7] + d2 * k[_R + 8]
    w[_PX] = px
    w[_PY] = py
    w[_PZ] = pz
    o = opac[i]
    if not (pz > k[_NEAR] and pz < k[_FAR] and o >= k[_AMIN]
            and _isfinite(px) and _isfinite(py) and _isfinite(pz)):
        return False, False
    one = k[_ONE]
    two = k[_TWO]
    iz = one / pz
    w[_IZ] = iz
    rx = px * iz
    ry = py * iz
    w[_RX] = rx
    w[_RY] = ry
    # torch.clamp(x, lo, hi) = min(max(x, lo), hi), written out in the tensor's dtype
    tx = rx if rx >= k[_LXN] else k[_LXN]
    tx = tx if tx <= k[_LXP] else k[_LXP]
    ty = ry if ry >= k[_LYN] else k[_LYN]
    ty = ty if ty <= k[_LYP] else k[_LYP]
    w[_TX] = tx
    w[_TY] = ty
    fxz = k[_FX] * iz
    fyz = k[_FY] * iz
    w[_FXZ] = fxz
    w[_FYZ] = fyz
    for j in range(3):
        w[_T0 + j] = fxz * (k[_R + j] - tx * k[_R + 6 + j])
        w[_T1 + j] = fyz * (k[_R + 3 + j] - ty * k[_R + 6 + j])
    # quaternion, smoothed normalisation
    qw = quats[i, 0]
    qx = quats[i, 1]
    qy = quats[i, 2]
    qz = quats[i, 3]
    nrm = np.sqrt(qw * qw + qx * qx + qy * qy + qz * qz + k[_QEPS2])
    w[_NRM] = nrm
    qw = qw / nrm
    qx = qx / nrm
    qy = qy / nrm
    qz = qz / nrm
    w[_QN] = qw
    w[_QN + 1] = qx
    w[_QN + 2] = qy
    w[_QN + 3] = qz
    w[_RQ + 0] = one - two * (qy * qy + qz * qz)
    w[_RQ + 1] = two * (qx * qy - qw * qz)
    w[_RQ + 2] = two * (qx * qz + qw * qy)
    w[_RQ + 3] = two * (qx * qy + qw * qz)
    w[_RQ + 4] = one - two * (qx * qx + qz * qz)
    w[_RQ + 5] = two * (qy * qz - qw * qx)
    w[_RQ + 6] = two * (qx * qz - qw * qy)
    w[_RQ + 7] = two * (qy * qz + qw * qx)
    w[_RQ + 8] = one - two * (qx * qx + qy * qy)
    # U = T M with M = R_q S: U[j] = (T[0] M[0,j] + T[1] M[1,j]) + T[2] M[2,j]
    for j in range(3):
        s = scales[i, j]
        m0 = w[_RQ + j] * s
        m1 = w[_RQ + 3 + j] * s
        m2 = w[_RQ + 6 + j] * s
        w[_U0 + j] = w[_T0] * m0 + w[_T0 + 1] * m1 + w[_T0 + 2] * m2
        w[_U1 + j] = w[_T1] * m0 + w[_T1 + 1] * m1 + w[_T1 + 2] * m2
    a = w[_U0] * w[_U0] + w[_U0 + 1] * w[_U0 + 1] + w[_U0 + 2] * w[_U0 + 2]
    b = w[_U0] * w[_U1] + w[_U0 + 1] * w[_U1 + 1] + w[_U0 + 2] * w[_U1 + 2]
    c = w[_U1] * w[_U1] + w[_U1 + 1] * w[_U1 + 1] + w[_U1 + 2] * w[_U1 + 2]
    w[_A] = a
    w[_B] = b
    w[_C] = c
    det_u = a * c - b * b
    w[_DETU] = det_u
    a_d = a + k[_DIL]
    c_d = c + k[_DIL]
    w[_AD] = a_d
    w[_CD] = c_d
    draw = a_d * c_d - b * b
    w[_DRAW] = draw
    det = draw if not (draw < k[_DD]) else k[_DD]  # clamp_min, NaN-propagating
    w[_DET] = det
    idet = one / det
    w[_IDET] = idet
    ca = c_d * idet
    cb = -b * idet
    cc = a_d * idet
    w[_CA] = ca
    w[_CB] = cb
    w[_CC] = cc
    if gate_on:
        du = det_u if not (det_u < k[_ZERO]) else k[_ZERO]
        sq = np.sqrt(du + k[_FLOOR])
        w[_SQ] = sq
        area = k[_PI] * sq
        g = one / (one + np.exp(-(k[_KAPPA] * (area - k[_ETA]))))
    else:
        g = one
    w[_G] = g
    op = o * g
    w[_OP] = op
    mx = k[_FX] * px * iz + k[_CX]
    my = k[_FY] * py * iz + k[_CY]
    w[_MX] = mx
    w[_MY] = my
    v = op * k[_C255]
    v = v if not (v < one) else one
    m2 = two * np.log(v)
    e0 = np.sqrt(m2 * a_d)
    e1 = np.sqrt(m2 * c_d)
    w[_E0] = e0
    w[_E1] = e1
    vis = (op >= k[_AMIN] and mx + e0 > k[_ZERO] and mx - e0 < k[_W] and my + e1 > k[_ZERO] and my - e1 < k[_H]
           and _isfinite(mx) and _isfinite(my) and _isfinite(ca) and _isfinite(cb) and _isfinite(cc))
    return True, vis


@njit(**_PAR)
def _forward(means, quats, scales, opac, k, gate_on, n_chunks, scratch, vis, out):
    n = means.shape[0]
    for ch in prange(n_chunks):
        w = scratch[ch]
        for i in range((n * ch) // n_chunks, (n * (ch + 1)) // n_chunks):
            _, v = _fwd_one(means, quats, scales, opac, i, k, gate_on, w)
            vis[i] = v
            if v:
                out[i, 0] = w[_MX]
                out[i, 1] = w[_MY]
                out[i, 2] = w[_CA]
                out[i, 3] = w[_CB]
                out[i, 4] = w[_CC]
                out[i, 5] = w[_OP]
                out[i, 6] = w[_PZ]
                out[i, 7] = w[_E0]
                out[i, 8] = w[_E1]
                out[i, 9] = w[_G]


@njit(**_PAR)
def _gather(idx, out, means2d, conics, op, depths, ext, gate):
    for r in prange(idx.shape[0]):
        i = idx[r]
        means2d[r, 0] = out[i, 0]
        means2d[r, 1] = out[i, 1]
        conics[r, 0] = out[i, 2]
        conics[r, 1] = out[i, 3]
        conics[r, 2] = out[i, 4]
        op[r] = out[i, 5]
        depths[r] = out[i, 6]
        ext[r, 0] = out[i, 7]
        ext[r, 1] = out[i, 8]
        gate[r] = out[i, 9]


@njit(**_PAR)
def _backward(means, quats, scales, opac, k, gate_on, n_chunks, scratch, idx, g_m2d, g_con, g_op, g_dep,
              d_means, d_quats, d_scales, d_opac):
    """Gradients of the rows ``idx`` (float64 chain at the input-dtype forward values); other rows stay zero."""
    m = idx.shape[0]
    fx = float(k[_FX])
    fy = float(k[_FY])
    for ch in prange(n_chunks):
        w = scratch[ch]
        dU0 = np.empty(3)
        dU1 = np.empty(3)
        dT0 = np.empty(3)
        dT1 = np.empty(3)
        dRq = np.empty(9)
        for r in range((m * ch) // n_chunks, (m * (ch + 1)) // n_chunks):
            i = idx[r]
            _fwd_one(means, quats, scales, opac, i, k, gate_on, w)
            o = float(opac[i])
            g = float(w[_G])
            gop = float(g_op[r])
            # op = o * g
            d_opac[i] = gop * g
            d_detu = 0.0
            if gate_on:
                dg = gop * o
                dsig = dg * (1.0 - g) * g
                dsq = float(k[_PI]) * float(k[_KAPPA]) * dsig
                if w[_DETU] >= k[_ZERO]:  # clamp_min passes the gradient where x >= min
                    d_detu = dsq / (2.0 * float(w[_SQ]))
            a = float(w[_A])
            b = float(w[_B])
            c = float(w[_C])
            a_d = float(w[_AD])
            c_d = float(w[_CD])
            idet = float(w[_IDET])
            gca = float(g_con[r, 0])
            gcb = float(g_con[r, 1])
            gcc = float(g_con[r, 2])
            # conics = (c_d, -b, a_d) * inv_det
            d_idet = gca * c_d - gcb * b + gcc * a_d
            d_cd = gca * idet
            d_ad = gcc * idet
            db = -gcb * idet
            if w[_DRAW] >= k[_DD]:  # det.clamp_min(0.09)
                d_draw = -d_idet * idet * idet
                d_ad += d_draw * c_d
                d_cd += d_draw * a_d
                db -= 2.0 * b * d_draw
            # det_u = a c - b^2 (the gate), a_d = a + 0.3, c_d = c + 0.3
            da = d_ad + d_detu * c
            dc = d_cd + d_detu * a
            db -= 2.0 * b * d_detu
            for j in range(3):
                u0 = float(w[_U0 + j])
                u1 = float(w[_U1 + j])
                dU0[j] = 2.0 * da * u0 + db * u1
                dU1[j] = 2.0 * dc * u1 + db * u0
            # U[j] = sum_i T[i] M[i, j], M[i, j] = Rq[i, j] s[j]
            for t in range(3):
                dT0[t] = 0.0
                dT1[t] = 0.0
            for j in range(3):
                s = float(scales[i, j])
                ds = 0.0
                for t in range(3):
                    rq = float(w[_RQ + 3 * t + j])
                    mij = float(w[_RQ + 3 * t + j] * scales[i, j])
                    dT0[t] += dU0[j] * mij
                    dT1[t] += dU1[j] * mij
                    dm = float(w[_T0 + t]) * dU0[j] + float(w[_T1 + t]) * dU1[j]
                    ds += dm * rq
                    dRq[3 * t + j] = dm * s
                d_scales[i, j] = ds
            # rotation from the normalised quaternion
            qw = float(w[_QN])
            qx = float(w[_QN + 1])
            qy = float(w[_QN + 2])
            qz = float(w[_QN + 3])
            dqw = 2.0 * (-qz * dRq[1] + qy * dRq[2] + qz * dRq[3] - qx * dRq[5] - qy * dRq[6] + qx * dRq[7])
            dqx = 2.0 * (qy * dRq[1] + qz * dRq[2] + qy * dRq[3] - 2.0 * qx * dRq[4] - qw * dRq[5] + qz * dRq[6]
                         + qw * dRq[7] - 2.0 * qx * dRq[8])
            dqy = 2.0 * (-2.0 * qy * dRq[0] + qx * dRq[1] + qw * dRq[2] + qx * dRq[3] + qz * dRq[5] - qw * dRq[6]
                         + qz * dRq[7] - 2.0 * qy * dRq[8])
            dqz = 2.0 * (-2.0 * qz * dRq[0] - qw * dRq[1] + qx * dRq[2] + qw * dRq[3] - 2.0 * qz * dRq[4]
                         + qy * dRq[5] + qx * dRq[6] + qy * dRq[7])
            # qn = q / sqrt(|q|^2 + eps^2): dq = (dqn - qn (dqn . qn)) / nrm
            dot = dqw * qw + dqx * qx + dqy * qy + dqz * qz
            inrm = 1.0 / float(w[_NRM])
            d_quats[i, 0] = (dqw - qw * dot) * inrm
            d_quats[i, 1] = (dqx - qx * dot) * inrm
            d_quats[i, 2] = (dqy - qy * dot) * inrm
            d_quats[i, 3] = (dqz - qz * dot) * inrm
            # T0 = fxz (R0 - tx R2), T1 = fyz (R1 - ty R2)
            tx = float(w[_TX])
            ty = float(w[_TY])
            fxz = float(w[_FXZ])
            fyz = float(w[_FYZ])
            d_fxz = 0.0
            d_fyz = 0.0
            d_tx = 0.0
            d_ty = 0.0
            for j in range(3):
                r0 = float(k[_R + j])
                r1 = float(k[_R + 3 + j])
                r2 = float(k[_R + 6 + j])
                d_fxz += dT0[j] * (r0 - tx * r2)
                d_fyz += dT1[j] * (r1 - ty * r2)
                d_tx -= dT0[j] * r2
                d_ty -= dT1[j] * r2
            d_tx *= fxz
            d_ty *= fyz
            px = float(w[_PX])
            py = float(w[_PY])
            iz = float(w[_IZ])
            gmx = float(g_m2d[r, 0])
            gmy = float(g_m2d[r, 1])
            # means2d = (f p) inv_z + c; fxz = fx inv_z
            d_iz = fx * d_fxz + fy * d_fyz + gmx * fx * px + gmy * fy * py
            dpx = gmx * fx * iz
            dpy = gmy * fy * iz
            # tx = clamp(px inv_z, lo, hi): the gradient passes where lo <= x <= hi
            if w[_RX] >= k[_LXN] and w[_RX] <= k[_LXP]:
                dpx += d_tx * iz
                d_iz += d_tx * px
            if w[_RY] >= k[_LYN] and w[_RY] <= k[_LYP]:
                dpy += d_ty * iz
                d_iz += d_ty * py
            dpz = float(g_dep[r]) - d_iz * iz * iz
            # p_cam = (means - shift) @ R^T
            for j in range(3):
                d_means[i, j] = dpx * float(k[_R + j]) + dpy * float(k[_R + 3 + j]) + dpz * float(k[_R + 6 + j])


# ---------------------------------------------------------------------------------------------------- driver
#: Below this many Gaussians the kernels run on the calling thread only (the pool's wake-up costs more).
_SMALL_WORK = 8_192


def _threads(n: int):
    return threads_for(n, _SMALL_WORK)  # reads the module constant at call time (tests lower it)


def _n_chunks(n: int, threads: int) -> int:
    return max(1, min(4 * threads, n))


def _constants(camera, gate: GateConfig, near: float, far: float, origin, np_dt) -> np.ndarray:
    """Every constant the reference uses, cast to the input dtype as torch casts a Python scalar."""
    W, H = camera.width, camera.height
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    tan_x, tan_y = 0.5 * W / fx, 0.5 * H / fy
    lim_xp, lim_xn = (W - cx) / fx + 0.3 * tan_x, cx / fx + 0.3 * tan_x
    lim_yp, lim_yn = (H - cy) / fy + 0.3 * tan_y, cy / fy + 0.3 * tan_y
    shift = camera.center - (np.zeros(3) if origin is None else torch.as_tensor(origin).detach().double().cpu().numpy())
    k = np.empty(_NK, np.float64)
    k[_NEAR], k[_FAR], k[_AMIN] = near, far, ALPHA_MIN
    k[_LXN], k[_LXP], k[_LYN], k[_LYP] = -lim_xn, lim_xp, -lim_yn, lim_yp
    k[_FX], k[_FY], k[_CX], k[_CY] = fx, fy, cx, cy
    k[_QEPS2], k[_ONE], k[_TWO] = QUAT_EPS**2, 1.0, 2.0
    k[_DIL], k[_DD] = DILATION, DILATION * DILATION
    k[_PI], k[_FLOOR], k[_KAPPA], k[_ETA] = math.pi, GATE_DET_FLOOR, gate.kappa, gate.eta
    k[_ZERO], k[_C255], k[_W], k[_H] = 0.0, 255.0, W, H
    k[_R:_R + 9] = np.asarray(camera.rotation, np.float64).reshape(9)
    k[_SH:_SH + 3] = np.asarray(shift, np.float64).reshape(3)
    return k.astype(np_dt)


class _ProjectCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, opacities, k, gate_on):
        n = means.shape[0]
        np_dt = k.dtype
        mn, qn, sn, on = (t.detach().numpy() for t in (means, quats, scales, opacities))
        vis = np.zeros(n, np.bool_)
        out = np.empty((n, _NOUT), np_dt)
        with _threads(n) as nt:
            nch = _n_chunks(n, nt)
            if n:
                _forward(mn, qn, sn, on, k, gate_on, nch, np.empty((nch, _NW), np_dt), vis, out)
            idx = np.flatnonzero(vis).astype(np.int64)
            m = idx.shape[0]
            m2d, con, op, dep = np.empty((m, 2), np_dt), np.empty((m, 3), np_dt), np.empty(m, np_dt), np.empty(m, np_dt)
            ext, gate = np.empty((m, 2), np_dt), np.empty(m, np_dt)
            if m:
                _gather(idx, out, m2d, con, op, dep, ext, gate)
        ctx.save_for_backward(means, quats, scales, opacities)
        ctx.k, ctx.gate_on, ctx.idx = k, gate_on, idx
        ext_t, gate_t, idx_t = torch.from_numpy(ext), torch.from_numpy(gate), torch.from_numpy(idx)
        ctx.mark_non_differentiable(ext_t, gate_t, idx_t)
        return torch.from_numpy(m2d), torch.from_numpy(con), torch.from_numpy(op), torch.from_numpy(dep), \
            ext_t, gate_t, idx_t

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_m2d, g_con, g_op, g_dep, _g_ext, _g_gate, _g_idx):
        means, quats, scales, opacities = ctx.saved_tensors
        k, idx = ctx.k, ctx.idx
        n, m = means.shape[0], idx.shape[0]
        np_dt = k.dtype

        def upstream(g, shape):
            if g is None:
                return np.zeros(shape)
            return np.ascontiguousarray(g.detach().to(torch.float64).numpy()).reshape(shape)

        gm = upstream(g_m2d, (m, 2))
        gc = upstream(g_con, (m, 3))
        go = upstream(g_op, (m,))
        gd = upstream(g_dep, (m,))
        d_means, d_quats = np.zeros((n, 3), np_dt), np.zeros((n, 4), np_dt)
        d_scales, d_opac = np.zeros((n, 3), np_dt), np.zeros(n, np_dt)
        if m:
            with _threads(m) as nt:
                nch = _n_chunks(m, nt)
                _backward(*(t.detach().numpy() for t in (means, quats, scales, opacities)), k, ctx.gate_on, nch,
                          np.empty((nch, _NW), np_dt), idx, gm, gc, go, gd, d_means, d_quats, d_scales, d_opac)
        return (torch.from_numpy(d_means), torch.from_numpy(d_quats), torch.from_numpy(d_scales),
                torch.from_numpy(d_opac), None, None)


def supports(means, quats, scales, opacities) -> bool:
    """Whether the fused path takes these inputs: CPU tensors of one float dtype (float32 or float64)."""
    dt = means.dtype
    return (dt in (torch.float32, torch.float64)
            and all(t.device.type == "cpu" and t.dtype == dt for t in (means, quats, scales, opacities))
            and means.dim() == 2 and means.shape[1] == 3 and quats.shape == (means.shape[0], 4)
            and scales.shape == (means.shape[0], 3) and opacities.shape == (means.shape[0],))


def project_gaussians_cpu(
    means: torch.Tensor,  # [N, 3] world (or relative to ``origin``)
    quats: torch.Tensor,  # [N, 4]
    scales: torch.Tensor,  # [N, 3] linear
    opacities: torch.Tensor,  # [N]
    colors: torch.Tensor,  # [N, C]
    camera,
    *,
    gate: GateConfig = GateConfig(),
    near: float = 0.01,
    far: float = 1e10,
    origin=None,
) -> Projected:
    """``project.project_gaussians`` (same arguments, same result), fused in numba with an analytic backward.

    Inputs it does not take (another device, mixed or half dtypes) go to the torch reference unchanged.
    """
    if not supports(means, quats, scales, opacities):
        return project_gaussians(means, quats, scales, opacities, colors, camera, gate=gate, near=near, far=far,
                                 origin=origin)
    np_dt = np.float64 if means.dtype == torch.float64 else np.float32
    k = _constants(camera, gate, near, far, origin, np_dt)
    m2d, con, op, dep, ext, g, idx = _ProjectCPU.apply(
        means.contiguous(), quats.contiguous(), scales.contiguous(), opacities.contiguous(), k, bool(gate.enabled))
    return Projected(means2d=m2d, conics=con, opacities=op, colors=colors[idx], depths=dep, extent=ext, index=idx,
                     gate=g, width=camera.width, height=camera.height)
