"""Time and memory of converting and encoding a 3DGS PLY against its size: how each stage grows.

    python benchmarks/scale.py BASE.ply [--sizes 0.1,0.3,1,3] [--iters 4] [--out DIR]
    python benchmarks/scale.py BASE.ply --make 1 BIG.ply    # only write the 1M-Gaussian PLY a size is made of

``BASE.ply``: a real 3DGS PLY (e.g. a bonsai fit). Each size (millions of Gaussians) is made from it: a seeded random
subset below its own size, the PLY itself at its size, and above it jittered copies of it laid side by side on a grid
(each copy shifted by 1.1 x its extent, its centres jittered by 1% of their own scales), so that density and scales
stay those of a real capture. Each size runs in its own process (its peak RSS its own): ``convert`` with the default
anchor rule (no budget), 100 initial-fit steps, ``--iters`` training iterations on 16 automatic 256 px teacher views
and one held-out report view, then ``encode`` (zstd, the conversion's stage-2 predictor). Recorded per stage: seconds,
and the process's peak RSS after it.

Outputs in ``--out`` (default ``benchmarks/results/scale``): ``scale.json`` (every figure, machine, versions),
``scale.md`` (with the growth exponent of each stage between the two largest sizes) and ``scale.png`` (log-log cost
against size).
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
STAGES = ("read", "voxel", "anchors", "initial_fit", "train", "report", "encode")


def peak_rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def make_ply(base_path: str, n: int, out: Path, seed: int = 0) -> dict:
    """A PLY of ``n`` Gaussians made from the base (module docstring)."""
    from proxycodec.formats.inria_ply import GaussianPly, write_inria_ply
    from proxycodec.formats.splats import read_splats

    base, _ = read_splats(base_path)
    rng = np.random.default_rng(seed)
    nb = base.n_gaussians
    if n <= nb:
        idx = np.sort(rng.choice(nb, n, replace=False)) if n < nb else np.arange(nb)
        ply = GaussianPly(base.means[idx], base.sh[idx], base.opacities[idx], base.scales[idx], base.quats[idx])
        how = "the PLY itself" if n == nb else f"a random {n / nb:.0%} of the PLY"
    else:
        copies = math.ceil(n / nb)
        side = math.ceil(copies ** (1 / 3))
        lo, hi = np.percentile(base.means, [1, 99], axis=0)
        step = 1.1 * float((hi - lo).max())
        parts = {k: [] for k in ("means", "sh", "opacities", "scales", "quats")}
        for c in range(copies):
            off = step * np.array([c % side, (c // side) % side, c // (side * side)], dtype=np.float64)
            jitter = 0.01 * np.exp(base.scales.astype(np.float64)) * rng.normal(size=base.means.shape)
            parts["means"].append((base.means + off + jitter).astype(np.float32))
            for k in ("sh", "opacities", "scales", "quats"):
                parts[k].append(getattr(base, k))
        ply = GaussianPly(*(np.concatenate(parts[k])[:n] for k in ("means", "sh", "opacities", "scales", "quats")))
        how = f"{copies} jittered copies of the PLY on a {side}^3 grid"
    write_inria_ply(out, ply)
    return {"gaussians": n, "made_as": how, "sh_degree": ply.sh_degree, "ply_bytes": out.stat().st_size}


def one(ply: str, iters: int, out_json: str) -> None:
    """Run one size (the child process)."""
    if str(REPO) not in sys.path:
        sys.path.insert(0, str(REPO))
    from proxycodec import codec
    from proxycodec.convert import ConvertConfig, convert, replace_fit

    rows: dict = {"rss_mb": {}}
    cfg = replace_fit(ConvertConfig(init_iters=100, views=16, view_size=256),
                      iters=iters, checkpoint_every=0.0, log_every=1e9)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        r = convert(ply, Path(tmp) / "a.ply", cfg, log=lambda s: None, report_views=1)
        total = time.perf_counter() - t0
        s = dict(r.seconds)
        rows["seconds"] = {k: s.get(k) for k in ("read", "voxel", "anchors", "initial_fit")}
        rows["seconds"]["train"] = s["train"]
        rows["seconds"]["report"] = total - s["setup"] - s["fit_call"]
        rows["rss_mb"]["convert"] = peak_rss_mb()
        rows["anchors"] = r.model.scene.num_anchors
        rows["voxel"] = r.voxel.__dict__
        rows["iterations"] = r.iterations
        t0 = time.perf_counter()
        e = codec.encode(Path(tmp) / "a.ply", Path(tmp) / "a.pxc", entropy="zstd", progress=lambda s: None)
        rows["seconds"]["encode"] = time.perf_counter() - t0
        rows["rss_mb"]["encode"] = peak_rss_mb()
        rows["container_bytes"] = e.file_bytes
    Path(out_json).write_text(json.dumps(rows))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("base", nargs="?")
    ap.add_argument("--sizes", default="0.1,0.3,1,3", help="millions of Gaussians")
    ap.add_argument("--iters", type=int, default=4, help="training iterations per size")
    ap.add_argument("--out", default=None)
    ap.add_argument("--one", nargs=2, metavar=("PLY", "JSON"), help=argparse.SUPPRESS)
    ap.add_argument("--make", nargs=2, metavar=("MILLIONS", "OUT_PLY"),
                    help="only write the PLY of that size made from BASE (e.g. for a timed `proxycodec encode` of it)")
    args = ap.parse_args(argv)
    if args.make:
        if str(REPO) not in sys.path:
            sys.path.insert(0, str(REPO))
        made = make_ply(args.base, int(round(float(args.make[0]) * 1e6)), Path(args.make[1]))
        print(f"{args.make[1]}: {made['gaussians']:,} Gaussians, {made['made_as']}, {made['ply_bytes']:,} B")
        return 0
    if args.one:
        one(args.one[0], args.iters, args.one[1])
        return 0
    if str(REPO) not in sys.path:
        sys.path.insert(0, str(REPO))
    from proxycodec.bench import machine_info, versions
    from proxycodec.fileio import write_bytes_atomic

    out = Path(args.out) if args.out else REPO / "benchmarks" / "results" / "scale"
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for m in (float(x) for x in args.sizes.split(",")):
        n = int(round(m * 1e6))
        with tempfile.TemporaryDirectory() as tmp:
            made = make_ply(args.base, n, Path(tmp) / "s.ply")
            t0 = time.perf_counter()
            p = subprocess.run([sys.executable, __file__, "--one", str(Path(tmp) / "s.ply"), str(Path(tmp) / "r.json"),
                                "--iters", str(args.iters)], capture_output=True, text=True)
            if p.returncode != 0:
                rows.append({**made, "failed": p.stderr.strip()[-2000:]})
                print(f"{n:,}: failed\n{p.stderr[-2000:]}", flush=True)
                continue
            r = {**made, **json.loads((Path(tmp) / "r.json").read_text()), "wall_s": time.perf_counter() - t0}
        rows.append(r)
        print(f"{n:,} Gaussians ({made['made_as']}): {r['anchors']:,} anchors, "
              + ", ".join(f"{k} {v:.1f} s" for k, v in r["seconds"].items())
              + f"; peak RSS {max(r['rss_mb'].values()):.0f} MB; container {r['container_bytes']:,} B", flush=True)
    meta = {"base": args.base, "iters": args.iters, "machine": machine_info(), "versions": versions(),
            "date": time.strftime("%Y-%m-%d"),
            "command": "python benchmarks/scale.py " + " ".join(argv if argv is not None else sys.argv[1:])}
    write_bytes_atomic(out / "scale.json", json.dumps({"meta": meta, "rows": rows}, indent=1).encode())
    ok = [r for r in rows if "failed" not in r]
    lines = [f"# Conversion and encoding against size ({Path(args.base).name})", "",
             f"{args.iters} training iterations per size; {meta['machine'].get('cpu_model', '?')}, "
             f"{meta['machine'].get('cpu_count')} cores.", "",
             "| Gaussians | made as | anchors | " + " | ".join(f"{s} s" for s in STAGES) + " | peak RSS MB | "
             "container B |", "|---:|---|---:|" + "---:|" * len(STAGES) + "---:|---:|"]
    for r in ok:
        lines.append(f"| {r['gaussians']:,} | {r['made_as']} | {r['anchors']:,} | "
                     + " | ".join(f"{r['seconds'][s]:.1f}" for s in STAGES)
                     + f" | {max(r['rss_mb'].values()):.0f} | {r['container_bytes']:,} |")
    if len(ok) >= 2:
        a, b = ok[-2], ok[-1]
        k = math.log(b["gaussians"] / a["gaussians"])
        lines += ["", f"Growth exponent between {a['gaussians']:,} and {b['gaussians']:,} Gaussians (cost ~ N^e): "
                  + ", ".join(f"{s} {math.log(max(b['seconds'][s], 1e-3) / max(a['seconds'][s], 1e-3)) / k:.2f}"
                              for s in STAGES)
                  + f", anchors {math.log(b['anchors'] / a['anchors']) / k:.2f}, peak RSS "
                  f"{math.log(max(b['rss_mb'].values()) / max(a['rss_mb'].values())) / k:.2f}."]
    for r in rows:
        if "failed" in r:
            lines.append(f"\n{r['gaussians']:,} Gaussians failed: `{r['failed'][-300:]}`")
    md = "\n".join(lines) + "\n"
    write_bytes_atomic(out / "scale.md", md.encode())
    if ok:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4.2))
        x = [r["gaussians"] for r in ok]
        for s in STAGES:
            ax.plot(x, [max(r["seconds"][s], 1e-3) for r in ok], "o-", label=s)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("Gaussians in the PLY")
        ax.set_ylabel("seconds (2 cores)")
        ax.set_title(f"stage time ({args.iters} training iterations)")
        ax.legend(fontsize=8)
        bx.plot(x, [max(r["rss_mb"].values()) for r in ok], "o-", label="peak RSS (MB)")
        bx.plot(x, [r["anchors"] / 100 for r in ok], "s--", label="anchors / 100")
        bx.set_xscale("log")
        bx.set_yscale("log")
        bx.set_xlabel("Gaussians in the PLY")
        bx.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(out / "scale.png", dpi=110)
    print("\n" + md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
