"""The scene codec: anchor scene + decoder -> compact proxy-anchor container (``.pxc``, scene format v1) and back.

``encode`` keeps ~30% of the anchors as proxies (density-aware, ``proxy.select_proxies``), fits the residual
predictor to the scene's own leaves, quantises the per-anchor attributes, and writes one zstd section per attribute
(``formats/container.py``). ``decode`` regenerates the leaf features from the proxies. Byte layout and every section:
``formats/CONTAINER.md``.

Exactness contract: ``decode(path)`` returns bit-for-bit the model that ``encode`` reports as ``report.model`` (both
go through ``_model_from_sections``): positions exactly as given when they lie on a voxel grid, other stored arrays
equal to their dequantised values, leaf features from the same predictor with the same (rounded) weights.
"""

from __future__ import annotations

import math
import os
import tempfile
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np
import zstandard
import torch

from . import octree
from .camera import Camera
from .camera import default_cameras as camera_defaults
from .decoder import GaussianDecoder
from .devices import as_device
from .errors import ProxycodecError
from .loop import check_run_length
from .formats.container import (
    MAGIC, ContainerError, SectionInfo, read_container, read_header, write_container,
)
from .model import SceneModel, SceneRender, reference_width, weights_path_for
from .scaffold_gs import find_scaffold_files, is_scaffold_output, load_scaffold_output
from .proxy import (
    PredictorConfig, ResidualPredictor, TrainConfig, TrainResult, default_cell_size, predictor_neighbours,
    check_proxy_selection, load_fitted_predictor, select_proxies, torch_threads, train_predictor,
)
from .scene import AnchorScene
# The scene format (both halves) is torch-free; proxycodec.lite reads containers through it too.
from .sections import (
    DEFAULT_WEIGHTS_DTYPE, FLOAT_BITS, MAX_ANCHORS, MAX_LEVEL_CELLS, OFFSETS, POSITION_CODINGS, PREDICT_CHUNK,
    PROXY_FEATURES, SCALINGS, SCENE_FORMAT, SCENE_FORMAT_ENTROPY, SCENE_FORMAT_LEVELS, SCENE_FORMAT_OCTREE, SCENE_KIND,
    WEIGHT_DTYPES, QuantizedAnchors,
    encode_positions, guarded, level_table, pack_weights, quantize_anchors, read_scene_container, scene_extras,
    scene_features, scene_metadata, scene_sections, stored_anchors, weights_from_sections, zero_dead_offsets,
)

__all__ = ["EncodeConfig", "EncodeReport", "CompressedScene", "encode", "decode", "load", "stats", "render",
           "SCENE_KIND", "SCENE_FORMAT"]

Progress = Callable[[str], None]


# ---------------------------------------------------------------------------------------------- configuration
@dataclass(frozen=True)
class EncodeConfig:
    proxy_ratio: float = 0.3
    cell_size: float | None = None  # world units; None: a multiple of the voxel size giving ~cell_target anchors/cell
    cell_target: float = 10.0
    # [D] "spread" (proxy.select_proxies) and context 4 by default, as fit's stage 2 (since 2026-11-23): on lego's
    # no-proxy scene (25 photos, 10%..100%) 25.87 dB against 23.57 for "random" (the paper's) and context 1 with the
    # L_recon-only predictor, +0.24 dB distilled (SPEC.md section 4); ~+11 KB of predictor weights
    proxy_selection: str = "spread"  # when not as fitted
    feature_bits: int = 8  # proxy features, uniform per channel (32 = float32)
    offset_bits: int = 8  # the most sensitive part of the file (SPEC.md section 4)
    scaling_bits: int = 8
    # MLP weights: "f16" | "f32" | "qN" (int8 matrices on a grid of 2^(N-1) - 1 levels each side, per-row scales).
    # [D] q7: 6.1 KB under q8 on every scene measured, at equal quality (lego's and bonsai's fits, bonsai's
    # conversion: -0.001 / +0.019 / +0.006 dB); q6 saves 6.2 KB more but costs lego 0.30 dB (SPEC.md section 4)
    weights_dtype: str = DEFAULT_WEIGHTS_DTYPE
    max_cameras: int = 16  # default cameras kept in the container (evenly spaced over the model's cameras)
    # True: leaves' offsets are predicted; False: every anchor's are stored; None: as the scene's stage-2 predictor
    # does when it is used (``fit --predict-offsets``), else stored
    predict_offsets: bool | None = None
    predictor_hidden: int = 64
    predictor_blocks: int = 2
    predictor_context: int = 4  # proxies the (refitted) predictor sees per leaf
    # [D] 6000: on the built-in scene (context 4) the decoded views gain 5-6 dB over 2000 iterations (SPEC.md
    # section 6) for ~10 s; a scene with a stage-2 predictor skips this fit, a distilled one trains its own
    predictor_iters: int = 6000
    predictor_lr: float = 2e-3
    leaf_sample: float = 0.2  # fraction of the leaves per predictor iteration [S Fig. 12]
    zstd_level: int = 19
    # "model": the stored attributes arithmetic-coded under the conditional entropy model (scene format 4,
    # ``proxycodec.entropy``); "zstd": zstd alone (scene format 2); "auto": the model where its stream and nets are
    # smaller than zstd's sections (small scenes: the nets' fixed cost does not pay). Predicted offsets and float32
    # attributes use zstd.
    entropy: str = "auto"
    # grid positions: "octree" (an octree's child masks, binary ANS under per-level contexts: scene format 6; bonsai's
    # 110k anchors 114 KB against 195 KB; SPEC.md section 4) or "delta" (Morton-ordered per-axis deltas, zstd: the
    # formats 2-5 that older readers read). [D] Lossless, so the default: the same scene in fewer bytes.
    positions: str = "octree"
    entropy_iters: int = 1500  # Adam iterations fitting the entropy model to the scene's symbols
    entropy_hidden: int = 16  # [D] lego at lambda 1e-4: 142,760 B against 146,315 B with 32 (nets halved, stream +1.3 KB)
    # Rate in distillation's loss (``FitConfig.lambda_rate``): noise quantisation with learned steps per channel.
    lambda_rate: float = 0.0
    quant_cells: int = 0  # with lambda_rate: per-cell quantisation levels (``FitConfig.quant_cells``; scene format 5)
    # Quantise with the steps rate training learned (the scene's ``quant_steps`` metadata) instead of the bit depths.
    learned_steps: bool = True
    seed: int = 0
    use_fitted: bool = True  # a stage-2 predictor + proxy mask in the weights sidecar (proxycodec fit) is used as is
    # Offsets of neural Gaussians that are never drawn (opacity <= dead_threshold from every sampled viewpoint and
    # resolution) are stored as the level nearest 0: the decoder never places them, so their value is free.
    # Off by default: it saves little for much encode time (SPEC.md section 4).
    drop_dead_offsets: bool = False
    dead_threshold: float = -0.02
    # Distillation (``proxycodec.distill``): fine-tune the proxy scene against the source scene's own renders.
    # None: decided by measurement for a scene without a stage-2 predictor (a fitted one is used as it is): its
    # L_recon encode is rendered against the source, and distilled only when that falls below distill_threshold;
    # True / False: always / never (never: the predictor is fitted on feature distance, L_recon, alone).
    distill: bool | None = None
    # [D] the choice's threshold, dB against the source rendered at the same resolution (mean over choice_views
    # views spread over the teacher's, at choice_resolutions): above what distillation reaches on lego's no-proxy
    # fit, below the built-in scene's L_recon encode (SPEC.md section 4; benchmarks/encode_choice.py)
    distill_threshold: float = 40.0
    choice_resolutions: tuple[float, ...] = (0.1, 0.3, 1.0)
    choice_views: int = 4
    # [D] 3600 iterations: the whole-multiple targets render the teacher on most iterations (1.40x per iteration);
    # lego's encode measured 15:14 and 18:17 on 2 cores (benchmarks/README.md)
    distill_iters: int | None = 3600
    distill_time_budget: float | None = None  # seconds; with distill_iters, whichever ends first
    distill_views: int = 32  # teacher views at least: automatic views are added around the scene up to this many
    # share of the distillation's iterations at 100% (fit's xi_full_share, whose default fitted the sources it
    # distils): the decoded scene's gap to its source sits at high resolution (SPEC.md section 4)
    distill_full_share: float = 0.25
    distill_lr_scale: float = 1.0  # fit's learning rates of the anchors and the decoder times this (not the predictor's)
    distill_lr_warmup: float = 0.05  # every learning rate ramps up over this fraction of the distillation
    # [D] fit's constant learning rates (features, scalings, covariance MLP) decay exponentially to this multiple over
    # the distillation (``FitConfig.lr_constant_final``): lego +0.04 dB on the photos, +0.57 dB against the source's
    # renders (SPEC.md section 4)
    distill_lr_final: float = 0.1
    # [D] how the teacher's targets are made (``distill.TARGET_RULES``): "whole" renders the teacher at the largest
    # whole multiple of the target's size within 100% and box-filters by that factor, "full" box-filters its 100%
    # render by any ratio (fractional ratios blur: lego's teacher at 90% was 1.2 dB further from the photos than its
    # own 90% render); "auto": "whole" for a teacher trained at random resolutions, else "full" (SPEC.md section 4)
    distill_targets: str = "auto"
    images: str | None = None  # a dataset folder: distil against its photos instead of the source's renders

    def __post_init__(self) -> None:
        self.check()

    def check(self) -> "EncodeConfig":
        """Raise ``ProxycodecError`` on an invalid setting (also run when the config is built)."""
        if not (0.0 < self.proxy_ratio <= 1.0):
            raise ProxycodecError(f"proxy ratio must be in (0, 1], got {self.proxy_ratio}")
        if self.cell_size is not None and not (math.isfinite(self.cell_size) and self.cell_size > 0):
            raise ProxycodecError(f"cell size must be positive, got {self.cell_size}")
        for k in ("feature_bits", "offset_bits", "scaling_bits"):
            b = getattr(self, k)
            if not (1 <= b <= 16 or b == FLOAT_BITS):
                raise ProxycodecError(f"{k.replace('_', ' ')} must be 1..16 or 32 (float32), got {b}")
        if self.weights_dtype not in WEIGHT_DTYPES:
            raise ProxycodecError(f"weights dtype must be one of {', '.join(WEIGHT_DTYPES)}, got {self.weights_dtype!r}")
        if self.max_cameras < 0:
            raise ProxycodecError("max cameras must be >= 0")
        check_proxy_selection(self.proxy_selection)
        if self.positions not in POSITION_CODINGS:
            raise ProxycodecError(f"position coding must be one of {', '.join(POSITION_CODINGS)}, got "
                                  f"{self.positions!r}")
        if self.entropy not in ("auto", "model", "zstd"):
            raise ProxycodecError(f"entropy coding must be 'auto', 'model' or 'zstd', got {self.entropy!r}")
        if self.entropy_iters < 0 or not 1 <= self.entropy_hidden <= 1024:
            raise ProxycodecError("entropy iterations must be >= 0 and its hidden width 1..1024")
        if not (1 <= self.zstd_level <= 22):
            raise ProxycodecError(f"zstd level must be 1..22, got {self.zstd_level}")
        if self.predictor_iters < 0:
            raise ProxycodecError("predictor iterations must be >= 0")
        if not (0.0 < self.leaf_sample <= 1.0):
            raise ProxycodecError(f"leaf sample fraction must be in (0, 1], got {self.leaf_sample}")
        if self.distill is not False or self.images is not None:
            check_run_length(self.distill_iters, self.distill_time_budget, None)
        if not (math.isfinite(self.distill_lr_scale) and self.distill_lr_scale >= 0):
            raise ProxycodecError(f"distill learning-rate scale must be >= 0, got {self.distill_lr_scale}")
        if not (math.isfinite(self.distill_lr_final) and 0.0 < self.distill_lr_final <= 1.0):
            raise ProxycodecError(f"distill final learning-rate multiple must be in (0, 1], got "
                                  f"{self.distill_lr_final}")
        if self.distill_views < 1:
            raise ProxycodecError(f"distill views must be >= 1, got {self.distill_views}")
        if not math.isfinite(self.distill_threshold):
            raise ProxycodecError(f"distill threshold must be a finite number of dB, got {self.distill_threshold}")
        if self.choice_views < 1 or not self.choice_resolutions:
            raise ProxycodecError("the encode path's choice needs at least one view and one resolution")
        from .camera import check_xi

        for xi in self.choice_resolutions:
            check_xi(xi)
        if not (0.0 <= self.distill_full_share <= 1.0):
            raise ProxycodecError(f"distill full share must be in [0, 1], got {self.distill_full_share}")
        if self.quant_cells and not (self.lambda_rate > 0 and self.distill is not False):
            raise ProxycodecError("quant cells are learned by distillation's rate term: give lambda_rate > 0 "
                                  "(and do not turn distillation off)")
        if not 0 <= self.quant_cells <= MAX_LEVEL_CELLS:
            raise ProxycodecError(f"quant cells must be in [0, {MAX_LEVEL_CELLS}], got {self.quant_cells}")
        if self.images is not None and self.distill is False:
            raise ProxycodecError("images are for distillation: drop --no-distill")
        from .distill import check_target_rule

        check_target_rule(self.distill_targets)
        return self

    def distilling(self, has_fitted_predictor: bool) -> bool:
        """Whether ``encode`` distils a scene with a stage-2 predictor it uses, or on a forced path (without one and
        ``distill`` None, ``encode`` decides by measurement)."""
        if self.images is not None:
            return True
        return (not has_fitted_predictor) if self.distill is None else self.distill


@dataclass
class EncodeReport:
    path: Path
    file_bytes: int
    anchors: int
    proxies: int
    leaves: int
    cell_size: float
    sections: list[dict]
    source_bytes: int | None  # PLY + weights sidecar of the input (None when unknown)
    seconds: dict[str, float]
    training: TrainResult | None
    model: SceneModel  # exactly what decode(path) returns
    meta: dict[str, Any] = field(repr=False, default_factory=dict)

    @property
    def ratio(self) -> float | None:
        return None if not self.source_bytes else self.source_bytes / self.file_bytes

    def to_json(self) -> dict:
        return {"path": str(self.path), "file_bytes": self.file_bytes, "anchors": self.anchors,
                "proxies": self.proxies, "leaves": self.leaves, "cell_size": self.cell_size,
                "source_bytes": self.source_bytes, "ratio": self.ratio, "seconds": self.seconds,
                "sections": self.sections, "distill": self.meta.get("distill"),
                "encode_choice": self.meta.get("encode_choice"), "convert": self.meta.get("convert"),
                "predictor": None if self.training is None else {
                    "baseline_loss": self.training.baseline_loss, "final_loss": self.training.final_loss,
                    "iters": self.training.iters}}


# ---------------------------------------------------------------------------------------------- helpers
def _source_model(source) -> tuple[SceneModel, int | None, str, tuple]:
    """(model, bytes of PLY + weights on disk or None, description, (fitted predictor, proxy mask) or (None, None))
    of what the user handed ``encode``."""
    if isinstance(source, SceneModel):
        return source, None, "SceneModel", (None, None)
    if isinstance(source, (tuple, list)) and len(source) == 2:
        ply, w = (Path(x) for x in source)
    elif isinstance(source, (str, os.PathLike)):
        if is_scaffold_output(source):  # a trained Scaffold-GS output: PLY + its MLP files (scaffold_gs.py)
            model = load_scaffold_output(source)
            return model, model.meta["scaffold_gs"]["bytes"], str(Path(source)), (None, None)
        from .formats.splats import SPLAT_KINDS, splat_kind

        if splat_kind(source):
            raise ProxycodecError(f"is an {SPLAT_KINDS[splat_kind(source)]}, not an anchor scene: `proxycodec encode` converts it "
                                  "first (or `proxycodec convert`; in Python, proxycodec.convert)", source)
        ply, w = Path(source), weights_path_for(source)
    else:
        raise ProxycodecError(f"encode expects a SceneModel, a PLY path or (PLY, weights) paths, "
                              f"got {type(source).__name__}")
    if ply.is_file() and ply.read_bytes()[:8] == MAGIC:
        raise ProxycodecError("is already a proxycodec container; encode takes an anchor PLY", ply)
    model = SceneModel.load(ply, w)
    try:
        fitted = load_fitted_predictor(w)
    except (KeyError, TypeError, ValueError) as e:
        raise ProxycodecError(f"bad stage-2 predictor in the weights file ({e})", w) from None
    return model, ply.stat().st_size + w.stat().st_size, str(ply), fitted


def _saved_size(model: SceneModel) -> int | None:
    """Bytes of the uncompressed anchor scene (PLY + weights sidecar) as ``SceneModel.save`` writes it."""
    try:
        with tempfile.TemporaryDirectory() as d:
            ply, w = model.save(Path(d) / "scene.ply")
            return ply.stat().st_size + w.stat().st_size
    except (ImportError, ProxycodecError, OSError):
        return None


def _progress_default(msg: str) -> None:
    pass


# ---------------------------------------------------------------------------------------------- encode
def encode(
    source,
    out: str | os.PathLike,
    config: EncodeConfig | None = None,
    *,
    predictor: ResidualPredictor | None = None,
    progress: Progress | None = None,
    extra_meta: dict | None = None,
    device=None,
    **knobs,
) -> EncodeReport:
    """Compress an anchor scene to a container at ``out`` (written atomically).

    ``source``: a ``SceneModel``, the path of an anchor PLY (weights sidecar beside it), or (PLY, weights) paths.
    Knobs: the fields of ``EncodeConfig`` (given as ``config`` or as keyword arguments). ``predictor``: a trained
    ``ResidualPredictor`` (e.g. from stage-2 training) to fine-tune for ``predictor_iters`` (0: keep as is).
    ``extra_meta``: JSON-able entries added to (or replacing) the container's metadata (``convert`` records the
    conversion, and the 3DGS PLY as the source). ``device`` (None: the CPU): where the distillation, the choice's
    renders and the predictor and entropy-model fits compute; positions, quantisation and coding stay on the CPU.
    """
    unknown = set(knobs) - set(EncodeConfig.__dataclass_fields__)
    if unknown:
        raise ProxycodecError(f"unknown encode option(s): {', '.join(sorted(unknown))}")
    cfg = replace(config or EncodeConfig(), **knobs)
    say = progress or _progress_default
    t_start = time.perf_counter()
    # 1. the scene (and the stage-2 predictor + proxy split a ``fit`` output carries)
    model, source_bytes, source_name, fitted = _source_model(source)
    _checked_scene(model, source_name)
    if source_bytes is None:
        source_bytes = _saved_size(model)
    source_info = {"bytes": source_bytes, "name": os.path.basename(source_name)}
    dev = as_device(device)
    on_device = model.to(dev)  # renders and distillation run there; the container is built from host arrays
    has_fitted = fitted[0] is not None and cfg.use_fitted  # a stage-2 predictor, used as fitted
    distilled = choice = built = None
    if predictor is None and cfg.distill is None and cfg.images is None and not has_fitted:
        # 2a. no predictor of its own and no forced path: the fast path first, distillation only if it falls short
        built = _build(model, fitted, cfg, None, source_info, say, device=dev)
        choice = _choose_path(built.decoded.to(dev), on_device, cfg, say)
        if choice["path"] == "distill":
            distilled = _distill(on_device, (None, None), cfg, say)
    else:
        if predictor is None and cfg.distilling(has_fitted):
            distilled = _distill(on_device, fitted if cfg.use_fitted else (None, None), cfg, say)
        choice = {"path": "distill" if distilled is not None else "stage-2 predictor" if has_fitted and
                  predictor is None else "L_recon", "forced": cfg.distill is not None or cfg.images is not None}
    if distilled is not None:
        # 2b. the distilled proxy scene, its predictor and split used as fitted
        built = _build(distilled.model, (distilled.predictor, distilled.proxy_mask), replace(cfg, use_fitted=True),
                       None, source_info, say, distilled=distilled, device=dev)
    elif built is None:
        built = _build(model, fitted, cfg, predictor, source_info, say, device=dev)
    cfg, meta, sections, decoded = built.cfg, built.meta, built.sections, built.decoded
    # the choice as measured, without its seconds: same input, same bytes (the time is in the report's seconds)
    meta["encode_choice"] = _jsonable({k: v for k, v in choice.items() if k != "seconds"})
    if distilled is not None:
        meta["distill"]["held_out"] = _held_out(decoded.to(dev), on_device, distilled, cfg, say)
    for k, v in (extra_meta or {}).items():  # the caller's word wins (convert: the source is the 3DGS PLY)
        meta[k] = _jsonable(v)
    t_entropy = time.perf_counter()
    raw = frozenset({octree.STREAM} & set(sections))  # ANS words: they do not compress
    if _entropy_coded(cfg, meta):
        sections, coded = _entropy_code(sections, meta, built.pos_sorted, built.voxel, built.mask, cfg, say, dev)
        raw |= coded
    t_entropy = time.perf_counter() - t_entropy
    packed, meta["weights_layout"] = pack_weights(sections)
    file_bytes = write_container(out, meta, packed, level=cfg.zstd_level, raw_sections=raw)
    _, _, infos, _ = read_header(out)
    say(f"wrote {out}: {file_bytes:,} B" + (f" ({source_bytes / file_bytes:.1f}x smaller than PLY + weights)"
                                           if source_bytes else ""))
    M, P = len(built.mask), int(built.mask.sum())
    return EncodeReport(
        path=Path(out), file_bytes=file_bytes, anchors=M, proxies=P, leaves=M - P, cell_size=built.cell_size,
        sections=[s.to_json() for s in infos], source_bytes=source_bytes,
        seconds={"total": time.perf_counter() - t_start, "predictor": built.t_train, "entropy": t_entropy,
                 **({} if choice.get("seconds") is None else {"choice": choice["seconds"]}),
                 **({} if distilled is None else {"distill": distilled.seconds})}, training=built.training,
        model=decoded, meta=meta)


@dataclass
class _Built:
    """A scene's container contents before entropy coding (``_build``)."""
    cfg: EncodeConfig  # with the proxy source and offsets mode settled
    meta: dict
    sections: dict
    decoded: SceneModel  # exactly what the decoder makes of ``sections``
    mask: np.ndarray  # proxies, in the stored (Morton) order
    pos_sorted: np.ndarray
    voxel: float
    cell_size: float
    training: TrainResult
    t_train: float


def _build(model: SceneModel, fitted: tuple, cfg: EncodeConfig, predictor: ResidualPredictor | None, source: dict,
           say: Progress, distilled=None, device=None) -> _Built:
    """Positions coded, proxies chosen, attributes quantised, the predictor fitted (L_recon, against the
    dequantised proxies), sections and metadata made, and the scene decoded from them as ``decode`` will."""
    scene = model.scene
    K, Fd, voxel = scene.n_offsets, scene.feat_dim, float(scene.voxel_size)
    pos = scene.positions.detach().cpu().numpy().astype(np.float32)
    coding = encode_positions(pos, voxel, cfg.positions, scene.metadata.get("grid_shift"))
    feats, offs, scal = (getattr(scene, k).detach().float().cpu()[torch.from_numpy(coding.order)].numpy()
                         for k in ("features", "offsets", "scalings"))
    pos_sorted = pos[coding.order]
    # proxies and the predictor to start from (those of stage-2 training, when the scene comes from ``fit``)
    mask, predictor, cfg, cell_size, proxy_source = _choose_proxies(cfg, pos_sorted, voxel, coding.order, fitted,
                                                                    predictor, say)
    if proxy_source == "fit":
        predictor = _rule_reproducing_leaves(predictor, pos_sorted, mask, feats, offs, say)
    # quantise what is stored; fit the predictor against what the decoder will see
    steps = _learned_steps(scene.metadata, cfg, Fd, K)
    q = quantize_anchors(feats, offs, scal, mask, feature_bits=cfg.feature_bits, offset_bits=cfg.offset_bits,
                         scaling_bits=cfg.scaling_bits, predict_offsets=cfg.predict_offsets, steps=steps,
                         positions=pos_sorted, voxel=voxel)
    pred, tcfg, training, t_train = _fit_predictor(cfg, predictor, pos_sorted, mask, q, offs, Fd, K, voxel, say,
                                                   device)
    sections = scene_sections(coding, mask, q, model.decoder.state_arrays(), pred.state_arrays(), cfg.weights_dtype)
    meta = scene_metadata(
        coding, mask, q, feat_dim=Fd, n_offsets=K, voxel_size=voxel, bounds=np.stack([pos.min(0), pos.max(0)]),
        predict_offsets=cfg.predict_offsets, weights_dtype=cfg.weights_dtype, decoder_config=model.decoder.config,
        predictor_config=pred.config, cameras=_spread(model.cameras or [], cfg.max_cameras),
        background=model.background,
        training={**tcfg.to_json(), "baseline_loss": training.baseline_loss, "final_loss": training.final_loss,
                  "loss": "feature L_recon (MSE + 0.1 cos)", "rendering_loss": distilled is not None},
        proxy={"source": proxy_source, "ratio": cfg.proxy_ratio, "cell_size": cell_size,
               "cell_size_voxels": cell_size / voxel, "cell_target": cfg.cell_target, "seed": cfg.seed},
        cameras_in_source=len(model.cameras or []),
        scene=_jsonable({k: v for k, v in scene.metadata.items() if k != "quant_steps"}),  # steps: in "quant"
        source=source,
        encoder={"zstd_level": cfg.zstd_level, "proxycodec": _version()},
        **({} if distilled is None else {"distill": {
            "iterations": distilled.iterations, "images": cfg.images,
            "teacher_views": len(distilled.views.train_indices),
            "full_share": cfg.distill_full_share, "targets": distilled.views.rule if cfg.images is None else None,
            "loss": "fit's rendering loss, random xi"}}))
    # the decoded model, through the decoder's own path (so report.model == decode(out), bit for bit)
    decoded = _model_from_sections(meta, sections, ProxycodecError)
    if cfg.drop_dead_offsets and not cfg.predict_offsets:
        decoded = _drop_dead_offsets(decoded, sections, meta, q, cfg.dead_threshold, say)
    return _Built(cfg, meta, sections, decoded, mask, pos_sorted, voxel, cell_size, training, t_train)


def against_source(decoded: SceneModel, source: SceneModel, cfg: EncodeConfig) -> dict:
    """The measurement behind encode's choice of path: ``decoded`` against ``source`` rendered at the same
    resolution, on ``cfg.choice_views`` views evenly spread over the teacher's (``distill.teacher_cameras``: the
    L_recon fit sees no image, so none was trained on) at ``cfg.choice_resolutions``; per resolution the mean PSNR
    over the views (each capped at ``CHOICE_PSNR_CAP``), and ``measured``, their mean."""
    from .distill import teacher_cameras
    from .metrics import psnr

    t0 = time.perf_counter()
    cams = teacher_cameras(source, cfg.distill_views)
    idx = _spread(list(range(len(cams))), cfg.choice_views)
    rows = []
    with torch.no_grad():
        for xi in cfg.choice_resolutions:
            vals = []
            for i in idx:
                cam = cams[i]
                a = decoded.render(cam, xi).image.clamp(0, 1)
                b = source.render(cam, xi).image.clamp(0, 1)
                vals.append(min(psnr(a, b), CHOICE_PSNR_CAP))
            rows.append({"xi": float(xi), "psnr": float(np.mean(vals))})
    return {"measured": float(np.mean([r["psnr"] for r in rows])), "per_resolution": rows,
            "views": [int(i) for i in idx], "seconds": time.perf_counter() - t0}


def _choose_path(decoded: SceneModel, source: SceneModel, cfg: EncodeConfig, say: Progress) -> dict:
    """Whether a scene without a stage-2 predictor is distilled: its L_recon encode (``decoded``) is measured
    against the source (``against_source``); below ``cfg.distill_threshold`` dB it is."""
    m = against_source(decoded, source, cfg)
    measured, rows = m["measured"], m["per_resolution"]
    path = "L_recon" if measured >= cfg.distill_threshold else "distill"
    per_res = ", ".join(f"{r['xi']:g}: {r['psnr']:.2f}" for r in rows)
    say(f"encode path: {'L_recon predictor kept' if path == 'L_recon' else 'distilling'}: the L_recon predictor "
        f"decodes at {measured:.2f} dB against the source ({per_res} on {len(m['views'])} views), "
        f"{'at or above' if path == 'L_recon' else 'below'} the threshold {cfg.distill_threshold:g} dB "
        f"({'--distill' if path == 'L_recon' else '--no-distill'} forces the other path; {m['seconds']:.1f} s)")
    return {"path": path, "forced": False, "threshold": cfg.distill_threshold, **m}


#: PSNR of identical renders is infinite; the choice's mean caps each view's at this
CHOICE_PSNR_CAP = 100.0


def _learned_steps(scene_meta: dict, cfg: EncodeConfig, Fd: int, K: int) -> dict | None:
    """The quantisation grids rate training learned (``quant_steps`` in the scene's metadata: per attribute
    ``{"step": [C], "origin": [C]}``, plus ``"levels"`` with ``fit --quant-cells``), checked; attributes the encode
    options store as float32 are left out."""
    grids = scene_meta.get("quant_steps") if isinstance(scene_meta, dict) else None
    if not cfg.learned_steps or not isinstance(grids, dict):
        return None
    want = {"features": Fd, "scalings": 6, "offsets": 3 * K}
    knob = {"features": "feature_bits", "scalings": "scaling_bits", "offsets": "offset_bits"}
    out = {}
    for k, n in want.items():
        g = grids.get(k)
        try:
            step, origin = (np.asarray(g[f], dtype=np.float64) for f in ("step", "origin"))
        except (TypeError, KeyError, ValueError):
            raise ProxycodecError(f"the scene's learned quantisation grid for {k} is malformed") from None
        if step.shape != (n,) or origin.shape != (n,) or not np.all(np.isfinite(step) & (step > 0)
                                                                  & np.isfinite(origin)):
            raise ProxycodecError(f"the scene's learned quantisation grid for {k} is malformed")
        if "levels" in g:
            level_table(g["levels"],
                        lambda m, k=k: ProxycodecError(f"the scene's learned quantisation grid for {k}: {m}"))
        if getattr(cfg, knob[k]) != FLOAT_BITS:
            out[k] = (step, origin) + ((g["levels"],) if "levels" in g else ())
    return out


def _entropy_coded(cfg: EncodeConfig, meta: dict) -> bool:
    return cfg.entropy != "zstd" and meta["offsets"] == "stored" and FLOAT_BITS not in (
        cfg.feature_bits, cfg.offset_bits, cfg.scaling_bits)


#: ``entropy="auto"`` does not even fit the model when its nets hold more values than this share of what zstd stores
#: for the same sections: measured savings stay well below it (SPEC.md section 4), so the nets could not pay.
AUTO_MAX_SAVING = 0.25


#: ``entropy="auto"`` does not fit the model when zstd's bytes are below this multiple of the model's starting point
#: (``entropy_fit.start_bytes``: a Laplace per channel, no context). The fit gains 9% on it on the built-in scene
#: (zstd at 0.66x: the model ends 39% above zstd, after ~30 s of fitting); where the model wins, zstd sits near the
#: start (lego's L_recon encode: 1.02x, the model 2.5% below zstd; SPEC.md section 4).
AUTO_MIN_START_RATIO = 0.8


def _net_shapes(F: int, K: int, hidden: int) -> list[tuple[int, int]]:
    from . import entropy  # noqa: PLC0415

    return [(i, o) for n_in, n_out in entropy.net_inputs(F, K).values()
            for i, o in ((n_in, hidden), (hidden, hidden), (hidden, 2 * n_out))]


def _entropy_code(sections: dict, meta: dict, pos_sorted: np.ndarray, voxel: float, mask: np.ndarray,
                  cfg: EncodeConfig, say: Progress, device=None) -> tuple[dict, frozenset]:
    """Scene format 4: the attribute sections replaced by the entropy stream and the integer nets (fitted here to
    the scene's symbols); ``meta`` gains ``entropy``. Lossless: the decoder gets the same symbols back."""
    from . import entropy, entropy_fit  # noqa: PLC0415

    names = (PROXY_FEATURES, SCALINGS, OFFSETS)
    cctx = zstandard.ZstdCompressor(level=cfg.zstd_level)
    zstd_bytes = sum(len(cctx.compress(np.ascontiguousarray(sections[k]).tobytes())) for k in names)
    M, Fd = len(mask), int(meta["anchors"]["feat_dim"])
    K = int(meta["anchors"]["n_offsets"])
    net_values = sum(i * o + o for i, o in _net_shapes(Fd, K, cfg.entropy_hidden))
    if cfg.entropy == "auto" and net_values > AUTO_MAX_SAVING * zstd_bytes:
        say(f"entropy model: its nets ({net_values:,} values) would outweigh what it can save on "
            f"{zstd_bytes:,} B: zstd kept (scene format 2)")
        return sections, frozenset()
    bits = {k: int(meta["quant"][k]["bits"]) for k in entropy.NETS}
    feats = np.zeros((M, Fd), np.int64)
    feats[mask] = entropy.centred(sections[PROXY_FEATURES].T, bits["features"])
    a = entropy.Attributes(feats, entropy.centred(sections[SCALINGS].T, bits["scalings"]),
                           entropy.centred(sections[OFFSETS].T, bits["offsets"]))
    ctx = entropy.Context.of(pos_sorted, voxel, mask)
    start = entropy_fit.start_bytes(ctx, a) if cfg.entropy == "auto" else None
    if start is not None and zstd_bytes < AUTO_MIN_START_RATIO * start:
        say(f"entropy model: zstd's {zstd_bytes:,} B are {zstd_bytes / start:.2f}x the model's starting point "
            f"({start:,.0f} B; below {AUTO_MIN_START_RATIO:g}x its fit cannot catch up): zstd kept (scene format 2)")
        return sections, frozenset()
    nets, _ = entropy_fit.fit_nets(ctx, a, hidden=cfg.entropy_hidden, iters=cfg.entropy_iters, seed=cfg.seed,
                                   progress=say, device=device)
    coded, emeta, sizes = entropy.encode(ctx, nets, a, bits)
    model_bytes = coded[entropy.STREAM].nbytes + sum(len(cctx.compress(v.tobytes())) for k, v in coded.items()
                                                     if k != entropy.STREAM)
    if cfg.entropy == "auto" and model_bytes >= zstd_bytes:
        say(f"entropy model: {model_bytes:,} B against zstd's {zstd_bytes:,} B: zstd kept (scene format 2)")
        return sections, frozenset()
    emeta["bytes"] = {k: round(v, 1) for k, v in sizes.items()}
    emeta["zstd_bytes"] = zstd_bytes  # what zstd alone would store for the same sections
    emeta["hidden"], emeta["iters"] = cfg.entropy_hidden, cfg.entropy_iters
    meta["entropy"] = emeta
    if meta["scene_format"] == SCENE_FORMAT_OCTREE:  # format 6 lists it
        meta["features"] = scene_features(meta)
    elif meta["scene_format"] != SCENE_FORMAT_LEVELS:  # format 5 covers both codings
        meta["scene_format"] = SCENE_FORMAT_ENTROPY
    out = {k: v for k, v in sections.items() if k not in names}
    out.update(coded)
    say("entropy model: " + ", ".join(f"{k} {v:,.0f} B" for k, v in sizes.items())
        + f" (+ nets; {model_bytes:,} B against zstd's {zstd_bytes:,} B)")
    return out, frozenset({entropy.STREAM})


def _distill(model: SceneModel, fitted: tuple, cfg: EncodeConfig, say: Progress):
    """The proxy scene fine-tuned against the source's renders (or ``cfg.images``' photos): ``distill.distill``
    with fit's configuration made from the encode knobs."""
    from .distill import distill
    from .train import FitConfig

    pos = model.scene.positions.detach().cpu().numpy()
    voxel = float(model.scene.voxel_size)
    fcfg = FitConfig(
        iters=cfg.distill_iters, time_budget=cfg.distill_time_budget, seed=cfg.seed, max_width=None,
        proxy_ratio=cfg.proxy_ratio, proxy_selection=cfg.proxy_selection, leaf_sample=cfg.leaf_sample,
        proxy_cell=float(cfg.cell_size) if cfg.cell_size else default_cell_size(pos, voxel, cfg.cell_target),
        predictor_hidden=cfg.predictor_hidden, predictor_blocks=cfg.predictor_blocks,
        predictor_context=cfg.predictor_context, predict_offsets=bool(cfg.predict_offsets),
        lr_warmup=cfg.distill_lr_warmup, lr_constant_final=cfg.distill_lr_final, xi_full_share=cfg.distill_full_share,
        lambda_rate=cfg.lambda_rate, quant_cells=cfg.quant_cells)
    views = None
    if cfg.images is not None:
        from .formats.datasets import load_dataset

        views = load_dataset(cfg.images, max_width=reference_width(model))
        say(f"distilling against the photos of {cfg.images}")
    start = fitted if fitted[0] is not None else None
    return distill(model, fcfg, views=views, start_proxies=start, log=say, min_views=cfg.distill_views,
                   lr_scale=cfg.distill_lr_scale, targets=cfg.distill_targets)


def _held_out(decoded: SceneModel, source: SceneModel, distilled, cfg: EncodeConfig, say: Progress) -> dict:
    """The decoded scene against the source's anti-aliased renders on held-out views, 10%..100%."""
    from .distill import TeacherViews, held_out_report, report_line, target_rule_for

    views = distilled.views
    if not isinstance(views, TeacherViews):  # distilled against photos: the report still compares with the source
        cams = [views.cameras[i] for i in views.test_indices] or list(views.cameras)
        views = TeacherViews(source, cams, held_out=list(range(len(cams))),
                             targets=target_rule_for(source, cfg.distill_targets))
    rep = held_out_report(decoded, views)
    say("decoded vs source renders on held-out views: " + report_line(rep))
    return rep


def _checked_scene(model: SceneModel, source_name: str) -> AnchorScene:
    scene = model.scene.validate(source_name)
    M = scene.num_anchors
    if M == 0:
        raise ProxycodecError("the scene has no anchors; nothing to encode")
    if M > MAX_ANCHORS:
        raise ProxycodecError(f"{M} anchors is more than this format allows ({MAX_ANCHORS})")
    dcfg = model.decoder.config
    if scene.feat_dim != dcfg.feat_dim or scene.n_offsets != dcfg.n_offsets:
        raise ProxycodecError("anchor feature/offset counts do not match the decoder configuration")
    return scene


def _choose_proxies(cfg: EncodeConfig, pos_sorted: np.ndarray, voxel: float, order: np.ndarray, fitted: tuple,
                    predictor: ResidualPredictor | None, say: Progress):
    """-> (proxy mask in the stored order, the predictor to start from or None, the config with the offsets mode
    settled, cell size, where the split comes from). A stage-2 predictor with its proxy mask (from ``fit``) is used
    as is, not refitted: it was trained jointly with the renderer."""
    M = len(pos_sorted)
    fitted_pred, fitted_mask = fitted
    cell_size = float(cfg.cell_size) if cfg.cell_size else default_cell_size(pos_sorted, voxel, cfg.cell_target)
    use_fitted = cfg.use_fitted and predictor is None and fitted_pred is not None and fitted_mask is not None
    if use_fitted:
        if fitted_mask.shape != (M,) or not fitted_mask.any():
            raise ProxycodecError(f"the stage-2 proxy mask has shape {fitted_mask.shape}, expected ({M},)")
        mask = np.asarray(fitted_mask, dtype=bool)[order]
        predictor = fitted_pred
        fitted_po = bool(fitted_pred.config.predict_offsets)
        if cfg.predict_offsets is not None and cfg.predict_offsets != fitted_po:
            raise ProxycodecError("the scene's stage-2 predictor " + ("predicts" if fitted_po else "does not predict")
                                  + " the leaves' offsets; drop the offsets option or refit the predictor")
        cfg = replace(cfg, predictor_iters=0, predict_offsets=fitted_po)
        say("using the stage-2 proxies and predictor from the weights file (no refit)")
    else:
        mask = select_proxies(pos_sorted, cell_size, cfg.proxy_ratio, cfg.seed, cfg.proxy_selection)
    if cfg.predict_offsets is None:
        cfg = replace(cfg, predict_offsets=False)
    P = int(mask.sum())
    say(f"{M} anchors: {P} proxies, {M - P} leaves (cell {cell_size:g} = {cell_size / voxel:g} voxels)")
    return mask, predictor, cfg, cell_size, "fit" if use_fitted else "encode"


#: A stage-2 predictor reproduces its scene's leaves when its predictions from the stored proxies are within this of
#: the leaves' features (the PLY holds them as training rendered them; float32 on another device or thread count
#: differs by ~1e-5).
LEAF_MATCH = 1e-3


def _rule_reproducing_leaves(pred: ResidualPredictor, pos_sorted: np.ndarray, mask: np.ndarray, feats: np.ndarray,
                             offs: np.ndarray, say: Progress) -> ResidualPredictor:
    """The stage-2 predictor under the tie rule (``nearest.TIES``) with which it reproduces the scene's leaves: its
    own when it does (always, for scenes fitted since the "grid" rule), else the first that does. A conversion
    written before that rule trained in its canonical frame and stored world coordinates, where "position" breaks
    the grid's ties otherwise than training did (bonsai: every leaf's neighbours changed, 27.07 -> 23.89 dB
    decoded); "grid" finds training's neighbours again. When no rule reproduces them the predictor is kept and the
    gap reported."""
    leaves = np.flatnonzero(~mask)
    if not len(leaves):
        return pred
    pos_t, f_t, o_t = (torch.from_numpy(np.ascontiguousarray(x)) for x in (pos_sorted, feats, offs))
    lv = torch.from_numpy(leaves)
    errors = {}
    state = pred.state_arrays()  # the check runs on the host, wherever ``pred`` lives
    for rule in dict.fromkeys([pred.config.ties, "grid", "position", "index"]):
        cand = ResidualPredictor.from_arrays(replace(pred.config, ties=rule), state).eval()
        near = torch.from_numpy(predictor_neighbours(pos_sorted, mask, cand.config))
        with torch.no_grad(), torch_threads(1):
            f, _ = cand.predict(pos_t, f_t, near, lv, o_t)
        errors[rule] = float((f - f_t[lv]).abs().max())
        if errors[rule] <= LEAF_MATCH:
            if rule == pred.config.ties:
                return pred
            say(f"the stage-2 predictor's tie rule {pred.config.ties!r} does not reproduce the scene's leaves "
                f"(max feature error {errors[pred.config.ties]:.3g}); {rule!r} does (max {errors[rule]:.2g}): "
                f"encoding with it")
            return cand.to(next(pred.parameters()).device)
    say("warning: the stage-2 predictor reproduces the scene's leaves under no tie rule (max feature error "
        + ", ".join(f"{r} {e:.3g}" for r, e in errors.items()) + "); the container decodes its own predictions")
    return pred


def _fit_predictor(cfg: EncodeConfig, predictor: ResidualPredictor | None, pos_sorted: np.ndarray, mask: np.ndarray,
                   q: QuantizedAnchors, offs: np.ndarray, Fd: int, K: int, voxel: float, say: Progress,
                   device=None):
    """The residual predictor (given, or new) fitted on the leaves against the dequantised proxies (what the
    decoder will see) for ``cfg.predictor_iters``. -> (predictor, its TrainConfig, TrainResult, seconds)."""
    pcfg = PredictorConfig(feat_dim=Fd, n_offsets=K, predict_offsets=cfg.predict_offsets,
                           hidden=cfg.predictor_hidden, n_blocks=cfg.predictor_blocks, dist_ref=voxel,
                           context=cfg.predictor_context)
    if predictor is not None:
        pc = predictor.config
        if (pc.feat_dim, pc.n_offsets, pc.predict_offsets) != (Fd, K, cfg.predict_offsets):
            raise ProxycodecError("the given predictor does not match the scene's feature/offset sizes or the "
                                  "offsets mode (--predict-offsets)")
        pcfg = predictor.config
        pred = ResidualPredictor.from_arrays(pcfg, predictor.state_arrays())
    else:
        torch.manual_seed(cfg.seed)
        pred = ResidualPredictor(pcfg)
    nearest = predictor_neighbours(pos_sorted, mask, pcfg)
    tcfg = TrainConfig(iters=cfg.predictor_iters, lr=cfg.predictor_lr, lr_final=cfg.predictor_lr / 10,
                       sample_frac=cfg.leaf_sample, seed=cfg.seed)

    def on_iter(it, total, loss, elapsed):
        eta = elapsed / it * (total - it)
        say(f"predictor  iter {it:5d}/{total}  L_recon {loss:.5f}  {elapsed:6.1f} s  ETA {eta:5.1f} s")

    t0 = time.perf_counter()
    offsets = q.offsets if not cfg.predict_offsets else np.where(mask[:, None, None], q.offsets, offs)
    dev = as_device(device)
    training = train_predictor(pred, torch.from_numpy(pos_sorted).to(dev), torch.from_numpy(q.features).to(dev), mask,
                               nearest, offsets=torch.from_numpy(offsets).to(dev), config=tcfg, progress=on_iter,
                               progress_every=max(1, min(100, cfg.predictor_iters // 10 or 1)))
    t_train = time.perf_counter() - t0
    say(f"predictor  L_recon over all leaves: proxy copy {training.baseline_loss:.5f} -> {training.final_loss:.5f}")
    return pred, tcfg, training, t_train


def _drop_dead_offsets(decoded: SceneModel, sections: dict, meta: dict, q: QuantizedAnchors, threshold: float,
                       say: Progress) -> SceneModel:
    """Store the offsets of never-drawn neural Gaussians as 0 (``sections`` and ``meta`` updated in place);
    -> the decoded model of the result."""
    dead = ~_live_slots(decoded, threshold)  # [M, K] in stored (Morton) order
    if dead.any():
        sections[OFFSETS] = zero_dead_offsets(sections[OFFSETS], q.quant["offsets"], dead, q.levels.get("offsets"))
        decoded = _model_from_sections(meta, sections, ProxycodecError)
    meta["offsets_dead"] = {"slots": int(dead.sum()), "of": int(dead.size), "threshold": threshold}
    say(f"{int(dead.sum())} of {dead.size} neural Gaussians are never drawn: their offsets are stored as 0")
    return decoded


def _sample_viewpoints(model: SceneModel, n_dirs: int = 128) -> np.ndarray:
    """Camera centres to judge which neural Gaussians can ever be drawn: the model's cameras, plus a Fibonacci
    sphere of ``n_dirs`` directions around the anchors' centre at 0.5, 1 and 2 times the median camera distance."""
    pos = model.scene.positions.detach().double().cpu().numpy()
    center = 0.5 * (pos.min(0) + pos.max(0))
    cams = np.array([c.center for c in (model.cameras or [])], dtype=np.float64).reshape(-1, 3)
    if len(cams):
        r = float(np.median(np.linalg.norm(cams - center, axis=1)))
    else:
        r = 2.0 * float(np.linalg.norm(pos.max(0) - pos.min(0))) + 1e-6
    i = np.arange(n_dirs) + 0.5
    z = 1.0 - 2.0 * i / n_dirs
    phi = math.pi * (1.0 + 5.0 ** 0.5) * i
    d = np.stack([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z], 1)
    sphere = np.concatenate([center + f * r * d for f in (0.5, 1.0, 2.0)])
    return np.concatenate([cams, sphere])


def _live_slots(model: SceneModel, threshold: float) -> np.ndarray:
    """[M, K] bool: neural Gaussians whose opacity exceeds ``threshold`` from some sampled viewpoint and xi."""
    from .decoder import live_slots

    lo, hi = model.decoder.config.film_xi_range
    xis = [1.0] if model.decoder.config.embedding == "none" else list(np.geomspace(lo, hi, 5))
    s = model.scene
    vp = torch.from_numpy(_sample_viewpoints(model)).to(s.positions.dtype)
    return live_slots(model.decoder, s.positions.detach(), s.features.detach(), vp, xis, threshold).numpy()


def _spread(items: list, n: int) -> list:
    """At most ``n`` items, evenly spaced, the first one included (fit stores test cameras first)."""
    if len(items) <= n:
        return list(items)
    return [items[int(i * len(items) / n)] for i in range(n)]


def _version() -> str:
    from . import __version__

    return __version__


def _jsonable(d: Any) -> Any:
    if isinstance(d, dict):
        return {str(k): _jsonable(v) for k, v in d.items()}
    if isinstance(d, (list, tuple)):
        return [_jsonable(v) for v in d]
    if isinstance(d, (np.generic,)):
        return d.item()
    if isinstance(d, float) and not math.isfinite(d):
        return None
    if d is None or isinstance(d, (str, int, float, bool)):
        return d
    return str(d)


# ---------------------------------------------------------------------------------------------- decode
@dataclass
class CompressedScene:
    """A parsed, verified scene container: metadata, sections, and the file's table of contents."""

    path: Path
    meta: dict[str, Any]
    sections: dict[str, np.ndarray]
    infos: tuple[SectionInfo, ...]
    file_bytes: int

    def to_model(self) -> SceneModel:
        return _model_from_sections(self.meta, self.sections, lambda m: ContainerError(m, self.path))

    def predictor(self) -> ResidualPredictor:
        """The stored residual predictor (eval mode): what regenerates the leaves in :meth:`to_model`."""
        err = lambda m: ContainerError(m, self.path)  # noqa: E731
        return guarded(lambda: _predictor_from_sections(
            stored_anchors(self.meta, self.sections, err).predictor_config, self.sections, err), err)


def load(path: str | os.PathLike) -> CompressedScene:
    """Read and verify a scene container without regenerating anything (raises ``ContainerError``)."""
    path = Path(path)
    c = read_scene_container(path)
    return CompressedScene(path, c.meta, dict(c.arrays), c.sections, c.file_size)


def decode(path: str | os.PathLike) -> SceneModel:
    """Decode a container to a renderable ``SceneModel`` (leaf features regenerated by the predictor)."""
    return load(path).to_model()


def _predictor_from_sections(pcfg: PredictorConfig, sections: dict[str, np.ndarray], err) -> ResidualPredictor:
    return ResidualPredictor.from_arrays(pcfg, weights_from_sections("predictor", sections, err)).eval()


def _model_from_sections(meta: dict, sections: dict[str, np.ndarray], err) -> SceneModel:
    return guarded(_model_from_sections_unchecked, err, meta, sections, err)


def _model_from_sections_unchecked(meta: dict, sections: dict[str, np.ndarray], err) -> SceneModel:
    a = stored_anchors(meta, sections, err)  # the stored arrays, dequantised, and the network configurations
    pos, mask, dcfg, pcfg = a.positions, a.proxy_mask, a.decoder_config, a.predictor_config
    decoder = GaussianDecoder.from_arrays(dcfg, weights_from_sections("decoder", sections, err)).eval()
    predictor = _predictor_from_sections(pcfg, sections, err)
    # leaves
    pos_t, feat_t, off_t = torch.from_numpy(pos), torch.from_numpy(a.features), torch.from_numpy(a.offsets)
    leaves = torch.from_numpy(np.flatnonzero(~mask))
    if leaves.numel():
        nearest = torch.from_numpy(predictor_neighbours(pos, mask, pcfg))
        with torch.no_grad(), torch_threads(1):  # fixed thread count: the same bits in encoder and decoder
            for s in range(0, leaves.numel(), PREDICT_CHUNK):
                lv = leaves[s:s + PREDICT_CHUNK]
                f_pred, o_pred = predictor.predict(pos_t, feat_t, nearest, lv, off_t)
                feat_t[lv] = f_pred
                if o_pred is not None:
                    off_t[lv] = o_pred
    if not (torch.isfinite(feat_t).all() and torch.isfinite(off_t).all()):
        raise err("regenerated leaves are not finite")
    cams, bg, scene_meta = scene_extras(meta, mask, err)
    scene = AnchorScene(pos_t, feat_t, off_t, torch.from_numpy(a.scalings), a.voxel_size, scene_meta)
    scene.validate()
    return SceneModel(scene, decoder, cams or None, bg)  # type: ignore[arg-type]


# ---------------------------------------------------------------------------------------------- stats
def stats(path: str | os.PathLike) -> dict:
    """Sizes and counts of a scene container, any proxycodec container, an anchor PLY, a Scaffold-GS output or an
    INRIA 3DGS PLY."""
    path = Path(path)
    scaffold = find_scaffold_files(path)
    if scaffold is not None:  # its PLY, with the MLP files as the weights
        return _ply_stats(scaffold.ply, scaffold.mlp_files(), scaffold.mode)
    try:
        head = path.open("rb").read(len(MAGIC))
    except FileNotFoundError:
        raise ProxycodecError("no such file", path) from None
    except IsADirectoryError:
        raise ProxycodecError("is a directory", path) from None
    if head == MAGIC:
        return _container_stats(path)
    from .formats.splats import splat_kind

    kind = splat_kind(path)
    if kind == "ply":
        return _inria_stats(path)
    if kind:
        return _splat_stats(path, kind)
    return _ply_stats(path)


def _splat_stats(path: Path, kind: str) -> dict:
    """An SPZ or a GLB: Gaussian count, SH degree, what its header says, bytes per Gaussian."""
    from .formats.splats import SPLAT_KINDS, read_splats

    ply, info = read_splats(path)
    size = path.stat().st_size
    n = ply.n_gaussians
    keep = ("version", "antialiased", "fractional_bits", "generator", "kernel", "color_space", "y_up_undone")
    return {"file": str(path), "type": kind, "what": SPLAT_KINDS[kind], "gaussians": n, "sh_degree": ply.sh_degree,
            "file_bytes": size, "bytes_per_gaussian": size / n if n else None,
            "header": {k: info[k] for k in keep if k in info}}


#: INRIA 3DGS PLY properties by what they hold (``stats``)
INRIA_GROUPS = {"positions": ("x", "y", "z"), "normals": ("nx", "ny", "nz"), "sh_dc": ("f_dc_",),
                "sh_rest": ("f_rest_",), "opacity": ("opacity",), "scales": ("scale_",), "rotations": ("rot_",)}


def _inria_stats(path: Path) -> dict:
    """An INRIA 3DGS PLY: Gaussian count, SH degree and the bytes of each attribute group, which add up to the file
    (header + groups + any bytes after the last vertex)."""
    from .formats.inria_ply import read_inria_ply
    from .formats.ply import read_ply_header

    header = read_ply_header(path)
    ply = read_inria_ply(path)  # validates the layout and the values
    size = path.stat().st_size
    N = int(header.count)
    by_group, body = _group_bytes(header, INRIA_GROUPS)
    return {"file": str(path), "type": "inria-3dgs-ply", "gaussians": N, "sh_degree": ply.sh_degree,
            "file_bytes": size, "header_bytes": header.header_size, "bytes_by_group": by_group,
            "trailing_bytes": size - header.header_size - body, "bytes_per_gaussian": body / N if N else None,
            "properties": len(header.names), "format": header.format}


def _group_bytes(header, groups: dict[str, tuple[str, ...]]) -> tuple[dict[str, int], int]:
    """-> (bytes of each group of PLY properties, bytes of all vertices). A group names properties exactly or, ending
    in ``_``, by prefix; properties no group names are counted under ``other``."""
    itemsize = {n: np.dtype(c).itemsize for n, c in header.properties}

    def member(n: str, prefixes) -> bool:
        return any(n == p or (p.endswith("_") and n.startswith(p)) for p in prefixes)

    N = int(header.count)
    by_group = {g: N * sum(sz for n, sz in itemsize.items() if member(n, prefixes)) for g, prefixes in groups.items()}
    by_group["other"] = N * sum(sz for n, sz in itemsize.items() if not any(member(n, ps) for ps in groups.values()))
    return by_group, N * sum(itemsize.values())


def _container_stats(path: Path) -> dict:
    c = read_container(path)  # every section is decompressed and CRC-checked: stats also verifies the file
    version, flags, infos, size = c.version, c.flags, c.sections, c.file_size
    meta = c.meta
    sections = [s.to_json() for s in infos]
    out: dict[str, Any] = {"file": str(path), "type": "container", "kind": meta.get("kind"),
                           "format_version": version, "flags": flags, "file_bytes": size,
                           "header_and_toc_bytes": infos[0].offset if infos else size,
                           "sections": sections}
    if meta.get("kind") == SCENE_KIND:
        try:
            out.update(_scene_stats(meta, infos, size))
        except (AttributeError, TypeError, ValueError, OverflowError) as e:
            raise ContainerError(f"malformed scene metadata ({type(e).__name__}: {e})", path) from None
    out["metadata"] = meta
    return out


def _scene_stats(meta: dict, infos, size: int) -> dict:
    """Derived figures of a scene container; raises on metadata of the wrong type (caller turns it into ours)."""
    a = meta.get("anchors", {})
    M = int(a.get("count", 0) or 0)
    src = (meta.get("source") or {}).get("bytes")
    groups: dict[str, int] = {}
    for s in infos:
        g = s.name.split("/")[0] if "/" in s.name else s.name
        groups[g] = groups.get(g, 0) + s.stored_size
    if src is not None and not (isinstance(src, (int, float)) and src >= 0):
        raise ValueError("source.bytes must be a non-negative number")
    return {
        "scene_format": meta.get("scene_format"), "anchors": M, "proxies": a.get("proxies"),
        "leaves": a.get("leaves"), "bits_per_anchor": 8.0 * size / M if M else None,
        "source_bytes": src, "ratio": (src / size) if src else None, "bytes_by_group": groups,
        "positions": " ".join(str(meta.get("positions", {}).get(k)) for k in ("mode", "coding")
                              if meta.get("positions", {}).get(k) is not None),
        "offsets": meta.get("offsets"),
        "proxy": meta.get("proxy"), "quant_bits": {k: v.get("bits") for k, v in meta.get("quant", {}).items()},
        "quant_levels": {k: {"cells": v["levels"].get("cells"), "entries": v["levels"].get("entries")}
                         for k, v in meta.get("quant", {}).items()
                         if isinstance(v, dict) and isinstance(v.get("levels"), dict)},
        "weights_dtype": meta.get("weights_dtype"), "distill": meta.get("distill"),
    }


def _ply_stats(path: Path, scaffold_mlps: list[Path] | None = None, scaffold_mode: str | None = None) -> dict:
    from .formats.ply import read_ply_header

    header = read_ply_header(path)
    names = list(header.names)
    size = path.stat().st_size
    w = weights_path_for(path)
    wbytes = w.stat().st_size if w.exists() else None
    if scaffold_mlps is not None:  # a Scaffold-GS output: its MLP files are the weights
        w, wbytes = path.parent, sum(p.stat().st_size for p in scaffold_mlps)
    M = int(header.count)
    groups = {"positions": ("x", "y", "z"), "offsets": ("f_offset_",), "features": ("f_anchor_feat_",),
              "scalings": ("scale_",), "unused": ("nx", "ny", "nz", "opacity", "rot_")}
    by_group, body = _group_bytes(header, groups)
    total = size + (wbytes or 0)
    out = {"file": str(path), "type": "ply", "anchors": M, "file_bytes": size, "weights_file": str(w),
           "weights_bytes": wbytes, "total_bytes": total, "bits_per_anchor": 8.0 * total / M if M else None,
           "raw_bytes_by_group": by_group, "properties": len(names), "header_bytes": header.header_size,
           "trailing_bytes": size - header.header_size - body}
    if scaffold_mlps is not None:
        out["scaffold_gs"] = {"mode": scaffold_mode, "mlp_files": [p.name for p in scaffold_mlps]}
    return out


# ---------------------------------------------------------------------------------------------- rendering
def default_cameras(model: SceneModel, n: int = 8, width: int = 256, height: int = 192) -> list[Camera]:
    """The model's own cameras, else an orbit around the anchors' bounds (``camera.default_cameras``)."""
    if model.cameras:
        return list(model.cameras)
    return camera_defaults(None, model.scene.bounds(), n, width, height)


def as_model(source) -> SceneModel:
    if isinstance(source, SceneModel):
        return source
    p = Path(source)
    try:
        is_container = p.is_file() and p.open("rb").read(len(MAGIC)) == MAGIC
    except FileNotFoundError:
        raise ProxycodecError("no such file", p) from None
    if not p.exists():
        raise ProxycodecError("no such file", p)
    if is_container:
        return decode(p)
    from .scaffold_gs import is_scaffold_output, load_scaffold_output

    return load_scaffold_output(p) if is_scaffold_output(p) else SceneModel.load(p)


def render(source, xi: float = 1.0, cameras: list[Camera] | None = None, *,
           backend: str = "auto") -> list[SceneRender]:
    """Render a container, an anchor PLY or a ``SceneModel`` at ratio ``xi`` for ``cameras`` (default: stored)."""
    model = as_model(source)
    return [model.render(c, xi, backend=backend) for c in (cameras or default_cameras(model))]
