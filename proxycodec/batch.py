"""Many scenes through one command: ``proxycodec batch COMMAND INPUTS... --out DIR [COMMAND'S OPTIONS]``.

One task per input. A task is the command itself, run as ``python -m proxycodec.cli COMMAND INPUT -o DIR/NAME ...`` in a
child process (its log in ``DIR/logs/NAME.log``, its peak RSS its own), so a task's output is byte-identical to the
command run alone with the same options and threads. Tasks run on Ray when it is installed (a local Ray started in
this process with the machine's cores, or an existing cluster: ``ray_address``), else one after another here.

A failing task is recorded with its one-line error and never stops the others; a task that crashed (an exit status
other than 0 and the user-error status 2) is retried up to ``retries`` times. A ``fit`` or ``convert`` whose checkpoint
(``DIR/NAME.ckpt.pxc``) exists continues from it (``--resume``), on a retry as on a re-run of an interrupted batch; a
checkpoint made with other options is removed and the task starts afresh. Stopping the batch (Ctrl-C, SIGTERM) stops
the running child with SIGTERM, so a training task writes its checkpoint first. A finished task is identified by a key
(the command, its options and the hash of the input's bytes, a PLY's weights sidecar included): a re-run with the same
key whose output still exists is skipped. Each output is written atomically by the command itself.
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

from . import __version__
from .errors import ProxycodecError
from .fileio import atomic_write, checkpoint_path_for
from .processes import CHILD_GRACE, CTRL_C_GRACE, sigint_raises, sigterm_kept, stop_child

__all__ = ["COMMANDS", "Task", "plan", "run_task", "run_batch", "summary_markdown", "write_summary"]

#: What each command makes of an input (the suffix of its output, or a folder) and where that output goes.
COMMANDS = {"encode": ".pxc", "convert": ".ply", "fit": ".ply", "eval": "_eval"}
#: Exit status of a user error (``cli.common.user_errors``): deterministic, never retried.
USER_ERROR = 2
#: Commands that checkpoint while training and continue with ``--resume``.
RESUMABLE = ("fit", "convert")
#: What a resumed run says when its checkpoint was made with other options (``train``, ``explicit``).
_STALE_CHECKPOINT = "checkpoint was made with different settings"
STATE = ".batch"


@dataclass(frozen=True)
class Task:
    name: str  # unique within the batch: the input's stem (a folder's name), numbered on a collision
    command: str
    input: str
    output: str
    argv: tuple[str, ...]  # the whole command line after ``python -m proxycodec.cli``
    key: str  # command + options + input bytes (+ sidecar) + proxycodec version (threads are not part of it)
    log: str
    threads: int | None = None  # PROXYCODEC_THREADS and NUMBA_NUM_THREADS of the child; None: its own default

    def to_json(self) -> dict:
        return {**asdict(self), "argv": list(self.argv)}


@dataclass
class Progress:
    """One progress bar for the batch, a line per finished task."""

    total: int
    say: Callable[[str], None]
    done: int = 0
    failed: int = 0
    skipped: int = 0
    t0: float = field(default_factory=time.perf_counter)

    def update(self, rec: dict) -> None:
        self.done += 1
        self.failed += rec["status"] == "error"
        self.skipped += rec["status"] == "skipped"
        el = time.perf_counter() - self.t0
        ran = self.done - self.skipped
        eta = el / ran * (self.total - self.done) if ran else 0.0
        width = 20
        bar = "#" * round(width * self.done / self.total) + "-" * (width - round(width * self.done / self.total))
        what = rec["status"] + (f": {rec['error']}" if rec.get("error") else "")
        self.say(f"batch [{bar}] {self.done}/{self.total}  failed {self.failed}  skipped {self.skipped}  "
                 f"{el:6.1f} s  ETA {eta:6.1f} s  | {rec['name']}: {what}")


def _hash_input(path: Path) -> str:
    """SHA-256 of what a task reads: a file (and a PLY's ``.weights.pxc`` sidecar), or every file of a folder
    (relative names and bytes, in sorted order). A missing input hashes as missing: its task reports the error."""
    h = hashlib.sha256()
    if path.is_dir():
        files = sorted(p for p in path.rglob("*") if p.is_file())
        for p in files:
            h.update(str(p.relative_to(path)).encode() + b"\0")
            _hash_file(h, p)
    elif path.is_file():
        _hash_file(h, path)
        side = path.with_name(path.stem + ".weights.pxc")
        if path.suffix == ".ply" and side.is_file():
            h.update(b"\0sidecar\0")
            _hash_file(h, side)
    else:
        h.update(b"missing")
    return h.hexdigest()


def _hash_file(h, path: Path) -> None:
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)


def plan(command: str, inputs: list[str], out_dir: str | os.PathLike, options: list[str], *,
         dataset: str | None = None, threads: int | None = None) -> list[Task]:
    """The tasks of a batch: one per input, outputs named after the inputs in ``out_dir``. ``options``: the
    command's own options, passed through unchanged (they may not name the output: the batch does)."""
    if command not in COMMANDS:
        raise ProxycodecError(f"batch runs {', '.join(COMMANDS)}, not {command!r}")
    if not inputs:
        raise ProxycodecError("batch needs at least one input")
    if any(o in ("-o", "--out") or o.startswith("--out=") for o in options):
        raise ProxycodecError("the batch names every output itself (DIR/NAME): drop the command's -o/--out")
    if command == "eval" and not dataset:
        raise ProxycodecError("batch eval needs --dataset DIR (the dataset every scene is evaluated on)")
    if command != "eval" and dataset:
        raise ProxycodecError("--dataset is for batch eval")
    out = Path(out_dir)
    dataset_hash = _hash_input(Path(dataset)) if dataset else None  # once: every task reads the same dataset
    seen: dict[str, int] = {}
    tasks = []
    for inp in inputs:
        p = Path(inp)
        stem = p.name if p.is_dir() else p.stem
        n = seen.get(stem, 0)
        seen[stem] = n + 1
        name = stem if n == 0 else f"{stem}_{n + 1}"
        suffix = COMMANDS[command]
        output = out / (name + suffix)
        argv = [command, str(p)] + ([str(dataset)] if command == "eval" else []) + ["-o", str(output)] + list(options)
        if command in ("encode", "convert"):
            argv.append("--json")  # the report on stdout: the summary's PSNR
        key_src = {"command": command, "options": list(options), "input": _hash_input(p),
                   "dataset": dataset_hash, "proxycodec": __version__}
        key = hashlib.sha256(json.dumps(key_src, sort_keys=True).encode()).hexdigest()
        tasks.append(Task(name, command, str(p), str(output), tuple(argv), key, str(out / "logs" / f"{name}.log"),
                          threads))
    return tasks


def run_task(task: dict, retries: int = 0) -> dict:
    """Run one task (``Task.to_json()``) in a child process; -> its record: status ok | error, the one-line error,
    seconds, peak RSS (MB), the output's bytes and the PSNR its report gives (where the command measures one)."""
    t = Task(**{**task, "argv": tuple(task["argv"])})
    Path(t.log).parent.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ)
    if t.threads:
        env["PROXYCODEC_THREADS"] = str(t.threads)
        env["NUMBA_NUM_THREADS"] = str(t.threads)
    ckpt = checkpoint_path_for(t.output) if t.command in RESUMABLE and "--resume" not in t.argv else None
    attempts = 0
    resumed = False
    while True:
        attempts += 1
        resume = ckpt is not None and ckpt.exists()
        cmd = [sys.executable, "-m", "proxycodec.cli", *t.argv, *(["--resume"] if resume else [])]
        code, stdout, seconds, rss_kb = _run_child(cmd, env, Path(t.log))
        if resume and code == USER_ERROR and _STALE_CHECKPOINT in Path(t.log).read_text(errors="replace"):
            ckpt.unlink(missing_ok=True)  # made with other options: start afresh (not counted as an attempt)
            attempts -= 1
            continue
        resumed |= resume
        if code in (0, USER_ERROR) or attempts > retries:
            break
    rec = {"name": t.name, "command": t.command, "input": t.input, "output": t.output, "key": t.key,
           "seconds": seconds, "attempts": attempts, "resumed": resumed, "log": t.log, "peak_rss_mb": rss_kb / 1024.0,
           "host": os.uname().nodename}
    if code != 0:
        lines = Path(t.log).read_text(errors="replace").strip().splitlines() or [f"exit {code}"]
        errs = [x for x in lines if x.startswith("error: ")]
        rec.update(status="error", error=(errs[-1][len("error: "):] if errs else lines[-1])[:300], exit_code=code)
        return rec
    rec.update(status="ok", bytes=_output_bytes(Path(t.output)), psnr=_psnr(t.command, Path(t.output), stdout))
    return rec


def _ray_task(task: dict, retries: int = 0) -> dict:
    """``run_task`` as a Ray task, cancellable wherever its worker was started (``processes.sigint_raises``); Ray's
    cancel stops the task's child with SIGTERM at once (no terminal sent it a Ctrl-C to wait for)."""
    with sigint_raises(cancel=True):
        return run_task(task, retries)


def _run_child(cmd: list[str], env: dict, log: Path) -> tuple[int, str, float, int]:
    """(exit status, stdout, seconds, peak RSS in KB of that child alone: ``os.wait4``'s own rusage). Interrupted
    while waiting (Ctrl-C, SIGTERM, Ray's cancel), it stops the child (``processes.stop_child``: a training child
    writes its checkpoint) and raises on."""
    import tempfile

    t0 = time.perf_counter()
    with open(log, "w") as err, tempfile.TemporaryFile("w+") as out:
        p = subprocess.Popen(cmd, stdout=out, stderr=err, text=True, env=env)
        try:
            while True:  # polled, not one blocking wait: Ray cancels a task by raising in its Python thread
                pid, status, usage = os.wait4(p.pid, os.WNOHANG)
                if pid:
                    break
                time.sleep(0.1)
        except BaseException as e:
            stop_child(p, e)
            raise
        p.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0)
        stdout = out.read()
    return p.returncode, stdout, time.perf_counter() - t0, usage.ru_maxrss


def _output_bytes(out: Path) -> int | None:
    if out.is_file():
        side = out.with_name(out.stem + ".weights.pxc")
        return out.stat().st_size + (side.stat().st_size if out.suffix == ".ply" and side.is_file() else 0)
    if out.is_dir():
        return sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    return None


def _psnr(command: str, out: Path, stdout: str) -> dict | None:
    """The PSNR the command's own report gives: encode, the decoded scene against its source (the distillation's
    held-out report, else the measurement behind its choice of path); convert, against the source's renders;
    eval, against the photos (10%..100%)."""
    try:
        if command == "eval":
            s = json.loads((out / "eval.json").read_text()).get("summary", {})
            v = s.get("psnr_avg")
            return None if v is None else {"psnr": v, "against": "the photos, 10%..100%"}
        rep = json.loads(stdout[stdout.index("{"):])
    except (OSError, ValueError):
        return None
    if command == "encode":
        held = (rep.get("distill") or {}).get("held_out") or {}
        if held.get("psnr_same_xi") is not None:
            return {"psnr": held["psnr_same_xi"], "against": "the source, held-out views (distilled)"}
        choice = rep.get("encode_choice") or {}
        if choice.get("measured") is not None:
            return {"psnr": choice["measured"], "against": "the source (encode's choice measurement)"}
        rep = rep.get("convert") or {}  # a 3DGS PLY: its conversion's report
    conv = (rep.get("report") or {}).get("converted") or {}
    return None if conv.get("psnr") is None else {"psnr": conv["psnr"], "against": "the source's renders"}


def _state_path(out: Path, name: str) -> Path:
    return out / STATE / f"{name}.json"


def finished(task: Task) -> dict | None:
    """The record of a task finished before with the same key, whose output still exists."""
    p = _state_path(Path(task.output).parent, task.name)
    try:
        rec = json.loads(p.read_text())
    except (OSError, ValueError):
        return None
    if rec.get("key") == task.key and rec.get("status") == "ok" and Path(task.output).exists():
        return {**rec, "status": "skipped", "skipped": "finished before (same input and options)"}
    return None


def _record(task: Task, rec: dict) -> None:
    if rec["status"] == "ok":
        p = _state_path(Path(task.output).parent, task.name)
        p.parent.mkdir(parents=True, exist_ok=True)
        with atomic_write(p, "w") as fh:
            json.dump(rec, fh, indent=1)


def run_batch(tasks: list[Task], *, use_ray: bool | None = None, ray_address: str | None = None,
              cpus_per_task: float = 1.0, gpus_per_task: float = 0.0, retries: int = 0,
              say: Callable[[str], None] = lambda s: print(s, file=sys.stderr, flush=True)) -> tuple[list[dict], dict]:
    """Run the tasks; -> (their records in input order, how they ran). ``use_ray``: None, Ray when it imports
    (say so otherwise); True: Ray or a user error; False: one after another here."""
    ray = None
    if use_ray is not False:
        if not ray_address:
            local_ray_on_loopback()
        try:
            import ray  # noqa: PLC0415
        except ImportError:
            if use_ray or ray_address:
                raise ProxycodecError("Ray is not installed: pip install -e \".[ray]\" (or drop --ray-address)") \
                    from None
            say("batch: Ray is not installed (pip install -e \".[ray]\"): running the tasks one after another here")
    records: dict[str, dict] = {}
    prog = Progress(len(tasks), say)
    todo = []
    for t in tasks:
        rec = finished(t)
        if rec is not None:
            records[t.name] = rec
            prog.update(rec)
        else:
            todo.append(t)
    how = {"engine": "sequential", "tasks": len(tasks), "ran": len(todo)}
    t0 = time.perf_counter()
    if ray is None:
        for t in todo:
            rec = run_task(t.to_json(), retries)
            _record(t, rec)
            records[t.name] = rec
            prog.update(rec)
    elif todo:
        started_here = not ray.is_initialized()
        if started_here:
            with sigterm_kept():  # Ray's core installs its own handler, which aborts the process
                if ray_address:
                    ray.init(address=ray_address, log_to_driver=False)
                else:
                    ray.init(num_cpus=os.cpu_count(), include_dashboard=False, log_to_driver=False)
        resources = ray.cluster_resources()
        how.update(engine="ray", address=ray_address or "local", nodes=len(ray.nodes()),
                   cluster_cpus=resources.get("CPU"), cluster_gpus=resources.get("GPU", 0.0),
                   cpus_per_task=cpus_per_task, gpus_per_task=gpus_per_task)
        remote = ray.remote(num_cpus=cpus_per_task, num_gpus=gpus_per_task, max_retries=retries)(_ray_task)
        # a task's threads: its CPUs on Ray unless given (Ray runs as many tasks at once as the CPUs allow)
        threads = max(1, int(cpus_per_task))
        pending = {remote.remote({**t.to_json(), "threads": t.threads or threads}, retries): t for t in todo}
        try:
            while pending:
                done, _ = ray.wait(list(pending), num_returns=1)
                t = pending.pop(done[0])
                try:
                    rec = ray.get(done[0])
                except Exception as e:  # noqa: BLE001 - a worker lost for good: this task fails, the others go on
                    rec = {"name": t.name, "command": t.command, "input": t.input, "output": t.output,
                           "status": "error", "error": f"the Ray task failed: {type(e).__name__}: {e}"[:300]}
                _record(t, rec)
                records[t.name] = rec
                prog.update(rec)
        except BaseException:  # Ctrl-C, SIGTERM: the running tasks stop their children (who keep a checkpoint)
            for ref in pending:
                ray.cancel(ref)  # a KeyboardInterrupt in the task: ``_run_child`` hands it on (``stop_child``)
            ray.wait(list(pending), num_returns=len(pending), timeout=CHILD_GRACE + CTRL_C_GRACE + 10.0)
            raise
        finally:
            if started_here:
                ray.shutdown()
    how["wall_seconds"] = time.perf_counter() - t0
    return [records[t.name] for t in tasks], how


def local_ray_on_loopback() -> None:
    """A Ray started here for this machine alone listens on 127.0.0.1, not on the machine's network address: Ray
    picks its node address once, when it is imported, from ``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER`` (off: the loopback
    address, as on macOS). A Ray already imported, or that variable already set, is left as it is."""
    import sys  # noqa: PLC0415

    if "ray" not in sys.modules:
        os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")


def summary_markdown(records: list[dict], how: dict) -> str:
    lines = [f"# proxycodec batch: {how['tasks']} tasks ({how['ran']} run, on {how['engine']}"
             + (f", {how.get('nodes')} node(s), {how.get('cluster_cpus'):g} CPUs" if how["engine"] == "ray" else "")
             + f"; {how['wall_seconds']:.1f} s)", "",
             "| input | status | output | bytes | PSNR dB | against | seconds | peak RSS MB | error |",
             "|---|---|---|---:|---:|---|---:|---:|---|"]
    for r in records:
        ps = r.get("psnr") or {}
        lines.append(f"| {r['input']} | {r['status']} | {Path(r['output']).name} | "
                     f"{'' if r.get('bytes') is None else format(r['bytes'], ',')} | "
                     f"{'' if ps.get('psnr') is None else format(ps['psnr'], '.2f')} | {ps.get('against', '')} | "
                     f"{'' if r.get('seconds') is None else format(r['seconds'], '.1f')} | "
                     f"{'' if r.get('peak_rss_mb') is None else format(r['peak_rss_mb'], '.0f')} | "
                     f"{r.get('error', '')} |")
    return "\n".join(lines) + "\n"


def write_summary(out_dir: str | os.PathLike, records: list[dict], how: dict) -> dict[str, Path]:
    out = Path(out_dir)
    paths = {"json": out / "batch.json", "markdown": out / "batch.md"}
    with atomic_write(paths["json"], "w") as fh:
        json.dump({"how": how, "tasks": records}, fh, indent=1)
    with atomic_write(paths["markdown"], "w") as fh:
        fh.write(summary_markdown(records, how))
    return paths
