"""The time price of distillation's target rules (``encode --distill-targets``), measured side by side.

    python benchmarks/distill_targets.py lego_np.ply                       # a fitted anchor scene without proxies
    python benchmarks/distill_targets.py lego_np.ply --iters 300 --repeats 3 --seed 0
    python benchmarks/distill_targets.py lego_np.ply --dataset ../shared/data/nerf_synthetic/lego --max-width 400

With ``--dataset``, first how close each rule's targets are to the photos on the dataset's test views (PSNR at
10%..100% against ``load_image``, as ``proxycodec eval`` scores): the teacher's own render at xi ("same xi"), its 100%
render area-averaged ("full") and the whole-multiple rule ("whole"). No training: this is what a student trained on
those targets could at best inherit.

Each repeat runs the same distillation (encode's configuration, ``--iters`` iterations, the same seed) once per rule,
the rules alternating, each in a fresh child process (its own peak RSS): "full" (the teacher's 100% render
box-filtered down by any ratio; the one render per view is cached) and "whole" (the teacher renders at the largest
whole multiple of the target's size within 100%: a render on most iterations). Reported per rule: the median over
repeats of the training seconds per iteration (the teacher's renders are inside them: the trainer fetches its target
in each step), the ratio to "full" measured in the same run, and the peak RSS. Quality is not measured here (it needs
the whole encode and the test photos: SPEC.md section 4, "Session 16", has the figures and the commands).

Outputs in ``--out`` (default ``benchmarks/results/distill_targets``): ``distill_targets.json`` (every figure,
machine, versions, seed), ``distill_targets.md`` and ``distill_targets.png``.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import resource
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
RULES = ("full", "whole")


def _one(scene: str, rule: str, iters: int, seed: int, threads: int | None, queue) -> None:
    """A child process: one distillation; puts (seconds of training, iterations, wall seconds, peak RSS MB)."""
    from proxycodec import codec
    from proxycodec.model import SceneModel
    from proxycodec.threads import set_threads

    set_threads(threads)
    model = SceneModel.load(scene)
    cfg = codec.EncodeConfig(distill_iters=iters, distill_targets=rule, seed=seed)
    t0 = time.perf_counter()
    res = codec._distill(model, (None, None), cfg, lambda s: None)
    wall = time.perf_counter() - t0
    queue.put((res.seconds, res.iterations, wall, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0))


def target_quality(scene: str, dataset: str, max_width: int | None, views: int | None) -> dict:
    """PSNR against the photos of the three candidate targets, per resolution (10%..100%), over the test views."""
    import torch

    from proxycodec.distill import TeacherViews
    from proxycodec.formats.datasets import load_dataset
    from proxycodec.metrics import psnr
    from proxycodec.model import SceneModel

    model = SceneModel.load(scene)
    data = load_dataset(dataset, max_width=max_width)
    idx = data.test_indices[:views] if views else data.test_indices
    cams = [data.cameras[i] for i in idx]
    rules = {r: TeacherViews(model, cams, targets=r, held_out=list(range(len(cams)))) for r in RULES}
    xis = [round(0.1 * k, 1) for k in range(1, 11)]
    out: dict[str, list[float]] = {"same xi": [], **{r: [] for r in RULES}}
    for xi in xis:
        acc: dict[str, list[float]] = {k: [] for k in out}
        for j, i in enumerate(idx):
            gt = data.load_image(i, xi).numpy()
            with torch.no_grad():
                acc["same xi"].append(psnr(model.render(cams[j], xi).image.clamp(0, 1).numpy(), gt))
            for r, v in rules.items():
                acc[r].append(psnr(v.load_image(j, xi).numpy(), gt))
        for k in out:
            out[k].append(float(np.mean(acc[k])))
        print(f"targets vs photos at {xi:.1f}: " + "  ".join(f"{k} {out[k][-1]:.2f}" for k in out), flush=True)
    return {"xi": xis, "views": [int(i) for i in idx], "psnr": out}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene", help="an anchor PLY (+ weights sidecar) without a stage-2 predictor")
    ap.add_argument("--iters", type=int, default=300)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=None, help="torch threads [default: PROXYCODEC_THREADS or cores].")
    ap.add_argument("--out", default=None)
    ap.add_argument("--dataset", default=None, help="also score each rule's targets against this dataset's photos")
    ap.add_argument("--max-width", type=int, default=None, help="the dataset's 100%% width (as fit/eval --max-width)")
    ap.add_argument("--views", type=int, default=None, help="test views for the target scores [default: all]")
    args = ap.parse_args(argv)
    if args.iters < 1 or args.repeats < 1:
        ap.error("--iters and --repeats must be >= 1")
    if str(REPO) not in sys.path:
        sys.path.insert(0, str(REPO))
    from proxycodec.bench import machine_info, versions
    from proxycodec.fileio import atomic_write

    out = Path(args.out) if args.out else REPO / "benchmarks" / "results" / "distill_targets"
    out.mkdir(parents=True, exist_ok=True)
    quality = None
    if args.dataset:
        from proxycodec.threads import set_threads

        set_threads(args.threads)
        quality = target_quality(args.scene, args.dataset, args.max_width, args.views)
    ctx = mp.get_context("spawn")
    runs: dict[str, list[dict]] = {r: [] for r in RULES}
    for rep in range(args.repeats):
        for rule in RULES if rep % 2 == 0 else RULES[::-1]:
            q = ctx.Queue()
            p = ctx.Process(target=_one, args=(args.scene, rule, args.iters, args.seed, args.threads, q))
            p.start()
            seconds, iterations, wall, rss = q.get()
            p.join()
            row = {"repeat": rep, "train_s": seconds, "iterations": iterations, "wall_s": wall, "peak_rss_mb": rss,
                   "s_per_iter": seconds / iterations}
            runs[rule].append(row)
            print(f"repeat {rep} {rule:5s}: {row['s_per_iter'] * 1e3:7.1f} ms/iteration ({seconds:.1f} s training, "
                  f"{wall:.1f} s with setup), peak RSS {rss:.0f} MB", flush=True)
    summary = {r: {"median_s_per_iter": float(np.median([x["s_per_iter"] for x in runs[r]])),
                   "peak_rss_mb": float(max(x["peak_rss_mb"] for x in runs[r]))} for r in RULES}
    for r in RULES:
        summary[r]["vs_full"] = summary[r]["median_s_per_iter"] / summary["full"]["median_s_per_iter"]
    meta = {"scene": str(args.scene), "iters": args.iters, "repeats": args.repeats, "seed": args.seed,
            "machine": machine_info(), "versions": versions()}
    lines = [f"# Distillation target rules: time per iteration ({Path(args.scene).name})", "",
             f"{args.iters} iterations per run, {args.repeats} repeats, rules alternating, seed {args.seed}; "
             f"{meta['machine'].get('cpu_model', '?')}, {meta['machine'].get('cpu_count')} cores.", "",
             "| rule | median ms / iteration | vs full | peak RSS MB |", "|---|---:|---:|---:|"]
    for r in RULES:
        s = summary[r]
        lines.append(f"| {r} | {s['median_s_per_iter'] * 1e3:.1f} | {s['vs_full']:.2f}x | {s['peak_rss_mb']:.0f} |")
    if quality is not None:
        lines += ["", f"Targets against the photos of {args.dataset} ({len(quality['views'])} test views), PSNR dB:", "",
                  "| target | " + " | ".join(f"{x:.0%}" for x in quality["xi"]) + " | mean |",
                  "|---|" + "---:|" * (len(quality["xi"]) + 1)]
        for k, v in quality["psnr"].items():
            lines.append(f"| {k} | " + " | ".join(f"{x:.2f}" for x in v) + f" | {np.mean(v):.2f} |")
    md = "\n".join(lines) + "\n"
    print("\n" + md)
    with atomic_write(out / "distill_targets.json") as f:
        f.write(json.dumps({**meta, "runs": runs, "summary": summary, "target_quality": quality}, indent=2).encode())
    with atomic_write(out / "distill_targets.md") as f:
        f.write(md.encode())
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2 if quality else 1, figsize=(10 if quality else 4.5, 3.4), squeeze=False)
    ax = axes[0, 0]
    for k, r in enumerate(RULES):
        ys = [x["s_per_iter"] * 1e3 for x in runs[r]]
        ax.bar(k, summary[r]["median_s_per_iter"] * 1e3, color=("#999999", "#3366aa")[k], width=0.6)
        ax.scatter([k] * len(ys), ys, color="k", s=10, zorder=3)
    ax.set_xticks(range(len(RULES)), [f"{r}\n({summary[r]['vs_full']:.2f}x)" for r in RULES])
    ax.set_ylabel("ms per distillation iteration")
    ax.set_title("teacher target rule: time price", fontsize=10)
    if quality:
        qa = axes[0, 1]
        for k, v in quality["psnr"].items():
            qa.plot(quality["xi"], v, marker="o", label=k)
        qa.set_xlabel("resolution ratio xi")
        qa.set_ylabel("PSNR vs photos (dB)")
        qa.set_title("targets against the photos", fontsize=10)
        qa.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "distill_targets.png", dpi=120)
    plt.close(fig)
    print(f"wrote {out / 'distill_targets.json'}, .md, .png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
