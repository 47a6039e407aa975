"""The training loop every scene trainer shares: the anchor fit (``train.Trainer``), the explicit 3DGS baseline
(``explicit.ExplicitTrainer``) and what builds on them.

One iteration is always the same sequence (``TrainingRun.optimise``)::

    sample view and resolution -> render -> loss -> backward -> gradient statistics -> optimiser step -> strategy

A trainer subclasses ``TrainingRun``; it renders, computes its loss, and supplies two hooks: ``observe`` (the
gradient statistics a densification strategy keeps, read after ``backward``) and ``after_step`` (growing,
pruning, densifying). Also here: what both trainers draw their run from (run length, initial points, targets).
"""

from __future__ import annotations

import contextlib
import math
import os
import time
from collections import OrderedDict
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import numpy as np
import torch

from .devices import CPU, as_device, upload
from .errors import ProxycodecError
from .fileio import checkpoint_path_for
from .formats.container import write_container
from .metrics import dssim
from .processes import signals_ignored

__all__ = [
    "ProgressFn", "TargetImages", "TrainingRun", "check_run_length", "checkpoint_path_for", "fmt_time",
    "initial_points", "knn_scale", "ndc_grad_norm", "photometric_loss", "run_checkpointed", "run_until_done",
]

ProgressFn = Callable[[str], None]
T = TypeVar("T")


# ================================================================================================ what a run is given
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


def knn_scale(points: np.ndarray) -> np.ndarray:
    """[N] sqrt of the mean squared distance to the 3 nearest neighbours (3DGS's distCUDA2), floored."""
    from scipy.spatial import cKDTree

    n = len(points)
    if n < 2:
        return np.full(n, 0.01)
    k = min(4, n)
    d, _ = cKDTree(points).query(points, k=k)
    d2 = (d[:, 1:] ** 2).mean(1)
    return np.sqrt(np.maximum(d2, 1e-7))


def has_sfm_points(data) -> bool:
    """Whether ``initial_points`` starts from the dataset's SfM points (at least 8) rather than random ones."""
    return data.points is not None and len(data.points) >= 8


def initial_points(data, n_random: int, rng: np.random.Generator, what: str
                   ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray, float]:
    """-> (points [N, 3] float64, their SfM colours [N, 3] 0..255 or None, bounds [2, 3], extent): the dataset's SfM
    points within half an extent of its bounds, or (Blender, no SfM points) ``n_random`` uniform points in the
    bounds, 3DGS/Scaffold-GS's random init for NeRF-Synthetic."""
    bounds = np.asarray(data.bounds, dtype=np.float64)
    extent = float((bounds[1] - bounds[0]).max())
    if extent <= 0 or not math.isfinite(extent):
        raise ProxycodecError(f"dataset bounds are empty; cannot place initial {what}")
    if has_sfm_points(data):
        pts = np.asarray(data.points, dtype=np.float64)
        inside = ((pts >= bounds[0] - 0.5 * extent) & (pts <= bounds[1] + 0.5 * extent)).all(1)
        colors = None if data.point_colors is None else np.asarray(data.point_colors, dtype=np.float64)[inside]
        return pts[inside], colors, bounds, extent
    return bounds[0] + rng.random((n_random, 3)) * (bounds[1] - bounds[0]), None, bounds, extent


class TargetImages:
    """Training targets at any xi: the dataset's 100% image (kept in a byte-bounded float16 LRU cache) area-resized
    with the dataset's own filter (``formats.images.resize_image``: PIL BOX, the exact area average).

    ``PosedImages.load_image(i, xi)`` decodes the file on every new size; with a random xi per iteration that is
    ~0.1 s per iteration on lego, the cost of a whole rendering step at low resolution. The 100% image is the
    dataset's anti-aliased reference, so a target is the area average of the reference (within float16 rounding,
    < 5e-4) rather than of the file's pixels directly; evaluation always uses ``load_image``.

    On a CUDA ``device`` the reference is uploaded once (the cache holds device tensors) and resized there by the
    same filter's weights (``resize_torch``), so an iteration moves no image between host and device.

    Any object with ``get(view, xi) -> [h, w, 3] tensor`` can stand in for it (e.g. a teacher scene's renders).
    """

    def __init__(self, data, max_bytes: int, device: torch.device | str | None = None):
        self.data = data
        self.max_bytes = int(max_bytes)
        self.device = as_device(device)
        self.items: OrderedDict[int, np.ndarray | torch.Tensor] = OrderedDict()
        self.nbytes = 0

    def reference(self, i: int) -> np.ndarray | torch.Tensor:
        a = self.items.get(i)
        if a is not None:
            self.items.move_to_end(i)
            return a
        img = self.data.load_image(i, 1.0)  # a photo (host), or a teacher's render (where the teacher renders)
        if self.device.type != CPU:
            a = torch.as_tensor(img).to(device=self.device, dtype=torch.float16)
        else:
            a = img.numpy().astype(np.float16)
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
        if isinstance(ref, torch.Tensor):
            return resize_torch(ref.float(), w, h)
        return torch.from_numpy(resize_image(ref.astype(np.float32), w, h))


def _pil_filter(kind: str):
    if kind == "box":
        return 0.5, lambda x: np.where((x > -0.5) & (x <= 0.5), 1.0, 0.0)
    a = -0.5  # PIL's bicubic

    def cubic(x):
        x = np.abs(x)
        return np.where(x < 1.0, ((a + 2.0) * x - (a + 3.0)) * x * x + 1.0,
                        np.where(x < 2.0, (((x - 5.0) * x + 8.0) * x - 4.0) * a, 0.0))

    return 2.0, cubic


def resize_weights(n_in: int, n_out: int) -> np.ndarray:
    """[n_out, n_in] float64: the 1D weights PIL's resampler uses to resize ``n_in`` pixels to ``n_out`` (BOX when
    shrinking, BICUBIC when enlarging, as ``resize_image``; Pillow's ``precompute_coeffs``), so an image resizes
    as ``Wy @ image @ Wx^T``."""
    support, f = _pil_filter("box" if n_out <= n_in else "bicubic")
    scale = n_in / n_out
    fscale = max(scale, 1.0)
    support *= fscale
    W = np.zeros((n_out, n_in))
    for j in range(n_out):
        center = (j + 0.5) * scale
        lo = max(int(center - support + 0.5), 0)
        hi = min(int(center + support + 0.5), n_in)
        k = f((np.arange(lo, hi) - center + 0.5) / fscale)
        if k.sum() != 0:
            k = k / k.sum()
        W[j, lo:hi] = k
    return W


def resize_torch(rgb: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """``formats.images.resize_image`` on a torch tensor [H, W, C] where it lies (float32 rounding apart): the
    same filter weights applied as two matrix products."""
    h0, w0 = rgb.shape[:2]
    if (w0, h0) == (width, height):
        return rgb.float().contiguous()
    wy = upload(resize_weights(h0, height), rgb.device, torch.float32)
    wx = upload(resize_weights(w0, width), rgb.device, torch.float32)
    out = torch.einsum("yh,hwc,xw->yxc", wy, rgb.float(), wx)
    return out if (width <= w0 and height <= h0) else out.clamp(0.0, 1.0)


# ================================================================================================ one iteration
def photometric_loss(img: torch.Tensor, gt: torch.Tensor, lambda_dssim: float) -> torch.Tensor:
    """3DGS's rendering loss: (1 - lambda) L1 + lambda D-SSIM."""
    return (1 - lambda_dssim) * (img - gt).abs().mean() + lambda_dssim * dssim(img, gt)


@torch.no_grad()
def ndc_grad_norm(grad: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """[N] float64 |d loss / d mean2D| in 3DGS's NDC-like units (d/d(ndc) = d/d(pixel) * size / 2), which its
    densification thresholds (0.0002) are stated in."""
    return (grad.double() * upload([0.5 * width, 0.5 * height], grad.device, torch.float64)).norm(dim=1)


class TrainingRun:
    """Where a run stands (``cfg.iters`` and/or ``cfg.time_budget`` against ``iteration`` and ``elapsed``) and the
    one step sequence of every trainer.

    A subclass sets ``data``, ``cfg`` (with ``iters``, ``time_budget``, ``backend``), ``device``, ``rng``,
    ``opt`` (an ``optim.Adam``) and ``images`` (targets), calls ``_start_run()``, and implements
    ``train_step`` with ``sample_view`` and ``optimise``, plus the hooks ``observe`` and ``after_step``.
    """

    def _start_run(self) -> None:
        """The run state every trainer keeps (and checkpoints, where it does)."""
        self.iteration = 0
        self.elapsed = 0.0
        self.view_stack: list[int] = []
        self.history: list[dict] = []
        self.ema_loss: float | None = None
        self.ema_psnr: float | None = None

    def run_state(self) -> tuple[dict, dict]:
        """(meta, arrays) of the run state ``_start_run`` creates, for a checkpoint (``load_run_state`` reads it)."""
        meta = {"iteration": self.iteration, "elapsed": self.elapsed, "rng": self.rng.bit_generator.state,
                "ema_loss": None if self.ema_loss is None else float(self.ema_loss),
                "ema_psnr": None if self.ema_psnr is None else float(self.ema_psnr), "history": self.history[-200:]}
        return meta, {"view_stack": np.asarray(self.view_stack, dtype=np.int64)}

    def checkpoint_arrays(self) -> tuple[dict, dict]:
        """(meta, arrays) of everything a resumed run needs (each trainer's own, ``run_state`` included)."""
        raise NotImplementedError

    def save_checkpoint(self, path: str | os.PathLike) -> None:
        """``checkpoint_arrays`` as our own container at ``path`` (atomic)."""
        meta, arrays = self.checkpoint_arrays()
        write_container(path, meta, arrays, level=3)

    def load_run_state(self, meta: dict, arrays) -> None:
        """Continue the run where ``run_state`` left it: iteration, time, random stream, view order, running means."""
        self.view_stack = [int(x) for x in arrays["view_stack"]]
        self.iteration = int(meta["iteration"])
        self.elapsed = float(meta["elapsed"])
        self.rng = np.random.default_rng()
        self.rng.bit_generator.state = meta["rng"]
        self.ema_loss, self.ema_psnr = meta.get("ema_loss"), meta.get("ema_psnr")
        self.history = list(meta.get("history", []))

    # ------------------------------------------------------------------ where the run stands
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

    # ------------------------------------------------------------------ the step sequence
    def next_view(self) -> int:
        """Training views in random order, each once per epoch (``self.rng``)."""
        if not self.view_stack:
            self.view_stack = [int(i) for i in self.rng.permutation(self.data.train_indices)]
        return self.view_stack.pop()

    def sample_view(self, xi_range: tuple[float, float] | float, sampling: str = "uniform"
                    ) -> tuple[int, float, torch.Tensor]:
        """-> (view, xi, its anti-aliased target at ``camera.scaled(xi)``): the next view, then xi drawn from
        ``xi_range`` as ``sampling`` says (``draw_xi``), both from ``self.rng``; a number instead of a range is
        the xi itself (nothing drawn)."""
        i = self.next_view()
        xi = float(xi_range) if isinstance(xi_range, (int, float)) else draw_xi(xi_range, sampling, self.rng.random())
        return i, xi, self.images.get(i, xi)

    def optimise(self, loss: torch.Tensor, render, width: int, height: int, lrs: dict[str, float]) -> None:
        """backward -> ``observe`` (gradient statistics) -> optimiser step -> iteration + 1 -> ``after_step``.
        ``render`` has ``projected.means2d``, whose gradient ``observe`` reads."""
        means2d = render.projected.means2d
        if means2d.requires_grad:
            means2d.retain_grad()
        self.opt.zero_grad()
        if loss.requires_grad:
            loss.backward()
        self.observe(render, width, height)
        self.opt.step(lrs)
        self.iteration += 1
        self.after_step()

    def observe(self, render, width: int, height: int) -> None:
        """Gradient statistics for the densification strategy (after backward, before the step)."""

    def after_step(self) -> None:
        """The strategy's turn: grow, prune, densify (after the step)."""

    @staticmethod
    def step_stats(loss: torch.Tensor, img: torch.Tensor, gt: torch.Tensor) -> dict:
        """The step's loss and squared error as 0-d tensors where they were computed: read back (a device sync)
        only when a progress line is written."""
        with torch.no_grad():
            mse = ((img.detach().clamp(0, 1) - gt) ** 2).mean()
        return {"loss": loss.detach(), "mse": mse}


# ================================================================================================ resolution sampling
XI_SAMPLINGS = ("uniform", "pixels", "log")


def check_xi_sampling(sampling: str) -> None:
    if sampling not in XI_SAMPLINGS:
        raise ProxycodecError(f"unknown resolution sampling {sampling!r}; choose from {', '.join(XI_SAMPLINGS)}")


def draw_xi(xi_range: tuple[float, float], sampling: str, u: float) -> float:
    """xi in [lo, hi] from one uniform draw ``u`` in [0, 1): uniform in xi (the paper's), uniform in pixel count
    (xi^2, so density ~ xi: more iterations near full resolution) or uniform in log xi (more near the bottom)."""
    lo, hi = float(xi_range[0]), float(xi_range[1])
    if sampling == "pixels":
        return math.sqrt(lo * lo + (hi * hi - lo * lo) * u)
    if sampling == "log":
        return lo * (hi / lo) ** u
    return lo + (hi - lo) * u


# ================================================================================================ the loop
def fmt_time(s: float) -> str:
    s = max(0, int(s))
    return f"{s // 3600:d}:{s % 3600 // 60:02d}:{s % 60:02d}" if s >= 3600 else f"{s // 60:02d}:{s % 60:02d}"


def timed_step(tr: TrainingRun, log_every: float, last_log: float, log: ProgressFn, detail, hist_extra
               ) -> tuple[dict, bool]:
    """One ``tr.train_step()``, timed into ``tr.elapsed``; EMA loss/PSNR; a progress line (and a history entry) at
    most every ``log_every`` seconds, on the first and on the last iteration. ``detail(st)``: the trainer's own
    fields for the line; ``hist_extra()``: its own history fields. -> (the step's stats, whether a line was
    written)."""
    t0 = time.perf_counter()
    st = tr.train_step()
    tr.elapsed += time.perf_counter() - t0
    # running means as float64 tensors on the step's device: nothing is read back until a line is written
    loss = st["loss"].double()
    psnr = 10.0 * torch.log10(1.0 / st["mse"].double().clamp_min(1e-10))
    a = 0.05 if tr.ema_loss is not None else 1.0
    tr.ema_loss = loss if tr.ema_loss is None else (1 - a) * tr.ema_loss + a * loss
    tr.ema_psnr = psnr if tr.ema_psnr is None else (1 - a) * tr.ema_psnr + a * psnr
    if not (time.perf_counter() - last_log >= log_every or tr.done() or tr.iteration == 1):
        return st, False
    p = tr.progress()
    eta = tr.elapsed * (1 - p) / max(p, 1e-9)
    total = tr.cfg.iters if tr.cfg.iters is not None else "?"
    ema_loss, ema_psnr = float(tr.ema_loss), float(tr.ema_psnr)
    log(f"it {tr.iteration:6d}/{total}  loss {ema_loss:.4f}  psnr {ema_psnr:5.2f}  {detail(st)}  "
        f"{fmt_time(tr.elapsed)} elapsed  eta {fmt_time(eta)}")
    tr.history.append({"it": tr.iteration, "loss": round(ema_loss, 6), "psnr": round(ema_psnr, 4),
                       **hist_extra(), "seconds": round(tr.elapsed, 2)})
    return st, True


def warm_up_renderer(tr: TrainingRun, log: ProgressFn) -> float:
    """``render.warm_up`` on the run's device and backend, outside ``tr.elapsed``: a time budget buys training, not
    numba's first compilation (~30 s in a process with an empty kernel cache, on 2 cores). -> its seconds."""
    from .render import warm_up

    seconds = warm_up(tr.cfg.backend, tr.device)
    if seconds >= 1.0:
        log(f"renderer ready in {seconds:.1f} s (kernels compiled or loaded; not counted as training time)")
    return seconds


def run_until_done(tr: TrainingRun, log: ProgressFn, detail, hist_extra,
                   between_steps: Callable[[float], None] | None = None) -> None:
    """``timed_step`` until the run is done (the renderer warmed up first, off the clock: ``warm_up_renderer``);
    ``between_steps(now)`` after each step (checkpoints, test stops)."""
    if not tr.done():
        warm_up_renderer(tr, log)
    last_log = time.perf_counter()
    while not tr.done():
        _, logged = timed_step(tr, tr.cfg.log_every, last_log, log, detail, hist_extra)
        now = time.perf_counter()
        last_log = now if logged else last_log
        if between_steps is not None:
            between_steps(now)


def run_checkpointed(tr: TrainingRun, ckpt: Path | None, checkpoint_every: float, log: ProgressFn, detail,
                     hist_extra, finish: Callable[[], T], *, keep_checkpoint: bool = False,
                     stop_after: int | None = None) -> T:
    """``run_until_done``, then ``finish()`` (writing the result; its value is returned), with
    ``tr.save_checkpoint(ckpt)`` every ``checkpoint_every`` seconds (0: never) and on interrupt or error, in training
    or in ``finish``: the work is kept, never a partial output. After success the checkpoint is removed unless
    ``keep_checkpoint``. ``ckpt`` None: no checkpoints at all. ``stop_after`` (tests) raises ``KeyboardInterrupt``
    after that many steps of this call."""
    last_ckpt = time.perf_counter()
    steps = 0

    def between_steps(now: float) -> None:
        nonlocal last_ckpt, steps
        steps += 1
        if ckpt is not None and checkpoint_every > 0 and now - last_ckpt >= checkpoint_every and not tr.done():
            tr.save_checkpoint(ckpt)
            last_ckpt = time.perf_counter()
        if stop_after is not None and steps >= stop_after:
            raise KeyboardInterrupt

    try:
        run_until_done(tr, log, detail, hist_extra, between_steps)
        result = finish()
    except BaseException:
        if ckpt is not None:
            with contextlib.suppress(Exception), signals_ignored():
                tr.save_checkpoint(ckpt)
                log(f"checkpoint saved at iteration {tr.iteration}: {ckpt} (continue with --resume)")
        raise
    if ckpt is not None and not keep_checkpoint:
        with contextlib.suppress(FileNotFoundError):
            ckpt.unlink()
    return result
