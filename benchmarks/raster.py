"""Rasterizer benchmark: projection + compositing, forward and backward, cpu (numba) vs reference (issue #3).

Each case runs in its own subprocess, so that its peak RSS (getrusage maxrss) is its own and the reference's memory
does not pollute the cpu figures. Timings are wall-clock medians (and minima) over repeats, after one warm-up render;
the four phases are timed separately: projection forward, raster forward, raster backward (to the 2D interface),
projection backward. ``total`` is their sum for one repeat. The projection runs on the path ``render.project`` picks
for the backend (the fused numba projection, ``render/project_cpu.py``, for ``cpu``; the torch reference,
``render/project.py``, otherwise), reported as ``project_backend``; a case with ``"project": "torch"`` forces the torch
projection (for the comparison). CPU times (``time.process_time``, all threads of the process) are recorded beside
the wall-clock ones, since the machine is shared.

    python benchmarks/raster.py                 # full grid, writes benchmarks/results/raster.json
    python benchmarks/raster.py --quick         # 400 px, 100k, xi 1.0 / 0.1, and the reference comparison
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

SEED = 0
BACKGROUND = (1.0, 1.0, 1.0)


def make_scene(n: int, seed: int = SEED):
    """Gaussians like a trained object scene: an object-sized (about 2 x 1.6 x 1.2 units) blob, most Gaussians near
    its surface, log-scales ~ N(log 0.01, 0.5), random rotations, opacities sigmoid(N(0, 2)), RGB colours."""
    import torch

    g = torch.Generator().manual_seed(seed)
    d = torch.randn(n, 3, generator=g)
    d = d / d.norm(dim=1, keepdim=True)
    shell = 0.8 + 0.08 * torch.randn(n, 1, generator=g)
    inner = torch.rand(n, 1, generator=g) ** (1 / 3) * 0.8
    r = torch.where(torch.rand(n, 1, generator=g) < 0.85, shell, inner)
    bumps = 1 + 0.15 * torch.sin(3 * d[:, :1]) * torch.cos(2 * d[:, 1:2])
    means = d * r * bumps * torch.tensor([1.0, 0.8, 0.6])
    quats = torch.randn(n, 4, generator=g)
    scales = torch.exp(math.log(0.01) + 0.5 * torch.randn(n, 3, generator=g))
    opacities = torch.sigmoid(2 * torch.randn(n, generator=g))
    colors = torch.rand(n, 3, generator=g)
    return means, quats, scales, opacities, colors


def make_camera(size: int, xi: float):
    from proxycodec.camera import Camera

    cam = Camera.look_at([2.6, 1.0, 1.1], [0.0, 0.0, 0.0], fov_x_deg=50.0, width=size, height=size, name="bench")
    return cam.scaled(xi)


# ---------------------------------------------------------------------------------------------------- worker
def run_case(case: dict) -> dict:
    import resource

    import numpy as np
    import torch

    from proxycodec.render import project, project_gaussians, rasterize, resolve_backend

    backend, n, size, xi, repeats = case["backend"], case["n"], case["size"], case["xi"], case["repeats"]
    force_torch = case.get("project") == "torch"
    fused = not force_torch and resolve_backend(backend, torch.device("cpu")) == "cpu"
    cam = make_camera(size, xi)
    params = [p.requires_grad_(True) for p in make_scene(n, case["seed"])]
    bg = torch.tensor(BACKGROUND)
    target = torch.rand(cam.height, cam.width, 3, generator=torch.Generator().manual_seed(1))

    def once():
        for p in params:
            p.grad = None
        c0 = time.process_time()
        t0 = time.perf_counter()
        proj = project_gaussians(*params, cam) if force_torch else project(*params, cam, backend=backend)
        t1 = time.perf_counter()
        leaves = [x.detach().requires_grad_(True) for x in (proj.means2d, proj.conics, proj.opacities, proj.colors)]
        proj2 = type(proj)(leaves[0], leaves[1], leaves[2], leaves[3], proj.depths, proj.extent, proj.index,
                           proj.gate, proj.width, proj.height)
        img, alpha = rasterize(proj2, bg, backend)
        t2 = time.perf_counter()
        loss = (img - target).square().mean() + 0.1 * alpha.mean()
        loss.backward()
        t3 = time.perf_counter()
        torch.autograd.backward([proj.means2d, proj.conics, proj.opacities, proj.colors], [x.grad for x in leaves])
        t4 = time.perf_counter()
        return proj, (t1 - t0, t2 - t1, t3 - t2, t4 - t3, t4 - t0, time.process_time() - c0)

    load_before = os.getloadavg()
    t_first = time.perf_counter()
    proj, _ = once()  # warm-up: numba cache load (or compile), allocator
    first_call_s = time.perf_counter() - t_first
    rows = [once()[1] for _ in range(repeats)]
    load_after = os.getloadavg()
    arr = np.array(rows) * 1e3
    names = ("proj_fwd_ms", "raster_fwd_ms", "raster_bwd_ms", "proj_bwd_ms", "total_ms")
    out = dict(case)
    out.update({
        "project_backend": "cpu-fused" if fused else "torch",
        "cpu_time_total_ms": {"median": float(np.median(arr[:, 5])), "min": float(arr[:, 5].min())},
        "width": cam.width, "height": cam.height, "visible": proj.count, "culled": n - proj.count,
        "median": {k: float(np.median(arr[:, i])) for i, k in enumerate(names)},
        "min": {k: float(arr[:, i].min()) for i, k in enumerate(names)},
        "first_call_s": first_call_s,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "loadavg_before": load_before, "loadavg_after": load_after,
    })
    if backend == "cpu":
        from proxycodec.render import cpu as cpu_backend

        b = cpu_backend._bin(*(x.detach().contiguous() for x in (proj.means2d, proj.conics, proj.opacities,
                                                                   proj.colors)), proj.depths, proj.extent,
                             proj.width, proj.height)
        out["tile_gaussian_pairs"] = b.n_isect
        out["tiles_touched"] = int((np.diff(b.tile_off) > 0).sum())
        out["tiles"] = b.tiles_x * b.tiles_y
    return out


# ---------------------------------------------------------------------------------------------------- driver
def spawn(case: dict, timeout: float) -> dict:
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", json.dumps(case)]
    try:
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, check=False)
    except subprocess.TimeoutExpired:
        return dict(case, error=f"timeout after {timeout:.0f} s")
    if res.returncode != 0:
        return dict(case, error=(res.stderr.strip().splitlines() or ["?"])[-1])
    return json.loads(res.stdout.strip().splitlines()[-1])


def versions() -> dict:
    import numba
    import numpy
    import torch

    return {"python": platform.python_version(), "torch": torch.__version__, "numpy": numpy.__version__,
            "numba": numba.__version__, "platform": platform.platform(), "processor": platform.processor()}


def fmt(r: dict) -> str:
    if "error" in r:
        return f"{r['backend']:9s} {r['n']:>7d} {r['size']:>4d} {r['xi']:>4.2f}  ERROR {r['error']}"
    m, mn = r["median"], r["min"]
    return (f"{r['backend']:9s} {r['project_backend']:9s} {r['n']:>7d} {r['size']:>4d} {r['xi']:>4.2f}"
            f" {r['width']:>4d}x{r['height']:<4d}"
            f"{r['visible']:>8d} {r['culled']:>7d} {m['proj_fwd_ms']:8.1f} {m['raster_fwd_ms']:8.1f}"
            f" {m['raster_bwd_ms']:8.1f} {m['proj_bwd_ms']:8.1f} {m['total_ms']:8.1f} {mn['total_ms']:8.1f}"
            f" {r['cpu_time_total_ms']['median']:8.1f} {r['peak_rss_mb']:7.0f}"
            f"  {r['loadavg_before'][0]:4.2f}/{r['loadavg_after'][0]:4.2f}")


HEADER = (f"{'backend':9s} {'project':9s} {'N':>7s} {'size':>4s} {'xi':>4s} {'W x H':^9s}{'visible':>8s}"
          f" {'culled':>7s} {'projF':>8s} {'rastF':>8s} {'rastB':>8s} {'projB':>8s} {'total':>8s} {'tot.min':>8s} {'cpu.tot':>8s}"
          f" {'RSS MB':>7s}  load1 before/after")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="a few cases, fewer repeats")
    ap.add_argument("--repeats", type=int, default=None, help="timed repeats per case (default 7, quick 5)")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "raster.json"))
    ap.add_argument("--seed", type=int, default=SEED)
    ap.add_argument("--timeout", type=float, default=900.0, help="seconds per case")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    from proxycodec.threads import set_threads

    threads = set_threads()  # $PROXYCODEC_THREADS, else the usable cores; the case workers inherit the count
    if args.worker:
        print(json.dumps(run_case(json.loads(args.worker))))
        return 0

    repeats = args.repeats or (5 if args.quick else 7)
    if args.quick:
        grid = [(100_000, 400, 1.0), (100_000, 400, 0.1)]
    else:
        grid = [(n, s, xi) for n in (100_000, 300_000) for s in (200, 400, 800) for xi in (1.0, 0.1)]
    # The reference keeps every tile's [pixels x Gaussians] tensors for autograd: it cannot run the big cases in
    # this memory. It runs on the cases below, with the cpu backend timed on the same cases in the same run.
    ref_grid = [(100_000, 400, 0.1), (20_000, 200, 1.0)]
    cases = [{"backend": "cpu", "n": n, "size": s, "xi": xi} for n, s, xi in grid]
    # the same raster with the torch projection: what the fused projection buys
    cases.append({"backend": "cpu", "n": 100_000, "size": 400, "xi": 1.0, "project": "torch"})
    for n, s, xi in ref_grid:
        if not any(c["n"] == n and c["size"] == s and c["xi"] == xi for c in cases):
            cases.append({"backend": "cpu", "n": n, "size": s, "xi": xi})
        cases.append({"backend": "reference", "n": n, "size": s, "xi": xi})
    for c in cases:
        c.update(seed=args.seed, repeats=repeats if c["backend"] == "cpu" else max(2, repeats // 3))

    meta = {"cpu_count": os.cpu_count(), "torch_threads": threads, "seed": args.seed, "repeats": repeats,
            "loadavg_start": os.getloadavg(), "versions": versions(), "background": BACKGROUND,
            "timer": "time.perf_counter wall clock; medians and minima over repeats after one warm-up"}
    print(f"cpus {meta['cpu_count']}, load average at start {meta['loadavg_start']}, seed {args.seed}, "
          f"versions {meta['versions']}")
    print("times in ms (median; tot.min = minimum total); peak RSS of the case's own process")
    print(HEADER)
    results = []
    for c in cases:
        r = spawn(c, args.timeout)
        results.append(r)
        print(fmt(r), flush=True)
    meta["loadavg_end"] = os.getloadavg()

    summary = {}
    for n, s, xi in ref_grid:
        pair = [r for r in results if r["n"] == n and r["size"] == s and r["xi"] == xi and "error" not in r
                and "project" not in r]
        by = {r["backend"]: r for r in pair}
        if "cpu" in by and "reference" in by:
            summary[f"speedup_vs_reference_{n}_{s}px_xi{xi}"] = (by["reference"]["median"]["total_ms"]
                                                                  / by["cpu"]["median"]["total_ms"])
    for n in (100_000, 300_000):
        for s in (200, 400, 800):
            full = [r for r in results if r["backend"] == "cpu" and r["n"] == n and r["size"] == s and "error" not in r
                    and "project" not in r]
            by = {r["xi"]: r for r in full}
            if 1.0 in by and 0.1 in by:
                summary[f"xi0.1_over_xi1.0_{n}_{s}px"] = by[0.1]["median"]["total_ms"] / by[1.0]["median"]["total_ms"]
    fused = [r for r in results if r["backend"] == "cpu" and (r["n"], r["size"], r["xi"]) == (100_000, 400, 1.0)
             and "error" not in r]
    by = {r.get("project", "auto"): r for r in fused}
    if "torch" in by and "auto" in by:
        for phase in ("proj_fwd_ms", "proj_bwd_ms", "total_ms"):
            summary[f"torch_over_fused_projection_{phase}_100000_400px"] = (by["torch"]["median"][phase]
                                                                            / by["auto"]["median"][phase])
    print("summary:", json.dumps(summary, indent=1))
    print(f"load average at end {meta['loadavg_end']}")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"meta": meta, "results": results, "summary": summary}, indent=1))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
