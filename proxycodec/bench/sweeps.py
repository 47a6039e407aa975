"""Points and sweeps: what one way of storing a scene measures, the encode-side sweeps around the defaults, and
``proxycodec bench`` (:func:`run_bench`)."""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..errors import ProxycodecError
from .report import write_report
from .runner import Runner, machine_info, safe_name, versions


@dataclass(frozen=True)
class EvalSpec:
    """How points of one scene are evaluated: the dataset, its 100% reference width, the COLMAP test split and the
    number of test views (the first ``views`` of the test split)."""

    dataset: str
    max_width: int | None
    views: int
    test_every: int = 8
    resolutions: tuple[float, ...] = tuple(round(0.1 * k, 1) for k in range(1, 11))
    backend: str = "auto"

    def to_json(self) -> dict:
        return {"dataset": self.dataset, "max_width": self.max_width, "views": self.views,
                "test_every": self.test_every, "resolutions": list(self.resolutions), "backend": self.backend}


def _res(rec: dict | None) -> dict:
    return (rec or {}).get("result", {}) if rec and rec.get("status") == "ok" else {}


def make_point(scene: str, pid: str, kind: str, *, fit: dict | None = None, enc: dict | None = None,
               ev: dict | None = None, dec: dict | None = None, bytes_: int | None = None, **extra) -> dict:
    """One point from its step records (``dec``: the decode timing when the quality comes from another point)."""
    f, e, v = _res(fit), _res(enc), _res(ev)
    d = _res(dec) if dec is not None else v
    p: dict[str, Any] = {
        "scene": scene, "id": pid, "kind": kind, "bytes": bytes_ if bytes_ is not None else e.get("bytes"),
        "psnr_avg": v.get("psnr_avg"), "ssim_avg": v.get("ssim_avg"), "lpips_avg": v.get("lpips_avg"),
        "lpips_note": v.get("lpips_note"), "psnr_10": v.get("psnr_10"),
        "psnr_100": v.get("psnr_100"),
        "fit_seconds": f.get("seconds"), "fit_iterations": f.get("iterations"),
        "encode_seconds": e.get("seconds"),
        "decode_seconds": d.get("load_seconds") if kind == "container" else None,
        "load_seconds": d.get("load_seconds"),
        "render_ms": {f"{r['xi']:g}": r["ms"] for r in v.get("per_resolution", [])},
        "views": len(v.get("views", [])) or None,
        "peak_rss_mb": {k: _res(r).get("peak_rss_mb") for k, r in
                        (("fit", fit), ("encode", enc), ("eval", ev), ("decode", dec)) if r is not None},
        "errors": [r.get("error") or r.get("result", {}).get("skipped") for r in (fit, enc, ev, dec)
                   if r is not None and r.get("status") != "ok"],
    }
    if p["fit_seconds"] is not None or p["encode_seconds"] is not None:
        p["production_seconds"] = (p["fit_seconds"] or 0.0) + (p["encode_seconds"] or 0.0)
    p.update(extra)
    return p


def eval_step(runner: Runner, sid: str, model_path: str | os.PathLike, ev: EvalSpec, *, gate: str = "model",
              views: int | None = None) -> dict:
    args = {"model": str(model_path), **ev.to_json(), "gate": gate}
    if views is not None:
        args["views"] = views
    return runner.step(sid, "eval", args, timeout=7200)


def encode_sweep_plan(quick: bool, sweeps: Sequence[str] | None = None) -> list[tuple[str, str, dict]]:
    """(sweep, label, EncodeConfig knobs) one setting at a time around the defaults; the encode-time predictor is
    refitted (``use_fitted=False``) on L_recon at every point (``distill=False``: a distillation per point would cost
    minutes each), since proxies and predictor change with the knobs."""
    from ..codec import EncodeConfig

    d = EncodeConfig()
    if quick:
        grid = {"proxy_ratio": [0.1, 0.3, 0.6], "leaf_sample": [0.05, 0.2, 0.5],
                "bits": [(6, 8, 8), (8, 8, 8), (10, 8, 8)], "zstd_level": [3, 19], "predictor_blocks": [1, 2],
                "entropy": ["zstd", "model"], "positions": ["delta"], "weights_dtype": ["q8", "q6"]}
    else:
        grid = {"proxy_ratio": [0.1, 0.2, 0.3, 0.45, 0.6], "leaf_sample": [0.05, 0.1, 0.2, 0.5],
                "bits": [(6, 8, 8), (8, 8, 8), (10, 8, 8), (8, 6, 6), (8, 10, 10)],
                "zstd_level": [3, 9, 19, 22], "predictor_blocks": [0, 1, 2, 4], "entropy": ["zstd", "model"],
                "positions": ["delta"], "weights_dtype": ["q8", "q6", "q5"]}
    unknown = set(sweeps or ()) - set(grid)
    if unknown:
        raise ProxycodecError(f"unknown sweep(s) {', '.join(sorted(unknown))}; choose from {', '.join(grid)}")
    plan = []
    for name, values in grid.items():
        if sweeps and name not in sweeps:
            continue
        for v in values:
            if name == "bits":  # [D] uniform grids of these depths: on a rate-trained scene encode otherwise quantises
                # on the learned grids and the bits change nothing (bonsai, 2026-11-24: five points, one file)
                knobs = {"offset_bits": v[0], "feature_bits": v[1], "scaling_bits": v[2], "learned_steps": False}
                label = f"offsets {v[0]} / features {v[1]} / scalings {v[2]}, uniform grids"
            else:
                knobs = {name: v}
                label = v if isinstance(v, str) else f"{v:g}"
            plan.append((name, label, {"use_fitted": False, **knobs}))
    base = {"use_fitted": False, "distill": False, "proxy_ratio": d.proxy_ratio, "leaf_sample": d.leaf_sample,
            "offset_bits": d.offset_bits, "feature_bits": d.feature_bits, "scaling_bits": d.scaling_bits,
            "zstd_level": d.zstd_level, "predictor_blocks": d.predictor_blocks, "weights_dtype": d.weights_dtype}
    return [(n, lab, {**base, **k}) for n, lab, k in plan]


def knob_id(knobs: dict) -> str:
    """A point's name from its encode knobs: those that differ from the defaults."""
    from ..codec import EncodeConfig

    d = EncodeConfig()
    diff = {k: v for k, v in sorted(knobs.items()) if k not in ("use_fitted", "distill") and getattr(d, k) != v}
    if not diff:
        return "encode default (refit)"
    return "encode " + ", ".join(f"{k}={v}" for k, v in diff.items())


def encode_point(runner: Runner, scene: str, pid: str, source_ply: str | os.PathLike, knobs: dict, ev: EvalSpec, *,
                 fit: dict | None = None, evaluated: dict[str, tuple[str, dict]], **extra) -> dict:
    """Encode ``source_ply`` with ``knobs``, then evaluate the container (or, when an identical content was evaluated
    already, only time its decode and reuse that quality)."""
    out = runner.work / scene / f"{safe_name(pid)}.pxc"
    out.parent.mkdir(parents=True, exist_ok=True)
    enc = runner.step(f"encode:{scene}/{pid}", "encode", {"source": str(source_ply), "out": str(out),
                                                           "knobs": knobs}, outputs=[out], timeout=3600)
    key = _res(enc).get("content_key")
    sid = f"eval:{scene}/{pid}"
    if key and key in evaluated and evaluated[key][0] != pid:
        src_pid, ev_rec = evaluated[key]
        dec = eval_step(runner, f"decode:{scene}/{pid}", out, ev, views=0)
        return make_point(scene, pid, "container", fit=fit, enc=enc, ev=ev_rec, dec=dec, knobs=knobs,
                          quality_from=src_pid, **extra)
    ev_rec = eval_step(runner, sid, out, ev) if enc.get("status") == "ok" else None
    if key and ev_rec is not None and ev_rec.get("status") == "ok":
        evaluated[key] = (pid, ev_rec)
    return make_point(scene, pid, "container", fit=fit, enc=enc, ev=ev_rec, knobs=knobs, **extra)


def run_encode_sweeps(runner: Runner, scene: str, source_ply: str | os.PathLike, ev: EvalSpec, *, quick: bool,
                      sweeps: Sequence[str] | None = None, fit: dict | None = None,
                      evaluated: dict | None = None, common: dict | None = None) -> list[dict]:
    """The encode-side sweeps on one fitted scene (one point per distinct setting; ``sweeps`` on each point says
    which sweeps it belongs to). Also the as-fitted default (``proxycodec encode SCENE`` with no options: the
    stage-2 proxies and predictor when the scene has them), marked ``default``. ``common``: encode knobs applied
    to every point (e.g. ``predictor_iters``), not part of the point names."""
    evaluated = {} if evaluated is None else evaluated
    common = dict(common or {})
    points: dict[str, dict] = {}
    p = encode_point(runner, scene, "encode default", source_ply, common, ev, fit=fit, evaluated=evaluated,
                     group="default", default=True, sweeps={})
    points[p["id"]] = p
    for order, (name, label, knobs) in enumerate(encode_sweep_plan(quick, sweeps)):
        pid = knob_id(knobs)
        if pid not in points:
            points[pid] = encode_point(runner, scene, pid, source_ply, {**knobs, **common}, ev, fit=fit,
                                       evaluated=evaluated, group="encode sweep", default=False, sweeps={})
        points[pid]["sweeps"][name] = label
        points[pid].setdefault("sweep_order", {})[name] = order
    return list(points.values())


def run_bench(scene_ply: str, dataset: str, out_dir: str, *, quick: bool = False, views: int | None = None,
              max_width: int | None = None, test_every: int = 8, sweeps: Sequence[str] | None = None,
              isolate: bool = True, fresh: bool = False, seed: int = 0, backend: str = "auto",
              predictor_iters: int | None = None, distill_iters: int | None = None, any_code: bool = False,
              log: Callable[[str], None] | None = None) -> dict[str, Path]:
    """``proxycodec bench``: the encode-side sweeps on a user's fitted scene (anchor PLY + weights sidecar).

    ``out_dir`` is resolved to an absolute path, as the scene and the dataset are: steps are keyed by their arguments,
    so the same folder named relatively and absolutely is one cache. ``any_code``: reuse the steps recorded by other
    code too (``Runner``), e.g. to add sweep points to a run after a change that does not touch them."""
    from ..formats.container import read_container
    from ..model import weights_path_for

    scene_ply = str(Path(scene_ply).resolve())
    dataset = str(Path(dataset).resolve())
    out_dir = str(Path(out_dir).resolve())
    w = weights_path_for(scene_ply)
    if not Path(scene_ply).is_file() or not w.is_file():
        raise ProxycodecError(f"bench needs an anchor PLY with its weights sidecar ({w.name})", scene_ply)
    fit_meta = read_container(w).meta.get("fit") or {}
    if max_width is None:
        max_width = (fit_meta.get("config") or {}).get("max_width", 1600)
    views = views if views is not None else (2 if quick else 8)
    name = Path(scene_ply).stem
    ev = EvalSpec(dataset, max_width, views, test_every, backend=backend)
    common = {"seed": seed} if seed else {}
    if predictor_iters is not None:
        common["predictor_iters"] = int(predictor_iters)
    if distill_iters is not None:  # the default point of a scene without a stage-2 predictor distils
        common["distill_iters"] = int(distill_iters)
    meta = {"kind": "proxycodec.bench", "seed": seed, "quick": quick, "machine": machine_info(),
            "versions": versions(), "encode_knobs_on_every_point": common,
            "scenes": {name: {"scene": scene_ply, "dataset": dataset, "reference width": max_width,
                              "test views evaluated": views, "fit seconds (from the weights file)":
                                  fit_meta.get("seconds")}}}
    runner = Runner(out_dir, meta, isolate=isolate, fresh=fresh, log=log, any_code=any_code)
    fit_rec = None
    if fit_meta.get("seconds") is not None:  # the scene's own training time, for the PSNR-vs-time plot
        fit_rec = {"status": "ok", "result": {"seconds": fit_meta.get("seconds"),
                                              "iterations": fit_meta.get("iterations")}}
    src_ev = eval_step(runner, f"eval:{name}/uncompressed", scene_ply, ev)
    src_bytes = Path(scene_ply).stat().st_size + w.stat().st_size
    points = [make_point(name, "uncompressed (PLY + weights)", "anchor-ply", fit=fit_rec, ev=src_ev,
                         bytes_=src_bytes, group="uncompressed")]
    points += run_encode_sweeps(runner, name, scene_ply, ev, quick=quick, sweeps=sweeps, fit=fit_rec, common=common)
    return write_report(runner, f"proxycodec bench: {name}", points, markdown_name="bench.md")

