"""What one training step dispatches: torch operations per iteration, by trainer and stage, and where they come from.

    python benchmarks/step_ops.py [DATASET] [--max-width 60] [--steps 3] [--timed 10] [--out DIR]

On a GPU every dispatched operation is at least one kernel launch (~5-20 us of host time each), and every operation
whose output size depends on the data (``nonzero``, boolean masks, ``.item()``) waits for the device to catch up. A
fit whose step dispatches thousands of small operations is launch-bound there whatever the GPU, which is what
``gpu.py`` measured (ours 14.9 it/s, our 3DGS trainer 67 it/s on an H100; benchmarks/README.md, "GPU runs"). The
count does not depend on the device, so it is measured here on the CPU, at a tiny image size (60 px) where the
figures are counts, not timings.

For our anchor fit in stage 1 and in stage 2 (its defaults, rate term included) and for ``fit --explicit``: the
operations per step (every ``__torch_dispatch__`` call, backward included), those that synchronise on a GPU, and
the source lines of proxycodec that dispatch the most (the backward pass is one line: ``loss.backward()``), and the
median wall time of ``--timed`` uncounted steps (at 60 px mostly the host's dispatch; at 800 px the numba rasterizer's,
which moves from run to run on a shared machine by more than a step's torch side). Writes
``step_ops.json`` (machine, versions, seed, every count, peak RSS) and prints the table. DATASET defaults to bonsai
in ``../shared/data`` (skipped with a reason when absent); any dataset ``fit`` reads will do.
"""

from __future__ import annotations

import argparse
import collections
import json
import resource
import statistics
import sys
import time
import traceback
from pathlib import Path

HERE = Path(__file__).resolve().parent
DEFAULT_DATA = HERE.parent.parent / "shared" / "data" / "mipnerf360" / "bonsai"
#: Operations that only make a new view of a tensor (or detach one): dispatched, but no kernel runs on a GPU.
VIEWS = {"detach", "t", "view", "_unsafe_view", "slice", "select", "as_strided", "transpose", "expand", "unsqueeze",
         "squeeze", "permute", "alias", "lift_fresh", "split", "split_with_sizes", "unbind", "narrow", "diagonal",
         "_reshape_alias", "unfold", "numpy_T", "real", "view_as_real", "_to_copy_view"}
#: Operations whose output size (or a host value) depends on the data: a host-device synchronisation on a GPU.
SYNCING = {"nonzero", "masked_select", "unique", "_unique2", "item", "_local_scalar_dense", "is_nonzero",
           "masked_scatter", "repeat_interleave"}


def count_ops(step, n: int) -> dict:
    """Run ``step`` ``n`` times under a dispatch mode -> per-step operation counts, by op name and by source line."""
    from proxycodec.bench.ops import dispatch_counter

    by_line = collections.Counter()

    def where(_name):
        own = [f for f in traceback.extract_stack(limit=40) if "/proxycodec/" in f.filename.replace("\\", "/")
               and not f.filename.replace("\\", "/").endswith("/bench/ops.py")]  # the counter's own frame
        f = own[-1] if own else None
        by_line[f"{f.filename.replace(chr(92), '/').split('/proxycodec/')[-1]}:{f.lineno} {f.name}" if f
                else "(outside proxycodec)"] += 1

    t = time.perf_counter()
    with dispatch_counter(where) as counter:
        for _ in range(n):
            step()
    by_op = counter.counts
    seconds = (time.perf_counter() - t) / n
    total = sum(by_op.values())
    return {"ops_per_step": round(total / n, 1),
            "kernel_ops_per_step": round(sum(c for k, c in by_op.items() if k not in VIEWS) / n, 1),
            "syncing_per_step": round(sum(c for k, c in by_op.items() if k in SYNCING) / n, 1),
            "syncing": {k: round(c / n, 1) for k, c in sorted(by_op.items()) if k in SYNCING},
            "top_ops": {k: round(c / n, 1) for k, c in by_op.most_common(12)},
            "top_lines": {k: round(c / n, 1) for k, c in by_line.most_common(15)},
            "by_op": {k: round(c / n, 1) for k, c in sorted(by_op.items())},
            "seconds_per_step_counting": round(seconds, 4)}


def time_steps(step, n: int) -> float:
    """Median wall seconds of ``n`` uncounted steps (at this tiny size, mostly the host's dispatch of each op)."""
    times = []
    for _ in range(n):
        t = time.perf_counter()
        step()
        times.append(time.perf_counter() - t)
    return round(statistics.median(times), 5)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dataset", nargs="?", default=str(DEFAULT_DATA))
    ap.add_argument("--max-width", type=int, default=60)
    ap.add_argument("--steps", type=int, default=3, help="steps counted per case (after 2 warm-up steps)")
    ap.add_argument("--timed", type=int, default=10, help="uncounted steps timed per case (median)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=str(HERE / "results" / "step_ops"))
    a = ap.parse_args(argv)
    if not Path(a.dataset).is_dir():
        print(f"skipped: {a.dataset}: no dataset there (../shared/data absent?)", file=sys.stderr)
        return 0
    from proxycodec.formats.datasets import load_dataset

    from proxycodec.bench import machine_info, versions
    from proxycodec.explicit import ExplicitConfig, ExplicitTrainer
    from proxycodec.threads import set_threads
    from proxycodec.train import FitConfig, Trainer

    set_threads(1)
    data = load_dataset(a.dataset, max_width=a.max_width)
    res = {"machine": machine_info(), "versions": versions(), "seed": a.seed, "dataset": a.dataset,
           "max_width": a.max_width, "steps": a.steps, "cases": {}}
    ours = Trainer(data, FitConfig(iters=40, seed=a.seed))
    for _ in range(2):
        ours.train_step()
    res["cases"]["ours, stage 1"] = count_ops(ours.train_step, a.steps)
    res["cases"]["ours, stage 1"]["seconds_per_step"] = time_steps(ours.train_step, min(a.timed, 8))
    while ours.stage < 2:
        ours.train_step()
    ours.train_step()
    res["cases"]["ours, stage 2"] = count_ops(ours.train_step, a.steps)
    res["cases"]["ours, stage 2"]["seconds_per_step"] = time_steps(ours.train_step, a.timed)
    res["cases"]["ours, stage 2"]["anchors"] = ours.anchors.num_anchors
    tdgs = ExplicitTrainer(data, ExplicitConfig(iters=40, seed=a.seed))
    for _ in range(2):
        tdgs.train_step()
    res["cases"]["3DGS (fit --explicit)"] = count_ops(tdgs.train_step, a.steps)
    res["cases"]["3DGS (fit --explicit)"]["seconds_per_step"] = time_steps(tdgs.train_step, a.timed)
    res["peak_rss_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "step_ops.json.tmp").write_text(json.dumps(res, indent=2))
    (out / "step_ops.json.tmp").replace(out / "step_ops.json")
    print("| case | ops / step | of them not views | syncing / step | ms / step (median) "
          "| top source lines (ops / step) |\n|---|---:|---:|---:|---:|---|")
    for name, c in res["cases"].items():
        lines = "; ".join(f"{k} {v:g}" for k, v in list(c["top_lines"].items())[:5])
        print(f"| {name} | {c['ops_per_step']:,.0f} | {c['kernel_ops_per_step']:,.0f} | {c['syncing_per_step']:g} | "
              f"{1000 * c['seconds_per_step']:.1f} | {lines} |")
    print(f"wrote {out / 'step_ops.json'}; peak RSS {res['peak_rss_mb']} MB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
