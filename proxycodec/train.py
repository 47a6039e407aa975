"""Training an anchor scene from posed images: ``proxycodec fit``.

Stage 1 is Scaffold-GS training made resolution-aware: every iteration draws xi ~ U[xi_min, xi_max], renders the
scene at ``camera.scaled(xi)`` with the FiLM resolution embedding and the pixel coverage gate on (the gate is part of
the projection, so it is trained jointly through autograd), and compares with the dataset's anti-aliased image at
that size; loss (1 - 0.2) L1 + 0.2 D-SSIM + 0.01 * mean volume of the neural Gaussians. Anchors grow where the mean
view-space gradient of their neural Gaussians is high and are pruned where their opacity stays low
(``strategy.ScaffoldStrategy``). Stage 2 freezes the anchor set, picks proxy anchors (density-aware, rho = 0.3) and
trains the residual predictor jointly: leaves are rendered with PREDICTED features.

The iteration itself is the shared loop of ``loop.TrainingRun``; schedules are fractions of the run (``FitConfig``
documents each), so the same config serves ``iters`` and a wall time budget. Everything random draws from one numpy
generator whose state is checkpointed: with ``iters`` (and no time budget) a run is deterministic for a seed, and a
resumed run continues exactly where the checkpoint was taken.

Checkpoints and outputs are our own containers (raw arrays + JSON), written atomically; nothing is pickled.
"""

from __future__ import annotations

import functools
import math
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .decoder import DecoderConfig, GaussianDecoder
from .devices import as_device, generator, synchronize, upload
from .entropy_fit import RateModel
from .errors import ProxycodecError
from .formats.container import read_container
from .loop import (
    ProgressFn, TargetImages, TrainingRun, check_run_length, check_xi_sampling, checkpoint_path_for, fmt_time,
    has_sfm_points, initial_points, knn_scale, photometric_loss, run_checkpointed, timed_step, warm_up_renderer,
)
from .model import SceneModel, render_scene, scene_visible, weights_path_for
from .netconfig import PredictorConfig
from .optim import Adam, exp_lr
from .proxy import (
    PREDICTOR_KINDS, RECON_LOSSES, ProxyLeafConfig, TrainConfig, check_proxy_selection, default_cell_size,
    predictor_neighbours, offset_recon_loss, predictor_from_json, proxy_encodings, recon_loss, select_proxies,
    train_predictor,
)
from .render.project import GateConfig
from .scene import AnchorScene, point_spacing
from .sections import MAX_LEVEL_CELLS
from .strategy import ScaffoldStrategy

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
VOXEL_RULES = ("auto", "extent", "spacing")
DENSITY_PROBE_STEPS = 10  # "auto" under a time budget: steps at the spacing density (the pace: all but the first)


#: A fitted container's bytes ~ FIT_BASE_BYTES + FIT_ANCHOR_BYTES x anchors (``FitConfig.target_size``): the weights,
#: predictor, entropy nets and metadata (~55 KB at the default q7 weights), and per anchor a little above the most
#: measured with the default encode, so that a container lands under its target: bonsai 14.2 B (an H200 fit of 4,176
#: iterations at extent / 128), 13.1 B (3,794 at the scene's density), 10.0-11.8 B (600-s CPU fits, ~2,000
#: iterations); lego 8.9 B (1,500 iterations at 200 px). Longer fits have stored more per anchor.
FIT_BASE_BYTES = 57_000
FIT_ANCHOR_BYTES = 15.0


def anchors_for_bytes(target_bytes: int, base_bytes: float, anchor_bytes: float) -> int:
    """The anchors a container of ``target_bytes`` holds when it takes ``base_bytes`` + ``anchor_bytes`` per anchor."""
    return max(1, int((target_bytes - base_bytes) / anchor_bytes))


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
    # how xi is drawn in [xi_min, xi_max] (loop.XI_SAMPLINGS): "uniform" in xi (the paper's), "pixels" (uniform in
    # pixel count, density ~ xi), "log" (uniform in log xi)
    xi_sampling: str = "uniform"
    # [D] this fraction of the iterations renders at xi_max instead of a drawn resolution: with xi uniform alone,
    # 100% was where the model was weakest (0.8 dB below plain Scaffold-GS on lego at 400 px); 0.25 puts it above,
    # and the average over 10%..100% rises too (SPEC.md section 5, benchmarks/results/full_res)
    xi_full_share: float = 0.25
    # densification statistics only from iterations with xi >= this (0: all; Scaffold-GS sees 100% only)
    stats_min_xi: float = 0.0
    # model
    embedding: str = "film"  # "film" | "additive" | "none"
    gate: bool = True  # pixel coverage gate on during training and rendering
    gate_kappa: float = 4.0
    gate_eta: float = 0.25
    # gsplat's antialiased mode on top of the gate (``GateConfig.antialiased``): the opacity times
    # sqrt(det Sigma2D / det(Sigma2D + 0.3 I)), in training and in every render of the scene
    antialiased: bool = False
    feat_dim: int = 32
    n_offsets: int = 10
    film_hidden: int = 64  # width of the FiLM MLP's hidden layer
    proxies: bool = True  # stage 2 (proxy anchors + residual predictor); False: Scaffold-GS only
    # initialisation
    voxel_size: float = 0.0  # > 0: this size; <= 0: chosen by ``voxel_rule``
    # "spacing": Scaffold-GS's automatic voxel, the median distance between the distinct SfM points and their
    # nearest neighbour (about one anchor per point: the scene decides); without SfM points (Blender's random init)
    # it falls back to "extent": the bounds' extent / voxel_divisions. [D] "auto": the density follows the run's
    # length: spacing when the run is expected to reach ``density_iters`` iterations at that density, else extent
    # (fewer, larger anchors, which a short run trains further). ``iters`` alone decides it; under a time budget
    # ``fit`` measures the pace of DENSITY_PROBE_STEPS steps at the spacing density first. Why: SPEC.md section 5.
    voxel_rule: str = "auto"
    voxel_divisions: int = 128
    density_iters: int = 1000
    init_points: int = 5_000  # random points in the bounds when the dataset has no SfM points (Blender)
    # [D] Adam steps that fit the new anchors' features (and the colour MLP) to their voxels' SfM colours before
    # training, on the training clock (``fit_initial_colors``); 0, or a dataset without SfM colours: Scaffold-GS's
    # zero features
    color_init_steps: int = 100
    # [D] the anchors' Gaussian scale (the last 3 of their 6 log scalings) starts at this multiple of Scaffold-GS's,
    # the anchors' 3-nearest-neighbour distance (the offsets' scale, the first 3, keeps it). None: as large as
    # Scaffold-GS's density (``voxel_rule`` spacing) would start it, i.e. the median of that distance at the spacing
    # voxel over its median at the voxel taken (1 at spacing and without SfM points; bonsai at extent / 128: 0.33).
    # Scaffold-GS's (1) at the coarser extent density costs a short fit its first ~250 iterations (SPEC.md section 5).
    init_gaussian_scale: float | None = None
    # loss
    lambda_dssim: float = 0.2
    lambda_volume: float = 0.01
    # [D] added to the opacity head's bias at initialisation, so the neural Gaussians start visible (opacity
    # 0.3-0.6, like 3DGS's init) and fade with a gradient instead of dying without one (SPEC.md section 5)
    opacity_bias_init: float = 0.5
    # learning rates (Scaffold-GS defaults; exponential decay init -> final over the run)
    lr_feature: float = 0.0075
    lr_offset: tuple[float, float] = (0.01, 0.0001)
    lr_scaling: float = 0.007
    lr_mlp_opacity: tuple[float, float] = (0.002, 0.00002)
    lr_mlp_cov: tuple[float, float] = (0.004, 0.004)
    lr_mlp_color: tuple[float, float] = (0.008, 0.00005)
    lr_mlp_embed: tuple[float, float] = (0.004, 0.00004)
    lr_mlp_feature_bank: tuple[float, float] = (0.01, 0.00001)  # imported Scaffold-GS decoders with a feature bank
    lr_predictor: tuple[float, float] = (0.002, 0.00002)
    # the learning rates above that are constant (features, scalings, the covariance MLP: Scaffold-GS's) decay
    # exponentially to this multiple over the run; 1: constant, as Scaffold-GS. Distillation fine-tunes a converged
    # scene and ends on 0.1 (``EncodeConfig.distill_lr_final``; SPEC.md section 4).
    lr_constant_final: float = 1.0
    # every learning rate ramps up linearly over this fraction of the run (0: none, as Scaffold-GS). Fine-tuning a
    # converged scene needs it: Adam's first steps move every parameter by about its learning rate.
    lr_warmup: float = 0.0
    # anchor growing / pruning (Scaffold-GS adjust_anchor; its 500/1500/15000 of 30000 iterations as fractions)
    start_stat: float = 0.0167
    update_from: float = 0.05
    update_until: float | None = None  # None: stage2_start (the anchor set is final when stage 2 begins)
    update_interval: int = 100  # at most this many iterations between adjustments (Scaffold-GS: 100 of 30k)
    update_interval_frac: float = 1.0 / 150  # ... and about this fraction of the run, at least 10 iterations
    success_threshold: float = 0.8
    grad_threshold: float = 0.0002
    min_opacity: float = 0.005
    update_depth: int = 3
    update_init_factor: int = 16
    update_hierarchy_factor: int = 4
    max_anchors: int | None = None  # growth stops at this many anchors (None: no cap, as Scaffold-GS; fit --max-anchors)
    # a budget in container bytes (fit --target-size): the anchors such a container holds (``anchors_for_bytes`` with
    # FIT_BASE_BYTES, FIT_ANCHOR_BYTES) become ``max_anchors`` (the smaller of the two), and a voxel rule that would
    # start above 80% of them starts at the finest coarser voxel that does not (``initial_anchors``)
    target_size: int | None = None
    # stage 2
    stage2_start: float = 0.5  # also ends anchor growing unless update_until is given
    recon_switch: float = 2.0 / 3.0  # the paper's 20k of 30k
    lambda_recon: tuple[float, float] = (0.1, 0.01)
    # lambda_recon in joint stage 2: this constant, or None for the paper's schedule above (supplement Table 10).
    # [D] 0 by default (why: SPEC.md section 5); the predictor warm-up still uses L_recon.
    lambda_recon_fixed: float | None = 0.0
    recon_loss: str = "mse+cos"  # ablation (supplement Table 6): "mse+cos" | "mse" | "l1"
    predictor: str = "residual"  # ablation (supplement Table 5): "residual" | "proxy-leaf-mlp" (fit/eval only)
    leaf_sample: float = 0.2
    proxy_ratio: float = 0.3
    proxy_cell: float = 0.0  # <= 0: proxy.default_cell_size (~10 anchors per occupied cell)
    # [D] "spread" (greedy k-median per cell; proxy.py) | "random" (the paper's): spread + context 4 halve what the
    # proxies cost (SPEC.md section 5)
    proxy_selection: str = "spread"
    predictor_hidden: int = 64
    predictor_blocks: int = 2
    predictor_warmup: int = 300  # L_recon-only predictor iterations at the stage switch (no rendering)
    predictor_context: int = 4  # proxies the residual predictor sees per leaf (1: the paper's nearest proxy)
    # The predictor is born at the stage switch: its learning rate decays over stage 2 (lr_predictor[0] at the
    # switch). False: over the whole run, as the other groups (a predictor born at p = 0.5 then starts at 1/10).
    predictor_lr_stage2: bool = True
    # [D] the decoder MLPs' learning-rate schedules restart at the stage switch too (their init -> final over
    # stage 2): they must re-fit to predicted leaf features (+0.11 dB on lego at 200 px)
    decoder_lr_stage2: bool = True
    # the leaves' rendered features pass from their own (stage-1) values to the predicted ones linearly over this
    # fraction of stage 2 (0: at once, the paper's switch); from then on the predictions alone, as decoded
    leaf_ramp: float = 0.0
    predict_offsets: bool = False  # stage 2 also predicts (and renders) the leaves' offsets; L_recon adds their MSE
    # Rate in the loss (stage 2; ``entropy_fit.RateModel``): lambda_rate x estimated bits per anchor of the stored
    # attributes; they are rendered rounded to a learned grid per attribute channel (straight-through), exported in
    # the scene metadata as ``quant_steps``, which encode quantises on. 0: off (training as before).
    # [D] 1e-4 by default (issue 17): on lego (400 px, 10,220 iterations) the container is 13.6x smaller than PLY +
    # weights at 0.002 dB below the fitted scene, against 6.9x without the term (5e-5: 11.4x); the fitted scene itself scores
    # 1.22 dB below a fit without it (SPEC.md section 4, "Entropy coding"): --lambda-rate 0 for the most quality.
    lambda_rate: float = 1e-4
    # [D] Adam on the log of each channel's step, 1e-2: the grids coarsen as far as lambda_rate asks within a short
    # stage 2. At 2e-3 (the default up to 2026-11-29) bonsai's 600-s fit ended on ~6-bit grids, 44% more bytes for
    # +0.14 dB; lego's 900-s fit within the ablations' noise (-15% bytes, -0.58 dB; benchmarks/README.md,
    # "The grids' learning rate"). Conversion keeps 2e-3 (ConvertConfig.fit).
    lr_quant_step: float = 1e-2
    # Per-cell quantisation levels (with the rate term; HAC++'s adaptive step, by position): the anchors' voxel
    # bounding box in quant_cells^3 cells, and per cell, attribute and proxy/leaf a learned level: the step is the
    # channel's x 2^(level / 4), level in [-8, 8] (straight-through), stored in the scene metadata and the
    # container (scene format 5). 0: per-channel steps only.
    quant_cells: int = 0
    lr_quant_level: float = 0.01  # Adam on the levels (a level is ln(2) / 4 = 0.17 of a log-step unit)
    lr_rate_model: float = 3e-3  # the float entropy nets
    # bookkeeping
    image_cache_mb: int = 2048  # decoded 100% training images kept (float16); beyond this they are re-read
    backend: str = "auto"
    checkpoint_every: float = 300.0  # seconds between checkpoints (0: never, except on interrupt)
    log_every: float = 10.0  # seconds between progress lines

    def __post_init__(self) -> None:
        check_run_length(self.iters, self.time_budget, self.max_width)
        if self.update_until is None:
            object.__setattr__(self, "update_until", self.stage2_start)
        if not (0.025 <= self.xi_min <= self.xi_max <= 2.0):
            raise ProxycodecError(f"resolution range [{self.xi_min}, {self.xi_max}] must lie in [0.025, 2]")
        DecoderConfig(embedding=self.embedding, film_hidden=self.film_hidden)  # validates the name and width
        check_xi_sampling(self.xi_sampling)
        if not (0.0 <= self.xi_full_share <= 1.0) or not (0.0 <= self.stats_min_xi <= self.xi_max):
            raise ProxycodecError(f"xi_full_share must be in [0, 1] and stats_min_xi in [0, xi_max], got "
                                  f"{self.xi_full_share}, {self.stats_min_xi}")
        if not (0 < self.proxy_ratio <= 1) or not (0 < self.leaf_sample <= 1):
            raise ProxycodecError("proxy ratio and leaf sample fraction must be in (0, 1]")
        PredictorConfig(hidden=self.predictor_hidden, n_blocks=self.predictor_blocks,
                        context=self.predictor_context)  # validates width, depth and context
        if not (math.isfinite(self.lambda_rate) and self.lambda_rate >= 0):
            raise ProxycodecError(f"lambda_rate must be >= 0, got {self.lambda_rate}")
        if not all(math.isfinite(v) and v > 0 for v in (self.lr_quant_step, self.lr_quant_level)):
            raise ProxycodecError(f"the grids' learning rates must be positive, got lr_quant_step "
                                  f"{self.lr_quant_step} and lr_quant_level {self.lr_quant_level}")
        if not (0 <= self.quant_cells <= MAX_LEVEL_CELLS):
            raise ProxycodecError(f"quantisation cells must be in [0, {MAX_LEVEL_CELLS}], got {self.quant_cells}")
        if self.quant_cells and not self.lambda_rate > 0:
            raise ProxycodecError("per-cell quantisation levels (quant cells) are learned by the rate term: "
                                  "give lambda_rate > 0")
        if not (math.isfinite(self.lr_constant_final) and 0.0 < self.lr_constant_final <= 1.0):
            raise ProxycodecError(f"the constant learning rates' final multiple must be in (0, 1], got "
                                  f"{self.lr_constant_final}")
        if not (0.0 <= self.lr_warmup < 1.0):
            raise ProxycodecError(f"learning-rate warm-up must be a fraction of the run in [0, 1), got {self.lr_warmup}")
        if self.max_anchors is not None and self.max_anchors < 1:
            raise ProxycodecError(f"the anchor cap must be >= 1, got {self.max_anchors}")
        if self.target_size is not None:
            if self.target_size < FIT_BASE_BYTES + FIT_ANCHOR_BYTES:
                raise ProxycodecError(f"a target size below {FIT_BASE_BYTES + FIT_ANCHOR_BYTES:,.0f} B holds no "
                                      f"anchor (the weights alone take ~{FIT_BASE_BYTES:,} B)")
            cap = anchors_for_bytes(self.target_size, FIT_BASE_BYTES, FIT_ANCHOR_BYTES)
            object.__setattr__(self, "max_anchors", cap if self.max_anchors is None else min(self.max_anchors, cap))
        if self.voxel_rule not in VOXEL_RULES:
            raise ProxycodecError(f"voxel rule {self.voxel_rule!r}: must be one of {', '.join(VOXEL_RULES)}")
        if self.density_iters < 1:
            raise ProxycodecError(f"the density switch must be >= 1 iteration, got {self.density_iters}")
        if self.init_gaussian_scale is not None and not (0.0 < self.init_gaussian_scale < math.inf):
            raise ProxycodecError(f"the initial Gaussian scale must be a positive multiple, got "
                                  f"{self.init_gaussian_scale}")
        if self.color_init_steps < 0:
            raise ProxycodecError(f"colour init steps must be >= 0, got {self.color_init_steps}")
        if not (0.0 <= self.leaf_ramp < 1.0):
            raise ProxycodecError(f"the leaves' ramp must be a fraction of stage 2 in [0, 1), got {self.leaf_ramp}")
        if self.predictor_warmup < 0:
            raise ProxycodecError(f"predictor warm-up must be >= 0 iterations, got {self.predictor_warmup}")
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

    def with_lr_scale(self, scale: float) -> FitConfig:
        """Every learning rate of the anchors and the decoder times ``scale`` (not the predictor's): fine-tuning a
        converged scene, where Adam's first steps move every parameter by about its learning rate."""
        if scale == 1.0:
            return self
        scaled = {f.name: (tuple(v * scale for v in lr) if isinstance(lr, tuple) else lr * scale)
                  for f in fields(self)
                  if f.name.startswith("lr_") and f.name not in ("lr_predictor", "lr_warmup", "lr_constant_final")
                  for lr in (getattr(self, f.name),)}
        return replace(self, **scaled)

    def decoder_config(self, center, radius: float) -> DecoderConfig:
        return DecoderConfig(feat_dim=self.feat_dim, n_offsets=self.n_offsets, embedding=self.embedding,
                             film_hidden=self.film_hidden,
                             scene_center=tuple(float(c) for c in center), scene_radius=float(radius),
                             film_xi_range=(1.0, 1.0) if self.fixed_res else (self.xi_min, self.xi_max),
                             gate=GateConfig(self.gate, self.gate_kappa, self.gate_eta, self.antialiased))



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


def voxelise(points: np.ndarray, voxel: float) -> np.ndarray:
    """Scaffold-GS: unique(round(p / v)) * v."""
    cells = np.unique(np.round(points / voxel).astype(np.int64), axis=0)
    return cells.astype(np.float64) * voxel


def cell_means(points: np.ndarray, values: np.ndarray, voxel: float, anchors: np.ndarray) -> np.ndarray:
    """[M, ...]: the mean of ``values`` [N, ...] over the points in each anchor's voxel (``voxelise``'s cells; the
    anchors may be a subset of them, as ``max_anchors`` leaves)."""
    cells = np.round(points / voxel).astype(np.int64)
    keys = np.round(anchors / voxel).astype(np.int64)
    uniq, inv = np.unique(cells, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    values = np.asarray(values, dtype=np.float64)
    sums = np.zeros((len(uniq), *values.shape[1:]))
    np.add.at(sums, inv, values)
    mean = sums / np.bincount(inv, minlength=len(uniq)).reshape(-1, *[1] * (values.ndim - 1))
    row = [("", np.int64)] * 3  # a cell as one structured scalar, to search np.unique's sorted rows
    at = np.searchsorted(uniq.view(row).reshape(-1), np.ascontiguousarray(keys).view(row).reshape(-1))
    return mean[at]


def fit_initial_colors(decoder: GaussianDecoder, positions: torch.Tensor, features: torch.Tensor,
                       target: torch.Tensor, camera_centers: torch.Tensor, steps: int, lr: float,
                       generator: torch.Generator) -> tuple[float, float]:
    """Fit the anchors' ``features`` (in place) and the colour MLP so that every neural Gaussian of an anchor
    starts with its voxel's SfM colour ``target`` [M, 3], seen from the training cameras, while the opacity and
    covariance MLPs' outputs stay where the zero features put them. Scaffold-GS starts from zero features, every
    anchor the same colour, and spends its first few hundred iterations on what 3DGS's SfM-coloured points start
    with (SPEC.md section 5). -> (colour RMSE before, after)."""
    cfg = decoder.config
    n_in = cfg.mlp_inputs()

    def heads(f: torch.Tensor, cams: torch.Tensor):  # the three MLPs' outputs, each on the input it reads
        x = decoder.mlp_input(positions, f, cams, 1.0)[1]
        return (torch.sigmoid(decoder.mlp_color(x[:, :n_in["mlp_color"]])),
                torch.tanh(decoder.mlp_opacity(x[:, :n_in["mlp_opacity"]])), decoder.mlp_cov(x[:, :n_in["mlp_cov"]]))

    M = positions.shape[0]
    f = features.detach().clone().requires_grad_(True)
    params = [f, *decoder.mlp_color.parameters()]
    opt = torch.optim.Adam(params, lr=lr)
    tgt = target.repeat(1, cfg.n_offsets)
    rmse = []
    for k in range(steps + 1):
        cams = camera_centers[torch.randint(len(camera_centers), (M,), generator=generator,
                                            device=generator.device)]
        with torch.no_grad():
            _, o0, c0 = heads(features, cams)
        color, o, c = heads(f, cams)
        err = (color - tgt).square().mean()
        if k in (0, steps):  # read back twice only (a GPU would wait at each)
            rmse.append(float(err.detach().sqrt()))
        if k == steps:
            break
        loss = err + (o - o0).square().mean() + (c - c0).square().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        features.copy_(f)
    return rmse[0], rmse[-1]


def stage2_progress(cfg: FitConfig, p: float) -> float:
    """Where a run at ``p`` stands within stage 2, in [0, 1] (1 when the run has no stage 2)."""
    return min(1.0, max(0.0, (p - cfg.stage2_start) / (1.0 - cfg.stage2_start))) if cfg.stage2_start < 1 else 1.0


def density_rule(cfg: FitConfig, expected_iters: float | None = None) -> str:
    """The voxel rule ``cfg`` stands for: "auto" resolved by the run's expected length (``expected_iters``, else
    ``cfg.iters``; neither known: spacing, which ``fit`` avoids by measuring the pace first)."""
    if cfg.voxel_rule != "auto":
        return cfg.voxel_rule
    n = expected_iters if expected_iters is not None else cfg.iters
    return "extent" if n is not None and n < cfg.density_iters else "spacing"


def initial_voxel(extent: float, cfg: FitConfig, spacing: Callable[[], float]) -> float:
    """The anchor voxel: ``cfg.voxel_size`` if given, else by ``cfg.voxel_rule`` (see ``FitConfig``). ``spacing()``:
    the SfM points' ``point_spacing``, 0 without SfM points (called only where the rule needs it)."""
    if cfg.voxel_size > 0:
        return float(cfg.voxel_size)
    if density_rule(cfg) == "spacing" and (s := spacing()) > 0:
        return s
    return extent / cfg.voxel_divisions


@dataclass(frozen=True)
class InitialAnchors:
    """Where a fit's anchors start (``initial_anchors``)."""

    positions: np.ndarray  # [M, 3] voxel centres
    voxel: float
    center: np.ndarray  # [3] the bounds' centre
    radius: float  # half the bounds' diagonal
    colors: np.ndarray | None  # [M, 3] in 0..1: the mean SfM colour of each voxel's points; None without colours
    gaussian_scale: float  # ``FitConfig.init_gaussian_scale`` resolved

    def scalings(self) -> np.ndarray:
        """[M, 6] log scalings: Scaffold-GS's, the anchors' 3-nearest-neighbour distance, the Gaussians' part (last
        3) times ``gaussian_scale``."""
        out = np.repeat(np.log(knn_scale(self.positions))[:, None], 6, 1)
        out[:, 3:] += math.log(self.gaussian_scale)
        return out


def first_true(pred: Callable[[int], bool], lo: int, hi: int) -> int:
    """The smallest i in [lo, hi] with ``pred(i)`` for a ``pred`` monotone in i (False ... True); hi if none does.
    Bisection: ~log2(hi - lo) calls."""
    while lo < hi:
        mid = (lo + hi) // 2
        if pred(mid):
            hi = mid
        else:
            lo = mid + 1
    return lo


def budget_voxel(points: np.ndarray, voxel: float, budget: int) -> float:
    """The finest voxel, ``voxel`` x 2^(k / 8) for 0 <= k <= 512, that voxelises ``points`` into at most ``budget``
    cells (``voxel`` itself when it does; 2^64 x ``voxel``, a cell for every point's box, is the coarsest tried)."""
    return voxel * 2.0 ** (first_true(lambda k: len(voxelise(points, voxel * 2.0 ** (k / 8))) <= budget, 0, 512) / 8)


def initial_anchors(data, cfg: FitConfig, rng: np.random.Generator) -> InitialAnchors:
    """The anchors of a new fit from the dataset's points (``initial_points``) voxelised. With ``cfg.target_size``
    (and no ``cfg.voxel_size``) the voxel coarsens until they are at most 80% of ``cfg.max_anchors``
    (``budget_voxel``), leaving the rest to growth. With ``cfg.max_anchors``, a larger voxelised set is subsampled to
    it (at random, seeded)."""
    pts, colors, bounds, extent = initial_points(data, cfg.init_points, rng, "anchors")
    # a k-d tree over every point: built at most once, for the voxel rule and the Gaussians' scale
    spacing = functools.cache(lambda: point_spacing(pts) if has_sfm_points(data) else 0.0)
    voxel = initial_voxel(extent, cfg, spacing)
    if cfg.target_size is not None and cfg.voxel_size <= 0:
        voxel = budget_voxel(pts, voxel, max(1, int(0.8 * cfg.max_anchors)))
    anchors = voxelise(pts, voxel)
    if cfg.max_anchors is not None and len(anchors) > cfg.max_anchors:
        anchors = anchors[np.sort(rng.choice(len(anchors), cfg.max_anchors, replace=False))]
    if len(anchors) == 0:
        raise ProxycodecError("no initial anchors")
    center = 0.5 * (bounds[0] + bounds[1])
    radius = max(0.5 * float(np.linalg.norm(bounds[1] - bounds[0])), 1e-6)
    colors = None if colors is None else np.clip(cell_means(pts, colors, voxel, anchors) / 255.0, 0.0, 1.0)
    scale = cfg.init_gaussian_scale
    if scale is None:
        scale = 1.0
        if 0 < (s := spacing()) < voxel:
            scale = min(1.0, float(np.median(knn_scale(voxelise(pts, s))) / np.median(knn_scale(anchors))))
    return InitialAnchors(anchors, float(voxel), center, radius, colors, scale)


# ================================================================================================ the trainer
@dataclass
class FitResult:
    model: SceneModel
    iterations: int
    seconds: float
    history: list[dict] = field(default_factory=list)
    extra_meta: dict = field(default_factory=dict)
    extra_arrays: dict = field(default_factory=dict)


class Trainer(TrainingRun):
    """Owns the anchors, the decoder, the predictor, the optimiser and the growing strategy of one fit."""

    def __init__(self, data, config: FitConfig, dataset_root: str = "", log: ProgressFn | None = None, *,
                 start: SceneModel | None = None, start_proxies: tuple | None = None, device=None):
        """``start``: fine-tune this scene (its anchors and decoder; the anchor set stays as it is when
        ``config.update_until`` is 0) instead of growing one from the dataset's points. ``start_proxies``:
        (residual predictor, proxy mask) that stage 2 then starts from instead of selecting proxies afresh.
        ``device``: where the run computes (None: the CPU); the result's scene and decoder are left there."""
        self.data = data
        self.device = dev = as_device(device)
        self.cfg = config
        self.dataset_root = dataset_root
        self.log = log or (lambda s: None)
        self.bg = torch.tensor(data.background, dtype=torch.float32, device=dev)
        if not data.train_indices:
            raise ProxycodecError("the dataset has no training images")
        self.rng = np.random.default_rng(config.seed)
        # a dataset that makes its own targets (a teacher scene's renders: ``distill.TeacherViews``) hands them over
        make_targets = getattr(data, "targets", None)
        self.images = (make_targets or (lambda n: TargetImages(data, n, dev)))(config.image_cache_mb << 20)
        torch.manual_seed(config.seed)
        if start is None:
            init = initial_anchors(data, config, self.rng)
            M, K, Fd = len(init.positions), config.n_offsets, config.feat_dim
            scale = init.scalings()
            self.log(f"anchors: {M} at voxel {init.voxel:.4g}, Gaussians start at {init.gaussian_scale:.3g}x the "
                     f"anchors' neighbour distance")
            self.anchors = TrainableAnchors(
                torch.tensor(init.positions, dtype=torch.float32, device=dev), torch.zeros(M, Fd, device=dev),
                torch.zeros(M, K, 3, device=dev), torch.tensor(scale, dtype=torch.float32, device=dev), init.voxel)
            self.decoder = GaussianDecoder(config.decoder_config(init.center, init.radius)).to(dev)
            with torch.no_grad():  # Gaussians start visible (see FitConfig.opacity_bias_init)
                self.decoder.mlp_opacity[-1].bias.add_(config.opacity_bias_init)
        else:
            s = start.scene
            self.anchors = TrainableAnchors(*(t.to(dev) for t in (s.positions, s.features, s.offsets, s.scalings)),
                                            s.voxel_size)
            dcfg = start.decoder.config
            if not config.fixed_res:  # the embedding is now trained over the configured band
                dcfg = replace(dcfg, film_xi_range=(config.xi_min, config.xi_max))
            self.decoder = GaussianDecoder.from_arrays(dcfg, start.decoder.state_arrays()).to(dev)
        self.start_proxies = start_proxies
        self.predictor = None
        self.proxy_mask: torch.Tensor | None = None  # [M] bool
        self.nearest: torch.Tensor | None = None  # [M, context] long
        self.encodings: torch.Tensor | None = None  # [M, context, n_geo]: proxy.proxy_encodings, stage 2
        self.leaf_target: torch.Tensor | None = None  # [L, F] stage-1 features of the leaves
        self.leaf_offset_target: torch.Tensor | None = None  # [L, K, 3] their stage-1 offsets (predict_offsets)
        self.leaves: torch.Tensor | None = None  # [L] long
        self.rate: RateModel | None = None  # stage 2 with lambda_rate > 0
        self.density: dict | None = None  # how "auto" chose the voxel rule (``fit``), recorded with the result
        self.opt = self._optimiser()
        self.strategy = ScaffoldStrategy(config, self.anchors.num_anchors, self.anchors.n_offsets, self.log, dev)
        self._start_run()
        self.initial_colors = init.colors if start is None else None  # ``color_init``'s targets
        self.stage = 1

    def color_init(self) -> None:
        """``fit_initial_colors`` on anchors grown from the dataset's points (``fit`` calls it once, before
        training), counted in ``elapsed``: a time budget pays for it."""
        c, data, a = self.cfg, self.data, self.anchors
        if self.initial_colors is None or c.color_init_steps <= 0:
            return
        t0 = time.perf_counter()
        target = self.initial_colors
        centers = np.stack([data.cameras[i].center for i in data.train_indices])
        gen = generator(self.device, c.seed)
        before, after = fit_initial_colors(
            self.decoder, a.positions, a.features.data, upload(target, self.device, torch.float32),
            upload(centers, self.device, torch.float32), c.color_init_steps, 0.01, gen)
        synchronize(self.device)
        seconds = time.perf_counter() - t0
        self.elapsed += seconds
        self.log(f"colour init: {c.color_init_steps} steps, colour RMSE {before:.3f} -> {after:.3f} against the "
                 f"voxels' SfM colours, {seconds:.1f} s")

    def _optimiser(self) -> Adam:
        opt = Adam(self.anchors.tensors())
        for k, p in self.decoder.named_parameters():
            opt.add(f"decoder.{k}", p)
        return opt

    # ------------------------------------------------------------------ schedule
    def learning_rates(self, p: float) -> dict[str, float]:
        c = self.cfg
        lrs: dict[str, float] = {"features": c.lr_feature, "offsets": exp_lr(*c.lr_offset, p),
                                 "scalings": c.lr_scaling}
        groups = {"mlp_opacity": c.lr_mlp_opacity, "mlp_cov": c.lr_mlp_cov, "mlp_color": c.lr_mlp_color,
                  "mlp_embed": c.lr_mlp_embed, "mlp_feature_bank": c.lr_mlp_feature_bank}
        p2 = stage2_progress(c, p)
        for name in self.opt.params:
            if name.startswith("decoder."):
                q = p2 if (c.decoder_lr_stage2 and self.stage >= 2) else p
                lrs[name] = exp_lr(*groups[name.split(".")[1]], q)
            elif name.startswith("predictor."):
                lrs[name] = exp_lr(*c.lr_predictor, p2 if c.predictor_lr_stage2 else p)
            elif name.startswith("rate.log_step"):
                lrs[name] = c.lr_quant_step
            elif name.startswith("rate.levels"):
                lrs[name] = c.lr_quant_level
            elif name.startswith("rate."):
                lrs[name] = c.lr_rate_model
        if c.lr_constant_final != 1.0:
            f = exp_lr(1.0, c.lr_constant_final, p)
            for k in ("features", "scalings", *(n for n in lrs if n.startswith("decoder.mlp_cov."))):
                lrs[k] *= f
        if c.lr_warmup > 0 and p < c.lr_warmup:
            ramp = p / c.lr_warmup
            lrs = {k: v * ramp for k, v in lrs.items()}
        return lrs

    def leaf_blend(self) -> float:
        """The predictions' share of the leaves' rendered features (``FitConfig.leaf_ramp``): 0 at the stage switch,
        1 from ``leaf_ramp`` of stage 2 on."""
        ramp = self.cfg.leaf_ramp
        return 1.0 if ramp <= 0 else min(1.0, stage2_progress(self.cfg, self.progress()) / ramp)

    def lambda_recon(self, p: float) -> float:
        if self.cfg.lambda_recon_fixed is not None:
            return float(self.cfg.lambda_recon_fixed)
        return self.cfg.lambda_recon[0] if p < self.cfg.recon_switch else self.cfg.lambda_recon[1]

    # ------------------------------------------------------------------ one iteration
    def train_step(self) -> dict:
        """sample view and resolution -> the visible leaves' predicted features (stage 2) -> render -> loss ->
        backward -> step -> growing and pruning (``loop.TrainingRun.optimise``)."""
        c = self.cfg
        p = self.progress()
        if c.proxies and self.stage == 1 and p >= c.stage2_start:
            self.enter_stage2()
        # the share of iterations at the top of the range (drawn only when there is one: the stream is unchanged)
        top = not c.fixed_res and c.xi_full_share > 0 and self.rng.random() < c.xi_full_share
        i, xi, gt = self.sample_view(1.0 if c.fixed_res else c.xi_max if top else (c.xi_min, c.xi_max),
                                     c.xi_sampling)
        self.step_xi = xi  # observe() reads it: densification statistics from xi >= stats_min_xi only
        cam = self.data.cameras[i]
        lam = self.lambda_recon(p) if self.stage >= 2 else 0.0
        scene, rounded, bits = self.anchors.scene(), None, None
        if self.rate is not None:  # the attributes on their quantisation grids, and their rate
            a = self.anchors
            # its noise and sample from a generator seeded by the run's rng: checkpointed, so a resumed run is the same
            gen = generator(self.device, int(self.rng.integers(1 << 62)))
            f_q, o_q, s_q, bits = self.rate(a.features, a.offsets, a.scalings, generator=gen)
            rounded = f_q, o_q
            scene = replace(scene, features=f_q, offsets=o_q, scalings=s_q)
        # one frustum test for the leaf tables and the render: the leaves predicted are the ones drawn (the scene
        # rendered, on its quantisation grids when rate-trained, is the one the decoder will see)
        vis = scene_visible(scene, self.decoder, cam.scaled(xi))
        feats, offs, l_recon = self.leaf_tables(vis, with_recon=lam != 0.0, rounded=rounded)
        r = render_scene(scene, self.decoder, cam, xi, background=self.bg, backend=c.backend,
                         features=feats, offsets=offs, visible=vis)
        loss = photometric_loss(r.image, gt, c.lambda_dssim)
        if r.gaussians.count:
            loss = loss + c.lambda_volume * r.gaussians.scales.prod(dim=1).mean()
        if lam != 0.0:
            loss = loss + lam * l_recon
        if bits is not None:
            loss = loss + c.lambda_rate * bits / self.anchors.num_anchors
        self.optimise(loss, r, r.image.shape[1], r.image.shape[0], self.learning_rates(p))
        return {**self.step_stats(loss, r.image, gt), "xi": xi, "view": i, "gaussians": int(r.projected.count),
                # 0-d tensors like loss and mse: reading them back would synchronise a GPU every step
                "recon": l_recon.detach(),
                **({} if bits is None else {"bits_per_anchor": bits.detach() / self.anchors.num_anchors})}

    def leaf_tables(self, vis: torch.Tensor, with_recon: bool = True, rounded: tuple | None = None
                    ) -> tuple[torch.Tensor | None, torch.Tensor | None, torch.Tensor]:
        """Stage 2: the feature (and, with ``predict_offsets``, offset) tables with the rows of the leaves among
        the visible anchors ``vis`` (``model.scene_visible``) predicted; and L_recon (0 without computing it when
        ``with_recon`` is False, i.e. its weight is 0: the leaf sample is still drawn, so the random stream does
        not depend on the weight). ``rounded``: (features, offsets) on their quantisation grids (rate training),
        rendered and fed to the predictor instead."""
        zero = torch.zeros((), device=self.device)
        if self.stage < 2 or self.predictor is None:
            return (None, None, zero) if rounded is None else (*rounded, zero)
        a = self.anchors
        po = self.cfg.predict_offsets
        leaf_vis = vis[~self.proxy_mask[vis]]
        base_f, base_o = rounded if rounded is not None else (a.features, a.offsets)
        feats, offs = base_f, (base_o if po or rounded is not None else None)
        if leaf_vis.numel():
            pred, pred_o = self.predictor.predict(a.positions, base_f, self.nearest, leaf_vis,
                                                  base_o if po else None, self.encodings)
            if (t := self.leaf_blend()) < 1.0:  # the ramp: own values -> predictions
                pred = torch.lerp(base_f[leaf_vis], pred, t)
                if po:
                    pred_o = torch.lerp(base_o[leaf_vis], pred_o, t)
            feats = base_f.index_put((leaf_vis,), pred)
            if po:
                offs = base_o.index_put((leaf_vis,), pred_o)
        # L_recon on a random 20% of all leaves (not only the visible ones) against their stage-1 values.
        L = int(self.leaves.numel())
        n = max(1, math.ceil(self.cfg.leaf_sample * L)) if L else 0
        if n == 0:
            return feats, offs, zero
        sel = upload(self.rng.choice(L, n, replace=False).astype(np.int64), self.device)
        if not with_recon:
            return feats, offs, zero
        pred_s, pred_so = self.predictor.predict(a.positions, a.features, self.nearest, self.leaves[sel],
                                                 a.offsets if po else None, self.encodings)
        loss = recon_loss(pred_s, self.leaf_target[sel], kind=self.cfg.recon_loss)
        if po:  # the offset term of proxy.train_predictor (offset_weight 1)
            loss = loss + offset_recon_loss(pred_so, self.leaf_offset_target[sel])
        return feats, offs, loss

    def observe(self, r, width: int, height: int) -> None:
        if self.stage < 2 and self.strategy.collecting(self.progress()) and self.step_xi >= self.cfg.stats_min_xi:
            self.strategy.observe(r, width, height)

    def after_step(self) -> None:
        if self.stage < 2:
            self.strategy.maybe_adjust(self, self.anchors, self.opt, self.rng)

    # ------------------------------------------------------------------ stage 2
    def _predictor_config(self):
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
        a = self.anchors
        self.proxy_mask = torch.from_numpy(np.asarray(mask, dtype=bool)).to(self.device)
        if self.predictor is None:
            self.predictor = predictor_from_json(self._predictor_config().to_json())
        elif isinstance(self.predictor.config, PredictorConfig) and self.predictor.config.ties != "grid":
            # a predictor from a file written before the rule (distillation's start): it trains on from here, so it
            # takes the rule under which the trainer's anchors and the container's give the same neighbours, in
            # any frame (``nearest.TIES``)
            self.predictor.config = replace(self.predictor.config, ties="grid")
        self.nearest = torch.from_numpy(predictor_neighbours(a.positions, mask, self.predictor.config)
                                        ).long().to(self.device)
        # the residual predictor's proxy -> leaf encodings, once: positions and neighbours stay fixed from here on
        self.encodings = (proxy_encodings(a.positions, self.nearest, self.predictor.config)
                          if isinstance(self.predictor.config, PredictorConfig) else None)
        self.leaves = (~self.proxy_mask).nonzero().squeeze(1)
        self.predictor.to(self.device)
        for k, p in self.predictor.named_parameters():
            self.opt.add(f"predictor.{k}", p)
        self.stage = 2

    def _setup_rate(self, mask: np.ndarray, state: dict[str, np.ndarray] | None = None) -> None:
        """The rate model of ``lambda_rate`` > 0 (grids from the current attributes, or ``state`` from a
        checkpoint), its parameters in the optimiser."""
        if self.cfg.lambda_rate <= 0:
            return
        a = self.anchors
        self.rate = RateModel(a.positions.cpu().numpy(), a.voxel_size, mask, a.features.detach().cpu(),
                              a.offsets.detach().cpu(), a.scalings.detach().cpu(),
                              cells=self.cfg.quant_cells).to(self.device)  # built on the host, moved whole
        if state is not None:
            self.rate.load_state_dict({k: torch.from_numpy(np.array(v)).to(self.device) for k, v in state.items()})
        for k, p in self.rate.named_parameters():
            self.opt.add(f"rate.{k}", p)

    def proxy_cell_size(self) -> float:
        c = self.cfg
        return c.proxy_cell if c.proxy_cell > 0 else default_cell_size(self.anchors.positions,
                                                                       self.anchors.voxel_size)

    def enter_stage2(self) -> None:
        """Freeze the anchor set, select proxies, warm the predictor up on L_recon alone, start joint training.
        With ``start_proxies`` the given split and predictor are used as they are (no selection, no warm-up)."""
        c = self.cfg
        a = self.anchors
        cell = self.proxy_cell_size()
        if self.start_proxies is not None:
            predictor, mask = self.start_proxies
            mask = np.asarray(mask, dtype=bool)
            self.predictor = predictor_from_json(predictor.config.to_json(), predictor.state_arrays())
        else:
            mask = select_proxies(a.positions, cell, c.proxy_ratio, c.seed, c.proxy_selection)
        leaf_rows = torch.from_numpy(~mask).to(self.device)
        self.leaf_target = a.features.detach()[leaf_rows].clone()
        if c.predict_offsets:
            self.leaf_offset_target = a.offsets.detach()[leaf_rows].clone()
        self._setup_proxies(mask)
        if c.predictor_warmup > 0 and self.leaves.numel() and self.start_proxies is None:
            res = train_predictor(self.predictor, a.positions, a.features.detach(), mask, self.nearest.cpu().numpy(),
                                  offsets=a.offsets.detach() if c.predict_offsets else None,
                                  config=TrainConfig(iters=c.predictor_warmup, sample_frac=c.leaf_sample,
                                                     seed=c.seed), recon=c.recon_loss)
            warm = f"; predictor warm-up L_recon {res.baseline_loss:.4f} -> {res.final_loss:.4f}"
        else:
            warm = ""
        self.predictor.train()
        self._setup_rate(mask)
        self.log(f"  stage 2 at iteration {self.iteration}: {int(mask.sum())} proxies / {a.num_anchors} anchors "
                 f"(cell {cell:.4g}){warm}" + (f"; rate term lambda {c.lambda_rate:g}" if self.rate else ""))

    # ------------------------------------------------------------------ results
    @torch.no_grad()
    def final_features(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Features and offsets as stage 2 rendered them: the proxies' own; the leaves' predicted features (and
        predicted offsets with ``predict_offsets``). With the rate term, the stored attributes on their grids."""
        a = self.anchors
        f = a.features.detach().clone()
        o = a.offsets.detach().clone()
        if self.rate is not None:
            f, o, _ = self.rate.rounded(f, o, a.scalings.detach())
        if self.stage >= 2 and self.predictor is not None and self.leaves.numel():
            self.predictor.eval()
            po = self.cfg.predict_offsets
            pred, pred_o = self.predictor.predict(a.positions, f.clone(), self.nearest, self.leaves,
                                                  o if po else None)
            f[self.leaves] = pred
            if po:
                o[self.leaves] = pred_o
        return f, o

    def result(self) -> FitResult:
        a = self.anchors
        meta: dict[str, Any] = {"name": Path(self.dataset_root).name if self.dataset_root else "fit"}
        if self.rate is not None:  # the learned quantisation steps: encode quantises with them
            meta["quant_steps"] = self.rate.grids()
        feats, offs = self.final_features()
        scene = a.export(feats, meta, offs)
        if self.rate is not None:  # the scalings as rendered too: on their grid
            scene = replace(scene, scalings=self.rate.rounded(a.features.detach(), a.offsets.detach(),
                                                              a.scalings.detach())[2]).validate()
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
            "stage": self.stage, **({} if self.density is None else {"density": self.density}),
        }
        arrays: dict[str, np.ndarray] = {}
        if self.stage >= 2 and self.predictor is not None:
            fit_meta["predictor"] = self.predictor.config.to_json()
            fit_meta["proxy_cell"] = self.proxy_cell_size()
            arrays["proxy_mask"] = self.proxy_mask.cpu().numpy().astype(np.uint8)
            for k, v in self.predictor.state_arrays().items():
                arrays[f"predictor/{k}"] = v
        return FitResult(model, self.iteration, self.elapsed, self.history, {"fit": fit_meta}, arrays)

    # ------------------------------------------------------------------ checkpoints
    def checkpoint_arrays(self) -> tuple[dict, dict]:
        a = self.anchors
        arrays: dict[str, np.ndarray] = {
            "anchors/positions": a.positions.cpu().numpy().copy(),
            "anchors/features": a.features.detach().cpu().numpy().copy(),
            "anchors/offsets": a.offsets.detach().cpu().numpy().copy(),
            "anchors/scalings": a.scalings.detach().cpu().numpy().copy(),
            **self.strategy.state_arrays(),
        }
        for k, v in self.decoder.state_arrays().items():
            arrays[f"decoder/{k}"] = v
        if self.stage >= 2:
            arrays["proxy_mask"] = self.proxy_mask.cpu().numpy().astype(np.uint8)
            arrays["leaf_target"] = self.leaf_target.cpu().numpy().copy()
            if self.cfg.predict_offsets:
                arrays["leaf_offset_target"] = self.leaf_offset_target.cpu().numpy().copy()
            for k, v in self.predictor.state_arrays().items():
                arrays[f"predictor/{k}"] = v
            if self.rate is not None:
                for k, v in self.rate.state_dict().items():
                    arrays[f"rate/{k}"] = v.detach().cpu().numpy().copy()
        arrays.update(self.opt.state_arrays())
        run_meta, run_arrays = self.run_state()
        arrays.update(run_arrays)
        meta = {
            "kind": CHECKPOINT_KIND, "version": CHECKPOINT_VERSION, "config": self.cfg.to_json(),
            "dataset": str(self.dataset_root), "stage": self.stage, "last_adjust": self.strategy.last_adjust,
            "voxel_size": a.voxel_size, "decoder": self.decoder.config.to_json(),
            "adam_steps": dict(self.opt.step_count), **run_meta,
            **({} if self.density is None else {"density": self.density}),
        }
        return meta, arrays

    def load_checkpoint(self, path: str | os.PathLike) -> None:
        ck = read_container(path)
        m = ck.meta
        if m.get("kind") != CHECKPOINT_KIND or m.get("version") != CHECKPOINT_VERSION:
            raise ProxycodecError("not a fit checkpoint of this version", path)
        try:
            saved = FitConfig.from_json(m["config"])
            cfg = self.cfg
            if cfg.voxel_rule == "auto":  # the rule "auto" chose when the run started
                cfg = replace(cfg, voxel_rule=saved.voxel_rule)
            # Run length may change on resume; everything else must match.
            ignore = {"iters", "time_budget", "checkpoint_every", "log_every", "backend", "max_anchors", "target_size"}
            diff = [f.name for f in fields(FitConfig) if f.name not in ignore
                    and getattr(saved, f.name) != getattr(cfg, f.name)]
            if diff:
                raise ProxycodecError(f"checkpoint was made with different settings ({', '.join(diff[:5])}); "
                                      "resume with the same options or start afresh", path)
            self.cfg = cfg
            self.density = m.get("density")
            arr = ck.arrays
            self.anchors = TrainableAnchors(*(torch.from_numpy(np.array(arr[f"anchors/{k}"])).to(self.device)
                                              for k in ("positions", "features", "offsets", "scalings")),
                                            float(m["voxel_size"]))
            dcfg = DecoderConfig.from_json(m["decoder"])
            self.decoder = GaussianDecoder.from_arrays(
                dcfg, {k[len("decoder/"):]: v for k, v in arr.items() if k.startswith("decoder/")}).to(self.device)
            self.opt = self._optimiser()
            self.stage = int(m["stage"])
            self.predictor = None
            if self.stage >= 2:
                self.predictor = predictor_from_json(
                    self._predictor_config().to_json() if "predictor" not in m else m["predictor"],
                    {k[len("predictor/"):]: v for k, v in arr.items() if k.startswith("predictor/")})
                self.leaf_target = torch.from_numpy(np.array(arr["leaf_target"])).to(self.device)
                if self.cfg.predict_offsets:
                    self.leaf_offset_target = torch.from_numpy(np.array(arr["leaf_offset_target"])).to(self.device)
                self._setup_proxies(np.asarray(arr["proxy_mask"], dtype=bool))
                self.predictor.train()
                self._setup_rate(np.asarray(arr["proxy_mask"], dtype=bool),
                                 {k[len("rate/"):]: v for k, v in arr.items() if k.startswith("rate/")})
            self.opt.load_arrays(arr, m["adam_steps"])
            self.strategy.load_arrays(arr, m.get("last_adjust", 0))
            self.load_run_state(m, arr)
        except KeyError as e:
            raise ProxycodecError(f"checkpoint is missing {e}", path) from None


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
        result.model.save(tmp_ply, extra_meta=result.extra_meta, extra_arrays=result.extra_arrays)
        os.replace(weights_path_for(tmp_ply), weights_path_for(ply_path))
        os.replace(tmp_ply, ply_path)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return ply_path, weights_path_for(ply_path)


# ================================================================================================ the run
def fit(data, out_ply: str | os.PathLike, config: FitConfig = FitConfig(), *, dataset_root: str = "",
        resume: bool = False, log: ProgressFn | None = None, keep_checkpoint: bool = False,
        stop_after: int | None = None, start: SceneModel | None = None,
        to_save: Callable[[FitResult], FitResult] | None = None, device=None) -> FitResult:
    """Train on ``data`` (a ``PosedImages``) and write ``out_ply`` (+ weights sidecar) atomically.

    ``start``: the scene to start from (``Trainer``'s; ``convert`` starts from anchors made of a 3DGS PLY's
    Gaussians) instead of anchors grown from the dataset's points.

    Checkpoints go to ``<out>.ckpt.pxc`` every ``config.checkpoint_every`` seconds and on interrupt/exception, and
    are removed after success unless ``keep_checkpoint``. ``resume`` continues from that checkpoint. ``to_save``:
    what is written instead of the result (``convert`` writes its canonical-frame result back in world units).
    ``device``: where it trains (None: the CPU; ``devices.resolve`` gives the command line's choice).
    ``stop_after`` (tests) raises ``KeyboardInterrupt`` after that many iterations of this call.
    """
    log = log or (lambda s: print(s, file=sys.stderr, flush=True))
    ckpt = checkpoint_path_for(out_ply)
    t_setup = time.perf_counter()

    def detail(st: dict) -> str:
        return (f"xi {st['xi']:.2f}  gauss {st['gaussians']:7d}  anchors {tr.anchors.num_anchors:6d}  "
                f"stage {tr.stage}")

    def hist_extra() -> dict:
        return {"anchors": tr.anchors.num_anchors}

    def make(cfg: FitConfig) -> Trainer:
        return Trainer(data, cfg, dataset_root, log, start=start, device=device)

    if resume:
        tr = make(config)
        if not ckpt.exists():
            raise ProxycodecError("no checkpoint to resume from", ckpt)
        tr.load_checkpoint(ckpt)
        log(f"resumed from {ckpt} at iteration {tr.iteration} ({fmt_time(tr.elapsed)} trained)")
    elif config.voxel_rule != "auto" or start is not None or config.voxel_size > 0:
        tr = make(config)
    elif not has_sfm_points(data) or config.time_budget is None or (
            config.iters is not None and config.iters < config.density_iters):
        # no SfM points: extent either way; a length in iterations decides by itself
        rule = density_rule(config) if has_sfm_points(data) else "extent"
        tr = make(replace(config, voxel_rule=rule))
        tr.density = {"rule": "auto", "chose": rule, "switch": config.density_iters}
        log(f"density auto: {rule} ({config.iters} iterations, switch at {config.density_iters})"
            if has_sfm_points(data) else "density auto: extent (no SfM points)")
    else:  # under a time budget: the pace at the spacing density decides
        tr = make(replace(config, voxel_rule="spacing"))
        warm_up_renderer(tr, log)
        t0 = time.perf_counter()
        for k in range(DENSITY_PROBE_STEPS):
            timed_step(tr, math.inf, t0, log, detail, hist_extra)
            if k == 0:  # the pace from the steps after the first, which carries one-off costs (a GPU's set-up)
                synchronize(tr.device)
                t1 = time.perf_counter()
        synchronize(tr.device)
        pace = (time.perf_counter() - t1) / (DENSITY_PROBE_STEPS - 1)
        expected = config.time_budget / pace if config.iters is None else min(config.time_budget / pace,
                                                                              config.iters)
        rule = density_rule(config, expected)
        info = {"rule": "auto", "chose": rule, "switch": config.density_iters, "expected_iterations":
                round(expected), "probe_steps": DENSITY_PROBE_STEPS, "probe_seconds": round(tr.elapsed, 3)}
        within = "" if config.target_size is None else f"; voxel {tr.anchors.voxel_size:.4g}, within the target size"
        log(f"density auto: {DENSITY_PROBE_STEPS} steps at the spacing density ({tr.anchors.num_anchors} anchors"
            f"{within}), {pace:.3g} s each after the first; the budget buys ~{expected:.0f} iterations, "
            f"{'>=' if rule == 'spacing' else '<'} {config.density_iters}: {rule}")
        if rule != "spacing":  # start afresh at the extent density; the probe's seconds stay spent
            spent = tr.elapsed
            tr = make(replace(config, voxel_rule=rule))
            tr.elapsed += spent
        tr.density = info
    if not resume:
        tr.color_init()
    log(f"fit: {len(data.train_indices)} training views, {tr.anchors.num_anchors} anchors "
        f"(voxel {tr.anchors.voxel_size:.4g}), setup {time.perf_counter() - t_setup:.1f} s; "
        f"iters {config.iters}, time budget {config.time_budget}")

    def finish() -> FitResult:
        res = tr.result()
        save_fitted(to_save(res) if to_save else res, out_ply)
        return res

    res = run_checkpointed(tr, ckpt, config.checkpoint_every, log, detail, hist_extra, finish,
                           keep_checkpoint=keep_checkpoint, stop_after=stop_after)
    log(f"done: {tr.iteration} iterations in {fmt_time(tr.elapsed)}, {tr.anchors.num_anchors} anchors -> "
        f"{out_ply}")
    return res
