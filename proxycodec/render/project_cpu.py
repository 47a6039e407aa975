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

import numpy as np
import torch

# The kernels and their numpy driver live in a torch-free module (the torch-free decode path calls them directly).
from ._project_kernels import NW, SMALL_WORK, backward_all, constants, project_forward
from ._project_kernels import n_chunks as _n_chunks
from ._raster_kernels import threads_for
from .project import GateConfig, Projected, project_gaussians

#: Below this many Gaussians the kernels run on the calling thread only (the pool's wake-up costs more).
_SMALL_WORK = SMALL_WORK


def _threads(n: int):
    return threads_for(n, _SMALL_WORK)  # reads the module constant at call time (tests lower it)


def _constants(camera, gate: GateConfig, near: float, far: float, origin, np_dt) -> np.ndarray:
    """Every constant the reference uses, cast to the input dtype (``_project_kernels.constants``)."""
    if origin is not None:
        origin = torch.as_tensor(origin).detach().double().cpu().numpy()
    return constants(camera, gate, near, far, origin, np_dt)


class _ProjectCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, opacities, k, gate_on):
        mn, qn, sn, on = (t.detach().numpy() for t in (means, quats, scales, opacities))
        m2d, con, op, dep, ext, gate, idx = project_forward(mn, qn, sn, on, k, gate_on, _SMALL_WORK)
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
                backward_all(*(t.detach().numpy() for t in (means, quats, scales, opacities)), k, ctx.gate_on, nch,
                          np.empty((nch, NW), np_dt), idx, gm, gc, go, gd, d_means, d_quats, d_scales, d_opac)
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
