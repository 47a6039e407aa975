"""Runs the steps of a benchmark and records them in ``results.json``; each step in a Python subprocess of its own
(``python -m proxycodec.bench --worker KIND JSON``: :func:`main` is that worker), so that its peak RSS is its own.
Also what a run records about the machine and the software."""

from __future__ import annotations

import hashlib
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
from ..processes import stop_child, stop_on_sigterm
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


def code_key() -> str:
    """What the code that runs a step is: a SHA-1 (16 hex digits) of the package's Python sources (``proxycodec``,
    with ``formats`` and ``cli``; paths and contents), so that a step recorded by other code is run again, and a
    change outside the package (a benchmark script, a document) keeps the steps."""
    import importlib.util

    h = hashlib.sha1()
    for name in ("proxycodec", "proxycodec.formats", "proxycodec.cli"):
        # found, not imported: the library never imports the CLI
        root = Path(importlib.util.find_spec(name).submodule_search_locations[0])
        for f in sorted(root.rglob("*.py")):
            if "__pycache__" in f.parts:
                continue
            rel = f.relative_to(root)
            if name == "proxycodec" and rel.parts[0] in ("formats", "cli", "tests", "benchmarks"):
                continue  # installed copies keep formats/ and cli/ inside: hashed under their own names
            h.update(f"{name}/{rel.as_posix()}\0".encode())
            h.update(f.read_bytes())
    return h.hexdigest()[:16]


class Runner:
    """Runs steps (each in a fresh subprocess unless ``isolate`` is False) and records them in ``results.json``.

    A step already recorded as done with the same arguments by the same code (``code_key``), whose ``outputs`` still
    exist, is not run again; ``any_code`` reuses what other code recorded too.
    """

    def __init__(self, out_dir: str | os.PathLike, meta: dict, *, isolate: bool = True, fresh: bool = False,
                 log: Callable[[str], None] | None = None, ray: "RaySteps | None" = None, any_code: bool = False):
        self.code = code_key()
        self.any_code = bool(any_code)
        self.out = Path(out_dir)
        self.out.mkdir(parents=True, exist_ok=True)
        self.work = self.out / "work"
        self.logs = self.out / "logs"
        self.work.mkdir(exist_ok=True)
        self.logs.mkdir(exist_ok=True)
        self.path = self.out / RESULTS
        self.isolate = isolate
        # with Ray, ``step`` only collects the steps a pass asks for (``run_in_waves`` runs them as Ray tasks)
        self.ray = ray
        self.collecting = False
        self.pending: dict[str, tuple] = {}
        self.attempted: set[str] = set()
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
                                   "loadavg_start": load_avg(), "isolate": isolate, "code": self.code})
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
                and (self.any_code or rec.get("code") == self.code) and all(Path(o).exists() for o in outputs)):
            return rec
        if self.collecting:
            if sid in self.attempted:  # ran (and failed) in an earlier wave of this run: as the runner reports it
                return rec
            self.pending[sid] = (kind, args, [str(o) for o in outputs], timeout, self._inputs_ready(args))
            return {"status": "pending", "result": {}}
        self.log(f"[{time.strftime('%H:%M:%S')}] {sid} ...")
        t0 = time.perf_counter()
        if self.isolate:
            rec = self._spawn(sid, kind, args, timeout)
        else:
            try:
                rec = {"status": "ok", "result": run_worker(kind, args), "rss_scope": "shared process"}
            except Exception as e:  # noqa: BLE001 - as a failed subprocess would: record it, go on
                rec = {"status": "error", "error": f"{type(e).__name__}: {e}"}
        rec.update(kind=kind, args=args, seconds=time.perf_counter() - t0, code=self.code,
                   finished=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()))
        if rec["status"] == "ok" and "skipped" in rec.get("result", {}):
            rec["status"] = "skipped"
        self.state["steps"][sid] = rec
        self.save()
        msg = rec.get("error") or rec.get("result", {}).get("skipped") or ""
        self.log(f"[{time.strftime('%H:%M:%S')}] {sid}: {rec['status']} in {rec['seconds']:.1f} s {msg}".rstrip())
        return rec

    def _spawn(self, sid: str, kind: str, args: dict, timeout: float) -> dict:
        return spawn_step(str(self.logs / f"{safe_name(sid)}.log"), kind, args, timeout)

    def _inputs_ready(self, args: dict) -> bool:
        """Whether the files a step reads exist: every argument that names a path in this run's folder, except
        the step's outputs (``out``, ``back``), must (a step reading another's output waits for a later wave)."""
        root = str(self.out.resolve())

        def paths(v):
            if isinstance(v, dict):
                for k, x in v.items():
                    if k not in ("out", "back"):
                        yield from paths(x)
            elif isinstance(v, list):
                for x in v:
                    yield from paths(x)
            elif isinstance(v, str) and (os.path.isabs(v) or os.sep in v):
                yield v

        return all(Path(v).exists() for v in paths(args) if str(Path(v).resolve()).startswith(root))

    def run_in_waves(self, plan_pass: Callable[[], Any]) -> Any:
        """Run a benchmark whose steps ``plan_pass`` asks for, as Ray tasks (``self.ray``): each pass collects the
        steps not done yet; those whose input files exist run at once, in parallel, and are recorded as
        ``step`` records them (the same cache); passes repeat until one asks for nothing new; then a last pass
        runs with every step cached and returns ``plan_pass``'s result. Without Ray: one ordinary pass."""
        if self.ray is None:
            return plan_pass()
        while True:
            self.collecting, self.pending = True, {}
            try:
                plan_pass()
            finally:
                self.collecting = False
            ready = {sid: p for sid, p in self.pending.items() if p[4]}
            if not self.pending:
                break
            if not ready:
                raise RuntimeError("steps wait for files no step makes: " + ", ".join(sorted(self.pending)))
            for sid, rec in self.ray.run(self, ready).items():
                self.attempted.add(sid)
                rec["code"] = self.code
                self.state["steps"][sid] = rec
                self.log(f"[{time.strftime('%H:%M:%S')}] {sid}: {rec['status']} in {rec['seconds']:.1f} s on "
                         f"{rec.get('host')} {rec.get('error') or ''}".rstrip())
            self.save()
        return plan_pass()

    def finish(self) -> None:
        self.state["runs"][-1].update(loadavg_end=load_avg(), wall_seconds=time.time() - self.t0)
        self.save()


def spawn_step(logf: str, kind: str, args: dict, timeout: float) -> dict:
    """One step in a fresh ``python -m proxycodec.bench --worker`` process (its stderr in ``logf``): its record."""
    cmd = [sys.executable, "-m", "proxycodec.bench", "--worker", kind, json.dumps(args)]
    with open(logf, "w") as err, subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=err, text=True) as p:
        try:
            stdout, _ = p.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            p.kill()
            p.communicate()
            return {"status": "error", "error": f"timeout after {timeout:.0f} s (log: {logf})"}
        except BaseException as e:  # Ctrl-C, SIGTERM: the worker stops too (a fit step writes its checkpoint)
            stop_child(p, e)
            raise
    if p.returncode != 0:
        tail = Path(logf).read_text(errors="replace").strip().splitlines()[-1:] or ["?"]
        return {"status": "error", "error": f"exit {p.returncode}: {tail[0][-300:]} (log: {logf})"}
    try:
        return {"status": "ok", "result": json.loads(stdout.strip().splitlines()[-1]), "rss_scope": "own process"}
    except (ValueError, IndexError):
        return {"status": "error", "error": f"no result from the worker (log: {logf})"}


def _ray_step(logf: str, sid: str, kind: str, args: dict, timeout: float) -> dict:
    """A Ray task: ``spawn_step`` with where and when it ran."""
    t0, start = time.perf_counter(), time.time()
    rec = spawn_step(logf, kind, args, timeout)
    rec.update(kind=kind, args=args, seconds=time.perf_counter() - t0, started_at=start, ended_at=time.time(),
               host=os.uname().nodename, finished=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()))
    if rec["status"] == "ok" and "skipped" in rec.get("result", {}):
        rec["status"] = "skipped"
    return rec


class RaySteps:
    """Where ``Runner.run_in_waves`` runs its steps: a Ray cluster (``address``; None: a local Ray started here with
    this machine's cores), each step reserving ``cpus_per_step`` CPUs (default: a whole node's, so that timed steps
    never share a machine's cores; fewer run several steps on one node, and each record then names the steps that
    overlapped it on its host: ``shared_host_with``)."""

    def __init__(self, address: str | None = None, cpus_per_step: float | None = None):
        if not address:
            from ..batch import local_ray_on_loopback  # noqa: PLC0415

            local_ray_on_loopback()
        import ray  # noqa: PLC0415

        self.ray = ray
        if not ray.is_initialized():
            if address:
                ray.init(address=address, log_to_driver=False)
            else:
                ray.init(num_cpus=os.cpu_count(), include_dashboard=False, log_to_driver=False)
        per_node = [n["Resources"].get("CPU", 0) for n in ray.nodes() if n.get("Alive")]
        self.cpus_per_step = float(cpus_per_step or max(per_node or [1.0]))
        self.info = {"address": address or "local", "nodes": len(per_node), "cpus_per_node": per_node,
                     "cpus_per_step": self.cpus_per_step}

    def run(self, runner: "Runner", steps: dict[str, tuple]) -> dict[str, dict]:
        task = self.ray.remote(num_cpus=self.cpus_per_step)(_ray_step)
        refs = {sid: task.remote(str(runner.logs / f"{safe_name(sid)}.log"), sid, kind, args, timeout)
                for sid, (kind, args, _, timeout, _) in steps.items()}
        for sid in refs:
            runner.log(f"[{time.strftime('%H:%M:%S')}] {sid} ... (Ray)")
        out = {sid: self.ray.get(ref) for sid, ref in refs.items()}
        for sid, rec in out.items():
            rec["ray"] = dict(self.info)
            rec["shared_host_with"] = sorted(
                o for o, r in out.items() if o != sid and r.get("host") == rec.get("host")
                and r["started_at"] < rec["ended_at"] and rec["started_at"] < r["ended_at"])
        return out


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
        stop_on_sigterm()  # stopped by its parent (``spawn_step``): a fit step writes its checkpoint
        print(json.dumps(run_worker(argv[1], json.loads(argv[2])), default=_json_default))
        return 0
    print("usage: python -m proxycodec.bench --worker KIND JSON (internal; see `proxycodec bench`)", file=sys.stderr)
    return 2

