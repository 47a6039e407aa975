"""The measured steps of a benchmark run (fit, 3DGS baseline fit, encode, decode + evaluation, SPZ conversion).

Each takes the JSON arguments the runner recorded for it and returns a JSON-able result; :func:`run_worker` runs one
and adds the process's peak RSS and load averages (``runner``: in a subprocess of its own, or in this one).
"""

from __future__ import annotations

import hashlib
import json
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from ..devices import resolve
from ..errors import ProxycodecError
from .node_tools import SPLAT_TRANSFORM as SPZ_TOOL


def load_avg() -> list[float]:
    try:
        return [round(v, 2) for v in os.getloadavg()]
    except OSError:  # pragma: no cover
        return []


def _rss_mb(who=None) -> float:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF if who is None else who).ru_maxrss / 1024.0


def _step_fit(a: dict) -> dict:
    from ..formats.datasets import load_dataset
    from ..train import FitConfig, checkpoint_path_for, fit

    data = load_dataset(a["dataset"], max_width=a["max_width"], test_every=a.get("test_every", 8))
    cfg = FitConfig(**{**a["config"], "max_width": a["max_width"]})
    out = Path(a["out"])
    out.parent.mkdir(parents=True, exist_ok=True)
    resume = checkpoint_path_for(out).exists()  # an interrupted earlier run of this step
    log = lambda s: print(s, file=sys.stderr, flush=True)  # noqa: E731
    try:
        res = fit(data, out, cfg, dataset_root=str(Path(a["dataset"]).resolve()), resume=resume, log=log)
    except ProxycodecError:
        if not resume:
            raise
        checkpoint_path_for(out).unlink(missing_ok=True)  # stale checkpoint of other settings: start afresh
        res = fit(data, out, cfg, dataset_root=str(Path(a["dataset"]).resolve()), log=log)
    from ..model import weights_path_for

    return {"iterations": res.iterations, "seconds": res.seconds, "anchors": res.model.scene.num_anchors,
            "bytes": out.stat().st_size + weights_path_for(out).stat().st_size, "resumed": resume}


def _step_explicit(a: dict) -> dict:
    from ..explicit import ExplicitConfig, run_explicit
    from ..formats.datasets import load_dataset

    data = load_dataset(a["dataset"], max_width=a["max_width"], test_every=a.get("test_every", 8))
    cfg = ExplicitConfig(**{**a["config"], "max_width": a["max_width"]})
    Path(a["out"]).parent.mkdir(parents=True, exist_ok=True)
    tr = run_explicit(data, cfg, lambda s: print(s, file=sys.stderr, flush=True), out=a["out"])
    return {"iterations": tr.iteration, "seconds": tr.elapsed, "gaussians": tr.num_gaussians,
            "bytes": Path(a["out"]).stat().st_size}


#: Metadata that says how the content is coded, not what it is: encodes differing only there decode to the same scene
CODING_META = ("encoder", "entropy", "scene_format", "features", "positions", "weights_layout", "quant")


def _content_key(path: Path) -> str:
    """Hash of the scene a container decodes to (its stored anchors dequantised, the split, the weights, the rest of
    the metadata), whatever coded it: encodes that differ only in the zstd level, the entropy coding or the position
    coding get one key, and share one quality evaluation."""
    from ..sections import read_scene_container, stored_anchors

    c = read_scene_container(path)  # weights unpacked

    def err(m):
        return ProxycodecError(m, path)

    a = stored_anchors(c.meta, dict(c.arrays), err)
    h = hashlib.sha256()
    meta = {k: v for k, v in c.meta.items() if k not in CODING_META}
    h.update(json.dumps(meta, sort_keys=True).encode())
    arrays = {"anchors": [a.positions, a.features, a.offsets, a.scalings, a.proxy_mask]}
    arrays.update({k: [v] for k, v in c.arrays.items() if k.startswith(("decoder/", "predictor/"))})
    for name in sorted(arrays):
        for arr in arrays[name]:
            arr = np.ascontiguousarray(arr)
            h.update(f"{name}|{arr.dtype.str}|{arr.shape}".encode())
            h.update(arr.tobytes())
    return h.hexdigest()


def _step_encode(a: dict) -> dict:
    from .. import codec

    t0 = time.perf_counter()
    r = codec.encode(a["source"], a["out"], **a["knobs"], device=resolve())
    total = time.perf_counter() - t0
    return {"bytes": r.file_bytes, "seconds": r.seconds["total"], "seconds_call": total,
            "predictor_seconds": r.seconds.get("predictor"), "anchors": r.anchors, "proxies": r.proxies,
            "source_bytes": r.source_bytes, "proxy_source": r.meta.get("proxy", {}).get("source"),
            "predictor_loss": None if r.training is None else [r.training.baseline_loss, r.training.final_loss],
            "content_key": _content_key(Path(a["out"]))}


def _step_eval(a: dict) -> dict:
    from ..evaluate import evaluate
    from ..explicit import ExplicitModel
    from ..model import apply_gate_mode
    from ..scenes import load_any

    t0 = time.perf_counter()
    model = load_any(a["model"])
    model = model.to(resolve()) if hasattr(model, "to") else model
    load_s = time.perf_counter() - t0
    out: dict[str, Any] = {"load_seconds": load_s, "rss_after_load_mb": _rss_mb()}
    out["gate"] = apply_gate_mode(model, a.get("gate", "model"))
    if int(a["views"]) <= 0:
        return out
    from ..formats.datasets import load_dataset

    data = load_dataset(a["dataset"], max_width=a["max_width"], test_every=a.get("test_every", 8))
    if isinstance(model, ExplicitModel):
        model.background = tuple(data.background)
    views = list(data.test_indices)[:int(a["views"])]
    if not views:
        raise ProxycodecError("the dataset has no test views")
    model.render(data.cameras[views[0]], 0.5, backend=a.get("backend", "auto"))  # warm-up (numba cache, allocator)
    rep = evaluate(model, data, resolutions=[float(x) for x in a["resolutions"]], views=views,
                   backend=a.get("backend", "auto"))
    s = rep.summary
    out.update({
        "views": views, "test_views_available": len(data.test_indices),
        "psnr_avg": s["psnr_avg"], "ssim_avg": s["ssim_avg"], "psnr_10": s["psnr_10"], "psnr_100": s["psnr_100"],
        "lpips_avg": s["lpips_avg"], "lpips_note": rep.lpips_note,
        "per_resolution": [{"xi": d["xi"], "width": d["width"], "height": d["height"], "psnr": d["psnr"],
                            "ssim": d["ssim"], "lpips": d["lpips"],
                            "ms": None if d["seconds"] is None else 1000.0 * d["seconds"],
                            "gaussians": d["gaussians"]} for d in rep.per_resolution],
    })
    return out


def _step_spz(a: dict) -> dict:
    """INRIA PLY -> SPZ with splat-transform, then SPZ -> PLY again so that the SPZ's own quality can be evaluated."""
    import resource

    from .node_tools import splat_transform, splat_transform_unavailable

    why = splat_transform_unavailable()
    if why:
        return {"skipped": why}
    t0 = time.perf_counter()
    r = splat_transform("-w", a["ply"], a["out"], timeout=900)
    conv_s = time.perf_counter() - t0
    if r.returncode != 0:
        raise ProxycodecError(f"splat-transform failed: {(r.stdout + r.stderr).strip()[-300:]}")
    t0 = time.perf_counter()
    r2 = splat_transform("-w", a["out"], a["back"], timeout=900)
    back_s = time.perf_counter() - t0
    if r2.returncode != 0:
        raise ProxycodecError(f"splat-transform (SPZ -> PLY) failed: {(r2.stdout + r2.stderr).strip()[-300:]}")
    return {"bytes": Path(a["out"]).stat().st_size, "seconds": conv_s, "back_seconds": back_s, "tool": SPZ_TOOL,
            "node_peak_rss_mb": _rss_mb(resource.RUSAGE_CHILDREN)}


def convert_config(d: dict):
    """The ``ConvertConfig`` of a step's JSON: its ``fit`` fields replace those of conversion's own ``FitConfig``
    (as the CLI does), not ``FitConfig``'s defaults."""
    from ..convert import ConvertConfig, replace_fit

    c = {k: tuple(v) if isinstance(v, list) else v for k, v in d.items()}
    fit = {k: tuple(v) if isinstance(v, list) else v for k, v in c.pop("fit", {}).items()}
    return replace_fit(ConvertConfig(**c), **fit)


def _step_convert(a: dict) -> dict:
    """``proxycodec encode SPLATS.ply --keep-anchor-scene``: convert an INRIA PLY, then encode its anchor scene."""
    from ..convert import convert_and_encode

    cfg = convert_config(a["convert"])
    log = lambda s: print(s, file=sys.stderr, flush=True)  # noqa: E731
    t0 = time.perf_counter()
    conv, rep = convert_and_encode(a["ply"], a["out"], cfg, keep=a.get("keep"), log=log, device=resolve())
    return {"bytes": rep.file_bytes, "seconds": time.perf_counter() - t0, "convert": conv.to_json(),
            "encode_seconds": rep.seconds["total"], "anchors": rep.anchors, "proxies": rep.proxies}


def _step_vs_source(a: dict) -> dict:
    """A scene (``model``: anything ``load_any`` opens) against the anti-aliased renders of the INRIA PLY ``source``
    (its 100% render box-filtered to each resolution) on the held-out views of ``cameras`` (every 8th, as
    ``convert`` holds them out), at 10%..100%."""
    from ..distill import TeacherViews, held_out_report
    from ..explicit import ExplicitModel
    from ..scaffold_gs import read_scaffold_cameras
    from ..scenes import load_any

    bg = tuple(float(x) for x in a["background"])
    teacher = ExplicitModel.load(a["source"], bg)
    views = TeacherViews(teacher, read_scaffold_cameras(a["cameras"]))
    model = load_any(a["model"])
    if isinstance(model, ExplicitModel):
        model.background = bg
    rep = held_out_report(model, views, max_views=int(a["views"]))
    return {"psnr_avg": rep["psnr"], "ssim_avg": rep["ssim"], "views": rep["views"],
            "per_resolution": rep["per_resolution"]}


STEPS: dict[str, Callable[[dict], dict]] = {"fit": _step_fit, "explicit": _step_explicit, "encode": _step_encode,
                                             "eval": _step_eval, "spz": _step_spz, "convert": _step_convert,
                                             "vs_source": _step_vs_source}


def run_worker(kind: str, args: dict) -> dict:
    """Run one step in this process; adds the process's peak RSS and load averages."""
    t0 = time.perf_counter()
    load0 = load_avg()
    out = STEPS[kind](args)
    out["peak_rss_mb"] = _rss_mb()
    out["wall_seconds"] = time.perf_counter() - t0
    out["loadavg_before"], out["loadavg_after"] = load0, load_avg()
    return out


