"""The size / quality / time trade-off benchmark (issue #7), shared by ``proxycodec bench`` and
``benchmarks/tradeoff.py``.

Every measured step (fit, encode, decode + evaluation, SPZ conversion) runs in its own Python subprocess
(``python -m proxycodec.bench --worker JSON``), so its peak RSS (``getrusage(RUSAGE_SELF).ru_maxrss`` of that process,
plus ``RUSAGE_CHILDREN`` for the Node.js converter) is its own. Steps are recorded in ``results.json`` as soon as they
finish (written atomically), keyed by a step id and its arguments: a re-run skips every step already done with the
same arguments (and whose output files still exist), so an interrupted run resumes where it stopped.

A *point* is one way of storing a scene: a container from some encode settings, the uncompressed anchor PLY + weights,
a plain 3DGS INRIA PLY or its SPZ conversion. Per point: bytes on disk, PSNR / SSIM averaged over the ten resolutions
10%..100% (on the first ``views`` test views), PSNR at 10% and 100%, fit / encode / decode seconds, mean render time
per resolution, peak RSS per step. Encodes whose stored content is identical (every section and the metadata but the
encoder's zstd level) share one quality evaluation (``quality_from``); their decode is still timed on its own.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import platform
import re
import shutil
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .errors import ProxycodecError
from .fileio import atomic_write

__all__ = [
    "EvalSpec", "Runner", "encode_sweep_plan", "pareto_front", "run_encode_sweeps",
    "write_report", "machine_info", "SPZ_TOOL",
]

SPZ_TOOL = "@playcanvas/splat-transform@2.7.1"
RESULTS = "results.json"
RESULTS_VERSION = 1


# ================================================================================================ small pieces
def pareto_front(points: Sequence[dict], x: str = "bytes", y: str = "psnr_avg") -> list[int]:
    """Indices (ascending ``x``) of the points no other point dominates: none has ``x`` <= and ``y`` >= with at least
    one strict. Smaller ``x`` and larger ``y`` are better; points missing either value are ignored."""
    ok = [i for i, p in enumerate(points)
          if p.get(x) is not None and p.get(y) is not None and math.isfinite(p[x]) and math.isfinite(p[y])]
    front = []
    for i in ok:
        xi, yi = points[i][x], points[i][y]
        dominated = any(points[j][x] <= xi and points[j][y] >= yi and (points[j][x] < xi or points[j][y] > yi)
                        for j in ok if j != i)
        if not dominated:
            front.append(i)
    return sorted(front, key=lambda i: (points[i][x], -points[i][y]))


def _load_avg() -> list[float]:
    try:
        return [round(v, 2) for v in os.getloadavg()]
    except OSError:  # pragma: no cover
        return []


def machine_info() -> dict:
    info: dict[str, Any] = {"cpu_count": os.cpu_count(), "platform": platform.platform(),
                            "processor": platform.processor(), "python": platform.python_version()}
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                info["cpu_model"] = line.split(":", 1)[1].strip()
                break
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal"):
                info["memory_gb"] = round(int(line.split()[1]) / 2**20, 1)
                break
    except OSError:  # pragma: no cover
        pass
    return info


def versions() -> dict:
    import numba
    import numpy
    import torch
    import zstandard

    from . import __version__

    v = {"proxycodec": __version__, "python": platform.python_version(), "torch": torch.__version__,
         "numpy": numpy.__version__, "numba": numba.__version__, "zstandard": zstandard.__version__}
    node = shutil.which("node")
    if node:
        try:
            v["node"] = subprocess.run([node, "--version"], capture_output=True, text=True, timeout=20).stdout.strip()
        except (OSError, subprocess.TimeoutExpired):  # pragma: no cover
            pass
    return v


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


# ================================================================================================ worker steps
def _rss_mb(who=None) -> float:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF if who is None else who).ru_maxrss / 1024.0


def _step_fit(a: dict) -> dict:
    from .formats.datasets import load_dataset
    from .train import FitConfig, checkpoint_path_for, fit

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
    from .model import weights_path_for

    return {"iterations": res.iterations, "seconds": res.seconds, "anchors": res.model.scene.num_anchors,
            "bytes": out.stat().st_size + weights_path_for(out).stat().st_size, "resumed": resume}


def _step_explicit(a: dict) -> dict:
    import torch

    from .explicit import ExplicitConfig, run_explicit

    torch.set_num_threads(2)
    from .formats.datasets import load_dataset

    data = load_dataset(a["dataset"], max_width=a["max_width"], test_every=a.get("test_every", 8))
    cfg = ExplicitConfig(**{**a["config"], "max_width": a["max_width"]})
    Path(a["out"]).parent.mkdir(parents=True, exist_ok=True)
    tr = run_explicit(data, cfg, lambda s: print(s, file=sys.stderr, flush=True), out=a["out"])
    return {"iterations": tr.iteration, "seconds": tr.elapsed, "gaussians": tr.num_gaussians,
            "bytes": Path(a["out"]).stat().st_size}


def _content_key(path: Path) -> str:
    """Hash of everything a decoder reads from a scene container except the encoder's zstd level."""
    from .formats.container import read_container

    c = read_container(path)
    h = hashlib.sha256()
    meta = dict(c.meta)
    meta.pop("encoder", None)
    h.update(json.dumps(meta, sort_keys=True).encode())
    for name in sorted(c.arrays):
        arr = np.ascontiguousarray(c.arrays[name])
        h.update(f"{name}|{arr.dtype.str}|{arr.shape}".encode())
        h.update(arr.tobytes())
    return h.hexdigest()


def _step_encode(a: dict) -> dict:
    from . import codec

    t0 = time.perf_counter()
    r = codec.encode(a["source"], a["out"], **a["knobs"])
    total = time.perf_counter() - t0
    return {"bytes": r.file_bytes, "seconds": r.seconds["total"], "seconds_call": total,
            "predictor_seconds": r.seconds.get("predictor"), "anchors": r.anchors, "proxies": r.proxies,
            "source_bytes": r.source_bytes, "proxy_source": r.meta.get("proxy", {}).get("source"),
            "predictor_loss": None if r.training is None else [r.training.baseline_loss, r.training.final_loss],
            "content_key": _content_key(Path(a["out"]))}


def _step_eval(a: dict) -> dict:
    import torch

    from .evaluate import evaluate
    from .explicit import ExplicitModel
    from .model import apply_gate_mode
    from .scenes import load_any

    torch.set_num_threads(2)
    t0 = time.perf_counter()
    model = load_any(a["model"])
    load_s = time.perf_counter() - t0
    out: dict[str, Any] = {"load_seconds": load_s, "rss_after_load_mb": _rss_mb()}
    out["gate"] = apply_gate_mode(model, a.get("gate", "model"))
    if int(a["views"]) <= 0:
        return out
    from .formats.datasets import load_dataset

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
        "per_resolution": [{"xi": d["xi"], "width": d["width"], "height": d["height"], "psnr": d["psnr"],
                            "ssim": d["ssim"], "ms": None if d["seconds"] is None else 1000.0 * d["seconds"],
                            "gaussians": d["gaussians"]} for d in rep.per_resolution],
    })
    return out


def _npx_tool() -> tuple[str | None, str | None]:
    """(npx path, None) when ``SPZ_TOOL`` runs, else (None, why not)."""
    npx = shutil.which("npx")
    if npx is None:
        return None, "npx (Node.js) is not installed"
    try:
        r = subprocess.run([npx, "-y", SPZ_TOOL, "--help"], capture_output=True, text=True, timeout=240)
    except subprocess.TimeoutExpired:
        return None, f"npx could not fetch {SPZ_TOOL} in time (no registry access?)"
    if r.returncode != 0 or "splat-transform" not in r.stdout:
        return None, f"npx could not run {SPZ_TOOL}: {r.stderr.strip()[-200:]}"
    return npx, None


def _step_spz(a: dict) -> dict:
    """INRIA PLY -> SPZ with splat-transform, then SPZ -> PLY again so that the SPZ's own quality can be evaluated."""
    import resource

    npx, why = _npx_tool()
    if npx is None:
        return {"skipped": why}
    t0 = time.perf_counter()
    r = subprocess.run([npx, "-y", SPZ_TOOL, "-w", a["ply"], a["out"]], capture_output=True, text=True, timeout=900)
    conv_s = time.perf_counter() - t0
    if r.returncode != 0:
        raise ProxycodecError(f"splat-transform failed: {(r.stdout + r.stderr).strip()[-300:]}")
    t0 = time.perf_counter()
    r2 = subprocess.run([npx, "-y", SPZ_TOOL, "-w", a["out"], a["back"]], capture_output=True, text=True, timeout=900)
    back_s = time.perf_counter() - t0
    if r2.returncode != 0:
        raise ProxycodecError(f"splat-transform (SPZ -> PLY) failed: {(r2.stdout + r2.stderr).strip()[-300:]}")
    return {"bytes": Path(a["out"]).stat().st_size, "seconds": conv_s, "back_seconds": back_s, "tool": SPZ_TOOL,
            "node_peak_rss_mb": _rss_mb(resource.RUSAGE_CHILDREN)}


STEPS: dict[str, Callable[[dict], dict]] = {"fit": _step_fit, "explicit": _step_explicit, "encode": _step_encode,
                                             "eval": _step_eval, "spz": _step_spz}


def run_worker(kind: str, args: dict) -> dict:
    """Run one step in this process; adds the process's peak RSS and load averages."""
    t0 = time.perf_counter()
    load0 = _load_avg()
    out = STEPS[kind](args)
    out["peak_rss_mb"] = _rss_mb()
    out["wall_seconds"] = time.perf_counter() - t0
    out["loadavg_before"], out["loadavg_after"] = load0, _load_avg()
    return out


# ================================================================================================ the runner
def _safe(sid: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.=-]+", "_", sid)


class Runner:
    """Runs steps (each in a fresh subprocess unless ``isolate`` is False) and records them in ``results.json``.

    A step already recorded as done with the same arguments, whose ``outputs`` still exist, is not run again.
    """

    def __init__(self, out_dir: str | os.PathLike, meta: dict, *, isolate: bool = True, fresh: bool = False,
                 log: Callable[[str], None] | None = None):
        self.out = Path(out_dir)
        self.out.mkdir(parents=True, exist_ok=True)
        self.work = self.out / "work"
        self.logs = self.out / "logs"
        self.work.mkdir(exist_ok=True)
        self.logs.mkdir(exist_ok=True)
        self.path = self.out / RESULTS
        self.isolate = isolate
        self.log = log or (lambda s: print(s, file=sys.stderr, flush=True))
        self.state: dict[str, Any] = {"version": RESULTS_VERSION, "steps": {}}
        if self.path.exists() and not fresh:
            try:
                old = json.loads(self.path.read_text())
                if old.get("version") == RESULTS_VERSION:
                    self.state["steps"] = old.get("steps", {})
                    self.state["runs"] = old.get("runs", [])
            except (OSError, ValueError):
                self.log(f"ignoring unreadable {self.path}")
        self.state.setdefault("runs", [])
        self.state["meta"] = meta
        self.t0 = time.time()
        self.state["runs"].append({"started": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                                   "loadavg_start": _load_avg(), "isolate": isolate})
        self.save()

    def save(self, extra: dict | None = None) -> None:
        if extra:
            self.state.update(extra)
        with atomic_write(self.path, "w") as fh:
            json.dump(self.state, fh, indent=1, default=_json_default)

    def step(self, sid: str, kind: str, args: dict, outputs: Sequence[str | os.PathLike] = (),
             timeout: float = 3600.0) -> dict:
        """The record of step ``sid`` (run now unless done before): ``status`` ok | error | skipped, ``result``."""
        args = json.loads(json.dumps(args, default=_json_default))
        rec = self.state["steps"].get(sid)
        if (rec and rec.get("kind") == kind and rec.get("args") == args and rec.get("status") in ("ok", "skipped")
                and all(Path(o).exists() for o in outputs)):
            return rec
        self.log(f"[{time.strftime('%H:%M:%S')}] {sid} ...")
        t0 = time.perf_counter()
        if self.isolate:
            rec = self._spawn(sid, kind, args, timeout)
        else:
            try:
                rec = {"status": "ok", "result": run_worker(kind, args), "rss_scope": "shared process"}
            except Exception as e:  # noqa: BLE001 - as a failed subprocess would: record it, go on
                rec = {"status": "error", "error": f"{type(e).__name__}: {e}"}
        rec.update(kind=kind, args=args, seconds=time.perf_counter() - t0,
                   finished=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()))
        if rec["status"] == "ok" and "skipped" in rec.get("result", {}):
            rec["status"] = "skipped"
        self.state["steps"][sid] = rec
        self.save()
        msg = rec.get("error") or rec.get("result", {}).get("skipped") or ""
        self.log(f"[{time.strftime('%H:%M:%S')}] {sid}: {rec['status']} in {rec['seconds']:.1f} s {msg}".rstrip())
        return rec

    def _spawn(self, sid: str, kind: str, args: dict, timeout: float) -> dict:
        logf = self.logs / f"{_safe(sid)}.log"
        cmd = [sys.executable, "-m", "proxycodec.bench", "--worker", kind, json.dumps(args)]
        with open(logf, "w") as err:
            try:
                r = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=err, text=True, timeout=timeout, check=False)
            except subprocess.TimeoutExpired:
                return {"status": "error", "error": f"timeout after {timeout:.0f} s (log: {logf})"}
        if r.returncode != 0:
            tail = logf.read_text(errors="replace").strip().splitlines()[-1:] or ["?"]
            return {"status": "error", "error": f"exit {r.returncode}: {tail[0][-300:]} (log: {logf})"}
        try:
            return {"status": "ok", "result": json.loads(r.stdout.strip().splitlines()[-1]),
                    "rss_scope": "own process"}
        except (ValueError, IndexError):
            return {"status": "error", "error": f"no result from the worker (log: {logf})"}

    def finish(self) -> None:
        self.state["runs"][-1].update(loadavg_end=_load_avg(), wall_seconds=time.time() - self.t0)
        self.save()


def _json_default(o):
    if isinstance(o, (np.generic,)):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    if isinstance(o, tuple):
        return list(o)
    raise TypeError(f"not JSON-serialisable: {type(o).__name__}")


# ================================================================================================ points
def _res(rec: dict | None) -> dict:
    return (rec or {}).get("result", {}) if rec and rec.get("status") == "ok" else {}


def make_point(scene: str, pid: str, kind: str, *, fit: dict | None = None, enc: dict | None = None,
               ev: dict | None = None, dec: dict | None = None, bytes_: int | None = None, **extra) -> dict:
    """One point from its step records (``dec``: the decode timing when the quality comes from another point)."""
    f, e, v = _res(fit), _res(enc), _res(ev)
    d = _res(dec) if dec is not None else v
    p: dict[str, Any] = {
        "scene": scene, "id": pid, "kind": kind, "bytes": bytes_ if bytes_ is not None else e.get("bytes"),
        "psnr_avg": v.get("psnr_avg"), "ssim_avg": v.get("ssim_avg"), "psnr_10": v.get("psnr_10"),
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
    refitted (``use_fitted=False``) at every point, since proxies and predictor change with the knobs."""
    from .codec import EncodeConfig

    d = EncodeConfig()
    if quick:
        grid = {"proxy_ratio": [0.1, 0.3, 0.6], "leaf_sample": [0.05, 0.2, 0.5],
                "bits": [(6, 8, 8), (8, 8, 8), (10, 8, 8)], "zstd_level": [3, 19], "predictor_blocks": [1, 2]}
    else:
        grid = {"proxy_ratio": [0.1, 0.2, 0.3, 0.45, 0.6], "leaf_sample": [0.05, 0.1, 0.2, 0.5],
                "bits": [(6, 8, 8), (8, 8, 8), (10, 8, 8), (8, 6, 6), (8, 10, 10)],
                "zstd_level": [3, 9, 19, 22], "predictor_blocks": [0, 1, 2, 4]}
    unknown = set(sweeps or ()) - set(grid)
    if unknown:
        raise ProxycodecError(f"unknown sweep(s) {', '.join(sorted(unknown))}; choose from {', '.join(grid)}")
    plan = []
    for name, values in grid.items():
        if sweeps and name not in sweeps:
            continue
        for v in values:
            if name == "bits":
                knobs = {"offset_bits": v[0], "feature_bits": v[1], "scaling_bits": v[2]}
                label = f"offsets {v[0]} / features {v[1]} / scalings {v[2]}"
            else:
                knobs = {name: v}
                label = f"{v:g}"
            plan.append((name, label, {"use_fitted": False, **knobs}))
    base = {"use_fitted": False, "proxy_ratio": d.proxy_ratio, "leaf_sample": d.leaf_sample,
            "offset_bits": d.offset_bits, "feature_bits": d.feature_bits, "scaling_bits": d.scaling_bits,
            "zstd_level": d.zstd_level, "predictor_blocks": d.predictor_blocks}
    return [(n, lab, {**base, **k}) for n, lab, k in plan]


def _knob_id(knobs: dict) -> str:
    from .codec import EncodeConfig

    d = EncodeConfig()
    diff = {k: v for k, v in sorted(knobs.items()) if k != "use_fitted" and getattr(d, k) != v}
    if not diff:
        return "encode default (refit)"
    return "encode " + ", ".join(f"{k}={v}" for k, v in diff.items())


def encode_point(runner: Runner, scene: str, pid: str, source_ply: str | os.PathLike, knobs: dict, ev: EvalSpec, *,
                 fit: dict | None = None, evaluated: dict[str, tuple[str, dict]], **extra) -> dict:
    """Encode ``source_ply`` with ``knobs``, then evaluate the container (or, when an identical content was evaluated
    already, only time its decode and reuse that quality)."""
    out = runner.work / scene / f"{_safe(pid)}.pxc"
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
        pid = _knob_id(knobs)
        if pid not in points:
            points[pid] = encode_point(runner, scene, pid, source_ply, {**knobs, **common}, ev, fit=fit,
                                       evaluated=evaluated, group="encode sweep", default=False, sweeps={})
        points[pid]["sweeps"][name] = label
        points[pid].setdefault("sweep_order", {})[name] = order
    return list(points.values())


# ================================================================================================ report
def _f(x, spec=".3f", none="n/a") -> str:
    return none if x is None or (isinstance(x, float) and not math.isfinite(x)) else format(x, spec)


def _rss(p: dict) -> str:
    return " / ".join(f"{k} {v:.0f}" for k, v in p.get("peak_rss_mb", {}).items() if v is not None) or "n/a"


def mark_pareto(points: list[dict]) -> None:
    """Sets ``pareto`` (bytes vs average PSNR) on each point, per scene."""
    for scene in sorted({p["scene"] for p in points}):
        ps = [p for p in points if p["scene"] == scene]
        front = set(pareto_front(ps))
        for i, p in enumerate(ps):
            p["pareto"] = i in front


POINT_HEADER = ("| point | bytes | avg PSNR | avg SSIM | PSNR 10% | PSNR 100% | fit s | encode s | decode s | "
                "Pareto | peak RSS MB |\n|---|---:|---:|---:|---:|---:|---:|---:|---:|:-:|---|")


def point_row(p: dict, label: str | None = None) -> str:
    name = label or p["id"]
    if p.get("default"):
        name = f"**{name}**"
    if p.get("quality_from"):
        name += f" (quality = {p['quality_from']})"
    if p.get("errors"):
        name += " — " + "; ".join(str(e) for e in p["errors"] if e)
    return (f"| {name} | {_f(p['bytes'], ',')} | {_f(p['psnr_avg'])} | {_f(p['ssim_avg'], '.4f')} | "
            f"{_f(p['psnr_10'])} | {_f(p['psnr_100'])} | {_f(p['fit_seconds'], '.0f')} | "
            f"{_f(p['encode_seconds'], '.1f')} | {_f(p['decode_seconds'], '.2f')} | "
            f"{'yes' if p.get('pareto') else ''} | {_rss(p)} |")


def markdown_report(title: str, meta: dict, points: list[dict], extra_sections: Sequence[str] = ()) -> str:
    runs = meta.get("runs") or [{}]
    lines = [f"# {title}", ""]
    m = meta.get("meta", {})
    mach, ver = m.get("machine", {}), m.get("versions", {})
    lines += [
        f"Machine: {mach.get('cpu_count')} CPUs ({mach.get('cpu_model', mach.get('processor', '?'))}), "
        f"{mach.get('memory_gb', '?')} GB; {mach.get('platform', '')}. Versions: "
        + ", ".join(f"{k} {v}" for k, v in ver.items()) + ".",
        f"Seed {m.get('seed')}; load average (1, 5, 15 min) at the start {runs[0].get('loadavg_start')} and at "
        f"the end {runs[-1].get('loadavg_end')}; wall time "
        f"{_f(sum(r.get('wall_seconds') or 0.0 for r in runs), '.0f')} s over {len(runs)} run(s) of this folder "
        "(a re-run reuses the steps already done; every step's own load averages are in the JSON).",
        "",
        "Quality: PSNR / SSIM averaged over the ten resolutions 10%..100% of the 100% reference on the first test "
        "views (count per scene below); render time = mean per view, after one warm-up render. Fit seconds are "
        "training time (setup excluded); encode seconds the `encode` call; decode seconds the container's decode "
        "(leaves regenerated) in a fresh process. Peak RSS per step (its own process). Bytes: the container, the "
        "anchor PLY + weights sidecar, the INRIA PLY or the SPZ file. Pareto: not dominated in (bytes, avg PSNR) "
        "among the scene's points.",
        "",
    ]
    for scene in sorted({p["scene"] for p in points}, key=lambda s: [p["scene"] for p in points].index(s)):
        ps = [p for p in points if p["scene"] == scene]
        spec = m.get("scenes", {}).get(scene, {})
        lines += [f"## {scene}", ""]
        if spec:
            lines += [", ".join(f"{k}: {v}" for k, v in spec.items()), ""]
        main = [p for p in ps if p.get("group") != "encode sweep"]
        lines += ["### Points", "", POINT_HEADER] + [point_row(p) for p in main] + [""]
        sw = {}
        for p in ps:
            for name, label in (p.get("sweeps") or {}).items():
                sw.setdefault(name, []).append((label, p))
        for name, rows in sw.items():
            rows.sort(key=lambda lp: (lp[1].get("sweep_order") or {}).get(name, -1))
            lines += [f"### Sweep: {name}", "", POINT_HEADER]
            lines += [point_row(p, f"{name} {label}" + (" (default)" if p["id"] == "encode default (refit)" else ""))
                      for label, p in rows] + [""]
        timed = [p for p in ps if p.get("render_ms") and _timed(p)]
        if timed:
            xs = sorted({x for p in timed for x in p["render_ms"]}, key=float)
            lines += ["### Render time per resolution (ms, mean per view)", "",
                      "| point | " + " | ".join(f"{float(x) * 100:g}%" for x in xs) + " |",
                      "|---|" + "---:|" * len(xs)]
            lines += [f"| {p['id']} | " + " | ".join(_f(p["render_ms"].get(x), ".1f") for x in xs) + " |"
                      for p in timed] + [""]
        lines += closing_notes(ps) + [""]
    lines += list(extra_sections)
    return "\n".join(lines).rstrip() + "\n"


def closing_notes(ps: list[dict]) -> list[str]:
    """The default's place on the Pareto front and, when measured, the container against SPZ of 3DGS."""
    out = []
    d = next((p for p in ps if p.get("default") and p["kind"] == "container"), None)
    if d is not None and d.get("psnr_avg") is not None:
        if d.get("pareto"):
            out.append(f"- Default settings ({d['id']}): {_f(d['bytes'], ',')} B, {_f(d['psnr_avg'])} dB: "
                       "on the Pareto front.")
        else:
            dom = [p for p in ps if p.get("pareto") and p["bytes"] <= d["bytes"] and p["psnr_avg"] >= d["psnr_avg"]]
            out.append(f"- Default settings ({d['id']}): {_f(d['bytes'], ',')} B, {_f(d['psnr_avg'])} dB: not on "
                       "the Pareto front; dominated by " + ", ".join(
                           f"{p['id']} ({_f(p['bytes'], ',')} B, {_f(p['psnr_avg'])} dB)" for p in dom[:3]) + ".")
    spz = next((p for p in ps if p["kind"] == "spz" and p.get("psnr_avg") is not None), None)
    if d is not None and spz is not None and d.get("bytes") and spz.get("bytes"):
        out.append(f"- Container vs SPZ of the 3DGS baseline: {_f(d['bytes'], ',')} B vs {_f(spz['bytes'], ',')} B "
                   f"({spz['bytes'] / d['bytes']:.2f}x), {_f(d['psnr_avg'])} vs {_f(spz['psnr_avg'])} dB "
                   f"({d['psnr_avg'] - spz['psnr_avg']:+.3f} dB).")
    return ["### Notes", ""] + out if out else []


def _timed(p: dict) -> bool:
    """Points whose render times are shown: everything but the encode sweeps (whose renders equal the default's up
    to quantisation), plus the sweeps' centre; fit-budget points other than the default too."""
    return p.get("group") not in ("encode sweep", "fit budget") or p["id"] == "encode default (refit)"


def _scene_colors(points):
    groups = sorted({p.get("group", p["kind"]) for p in points})
    import matplotlib

    cmap = matplotlib.colormaps["tab10"]
    return {g: cmap(i % 10) for i, g in enumerate(groups)}


def plot_report(points: list[dict], out_dir: Path) -> dict[str, Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    scenes = list(dict.fromkeys(p["scene"] for p in points))
    paths = {"psnr_vs_bytes": out_dir / "psnr_vs_bytes.png", "psnr_vs_time": out_dir / "psnr_vs_time.png",
             "render_time": out_dir / "render_time_vs_resolution.png"}
    colors = _scene_colors(points)

    def scatter(ax, ps, xkey, xlabel, front: bool):
        good = [p for p in ps if p.get(xkey) and p.get("psnr_avg") is not None]
        for g in sorted({p.get("group", p["kind"]) for p in good}):
            sel = [p for p in good if p.get("group", p["kind"]) == g]
            ax.scatter([p[xkey] for p in sel], [p["psnr_avg"] for p in sel], s=22, color=colors[g], label=g,
                       zorder=3)
        if front:
            idx = pareto_front(good, x=xkey)
            ax.plot([good[i][xkey] for i in idx], [good[i]["psnr_avg"] for i in idx], "-", color="0.3", lw=1,
                    zorder=2, label="Pareto front")
            ax.scatter([good[i][xkey] for i in idx], [good[i]["psnr_avg"] for i in idx], s=70, facecolors="none",
                       edgecolors="0.2", zorder=4)
        for p in good:
            if p.get("default"):
                ax.scatter([p[xkey]], [p["psnr_avg"]], marker="*", s=220, color="gold", edgecolors="k", zorder=5,
                           label="default settings")
            if p["kind"] != "container" or p.get("default"):
                ax.annotate(p["id"], (p[xkey], p["psnr_avg"]), fontsize=6, xytext=(3, 3),
                            textcoords="offset points")
        ax.set_xscale("log")
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.set_xlabel(xlabel)
        ax.set_ylabel("avg PSNR 10%..100% (dB)")
        h, lab = ax.get_legend_handles_labels()
        keep = dict(zip(lab, h))
        ax.legend(keep.values(), keep.keys(), fontsize=6, loc="best")

    for key, xkey, xlabel, front in (("psnr_vs_bytes", "bytes", "bytes on disk", True),
                                     ("psnr_vs_time", "production_seconds", "fit + encode time (s)", False)):
        fig, axes = plt.subplots(1, len(scenes), figsize=(6.5 * len(scenes), 4.8), dpi=110, squeeze=False)
        for ax, scene in zip(axes[0], scenes):
            scatter(ax, [p for p in points if p["scene"] == scene], xkey, xlabel, front)
            ax.set_title(f"{scene}: PSNR vs {'bytes' if front else 'fit + encode time'}")
        fig.tight_layout()
        with atomic_write(paths[key]) as fh:
            fig.savefig(fh, format="png")
        plt.close(fig)

    fig, axes = plt.subplots(1, len(scenes), figsize=(6.5 * len(scenes), 4.4), dpi=110, squeeze=False)
    for ax, scene in zip(axes[0], scenes):
        for p in points:
            if p["scene"] != scene or not p.get("render_ms") or not _timed(p):
                continue
            xs = sorted(p["render_ms"], key=float)
            ax.plot([float(x) * 100 for x in xs], [p["render_ms"][x] for x in xs], "o-", ms=3, label=p["id"])
        ax.set_xlabel("resolution (% of the 100% reference)")
        ax.set_ylabel("render time per view (ms)")
        ax.set_yscale("log")
        ax.set_title(f"{scene}: render time vs resolution")
        ax.legend(fontsize=6)
    fig.tight_layout()
    with atomic_write(paths["render_time"]) as fh:
        fig.savefig(fh, format="png")
    plt.close(fig)
    return paths


def write_report(runner: Runner, title: str, points: list[dict], extra_sections: Sequence[str] = (),
                 extra_json: dict | None = None, markdown_name: str = "tradeoff.md") -> dict[str, Path]:
    """Mark the Pareto fronts, then write ``results.json`` (steps, points, meta), the markdown and the plots."""
    mark_pareto(points)
    runner.finish()
    runner.save({"points": points, **(extra_json or {})})
    md = runner.out / markdown_name
    with atomic_write(md, "w") as fh:
        fh.write(markdown_report(title, runner.state, points, extra_sections))
    paths = {"json": runner.path, "markdown": md}
    paths.update(plot_report(points, runner.out))
    return paths


# ================================================================================================ proxycodec bench
def run_bench(scene_ply: str, dataset: str, out_dir: str, *, quick: bool = False, views: int | None = None,
              max_width: int | None = None, test_every: int = 8, sweeps: Sequence[str] | None = None,
              isolate: bool = True, fresh: bool = False, seed: int = 0, backend: str = "auto",
              predictor_iters: int | None = None, log: Callable[[str], None] | None = None) -> dict[str, Path]:
    """``proxycodec bench``: the encode-side sweeps on a user's fitted scene (anchor PLY + weights sidecar)."""
    from .formats.container import read_container
    from .model import weights_path_for

    scene_ply = str(Path(scene_ply).resolve())
    dataset = str(Path(dataset).resolve())
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
    meta = {"kind": "proxycodec.bench", "seed": seed, "quick": quick, "machine": machine_info(),
            "versions": versions(), "encode_knobs_on_every_point": common,
            "scenes": {name: {"scene": scene_ply, "dataset": dataset, "reference width": max_width,
                              "test views evaluated": views, "fit seconds (from the weights file)":
                                  fit_meta.get("seconds")}}}
    runner = Runner(out_dir, meta, isolate=isolate, fresh=fresh, log=log)
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


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if len(argv) == 3 and argv[0] == "--worker":
        print(json.dumps(run_worker(argv[1], json.loads(argv[2])), default=_json_default))
        return 0
    print("usage: python -m proxycodec.bench --worker KIND JSON (internal; see `proxycodec bench`)", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
