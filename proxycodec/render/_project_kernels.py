"""The fused CPU projection's numba kernels and their numpy driver, torch-free (``project_cpu.py`` documents them).

``project_cpu.py`` wraps them in a torch autograd Function; ``proxycodec.lite`` calls ``project_forward`` on numpy
arrays directly, so that decoding and rendering a view never imports torch. Both go through the same functions here,
so they give the same bits.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from ._raster_kernels import threads_for
from .project import ALPHA_MIN, DILATION, GATE_DET_FLOOR, QUAT_EPS, GateConfig

_PAR = {"parallel": True, "fastmath": False, "cache": True, "nogil": True}
_SER = {"fastmath": False, "cache": True, "nogil": True}

# Constants, in the input dtype (index into ``k``).
(_NEAR, _FAR, _AMIN, _LXN, _LXP, _LYN, _LYP, _FX, _FY, _CX, _CY, _QEPS2, _ONE, _TWO, _DIL, K_DD, _PI, _FLOOR,
 _KAPPA, _ETA, _ZERO, _C255, _W, _H) = range(24)
_R = 24  # camera rotation, 9 entries (row-major)
_SH = 33  # shift, 3 entries
_AA = 36  # 1: GateConfig.antialiased (the opacity times rho = sqrt(det_u + floor) sqrt(1 / det)), else 0
_NK = 37

# Per-Gaussian forward values (scratch row, input dtype), what the backward needs.
(_PX, _PY, _PZ, _IZ, _RX, _RY, _TX, _TY, _FXZ, _FYZ, _NRM, _QN, _RQ, _T0, _T1, _U0, _U1, _A, _B, _C, W_DETU,
 _AD, _CD, W_DRAW, _DET, _IDET, _G, _OP, _SQ, _MX, _MY, _E0, _E1, _CA, _CB, _CC, _RHO) = (
    0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 15, 24, 27, 30, 33, 36, 37, 38, 39, 40, 41, 42, 43, 44, 45, 46, 47, 48,
    49, 50, 51, 52, 53, 54, 55)
NW = 56

# Output columns of the forward's full-size buffer.
_NOUT = 10  # mx, my, conic a, b, c, op, z, ext x, ext y, g


@njit(**_SER)
def _isfinite(x):
    return x - x == x - x  # False for inf and NaN, in any float dtype


@njit(**_SER)
def forward_one(means, quats, scales, opac, i, k, gate_on, w):
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
    w[W_DETU] = det_u
    a_d = a + k[_DIL]
    c_d = c + k[_DIL]
    w[_AD] = a_d
    w[_CD] = c_d
    draw = a_d * c_d - b * b
    w[W_DRAW] = draw
    det = draw if not (draw < k[K_DD]) else k[K_DD]  # clamp_min, NaN-propagating
    w[_DET] = det
    idet = one / det
    w[_IDET] = idet
    ca = c_d * idet
    cb = -b * idet
    cc = a_d * idet
    w[_CA] = ca
    w[_CB] = cb
    w[_CC] = cc
    aa = k[_AA] != k[_ZERO]
    sq = one
    if gate_on or aa:
        du = det_u if not (det_u < k[_ZERO]) else k[_ZERO]
        sq = np.sqrt(du + k[_FLOOR])
        w[_SQ] = sq
    if gate_on:
        area = k[_PI] * sq
        g = one / (one + np.exp(-(k[_KAPPA] * (area - k[_ETA]))))
    else:
        g = one
    w[_G] = g
    op = o * g
    if aa:
        rho = sq * np.sqrt(idet)
        w[_RHO] = rho
        op = op * rho
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
            _, v = forward_one(means, quats, scales, opac, i, k, gate_on, w)
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
                out[i, 9] = w[_G] * w[_RHO] if k[_AA] != k[_ZERO] else w[_G]


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
def backward_all(means, quats, scales, opac, k, gate_on, n_chunks, scratch, idx, g_m2d, g_con, g_op, g_dep,
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
            forward_one(means, quats, scales, opac, i, k, gate_on, w)
            o = float(opac[i])
            g = float(w[_G])
            gop = float(g_op[r])
            aa = k[_AA] != k[_ZERO]
            # op = o * g (* rho, antialiased: rho = sq sqrt(idet), sq = sqrt(max(det_u, 0) + floor))
            rho = float(w[_RHO]) if aa else 1.0
            d_opac[i] = gop * g * rho
            dsq = 0.0
            d_det_aa = 0.0
            if gate_on:
                dg = gop * o * rho
                dsig = dg * (1.0 - g) * g
                dsq = float(k[_PI]) * float(k[_KAPPA]) * dsig
            if aa:
                drho = gop * o * g
                dsq += drho * np.sqrt(float(w[_IDET]))
                d_det_aa = -0.5 * drho * rho * float(w[_IDET])  # d rho / d det = -rho / (2 det)
            d_detu = 0.0
            if (gate_on or aa) and w[W_DETU] >= k[_ZERO]:  # clamp_min passes the gradient where x >= min
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
            if w[W_DRAW] >= k[K_DD]:  # det.clamp_min(0.09)
                d_draw = -d_idet * idet * idet + d_det_aa
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
SMALL_WORK = 8_192


def n_chunks(n: int, threads: int) -> int:
    return max(1, min(4 * threads, n))


def constants(camera, gate: GateConfig, near: float, far: float, origin, np_dt) -> np.ndarray:
    """Every constant the reference uses, cast to the input dtype as torch casts a Python scalar.

    ``origin``: None, or the world point (float64 [3]) the means are relative to."""
    W, H = camera.width, camera.height
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    tan_x, tan_y = 0.5 * W / fx, 0.5 * H / fy
    lim_xp, lim_xn = (W - cx) / fx + 0.3 * tan_x, cx / fx + 0.3 * tan_x
    lim_yp, lim_yn = (H - cy) / fy + 0.3 * tan_y, cy / fy + 0.3 * tan_y
    shift = camera.center - (np.zeros(3) if origin is None else np.asarray(origin, np.float64))
    k = np.empty(_NK, np.float64)
    k[_NEAR], k[_FAR], k[_AMIN] = near, far, ALPHA_MIN
    k[_LXN], k[_LXP], k[_LYN], k[_LYP] = -lim_xn, lim_xp, -lim_yn, lim_yp
    k[_FX], k[_FY], k[_CX], k[_CY] = fx, fy, cx, cy
    k[_QEPS2], k[_ONE], k[_TWO] = QUAT_EPS**2, 1.0, 2.0
    k[_DIL], k[K_DD] = DILATION, DILATION * DILATION
    k[_PI], k[_FLOOR], k[_KAPPA], k[_ETA] = math.pi, GATE_DET_FLOOR, gate.kappa, gate.eta
    k[_ZERO], k[_C255], k[_W], k[_H] = 0.0, 255.0, W, H
    k[_R:_R + 9] = np.asarray(camera.rotation, np.float64).reshape(9)
    k[_SH:_SH + 3] = np.asarray(shift, np.float64).reshape(3)
    k[_AA] = 1.0 if gate.antialiased else 0.0
    return k.astype(np_dt)


def project_forward(means, quats, scales, opacities, k, gate_on: bool, small: int = SMALL_WORK):
    """The fused forward on C-contiguous numpy arrays of k's dtype -> (means2d, conics, opacities, depths, extent,
    gate, index) of the rows that survive, as ``project_gaussians`` returns them. ``small``: see ``SMALL_WORK``."""
    n = means.shape[0]
    np_dt = k.dtype
    vis = np.zeros(n, np.bool_)
    out = np.empty((n, _NOUT), np_dt)
    with threads_for(n, small) as nt:
        nch = n_chunks(n, nt)
        if n:
            _forward(means, quats, scales, opacities, k, gate_on, nch, np.empty((nch, NW), np_dt), vis, out)
        idx = np.flatnonzero(vis).astype(np.int64)
        m = idx.shape[0]
        m2d, con, op, dep = np.empty((m, 2), np_dt), np.empty((m, 3), np_dt), np.empty(m, np_dt), np.empty(m, np_dt)
        ext, gate = np.empty((m, 2), np_dt), np.empty(m, np_dt)
        if m:
            _gather(idx, out, m2d, con, op, dep, ext, gate)
    return m2d, con, op, dep, ext, gate, idx
