"""Training an anchor scene from posed images: ``proxycodec fit`` (issue #4).

Stage 1 is Scaffold-GS training made resolution-aware: every iteration draws xi ~ U[xi_min, xi_max], renders the
scene at ``camera.scaled(xi)`` with the FiLM resolution embedding and the pixel coverage gate on (the gate is part of
the projection, so it is trained jointly through autograd), and compares with the dataset's anti-aliased image at
that size; loss (1 - 0.2) L1 + 0.2 D-SSIM + 0.01 * mean volume of the neural Gaussians. Anchors grow where the mean
view-space gradient of their neural Gaussians is high and are pruned where their opacity stays low (Scaffold-GS's
``adjust_anchor``). Stage 2 freezes the anchor set, picks proxy anchors (density-aware, rho = 0.3) and trains the
residual predictor jointly: leaves are rendered with PREDICTED features and L_recon (MSE + 0.1 (1 - cos), 20% of
leaves per iteration, against the leaves' stage-1 features) is added with lambda 0.1, then 0.01 from 2/3 of training.

Schedules are fractions of the run (``FitConfig`` documents each), so the same config serves ``iters`` and a wall
time budget. Everything random draws from one numpy generator whose state is checkpointed: with ``iters`` (and no
time budget) a run is deterministic for a seed, and a resumed run continues exactly where the checkpoint was taken.

Checkpoints and outputs are our own containers (raw arrays + JSON), written atomically; nothing is pickled.
"""

from __future__ import annotations

import contextlib
import math
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .camera import Camera
from .decoder import DecoderConfig, GaussianDecoder, visible_anchors
from .errors import ProxycodecError
from .metrics import dssim, mse_to_psnr
from .model import SceneModel, render_scene, weights_path_for
from .netconfig import PredictorConfig
from .render.project import GateConfig
from .scene import AnchorScene

__all__ = [
    "CHECKPOINT_KIND",
    "FIT_KIND",
    "FitConfig",
    "FitResult",
    "TrainableAnchors",
    "Trainer",
    "checkpoint_path_for",
    "fit",
    "save_fitted",
]

CHECKPOINT_KIND = "proxycodec.fit-checkpoint"
CHECKPOINT_VERSION = 1
FIT_KIND = "proxycodec.fit"


# ================================================================================================ configuration
def check_run_length(iters: int | None, time_budget: float | None, max_width: int | None) -> None:
    """The options every trainer shares: a number of iterations and/or a time budget; a sane reference width."""
    if iters is None and time_budget is None:
        raise ProxycodecError("give a number of iterations, a time budget, or both")
    if iters is not None and int(iters) < 1:
        raise ProxycodecError(f"iterations must be >= 1, got {iters}")
    if time_budget is not None and not (time_budget > 0):
        raise ProxycodecError(f"time budget must be positive, got {time_budget}")
    if max_width is not None and int(max_width) < 8:
        raise ProxycodecError(f"max width must be >= 8 pixels, got {max_width}")


@dataclass(frozen=True)
class FitConfig:
    """Everything that determines a training run. Fractions are of the whole run (iterations or time budget)."""

    # run length and resolution
    iters: int | None = 3000  # None: run until time_budget
    time_budget: float | None = None  # seconds of training (checkpoint/eval time excluded); None: iters only
    seed: int = 0
    max_width: int | None = 1600  # 3DGS rule: the 100% reference is the image downscaled to this width
    xi_min: float = 0.1
    xi_max: float = 1.0
    fixed_res: bool = False  # ablation: xi = 1 always (plain single-resolution training)
    # model
    embedding: str = "film"  # "film" | "additive" | "none"
    gate: bool = True  # pixel coverage gate on during training and rendering
    gate_kappa: float = 4.0
    gate_eta: float = 0.25
    feat_dim: int = 32
    n_offsets: int = 10
    proxies: bool = True  # stage 2 (proxy anchors + residual predictor); False: Scaffold-GS only
    # initialisation
    voxel_size: float = 0.0  # <= 0: auto = extent / voxel_divisions
    voxel_divisions: int = 128
    init_points: int = 5_000  # random points in the bounds when the dataset has no SfM points (Blender)
    max_init_anchors: int = 40_000  # voxelised SfM points beyond this are subsampled
    # loss
    lambda_dssim: float = 0.2
    lambda_volume: float = 0.01
    # Added to the opacity head's bias at initialisation. Scaffold-GS starts it at PyTorch's default (about
    # +-0.18), so about half the neural Gaussians start with opacity <= 0 (never drawn, no gradient) and, with
    # zero-initialised features, the rest move together: on mic (random init, 85% background) every Gaussian
    # was below zero after 20 iterations and the scene died. +0.5 starts them at opacity 0.3-0.6, like 3DGS's
    # visible-at-start init; empty-space Gaussians then fade with gradient instead of vanishing without one.
    opacity_bias_init: float = 0.5
    # learning rates (Scaffold-GS defaults; exponential decay init -> final over the run)
    lr_feature: float = 0.0075
    lr_offset: tuple[float, float] = (0.01, 0.0001)
    lr_scaling: float = 0.007
    lr_mlp_opacity: tuple[float, float] = (0.002, 0.00002)
    lr_mlp_cov: tuple[float, float] = (0.004, 0.004)
    lr_mlp_color: tuple[float, float] = (0.008, 0.00005)
    lr_mlp_embed: tuple[float, float] = (0.004, 0.00004)
    lr_predictor: tuple[float, float] = (0.002, 0.00002)
    # anchor growing / pruning (Scaffold-GS adjust_anchor; its 500/1500/15000 of 30000 iterations as fractions)
    start_stat: float = 0.0167
    update_from: float = 0.05
    update_until: float = 0.5
    update_interval: int = 100  # at most this many iterations between adjustments (Scaffold-GS: 100 of 30k)
    update_interval_frac: float = 1.0 / 150  # ... and about this fraction of the run, at least 10 iterations
    success_threshold: float = 0.8
    grad_threshold: float = 0.0002
    min_opacity: float = 0.005
    update_depth: int = 3
    update_init_factor: int = 16
    update_hierarchy_factor: int = 4
    max_anchors: int = 200_000  # growth stops beyond this (a memory/time guard for CPU runs)
    # stage 2
    stage2_start: float = 0.5  # = update_until: the anchor set is final from here on
    recon_switch: float = 2.0 / 3.0  # the paper's 20k of 30k
    lambda_recon: tuple[float, float] = (0.1, 0.01)
    # lambda_recon in joint stage 2: this constant, or None for the paper's schedule above (supplement Table 10).
    # [D] 0: on lego (200 px, 4000 iterations) any weight of the paper's size lets L_recon (pulling predicted leaf
    # features to their frozen stage-1 values) outweigh the rendering loss in the predictor's Adam updates: the
    # schedule scored 28.705 dB, fixed 0.01 28.66, 0 29.084 (no proxies: 29.375). The warm-up still uses L_recon.
    lambda_recon_fixed: float | None = 0.0
    recon_loss: str = "mse+cos"  # ablation (supplement Table 6): "mse+cos" | "mse" | "l1"
    predictor: str = "residual"  # ablation (supplement Table 5): "residual" | "proxy-leaf-mlp" (fit/eval only)
    leaf_sample: float = 0.2
    proxy_ratio: float = 0.3
    proxy_cell: float = 0.0  # <= 0: proxy.default_cell_size (~10 anchors per occupied cell)
    proxy_selection: str = "random"  # "random" (the paper's) | "spread" (greedy k-median per cell; proxy.py)
    predictor_hidden: int = 64
    predictor_blocks: int = 2
    predictor_warmup: int = 300  # L_recon-only predictor iterations at the stage switch (no rendering)
    predictor_context: int = 1  # proxies the residual predictor sees per leaf (1: the paper's nearest proxy)
    # The predictor is born at the stage switch: its learning rate decays over stage 2 (lr_predictor[0] at the
    # switch). False: over the whole run, as the other groups (a predictor born at p = 0.5 then starts at 1/10).
    predictor_lr_stage2: bool = True
    # [D] the decoder MLPs' learning-rate schedules restart at the stage switch too (their init -> final over
    # stage 2): they must re-fit to predicted leaf features (+0.11 dB on lego at 200 px)
    decoder_lr_stage2: bool = True
    predict_offsets: bool = False  # stage 2 also predicts (and renders) the leaves' offsets; L_recon adds their MSE
    # bookkeeping
    image_cache_mb: int = 2048  # decoded 100% training images kept (float16); beyond this they are re-read
    backend: str = "auto"
    checkpoint_every: float = 300.0  # seconds between checkpoints (0: never, except on interrupt)
    log_every: float = 10.0  # seconds between progress lines

    def __post_init__(self) -> None:
        check_run_length(self.iters, self.time_budget, self.max_width)
        if not (0.025 <= self.xi_min <= self.xi_max <= 2.0):
            raise ProxycodecError(f"resolution range [{self.xi_min}, {self.xi_max}] must lie in [0.025, 2]")
        DecoderConfig(embedding=self.embedding)  # validates the name
        if not (0 < self.proxy_ratio <= 1) or not (0 < self.leaf_sample <= 1):
            raise ProxycodecError("proxy ratio and leaf sample fraction must be in (0, 1]")
        PredictorConfig(hidden=self.predictor_hidden, n_blocks=self.predictor_blocks,
                        context=self.predictor_context)  # validates width, depth and context
        if self.predictor_warmup < 0:
            raise ProxycodecError(f"predictor warm-up must be >= 0 iterations, got {self.predictor_warmup}")
        from .proxy import PREDICTOR_KINDS, RECON_LOSSES, check_proxy_selection

        if self.recon_loss not in RECON_LOSSES:
            raise ProxycodecError(f"unknown reconstruction loss {self.recon_loss!r}; choose from "
                                  f"{', '.join(RECON_LOSSES)}")
        check_proxy_selection(self.proxy_selection)
        if self.predict_offsets and self.predictor != "residual":
            raise ProxycodecError("predicting offsets needs the residual predictor")
        if self.predictor not in PREDICTOR_KINDS:
            raise ProxycodecError(f"unknown predictor {self.predictor!r}; choose from {', '.join(PREDICTOR_KINDS)}")
        if self.lambda_recon_fixed is not None and not (math.isfinite(self.lambda_recon_fixed)
                                                        and self.lambda_recon_fixed >= 0):
            raise ProxycodecError(f"fixed lambda_recon must be >= 0, got {self.lambda_recon_fixed}")
        if not (math.isfinite(self.gate_kappa) and self.gate_kappa > 0 and math.isfinite(self.gate_eta)):
            raise ProxycodecError(f"gate kappa must be positive and eta finite, got kappa {self.gate_kappa}, "
                                  f"eta {self.gate_eta}")

    def to_json(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}

    @staticmethod
    def from_json(d: dict) -> FitConfig:
        kw = {}
        for f in fields(FitConfig):
            if f.name in d:
                v = d[f.name]
                kw[f.name] = tuple(v) if isinstance(v, list) else v
        return FitConfig(**kw)

    def decoder_config(self, center, radius: float) -> DecoderConfig:
        return DecoderConfig(feat_dim=self.feat_dim, n_offsets=self.n_offsets, embedding=self.embedding,
                             scene_center=tuple(float(c) for c in center), scene_radius=float(radius),
                             film_xi_range=(1.0, 1.0) if self.fixed_res else (self.xi_min, self.xi_max),
                             gate=GateConfig(self.gate, self.gate_kappa, self.gate_eta))


def _exp_lr(init: float, final: float, t: float) -> float:
    """Scaffold-GS's get_expon_lr_func without delay: log-linear from init to final as t goes 0 -> 1."""
    t = min(max(t, 0.0), 1.0)
    if init <= 0 or final <= 0:
        return init * (1 - t) + final * t
    return math.exp(math.log(init) * (1 - t) + math.log(final) * t)


# ================================================================================================ trainable anchors
class TrainableAnchors:
    """Anchor tensors being optimised (positions fixed on the voxel grid, as in Scaffold-GS) -> ``AnchorScene``."""

    TRAINED = ("features", "offsets", "scalings")

    def __init__(self, positions: torch.Tensor, features: torch.Tensor, offsets: torch.Tensor,
                 scalings: torch.Tensor, voxel_size: float):
        self.positions = positions.detach().float().contiguous()  # [M, 3]
        self.features = features.detach().float().clone().requires_grad_(True)  # [M, F]
        self.offsets = offsets.detach().float().clone().requires_grad_(True)  # [M, K, 3]
        self.scalings = scalings.detach().float().clone().requires_grad_(True)  # [M, 6] log
        self.voxel_size = float(voxel_size)

    @property
    def num_anchors(self) -> int:
        return int(self.positions.shape[0])

    @property
    def n_offsets(self) -> int:
        return int(self.offsets.shape[1])

    def scene(self, features: torch.Tensor | None = None, metadata: dict | None = None) -> AnchorScene:
        """The live scene (tensors carry gradients)."""
        return AnchorScene(self.positions, self.features if features is None else features, self.offsets,
                           self.scalings, self.voxel_size, metadata or {})

    def export(self, features: torch.Tensor | None = None, metadata: dict | None = None,
               offsets: torch.Tensor | None = None) -> AnchorScene:
        f = self.features if features is None else features
        o = self.offsets if offsets is None else offsets
        return AnchorScene(self.positions.clone(), f.detach().clone(), o.detach().clone(),
                           self.scalings.detach().clone(), self.voxel_size, dict(metadata or {})).validate()

    def tensors(self) -> dict[str, torch.Tensor]:
        return {"features": self.features, "offsets": self.offsets, "scalings": self.scalings}

    def keep(self, index: torch.Tensor) -> None:
        self.positions = self.positions[index].contiguous()
        for name in self.TRAINED:
            setattr(self, name, getattr(self, name).detach()[index].clone().requires_grad_(True))

    def append(self, positions, features, offsets, scalings) -> None:
        self.positions = torch.cat([self.positions, positions.float()]).contiguous()
        for name, new in (("features", features), ("offsets", offsets), ("scalings", scalings)):
            old = getattr(self, name).detach()
            setattr(self, name, torch.cat([old, new.float()]).requires_grad_(True))


# ================================================================================================ optimiser
class _Adam:
    """Adam over named tensors (3DGS's eps = 1e-15) whose rows can be appended or dropped between steps.

    torch.optim.Adam would need "optimizer surgery" for anchor growing and pickling for checkpoints; this keeps
    the moments as plain tensors that follow the anchor rows and serialise as raw arrays.
    """

    def __init__(self, betas=(0.9, 0.999), eps=1e-15):
        self.b1, self.b2 = betas
        self.eps = eps
        self.params: dict[str, torch.Tensor] = {}
        self.m: dict[str, torch.Tensor] = {}
        self.v: dict[str, torch.Tensor] = {}
        self.step_count: dict[str, int] = {}

    def add(self, name: str, p: torch.Tensor) -> None:
        self.params[name] = p
        self.m.setdefault(name, torch.zeros_like(p.detach()))
        self.v.setdefault(name, torch.zeros_like(p.detach()))
        self.step_count.setdefault(name, 0)

    def rebind(self, name: str, p: torch.Tensor, keep: torch.Tensor | None = None, append: int = 0) -> None:
        """The tensor ``name`` was replaced: rows ``keep`` survive (in order), then ``append`` zero rows follow."""
        m, v = self.m[name], self.v[name]
        if keep is not None:
            m, v = m[keep], v[keep]
        if append:
            z = torch.zeros((append,) + tuple(m.shape[1:]), dtype=m.dtype)
            m, v = torch.cat([m, z]), torch.cat([v, z])
        self.m[name], self.v[name] = m.contiguous(), v.contiguous()
        self.params[name] = p

    @torch.no_grad()
    def step(self, lrs: dict[str, float]) -> None:
        for name, p in self.params.items():
            g = p.grad
            lr = lrs.get(name, 0.0)
            if g is None or lr == 0.0:
                continue
            self.step_count[name] += 1
            t = self.step_count[name]
            m, v = self.m[name], self.v[name]
            m.mul_(self.b1).add_(g, alpha=1 - self.b1)
            v.mul_(self.b2).addcmul_(g, g, value=1 - self.b2)
            denom = (v / (1 - self.b2**t)).sqrt_().add_(self.eps)
            p.addcdiv_(m, denom, value=-lr / (1 - self.b1**t))

    def zero_grad(self) -> None:
        for p in self.params.values():
            p.grad = None

    def state_arrays(self) -> dict[str, np.ndarray]:
        out = {}
        for name in self.params:
            out[f"adam_m/{name}"] = self.m[name].numpy().copy()
            out[f"adam_v/{name}"] = self.v[name].numpy().copy()
        return out

    def load_arrays(self, arrays: dict[str, np.ndarray], steps: dict[str, int]) -> None:
        for name, p in self.params.items():
            for kind, store in (("adam_m", self.m), ("adam_v", self.v)):
                a = arrays.get(f"{kind}/{name}")
                if a is None or tuple(a.shape) != tuple(p.shape):
                    raise ProxycodecError(f"checkpoint optimiser state {kind}/{name} is missing or has a wrong shape")
                store[name] = torch.from_numpy(np.array(a, dtype=np.float32))
            self.step_count[name] = int(steps.get(name, 0))


# ================================================================================================ initialisation
def _voxelise(points: np.ndarray, voxel: float) -> np.ndarray:
    """Scaffold-GS: unique(round(p / v)) * v."""
    cells = np.unique(np.round(points / voxel).astype(np.int64), axis=0)
    return cells.astype(np.float64) * voxel


def _knn_scale(points: np.ndarray) -> np.ndarray:
    """[N] sqrt of the mean squared distance to the 3 nearest neighbours (3DGS's distCUDA2), floored."""
    from scipy.spatial import cKDTree

    n = len(points)
    if n < 2:
        return np.full(n, 0.01)
    k = min(4, n)
    d, _ = cKDTree(points).query(points, k=k)
    d2 = (d[:, 1:] ** 2).mean(1)
    return np.sqrt(np.maximum(d2, 1e-7))


def initial_points(data, n_random: int, rng: np.random.Generator, what: str
                   ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray, float]:
    """-> (points [N, 3] float64, their SfM colours [N, 3] 0..255 or None, bounds [2, 3], extent): the dataset's SfM
    points within half an extent of its bounds, or (Blender, no SfM points) ``n_random`` uniform points in the
    bounds, 3DGS/Scaffold-GS's random init for NeRF-Synthetic. Shared by the anchor and the explicit trainers."""
    bounds = np.asarray(data.bounds, dtype=np.float64)
    extent = float((bounds[1] - bounds[0]).max())
    if extent <= 0 or not math.isfinite(extent):
        raise ProxycodecError(f"dataset bounds are empty; cannot place initial {what}")
    pts = data.points
    if pts is not None and len(pts) >= 8:
        pts = np.asarray(pts, dtype=np.float64)
        inside = ((pts >= bounds[0] - 0.5 * extent) & (pts <= bounds[1] + 0.5 * extent)).all(1)
        colors = None if data.point_colors is None else np.asarray(data.point_colors, dtype=np.float64)[inside]
        return pts[inside], colors, bounds, extent
    return bounds[0] + rng.random((n_random, 3)) * (bounds[1] - bounds[0]), None, bounds, extent


def initial_anchors(data, cfg: FitConfig, rng: np.random.Generator) -> tuple[np.ndarray, float, np.ndarray, float]:
    """-> (anchor positions [M, 3], voxel size, scene centre [3], scene radius) from the dataset."""
    pts, _, bounds, extent = initial_points(data, cfg.init_points, rng, "anchors")
    voxel = cfg.voxel_size if cfg.voxel_size > 0 else extent / cfg.voxel_divisions
    anchors = _voxelise(pts, voxel)
    if len(anchors) > cfg.max_init_anchors:
        anchors = anchors[np.sort(rng.choice(len(anchors), cfg.max_init_anchors, replace=False))]
    if len(anchors) == 0:
        raise ProxycodecError("no initial anchors")
    center = 0.5 * (bounds[0] + bounds[1])
    radius = max(0.5 * float(np.linalg.norm(bounds[1] - bounds[0])), 1e-6)
    return anchors, float(voxel), center, radius


# ================================================================================================ targets
class _TargetImages:
    """Training targets at any xi: the dataset's 100% image (kept in a byte-bounded float16 LRU cache) area-resized
    with the dataset's own filter (``formats.images.resize_image``: PIL BOX, the exact area average).

    ``PosedImages.load_image(i, xi)`` decodes the file on every new size; with a random xi per iteration that is
    ~0.1 s per iteration on lego, the cost of a whole rendering step at low resolution. The 100% image is the
    dataset's anti-aliased reference, so a target is the area average of the reference (within float16 rounding,
    < 5e-4) rather than of the file's pixels directly; evaluation always uses ``load_image``.
    """

    def __init__(self, data, max_bytes: int):
        from collections import OrderedDict

        self.data = data
        self.max_bytes = int(max_bytes)
        self.items: OrderedDict[int, np.ndarray] = OrderedDict()
        self.nbytes = 0

    def reference(self, i: int) -> np.ndarray:
        a = self.items.get(i)
        if a is not None:
            self.items.move_to_end(i)
            return a
        a = self.data.load_image(i, 1.0).numpy().astype(np.float16)
        if a.nbytes <= self.max_bytes:
            self.items[i] = a
            self.nbytes += a.nbytes
            while self.nbytes > self.max_bytes:
                _, old = self.items.popitem(last=False)
                self.nbytes -= old.nbytes
        return a

    def get(self, i: int, xi: float) -> torch.Tensor:
        from .formats.images import resize_image

        ref = self.reference(i)
        w, h = self.data.image_size(i, xi)
        return torch.from_numpy(resize_image(ref.astype(np.float32), w, h))


# ================================================================================================ the trainer
@dataclass
class FitResult:
    model: SceneModel
    iterations: int
    seconds: float
    history: list[dict] = field(default_factory=list)
    extra_meta: dict = field(default_factory=dict)
    extra_arrays: dict = field(default_factory=dict)


def checkpoint_path_for(out_ply: str | os.PathLike) -> Path:
    p = Path(out_ply)
    return p.with_name(p.stem + ".ckpt.pxc")


ProgressFn = Callable[[str], None]


class RunSchedule:
    """Where a run stands: ``cfg.iters`` and/or ``cfg.time_budget`` against ``iteration`` and ``elapsed`` (shared by
    the anchor and the explicit trainers)."""

    def _start_run(self) -> None:
        """The run state both trainers keep (and checkpoint, where they do)."""
        self.iteration = 0
        self.elapsed = 0.0
        self.view_stack: list[int] = []
        self.history: list[dict] = []
        self.ema_loss: float | None = None
        self.ema_psnr: float | None = None

    def _next_view(self) -> int:
        """Training views in random order, each once per epoch (``self.rng``)."""
        if not self.view_stack:
            self.view_stack = [int(i) for i in self.rng.permutation(self.data.train_indices)]
        return self.view_stack.pop()

    def progress(self) -> float:
        c = self.cfg
        p = 0.0
        if c.iters is not None:
            p = self.iteration / c.iters
        if c.time_budget is not None:
            p = max(p, self.elapsed / c.time_budget)
        return min(p, 1.0)

    def done(self) -> bool:
        return self.progress() >= 1.0

    def expected_iterations(self) -> float:
        """The run's length in iterations: ``iters``, or extrapolated from the pace so far under a time budget."""
        c = self.cfg
        if c.time_budget is None:
            return float(c.iters)
        p = self.progress()
        est = self.iteration / p if p > 0.02 and self.iteration > 0 else float(c.iters or 1e9)
        return min(est, float(c.iters)) if c.iters is not None else est


class Trainer(RunSchedule):
    """Owns the anchors, the decoder, the predictor, the optimiser and the running statistics of one fit."""

    def __init__(self, data, config: FitConfig, dataset_root: str = "", log: ProgressFn | None = None):
        self.data = data
        self.cfg = config
        self.dataset_root = dataset_root
        self.log = log or (lambda s: None)
        self.bg = torch.tensor(data.background, dtype=torch.float32)
        if not data.train_indices:
            raise ProxycodecError("the dataset has no training images")
        self.rng = np.random.default_rng(config.seed)
        self.images = _TargetImages(data, config.image_cache_mb << 20)
        torch.manual_seed(config.seed)
        anchors, voxel, center, radius = initial_anchors(data, config, self.rng)
        M, K, Fd = len(anchors), config.n_offsets, config.feat_dim
        scale = np.log(_knn_scale(anchors))
        self.anchors = TrainableAnchors(
            torch.tensor(anchors, dtype=torch.float32), torch.zeros(M, Fd), torch.zeros(M, K, 3),
            torch.tensor(np.repeat(scale[:, None], 6, 1), dtype=torch.float32), voxel)
        self.decoder = GaussianDecoder(config.decoder_config(center, radius))
        with torch.no_grad():  # Gaussians start visible (see FitConfig.opacity_bias_init)
            self.decoder.mlp_opacity[-1].bias.add_(config.opacity_bias_init)
        self.predictor = None
        self.proxy_mask: torch.Tensor | None = None  # [M] bool
        self.nearest: torch.Tensor | None = None  # [M] long
        self.leaf_target: torch.Tensor | None = None  # [L, F] stage-1 features of the leaves
        self.leaf_offset_target: torch.Tensor | None = None  # [L, K, 3] their stage-1 offsets (predict_offsets)
        self.leaves: torch.Tensor | None = None  # [L] long
        self.opt = _Adam()
        for k, t in self.anchors.tensors().items():
            self.opt.add(k, t)
        for k, p in self.decoder.named_parameters():
            self.opt.add(f"decoder.{k}", p)
        self._reset_stats()
        self._start_run()
        self.last_adjust = 0
        self.stage = 1

    # ------------------------------------------------------------------ running statistics (Scaffold-GS)
    def _reset_stats(self) -> None:
        M, K = self.anchors.num_anchors, self.anchors.n_offsets
        self.opacity_accum = torch.zeros(M, dtype=torch.float64)
        self.anchor_denom = torch.zeros(M, dtype=torch.float64)
        self.offset_grad_accum = torch.zeros(M * K, dtype=torch.float64)
        self.offset_denom = torch.zeros(M * K, dtype=torch.float64)

    # ------------------------------------------------------------------ schedule

    def learning_rates(self, p: float) -> dict[str, float]:
        c = self.cfg
        lrs: dict[str, float] = {"features": c.lr_feature, "offsets": _exp_lr(*c.lr_offset, p),
                                 "scalings": c.lr_scaling}
        groups = {"mlp_opacity": c.lr_mlp_opacity, "mlp_cov": c.lr_mlp_cov, "mlp_color": c.lr_mlp_color,
                  "mlp_embed": c.lr_mlp_embed}
        p2 = min(1.0, max(0.0, (p - c.stage2_start) / (1.0 - c.stage2_start))) if c.stage2_start < 1 else 1.0
        for name in self.opt.params:
            if name.startswith("decoder."):
                q = p2 if (c.decoder_lr_stage2 and self.stage >= 2) else p
                lrs[name] = _exp_lr(*groups[name.split(".")[1]], q)
            elif name.startswith("predictor."):
                lrs[name] = _exp_lr(*c.lr_predictor, p2 if c.predictor_lr_stage2 else p)
        return lrs

    def lambda_recon(self, p: float) -> float:
        if self.cfg.lambda_recon_fixed is not None:
            return float(self.cfg.lambda_recon_fixed)
        return self.cfg.lambda_recon[0] if p < self.cfg.recon_switch else self.cfg.lambda_recon[1]

    # ------------------------------------------------------------------ one iteration
    def _features_for(self, cam: Camera, with_recon: bool = True
                      ) -> tuple[torch.Tensor | None, torch.Tensor | None, torch.Tensor]:
        """Stage 2: the feature (and, with ``predict_offsets``, offset) tables with the visible leaves' rows
        predicted; and L_recon (0 without computing it when ``with_recon`` is False, i.e. its weight is 0: the
        leaf sample is still drawn, so the random stream does not depend on the weight)."""
        zero = torch.zeros(())
        if self.stage < 2 or self.predictor is None:
            return None, None, zero
        a = self.anchors
        po = self.cfg.predict_offsets
        vis = visible_anchors(a.positions, a.scene().extent_radius().detach(), cam)
        leaf_vis = vis[~self.proxy_mask[vis]]
        feats, offs = a.features, (a.offsets if po else None)
        if leaf_vis.numel():
            pred, pred_o = self.predictor.predict(a.positions, a.features, self.nearest, leaf_vis, offs)
            feats = a.features.index_put((leaf_vis,), pred)
            if po:
                offs = a.offsets.index_put((leaf_vis,), pred_o)
        # L_recon on a random 20% of all leaves (not only the visible ones) against their stage-1 values.
        L = int(self.leaves.numel())
        n = max(1, math.ceil(self.cfg.leaf_sample * L)) if L else 0
        if n == 0:
            return feats, offs, zero
        sel = torch.from_numpy(self.rng.choice(L, n, replace=False)).long()
        if not with_recon:
            return feats, offs, zero
        from .proxy import offset_recon_loss, recon_loss

        pred_s, pred_so = self.predictor.predict(a.positions, a.features, self.nearest, self.leaves[sel],
                                                 a.offsets if po else None)
        loss = recon_loss(pred_s, self.leaf_target[sel], kind=self.cfg.recon_loss)
        if po:  # the offset term of proxy.train_predictor (offset_weight 1)
            loss = loss + offset_recon_loss(pred_so, self.leaf_offset_target[sel])
        return feats, offs, loss

    def train_step(self) -> dict:
        c = self.cfg
        p = self.progress()
        if c.proxies and self.stage == 1 and p >= c.stage2_start:
            self.enter_stage2()
        i = self._next_view()
        xi = 1.0 if c.fixed_res else float(c.xi_min + (c.xi_max - c.xi_min) * self.rng.random())
        cam = self.data.cameras[i]
        gt = self.images.get(i, xi)  # [h, w, 3] anti-aliased to camera.scaled(xi)
        lam = self.lambda_recon(p) if self.stage >= 2 else 0.0
        feats, offs, l_recon = self._features_for(cam.scaled(xi), with_recon=lam != 0.0)
        r = render_scene(self.anchors.scene(), self.decoder, cam, xi, background=self.bg, backend=c.backend,
                         features=feats, offsets=offs)
        img = r.image
        l1 = (img - gt).abs().mean()
        loss = (1 - c.lambda_dssim) * l1 + c.lambda_dssim * dssim(img, gt)
        g = r.gaussians
        if g.count:
            loss = loss + c.lambda_volume * g.scales.prod(dim=1).mean()
        if lam != 0.0:
            loss = loss + lam * l_recon
        means2d = r.projected.means2d
        if means2d.requires_grad:
            means2d.retain_grad()
        self.opt.zero_grad()
        if loss.requires_grad:
            loss.backward()
        self._update_stats(r, img.shape[1], img.shape[0])
        self.opt.step(self.learning_rates(p))
        with torch.no_grad():
            mse = float(((img.detach().clamp(0, 1) - gt) ** 2).mean())
        self.iteration += 1
        self._maybe_adjust_anchors()
        return {"loss": float(loss.detach()), "psnr": mse_to_psnr(max(mse, 1e-10)), "xi": xi, "view": i,
                "gaussians": int(r.projected.count), "recon": float(l_recon.detach())}

    @torch.no_grad()
    def _update_stats(self, r, width: int, height: int) -> None:
        """Scaffold-GS's training_statis: opacity of visible anchors, view-space gradient of drawn Gaussians."""
        c = self.cfg
        if self.stage >= 2 or self.progress() >= c.update_until:
            return
        if self.progress() < c.start_stat:
            return
        g, proj = r.gaussians, r.projected
        K = self.anchors.n_offsets
        vis = r.visible_anchor_index
        self.anchor_denom[vis] += 1
        if g.count:
            self.opacity_accum.index_add_(0, g.anchor_index, g.opacities.detach().double())
        grad = proj.means2d.grad
        if grad is None or proj.count == 0:
            return
        # 3DGS measures the gradient in NDC-like units: d/d(ndc) = d/d(pixel) * (size / 2).
        gn = (grad.double() * torch.tensor([0.5 * width, 0.5 * height], dtype=torch.float64)).norm(dim=1)
        rows = proj.index
        flat = g.anchor_index[rows] * K + g.slot[rows]
        self.offset_grad_accum.index_add_(0, flat, gn)
        self.offset_denom.index_add_(0, flat, torch.ones_like(gn))

    # ------------------------------------------------------------------ growing and pruning
    def _maybe_adjust_anchors(self) -> None:
        c = self.cfg
        if self.stage >= 2:
            return
        p = self.progress()
        if c.update_from <= p < c.update_until and self.iteration - self.last_adjust >= self.update_interval():
            self.last_adjust = self.iteration
            self.adjust_anchors()

    def update_interval(self) -> int:
        """Iterations between anchor adjustments: Scaffold-GS's 100 in 30k scaled to short CPU runs (>= 10)."""
        c = self.cfg
        return int(min(c.update_interval, max(10, round(self.expected_iterations() * c.update_interval_frac))))

    @torch.no_grad()
    def adjust_anchors(self) -> None:
        c = self.cfg
        K = self.anchors.n_offsets
        grads = self.offset_grad_accum / self.offset_denom
        grads[~torch.isfinite(grads)] = 0.0
        interval = self.update_interval()
        offset_mask = self.offset_denom > interval * c.success_threshold * 0.5
        n_before = self.anchors.num_anchors
        if n_before < c.max_anchors:
            self._grow(grads, offset_mask)
        n_new = self.anchors.num_anchors - n_before
        # Reset the gradient statistics of the offsets that were judged; new anchors start at zero.
        self.offset_denom[offset_mask] = 0
        self.offset_grad_accum[offset_mask] = 0
        pad = torch.zeros(n_new * K, dtype=torch.float64)
        self.offset_denom = torch.cat([self.offset_denom, pad])
        self.offset_grad_accum = torch.cat([self.offset_grad_accum, pad])
        padm = torch.zeros(n_new, dtype=torch.float64)
        self.opacity_accum = torch.cat([self.opacity_accum, padm])
        self.anchor_denom = torch.cat([self.anchor_denom, padm])
        # Prune anchors seen often enough whose Gaussians stayed (nearly) transparent.
        prune = self.opacity_accum < c.min_opacity * self.anchor_denom
        judged = self.anchor_denom > interval * c.success_threshold
        prune &= judged
        self.opacity_accum[judged] = 0
        self.anchor_denom[judged] = 0
        if bool(prune.any()) and int((~prune).sum()) > 0:
            keep = (~prune).nonzero().squeeze(1)
            self._keep_anchors(keep)
        if n_new or bool(prune.any()):
            self.log(f"  anchors: +{n_new} grown, -{int(prune.sum())} pruned -> {self.anchors.num_anchors}")

    def _keep_anchors(self, keep: torch.Tensor) -> None:
        K = self.anchors.n_offsets
        self.anchors.keep(keep)
        for k, t in self.anchors.tensors().items():
            self.opt.rebind(k, t, keep=keep)
        flat = (keep[:, None] * K + torch.arange(K)).reshape(-1)
        self.offset_grad_accum = self.offset_grad_accum[flat]
        self.offset_denom = self.offset_denom[flat]
        self.opacity_accum = self.opacity_accum[keep]
        self.anchor_denom = self.anchor_denom[keep]

    def _grow(self, grads: torch.Tensor, offset_mask: torch.Tensor) -> None:
        """Scaffold-GS anchor_growing: new anchors in (coarse to fine) voxels holding high-gradient Gaussians."""
        c = self.cfg
        a = self.anchors
        K = a.n_offsets
        init_len = a.num_anchors * K
        for i in range(c.update_depth):
            threshold = c.grad_threshold * ((c.update_hierarchy_factor // 2) ** i)
            cand = (grads >= threshold) & offset_mask
            rand = torch.from_numpy(self.rng.random(cand.shape[0]) > 0.5 ** (i + 1))
            cand = cand & rand
            inc = a.num_anchors * K - init_len
            if inc == 0 and i > 0:
                continue
            if inc:
                cand = torch.cat([cand, torch.zeros(inc, dtype=torch.bool)])
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
            new_mask = torch.tensor([tuple(u) not in existing for u in uniq.tolist()], dtype=torch.bool)
            if not bool(new_mask.any()):
                continue
            new_pos = uniq[new_mask].double() * size
            n = int(new_pos.shape[0])
            if a.num_anchors + n > c.max_anchors:
                n = max(0, c.max_anchors - a.num_anchors)
                if n == 0:
                    return
            feats_rep = a.features.detach()[:, None, :].expand(-1, K, -1).reshape(-1, a.features.shape[1])[cand]
            Fd = feats_rep.shape[1]
            pooled = torch.full((uniq.shape[0], Fd), -torch.inf).scatter_reduce(
                0, inverse[:, None].expand(-1, Fd), feats_rep, reduce="amax", include_self=True)
            new_feat = pooled[new_mask][:n]
            new_pos = new_pos[:n].float()
            new_scal = torch.full((n, 6), math.log(size), dtype=torch.float32)
            new_off = torch.zeros(n, K, 3)
            a.append(new_pos, new_feat, new_off, new_scal)
            for k, t in a.tensors().items():
                self.opt.rebind(k, t, append=n)

    # ------------------------------------------------------------------ stage 2
    def _predictor_config(self):
        from .proxy import PredictorConfig, ProxyLeafConfig

        if self.cfg.predictor == "proxy-leaf-mlp":
            d = self.decoder.config
            return ProxyLeafConfig(feat_dim=self.cfg.feat_dim, n_offsets=self.cfg.n_offsets,
                                   hidden=self.cfg.predictor_hidden, n_blocks=self.cfg.predictor_blocks,
                                   scene_center=d.scene_center, scene_radius=d.scene_radius)
        return PredictorConfig(feat_dim=self.cfg.feat_dim, n_offsets=self.cfg.n_offsets,
                               hidden=self.cfg.predictor_hidden, n_blocks=self.cfg.predictor_blocks,
                               dist_ref=self.anchors.voxel_size, predict_offsets=self.cfg.predict_offsets,
                               context=self.cfg.predictor_context)

    def _setup_proxies(self, mask: np.ndarray) -> None:
        from .proxy import nearest_proxies, predictor_from_json

        a = self.anchors
        self.proxy_mask = torch.from_numpy(np.asarray(mask, dtype=bool))
        ctx = self.cfg.predictor_context if self.cfg.predictor == "residual" else 1
        self.nearest = torch.from_numpy(nearest_proxies(a.positions, mask, ctx)).long()  # [M, ctx]
        self.leaves = (~self.proxy_mask).nonzero().squeeze(1)
        if self.predictor is None:
            self.predictor = predictor_from_json(self._predictor_config().to_json())
        for k, p in self.predictor.named_parameters():
            self.opt.add(f"predictor.{k}", p)
        self.stage = 2

    def proxy_cell_size(self) -> float:
        from .proxy import default_cell_size

        c = self.cfg
        return c.proxy_cell if c.proxy_cell > 0 else default_cell_size(self.anchors.positions,
                                                                       self.anchors.voxel_size)

    def enter_stage2(self) -> None:
        """Freeze the anchor set, select proxies, warm the predictor up on L_recon alone, start joint training."""
        from .proxy import TrainConfig, select_proxies, train_predictor

        c = self.cfg
        a = self.anchors
        cell = self.proxy_cell_size()
        mask = select_proxies(a.positions, cell, c.proxy_ratio, c.seed, c.proxy_selection)
        self.leaf_target = a.features.detach()[torch.from_numpy(~mask)].clone()
        if c.predict_offsets:
            self.leaf_offset_target = a.offsets.detach()[torch.from_numpy(~mask)].clone()
        self._setup_proxies(mask)
        if c.predictor_warmup > 0 and self.leaves.numel():
            res = train_predictor(self.predictor, a.positions, a.features.detach(), mask, self.nearest.numpy(),
                                  offsets=a.offsets.detach() if c.predict_offsets else None,
                                  config=TrainConfig(iters=c.predictor_warmup, sample_frac=c.leaf_sample,
                                                     seed=c.seed), recon=c.recon_loss)
            warm = f"; predictor warm-up L_recon {res.baseline_loss:.4f} -> {res.final_loss:.4f}"
        else:
            warm = ""
        self.predictor.train()
        self.log(f"  stage 2 at iteration {self.iteration}: {int(mask.sum())} proxies / {a.num_anchors} anchors "
                 f"(cell {cell:.4g}){warm}")

    # ------------------------------------------------------------------ results
    @torch.no_grad()
    def final_features(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Features and offsets as stage 2 rendered them: the proxies' own; the leaves' predicted features (and
        predicted offsets with ``predict_offsets``)."""
        a = self.anchors
        f = a.features.detach().clone()
        o = a.offsets.detach().clone()
        if self.stage >= 2 and self.predictor is not None and self.leaves.numel():
            self.predictor.eval()
            po = self.cfg.predict_offsets
            pred, pred_o = self.predictor.predict(a.positions, a.features.detach(), self.nearest, self.leaves,
                                                  o if po else None)
            f[self.leaves] = pred
            if po:
                o[self.leaves] = pred_o
        return f, o

    def result(self) -> FitResult:
        a = self.anchors
        meta = {"name": Path(self.dataset_root).name if self.dataset_root else "fit"}
        feats, offs = self.final_features()
        scene = a.export(feats, meta, offs)
        dec = self.decoder
        dec.eval()
        cams = [self.data.cameras[i] for i in self.data.test_indices] + \
               [self.data.cameras[i] for i in self.data.train_indices]
        nt = len(self.data.test_indices)
        model = SceneModel(scene, dec, cams, tuple(self.data.background))
        fit_meta: dict[str, Any] = {
            "kind": FIT_KIND, "config": self.cfg.to_json(), "dataset": str(self.dataset_root),
            "iterations": self.iteration, "seconds": round(self.elapsed, 3),
            "camera_split": {"test": list(range(nt)), "train": list(range(nt, len(cams)))},
            "stage": self.stage,
        }
        arrays: dict[str, np.ndarray] = {}
        if self.stage >= 2 and self.predictor is not None:
            fit_meta["predictor"] = self.predictor.config.to_json()
            fit_meta["proxy_cell"] = self.proxy_cell_size()
            arrays["proxy_mask"] = self.proxy_mask.numpy().astype(np.uint8)
            for k, v in self.predictor.state_arrays().items():
                arrays[f"predictor/{k}"] = v
        return FitResult(model, self.iteration, self.elapsed, self.history, {"fit": fit_meta}, arrays)

    # ------------------------------------------------------------------ checkpoints
    def checkpoint_arrays(self) -> tuple[dict, dict]:
        a = self.anchors
        arrays: dict[str, np.ndarray] = {
            "anchors/positions": a.positions.numpy().copy(),
            "anchors/features": a.features.detach().numpy().copy(),
            "anchors/offsets": a.offsets.detach().numpy().copy(),
            "anchors/scalings": a.scalings.detach().numpy().copy(),
            "stats/opacity_accum": self.opacity_accum.numpy().copy(),
            "stats/anchor_denom": self.anchor_denom.numpy().copy(),
            "stats/offset_grad_accum": self.offset_grad_accum.numpy().copy(),
            "stats/offset_denom": self.offset_denom.numpy().copy(),
            "view_stack": np.asarray(self.view_stack, dtype=np.int64),
        }
        for k, v in self.decoder.state_arrays().items():
            arrays[f"decoder/{k}"] = v
        if self.stage >= 2:
            arrays["proxy_mask"] = self.proxy_mask.numpy().astype(np.uint8)
            arrays["leaf_target"] = self.leaf_target.numpy().copy()
            if self.cfg.predict_offsets:
                arrays["leaf_offset_target"] = self.leaf_offset_target.numpy().copy()
            for k, v in self.predictor.state_arrays().items():
                arrays[f"predictor/{k}"] = v
        arrays.update(self.opt.state_arrays())
        meta = {
            "kind": CHECKPOINT_KIND, "version": CHECKPOINT_VERSION, "config": self.cfg.to_json(),
            "dataset": str(self.dataset_root), "iteration": self.iteration, "elapsed": self.elapsed,
            "stage": self.stage, "last_adjust": self.last_adjust, "voxel_size": a.voxel_size, "decoder": self.decoder.config.to_json(),
            "rng": self.rng.bit_generator.state, "adam_steps": dict(self.opt.step_count),
            "ema_loss": self.ema_loss, "ema_psnr": self.ema_psnr, "history": self.history[-200:],
        }
        return meta, arrays

    def save_checkpoint(self, path: str | os.PathLike) -> None:
        from .formats.container import write_container

        meta, arrays = self.checkpoint_arrays()
        write_container(path, meta, arrays, level=3)

    def load_checkpoint(self, path: str | os.PathLike) -> None:
        from .formats.container import read_container
        from .proxy import predictor_from_json

        ck = read_container(path)
        m = ck.meta
        if m.get("kind") != CHECKPOINT_KIND or m.get("version") != CHECKPOINT_VERSION:
            raise ProxycodecError("not a fit checkpoint of this version", path)
        try:
            saved = FitConfig.from_json(m["config"])
            # Run length may change on resume; everything else must match.
            ignore = {"iters", "time_budget", "checkpoint_every", "log_every", "backend"}
            diff = [f.name for f in fields(FitConfig) if f.name not in ignore
                    and getattr(saved, f.name) != getattr(self.cfg, f.name)]
            if diff:
                raise ProxycodecError(f"checkpoint was made with different settings ({', '.join(diff[:5])}); "
                                      "resume with the same options or start afresh", path)
            arr = ck.arrays
            self.anchors = TrainableAnchors(
                torch.from_numpy(np.array(arr["anchors/positions"])), torch.from_numpy(np.array(arr["anchors/features"])),
                torch.from_numpy(np.array(arr["anchors/offsets"])), torch.from_numpy(np.array(arr["anchors/scalings"])),
                float(m["voxel_size"]))
            dcfg = DecoderConfig.from_json(m["decoder"])
            self.decoder = GaussianDecoder.from_arrays(
                dcfg, {k[len("decoder/"):]: v for k, v in arr.items() if k.startswith("decoder/")})
            self.opt = _Adam()
            for k, t in self.anchors.tensors().items():
                self.opt.add(k, t)
            for k, p in self.decoder.named_parameters():
                self.opt.add(f"decoder.{k}", p)
            self.stage = int(m["stage"])
            self.predictor = None
            if self.stage >= 2:
                self.predictor = predictor_from_json(
                    self._predictor_config().to_json() if "predictor" not in m else m["predictor"],
                    {k[len("predictor/"):]: v for k, v in arr.items() if k.startswith("predictor/")})
                self.leaf_target = torch.from_numpy(np.array(arr["leaf_target"]))
                if self.cfg.predict_offsets:
                    self.leaf_offset_target = torch.from_numpy(np.array(arr["leaf_offset_target"]))
                self._setup_proxies(np.asarray(arr["proxy_mask"], dtype=bool))
                self.predictor.train()
            self.opt.load_arrays(arr, m["adam_steps"])
            self.opacity_accum = torch.from_numpy(np.array(arr["stats/opacity_accum"]))
            self.anchor_denom = torch.from_numpy(np.array(arr["stats/anchor_denom"]))
            self.offset_grad_accum = torch.from_numpy(np.array(arr["stats/offset_grad_accum"]))
            self.offset_denom = torch.from_numpy(np.array(arr["stats/offset_denom"]))
            self.view_stack = [int(x) for x in arr["view_stack"]]
            self.iteration = int(m["iteration"])
            self.last_adjust = int(m.get("last_adjust", 0))
            self.elapsed = float(m["elapsed"])
            self.rng = np.random.default_rng()
            self.rng.bit_generator.state = m["rng"]
            self.ema_loss, self.ema_psnr = m.get("ema_loss"), m.get("ema_psnr")
            self.history = list(m.get("history", []))
        except KeyError as e:
            raise ProxycodecError(f"checkpoint is missing {e}", path) from None

    def checkpoint_meta_for_predictor(self) -> dict:
        return {"predictor": self.predictor.config.to_json()} if self.predictor is not None else {}


# ================================================================================================ saving
def save_fitted(result: FitResult, ply_path: str | os.PathLike) -> tuple[Path, Path]:
    """Write the anchor PLY and its weights sidecar as one atomic pair.

    Both files are first written into a temporary folder beside the target, then moved into place (weights first,
    the PLY last), so an interrupted save leaves no PLY without its weights. The sidecar is ``SceneModel.save``'s
    plus ``fit`` metadata and, after stage 2, the predictor weights (``predictor/*``) and the proxy mask.
    """
    ply_path = Path(ply_path)
    ply_path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{ply_path.name}.", suffix=".tmp", dir=ply_path.parent))
    try:
        tmp_ply = tmp / ply_path.name
        _save_model(result.model, tmp_ply, result.extra_meta, result.extra_arrays)
        os.replace(weights_path_for(tmp_ply), weights_path_for(ply_path))
        os.replace(tmp_ply, ply_path)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return ply_path, weights_path_for(ply_path)


def _save_model(model: SceneModel, ply_path: Path, extra_meta: dict, extra_arrays: dict) -> None:
    model.save(ply_path, extra_meta=extra_meta, extra_arrays=extra_arrays)


def load_predictor(weights_path: str | os.PathLike):
    """(predictor, proxy mask) stored by ``fit`` in a weights sidecar, or (None, None) when it has none.

    Also (None, None) for the Proxy&Leaf MLP ablation (``fit --predictor proxy-leaf-mlp``): the container stores
    residual predictors only, so ``encode`` selects proxies and fits a residual predictor of its own for such a scene
    (its PLY already holds the leaves' predicted features, which is what ``eval`` measures)."""
    from .formats.container import read_container
    from .proxy import PredictorConfig, ResidualPredictor

    c = read_container(weights_path)
    fit_meta = c.meta.get("fit", {})
    if "predictor" not in fit_meta:
        return None, None
    if isinstance(fit_meta["predictor"], dict) and fit_meta["predictor"].get("kind", "residual") != "residual":
        return None, None
    cfg = PredictorConfig.from_json(fit_meta["predictor"])
    pred = ResidualPredictor.from_arrays(cfg, {k[len("predictor/"):]: v for k, v in c.arrays.items()
                                               if k.startswith("predictor/")})
    return pred.eval(), np.asarray(c.arrays["proxy_mask"], dtype=bool)


# ================================================================================================ the loop
def _fmt_time(s: float) -> str:
    s = max(0, int(s))
    return f"{s // 3600:d}:{s % 3600 // 60:02d}:{s % 60:02d}" if s >= 3600 else f"{s // 60:02d}:{s % 60:02d}"



def timed_step(tr, log_every: float, last_log: float, log: ProgressFn, detail, hist_extra) -> tuple[dict, bool]:
    """One ``tr.train_step()``, timed into ``tr.elapsed``; EMA loss/PSNR; a progress line (and a history entry) at
    most every ``log_every`` seconds, on the first and on the last iteration. ``detail(st)``: the trainer's own
    fields for the line; ``hist_extra()``: its own history fields. Shared by the anchor and the explicit trainers.
    -> (the step's stats, whether a line was written)."""
    t0 = time.perf_counter()
    st = tr.train_step()
    tr.elapsed += time.perf_counter() - t0
    a = 0.05 if tr.ema_loss is not None else 1.0
    tr.ema_loss = st["loss"] if tr.ema_loss is None else (1 - a) * tr.ema_loss + a * st["loss"]
    tr.ema_psnr = st["psnr"] if tr.ema_psnr is None else (1 - a) * tr.ema_psnr + a * st["psnr"]
    if not (time.perf_counter() - last_log >= log_every or tr.done() or tr.iteration == 1):
        return st, False
    p = tr.progress()
    eta = tr.elapsed * (1 - p) / max(p, 1e-9)
    total = tr.cfg.iters if tr.cfg.iters is not None else "?"
    log(f"it {tr.iteration:6d}/{total}  loss {tr.ema_loss:.4f}  psnr {tr.ema_psnr:5.2f}  {detail(st)}  "
        f"{_fmt_time(tr.elapsed)} elapsed  eta {_fmt_time(eta)}")
    tr.history.append({"it": tr.iteration, "loss": round(tr.ema_loss, 6), "psnr": round(tr.ema_psnr, 4),
                       **hist_extra(), "seconds": round(tr.elapsed, 2)})
    return st, True


def fit(data, out_ply: str | os.PathLike, config: FitConfig = FitConfig(), *, dataset_root: str = "",
        resume: bool = False, log: ProgressFn | None = None, keep_checkpoint: bool = False,
        stop_after: int | None = None) -> FitResult:
    """Train on ``data`` (a ``PosedImages``) and write ``out_ply`` (+ weights sidecar) atomically.

    Checkpoints go to ``<out>.ckpt.pxc`` every ``config.checkpoint_every`` seconds and on interrupt/exception, and
    are removed after success unless ``keep_checkpoint``. ``resume`` continues from that checkpoint.
    ``stop_after`` (tests) raises ``KeyboardInterrupt`` after that many iterations of this call.
    """
    torch.set_num_threads(2)
    log = log or (lambda s: print(s, file=sys.stderr, flush=True))
    ckpt = checkpoint_path_for(out_ply)
    t_setup = time.perf_counter()
    tr = Trainer(data, config, dataset_root, log)
    if resume:
        if not ckpt.exists():
            raise ProxycodecError("no checkpoint to resume from", ckpt)
        tr.load_checkpoint(ckpt)
        log(f"resumed from {ckpt} at iteration {tr.iteration} ({_fmt_time(tr.elapsed)} trained)")
    log(f"fit: {len(data.train_indices)} training views, {tr.anchors.num_anchors} anchors "
        f"(voxel {tr.anchors.voxel_size:.4g}), setup {time.perf_counter() - t_setup:.1f} s; "
        f"iters {config.iters}, time budget {config.time_budget}")
    last_ckpt = last_log = time.perf_counter()
    n_this_call = 0
    try:
        while not tr.done():
            _, logged = timed_step(tr, config.log_every, last_log, log, lambda st: (
                f"xi {st['xi']:.2f}  gauss {st['gaussians']:7d}  anchors {tr.anchors.num_anchors:6d}  "
                f"stage {tr.stage}"), lambda: {"anchors": tr.anchors.num_anchors})
            n_this_call += 1
            now = time.perf_counter()
            last_log = now if logged else last_log
            if config.checkpoint_every > 0 and now - last_ckpt >= config.checkpoint_every and not tr.done():
                tr.save_checkpoint(ckpt)
                last_ckpt = time.perf_counter()
            if stop_after is not None and n_this_call >= stop_after:
                raise KeyboardInterrupt
        res = tr.result()
        save_fitted(res, out_ply)
    except BaseException:
        # Interrupt or error (while training or saving): keep the work, never a partial output.
        with contextlib.suppress(Exception):
            tr.save_checkpoint(ckpt)
            log(f"checkpoint saved at iteration {tr.iteration}: {ckpt} (continue with --resume)")
        raise
    if not keep_checkpoint:
        with contextlib.suppress(FileNotFoundError):
            ckpt.unlink()
    log(f"done: {tr.iteration} iterations in {_fmt_time(tr.elapsed)}, {tr.anchors.num_anchors} anchors -> "
        f"{out_ply}")
    return res
