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
whole multiple of the target's size within 100%: a render on most iterations). Reported per rule (medians over
repeats): the training seconds per iteration of the run, split into the student's and the targets' (each target
fetch is timed: the teacher renders inside it); the steady state (the student plus the targets after the first
epoch, when "full" has every 100% render cached) and its ratio to "full" measured in the same run; the peak RSS.
The quality of the encodes is not measured here (it needs the whole encode and the test photos: SPEC.md section 4,
2026-11-25, has the figures and the commands).

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
    """A child process: one distillation; puts (seconds of training, iterations, wall seconds, peak RSS MB, the
    seconds of each target fetch in order)."""
    from proxycodec import codec
    from proxycodec.distill import TeacherViews
    from proxycodec.model import SceneModel
    from proxycodec.threads import set_threads

    set_threads(threads)
    fetches: list[float] = []
    make = TeacherViews.targets

    def timed_targets(self, max_bytes):  # the trainer's targets, each fetch timed (the teacher renders inside)
        inner = make(self, max_bytes)

        class Timed:
            def get(self, i, xi):
                t = time.perf_counter()
                out = inner.get(i, xi)
                fetches.append(time.perf_counter() - t)
                return out
        return Timed()

    TeacherViews.targets = timed_targets
    model = SceneModel.load(scene)
    cfg = codec.EncodeConfig(distill_iters=iters, distill_targets=rule, seed=seed)
    t0 = time.perf_counter()
    res = codec._distill(model, (None, None), cfg, lambda s: None)
    wall = time.perf_counter() - t0
    queue.put((res.seconds, res.iterations, wall, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
               fetches, len(res.views.train_indices)))


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
            seconds, iterations, wall, rss, fetches, epoch = q.get()
            p.join()
            later = fetches[epoch:] or fetches  # after the first epoch the 100% renders are all cached
            student = (seconds - sum(fetches)) / iterations
            row = {"repeat": rep, "train_s": seconds, "iterations": iterations, "wall_s": wall, "peak_rss_mb": rss,
                   "s_per_iter": seconds / iterations, "targets_s": sum(fetches),
                   "target_s_per_iter_after_epoch1": float(np.mean(later)), "student_s_per_iter": student,
                   "steady_s_per_iter": student + float(np.mean(later))}
            runs[rule].append(row)
            print(f"repeat {rep} {rule:5s}: {row['s_per_iter'] * 1e3:7.1f} ms/iteration ({seconds:.1f} s training, "
                  f"{wall:.1f} s with setup); targets after the first epoch "
                  f"{row['target_s_per_iter_after_epoch1'] * 1e3:.1f} ms, the student {student * 1e3:.1f} ms; "
                  f"peak RSS {rss:.0f} MB", flush=True)
    summary = {r: {k: float(np.median([x[k] for x in runs[r]])) for k in
                   ("s_per_iter", "target_s_per_iter_after_epoch1", "student_s_per_iter", "steady_s_per_iter")}
               for r in RULES}
    for r in RULES:
        summary[r]["peak_rss_mb"] = float(max(x["peak_rss_mb"] for x in runs[r]))
        summary[r]["steady_vs_full"] = summary[r]["steady_s_per_iter"] / summary["full"]["steady_s_per_iter"]
    meta = {"scene": str(args.scene), "iters": args.iters, "repeats": args.repeats, "seed": args.seed,
            "machine": machine_info(), "versions": versions()}
    lines = [f"# Distillation target rules: time per iteration ({Path(args.scene).name})", "",
             f"{args.iters} iterations per run, {args.repeats} repeats, rules alternating, seed {args.seed}; "
             f"{meta['machine'].get('cpu_model', '?')}, {meta['machine'].get('cpu_count')} cores.", "",
             "Medians over repeats. The first epoch renders every view's 100% target under both rules; after it",
             "\"full\" reads them from its cache and \"whole\" renders most targets: the steady state (the student's",
             "time plus the targets' after the first epoch) is what a long distillation pays per iteration.", "",
             "| rule | ms / iteration (this run) | targets ms / it. after epoch 1 | student ms / it. | steady state "
             "ms / it. | steady vs full | peak RSS MB |", "|---|---:|---:|---:|---:|---:|---:|"]
    for r in RULES:
        s = summary[r]
        lines.append(f"| {r} | {s['s_per_iter'] * 1e3:.1f} | {s['target_s_per_iter_after_epoch1'] * 1e3:.1f} | "
                     f"{s['student_s_per_iter'] * 1e3:.1f} | {s['steady_s_per_iter'] * 1e3:.1f} | "
                     f"{s['steady_vs_full']:.2f}x | {s['peak_rss_mb']:.0f} |")
    if quality is not None:
        n_views = len(quality["views"])
        lines += ["", f"Targets against the photos of {args.dataset} ({n_views} test views), PSNR dB:", "",
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
        st, tg = summary[r]["student_s_per_iter"] * 1e3, summary[r]["target_s_per_iter_after_epoch1"] * 1e3
        ax.bar(k, st, color="#999999", width=0.6, label="the student" if k == 0 else None)
        ax.bar(k, tg, bottom=st, color="#3366aa", width=0.6, label="targets (teacher renders)" if k == 0 else None)
        ys = [x["steady_s_per_iter"] * 1e3 for x in runs[r]]
        ax.scatter([k] * len(ys), ys, color="k", s=10, zorder=3)
    ax.set_xticks(range(len(RULES)), [f"{r}\n({summary[r]['steady_vs_full']:.2f}x)" for r in RULES])
    ax.set_ylabel("ms per iteration, steady state")
    ax.legend(fontsize=8, loc="lower right")
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
