"""Any 3DGS PLY in: plain Gaussians -> a resolution-aware anchor scene, without the training images.

1. **Anchors from a voxel grid over the Gaussians** (``choose_voxel``): every Gaussian falls in the cell
   ``round(mu / v)``; an anchor sits at each occupied cell's centre (Scaffold-GS's rule). The automatic ``v`` is the
   largest voxel (on a 2^(1/8) grid) at which the K = 10 heaviest Gaussians of each cell (weight: opacity x the area
   of the two largest axes) hold ``keep`` (90%) of all the weight: the anchor count follows the scene's density and
   scales. A budget is optional: ``max_anchors``, or ``target_size`` (container bytes, turned into anchors by
   ``anchors_for_size``); under a budget the voxel is the smallest that keeps within it.
2. **Each anchor starts from its cell's Gaussians** (``anchors_from_gaussians``): the K heaviest become its K
   offsets (``(mu - anchor) / v``, ``scaling[0:3] = log v``), ``scaling[3:6]`` is log(2 x the largest axis among
   them); free slots sit at the centre and start invisible. The features and the decoder's three MLPs are then
   fitted by regression (``fit_attributes``, no rendering) so that the decoded Gaussians start near the source's:
   opacity (tanh -> the source's sigmoid; free slots -> -0.5), log scale, rotation (1 - <q, q_src>^2) and colour
   (the source's SH colour along random view directions).
0. **In a canonical frame** (``CanonicalFrame``): the Gaussians and cameras are moved and scaled so that the
   scene's extent is ``CANONICAL_EXTENT`` about the origin; everything below (voxel, losses, learning rates, views,
   the near plane) then sees the same numbers whatever the PLY's units, and the result is written back in the PLY's
   units (``DecoderConfig.length_unit`` keeps it rendering the same there).
3. **Training against the PLY's own renders**: ``fit``'s trainer (growing and pruning, then stage 2: proxies and the
   residual predictor) on ``distill.TeacherViews`` of the source rendered as plain 3DGS, at random resolutions in
   [0.1, 1] with anti-aliased targets (the teacher's 100% render box-filtered down). Cameras: a ``cameras.json``
   beside the PLY (or two folders up, 3DGS's output layout), else automatic views (``auto_views``).
"""

from __future__ import annotations

import math
import os
import sys
import time
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

import numpy as np
import torch

from .camera import Camera
from .devices import as_device
from .errors import ProxycodecError
from .formats.images import check_background
from .loop import ProgressFn
from .model import SceneModel
from .scene import AnchorScene
from .train import FitConfig, anchors_for_bytes, first_true

__all__ = ["ConvertConfig", "ConvertResult", "VoxelChoice", "anchors_from_gaussians", "auto_views",
           "choose_voxel", "convert", "fit_attributes", "initial_model", "load_gaussians"]


@dataclass(frozen=True)
class ConvertConfig:
    """A conversion. ``fit``: the training run against the PLY's renders (its defaults below: 4000 iterations,
    cameras.json's views downscaled to 800 px; the anchor set grows and is pruned until stage 2 starts at half the
    run)."""

    # [D] measured on lego's PLY, 2x2 (SPEC.md section 11): fit's spread proxies and context-4 predictor (+0.30..0.37
    # dB against the source renders over random / context 1) and no learning-rate warm-up (+0.46..0.53 dB over 5%):
    # 32.38 dB against 31.55 for the settings used before. Resolutions drawn uniformly (no share at 100%). [D] The
    # rate term at fit's weight (1e-4): on bonsai's 300k-Gaussian PLY (20 minutes of training each) the container
    # is 35% smaller (556,352 B against 858,895; 1/9.0 of the SPZ against 1/5.8) for -0.49 dB against the source's
    # renders and -0.06 against the photos (SPEC.md section 11). [D] The grids learn at the former 2e-3, not fit's
    # 1e-2: conversion's ~2,000 stage-2 steps reach their balance at 2e-3, and on a 300k-Gaussian bonsai PLY 1e-2
    # took only 3.3% off the container for -0.46 dB (benchmarks/README.md, "The grids' learning rate").
    fit: FitConfig = field(default_factory=lambda: FitConfig(iters=4000, max_width=800, lr_warmup=0.0,
                                                             xi_full_share=0.0, lambda_rate=1e-4,
                                                             lr_quant_step=2e-3))
    voxel_size: float = 0.0  # <= 0: automatic (choose_voxel)
    keep: float = 0.9  # automatic voxel: share of the Gaussians' weight the anchors' K slots must hold
    # automatic voxel: at most this many anchors (None: as many as the keep rule asks; SPEC.md section 11)
    max_anchors: int | None = None
    # automatic voxel: the anchors a container of about this many bytes holds (``anchors_for_size``); None: no budget
    target_size: int | None = None
    init_iters: int = 400  # regression steps of fit_attributes
    views: int = 64  # automatic teacher views when the PLY has no cameras.json
    view_size: int = 400  # their width and height
    # the background the source is rendered on (and the anchor scene's); None: the one the PLY was trained on
    # (``explicit.ply_background``: its cfg_args, else black)
    background: tuple[float, float, float] | None = None
    # whether the source renders with the antialiased filter's opacity compensation (``GateConfig.antialiased``);
    # None: as the file says (an SPZ's or GLB's flag; an INRIA PLY has none)
    source_antialiased: bool | None = None
    lr_scale: float = 1.0  # fit's learning rates of the anchors and the decoder times this (FitConfig.with_lr_scale)

    def __post_init__(self) -> None:
        if not (0.0 < self.keep <= 1.0):
            raise ProxycodecError(f"keep must be in (0, 1], got {self.keep}")
        if not (math.isfinite(self.voxel_size) and self.voxel_size >= 0):
            raise ProxycodecError(f"voxel size must be a finite number >= 0 (0: automatic), got {self.voxel_size}")
        if (self.max_anchors is not None and self.max_anchors < 1) or self.init_iters < 0 or self.views < 2 \
                or self.view_size < 8:
            raise ProxycodecError("max_anchors >= 1, init_iters >= 0, views >= 2 and view_size >= 8 are required")
        if self.target_size is not None and self.target_size < CONTAINER_BASE_BYTES + CONTAINER_ANCHOR_BYTES:
            raise ProxycodecError(f"a target size below {CONTAINER_BASE_BYTES + CONTAINER_ANCHOR_BYTES:,} B holds no "
                                  f"anchor (the weights alone take ~{CONTAINER_BASE_BYTES:,} B)")
        if self.background is not None:
            object.__setattr__(self, "background", check_background(self.background))
        if not (math.isfinite(self.lr_scale) and self.lr_scale >= 0):
            raise ProxycodecError(f"learning-rate scale must be a finite number >= 0, got {self.lr_scale}")

    def anchor_budget(self) -> int | None:
        """The most anchors the automatic voxel may make: ``max_anchors``, ``target_size``'s, the smaller of both."""
        caps = [c for c in (self.max_anchors, anchors_for_size(self.target_size) if self.target_size else None)
                if c is not None]
        return min(caps) if caps else None


# ================================================================================================ the source
#: The extent (the 1..99% percentile box's largest side) every conversion works at: about lego's and the built-in
#: scene's (2.6, 2.35), on which conversion's defaults were measured.
CANONICAL_EXTENT = 2.5


@dataclass(frozen=True)
class CanonicalFrame:
    """``world = scale * canonical + center``: where a conversion works, and how its result goes back."""

    center: np.ndarray  # [3] float64
    scale: float

    @staticmethod
    def of(ply) -> "CanonicalFrame":
        """The frame that centres ``ply``'s 1..99% box on the origin and scales its extent to ``CANONICAL_EXTENT``."""
        center, extent = robust_box(ply.means)
        return CanonicalFrame(center, extent / CANONICAL_EXTENT)

    def gaussians_in(self, ply):
        """A ``GaussianPly`` in this frame (centres moved and scaled, log scales shifted; the rest as is)."""
        from .formats.inria_ply import GaussianPly

        means = ((ply.means.astype(np.float64) - self.center) / self.scale).astype(np.float32)
        scales = (ply.scales.astype(np.float64) - math.log(self.scale)).astype(np.float32)
        return GaussianPly(means, ply.sh, ply.opacities, scales, ply.quats, ply.normals, ply.has_normals)

    def camera_in(self, cam: Camera) -> Camera:
        """``cam`` (world) in this frame: the same image of the same points."""
        m = cam.world_to_camera.copy()
        m[:3, 3] = (m[:3, :3] @ self.center + m[:3, 3]) / self.scale
        return replace(cam, world_to_camera=m)

    def camera_out(self, cam: Camera) -> Camera:
        m = cam.world_to_camera.copy()
        m[:3, 3] = self.scale * m[:3, 3] - m[:3, :3] @ self.center
        return replace(cam, world_to_camera=m)

    def positions_out(self, positions: torch.Tensor, voxel: float) -> tuple[torch.Tensor, list[float] | None]:
        """Canonical anchor positions -> (world positions, the world grid's node 0 or None). The map is
        ``scale * p + center``; where every position is a node i x voxel / 2^j of the canonical grid (as ``fit``
        places anchors), the world position is that node's on the world grid through ``center``, f32(center + i x
        scale x voxel / 2^j) (``sections.grid_to_xyz``; within float32 rounding of the map), so that ``encode``
        codes the integers i (an octree, the scene's ``grid_shift``) instead of float32 positions."""
        from .sections import grid_positions, grid_to_xyz

        c = torch.as_tensor(self.center, dtype=torch.float64, device=positions.device)
        affine = (positions.detach().double() * self.scale + c).float()
        on = grid_positions(positions.detach().cpu().numpy(), voxel) if len(positions) else None
        if on is None:
            return affine, None
        ii, info = on
        shift = [float(v) for v in self.center]
        # the world grid's step at this subdivision: world voxel / 2^j, as encode's grid search divides it
        world = float(voxel * self.scale) / (voxel / info["step"])
        on_world = torch.from_numpy(grid_to_xyz(ii, world, "f64", shift)).to(positions.device)
        if float((on_world.double() - affine.double()).abs().max()) > 1e-3 * world:  # a safeguard: never moves
            return affine, None
        return on_world, shift

    def model_out(self, model: SceneModel) -> SceneModel:
        """A scene trained in this frame, in world units: positions moved back, every log scaling shifted by
        log(scale) (offsets are in units of the first three), the decoder's length unit and embedding frame scaled;
        it renders from world cameras what the canonical scene renders from canonical ones."""
        s = model.scene
        pos, shift = self.positions_out(s.positions, s.voxel_size)
        scal = (s.scalings.detach().double() + math.log(self.scale)).float()
        meta = {k: v for k, v in s.metadata.items() if k != "grid_shift"}
        scene = AnchorScene(pos, s.features.detach(), s.offsets.detach(), scal, float(s.voxel_size * self.scale),
                            {**meta, **({} if shift is None else {"grid_shift": shift})}).validate()
        cfg = model.decoder.config
        dcfg = replace(cfg, scene_center=tuple(float(v) for v in self.center + self.scale * np.asarray(
            cfg.scene_center, dtype=np.float64)), scene_radius=float(cfg.scene_radius * self.scale),
                       length_unit=float(cfg.length_unit * self.scale))
        from .decoder import GaussianDecoder

        dec = GaussianDecoder.from_arrays(dcfg, model.decoder.state_arrays()).to(s.positions.device).eval()
        cams = [self.camera_out(c) for c in model.cameras] if model.cameras else model.cameras
        return SceneModel(scene, dec, cams, model.background, dict(model.meta))

    def result_out(self, res):
        """``train.FitResult`` in world units: the model, and the stage-2 predictor's distance reference and proxy
        cell (``fit`` metadata) scaled."""
        meta = {k: (dict(v) if isinstance(v, dict) else v) for k, v in res.extra_meta.items()}
        fit_meta = meta.get("fit")
        if isinstance(fit_meta, dict):
            if isinstance(fit_meta.get("predictor"), dict) and "dist_ref" in fit_meta["predictor"]:
                fit_meta["predictor"] = {**fit_meta["predictor"],
                                         "dist_ref": float(fit_meta["predictor"]["dist_ref"]) * self.scale}
            if isinstance(fit_meta.get("proxy_cell"), (int, float)):
                fit_meta["proxy_cell"] = float(fit_meta["proxy_cell"]) * self.scale
            fit_meta["canonical_frame"] = {"center": [float(v) for v in self.center], "scale": float(self.scale)}
        return replace(res, model=self.model_out(res.model), extra_meta=meta)


@dataclass
class Gaussians:
    """A 3DGS PLY's Gaussians, activated and made safe to build from (float64 numpy)."""

    means: np.ndarray  # [N, 3]
    sh: np.ndarray  # [N, C, 3] float32 (as stored)
    alpha: np.ndarray  # [N] sigmoid(opacity)
    scales: np.ndarray  # [N, 3] exp(log scale), clamped to [1e-7, 1e3] x the scene's extent
    quats: np.ndarray  # [N, 4] unit wxyz (zero quaternions -> identity)
    degree: int
    extent: float  # robust size of the scene (the 1..99% percentile box's largest side)


def robust_box(means: np.ndarray) -> tuple[np.ndarray, float]:
    """(centre, extent) of the centres' 1..99th percentile box (all of them below 100 Gaussians), the extent its
    largest side (the whole box's where that is 0); no centres, or all in one point, are refused (there is nothing
    to place anchors on)."""
    n = len(means)
    if n == 0:
        raise ProxycodecError("the PLY holds no Gaussians; nothing to convert")
    means = means.astype(np.float64)
    lo, hi = np.percentile(means, [1, 99], axis=0) if n >= 100 else (means.min(0), means.max(0))
    extent = float((hi - lo).max())
    if not extent > 0:
        extent = float((means.max(0) - means.min(0)).max())
    if not extent > 0:
        raise ProxycodecError(f"all {n} Gaussians sit in one point; there is no scene to place anchors on")
    return 0.5 * (lo + hi), extent


def load_gaussians(ply) -> Gaussians:
    """``formats.inria_ply.GaussianPly`` -> ``Gaussians`` (``robust_box`` gives the extent and refuses empty or
    one-point PLYs)."""
    _, extent = robust_box(ply.means)
    means = ply.means.astype(np.float64)
    q = ply.quats.astype(np.float64)
    qn = np.linalg.norm(q, axis=1, keepdims=True)
    q = np.where(qn > 1e-12, q / np.maximum(qn, 1e-300), np.array([1.0, 0.0, 0.0, 0.0]))
    log_s = np.clip(ply.scales.astype(np.float64), math.log(1e-7 * extent), math.log(1e3 * extent))
    alpha = 1.0 / (1.0 + np.exp(-ply.opacities.astype(np.float64)))
    return Gaussians(means, ply.sh, alpha, np.exp(log_s), q, ply.sh_degree, extent)


def _weights(g: Gaussians) -> np.ndarray:
    """What a Gaussian weighs in a picture: opacity x the area of its two largest axes."""
    s = np.sort(g.scales, axis=1)
    return g.alpha * s[:, 1] * s[:, 2] + 1e-30


# ================================================================================================ the voxel grid
@dataclass(frozen=True)
class VoxelChoice:
    voxel: float
    anchors: int
    kept_gaussians: int  # Gaussians that become a slot (the K heaviest of each cell)
    kept_weight: float  # their share of the weight
    automatic: bool

    def describe(self) -> str:
        how = "automatic" if self.automatic else "given"
        return (f"voxel {self.voxel:.5g} ({how}): {self.anchors:,} anchors; the K heaviest Gaussians of each cell "
                f"keep {self.kept_gaussians:,} Gaussians, {100 * self.kept_weight:.1f}% of the weight")


#: A converted container's bytes ~ CONTAINER_BASE_BYTES + CONTAINER_ANCHOR_BYTES x anchors (``target_size``):
#: the weights, predictor and metadata (~57 KB), and per anchor the larger of the two measurements with the rate
#: term, so that a container lands under its target: the built-in scene's 3DGS export 31.1 B at 1000 iterations,
#: bonsai's PLY 22.3 B at 2,265 (benchmarks/README.md, "Anchor budgets"; 39.8 and 35.8 B without the rate term).
CONTAINER_BASE_BYTES = 57_000
CONTAINER_ANCHOR_BYTES = 31.0


def anchors_for_size(target_bytes: int) -> int:
    """The anchors a converted container of ``target_bytes`` holds, by the linear model above."""
    return anchors_for_bytes(target_bytes, CONTAINER_BASE_BYTES, CONTAINER_ANCHOR_BYTES)


def _cells(means: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """-> (unique cells [M, 3] int64, cell index of each point [N]), sorted as ``np.unique(axis=0)`` sorts them.

    Sparse voxel hashing: the three cell indices packed into one int64 key (a 1-D unique, several times faster
    than the row-wise one and O(N) memory) where their ranges fit in 63 bits; else row-wise."""
    cells = np.round(means / voxel).astype(np.int64)
    lo = cells.min(0)
    span = cells.max(0) - lo + 1
    if float(span[0]) * float(span[1]) * float(span[2]) < 2.0 ** 62:
        c = cells - lo
        key = (c[:, 0] * span[1] + c[:, 1]) * span[2] + c[:, 2]
        ukey, inv = np.unique(key, return_inverse=True)
        z = ukey % span[2]
        y = (ukey // span[2]) % span[1]
        x = ukey // (span[1] * span[2])
        return np.stack([x, y, z], 1) + lo, inv.reshape(-1)
    uniq, inv = np.unique(cells, axis=0, return_inverse=True)
    return uniq, inv.reshape(-1)


def _slots(inv: np.ndarray, weight: np.ndarray, M: int, K: int) -> tuple[np.ndarray, np.ndarray]:
    """-> (order: points grouped by cell, heaviest first; rank of each point of ``order`` within its cell)."""
    order = np.lexsort((-weight, inv))
    cell = inv[order]
    starts = np.searchsorted(cell, np.arange(M))
    rank = np.arange(len(order)) - starts[cell]
    return order, rank


def _kept(means, weight, voxel, K) -> tuple[int, int, float]:
    uniq, inv = _cells(means, voxel)
    order, rank = _slots(inv, weight, len(uniq), K)
    keep = rank < K
    return len(uniq), int(keep.sum()), float(weight[order][keep].sum() / weight.sum())


#: The automatic voxel's grid: extent / 16 x 2^(-i/8), i = 0..64 (down to extent / 4096).
VOXEL_STEPS = 64


def choose_voxel(g: Gaussians, K: int, cfg: ConvertConfig) -> VoxelChoice:
    """The anchors' voxel: ``cfg.voxel_size``, or the largest on a 2^(1/8) grid between extent/16 and extent/4096
    whose cells' K heaviest Gaussians keep ``cfg.keep`` of the weight (the finest when none does); under a budget
    (``cfg.anchor_budget()``) no finer than the finest within it. Bisection on the grid: the kept share grows and
    the anchor count grows as the voxel shrinks (O(N log N) per probe, ~2 log2(64) probes)."""
    w = _weights(g)
    if cfg.voxel_size > 0:
        M, kept, share = _kept(g.means, w, cfg.voxel_size, K)
        return VoxelChoice(cfg.voxel_size, M, kept, share, False)
    cache: dict[int, VoxelChoice] = {}

    def at(i: int) -> VoxelChoice:
        if i not in cache:
            v = g.extent / 16.0 * 2.0 ** (-i / 8.0)
            cache[i] = VoxelChoice(v, *_kept(g.means, w, v, K), True)
        return cache[i]

    i = first_true(lambda k: at(k).kept_weight >= cfg.keep, 0, VOXEL_STEPS)
    budget = cfg.anchor_budget()
    if budget is not None and at(i).anchors > budget:
        j = first_true(lambda k: at(k).anchors > budget, 0, i) - 1  # the finest voxel within the budget
        i = max(j, 0)
    return at(i)


# ================================================================================================ the initial anchors
@dataclass
class SlotTargets:
    """What each anchor's K decoded Gaussians should start as (``fit_attributes``'s targets)."""

    used: torch.Tensor  # [M, K] bool: slot holds a source Gaussian
    alpha: torch.Tensor  # [M, K] opacity (0 where unused)
    log_scale: torch.Tensor  # [M, K, 3]
    quat: torch.Tensor  # [M, K, 4] unit
    sh: torch.Tensor  # [M, K, C, 3]

    def to(self, device) -> SlotTargets:
        return SlotTargets(*(getattr(self, f.name).to(device) for f in fields(self)))


def anchors_from_gaussians(g: Gaussians, voxel: float, K: int, F: int) -> tuple[AnchorScene, SlotTargets]:
    """Anchors at the occupied cells' centres; the K heaviest Gaussians of a cell as its offsets (free slots at the
    centre); features zero (``fit_attributes`` sets them)."""
    uniq, inv = _cells(g.means, voxel)
    M = len(uniq)
    order, rank = _slots(inv, _weights(g), M, K)
    keep = rank < K
    src, cell, slot = order[keep], inv[order][keep], rank[keep]
    anchors = uniq.astype(np.float64) * voxel
    used = np.zeros((M, K), bool)
    used[cell, slot] = True
    offsets = np.zeros((M, K, 3))
    offsets[cell, slot] = (g.means[src] - anchors[cell]) / voxel
    s = np.ones((M, K, 3)) * voxel
    s[cell, slot] = g.scales[src]
    q = np.tile(np.array([1.0, 0.0, 0.0, 0.0]), (M, K, 1))
    q[cell, slot] = g.quats[src]
    alpha = np.zeros((M, K))
    alpha[cell, slot] = g.alpha[src]
    sh = np.zeros((M, K) + g.sh.shape[1:], np.float32)
    sh[cell, slot] = g.sh[src]
    base = np.log(2.0 * np.where(used[..., None], s, 0.0).max(axis=(1, 2)).clip(min=1e-7 * g.extent))
    scal = np.concatenate([np.full((M, 3), math.log(voxel)), np.repeat(base[:, None], 3, 1)], 1)
    f32 = lambda a: torch.tensor(a, dtype=torch.float32)  # noqa: E731
    scene = AnchorScene(f32(anchors), torch.zeros(M, F), f32(offsets), f32(scal), float(voxel),
                        {"name": "converted"}).validate()
    targets = SlotTargets(torch.from_numpy(used), f32(alpha), f32(np.log(s)), f32(q), torch.from_numpy(sh))
    return scene, targets


def fit_attributes(scene: AnchorScene, decoder, targets: SlotTargets, degree: int, view_distance: float,
                   iters: int, seed: int = 0, log: ProgressFn | None = None) -> AnchorScene:
    """Fit the anchors' features and the decoder's opacity / covariance / colour MLPs so that each anchor's decoded
    Gaussians start near its slots' targets (no rendering; the embedding is the identity at this point). Views:
    random directions at ``view_distance``. Returns the scene with the fitted features; the decoder is changed in
    place."""
    from .explicit import eval_sh

    log = log or (lambda s: None)
    M, K = targets.used.shape
    if iters == 0 or M == 0:
        return scene
    dev = scene.positions.device  # random draws on the CPU (the same on every device), moved there
    gen = torch.Generator().manual_seed(seed)
    feats = (0.01 * torch.randn(scene.features.shape, generator=gen)).to(dev).requires_grad_(True)
    mlps = [decoder.mlp_opacity, decoder.mlp_cov, decoder.mlp_color]
    params = [feats] + [p for m in mlps for p in m.parameters()]
    opt = torch.optim.Adam([{"params": [feats], "lr": 0.02}, {"params": params[1:], "lr": 0.003}])
    base = scene.scalings[:, 3:]
    used = targets.used
    alpha_t = torch.where(used, targets.alpha, torch.full_like(targets.alpha, -0.5))
    cfg = decoder.config
    batch = min(M, 16384)
    t0 = time.perf_counter()
    for it in range(iters):
        idx = (torch.randint(0, M, (batch,), generator=gen) if batch < M else torch.arange(M)).to(dev)
        d = torch.randn(len(idx), 3, generator=gen).to(dev)
        d = d / d.norm(dim=1, keepdim=True).clamp_min(1e-12)  # view direction: camera -> anchor
        dist = torch.full((len(idx), 1), float(view_distance), device=dev)
        x = torch.cat([feats[idx], d, dist], -1)
        op = torch.tanh(decoder.mlp_opacity(x if cfg.opacity_dist else x[:, :-1]))
        cov = decoder.mlp_cov(x if cfg.cov_dist else x[:, :-1]).reshape(-1, K, 7)
        col = torch.sigmoid(decoder.mlp_color(x if cfg.color_dist else x[:, :-1])).reshape(-1, K, 3)
        u = used[idx].float()
        n_used = u.sum().clamp_min(1.0)
        loss_op = ((op - alpha_t[idx]) ** 2).mean()
        log_s = base[idx][:, None, :] + torch.nn.functional.logsigmoid(cov[..., :3])
        loss_s = (((log_s - targets.log_scale[idx]) ** 2).mean(-1) * u).sum() / n_used
        qhat = cov[..., 3:] / cov[..., 3:].norm(dim=-1, keepdim=True).clamp_min(1e-12)
        loss_q = ((1.0 - (qhat * targets.quat[idx]).sum(-1) ** 2) * u).sum() / n_used
        with torch.no_grad():  # the source's colour of each slot seen along this anchor's view direction
            sh = targets.sh[idx].reshape(-1, *targets.sh.shape[2:])
            dirs = d[:, None, :].expand(-1, K, 3).reshape(-1, 3)
            rgb = (eval_sh(degree, sh, dirs) + 0.5).clamp(0.0, 1.0).reshape(-1, K, 3)
        loss_c = (((col - rgb) ** 2).mean(-1) * u).sum() / n_used
        loss = loss_op + 0.1 * loss_s + 0.1 * loss_q + loss_c
        opt.zero_grad()
        loss.backward()
        opt.step()
        if it == 0 or it + 1 == iters or (it + 1) % 100 == 0:
            log(f"  initial fit {it + 1:4d}/{iters}: opacity {loss_op.item():.4f}  log-scale {loss_s.item():.3f}  "
                f"rotation {loss_q.item():.3f}  colour {loss_c.item():.4f}  ({time.perf_counter() - t0:.1f} s)")
    return AnchorScene(scene.positions, feats.detach().clone(), scene.offsets, scene.scalings, scene.voxel_size,
                       dict(scene.metadata)).validate()


# ================================================================================================ the views
def auto_views(g: Gaussians, n: int, size: int) -> tuple[list[Camera], str]:
    """Views for a PLY without cameras, and which layout they follow.

    Decided from how the Gaussians' weight spreads around their weighted centre: ``r50`` / ``r90``, the radii
    holding half and 90% of it. An object (r90 < 3 r50: the weight sits in one blob) is seen **outside-in**: views on
    a sphere (icosphere directions) at the distance where the 90% sphere fills a 50-degree field of view, looking at
    the centre. A room or an unbounded capture (r90 >= 3 r50: a near part and far walls or background) is seen
    **inside-out**: views at r50 / 2 from the centre looking outward, alternating with views at r50 looking in.
    """
    import trimesh

    w = g.alpha + 1e-12
    center = (g.means * w[:, None]).sum(0) / w.sum()
    r = np.linalg.norm(g.means - center, axis=1)
    o = np.argsort(r)
    cw = np.cumsum(w[o]) / w.sum()
    r50 = float(r[o][np.searchsorted(cw, 0.5)])
    r90 = float(r[o][min(np.searchsorted(cw, 0.9), len(o) - 1)])
    r50 = max(r50, 1e-6 * g.extent, 1e-9)
    r90 = max(r90, r50)
    dirs = np.asarray(trimesh.creation.icosphere(subdivisions=3).vertices, dtype=np.float64)  # 642 directions
    pick = dirs[np.round(np.linspace(0, len(dirs) - 1, min(n, len(dirs)))).astype(int)]
    fov = 50.0
    up = np.array([0.0, 0.0, 1.0])
    cams = []
    if r90 < 3.0 * r50:
        layout = "outside-in"
        dist = r90 / math.sin(math.radians(fov) / 2)
        for i, d in enumerate(pick):
            cams.append(Camera.look_at(center + dist * d, center, up, fov_x_deg=fov, width=size, height=size,
                                       name=f"auto_{i:03d}"))
    else:
        layout = "inside-out"
        for i, d in enumerate(pick):
            if i % 2 == 0:
                eye, target = center + 0.5 * r50 * d, center + 2.0 * r50 * d
            else:
                eye, target = center + r50 * d, center
            cams.append(Camera.look_at(eye, target, up, fov_x_deg=fov + 20.0, width=size, height=size,
                                       name=f"auto_{i:03d}"))
    return cams, layout


# ================================================================================================ the run
@dataclass
class ConvertResult:
    path: Path  # the anchor PLY written (weights sidecar beside it)
    model: SceneModel
    voxel: VoxelChoice
    cameras: str  # where the teacher's views came from
    layout: str | None  # automatic views: outside-in / inside-out
    iterations: int
    seconds: dict
    report: dict  # held-out: the converted scene and the source PLY against the anti-aliased source renders
    history: list = field(default_factory=list)

    def to_json(self) -> dict:
        return {"path": str(self.path), "voxel": self.voxel.__dict__, "cameras": self.cameras,
                "layout": self.layout, "iterations": self.iterations, "seconds": self.seconds,
                "report": self.report}


def initial_model(g: Gaussians, cfg: ConvertConfig, cameras: list[Camera], log: ProgressFn,
                  seconds: dict | None = None, device=None) -> tuple[SceneModel, VoxelChoice]:
    """The anchor scene a conversion starts from: voxel, anchors, decoder and features fitted to the Gaussians
    (on ``device``; the voxel and the anchors are found on the CPU). ``seconds`` (optional) receives each step's
    time: ``voxel``, ``anchors``, ``initial_fit``."""
    from .decoder import GaussianDecoder

    seconds = {} if seconds is None else seconds
    fc = cfg.fit
    t = time.perf_counter()
    choice = choose_voxel(g, fc.n_offsets, cfg)
    seconds["voxel"] = time.perf_counter() - t
    t = time.perf_counter()
    scene, targets = anchors_from_gaussians(g, choice.voxel, fc.n_offsets, fc.feat_dim)
    dev = as_device(device)
    scene, targets = scene.to(dev), targets.to(dev)
    seconds["anchors"] = time.perf_counter() - t
    b = scene.bounds()
    center = 0.5 * (b[0] + b[1])
    radius = max(0.5 * float(np.linalg.norm(b[1] - b[0])), 1e-6)
    torch.manual_seed(fc.seed)
    dec = GaussianDecoder(fc.decoder_config(center, radius)).to(dev)
    cam_c = np.array([c.center for c in cameras])
    dist = float(np.median(np.linalg.norm(cam_c - center, axis=1))) if len(cam_c) else radius
    t = time.perf_counter()
    scene = fit_attributes(scene, dec, targets, g.degree, dist, cfg.init_iters, fc.seed, log)
    seconds["initial_fit"] = time.perf_counter() - t
    from .explicit import PLY_BACKGROUND

    return SceneModel(scene, dec.eval(), list(cameras), tuple(cfg.background or PLY_BACKGROUND)), choice


def convert(ply_path: str | os.PathLike, out_ply: str | os.PathLike, config: ConvertConfig = ConvertConfig(), *,
            resume: bool = False, log: ProgressFn | None = None, report_views: int = 8,
            stop_after: int | None = None, device=None) -> ConvertResult:
    """Convert the INRIA 3DGS PLY at ``ply_path`` into an anchor scene at ``out_ply`` (+ weights sidecar, written
    atomically by ``fit``; resumable from its checkpoint, ``<out>.ckpt.pxc``, saved on interrupt as ``fit`` saves
    it). ``stop_after`` (tests): interrupt after that many training iterations. ``device``: where the initial fit,
    the teacher's renders and the training compute (None: the CPU)."""
    from .distill import TeacherViews, held_out_report, report_line
    from .explicit import ExplicitModel, ply_background
    from .formats.splats import read_splats
    from .scaffold_gs import find_cameras_json, read_scaffold_cameras
    from .train import fit

    log = log or (lambda s: print(s, file=sys.stderr, flush=True))
    t0 = time.perf_counter()
    world_ply, info = read_splats(ply_path)
    stages = {"read": time.perf_counter() - t0}
    frame = CanonicalFrame.of(world_ply)
    ply = frame.gaussians_in(world_ply)  # everything below works in the canonical frame
    del world_ply
    g = load_gaussians(ply)
    log(f"convert: {ply.n_gaussians:,} Gaussians, SH degree {ply.sh_degree}, extent {frame.scale * g.extent:.4g} "
        f"(worked at {g.extent:.4g})")
    if config.background is None:
        bg, where = ply_background(ply_path)
        config = replace(config, background=bg)
    else:
        where = "given"
    log(f"background: {' '.join(f'{b:g}' for b in config.background)} ({where})")
    # the source renders as it was trained (SPZ flag 0x1), unless told
    aa = bool(info.get("antialiased", False)) if config.source_antialiased is None else config.source_antialiased
    if aa:
        log("the source renders antialiased (the filter's opacity compensation): "
            + ("its file says it was trained so" if config.source_antialiased is None else "as asked"))
    teacher = ExplicitModel(ply, tuple(config.background),
                            {"kind": "inria-3dgs", "source": str(Path(ply_path)), "background_from": where,
                             "antialiased": aa}, antialiased=aa).to(as_device(device))
    cj = find_cameras_json(ply_path)
    layout = None
    if cj is not None:
        cams = [frame.camera_in(c) for c in read_scaffold_cameras(cj)]
        if config.fit.max_width:
            cams = [c.with_max_width(int(config.fit.max_width)) for c in cams]
        where = f"{cj} ({len(cams)} views)"
    else:
        cams, layout = auto_views(g, config.views, config.view_size)
        where = f"automatic, {layout} ({len(cams)} views of {config.view_size} px)"
    log(f"teacher views: {where}")
    views = TeacherViews(teacher, cams, backend=config.fit.backend)
    # resuming: the checkpoint replaces the start's features and decoder, so they are not fitted again
    work = replace(config, voxel_size=config.voxel_size / frame.scale)  # a given voxel: world units -> canonical
    start, choice = initial_model(g, replace(work, init_iters=0) if resume else work, cams, log, stages, device)
    choice = replace(choice, voxel=choice.voxel * frame.scale)
    log(choice.describe() + (f" (budget {config.anchor_budget():,} anchors)" if config.anchor_budget() else ""))
    t_init = time.perf_counter() - t0
    fit_cfg = config.fit.with_lr_scale(config.lr_scale)
    if config.anchor_budget() is not None:  # growing keeps within the budget too
        cap = config.anchor_budget() if fit_cfg.max_anchors is None else min(fit_cfg.max_anchors, config.anchor_budget())
        fit_cfg = replace(fit_cfg, max_anchors=cap)
    res = fit(views, out_ply, fit_cfg, dataset_root=str(ply_path), resume=resume,
              log=log, start=start, stop_after=stop_after, to_save=frame.result_out, device=device)
    t_fit = time.perf_counter() - t0 - t_init
    rep = held_out_report(res.model, views, max_views=report_views, backend=config.fit.backend)
    src = held_out_report(teacher, views, max_views=report_views, backend=config.fit.backend)
    log(f"converted vs the source's anti-aliased renders (held out): {report_line(rep)}")
    log(f"the source PLY rendered directly, same reference:         {report_line(src)}")
    seconds = {**stages, "setup": t_init, "train": res.seconds, "fit_call": t_fit, "total": time.perf_counter() - t0}
    return ConvertResult(Path(out_ply), frame.model_out(res.model), choice, where, layout, res.iterations, seconds,
                         {"converted": rep, "source_direct": src}, res.history)


def replace_fit(config: ConvertConfig, **fit_fields) -> ConvertConfig:
    """``config`` with fields of its ``FitConfig`` replaced."""
    return replace(config, fit=replace(config.fit, **fit_fields))


def convert_and_encode(ply_path: str | os.PathLike, out: str | os.PathLike, config: ConvertConfig = ConvertConfig(),
                       *, keep: str | os.PathLike | None = None, log: ProgressFn | None = None, device=None,
                       **encode_knobs):
    """``convert`` then ``codec.encode`` of the anchor scene (its stage-2 predictor as fitted): -> (ConvertResult,
    EncodeReport). ``keep``: where the intermediate anchor PLY (+ weights) goes; default a temporary folder that is
    removed afterwards."""
    import shutil
    import tempfile

    from .codec import encode

    log = log or (lambda s: print(s, file=sys.stderr, flush=True))
    tmp = None
    if keep is None:
        out_dir = Path(out).resolve().parent
        out_dir.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{Path(out).name}.", suffix=".convert", dir=out_dir))
        keep = tmp / "anchors.ply"
    try:
        conv = convert(ply_path, keep, config, log=log, device=device)
        src = {"name": Path(ply_path).name, "bytes": Path(ply_path).stat().st_size, "kind": "inria-3dgs"}
        info = {**conv.to_json(), "source": src, "kept": None if tmp is not None else str(keep)}
        info.pop("path")
        info.pop("seconds")  # same input, same bytes: the container holds no time (the result keeps it)
        # the container's source is the 3DGS PLY (stats' ratio is against it), not the intermediate anchor scene
        report = encode(keep, out, progress=log, extra_meta={"convert": info, "source": src}, device=device,
                        **encode_knobs)
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    report.source_bytes = src["bytes"]
    return conv, report
