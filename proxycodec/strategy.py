"""Scaffold-GS's anchor growing and pruning (its ``training_statis`` and ``adjust_anchor``) as a strategy object with
its own statistics, as gsplat's ``strategy/`` keeps densification apart from the training loop.

The trainer calls ``observe`` after each backward pass (accumulating the statistics) and ``maybe_adjust`` after each
optimiser step (growing and pruning on schedule). Growing and pruning change the anchor rows; the strategy keeps its
accumulators and the optimiser's moments aligned with them.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from .devices import as_device, upload
from .loop import ndc_grad_norm

__all__ = ["ScaffoldStrategy"]

STAT_NAMES = ("opacity_accum", "anchor_denom", "offset_grad_accum", "offset_denom")


class ScaffoldStrategy:
    """Per anchor: accumulated opacity of its neural Gaussians and the number of views that saw it; per neural
    Gaussian (anchor x offset slot): accumulated view-space gradient (NDC units) and the number of views that drew it.

    ``cfg`` holds the schedule (fractions of the run): ``start_stat``, ``update_from``, ``update_until``,
    ``update_interval`` / ``update_interval_frac``, and the thresholds ``success_threshold``, ``grad_threshold``,
    ``min_opacity``, ``update_depth``, ``update_init_factor``, ``update_hierarchy_factor``, ``max_anchors``.
    """

    def __init__(self, cfg, num_anchors: int, n_offsets: int, log=None, device=None):
        self.cfg = cfg
        self.device = as_device(device)
        self.K = int(n_offsets)
        self.log = log or (lambda s: None)
        self.last_adjust = 0
        self.reset(num_anchors)

    def reset(self, num_anchors: int) -> None:
        M, K = num_anchors, self.K
        z = dict(dtype=torch.float64, device=self.device)
        self.opacity_accum = torch.zeros(M, **z)
        self.anchor_denom = torch.zeros(M, **z)
        self.offset_grad_accum = torch.zeros(M * K, **z)
        self.offset_denom = torch.zeros(M * K, **z)

    # ------------------------------------------------------------------ checkpoints
    def state_arrays(self) -> dict[str, np.ndarray]:
        return {f"stats/{k}": getattr(self, k).cpu().numpy().copy() for k in STAT_NAMES}

    def load_arrays(self, arrays: dict[str, np.ndarray], last_adjust: int) -> None:
        for k in STAT_NAMES:
            setattr(self, k, torch.from_numpy(np.array(arrays[f"stats/{k}"])).to(self.device))
        self.last_adjust = int(last_adjust)

    # ------------------------------------------------------------------ statistics
    def collecting(self, progress: float) -> bool:
        return self.cfg.start_stat <= progress < self.cfg.update_until

    @torch.no_grad()
    def observe(self, r, width: int, height: int) -> None:
        """Scaffold-GS's ``training_statis`` for one rendered view ``r`` (a ``SceneRender`` after backward): opacity
        of the visible anchors' Gaussians, view-space gradient of the drawn ones."""
        g, proj = r.gaussians, r.projected
        vis = r.visible_anchor_index
        self.anchor_denom[vis] += 1
        if g.count:
            self.opacity_accum.index_add_(0, g.anchor_index, g.opacities.detach().double())
        grad = proj.means2d.grad
        if grad is None or proj.count == 0:
            return
        gn = ndc_grad_norm(grad, width, height)
        rows = proj.index
        flat = g.anchor_index[rows] * self.K + g.slot[rows]
        self.offset_grad_accum.index_add_(0, flat, gn)
        self.offset_denom.index_add_(0, flat, torch.ones_like(gn))

    # ------------------------------------------------------------------ growing and pruning
    def update_interval(self, expected_iterations: float) -> int:
        """Iterations between anchor adjustments: Scaffold-GS's 100 in 30k scaled to short runs (>= 10)."""
        c = self.cfg
        return int(min(c.update_interval, max(10, round(expected_iterations * c.update_interval_frac))))

    def maybe_adjust(self, run, anchors, opt, rng: np.random.Generator) -> None:
        """Adjust when the run (``progress()``, ``iteration``, ``expected_iterations()``) is inside the update window
        and an interval has passed since the last adjustment."""
        p = run.progress()
        interval = self.update_interval(run.expected_iterations())
        if self.cfg.update_from <= p < self.cfg.update_until and run.iteration - self.last_adjust >= interval:
            self.last_adjust = run.iteration
            self.adjust(anchors, opt, rng, interval)

    @torch.no_grad()
    def adjust(self, anchors, opt, rng: np.random.Generator, interval: int) -> None:
        """Scaffold-GS's ``adjust_anchor``: grow anchors where the Gaussians' mean gradient is high, then prune
        anchors seen often enough whose Gaussians stayed (nearly) transparent."""
        c, K = self.cfg, self.K
        grads = self.offset_grad_accum / self.offset_denom
        grads[~torch.isfinite(grads)] = 0.0
        offset_mask = self.offset_denom > interval * c.success_threshold * 0.5
        n_before = anchors.num_anchors
        if c.max_anchors is None or n_before < c.max_anchors:
            self._grow(anchors, opt, rng, grads, offset_mask)
        n_new = anchors.num_anchors - n_before
        # Reset the gradient statistics of the offsets that were judged; new anchors start at zero.
        self.offset_denom[offset_mask] = 0
        self.offset_grad_accum[offset_mask] = 0
        pad = self.offset_denom.new_zeros(n_new * K)
        self.offset_denom = torch.cat([self.offset_denom, pad])
        self.offset_grad_accum = torch.cat([self.offset_grad_accum, pad])
        padm = self.opacity_accum.new_zeros(n_new)
        self.opacity_accum = torch.cat([self.opacity_accum, padm])
        self.anchor_denom = torch.cat([self.anchor_denom, padm])
        prune = self.opacity_accum < c.min_opacity * self.anchor_denom
        judged = self.anchor_denom > interval * c.success_threshold
        prune &= judged
        self.opacity_accum[judged] = 0
        self.anchor_denom[judged] = 0
        if bool(prune.any()) and int((~prune).sum()) > 0:
            self._keep(anchors, opt, (~prune).nonzero().squeeze(1))
        if n_new or bool(prune.any()):
            self.log(f"  anchors: +{n_new} grown, -{int(prune.sum())} pruned -> {anchors.num_anchors}")

    def _keep(self, anchors, opt, keep: torch.Tensor) -> None:
        K = self.K
        anchors.keep(keep)
        for k, t in anchors.tensors().items():
            opt.rebind(k, t, keep=keep)
        flat = (keep[:, None] * K + torch.arange(K, device=keep.device)).reshape(-1)
        self.offset_grad_accum = self.offset_grad_accum[flat]
        self.offset_denom = self.offset_denom[flat]
        self.opacity_accum = self.opacity_accum[keep]
        self.anchor_denom = self.anchor_denom[keep]

    def _grow(self, a, opt, rng: np.random.Generator, grads: torch.Tensor, offset_mask: torch.Tensor) -> None:
        """Scaffold-GS ``anchor_growing``: new anchors in (coarse to fine) voxels holding high-gradient Gaussians."""
        c, K = self.cfg, self.K
        init_len = a.num_anchors * K
        for i in range(c.update_depth):
            threshold = c.grad_threshold * ((c.update_hierarchy_factor // 2) ** i)
            cand = (grads >= threshold) & offset_mask
            rand = upload(rng.random(cand.shape[0]) > 0.5 ** (i + 1), cand.device)
            cand = cand & rand
            inc = a.num_anchors * K - init_len
            if inc == 0 and i > 0:
                continue
            if inc:
                cand = torch.cat([cand, cand.new_zeros(inc)])
            if not bool(cand.any()):
                continue
            all_xyz = a.positions[:, None, :] + a.offsets.detach() * torch.exp(a.scalings.detach()[:, None, :3])
            size = a.voxel_size * (c.update_init_factor // (c.update_hierarchy_factor**i))
            grid = torch.round(a.positions / size).long()
            sel_xyz = all_xyz.reshape(-1, 3)[cand]
            sel_grid = torch.round(sel_xyz / size).long()
            uniq, inverse = torch.unique(sel_grid, return_inverse=True, dim=0)
            # Drop cells that already hold an anchor (exact integer-cell comparison via a hashed key).
            existing = set(map(tuple, grid.tolist()))
            new_mask = torch.tensor([tuple(u) not in existing for u in uniq.tolist()], dtype=torch.bool,
                                    device=uniq.device)
            if not bool(new_mask.any()):
                continue
            new_pos = uniq[new_mask].double() * size
            n = int(new_pos.shape[0])
            if c.max_anchors is not None and a.num_anchors + n > c.max_anchors:
                n = max(0, c.max_anchors - a.num_anchors)
                if n == 0:
                    return
            feats_rep = a.features.detach()[:, None, :].expand(-1, K, -1).reshape(-1, a.features.shape[1])[cand]
            Fd = feats_rep.shape[1]
            pooled = feats_rep.new_full((uniq.shape[0], Fd), -torch.inf).scatter_reduce(
                0, inverse[:, None].expand(-1, Fd), feats_rep, reduce="amax", include_self=True)
            new_feat = pooled[new_mask][:n]
            new_pos = new_pos[:n].float()
            new_scal = a.positions.new_full((n, 6), math.log(size))
            new_off = a.positions.new_zeros(n, K, 3)
            a.append(new_pos, new_feat, new_off, new_scal)
            for k, t in a.tensors().items():
                opt.rebind(k, t, append=n)
