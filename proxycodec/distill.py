"""The image-free encoder: fine-tune the proxy scene against its source scene's own renders.

The teacher is the source scene itself (a ``fit`` output, an imported scene, a converted 3DGS PLY). It is rendered
from its cameras (the stored ones; automatic views around the anchors when there are few or none) and anti-aliased
to each training resolution: ``TeacherViews`` is a dataset whose images are the teacher's renders. A teacher trained
at random resolutions renders at the largest whole multiple of the target's size within 100% and is box-filtered by
that whole factor (at 50%..100%: its own render at that size); any other teacher renders at 100% and is box-filtered
down by any ratio, as ``fit`` anti-aliases its photos (``TARGET_RULES``; SPEC.md section 4 has the measurement). The
student is the proxy scene: ``fit``'s own trainer
(``train.Trainer``) starts from the source's anchors and decoder, enters stage 2 at once (proxies selected, the
residual predictor warmed up on ``L_recon``, or the scene's fitted predictor and split), and trains the predictor,
the proxies' features, offsets, scalings and the decoder MLPs (FiLM and gate included) with ``fit``'s rendering loss
at random resolutions in [0.1, 1]. The anchor set never changes. Held-out views measure the result.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace

import numpy as np
import torch

from .camera import Camera
from .devices import CPU
from .errors import ProxycodecError
from .loop import ProgressFn, TargetImages, fmt_time, resize_torch, run_until_done
from .metrics import psnr, ssim
from .model import SceneModel
from .train import FitConfig, Trainer

__all__ = ["REPORT_RESOLUTIONS", "TARGET_RULES", "DistillResult", "TeacherViews", "distill", "held_out_report",
           "report_line", "resolution_aware", "target_rule_for", "teacher_cameras"]

#: the resolutions the held-out report measures (10%..100%, as the paper's tables)
REPORT_RESOLUTIONS = tuple(round(0.1 * k, 1) for k in range(1, 11))


# ================================================================================================ the teacher
def teacher_cameras(model: SceneModel, min_views: int, width: int = 256, height: int = 256) -> list[Camera]:
    """The model's cameras, plus automatic views when it has fewer than ``min_views``: cameras on the vertices of
    an icosphere (``trimesh.creation.icosphere``) around the anchors' centre, looking at it, at the stored cameras'
    median distance with the first stored camera's size and field of view (else 2.2x the bounds' half-diagonal,
    50 degrees, ``width`` x ``height``). With stored cameras, only directions within ~100 degrees of their mean
    direction are added (a captured object is seen from its capture side; views from below a floor teach nothing).
    """
    import trimesh

    cams = list(model.cameras or [])
    if len(cams) >= min_views:
        return cams
    b = model.scene.bounds()
    center = 0.5 * (b[0] + b[1])
    fov = 50.0
    if cams:
        centers = np.array([c.center for c in cams])
        dist = float(np.median(np.linalg.norm(centers - center, axis=1)))
        mean_dir = (centers - center).mean(0)
        mean_dir = mean_dir / max(np.linalg.norm(mean_dir), 1e-12)
        ref = cams[0]
        width, height = ref.width, ref.height
        fov = float(np.degrees(2 * np.arctan(0.5 * ref.width / ref.fx)))
        up = -np.asarray(ref.rotation)[1]  # the image's up direction in the world (OpenCV: y points down)
    else:
        dist = 2.2 * max(float(np.linalg.norm(b[1] - b[0])) / 2.0, 1e-3)
        mean_dir, up = None, np.array([0.0, 0.0, 1.0])
    sphere = trimesh.creation.icosphere(subdivisions=2)  # 162 directions, evenly spread
    dirs = np.asarray(sphere.vertices, dtype=np.float64)
    if mean_dir is not None and np.linalg.norm(mean_dir) > 0:
        dirs = dirs[dirs @ mean_dir > -0.2]
    need = min_views - len(cams)
    if need <= 0 or len(dirs) == 0:
        return cams
    pick = dirs[np.round(np.linspace(0, len(dirs) - 1, min(need, len(dirs)))).astype(int)]
    auto = [Camera.look_at(center + dist * d, center, up, fov_x_deg=fov, width=width, height=height,
                           name=f"auto_{i}") for i, d in enumerate(pick)]
    return cams + auto


#: How a teacher's target at a training resolution is made (``TeacherViews``; ``encode --distill-targets``):
#: "whole": rendered at the largest whole multiple k of the target's size that fits in 100% and box-filtered by k
#: (k = 1: the teacher's own render at that size); "full": the 100% render box-filtered down (any ratio).
TARGET_RULES = ("whole", "full")


def check_target_rule(rule: str, auto: bool = True) -> None:
    """A rule of ``TARGET_RULES``, or (with ``auto``) "auto"; else a one-line user error."""
    allowed = (("auto",) if auto else ()) + TARGET_RULES
    if rule not in allowed:
        raise ProxycodecError(f"unknown distillation target rule {rule!r}; choose from {', '.join(allowed)}")


def resolution_aware(model) -> bool:
    """Whether ``model`` was trained to render every resolution itself: a ``fit`` output (or a conversion) trained
    at random resolutions. An imported Scaffold-GS output or a 3DGS PLY was trained at one size only: below it its
    own render aliases, so its targets are its 100% render box-filtered down."""
    cfg = ((getattr(model, "meta", None) or {}).get("fit") or {}).get("config") or {}
    return bool(cfg) and not cfg.get("fixed_res", False) and cfg.get("xi_min", 0.1) < cfg.get("xi_max", 1.0)


def target_rule_for(model, rule: str = "auto") -> str:
    """``rule`` with "auto" resolved: "whole" for a resolution-aware teacher (``resolution_aware``), else "full"."""
    check_target_rule(rule)
    if rule != "auto":
        return rule
    return "whole" if resolution_aware(model) else "full"


class TeacherViews:
    """A dataset (the ``PosedImages`` interface the trainer reads) whose images are a teacher scene's renders,
    anti-aliased to ``camera.scaled(xi)`` by ``targets`` (``TARGET_RULES``): the 100% render area-averaged down like
    any photo ("full"), or the render at the largest whole multiple of the size within 100% box-filtered by that
    whole factor ("whole"). ``held_out`` cameras (default: the test cameras a ``fit`` recorded, ``camera_split``,
    when the teacher has them and they are its first cameras; else every ``holdout_every``-th camera) are never
    trained on: they are the report's."""

    def __init__(self, teacher: SceneModel, cameras: list[Camera], holdout_every: int = 8, backend: str = "auto",
                 held_out: list[int] | None = None, targets: str = "full"):
        if not cameras:
            raise ProxycodecError("the scene has no cameras to distil from")
        check_target_rule(targets, auto=False)
        self.teacher = teacher
        self.cameras = list(cameras)
        self.backend = backend
        self.rule = targets
        n = len(self.cameras)
        split = (teacher.meta.get("fit") or {}).get("camera_split") or {}
        fitted_test = [int(i) for i in split.get("test", []) if isinstance(i, int) and 0 <= i < n]
        if held_out is not None:
            held = {int(i) for i in held_out if 0 <= int(i) < n}
        elif fitted_test and len(fitted_test) < n and teacher.cameras and \
                self.cameras[:len(teacher.cameras)] == list(teacher.cameras):
            held = set(fitted_test)
        else:
            held = set(range(0, n, holdout_every)) if n >= 2 * holdout_every else {0} if n > 1 else set()
        self.test_indices = sorted(held)
        self.train_indices = [i for i in range(n) if i not in held]
        self.background = tuple(float(v) for v in teacher.background)
        self.bounds = teacher.scene.bounds()
        self.device = teacher.device  # targets are made where the teacher renders
        self.points = self.point_colors = None
        self._full: dict[int, np.ndarray] = {}

    def image_size(self, i: int, xi: float = 1.0) -> tuple[int, int]:
        cam = self.cameras[i].scaled(xi)
        return cam.width, cam.height

    def source_size(self, i: int, width: int, height: int) -> tuple[int, int]:
        """The size the teacher renders at for a ``width x height`` target: its 100% size ("full"), or the largest
        whole multiple k of the target's size within it ("whole"; k = 1: the target's own size)."""
        cam = self.cameras[i]
        if self.rule == "full":
            return cam.width, cam.height
        k = max(1, min(cam.width // width, cam.height // height))
        return k * width, k * height

    def render(self, i: int, size: tuple[int, int]) -> np.ndarray:
        """The teacher's render of view ``i`` at ``size`` (float32 [h, w, 3], clamped to [0, 1] as a photo, and every
        render we report, is: a 3DGS teacher's SH colours can exceed 1)."""
        return self.render_tensor(i, size).cpu().numpy().astype(np.float32)

    def render_tensor(self, i: int, size: tuple[int, int]) -> torch.Tensor:
        """``render`` as a tensor where the teacher renders."""
        cam = self.cameras[i]
        img = self.teacher.render(cam, size[0] / cam.width, backend=self.backend, size=size).image
        return img.clamp(0.0, 1.0)

    def load_image(self, i: int, xi: float = 1.0) -> torch.Tensor:
        """The teacher's target for view ``i`` at ``xi`` (float32 [h, w, 3]): its render at ``source_size``,
        area-averaged to the size of ``camera.scaled(xi)``."""
        return self.target(i, xi, self._full_render)

    def target(self, i: int, xi: float, full) -> torch.Tensor:
        """``load_image`` with the 100% render taken from ``full(i)`` (float32 [H, W, 3]) where the rule uses it;
        other sizes are rendered here."""
        from .formats.images import resize_image

        w, h = self.image_size(i, xi)
        size = self.source_size(i, w, h)
        cam = self.cameras[i]
        if self.device.type != CPU:  # on the device: rendered, cached and resized there (``loop.resize_torch``)
            src = full(i) if size == (cam.width, cam.height) else self.render_tensor(i, size)
            return resize_torch(torch.as_tensor(src, device=self.device).float(), w, h)
        src = full(i) if size == (cam.width, cam.height) else self.render(i, size)
        return torch.from_numpy(resize_image(src, w, h) if (w, h) != src.shape[1::-1] else src.copy())

    def _full_render(self, i: int) -> np.ndarray | torch.Tensor:
        """View ``i``'s 100% render: numpy on the CPU, a tensor where a device teacher renders."""
        src = self._full.get(i)
        if src is None:
            cam = self.cameras[i]
            size = (cam.width, cam.height)
            src = self.render(i, size) if self.device.type == CPU else self.render_tensor(i, size)
            if i in self.test_indices:  # the report reads them at every resolution; training views are cached
                self._full[i] = src      # by the trainer's targets (``targets``), not twice
        return src

    def targets(self, max_bytes: int):
        """The trainer's targets (``get(view, xi)``): the 100% renders kept in ``loop.TargetImages``' bounded cache
        (float16) and area-averaged from there; sizes the rule renders at another size are rendered on demand."""
        return _TeacherTargets(self, TargetImages(self, max_bytes, self.device))


class _TeacherTargets:
    def __init__(self, views: TeacherViews, full: TargetImages):
        self.views, self.full = views, full

    def get(self, i: int, xi: float) -> torch.Tensor:
        return self.views.target(i, xi, lambda j: _as_float32(self.full.reference(j)))


def _as_float32(a):
    return a.float() if isinstance(a, torch.Tensor) else a.astype(np.float32)


# ================================================================================================ the run
@dataclass
class DistillResult:
    model: SceneModel  # the student: leaves' features (and offsets) as its predictor regenerates them
    predictor: object  # the residual predictor
    proxy_mask: np.ndarray  # [M] bool, in the source's anchor order
    iterations: int
    seconds: float
    views: TeacherViews
    history: list[dict]


def distill(source: SceneModel, config: FitConfig, *, views: TeacherViews | None = None, start_proxies=None,
            log: ProgressFn | None = None, min_views: int = 32, lr_scale: float = 1.0,
            targets: str = "auto") -> DistillResult:
    """Fine-tune the proxy scene of ``source`` against ``views`` (default: ``TeacherViews`` of ``source`` itself).

    ``config``: ``fit``'s configuration; stage 2 starts at once and the anchor set is frozen (``stage2_start`` and
    ``update_until`` are set to 0 here). ``start_proxies``: (predictor, proxy mask) to start from (a fitted scene's).
    ``lr_scale`` multiplies the learning rates of the anchors and the decoder (not the predictor's): a converged
    scene is fine-tuned, and Adam's first steps move every parameter by about its learning rate. ``targets``: how
    the default views make their targets (``TARGET_RULES``, or "auto": ``target_rule_for``). It runs where
    ``source`` lies (``SceneModel.to``); the result is left there.
    """
    log = log or (lambda s: None)
    cfg = replace(config, proxies=True, stage2_start=0.0, update_until=0.0, checkpoint_every=0.0)
    cfg = cfg.with_lr_scale(lr_scale)
    if start_proxies is not None:
        pc = start_proxies[0].config
        cfg = replace(cfg, predictor="residual", predictor_hidden=pc.hidden, predictor_blocks=pc.n_blocks,
                      predictor_context=pc.context, predict_offsets=pc.predict_offsets)
    views = views or TeacherViews(source, teacher_cameras(source, min_views), backend=cfg.backend,
                                  targets=target_rule_for(source, targets))
    t0 = time.perf_counter()
    tr = Trainer(views, cfg, "distill", log, start=source, start_proxies=start_proxies, device=source.device)
    log(f"distill: {len(views.train_indices)} teacher views ({len(views.test_indices)} held out), "
        f"{tr.anchors.num_anchors} anchors; iters {cfg.iters}, time budget {cfg.time_budget}")
    run_until_done(tr, log, lambda st: f"xi {st['xi']:.2f}  gauss {st['gaussians']:7d}",
                   lambda: {"anchors": tr.anchors.num_anchors})
    res = tr.result()
    res.model.cameras = list(source.cameras) if source.cameras else None
    log(f"distill: {tr.iteration} iterations in {fmt_time(tr.elapsed)} "
        f"({time.perf_counter() - t0:.1f} s with the teacher's renders)")
    return DistillResult(res.model, tr.predictor.eval(), tr.proxy_mask.cpu().numpy().copy(), tr.iteration, tr.elapsed,
                         views, tr.history)


@torch.no_grad()
def held_out_report(model: SceneModel, views: TeacherViews, resolutions=REPORT_RESOLUTIONS, *, max_views: int = 8,
                    backend: str = "auto") -> dict:
    """PSNR / SSIM of ``model`` against the teacher's anti-aliased renders (``views.load_image``: the
    distillation's targets) on (up to ``max_views``) held-out views at each resolution, and PSNR against the teacher
    rendered at the same resolution (``psnr_same_xi``: the scene's own render at that size, which the teacher itself
    matches exactly); means per resolution and over all. Below 100% the two differ: the source matches its own
    anti-aliased renders only to ~30-37 dB on lego (SPEC section 4), which caps the first figure, not the second."""
    idx = views.test_indices[:max_views] or views.train_indices[:max_views]
    rows = []
    for xi in resolutions:
        p, s, q = [], [], []
        for i in idx:
            gt = views.load_image(i, xi).cpu().numpy()
            img = model.render(views.cameras[i], xi, backend=backend).image.clamp(0, 1).cpu().numpy()
            same = views.teacher.render(views.cameras[i], xi, backend=backend).image.clamp(0, 1).cpu().numpy()
            p.append(psnr(img, gt))
            s.append(ssim(img, gt))
            q.append(psnr(img, same))
        rows.append({"xi": float(xi), "psnr": _finite_mean(p), "ssim": _mean(s), "psnr_same_xi": _finite_mean(q)})
    # PSNR is undefined (infinite) where the images are identical (the teacher against itself at 100%): None there,
    # and the mean is over the other resolutions
    return {"views": [int(i) for i in idx], "held_out": bool(views.test_indices), "per_resolution": rows,
            "psnr": _mean([r["psnr"] for r in rows]), "ssim": _mean([r["ssim"] for r in rows]),
            "psnr_same_xi": _mean([r["psnr_same_xi"] for r in rows])}


def report_line(rep: dict) -> str:
    """A held-out report on one line: PSNR per resolution (``ref`` where undefined: the teacher against itself) and
    the mean, as the encode log, ``convert`` and ``stats`` print it; then the same-resolution mean where reported."""
    rows = rep.get("per_resolution") or []
    mean = rep.get("psnr")
    same = rep.get("psnr_same_xi")
    return "  ".join(f"{r['xi']:.1f}: " + ("ref" if r.get("psnr") is None else f"{r['psnr']:.2f}") for r in rows) + \
        f"  (mean {float('nan') if mean is None else mean:.2f} dB" + \
        ("" if same is None else f"; vs its renders at the same resolution {same:.2f} dB") + ")"


def _finite_mean(values) -> float | None:
    m = float(np.mean(values))
    return m if math.isfinite(m) else None


def _mean(values) -> float | None:
    """Mean of the defined values (SSIM is undefined below 3 x 3 pixels), None when there are none."""
    v = [x for x in values if x is not None]
    return float(np.mean(v)) if v else None
