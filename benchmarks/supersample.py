"""What supersampling buys and costs: PSNR and render time per resolution, per model, per factor.

    python benchmarks/supersample.py ours=scene.ply 3dgs=3dgs.ply --dataset ../shared/data/mipnerf360/bonsai \\
        --max-width 800 --res 0.1,0.2,0.3,0.4,0.5,0.6,0.7,0.8,0.9,1 --factors 1,2,3:0.5 --views-every 3 \
        --out benchmarks/results/bonsai800/supersample

Each model (LABEL=PATH: an anchor scene, a container or a 3DGS PLY, as ``proxycodec eval`` reads them) is evaluated
on the dataset's test views at each resolution with each supersampling factor (``render.render_supersampled``:
rendered at N x the size, the resolution embedding at N x the ratio, each N x N block averaged; factor 1 is the plain
render), against the same box-filtered photos as ``eval``. A 3DGS PLY renders on the dataset's background, as in
``eval``. Render times are per-view medians, measured in the same run as factor 1's, whose ratio is the price quoted.

Writes ``supersample.json`` (machine, versions, peak RSS, every figure per view), ``supersample.md`` (the table) and
``supersample.png`` (PSNR and time against resolution) in ``--out``; prints the table.

``--embedding-at XI:E1,E2,...`` adds a diagnostic for anchor scenes: the plain render at resolution XI with the
resolution embedding told E instead (what the embedding, rather than the sampling, does to that size).
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def load(models: dict[str, str], dataset: str, max_width: int | None):
    """-> (the dataset, label -> model), each loaded once for every measurement of the run."""
    from proxycodec.explicit import ExplicitModel
    from proxycodec.formats.datasets import load_dataset
    from proxycodec.scenes import load_any

    data = load_dataset(dataset, max_width=max_width)
    loaded = {}
    for label, path in models.items():
        loaded[label] = load_any(path)
        if isinstance(loaded[label], ExplicitModel):  # the dataset's background, as ``eval`` renders a 3DGS PLY
            loaded[label].background = tuple(data.background)
    return data, loaded


def run(models: dict[str, str], loaded: dict, data, res: list[float], factors: dict[int, float], views_every: int,
        log) -> dict:
    """``factors``: factor -> the largest resolution it is measured at; ``loaded``, ``data``: from ``load``."""
    from proxycodec.evaluate import evaluate

    views = list(data.test_indices)[::views_every]
    out = {"views": views, "resolutions": res, "factors": {str(f): m for f, m in factors.items()}, "models": {}}
    for label, path in models.items():
        model = loaded[label]
        model.render(data.cameras[views[0]], 0.5)  # warm-up (numba's cache, the allocator): not timed
        per = {}
        for f, top in factors.items():
            t0 = time.perf_counter()
            fres = [x for x in res if x <= top + 1e-9]
            rep = evaluate(model, data, resolutions=fres, views=views, supersample=f)
            rows = {}
            for xi in fres:
                rs = [r for r in rep.rows if r["xi"] == float(xi)]
                rows[f"{xi:g}"] = {"psnr": statistics.fmean(r["psnr"] for r in rs),
                                   "ssim": statistics.fmean(r["ssim"] for r in rs),
                                   "ms_median": 1000 * statistics.median(r["seconds"] for r in rs),
                                   "per_view": [{k: r[k] for k in ("view", "psnr", "ssim", "seconds")} for r in rs]}
            per[str(f)] = rows
            log(f"{label} x{f}: " + "  ".join(f"{k}: {v['psnr']:.2f} dB {v['ms_median']:.0f} ms"
                                              for k, v in rows.items()) + f"  ({time.perf_counter() - t0:.0f} s)")
        out["models"][label] = {"path": str(path), "per_factor": per}
    return out


def embedding_probe(loaded: dict, data, xi: float, embeds: list[float], views_every: int, log) -> dict:
    """Per anchor scene: mean PSNR of the plain render at ``xi`` with the embedding told each of ``embeds``."""
    import torch

    from proxycodec.metrics import psnr

    views = list(data.test_indices)[::views_every]
    out = {}
    for label, model in loaded.items():
        if getattr(model.scene, "num_anchors", None) is None:
            continue  # plain 3DGS has no embedding
        vals = {e: [] for e in embeds}
        with torch.no_grad():
            for v in views:
                gt = data.load_image(v, xi)
                for e in embeds:
                    img = model.render(data.cameras[v], e, size=(gt.shape[1], gt.shape[0])).image.clamp(0, 1)
                    vals[e].append(psnr(img, gt))
        out[label] = {f"{e:g}": statistics.fmean(x) for e, x in vals.items()}
        log(f"{label} at {xi:g}, embedding told: " + "  ".join(f"{e}: {p:.2f} dB" for e, p in out[label].items()))
    return out


def markdown(res: dict) -> str:
    xi = [f"{x:g}" for x in res["resolutions"]]
    lines = ["PSNR (dB) per resolution; in brackets, the change against the plain render (factor 1) and the median "
             "render time as a multiple of its own.", "",
             "| model | factor | " + " | ".join(f"{round(float(x) * 100)}%" for x in xi) + " | mean |",
             "|---|---:|" + "---:|" * (len(xi) + 1)]
    for label, m in res["models"].items():
        base = m["per_factor"].get("1")
        for f, rows in m["per_factor"].items():
            cells = []
            for x in xi:
                r = rows.get(x)
                if r is None:
                    cells.append("")
                elif base is None or f == "1":
                    cells.append(f"{r['psnr']:.2f} ({r['ms_median']:.0f} ms)")
                else:
                    b = base[x]
                    cells.append(f"{r['psnr']:.2f} ({r['psnr'] - b['psnr']:+.2f}, "
                                 f"{r['ms_median'] / b['ms_median']:.1f}x)")
            mean = statistics.fmean(rows[x]["psnr"] for x in xi) if all(x in rows for x in xi) else None
            lines.append(f"| {label} | {f} | " + " | ".join(cells) + f" | {'' if mean is None else f'{mean:.2f}'} |")
    return "\n".join(lines) + "\n"


def plot(res: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
    for i, (label, m) in enumerate(res["models"].items()):
        for j, (f, rows) in enumerate(m["per_factor"].items()):
            style = dict(color=f"C{i}", ls=["-", "--", ":", "-."][j % 4], marker="o", label=f"{label}, x{f}")
            xf = [x for x in res["resolutions"] if f"{x:g}" in rows]
            a.plot([100 * x for x in xf], [rows[f"{x:g}"]["psnr"] for x in xf], **style)
            b.plot([100 * x for x in xf], [rows[f"{x:g}"]["ms_median"] for x in xf], **style)
    a.set(xlabel="resolution (%)", ylabel="PSNR (dB)", title="quality")
    b.set(xlabel="resolution (%)", ylabel="render time, median (ms)", title="price", yscale="log")
    a.grid(alpha=0.3)
    b.grid(alpha=0.3)
    a.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("models", nargs="+", help="LABEL=PATH")
    ap.add_argument("--dataset", required=True)
    ap.add_argument("--max-width", type=int, default=None)
    ap.add_argument("--res", default="0.1,0.2,0.3,0.4,0.5")
    ap.add_argument("--factors", default="1,2,3", help="comma-separated factors, each F or F:MAXRES (measured only "
                    "up to that resolution)")
    ap.add_argument("--views-every", type=int, default=1, help="every K-th test view [default: all]")
    ap.add_argument("--embedding-at", default=None, metavar="XI:E1,E2,...",
                    help="also render resolution XI plainly with the embedding told each E (anchor scenes)")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    sys.path.insert(0, str(REPO))
    from proxycodec.bench import machine_info, versions
    from proxycodec.threads import set_threads

    threads = set_threads()  # $PROXYCODEC_THREADS, else the usable cores

    models = {}
    for m in args.models:
        label, sep, path = m.partition("=")
        if not sep or not Path(path).exists():
            ap.error(f"{m!r}: give LABEL=PATH to an existing scene")
        models[label] = path
    res = [float(x) for x in args.res.split(",")]
    factors = {}
    for tok in args.factors.split(","):
        f, _, top = tok.partition(":")
        factors[int(f)] = float(top) if top else max(res)
    if 1 not in factors:
        ap.error("--factors must include 1 (the plain render the others are priced against)")
    t0 = time.time()
    data, loaded = load(models, args.dataset, args.max_width)
    out = run(models, loaded, data, res, factors, args.views_every, lambda s: print(s, flush=True))
    if args.embedding_at:
        xi, _, es = args.embedding_at.partition(":")
        out["embedding_probe"] = {"xi": float(xi), "psnr": embedding_probe(
            loaded, data, float(xi), [float(e) for e in es.split(",")], args.views_every,
            lambda s: print(s, flush=True))}
    out.update({"kind": "proxycodec.supersample", "dataset": args.dataset, "max_width": args.max_width,
                "machine": machine_info(), "versions": versions(), "threads": threads, "seed": None,
                "seconds": time.time() - t0,
                "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                "generated": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())})
    od = Path(args.out)
    od.mkdir(parents=True, exist_ok=True)
    (od / "supersample.json").write_text(json.dumps(out, indent=1))
    md = markdown(out)
    if "embedding_probe" in out:
        ep = out["embedding_probe"]
        md += (f"\nThe plain render at {ep['xi']:g} with the embedding told another resolution (PSNR dB):\n\n"
               + "\n".join(f"- {label}: " + ", ".join(f"told {e}: {p:.2f}" for e, p in vals.items())
                           for label, vals in ep["psnr"].items()) + "\n")
    (od / "supersample.md").write_text(f"# Supersampling: {args.dataset}\n\n{md}")
    plot(out, od / "supersample.png")
    print(md)
    print(f"wrote {od}/supersample.json, supersample.md, supersample.png in {time.time() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
