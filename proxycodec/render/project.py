"""EWA projection of 3D Gaussians to the 2D interface every rasterizer backend consumes, with the pixel coverage gate.

Device-agnostic, differentiable PyTorch. This is the split gsplat uses: everything up to 2D means, conics and gated
opacities lives here (autograd gives the gradients, the gate's included: supplement eq. 17-20); backends only
composite. Culling happens here, before any sorting: Gaussians behind the near plane, whose gated opacity is below
1/255, or whose footprint misses the image never reach a rasterizer.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..devices import upload

if TYPE_CHECKING:
    import torch

# torch is imported inside the functions: the constants and GateConfig here are shared with torch-free code
# (the numba kernels, ``proxycodec.lite``), which must not pay for importing torch.

#: 3DGS's low-pass dilation of the projected covariance (pixels^2).
DILATION = 0.3
#: Compositing thresholds shared by every backend (3DGS values).
ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4
#: Floor under det(Sigma2D) inside the gate's sqrt (pixels^4): keeps dA/dSigma = (pi/2) adj(Sigma)/sqrt(det) bounded
#: for needle-thin and flat Gaussians. sqrt(floor) = 0.01 px^2, far below eta = 0.25, where the gate is flat anyway.
GATE_DET_FLOOR = 1e-4
#: Smoothing under quaternion normalisation: a zero quaternion becomes the identity rotation, gradients stay bounded.
QUAT_EPS = 1e-4


@dataclass(frozen=True)
class GateConfig:
    """What a Gaussian's footprint in pixels does to its opacity.

    The pixel coverage gate g = sigmoid(kappa (A - eta)), A = pi sqrt(det Sigma2D) in pixels^2 (supplement 7.5),
    when ``enabled``. ``antialiased``: also gsplat's ``rasterize_mode="antialiased"`` (Mip-Splatting's 2D filter):
    the opacity times rho = sqrt(det Sigma2D / det(Sigma2D + 0.3 I)), so that the dilation keeps a Gaussian's
    integral instead of adding to it: a sub-pixel Gaussian then weighs what it covers. The two multiply."""

    enabled: bool = True
    kappa: float = 4.0
    eta: float = 0.25
    antialiased: bool = False

    def to_json(self) -> dict:
        d = {"enabled": self.enabled, "kappa": self.kappa, "eta": self.eta}
        if self.antialiased:  # written only when on: scenes without it keep their bytes
            d["antialiased"] = True
        return d

    @staticmethod
    def from_json(d: dict) -> "GateConfig":
        return GateConfig(bool(d.get("enabled", True)), float(d.get("kappa", 4.0)), float(d.get("eta", 0.25)),
                          bool(d.get("antialiased", False)))


@dataclass
class Projected:
    """The 2D interface: one row per Gaussian that survived culling, in no particular order.

    ``index`` maps each row back to the input Gaussian. ``extent`` is the half-size (pixels) of the axis-aligned box
    outside which the Gaussian's alpha is below 1/255 everywhere: backends bin by it, and since it is conservative,
    the image does not depend on how a backend bins.
    """

    means2d: torch.Tensor  # [N, 2] pixels, pixel (i, j) centred at (i + 0.5, j + 0.5)
    conics: torch.Tensor  # [N, 3] (a, b, c) of the inverse dilated covariance
    opacities: torch.Tensor  # [N] gated opacity alpha * g
    colors: torch.Tensor  # [N, C]
    depths: torch.Tensor  # [N] camera-space z
    extent: torch.Tensor  # [N, 2] half-widths in pixels (no gradient)
    index: torch.Tensor  # [N] long
    gate: torch.Tensor  # [N] the factor the footprint puts on the opacity: the gate g (times rho when antialiased)
    width: int
    height: int

    @property
    def count(self) -> int:
        return int(self.means2d.shape[0])


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """[N, 4] (w, x, y, z), any norm -> [N, 3, 3]. Zero quaternions map to the identity, with bounded gradients."""
    import torch

    q = quats / torch.sqrt((quats * quats).sum(-1, keepdim=True) + QUAT_EPS**2)
    w, x, y, z = q.unbind(-1)
    R = torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    )
    return R.reshape(quats.shape[:-1] + (3, 3))


def covariance_3d(quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """Sigma = R S S^T R^T from quaternions [N,4] and linear scales [N,3] -> [N,3,3]."""
    M = quat_to_rotmat(quats) * scales[..., None, :]
    return M @ M.transpose(-1, -2)


def aa_compensation(det_sigma2d: torch.Tensor, det_dilated: torch.Tensor) -> torch.Tensor:
    """rho = sqrt(det Sigma2D) * sqrt(1 / det(Sigma2D + 0.3 I)) (``GateConfig.antialiased``), the undilated det
    clamped at 0 and floored by ``GATE_DET_FLOOR`` as in the gate (a bounded gradient for flat Gaussians; rho >= 0.03
    there, where the gate is ~0 anyway). ``det_dilated``: the clamped dilated det the conics invert."""
    import torch

    return torch.sqrt(det_sigma2d.clamp_min(0.0) + GATE_DET_FLOOR) * torch.sqrt(1.0 / det_dilated)


def coverage_gate(det_sigma2d: torch.Tensor, gate: GateConfig) -> torch.Tensor:
    """g(A) with A = pi sqrt(det Sigma2D); ``det_sigma2d`` is the det of the undilated projected covariance."""
    import torch

    if not gate.enabled:
        return torch.ones_like(det_sigma2d)
    area = math.pi * torch.sqrt(det_sigma2d.clamp_min(0.0) + GATE_DET_FLOOR)
    return torch.sigmoid(gate.kappa * (area - gate.eta))


def project_gaussians(
    means: torch.Tensor,  # [N, 3] world
    quats: torch.Tensor,  # [N, 4]
    scales: torch.Tensor,  # [N, 3] linear
    opacities: torch.Tensor,  # [N] in [0, 1]
    colors: torch.Tensor,  # [N, C]
    camera,  # proxycodec.camera.Camera at the resolution to render
    *,
    gate: GateConfig = GateConfig(),
    near: float = 0.01,
    far: float = 1e10,
    origin=None,
) -> Projected:
    """``means`` are world positions, or positions relative to ``origin`` (world axes) when it is given.

    Points are moved into camera coordinates as ``(means - (c - origin)) @ R^T`` with the camera centre ``c``
    subtracted first (in float64 for the offset), not ``R p + t``: at coordinates of 1e5 in float32 the latter loses
    about 2 cm to cancellation, the former nothing beyond the inputs' own rounding.
    """
    import torch

    dev, dt = means.device, means.dtype
    W, H = camera.width, camera.height
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    R = upload(camera.rotation, dev, dt)
    # c - origin in float64 where the means lie (no read-back of a device origin), then in the means' precision
    shift64 = upload(np.asarray(camera.center, dtype=np.float64), dev)
    if origin is not None:
        shift64 = shift64 - torch.as_tensor(origin).detach().to(device=dev, dtype=torch.float64)
    shift_t = shift64.to(dt)

    # Cheap culls first, on centres only: depth, then opacity (gate <= 1, so alpha < 1/255 can never show).
    # Small 3x3 products are written out elementwise: torch's batched matmul is slow for them on CPU.
    d = means - shift_t
    p_cam = d[:, :1] * R[:, 0] + d[:, 1:2] * R[:, 1] + d[:, 2:3] * R[:, 2]  # [N, 3] = d @ R^T
    z = p_cam[:, 2]
    with torch.no_grad():
        keep = (z > near) & (z < far) & (opacities >= ALPHA_MIN) & torch.isfinite(p_cam).all(-1)
        # one data-dependent size (a GPU synchronisation), also when every Gaussian is kept: asking first whether
        # all are would be a second
        idx = keep.nonzero().squeeze(1)
    p_cam, z, quats, scales, opacities, colors = (t[idx] for t in (p_cam, z, quats, scales, opacities, colors))

    # EWA: Sigma2D = J W Sigma W^T J^T, with the tangent-plane coordinates clamped as gsplat does so that Gaussians
    # far outside the view (or straddling the near plane) do not produce huge Jacobians.
    tan_x, tan_y = 0.5 * W / fx, 0.5 * H / fy
    lim_xp, lim_xn = (W - cx) / fx + 0.3 * tan_x, cx / fx + 0.3 * tan_x
    lim_yp, lim_yn = (H - cy) / fy + 0.3 * tan_y, cy / fy + 0.3 * tan_y
    inv_z = 1.0 / z
    tx = torch.clamp(p_cam[:, 0] * inv_z, -lim_xn, lim_xp)
    ty = torch.clamp(p_cam[:, 1] * inv_z, -lim_yn, lim_yp)
    # Rows of T = J R: T0 = fx/z (R0 - tx R2), T1 = fy/z (R1 - ty R2).
    T0 = (fx * inv_z)[:, None] * (R[0] - tx[:, None] * R[2])
    T1 = (fy * inv_z)[:, None] * (R[1] - ty[:, None] * R[2])
    # Sigma = M M^T with M = R_q S; then U = T M, so Sigma2D = U U^T.
    M = quat_to_rotmat(quats) * scales[:, None, :]  # [n, 3, 3]
    U0 = (T0[:, :, None] * M).sum(1)  # [n, 3] = T0 @ M
    U1 = (T1[:, :, None] * M).sum(1)
    a, b, c = (U0 * U0).sum(1), (U0 * U1).sum(1), (U1 * U1).sum(1)
    det_u = a * c - b * b  # undilated: what the gate measures
    a_d, c_d = a + DILATION, c + DILATION
    det = (a_d * c_d - b * b).clamp_min(DILATION * DILATION)  # dilation bounds det from below (0.09 px^4)
    inv_det = 1.0 / det
    conics = torch.stack([c_d * inv_det, -b * inv_det, a_d * inv_det], -1)

    g = coverage_gate(det_u, gate)
    op = opacities * g
    if gate.antialiased:
        rho = aa_compensation(det_u, det)
        op = op * rho
        g = g * rho  # ``gate``: the whole factor the footprint puts on the opacity
    means2d = torch.stack([fx * p_cam[:, 0] * inv_z + cx, fy * p_cam[:, 1] * inv_z + cy], -1)

    # Conservative footprint: alpha = op * exp(-m^2/2) >= 1/255  <=>  m^2 <= 2 ln(255 op).
    with torch.no_grad():
        m2 = 2.0 * torch.log((op * 255.0).clamp_min(1.0))
        ext = torch.stack([torch.sqrt(m2 * a_d), torch.sqrt(m2 * c_d)], -1)
        mx, my = means2d[:, 0], means2d[:, 1]
        vis = (
            (op >= ALPHA_MIN)
            & (mx + ext[:, 0] > 0) & (mx - ext[:, 0] < W)
            & (my + ext[:, 1] > 0) & (my - ext[:, 1] < H)
            & torch.isfinite(means2d).all(-1) & torch.isfinite(conics).all(-1)
        )
        sel = vis.nonzero().squeeze(1)
    return Projected(
        means2d=means2d[sel], conics=conics[sel], opacities=op[sel], colors=colors[sel], depths=z[sel],
        extent=ext[sel], index=idx[sel], gate=g[sel].detach(), width=W, height=H,
    )
