"""Runs the steps of a benchmark and records them in ``results.json``; each step in a Python subprocess of its own
(``python -m proxycodec.bench --worker KIND JSON``: :func:`main` is that worker), so that its peak RSS is its own.
Also what a run records about the machine and the software."""

from __future__ import annotations

import json
import os
import platform
import re
import shutil
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..fileio import atomic_write
from ..threads import set_threads
from .steps import load_avg, run_worker

RESULTS = "results.json"
RESULTS_VERSION = 1


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

    from .. import __version__

    v = {"proxycodec": __version__, "python": platform.python_version(), "torch": torch.__version__,
         "numpy": numpy.__version__, "numba": numba.__version__, "zstandard": zstandard.__version__}
    node = shutil.which("node")
    if node:
        try:
            v["node"] = subprocess.run([node, "--version"], capture_output=True, text=True, timeout=20).stdout.strip()
        except (OSError, subprocess.TimeoutExpired):  # pragma: no cover
            pass
    return v


def safe_name(sid: str) -> str:
    """``sid`` as a file name."""
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
                                   "loadavg_start": load_avg(), "isolate": isolate})
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
        logf = self.logs / f"{safe_name(sid)}.log"
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
        self.state["runs"][-1].update(loadavg_end=load_avg(), wall_seconds=time.time() - self.t0)
        self.save()


def _json_default(o):
    """``json.dump``'s ``default``: numpy scalars, paths and tuples."""
    if isinstance(o, (np.generic,)):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    if isinstance(o, tuple):
        return list(o)
    raise TypeError(f"not JSON-serialisable: {type(o).__name__}")


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if len(argv) == 3 and argv[0] == "--worker":
        set_threads()  # the count the parent chose reaches this process through the environment
        print(json.dumps(run_worker(argv[1], json.loads(argv[2])), default=_json_default))
        return 0
    print("usage: python -m proxycodec.bench --worker KIND JSON (internal; see `proxycodec bench`)", file=sys.stderr)
    return 2

