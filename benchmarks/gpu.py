"""GPU run: proxycodec's CLI and rasterizer on one NVIDIA H100/H200, in one call of at most 10 minutes.

    bash .device/bootstrap.sh && export PYTHONPATH=/tmp/site && python benchmarks/gpu.py --out $OUT
    python benchmarks/gpu.py --device cpu --smoke --stages b,c --threads 1 --out /tmp/gpu_smoke  # on a CPU

Stages (benchmarks/README.md, "GPU runs"), in the order --stages gives (default: the acceptance figures first):
  a  pytest -m cuda
  b  lego fit at 400 px under --budget-lego, eval at 10%..100%; iterations/s against the 2-core CPU
  c  encode of the lego fit as fitted, decode at 30%, stats; its distillation (--refit-predictor --distill, timed)
     and the distilled container's eval
  d  bonsai fit at 800 px under --budget-bonsai, eval at 10%..100%
  e  plain 3DGS fit of lego (--explicit), convert, encode
  f  render command; in-process micro-benchmark: torch projection + cuda compositor against the reference, and
     the projection alone, ours against gsplat's fused one, on the same Gaussians
  g  plain 3DGS (fit --explicit) on bonsai for stage d's budget, eval at 10%..100%, ours minus it per size, its SPZ
  n  encode of stage d's fit as fitted (the container stage g's SPZ is compared with), stats
  p  torch.profiler over training steps in this process (ours in stage 1 and 2 at bonsai's density, 800 px; plain
     3DGS): wall and device-busy ms per step, kernel launches, the operations with the most host and device time
  v  conversion of stage g's bonsai 3DGS PLY (bonsai's training cameras in a cameras.json beside it) under
     --budget-convert, then encode: iterations/s against the 2-core CPU's, the held-out PSNR against the source's
     renders, bytes against the SPZ
  x  stage d at the former default density (fit --voxel-rule extent) for d's budget, eval at 10%..100%, stage d
     minus it per size (stage d fits at the default, Scaffold-GS's density, since 2026-11-27), encode
Stage d copies its fitted PLY and weights, and stages n, v and x their containers, into OUT/fits/ (the PLY in parts of
at most 15 MiB, the device tool's limit per file: `cat bonsai.ply.part* > bonsai.ply`), to be evaluated and
encoded on a CPU.
Each stage has its own wall-clock limit and the run a total deadline (later stages are then skipped); a failing
stage is recorded and the next one runs. gpu.json, gpu.md and logs.tar.gz are rewritten after every stage.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import platform
import re
import resource
import shutil
import signal
import subprocess
import sys
import tarfile
import tempfile
import threading
import time
import traceback
from importlib import metadata
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
LEGO_RES = "0.1,0.2,0.3,0.4,0.5,0.6,0.7,0.8,0.9,1.0"

# The 2-core CPU figures the stages are compared with (benchmarks/README.md, the section named in "source").
CPU = {
    "lego_fit": {"iterations": 10220, "seconds": 1014, "source": '"The 100% gap", confirmation table, old '
                 "defaults: 10,220 iterations in 16:54 (2 threads, alone; the fastest 400 px lego fit recorded)"},
    "lego_psnr": {"psnr_avg": 30.146, "source": '"The 100% gap": the new defaults at 10,220 iterations'},
    "lego_distill": {"seconds": 1419, "source": "\"encode's choice of path\": lego's default encode (distilled, "
                     "3600 iterations) 23:39 wall beside other jobs; \"Distillation's target rules\": 304.6 ms "
                     "per iteration in steady state (18.3 min for 3600)"},
    "bonsai_fit": {"iterations": 3598, "seconds": 1200, "source": "Measurement log 2026-11-26: 3,598 iterations "
                   "in 20:00 at 400 px (no 800 px figure on the rebuilt poses yet)"},
    "convert": {"iterations": 4000, "seconds": 583, "source": '"3DGS PLY conversion", conversion settings: spread, '
                "context 4, no warm-up: training 583 s for 4000 iterations"},
    "convert_bonsai": {"iterations": 8154, "seconds": 2400, "psnr_report": 28.62,
                       "source": '"Against training time": bonsai\'s 600-s 3DGS PLY (299,732 Gaussians) converted for '
                                 "2,400 s at 800 px: 8,154 iterations, 28.62 dB against the source's renders (4 "
                                 "views); 40,752 iterations in 13,000 s: 29.76 (4 views), 29.99 in its own report"},
    "raster": {"ms": 196, "source": 'SPEC.md section 2 ("Rasterizer"): numba cpu backend, 100k Gaussians at '
               "400 px, forward + backward"},
}
# The last GPU run of each stage's fit (benchmarks/README.md, "GPU runs"): whether a change to the training
# step shows on the device. Compared as it/s; marked as not comparable when this run's GPU is another.
GPU_BEFORE = {
    "bonsai_fit": {"iterations": 3794, "seconds": 140, "gpu": "NVIDIA H200", "commit": "abe4079",
                   "source": "stage d at commit abe4079: 27.1 it/s, 79,740 -> 101,897 anchors (18.74 it/s on an "
                             "H100 at a77e52d)"},
    "bonsai_3dgs": {"iterations": 12668, "seconds": 140, "gpu": "NVIDIA H200", "commit": "abe4079",
                    "source": "stage g at commit abe4079: 90.49 it/s, 299,784 Gaussians (62.98 it/s on an H100 at "
                              "a77e52d)"},
    "bonsai_extent": {"iterations": 4176, "seconds": 140, "gpu": "NVIDIA H200", "commit": "abe4079",
                      "source": "stage x's commands at commit abe4079: 29.8 it/s, 27,246 anchors (23.07 it/s on an "
                                "H100 at a77e52d)"},
}
DONE = re.compile(r"done: (\d+) iterations in ([\d:]+)")
PROG = re.compile(r"it\s+(\d+)/(\S+)\s+loss\s+([-\d.naif]+)\s+psnr\s+([-\d.naif]+).*?([\d:]+) elapsed")
DISTILL_DONE = re.compile(r"distill: (\d+) iterations in ([\d:]+) \(([\d.]+) s")


class Skip(Exception):
    """A stage that cannot run (no data, no time left, an earlier stage's output missing)."""


def secs(text: str) -> int:
    s = 0
    for part in text.split(":"):
        s = s * 60 + int(part)
    return s


def machine_facts(args) -> dict:
    m = {"python": platform.python_version(), "platform": platform.platform(), "cpu_count": os.cpu_count(),
         "usable_cores": len(os.sched_getaffinity(0)), "device": args.device, "seed": args.seed,
         "loadavg_start": os.getloadavg(), "started": time.strftime("%Y-%m-%d %H:%M:%S %Z"), "commit": args.commit}
    for pkg in ("torch", "gsplat", "numpy", "numba", "proxycodec"):
        try:
            m[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            m[pkg] = None
    if m["commit"] is None:
        try:
            m["commit"] = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                                         timeout=10, check=False).stdout.strip() or None
        except (OSError, subprocess.SubprocessError):
            pass
    try:
        import torch

        m["torch_cuda"], m["cuda_available"] = torch.version.cuda, torch.cuda.is_available()
        if m["cuda_available"]:
            p = torch.cuda.get_device_properties(0)
            m["gpu"], m["gpu_memory_gib"] = p.name, round(p.total_memory / 2**30, 1)
    except Exception as e:  # noqa: BLE001 - recorded, not fatal
        m["torch_error"] = f"{type(e).__name__}: {e}"
    return m


def gpu_sampler(peak: list, stop: threading.Event) -> None:
    """nvidia-smi's memory.used (MiB, the whole device), once a second, into peak[0], until ``stop``."""
    while not stop.is_set():
        try:
            out = subprocess.run(["nvidia-smi", "--query-gpu=memory.used", "--format=csv,noheader,nounits"],
                                 capture_output=True, text=True, timeout=5, check=False).stdout.split()
            peak[0] = max([int(x) for x in out] + ([peak[0]] if peak[0] is not None else []), default=None)
        except (OSError, ValueError, subprocess.SubprocessError):
            return
        stop.wait(1.0)


class Run:
    def __init__(self, args):
        self.args, self.t0, self.stage_end = args, time.monotonic(), float("inf")
        self.out, self.work = Path(args.out).resolve(), Path(args.work).resolve()
        self.logs = self.work / "logs"  # packed into OUT/logs.tar.gz: the device tool returns at most 8 files
        for d in (self.out, self.logs):
            d.mkdir(parents=True, exist_ok=True)
        self.res = {"machine": machine_facts(args), "args": vars(args), "cpu_reference": CPU,
                    "gpu_before": GPU_BEFORE, "stages": {}}

    def say(self, msg: str) -> None:
        print(f"[gpu.py {time.monotonic() - self.t0:5.0f} s] {msg}", file=sys.stderr, flush=True)

    def left(self) -> float:
        return min(self.args.deadline - (time.monotonic() - self.t0), self.stage_end - time.monotonic())

    def data(self, name: str) -> Path:
        kit, shared = {"lego": ("lego400", "nerf_synthetic/lego"), "bonsai": ("bonsai", "mipnerf360/bonsai")}[name]
        for p in (Path(self.args.data) / kit, Path(self.args.data) / name, ROOT.parent / "shared/data" / shared):
            if p.is_dir():
                return p.resolve()
        raise Skip(f"no {name} data under {self.args.data} nor ../shared/data/{shared}")

    def sh(self, name: str, cmd: list, timeout: float, env: dict | None = None) -> dict:
        """Run ``cmd`` in the work folder (so the checkout's proxycodec/ never shadows an installed one), stdout
        and stderr to WORK/logs/NAME.out|err; -> rc, seconds, the child's peak RSS, peak GPU memory; texts under _out,
        _err. Past ``timeout`` (cut to the time left) its process group gets SIGTERM, then SIGKILL."""
        if self.left() < 3:
            raise Skip(f"{name}: no time left")
        timeout = min(timeout, self.left())
        cmd = [str(c) for c in cmd]
        self.say(f"{name}: {' '.join(cmd[2:] if cmd[1:2] == ['-m'] else cmd)} (limit {timeout:.0f} s)")
        peak, stop = [None], threading.Event()
        if shutil.which("nvidia-smi") and self.args.device != "cpu":
            threading.Thread(target=gpu_sampler, args=(peak, stop), daemon=True).start()
        so, se = self.logs / f"{name}.out", self.logs / f"{name}.err"
        t, timed_out, kill_at = time.monotonic(), False, None
        with open(so, "w") as fo, open(se, "w") as fe:
            p = subprocess.Popen(cmd, cwd=self.work, stdout=fo, stderr=fe, start_new_session=True, env=env)
            while True:
                pid, status, ru = os.wait4(p.pid, os.WNOHANG)  # wait4: this child's own peak RSS
                if pid:
                    break
                now = time.monotonic()
                if not timed_out and now - t > timeout:
                    timed_out, kill_at = True, now + 10
                    os.killpg(p.pid, signal.SIGTERM)
                elif kill_at is not None and now > kill_at:
                    os.killpg(p.pid, signal.SIGKILL)
                    kill_at = None
                time.sleep(0.1)
            p.returncode = os.waitstatus_to_exitcode(status)
        stop.set()
        r = {"cmd": " ".join(cmd), "rc": p.returncode, "seconds": round(time.monotonic() - t, 2),
             "timed_out": timed_out, "peak_rss_mb": round(ru.ru_maxrss / 1024, 1), "gpu_mem_peak_mib": peak[0],
             "_out": so.read_text(errors="replace"), "_err": se.read_text(errors="replace")}
        self.say(f"{name}: rc {r['rc']}{' (timed out)' if timed_out else ''} in {r['seconds']:.1f} s")
        return r

    def cli(self, name: str, argv: list, timeout: float) -> dict:
        cmd = [sys.executable, "-m", "proxycodec.cli"] + (["--threads", self.args.threads] if self.args.threads
                                                           else [])
        return self.sh(name, cmd + ["--device", self.args.device] + argv, timeout)

    def fit_budget(self, budget: float, reserve: float) -> int:
        """A fit's --time-budget, cut to what the stage and the deadline leave after ``reserve`` seconds."""
        t = min(budget, self.left() - reserve)
        if t < (5 if self.args.smoke else 20):
            raise Skip(f"{max(t, 0):.0f} s left for a {budget:.0f}-s fit")
        return round(t)

    def stage(self, key: str, title: str, fn, limit: float) -> None:
        rec = self.res["stages"][key] = {"title": title, "status": "running"}
        t = time.monotonic()
        if self.args.deadline - (t - self.t0) < 10:
            rec.update(status="skipped", reason="total deadline reached", seconds=0)
            return self.save()
        self.stage_end = t + limit
        self.say(f"stage {key}: {title} (limit {self.left():.0f} s)")
        try:
            fn(self, rec)
            rec["status"] = "ok"
        except Skip as e:
            rec.update(status="skipped", reason=str(e))
        except Exception as e:  # noqa: BLE001 - one stage's failure must not lose the others
            rec.update(status="failed", error=f"{type(e).__name__}: {e}", traceback=traceback.format_exc()[-2000:])
        self.stage_end = float("inf")
        rec["seconds"] = round(time.monotonic() - t, 1)
        self.say(f"stage {key}: {rec['status']} in {rec['seconds']} s {rec.get('reason') or rec.get('error') or ''}")
        self.save()

    def save(self) -> None:
        self.res["elapsed_s"] = round(time.monotonic() - self.t0, 1)
        self.res["peak_rss_mb"] = {"self": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                                   "children_max": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024}
        torch = sys.modules.get("torch")
        if torch is not None and torch.cuda.is_available() and torch.cuda.is_initialized():
            self.res["gpu_max_memory_allocated_mb"] = round(torch.cuda.max_memory_allocated() / 2**20, 1)
        for name, text in (("gpu.json", json.dumps(self.res, indent=2, default=str)), ("gpu.md", markdown(self.res))):
            (self.out / f"{name}.tmp").write_text(text)
            os.replace(self.out / f"{name}.tmp", self.out / name)
        with tarfile.open(self.out / "logs.tar.gz.tmp", "w:gz") as tar:
            tar.add(self.logs, arcname="logs")
        os.replace(self.out / "logs.tar.gz.tmp", self.out / "logs.tar.gz")


def check(r: dict) -> None:
    if r["rc"] != 0:
        tail = (r["_err"].strip() or r["_out"].strip())[-1500:]
        raise RuntimeError(f"rc {r['rc']}{' (timed out)' if r['timed_out'] else ''}: "
                           f"{(tail.splitlines() or [''])[-1]}\n{tail}")


def brief(r: dict) -> dict:
    return {k: v for k, v in r.items() if not k.startswith("_")}


def json_out(r: dict) -> dict:
    return json.loads(r["_out"][r["_out"].index("{"):])


def parse_fit(r: dict) -> dict:
    """Iterations, training seconds (the `done:` line, else the last progress line), it/s, anchors or Gaussians."""
    text = r["_out"] + r["_err"]
    prog = [(int(m[1]), float(m[3]), float(m[4]), secs(m[5])) for m in PROG.finditer(text)]
    f = dict(brief(r), progress=[{"it": i, "loss": lo, "psnr": ps, "elapsed_s": e} for i, lo, ps, e in prog[-3:]])
    done = DONE.search(text)
    if done:
        f["iterations"], f["train_seconds"] = int(done[1]), secs(done[2])
    elif prog:
        f["iterations"], f["train_seconds"] = prog[-1][0], prog[-1][3]
    if f.get("train_seconds"):
        f["it_per_s"] = round(f["iterations"] / f["train_seconds"], 2)
    if len(prog) >= 3 and prog[-1][3] > prog[1][3]:  # from the second progress line on: past the first steps
        f["it_per_s_steady"] = round((prog[-1][0] - prog[1][0]) / (prog[-1][3] - prog[1][3]), 2)
    m = re.search(r"\((\d+) (anchors|Gaussians)", r["_out"])
    if m:
        f[m[2].lower()] = int(m[1])
    return f


def run_eval(R: Run, name: str, scene: Path, data: Path, res: str, extra=()) -> dict:
    out = R.work / f"{name}_report"
    r = R.cli(name, ["eval", scene, data, "-o", out, "--res", res, *extra] + (["--views", 1] if R.args.smoke else []),
              600)
    check(r)
    j = json.loads((out / "eval.json").read_text())
    per = {f"{d['xi']:g}": {"psnr": d["psnr"], "ssim": d["ssim"], "render_ms": round(d["seconds"] * 1e3, 2),
                            "gaussians": d["gaussians"]} for d in j["per_resolution"]}
    mean = sum(d["psnr"] for d in per.values()) / len(per)  # = psnr_avg when --res is 10%..100%
    return dict(brief(r), psnr_avg=j["summary"]["psnr_avg"], psnr_mean=mean, ssim_avg=j["summary"]["ssim_avg"],
                views=j["summary"]["views"], per_resolution=per)


def eval_text(ev: dict) -> str:
    per = ev["per_resolution"]
    ends = ", ".join(f"{k}: {per[k]['psnr']:.2f} dB {per[k]['render_ms']:.1f} ms"
                     for k in list(per)[:: len(per) - 1 or 1])
    return f"PSNR {ev['psnr_mean']:.3f} dB (mean of {len(per)} sizes, {ev['views']} views; {ends})"


# --------------------------------------------------------------------------------------------------- stages
def stage_a(R: Run, rec: dict) -> None:
    # tests import `tests.test_codec`: the checkout goes on the path, after an installed proxycodec (/tmp/site)
    path = os.pathsep.join(filter(None, [os.environ.get("PYTHONPATH"), str(ROOT)]))
    r = R.sh("a_pytest", [sys.executable, "-m", "pytest", "-q", "-m", "cuda", ROOT / "tests", "-p",
                          "no:cacheprovider"], 300, env=dict(os.environ, PYTHONPATH=path))
    counts = {k: int(n) for n, k in re.findall(r"(\d+) (passed|failed|skipped|deselected|errors?|xfailed|xpassed)",
                                               r["_out"].strip()[-400:])}
    rec.update(brief(r), counts=counts, tail=r["_out"][-2500:])
    rec["key"] = ", ".join(f"{n} {k}" for k, n in counts.items()) or "no summary line"
    if r["rc"] not in (0, 5):  # 5: no test carries the marker
        raise RuntimeError(f"pytest rc {r['rc']}: {rec['key']}")


def fit(R: Run, rec: dict, name: str, data: Path, ply: Path, width: int, budget: float, extra=(),
        reserve: float = 60) -> dict:
    """``proxycodec fit`` under a time budget cut to leave ``reserve`` s (smoke: less) of the stage after it."""
    ply.unlink(missing_ok=True)
    t = R.fit_budget(budget, min(reserve, 25) if R.args.smoke else reserve)
    r = R.cli(name, ["fit", data, "-o", ply, "--max-width", width, "--time-budget", t, "--seed", R.args.seed,
                     *extra], t + 150)
    rec["fit"] = dict(parse_fit(r), budget_s=t, data=str(data))
    check(r)
    if "it_per_s" not in rec["fit"]:
        raise RuntimeError("the fit printed no `done:` or progress line")
    return rec["fit"]


def fit_eval(R: Run, rec: dict, key: str, scene: str, width: int, budget: float, res: str) -> dict:
    """stage b (lego) and d (bonsai): fit under a time budget, iterations/s against the CPU's, eval."""
    data, ply = R.data(scene), R.work / f"{scene}.ply"
    f = fit(R, rec, f"{key}_fit", data, ply, width, budget)
    cpu = CPU[f"{scene}_fit"]["iterations"] / CPU[f"{scene}_fit"]["seconds"]
    x = f["it_per_s"] / cpu
    rec["vs_cpu"] = {"cpu_it_per_s": round(cpu, 2), "ratio": round(x, 2)}
    rec["key"] = (f"{f['iterations']:,} it in {f['train_seconds']} s = **{f['it_per_s']} it/s** at {width} px, "
                  f"{f.get('anchors', '?')} anchors")
    rec["cpu"] = f"{cpu:.2f} it/s: **{x:.1f}x**"
    rec["eval"] = ev = run_eval(R, f"{key}_eval", ply, data, res)
    rec["key"] += "; " + eval_text(ev)
    return rec["vs_cpu"]


def stage_b(R: Run, rec: dict) -> None:
    v = fit_eval(R, rec, "b", "lego", 400, R.args.budget_lego, "0.1,0.5,1.0" if R.args.smoke else LEGO_RES)
    v.update(at_least_10x=v["ratio"] >= 10, goal_20x=v["ratio"] >= 20)
    rec["cpu"] += (f" (>= 10x: {'yes' if v['at_least_10x'] else 'NO'}, goal 20x); "
                   f"{CPU['lego_psnr']['psnr_avg']} dB after 10,220 it")


def keep(R: Run, rec: dict, *paths: Path) -> None:
    """Copy ``paths`` into OUT/fits/, each in parts of at most 15 MiB (the device tool returns files of at
    most 16 MiB); their names and sizes into ``rec["kept"]``."""
    part, dest = 15 * 2**20, R.out / "fits"
    dest.mkdir(exist_ok=True)
    for path in paths:
        data = path.read_bytes()
        chunks = [data[i:i + part] for i in range(0, len(data), part)] or [data]
        names = [path.name] if len(chunks) == 1 else [f"{path.name}.part{i:02d}" for i in range(len(chunks))]
        for name, chunk in zip(names, chunks):
            (dest / name).write_bytes(chunk)
        rec.setdefault("kept", {})[path.name] = {"bytes": len(data), "files": names}


def stage_d(R: Run, rec: dict) -> None:
    fit_eval(R, rec, "d", "bonsai", 800, R.args.budget_bonsai, "0.25" if R.args.smoke else LEGO_RES)
    ply = R.work / "bonsai.ply"
    keep(R, rec, ply, ply.with_suffix(".weights.pxc"))
    rec["cpu"] += " (CPU at 400 px, the GPU at 4x the pixels)" + before_text(R, rec, "bonsai_fit")


def before_text(R: Run, rec: dict, key: str) -> str:
    """The stage's it/s against the earlier GPU run of ``GPU_BEFORE[key]`` (noted as another GPU where it was)."""
    b = GPU_BEFORE[key]
    x = rec["fit"]["it_per_s"] / (b["iterations"] / b["seconds"])
    rec["vs_gpu_before"] = {"before_it_per_s": round(b["iterations"] / b["seconds"], 2), "ratio": round(x, 2),
                            "same_gpu": R.res["machine"].get("gpu") == b["gpu"], "source": b["source"]}
    return f"; {x:.2f}x the {b['gpu']} run at {b['commit']}" + ("" if rec["vs_gpu_before"]["same_gpu"] else
                                                          " (another GPU: not comparable)")


def stage_g(R: Run, rec: dict) -> None:
    """Plain 3DGS (`fit --explicit`) on bonsai at 800 px for stage d's training time on the same GPU, evaluated at
    the same sizes; per size, stage d's PSNR minus this one's, and the 3DGS PLY's SPZ size."""
    data, ply, d = R.data("bonsai"), R.work / "bonsai_3dgs.ply", R.res["stages"].get("d", {})
    budget = (d.get("fit") or {}).get("budget_s") or R.args.budget_bonsai
    f = fit(R, rec, "g_fit", data, ply, 800, budget, ["--explicit"])
    rec["equal_time"] = f["budget_s"] == budget
    rec["cpu"] = before_text(R, rec, "bonsai_3dgs").lstrip("; ")
    rec["key"] = (f"3DGS {f['iterations']:,} it in {f['train_seconds']} s = **{f['it_per_s']} it/s**, "
                  f"{f.get('gaussians', '?')} Gaussians"
                  + ("" if rec["equal_time"] else f" (budget cut from {budget} s)"))
    ev = rec["eval"] = run_eval(R, "g_eval", ply, data, "0.25" if R.args.smoke else LEGO_RES, ["--max-width", 800])
    rec["key"] += "; " + eval_text(ev)
    try:
        from proxycodec.formats.inria_ply import read_inria_ply
        from proxycodec.formats.spz import write_spz

        rec["spz_bytes"] = write_spz(R.work / "bonsai_3dgs.spz", read_inria_ply(ply))
        rec["key"] += f"; SPZ {rec['spz_bytes']:,} B"
    except Exception as e:  # noqa: BLE001 - recorded, the comparison below still counts
        rec["spz_error"] = f"{type(e).__name__}: {e}"
    rec["cpu"] += d_minus(rec, d, ev, "ours_minus_3dgs", "ours - 3DGS",
                          " (acceptance: >= 0 at every size, >= +3 on average)")


def d_minus(rec: dict, d: dict, ev: dict, field: str, label: str, tail: str = "") -> str:
    """Stage d's PSNR minus ``ev``'s per size into ``rec[field]``, and its mean and minimum as text ('' without d)."""
    ours = (d.get("eval") or {}).get("per_resolution")
    if not ours:
        return ""
    diff = {k: round(ours[k]["psnr"] - v["psnr"], 3) for k, v in ev["per_resolution"].items() if k in ours}
    rec[field] = diff
    return f"; {label}: mean {sum(diff.values()) / len(diff):+.2f} dB, min {min(diff.values()):+.2f}{tail}"


def stage_x(R: Run, rec: dict) -> None:
    """Stage d at the former default anchor density (`fit --voxel-rule extent`: extent / 128, about a quarter of
    the anchors) for stage d's training time on the same GPU, evaluated at the same sizes; per size, stage d's PSNR
    minus this one's, and its it/s against the last run of this density."""
    data, ply, d = R.data("bonsai"), R.work / "bonsai_extent.ply", R.res["stages"].get("d", {})
    budget = (d.get("fit") or {}).get("budget_s") or R.args.budget_bonsai
    f = fit(R, rec, "x_fit", data, ply, 800, budget, ["--voxel-rule", "extent"])
    rec["key"] = (f"{f['iterations']:,} it in {f['train_seconds']} s = **{f['it_per_s']} it/s**, "
                  f"{f.get('anchors', '?')} anchors")
    ev = rec["eval"] = run_eval(R, "x_eval", ply, data, "0.25" if R.args.smoke else LEGO_RES)
    rec["key"] += "; " + eval_text(ev)
    rec["cpu"] = (before_text(R, rec, "bonsai_extent").lstrip("; ")
                  + d_minus(rec, d, ev, "d_minus_x", "stage d (spacing) minus this"))
    # its container too: at this density the bytes may meet the 10x bar that stage n's miss (README, "GPU runs")
    e = encode_kept(R, rec, "x_encode", ply)
    rec["key"] += f"; encode {e['seconds']:.0f} s, {e['bytes']:,} B"
    if "spz_over_container" in rec:
        rec["cpu"] += f"; SPZ of stage g's 3DGS / this container: {rec['spz_over_container']}x"


def encode_kept(R: Run, rec: dict, name: str, ply: Path) -> dict:
    """``encode`` of ``ply`` as fitted (its stage-2 predictor), on the device, into ``rec["encode"]``; the container
    kept in OUT/fits/ and, where stage g ran, its bytes against stage g's SPZ (``rec["spz_over_container"]``)."""
    pxc = ply.with_suffix(".pxc")
    pxc.unlink(missing_ok=True)
    small = ["--entropy-iters", 50] if R.args.smoke else []
    r = R.cli(name, ["encode", ply, "-o", pxc, "--json", "--seed", R.args.seed, *small], 400)
    check(r)
    j = json_out(r)
    rec["encode"] = dict(brief(r), bytes=j["file_bytes"], ratio=j["ratio"], encode_seconds=j["seconds"])
    keep(R, rec, pxc)
    spz = R.res["stages"].get("g", {}).get("spz_bytes")
    if spz:
        rec["spz_over_container"] = round(spz / j["file_bytes"], 2)
    return rec["encode"]


def stage_n(R: Run, rec: dict) -> None:
    """``encode`` of stage d's fit as fitted (its stage-2 predictor), on the device; the container's bytes
    against stage g's SPZ (the acceptance: >= 10x smaller)."""
    ply = R.work / "bonsai.ply"
    if not ply.exists():
        raise Skip("no bonsai fit (stage d)")
    e = encode_kept(R, rec, "n_encode", ply)
    rec["key"] = f"encode as fitted **{e['seconds']:.0f} s**, {e['bytes']:,} B ({e['ratio']:.1f}x PLY + weights)"
    if "spz_over_container" in rec:
        rec["cpu"] = (f"SPZ of stage g's 3DGS / container: **{rec['spz_over_container']}x** "
                      "(acceptance: >= 10x)")


def stage_v(R: Run, rec: dict) -> None:
    """Conversion on the device: stage g's bonsai 3DGS PLY as the teacher, with bonsai's training cameras at 800 px
    in a cameras.json beside it (as ``convert.py`` sets it up on the CPU), converted with conversion's defaults under
    ``--budget-convert``, then encoded as converted. Its own folder, so no other PLY finds that cameras.json."""
    a, g = R.args, R.work / "bonsai_3dgs.ply"
    if not g.exists():
        raise Skip("no bonsai 3DGS PLY (stage g)")
    from proxycodec.formats.datasets import load_dataset
    from proxycodec.scaffold_gs import write_cameras_json

    work = R.work / "convert_bonsai"
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir()
    src, conv = work / "point_cloud.ply", work / "converted_anchors.ply"
    shutil.copyfile(g, src)
    data = load_dataset(str(R.data("bonsai")), max_width=800, test_every=8)
    cams = [data.cameras[i] for i in data.train_indices]
    write_cameras_json(work / "cameras.json", cams[:9] if a.smoke else cams)  # smoke: 8 to train on, 1 held out
    t = R.fit_budget(a.budget_convert, 40 if a.smoke else 150)  # encode and the report after it
    r = R.cli("v_convert", ["convert", src, "-o", conv, "--time-budget", t, "--max-width", 64 if a.smoke else 800,
                            "--background", "black", "--seed", a.seed, "--json"], t + 400)
    c = rec["convert"] = dict(parse_fit(r), budget_s=t)
    check(r)
    j = json_out(r)
    c.update({k: v for k, v in j.items() if k in ("cameras", "iterations", "seconds")})
    rep = j["report"]["converted"]
    c["report"] = {"psnr": rep["psnr"], "views": len(rep["views"]),
                   "per_resolution": {f"{d['xi']:g}": d["psnr"] for d in rep["per_resolution"]},
                   "source_psnr": j["report"]["source_direct"]["psnr"]}
    it_s = c["iterations"] / max(c.get("train_seconds") or t, 1)
    cpu = CPU["convert_bonsai"]
    rec["vs_cpu"] = {"cpu_it_per_s": round(cpu["iterations"] / cpu["seconds"], 2),
                     "ratio": round(it_s / (cpu["iterations"] / cpu["seconds"]), 2)}
    rec["key"] = (f"convert {c['iterations']:,} it in {t} s = **{it_s:.2f} it/s**; held-out vs the source's renders "
                  f"**{rep['psnr']:.2f} dB** ({len(rep['views'])} views)")
    e = encode_kept(R, rec, "v_encode", conv)
    rec["key"] += f"; encode {e['seconds']:.0f} s, {e['bytes']:,} B"
    rec["cpu"] = f"{rec['vs_cpu']['cpu_it_per_s']} it/s: **{rec['vs_cpu']['ratio']:.1f}x**; {cpu['source']}"
    if "spz_over_container" in rec:
        rec["cpu"] += f"; SPZ of stage g's 3DGS / container: {rec['spz_over_container']}x (acceptance: >= 10x)"


def profile_steps(step, n: int, dev) -> dict:
    """``step`` run n times, timed (synchronised) and then under torch.profiler: wall ms per step, the device's busy
    ms per step (its kernels' self time), kernel launches per step, and the operations with the most host and device
    time. Busy much below wall: the host (Python, dispatch, synchronisations) sets the pace, not the GPU."""
    import torch
    from torch.autograd import DeviceType
    from torch.profiler import ProfilerActivity, profile

    cuda = dev.type == "cuda"

    def sync():
        if cuda:
            torch.cuda.synchronize(dev)

    for _ in range(3):  # warm-up: caches, allocator
        step()
    sync()
    t = time.perf_counter()
    for _ in range(n):
        step()
    sync()
    wall = (time.perf_counter() - t) / n
    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
    with profile(activities=acts) as prof:
        for _ in range(n):
            step()
        sync()
    ka = prof.key_averages()

    def dev_us(e):  # the attribute's name moved across torch versions
        return getattr(e, "self_device_time_total", None) or getattr(e, "self_cuda_time_total", 0) or 0

    kernels = [e for e in prof.events() if e.device_type == DeviceType.CUDA]  # kernels and copies on the device
    busy = sum(e.time_range.elapsed_us() for e in kernels)

    def top(key):
        rows = sorted(ka, key=key, reverse=True)[:12]
        return [{"op": e.key, "calls_per_step": round(e.count / n, 1), "ms_per_step": round(key(e) / n / 1e3, 3)}
                for e in rows if key(e) > 0]

    return {"steps": n, "wall_ms": round(wall * 1e3, 2), "device_busy_ms": round(busy / n / 1e3, 2),
            "busy_fraction": round(busy / n / 1e3 / (wall * 1e3), 3) if cuda else None,
            "kernels_per_step": round(len(kernels) / n, 1),
            "top_host": top(lambda e: e.self_cpu_time_total), "top_device": top(dev_us) if cuda else []}


def stage_p(R: Run, rec: dict) -> None:
    """Where a training step's time goes: ``profile_steps`` over our anchor fit in stage 1 and in stage 2 (bonsai at
    800 px, the scene's density, the defaults otherwise) and over plain 3DGS, in this process on the device."""
    import torch
    from proxycodec.explicit import ExplicitConfig, ExplicitTrainer
    from proxycodec.formats.datasets import load_dataset
    from proxycodec.train import FitConfig, Trainer

    dev = torch.device("cuda" if R.args.device != "cpu" and torch.cuda.is_available() else "cpu")
    smoke = R.args.smoke
    data = load_dataset(str(R.data("bonsai")), max_width=100 if smoke else 800, test_every=8)
    n, iters = (3, 40) if smoke else (20, 400)
    t0 = time.monotonic()
    ours = Trainer(data, FitConfig(iters=iters, seed=R.args.seed, voxel_rule="spacing"), device=dev)
    for _ in range(10 if smoke else 50):
        ours.train_step()
    cases = rec["cases"] = {}
    cases["ours, stage 1"] = dict(profile_steps(ours.train_step, n, dev), anchors=ours.anchors.num_anchors)
    while ours.stage < 2:
        ours.train_step()
    cases["ours, stage 2"] = dict(profile_steps(ours.train_step, n, dev), anchors=ours.anchors.num_anchors)
    del ours
    tdgs = ExplicitTrainer(data, ExplicitConfig(iters=iters, seed=R.args.seed), device=dev)
    for _ in range(10 if smoke else 50):
        tdgs.train_step()
    cases["3DGS (fit --explicit)"] = profile_steps(tdgs.train_step, n, dev)
    rec["setup_and_steps_s"] = round(time.monotonic() - t0, 1)
    rec["key"] = "; ".join(f"{k}: {c['wall_ms']} ms/step, device busy {c['device_busy_ms']} ms, "
                           f"{c['kernels_per_step']:g} kernels" for k, c in cases.items())


def stage_c(R: Run, rec: dict) -> None:
    a, ply, pxc, dist = R.args, R.work / "lego.ply", R.work / "lego.pxc", R.work / "lego_distill.pxc"
    if not ply.exists():
        raise Skip("no lego fit (stage b)")
    small = ["--entropy-iters", 50] if a.smoke else []
    r = R.cli("c_encode", ["encode", ply, "-o", pxc, "--json", "--seed", a.seed, *small], 300)
    check(r)
    j = json_out(r)
    rec["encode"] = dict(brief(r), bytes=j["file_bytes"], ratio=j["ratio"], encode_seconds=j["seconds"])
    rec["key"] = f"encode as fitted {r['seconds']:.0f} s, {j['file_bytes']:,} B"
    r = R.cli("c_decode", ["decode", pxc, "--res", 0.3, "-o", R.work / "dec"], 180)
    check(r)
    rec["decode"] = dict(brief(r), pngs=len(list((R.work / "dec").glob("*.png"))))
    rec["key"] += f"; decode at 30% {r['seconds']:.1f} s ({rec['decode']['pngs']} PNGs)"
    r = R.cli("c_stats", ["stats", pxc, "--json"], 60)
    check(r)
    rec["stats"] = dict(brief(r), **{k: v for k, v in json_out(r).items() if k in (
        "file_bytes", "scene_format", "anchors", "proxies", "leaves", "bits_per_anchor", "ratio", "bytes_by_group")})
    dist.unlink(missing_ok=True)
    small += ["--distill-iters", 10] if a.smoke else []
    r = R.cli("c_distill", ["encode", ply, "-o", dist, "--refit-predictor", "--distill", "--json", "--seed",
                            a.seed, *small], 600)
    d = rec["distill"] = brief(r)
    m = DISTILL_DONE.search(r["_err"])
    if m:
        d.update(iterations=int(m[1]), train_seconds=secs(m[2]), with_targets_s=float(m[3]))
    prog = [(int(x[1]), x[2], secs(x[5])) for x in PROG.finditer(r["_err"])]
    if not m and prog and prog[-1][0] and prog[-1][1].isdigit():  # cut short: extrapolate its last line
        d["estimated_distill_s"] = round(prog[-1][2] * int(prog[-1][1]) / prog[-1][0])
    d["at_most_120s"] = r["rc"] == 0 and r["seconds"] <= 120
    wall = r["seconds"] if r["rc"] == 0 else d.get("estimated_distill_s")
    rec["key"] += (f"; distilled encode **{r['seconds']:.0f} s** (<= 120 s: {'yes' if d['at_most_120s'] else 'NO'}"
                   + (f"; distillation alone est. {wall} s" if r["rc"] and wall else "") + ")")
    rec["cpu"] = f"distilled encode {CPU['lego_distill']['seconds'] / 60:.1f} min" + (
        f": {CPU['lego_distill']['seconds'] / wall:.1f}x" if wall else "")
    check(r)
    j = json_out(r)
    d.update(bytes=j["file_bytes"], encode_seconds=j["seconds"], held_out=(j.get("distill") or {}).get("held_out"))
    rec["key"] += f", {d.get('iterations', '?')} it in {d.get('train_seconds', '?')} s, {j['file_bytes']:,} B"
    rec["eval_distilled"] = ev = run_eval(R, "c_eval", dist, R.data("lego"), "0.1,0.5,1.0" if a.smoke else LEGO_RES)
    rec["key"] += "; distilled " + eval_text(ev)


def stage_e(R: Run, rec: dict) -> None:
    a, src, conv = R.args, R.work / "explicit.ply", R.work / "conv.ply"
    f = fit(R, rec, "e_fit", R.data("lego"), src, 400, a.budget_explicit, ["--explicit"], reserve=240)
    rec["key"] = f"3DGS {f['iterations']:,} it ({f['it_per_s']} it/s), {f.get('gaussians', '?')} Gaussians"
    small = ["--iters", 20, "--views", 4, "--view-size", 64] if a.smoke else []
    r = R.cli("e_convert", ["convert", src, "-o", conv, "--seed", a.seed, "--json", *small], 400)
    c = rec["convert"] = parse_fit(r)
    check(r)
    c.update({k: v for k, v in json_out(r).items() if k in ("cameras", "iterations", "seconds", "report")})
    cpu = CPU["convert"]["iterations"] / CPU["convert"]["seconds"]
    rec["key"] += f"; convert **{r['seconds']:.0f} s** ({c.get('iterations', '?')} it, {c.get('it_per_s')} it/s)"
    rec["cpu"] = f"convert {cpu:.2f} it/s" + (f": {c['it_per_s'] / cpu:.1f}x" if c.get("it_per_s") else "")
    r = R.cli("e_encode", ["encode", conv, "-o", R.work / "conv.pxc", "--json", "--seed", a.seed], 200)
    check(r)
    rec["encode"] = dict(brief(r), bytes=json_out(r)["file_bytes"])
    rec["key"] += f"; encode {r['seconds']:.0f} s, {rec['encode']['bytes']:,} B"


def stage_f(R: Run, rec: dict) -> None:
    pxc, keys = R.work / "lego.pxc", []
    if pxc.exists():
        r = R.cli("f_render", ["render", pxc, "--res", "0.25,0.5,1.0", "--view", 0, "-o", R.work / "render"], 120)
        rec["render"] = dict(brief(r), pngs=len(list((R.work / "render").glob("*.png"))))
        keys.append(f"`render` 1 view x 3 sizes: {r['seconds']:.1f} s (the whole process)")
    m = rec["micro"] = micro(R)
    keys.append("fwd+bwd " + ", ".join(f"{k} {v['total_ms']:.1f} ms" for k, v in m.items()
                                       if isinstance(v, dict) and "total_ms" in v))
    rec["key"] = "; ".join(keys)
    main = m.get("cuda xi1") or m.get("cpu xi1") or {}
    rec["cpu"] = f"numba {CPU['raster']['ms']} ms" + (f": {CPU['raster']['ms'] / main['total_ms']:.0f}x"
                                                      if main.get("total_ms") else "")


def micro(R: Run) -> dict:
    """Medians (ms) of forward + backward, CUDA synchronized around each phase, on the "Rasterizer" benchmark's
    Gaussians: project_gaussians (torch) + our compositor and + the reference (an L2 image loss), then the
    projection alone, ours against gsplat's fully_fused_projection (a loss on means2d and conics)."""
    import torch

    sys.path.insert(0, str(HERE))
    from raster import make_camera, make_scene

    from proxycodec.render.project import project_gaussians
    from proxycodec.render.reference import rasterize_reference
    from proxycodec.threads import set_threads

    set_threads(R.args.threads)  # None: $PROXYCODEC_THREADS, else the usable cores
    dev = torch.device("cuda" if R.args.device != "cpu" and torch.cuda.is_available() else "cpu")
    n, size, reps = (2_000, 64, 3) if R.args.smoke else (100_000, 400, 10)
    if dev.type == "cuda":
        from proxycodec.render.cuda import rasterize_cuda as ours
    else:
        from proxycodec.render.cpu import rasterize_cpu as ours
    params = [p.to(dev).requires_grad_(True) for p in make_scene(n, R.args.seed)]
    bg, out, images = torch.ones(3, device=dev), {"n": n, "size": size, "repeats": reps, "device": str(dev)}, {}

    def sync():
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)

    def timed(key: str, fn, need: float = 15) -> None:
        """out[key]: medians of fn()'s phases after one warm-up call (a call over 5 s: one more only); skipped
        with less than ``need`` seconds of the stage left."""
        if time.monotonic() > R.stage_end - need:
            out[key] = {"skipped": "stage time"}
            return
        try:
            if dev.type == "cuda":
                torch.cuda.reset_peak_memory_stats(dev)
            t = time.perf_counter()
            fn()
            first = time.perf_counter() - t
            rows = [fn() for _ in range(reps if first < 5 else 1)]
            out[key] = {k: round(sorted(r[k] for r in rows)[len(rows) // 2] * (1e3 if "_ms" in k else 1), 3)
                        for k in rows[0]}
            out[key].update(first_call_s=round(first, 3), repeats=len(rows))
            if dev.type == "cuda":
                out[key]["peak_mb"] = round(torch.cuda.max_memory_allocated(dev) / 2**20, 1)
        except Exception as e:  # noqa: BLE001 - the reference may not fit in memory; gsplat may be absent
            out[key] = {"error": f"{type(e).__name__}: {str(e)[:300]}"}
        if dev.type == "cuda":
            torch.cuda.empty_cache()

    def phases(*fns) -> dict:
        """Zero the gradients, then time each step of ``fns`` (each takes the previous one's result)."""
        for p in params:
            p.grad = None
        sync()
        t, res, row = time.perf_counter(), None, {}
        for name, fn in fns:
            res = fn(res)
            sync()
            row[f"{name}_ms"], t = time.perf_counter() - t, time.perf_counter()
        row["total_ms"] = sum(row.values())
        return row

    for xi in (0.1, 1.0):  # the reference keeps [pixels x Gaussians] per tile for autograd: the small size first
        cam = make_camera(size, xi)
        target = torch.rand(cam.height, cam.width, 3, generator=torch.Generator().manual_seed(1)).to(dev)
        for name, comp in ((dev.type, ours), ("reference", rasterize_reference)):
            def render(proj, comp=comp, name=name):
                images[name] = comp(proj.means2d, proj.conics, proj.opacities, proj.colors, proj.depths,
                                    proj.extent, proj.width, proj.height, bg)
                return images[name]

            def loss(img_alpha, target=target):
                ((img_alpha[0] - target).square().mean() + 0.1 * img_alpha[1].mean()).backward()

            timed(f"{name} xi{xi:g}", functools.partial(phases, ("proj_fwd", lambda _, c=cam: project_gaussians(
                *params, c)), ("raster_fwd", render), ("bwd", loss)), need=60 if name == "reference" else 15)
        if len(images) == 2:
            a, b = (img.detach() for img, _ in images.values())
            out[f"max_abs_diff {dev.type} vs reference xi{xi:g}"] = float((a - b).abs().max())
        images.clear()

    cam = make_camera(size, 1.0)
    vm = torch.eye(4, device=dev)
    vm[:3, :3] = torch.as_tensor(cam.rotation, dtype=torch.float32, device=dev)
    vm[:3, 3] = torch.as_tensor(cam.translation, dtype=torch.float32, device=dev)
    K = torch.as_tensor(cam.K, dtype=torch.float32, device=dev)[None]

    def ours_2d(_):
        p = project_gaussians(*params, cam)
        return p.means2d, p.conics

    def gsplat_2d(_):  # no gate, no culling: every Gaussian keeps a row (radius 0 where culled)
        from gsplat import fully_fused_projection

        o = fully_fused_projection(params[0], None, params[1], params[2], vm[None], K, cam.width, cam.height,
                                   eps2d=0.3, near_plane=0.01)
        return o[1], o[3]

    def loss_2d(m_c):
        (m_c[0].square().mean() + m_c[1].mean()).backward()

    for name, fn in (("projection ours", ours_2d), ("projection gsplat", gsplat_2d)):
        timed(f"{name} xi1", functools.partial(phases, ("fwd", fn), ("bwd", loss_2d)))
    params.clear()
    images.clear()
    if dev.type == "cuda":
        torch.cuda.empty_cache()  # give the later stages' processes the GPU memory back
    return out


STAGES = {"a": ("pytest -m cuda", stage_a, lambda a: 300),
          "b": ("lego fit 400 px + eval", stage_b, lambda a: a.budget_lego + 200),
          "c": ("lego encode, distillation, decode, stats, eval", stage_c, lambda a: 480),
          "d": ("bonsai fit 800 px + eval", stage_d, lambda a: a.budget_bonsai + 200),
          "e": ("3DGS fit, convert, encode", stage_e, lambda a: a.budget_explicit + 420),
          "f": ("render, micro-benchmark", stage_f, lambda a: 150),
          "g": ("bonsai plain 3DGS at d's budget + eval", stage_g, lambda a: a.budget_bonsai + 200),
          "n": ("bonsai encode as fitted (stage d's fit)", stage_n, lambda a: 420),
          "v": ("bonsai conversion of stage g's 3DGS PLY + encode", stage_v, lambda a: a.budget_convert + 420),
          "p": ("profile of training steps: ours stage 1 and 2, 3DGS", stage_p, lambda a: 240),
          "x": ("bonsai fit at the extent / 128 density, d's budget + eval + encode", stage_x,
                lambda a: a.budget_bonsai + 260)}


def markdown(res: dict) -> str:
    m = res["machine"]
    head = (f"{m.get('gpu') or 'no GPU'} ({m.get('gpu_memory_gib', '?')} GiB), {m['cpu_count']} CPUs, device "
            f"`{m['device']}`; torch {m.get('torch')} (CUDA {m.get('torch_cuda')}), gsplat {m.get('gsplat')}; "
            f"commit {(m.get('commit') or 'unknown')[:12]}; seed {m['seed']}; {res.get('elapsed_s')} s in all; "
            f"peak RSS {res['peak_rss_mb']['children_max']:.0f} MB (largest command); GPU memory allocated by "
            f"this script at most {res.get('gpu_max_memory_allocated_mb', 'n/a')} MB.")
    smoke = " (--smoke: checks the script, measures nothing)" if res["args"].get("smoke") else ""
    lines = [f"# GPU run ({m.get('started')}){smoke}", "", head, "", "| stage | status | s | figures | 2-core CPU |",
             "|---|---|---:|---|---|"]
    for k, s in res["stages"].items():
        why = (s.get("reason") or s.get("error") or "").strip().splitlines()
        note = "; ".join(filter(None, [s.get("key"), why[0][:200] if why and s["status"] != "ok" else ""]))
        lines.append(f"| {k} {s['title']} | {s['status']} | {s.get('seconds', '')} | {note.replace('|', '/')} | "
                     f"{s.get('cpu', '')} |")
    return "\n".join(lines + ["", "CPU figures: benchmarks/README.md (sources in gpu.json, `cpu_reference`)."]) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=str(ROOT / ".device" / "data"),
                    help="folder with lego400/ and bonsai/ (the kit's); else ../shared/data's are used")
    ap.add_argument("--out", default=os.environ.get("OUT") or str(HERE / "results" / "gpu"))
    ap.add_argument("--work", default=str(Path(tempfile.gettempdir()) / "proxycodec_gpu"),
                    help="fitted scenes, containers and renders (kept out of --out)")
    ap.add_argument("--device", default="cuda", choices=("cuda", "cpu", "auto"))
    ap.add_argument("--threads", type=int, default=None, help="forwarded as proxycodec --threads N")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--budget-lego", type=float, default=150.0, help="lego fit --time-budget, s")
    ap.add_argument("--budget-bonsai", type=float, default=120.0, help="bonsai fit --time-budget, s")
    ap.add_argument("--budget-explicit", type=float, default=60.0, help="stage e's 3DGS fit --time-budget, s")
    ap.add_argument("--budget-convert", type=float, default=240.0, help="stage v's convert --time-budget, s")
    ap.add_argument("--stages", default="b,c,f,a,d,e", help="stages to run, in this order")
    ap.add_argument("--deadline", type=float, default=440.0,
                    help="total seconds, after which stages are skipped (the bootstrap took 135 s of a 600-s call on "
                         "an H100, 121 s of it compiling gsplat)")
    ap.add_argument("--smoke", action="store_true", help="tiny budgets and sizes, to check the script on a CPU")
    ap.add_argument("--commit", default=None, help="commit to record (default: git rev-parse HEAD, if a repo)")
    args = ap.parse_args(argv)
    keys = [k.strip() for k in args.stages.split(",") if k.strip()]
    if bad := [k for k in keys if k not in STAGES]:
        ap.error(f"unknown stages {bad}; choose from {','.join(STAGES)}")
    if args.smoke:
        args.budget_lego, args.budget_bonsai, args.budget_explicit, args.budget_convert = (
            min(x, 10.0) for x in (args.budget_lego, args.budget_bonsai, args.budget_explicit, args.budget_convert))
    if args.threads:
        os.environ["PROXYCODEC_THREADS"] = str(args.threads)  # pytest, and torch in this process
    R = Run(args)
    R.say(f"machine: {json.dumps(R.res['machine'])}")
    R.save()
    for k in keys:
        title, fn, limit = STAGES[k]
        R.stage(k, title, fn, limit(args))
    print((R.out / "gpu.md").read_text())
    print(f"wrote {R.out / 'gpu.json'} and {R.out / 'gpu.md'}")
    return 0 if all(s["status"] == "ok" for s in R.res["stages"].values()) else 1


if __name__ == "__main__":
    sys.exit(main())
