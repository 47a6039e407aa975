"""Plain 3DGS training (``proxycodec fit --explicit``): the explicit-Gaussian baseline for issue #7.

What users would otherwise pick is an INRIA 3DGS PLY (or its SPZ conversion). To compare the anchor codec with it at
an equal time budget, this module trains one with the project's own projection and rasterizer, following
graphdeco-inria/gaussian-splatting's ``train.py`` / ``GaussianModel``:

- parameters per Gaussian: position, SH coefficients (DC and rest, degree ``sh_degree``), opacity logit, log scales,
  a quaternion; activations ``sigmoid(opacity)``, ``exp(scale)``, normalised quaternion; colour = SH evaluated in the
  direction from the camera centre to the Gaussian, ``+ 0.5``, clamped at 0; the active SH degree grows by one every
  1/30 of the run (3DGS: every 1000 of 30k iterations);
- initialisation: SfM points with their colours (COLMAP), else ``init_points`` uniform random points in the dataset
  bounds (Blender, as the anchor trainer does), grey; scales from the 3 nearest neighbours, opacity 0.1, identity
  rotation;
- loss 0.8 L1 + 0.2 D-SSIM, Adam (eps 1e-15) with 3DGS's learning rates, the position one scaled by the cameras'
  extent (``getNerfppNorm``: 1.1 x the largest distance of a training camera from their centroid) and decayed
  exponentially over the run;
- adaptive density control: the view-space positional gradient (of the projected 2D means, in NDC units as 3DGS
  measures it) is averaged per Gaussian over the views that drew it; every ``densify_interval`` iterations between
  ``densify_from`` and ``densify_until`` (fractions of the run: 3DGS's 500 and 15000 of 30000) Gaussians whose
  average is at least ``grad_threshold`` are cloned (largest scale <= ``percent_dense`` x extent) or split in two
  (larger: children sampled from the parent, scales / 1.6), then Gaussians with opacity < ``prune_opacity`` are
  removed, and, from ``prune_big_from`` on, those larger than 0.1 x extent in world space;
- no coverage gate (plain 3DGS has none), fixed 100% resolution unless ``random_res``.

Deliberately left out: 3DGS's screen-space "big point" pruning (its ``max_radii2D`` is zeroed by
``densification_postfix`` before the test, so it never fires in the reference code either: issue #123 there),
opacity resets by default (``opacity_reset_every`` restores them as a fraction of the run; on short CPU runs each
reset costs more than it gives), exposure compensation, depth regularisation, anti-aliasing variants.
``max_gaussians`` (``fit --explicit --max-gaussians``) caps densification as a CPU memory/time guard.

With ``iters`` and no time budget a run is deterministic for a seed (one numpy generator draws the view order and
the split samples; the CPU kernels are deterministic). Checkpoints (``OUT.ckpt.pxc``, our own container: raw arrays
and JSON) are written every ``checkpoint_every`` seconds and on interrupt or error; ``resume`` continues the same
random stream, so an interrupted and resumed run writes the same PLY bytes as one run straight through.
"""

from __future__ import annotations

import copy
import math
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from .devices import as_device, upload
from .errors import ProxycodecError
from .formats.container import read_container
from .formats.inria_ply import GaussianPly, rgb_to_sh_dc, write_inria_ply
from .formats.splats import is_inria_ply
from .loop import (
    ProgressFn, TargetImages, TrainingRun, check_run_length, checkpoint_path_for, fmt_time, initial_points, knn_scale,
    ndc_grad_norm, photometric_loss, run_checkpointed,
)
from .optim import Adam, exp_lr
from .render import GateConfig, RenderResult, render_gaussians
from .render.project import quat_to_rotmat

__all__ = [
    "NO_GATE",
    "NO_GATE_ANTIALIASED",
    "DensifyResult",
    "ExplicitConfig",
    "ExplicitModel",
    "ExplicitTrainer",
    "densify_and_prune",
    "eval_sh",
    "is_inria_ply",
    "run_explicit",
    "sh_colors",
    "train_explicit",
]

#: Plain 3DGS has no pixel coverage gate.
NO_GATE = GateConfig(enabled=False)
#: ... and a file trained with Mip-Splatting's / gsplat's antialiased filter (SPZ flag 0x1, our GLB extras) renders
#: with its opacity compensation, as those trainers render it.
NO_GATE_ANTIALIASED = GateConfig(enabled=False, antialiased=True)


def plain_gate(antialiased: bool) -> GateConfig:
    """How plain 3DGS renders: no gate, the antialiased filter's compensation when it was trained with it."""
    return NO_GATE_ANTIALIASED if antialiased else NO_GATE

EXPLICIT_CHECKPOINT_KIND = "proxycodec.explicit-checkpoint"
EXPLICIT_CHECKPOINT_VERSION = 1
#: The parameter tensors of a run, in the order they are created (``initial_gaussians``).
_PARAM_NAMES = ("means", "sh_dc", "sh_rest", "opacities", "scales", "quats")
#: Settings a resumed run may change: its length and bookkeeping.
_RESUME_MAY_CHANGE = frozenset({"iters", "time_budget", "checkpoint_every", "log_every", "backend", "image_cache_mb",
                                "max_gaussians"})

# Real spherical harmonics constants of 3DGS's ``utils/sh_utils.py`` (degree <= 3).
SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
         1.445305721320277, -0.5900435899266435)

PARAMS = ("means", "sh_dc", "sh_rest", "opacities", "scales", "quats")


# ================================================================================================ spherical harmonics
def eval_sh(degree: int, sh: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """3DGS's ``eval_sh``: ``sh`` [N, >= (degree+1)^2, C] coefficients, ``dirs`` [N, 3] unit vectors -> [N, C]."""
    if not 0 <= degree <= 3:
        raise ProxycodecError(f"SH degree must be 0..3, got {degree}")
    if sh.shape[1] < (degree + 1) ** 2:
        raise ProxycodecError(f"degree {degree} needs {(degree + 1) ** 2} SH coefficients, got {sh.shape[1]}")
    res = SH_C0 * sh[:, 0]
    if degree < 1:
        return res
    x, y, z = (dirs[:, i:i + 1] for i in range(3))
    res = res - SH_C1 * y * sh[:, 1] + SH_C1 * z * sh[:, 2] - SH_C1 * x * sh[:, 3]
    if degree < 2:
        return res
    xx, yy, zz = x * x, y * y, z * z
    xy, yz, xz = x * y, y * z, x * z
    res = (res + SH_C2[0] * xy * sh[:, 4] + SH_C2[1] * yz * sh[:, 5] + SH_C2[2] * (2.0 * zz - xx - yy) * sh[:, 6]
           + SH_C2[3] * xz * sh[:, 7] + SH_C2[4] * (xx - yy) * sh[:, 8])
    if degree < 3:
        return res
    return (res + SH_C3[0] * y * (3 * xx - yy) * sh[:, 9] + SH_C3[1] * xy * z * sh[:, 10]
            + SH_C3[2] * y * (4 * zz - xx - yy) * sh[:, 11] + SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy) * sh[:, 12]
            + SH_C3[4] * x * (4 * zz - xx - yy) * sh[:, 13] + SH_C3[5] * z * (xx - yy) * sh[:, 14]
            + SH_C3[6] * x * (xx - 3 * yy) * sh[:, 15])


def sh_colors(sh: torch.Tensor, means: torch.Tensor, cam_center, degree: int) -> torch.Tensor:
    """Per-Gaussian RGB seen from ``cam_center`` (world): ``max(eval_sh(dir) + 0.5, 0)`` as 3DGS computes it."""
    c = upload(np.asarray(cam_center, dtype=np.float64), means.device, means.dtype)
    d = means - c
    d = d / d.norm(dim=1, keepdim=True).clamp_min(1e-12)
    return (eval_sh(degree, sh, d) + 0.5).clamp_min(0.0)


# ================================================================================================ configuration
@dataclass(frozen=True)
class ExplicitConfig:
    """A plain 3DGS run. Fractions are of the whole run (iterations or time budget); 3DGS's values in comments."""

    iters: int | None = 3000  # None: run until time_budget
    time_budget: float | None = None  # seconds of training steps
    seed: int = 0
    max_width: int | None = 1600  # applied by the dataset loader (3DGS's rule); recorded here for reference
    sh_degree: int = 1  # 0..3 (3DGS: 3; 1 keeps CPU runs and files small)
    random_res: bool = False  # xi ~ U[xi_min, 1] per iteration instead of 100% (not in 3DGS)
    xi_min: float = 0.1
    # initialisation
    init_points: int = 10_000  # random points when the dataset has no SfM points (3DGS: 100k for NeRF-Synthetic)
    max_init_points: int = 200_000  # SfM points beyond this are subsampled
    init_opacity: float = 0.1
    # loss and learning rates (3DGS OptimizationParams)
    lambda_dssim: float = 0.2
    lr_position: tuple[float, float] = (0.00016, 0.0000016)  # x scene extent, exponential decay over the run
    lr_sh_dc: float = 0.0025
    lr_sh_rest: float = 0.0025 / 20.0
    lr_opacity: float = 0.05
    lr_scaling: float = 0.005
    lr_rotation: float = 0.001
    sh_up_every: float = 1.0 / 30.0  # active SH degree += 1 per this fraction (3DGS: 1000 of 30000)
    # adaptive density control
    densify_from: float = 500.0 / 30000.0
    densify_until: float = 15000.0 / 30000.0
    densify_interval: int = 100  # at most this many iterations between densifications (3DGS: 100)
    densify_interval_frac: float = 1.0 / 300.0  # ... and about this fraction of the run, at least 10 iterations
    grad_threshold: float = 0.0002
    percent_dense: float = 0.01
    prune_opacity: float = 0.005
    prune_big_from: float = 3000.0 / 30000.0  # world-space big-Gaussian pruning from here (3DGS: after 1st reset)
    prune_big_world: float = 0.1  # x extent
    opacity_reset_every: float = 0.0  # 0: never (3DGS: 3000 of 30000 = 0.1)
    max_gaussians: int = 300_000  # densification stops at this count (CPU guard)
    # train with the antialiased filter's opacity compensation (gsplat's antialiased mode; ``GateConfig``): the PLY
    # then renders as trained with ``render`` / ``eval --antialiased on`` (an INRIA PLY cannot say so itself)
    antialiased: bool = False
    # bookkeeping
    image_cache_mb: int = 2048
    backend: str = "auto"
    log_every: float = 10.0  # seconds between progress lines
    checkpoint_every: float = 300.0  # seconds between checkpoints (0: never, except on interrupt)

    def __post_init__(self) -> None:
        check_run_length(self.iters, self.time_budget, self.max_width)
        if not (isinstance(self.sh_degree, int) and 0 <= self.sh_degree <= 3):
            raise ProxycodecError(f"SH degree must be 0..3, got {self.sh_degree!r}")
        if not (0.025 <= self.xi_min <= 1.0):
            raise ProxycodecError(f"xi_min must be in [0.025, 1], got {self.xi_min}")
        if self.init_points < 1 or self.max_gaussians < 1:
            raise ProxycodecError("init_points and max_gaussians must be >= 1")
        if not self.checkpoint_every >= 0:
            raise ProxycodecError(f"checkpoint_every must be >= 0 seconds, got {self.checkpoint_every}")

    def to_json(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}


# ================================================================================================ densification
@dataclass
class DensifyResult:
    params: dict[str, torch.Tensor]  # the new parameter tensors (detached)
    keep_old: torch.Tensor  # rows of the old set that survive densification, in order (split parents removed)
    n_new: int  # rows appended after them (clones, then split children)
    keep_final: torch.Tensor  # rows of (old[keep_old] + new) that survive pruning
    n_clone: int = 0
    n_split: int = 0
    n_pruned: int = 0


@torch.no_grad()
def densify_and_prune(params: dict[str, torch.Tensor], grads: torch.Tensor, *, grad_threshold: float,
                      percent_dense: float, extent: float, prune_opacity: float, prune_big_world: float | None,
                      max_gaussians: int, rng: np.random.Generator) -> DensifyResult:
    """3DGS's ``densify_and_prune`` on named parameter tensors (raw, before activation).

    ``grads`` [N]: the mean view-space gradient norm per Gaussian. Clone where ``grads >= threshold`` and the largest
    scale is <= ``percent_dense * extent``, split (2 children from N(parent, scales), scales / 1.6, parent removed)
    where it is larger; beyond ``max_gaussians`` only the highest gradients are densified. Then prune opacity <
    ``prune_opacity`` and, when ``prune_big_world`` is given, largest scale > ``prune_big_world * extent``.
    """
    p = {k: v.detach() for k, v in params.items()}
    n = int(p["means"].shape[0])
    scale_max = torch.exp(p["scales"]).max(dim=1).values
    high = grads >= grad_threshold
    small = scale_max <= percent_dense * extent
    budget = max(0, int(max_gaussians) - n)
    cand = high.nonzero().squeeze(1)
    if cand.numel() > budget:  # each clone or split adds one Gaussian: keep the highest gradients
        order = torch.sort(-grads[cand].double(), stable=True).indices
        sel = torch.zeros(n, dtype=torch.bool, device=grads.device)
        sel[cand[order[:budget]]] = True
        high = sel
    clone = high & small
    split = high & ~small
    ci = clone.nonzero().squeeze(1)
    si = split.nonzero().squeeze(1)
    new: dict[str, list[torch.Tensor]] = {k: [v[ci]] for k, v in p.items()}
    ns = int(si.numel())
    if ns:
        s = torch.exp(p["scales"][si]).repeat(2, 1)  # [2 ns, 3] (3DGS's repeat(N, 1): all parents, twice)
        samples = upload(rng.standard_normal((2 * ns, 3)), s.device, s.dtype) * s
        R = quat_to_rotmat(p["quats"][si]).repeat(2, 1, 1)
        child_means = (R @ samples[:, :, None]).squeeze(-1) + p["means"][si].repeat(2, 1)
        for k, v in p.items():
            if k == "means":
                new[k].append(child_means)
            elif k == "scales":
                new[k].append(torch.log(s / (0.8 * 2)))
            else:
                new[k].append(v[si].repeat((2,) + (1,) * (v.dim() - 1)))
    keep_old = (~split).nonzero().squeeze(1)
    out = {k: torch.cat([p[k][keep_old]] + new[k]) for k in p}
    n_new = int(out["means"].shape[0] - keep_old.numel())
    prune = torch.sigmoid(out["opacities"]) < prune_opacity
    if prune_big_world is not None:
        prune |= torch.exp(out["scales"]).max(dim=1).values > prune_big_world * extent
    if bool(prune.all()):  # never prune everything
        prune[:] = False
    keep_final = (~prune).nonzero().squeeze(1)
    out = {k: v[keep_final].contiguous() for k, v in out.items()}
    return DensifyResult(out, keep_old, n_new, keep_final, int(ci.numel()), ns, int(prune.sum()))


# ================================================================================================ initialisation
def cameras_extent(cameras) -> float:
    """3DGS's ``getNerfppNorm`` radius: 1.1 x the largest distance of a camera centre from their centroid."""
    c = np.stack([cam.center for cam in cameras])
    r = float(np.linalg.norm(c - c.mean(0), axis=1).max()) * 1.1
    return r if r > 0 and math.isfinite(r) else 1.0


def initial_gaussians(data, cfg: ExplicitConfig, rng: np.random.Generator, device=None) -> dict[str, torch.Tensor]:
    """3DGS's ``create_from_pcd`` on SfM points (with colours) or random points in the dataset bounds (grey), on
    ``device``."""
    pts, colors, _, _ = initial_points(data, cfg.init_points, rng, "Gaussians")
    colors = None if colors is None else colors / 255.0
    if data.points is not None and len(data.points) >= 8 and len(pts) > cfg.max_init_points:
        idx = np.sort(rng.choice(len(pts), cfg.max_init_points, replace=False))
        pts = pts[idx]
        colors = colors[idx] if colors is not None else None
    if len(pts) == 0:
        raise ProxycodecError("no initial points")
    n = len(pts)
    n_coef = (cfg.sh_degree + 1) ** 2
    dc = np.zeros((n, 1, 3)) if colors is None else rgb_to_sh_dc(colors)[:, None, :]
    logit = math.log(cfg.init_opacity / (1 - cfg.init_opacity))
    quats = np.zeros((n, 4))
    quats[:, 0] = 1.0
    f = lambda a: torch.tensor(np.asarray(a), dtype=torch.float32, device=device)  # noqa: E731
    return {
        "means": f(pts),
        "sh_dc": f(dc),
        "sh_rest": torch.zeros(n, n_coef - 1, 3, device=device),
        "opacities": torch.full((n,), logit, device=device),
        "scales": f(np.repeat(np.log(knn_scale(pts))[:, None], 3, 1)),
        "quats": f(quats),
    }


# ================================================================================================ the trainer
class ExplicitTrainer(TrainingRun):
    """Owns the Gaussians, the optimiser and the densification statistics of one plain 3DGS run."""

    def __init__(self, data, config: ExplicitConfig, log: ProgressFn | None = None, device=None):
        if not data.train_indices:
            raise ProxycodecError("the dataset has no training images")
        self.data = data
        self.device = dev = as_device(device)
        self.cfg = config
        self.log = log or (lambda s: None)
        self.bg = torch.tensor(data.background, dtype=torch.float32, device=dev)
        self.rng = np.random.default_rng(config.seed)
        torch.manual_seed(config.seed)
        self.images = TargetImages(data, config.image_cache_mb << 20, dev)
        self.extent = cameras_extent([data.cameras[i] for i in data.train_indices])
        self.opt = Adam()
        self.params: dict[str, torch.Tensor] = {}
        for k, v in initial_gaussians(data, config, self.rng, dev).items():
            self.params[k] = v.requires_grad_(True)
            self.opt.add(k, self.params[k])
        self._reset_stats()
        self._start_run()
        self.last_densify = 0
        self.last_reset = 0

    @property
    def num_gaussians(self) -> int:
        return int(self.params["means"].shape[0])

    def _reset_stats(self) -> None:
        n = self.num_gaussians
        self.grad_accum = torch.zeros(n, dtype=torch.float64, device=self.device)
        self.denom = torch.zeros(n, dtype=torch.float64, device=self.device)

    # ------------------------------------------------------------------ schedule
    def densify_interval(self) -> int:
        c = self.cfg
        return int(min(c.densify_interval, max(10, round(self.expected_iterations() * c.densify_interval_frac))))

    def active_sh_degree(self, p: float) -> int:
        return min(self.cfg.sh_degree, int(p / self.cfg.sh_up_every)) if self.cfg.sh_up_every > 0 else \
            self.cfg.sh_degree

    def learning_rates(self, p: float) -> dict[str, float]:
        c = self.cfg
        return {"means": exp_lr(c.lr_position[0] * self.extent, c.lr_position[1] * self.extent, p),
                "sh_dc": c.lr_sh_dc, "sh_rest": c.lr_sh_rest, "opacities": c.lr_opacity, "scales": c.lr_scaling,
                "quats": c.lr_rotation}

    # ------------------------------------------------------------------ one iteration
    def render(self, camera, degree: int) -> RenderResult:
        """Render the live Gaussians (with gradients) from ``camera`` at its own size, no gate (the antialiased
        filter's compensation with ``antialiased``)."""
        q = self.params
        n_coef = (degree + 1) ** 2
        sh = torch.cat([q["sh_dc"], q["sh_rest"][:, :n_coef - 1]], 1)
        colors = sh_colors(sh, q["means"], camera.center, degree)
        return render_gaussians(q["means"], q["quats"], torch.exp(q["scales"]), torch.sigmoid(q["opacities"]),
                                colors, camera, background=self.bg, gate=plain_gate(self.cfg.antialiased),
                                backend=self.cfg.backend)

    def train_step(self) -> dict:
        """sample view and resolution -> render -> loss -> backward -> step -> densify (``TrainingRun.optimise``)."""
        c = self.cfg
        p = self.progress()
        i, xi, gt = self.sample_view((c.xi_min, 1.0) if c.random_res else 1.0)
        cam = self.data.cameras[i].scaled(xi)
        r = self.render(cam, self.active_sh_degree(p))
        loss = photometric_loss(r.image, gt, c.lambda_dssim)
        self.optimise(loss, r, cam.width, cam.height, self.learning_rates(p))
        return {**self.step_stats(loss, r.image, gt), "xi": xi, "view": i, "drawn": int(r.projected.count)}

    def observe(self, r, width: int, height: int) -> None:
        if self.progress() < self.cfg.densify_until:
            self._update_stats(r.projected, width, height)

    def after_step(self) -> None:
        self._maybe_densify()

    @torch.no_grad()
    def _update_stats(self, proj, width: int, height: int) -> None:
        """3DGS's ``add_densification_stats``: |d loss / d mean2D| in NDC units for every Gaussian drawn."""
        g = proj.means2d.grad
        if g is None or proj.count == 0:
            return
        gn = ndc_grad_norm(g, width, height)
        self.grad_accum.index_add_(0, proj.index, gn)
        self.denom.index_add_(0, proj.index, torch.ones_like(gn))

    # ------------------------------------------------------------------ adaptive density control
    def _maybe_densify(self) -> None:
        c = self.cfg
        p = self.progress()
        if not (c.densify_from <= p < c.densify_until):
            return
        if self.iteration - self.last_densify >= self.densify_interval():
            self.last_densify = self.iteration
            self.densify(prune_big=p >= c.prune_big_from)
        if c.opacity_reset_every > 0:
            k = int(p / c.opacity_reset_every)
            if k > self.last_reset:
                self.last_reset = k
                self.reset_opacity()

    @torch.no_grad()
    def densify(self, prune_big: bool = False) -> DensifyResult:
        c = self.cfg
        grads = self.grad_accum / self.denom
        grads[~torch.isfinite(grads)] = 0.0
        n0 = self.num_gaussians
        res = densify_and_prune(self.params, grads.float(), grad_threshold=c.grad_threshold,
                                percent_dense=c.percent_dense, extent=self.extent, prune_opacity=c.prune_opacity,
                                prune_big_world=c.prune_big_world if prune_big else None,
                                max_gaussians=c.max_gaussians, rng=self.rng)
        for k, t in res.params.items():
            t.requires_grad_(True)
            self.params[k] = t
            self.opt.rebind(k, t, keep=res.keep_old, append=res.n_new)  # densified rows: fresh moments
            self.opt.rebind(k, t, keep=res.keep_final)
        self._reset_stats()
        self.log(f"  densify at iteration {self.iteration}: +{res.n_clone} cloned, +{res.n_split} split, "
                 f"-{res.n_pruned} pruned: {n0} -> {self.num_gaussians} Gaussians")
        return res

    @torch.no_grad()
    def reset_opacity(self) -> None:
        """3DGS's ``reset_opacity``: opacities to at most 0.01, their Adam moments zeroed."""
        op = self.params["opacities"]
        cap = math.log(0.01 / 0.99)
        op.copy_(op.clamp_max(cap))
        self.opt.m["opacities"].zero_()
        self.opt.v["opacities"].zero_()
        self.log(f"  opacity reset at iteration {self.iteration}")

    # ------------------------------------------------------------------ checkpoints
    def checkpoint_arrays(self) -> tuple[dict, dict]:
        arrays: dict[str, np.ndarray] = {f"gaussians/{k}": v.detach().cpu().numpy().copy()
                                         for k, v in self.params.items()}
        arrays["stats/grad_accum"] = self.grad_accum.cpu().numpy().copy()
        arrays["stats/denom"] = self.denom.cpu().numpy().copy()
        arrays.update(self.opt.state_arrays())
        run_meta, run_arrays = self.run_state()
        arrays.update(run_arrays)
        meta = {"kind": EXPLICIT_CHECKPOINT_KIND, "version": EXPLICIT_CHECKPOINT_VERSION, "config": self.cfg.to_json(),
                "last_densify": self.last_densify, "last_reset": self.last_reset,
                "adam_steps": dict(self.opt.step_count), **run_meta}
        return meta, arrays

    def load_checkpoint(self, path: str | os.PathLike) -> None:
        """Continue from ``save_checkpoint``'s file; its settings must be this run's but for the run length and
        bookkeeping (one-line errors naming the file otherwise)."""
        ck = read_container(path)
        m = ck.meta
        if m.get("kind") != EXPLICIT_CHECKPOINT_KIND or m.get("version") != EXPLICIT_CHECKPOINT_VERSION:
            raise ProxycodecError("not a `fit --explicit` checkpoint of this version", path)
        try:
            saved, now = m["config"], self.cfg.to_json()
            default = ExplicitConfig().to_json()  # a setting newer than the checkpoint: it was at its default
            diff = [k for k in now if k not in _RESUME_MAY_CHANGE and saved.get(k, default[k]) != now[k]]
            if diff:
                raise ProxycodecError(f"checkpoint was made with different settings ({', '.join(diff[:5])}); "
                                      "resume with the same options or start afresh", path)
            arr = ck.arrays
            self.opt = Adam()
            self.params = {}
            for k in _PARAM_NAMES:
                t = torch.from_numpy(np.array(arr[f"gaussians/{k}"], dtype=np.float32)).to(self.device)
                self.params[k] = t.requires_grad_(True)
                self.opt.add(k, t)
            self.opt.load_arrays(arr, m["adam_steps"])
            n = self.num_gaussians
            for k in ("grad_accum", "denom"):
                a = np.array(arr[f"stats/{k}"], dtype=np.float64)
                if a.shape != (n,):
                    raise ProxycodecError(f"checkpoint's stats/{k} has shape {a.shape}, expected ({n},)", path)
                setattr(self, k, torch.from_numpy(a).to(self.device))
            self.last_densify = int(m["last_densify"])
            self.last_reset = int(m["last_reset"])
            self.load_run_state(m, arr)
        except KeyError as e:
            raise ProxycodecError(f"checkpoint is missing {e}", path) from None

    # ------------------------------------------------------------------ result
    @torch.no_grad()
    def result(self) -> GaussianPly:
        q = {k: v.detach().cpu() for k, v in self.params.items()}
        sh = torch.cat([q["sh_dc"], q["sh_rest"]], 1)
        return GaussianPly(q["means"].numpy(), sh.numpy(), q["opacities"].numpy(), q["scales"].numpy(),
                           q["quats"].numpy())


def train_explicit(data, cfg: ExplicitConfig = ExplicitConfig(), log: ProgressFn | None = print, *,
                   out: str | os.PathLike | None = None, device=None) -> GaussianPly:
    """Train plain 3DGS on ``data`` (a ``PosedImages``) on ``device`` (None: the CPU); write ``out`` (INRIA PLY,
    atomic) when given."""
    return run_explicit(data, cfg, log, out=out, device=device).result()


def run_explicit(data, cfg: ExplicitConfig = ExplicitConfig(), log: ProgressFn | None = print, *,
                 out: str | os.PathLike | None = None, device=None, resume: bool = False,
                 keep_checkpoint: bool = False, stop_after: int | None = None) -> ExplicitTrainer:
    """``train_explicit`` returning the finished trainer (iterations, time, history, the Gaussians).

    With ``out``, checkpoints go to ``OUT.ckpt.pxc`` every ``cfg.checkpoint_every`` seconds and on interrupt or error
    (removed after success unless ``keep_checkpoint``), and ``resume`` continues from it. ``stop_after`` (tests)
    raises ``KeyboardInterrupt`` after that many iterations of this call."""
    log = log or (lambda s: None)
    if resume and out is None:
        raise ProxycodecError("resume needs the output path (its checkpoint lies beside it)")
    ckpt = checkpoint_path_for(out) if out is not None else None
    t_setup = time.perf_counter()
    tr = ExplicitTrainer(data, cfg, log, device)
    if resume:
        if not ckpt.exists():
            raise ProxycodecError("no checkpoint to resume from", ckpt)
        tr.load_checkpoint(ckpt)
        log(f"resumed from {ckpt} at iteration {tr.iteration} ({fmt_time(tr.elapsed)} trained, "
            f"{tr.num_gaussians} Gaussians)")
    log(f"fit --explicit (plain 3DGS): {len(data.train_indices)} training views, {tr.num_gaussians} "
        f"{'' if resume else 'initial '}Gaussians, extent {tr.extent:.3g}, SH degree {cfg.sh_degree}, "
        f"setup {time.perf_counter() - t_setup:.1f} s; iters {cfg.iters}, time budget {cfg.time_budget}")
    def detail(st: dict) -> str:
        return f"gauss {tr.num_gaussians:7d}  drawn {st['drawn']:7d}"

    def hist() -> dict:
        return {"gaussians": tr.num_gaussians}

    run_checkpointed(tr, ckpt, cfg.checkpoint_every, log, detail, hist,
                     (lambda: None) if out is None else (lambda: write_inria_ply(out, tr.result())),
                     keep_checkpoint=keep_checkpoint, stop_after=stop_after)
    log(f"done: {tr.iteration} iterations in {fmt_time(tr.elapsed)}, {tr.num_gaussians} Gaussians"
        + (f" -> {out}" if out is not None else ""))
    return tr


# ================================================================================================ rendering a PLY
#: [D] the background a 3DGS PLY is rendered on when nothing says otherwise: black, the default of the reference
#: trainer (``--white_background`` off), gsplat and nerfstudio; a PLY trained on black and composited on white shows
#: white haze wherever its accumulated alpha is below 1
PLY_BACKGROUND = (0.0, 0.0, 0.0)


def ply_background(path: str | os.PathLike) -> tuple[tuple[float, float, float], str]:
    """(RGB, where it comes from) of the background a 3DGS PLY was trained on: the ``white_background`` of the
    trainer's ``cfg_args`` (``Namespace(...)``, read without ``eval``) beside the PLY or two folders up, as 3DGS and
    Scaffold-GS write it; else ``PLY_BACKGROUND``. An unreadable ``cfg_args`` is a one-line error naming it."""
    from .scaffold_gs import find_beside, read_cfg_args

    cfg_path = find_beside(path, "cfg_args")
    if cfg_path is not None:
        white = read_cfg_args(cfg_path).get("white_background")
        if isinstance(white, bool):
            return ((1.0, 1.0, 1.0) if white else (0.0, 0.0, 0.0)), f"{cfg_path} (white_background={white})"
    return PLY_BACKGROUND, "default (black, the 3DGS trainers' default)"


@dataclass
class _ExplicitInfo:
    """What ``evaluate`` asks of ``model.scene``: an explicit scene has Gaussians, no anchors."""

    num_gaussians: int
    means: np.ndarray | None = None  # [N, 3]
    num_anchors: None = None

    def bounds(self) -> np.ndarray:
        """[2, 3] axis-aligned bounds of the Gaussians' centres, robust to floaters: their 1st and 99th
        percentiles from 100 Gaussians on (zeros when there are none)."""
        if self.means is None or len(self.means) == 0:
            return np.zeros((2, 3))
        m = self.means.astype(np.float64)
        return np.percentile(m, [1, 99], axis=0) if len(m) >= 100 else np.stack([m.min(0), m.max(0)])


@dataclass
class ExplicitModel:
    """An INRIA 3DGS PLY rendered as plain 3DGS (SH colours, no gate): the eval counterpart of ``SceneModel``."""

    ply: GaussianPly
    background: tuple[float, float, float] = PLY_BACKGROUND
    meta: dict = field(default_factory=dict)
    cameras: list | None = None
    antialiased: bool = False  # the file says it was trained with the antialiased filter: rendered with it

    @property
    def gate(self) -> GateConfig:
        return plain_gate(self.antialiased)

    def __post_init__(self) -> None:
        g = self.ply
        self._means = torch.from_numpy(g.means.copy())
        self._sh = torch.from_numpy(g.sh.copy())
        self._op = torch.sigmoid(torch.from_numpy(g.opacities.copy()))
        self._scales = torch.exp(torch.from_numpy(g.scales.copy()))
        self._quats = torch.from_numpy(g.quats.copy())

    @property
    def num_gaussians(self) -> int:
        return self.ply.n_gaussians

    @property
    def device(self) -> torch.device:
        return self._means.device

    def to(self, device) -> ExplicitModel:
        """This model rendering on ``device`` (a copy; itself when already there)."""
        if torch.device(device) == self.device:
            return self
        out = copy.copy(self)
        for k in ("_means", "_sh", "_op", "_scales", "_quats"):
            setattr(out, k, getattr(self, k).to(device))
        return out

    @property
    def scene(self) -> _ExplicitInfo:
        return _ExplicitInfo(self.ply.n_gaussians, self.ply.means)

    def render(self, camera, xi: float = 1.0, *, backend: str = "auto",
               size: tuple[int, int] | None = None) -> RenderResult:
        cam = camera.scaled(xi) if size is None else camera.sized(*size)
        with torch.no_grad():
            colors = sh_colors(self._sh, self._means, cam.center, self.ply.sh_degree)
            return render_gaussians(self._means, self._quats, self._scales, self._op, colors, cam,
                                    background=self.background, gate=self.gate, backend=backend)

    @staticmethod
    def load(path: str | os.PathLike, background=None) -> ExplicitModel:
        """The 3DGS file at ``path`` (an INRIA PLY, an SPZ or a GLB: ``formats.splats``), with the views of a 3DGS ``cameras.json`` beside it (or two folders up, 3DGS's
        output layout) when there is one, else an orbit around its Gaussians. ``background``: RGB in [0, 1]; None:
        the one the PLY was trained on (``ply_background``)."""
        from .camera import default_cameras
        from .scaffold_gs import find_cameras_json, read_scaffold_cameras

        from .formats.splats import read_splats

        ply, info = read_splats(path)
        cj = find_cameras_json(path)
        bg, where = ply_background(path) if background is None else (tuple(float(b) for b in background), "given")
        aa = bool(info.get("antialiased", False))
        model = ExplicitModel(ply, bg, {"kind": "inria-3dgs", "source": str(Path(path)), "background_from": where,
                                        "file_kind": info["kind"], "antialiased": aa}, antialiased=aa)
        model.cameras = read_scaffold_cameras(cj) if cj else default_cameras(None, model.scene.bounds())
        return model
