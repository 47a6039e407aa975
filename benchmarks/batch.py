"""`proxycodec batch encode` over four kinds of scene, one after another, on a local Ray and on a two-node Ray
cluster on this machine: the summary of each and their wall times side by side.

    python benchmarks/batch.py lego_np.ply --options="--distill-iters 50"

The four inputs: the built-in scene (``proxycodec sample``), an anchor scene without proxies given on the command
line (lego's ``fit --no-proxies``), a plain 3DGS PLY (the built-in scene decoded and exported with ``decode --ply``,
which ``encode`` converts first) and a trained Scaffold-GS output folder (the one ``tests/test_scaffold_import.py``
writes). The same options go to every task (``--options``). Each way runs in a fresh output folder; the containers of
the three ways are compared byte for byte (each task runs with one thread, as ``--cpus-per-task 1`` asks).

Outputs in ``--out`` (default ``benchmarks/results/batch``): ``batch.json`` (every record, machine, versions, wall
times, peak RSS) and ``batch.md``.
"""

from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def make_inputs(work: Path, anchor_scene: str) -> list[str]:
    """The four inputs, made in ``work`` (the sample, its 3DGS export, a Scaffold-GS output) plus ``anchor_scene``."""
    work.mkdir(parents=True, exist_ok=True)
    run = lambda *a: subprocess.run([sys.executable, "-m", "proxycodec.cli", *a], check=True,  # noqa: E731
                                    capture_output=True, text=True)
    sample = work / "sample.ply"
    if not sample.exists():
        run("sample", str(sample))
    splats = work / "splats.ply"
    if not splats.exists():
        run("encode", str(sample), "-o", str(work / "sample_for_export.pxc"), "--no-distill", "--predictor-iters", "200",
            "--entropy", "zstd")
        run("decode", str(work / "sample_for_export.pxc"), "--no-render", "--ply", str(splats))
    scaffold = work / "scaffold_output"
    if not scaffold.exists():
        sys.path.insert(0, str(REPO / "tests"))
        from test_scaffold_import import scaffold_mlps, write_output  # noqa: PLC0415

        write_output(scaffold, scaffold_mlps())
    return [str(sample), str(anchor_scene), str(splats), str(scaffold)]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("anchor_scene", help="an anchor PLY without proxies (e.g. fit --no-proxies)")
    ap.add_argument("--options", default="--distill-iters 50", help="encode options for every task (one string)")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    if str(REPO) not in sys.path:
        sys.path.insert(0, str(REPO))
    from proxycodec.batch import local_ray_on_loopback, plan, run_batch, summary_markdown
    from proxycodec.bench import machine_info, versions
    from proxycodec.fileio import atomic_write

    out = Path(args.out) if args.out else REPO / "benchmarks" / "results" / "batch"
    inputs = make_inputs(out / "inputs", args.anchor_scene)
    options = shlex.split(args.options)
    local_ray_on_loopback()  # a local Ray and a two-node cluster on this machine: on 127.0.0.1
    import ray

    runs = {}

    def one(way: str, threads: int | None = 1, **kw) -> None:
        folder = out / way
        if folder.exists():
            import shutil

            shutil.rmtree(folder)
        t0 = time.perf_counter()
        records, how = run_batch(plan("encode", inputs, folder, options, threads=threads), cpus_per_task=1,
                                 say=lambda s: print(f"{way}: {s}", file=sys.stderr, flush=True), **kw)
        runs[way] = {"wall_seconds": time.perf_counter() - t0, "how": how, "records": records,
                     "markdown": summary_markdown(records, how)}
        print(runs[way]["markdown"], flush=True)

    one("one_by_one_all_cores", threads=None, use_ray=False)  # each command with its own default threads
    one("one_by_one", use_ray=False)
    one("local_ray", use_ray=True)  # a local Ray started in this process with the machine's cores
    from ray.cluster_utils import Cluster

    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1})
    try:
        cluster.add_node(num_cpus=1)
        ray.init(address=cluster.address, log_to_driver=False)
        one("two_node_cluster", use_ray=True)
    finally:
        ray.shutdown()
        cluster.shutdown()
    same = {}
    for i, name in enumerate(r["name"] for r in runs["one_by_one"]["records"]):
        blobs = []
        for way in ("one_by_one", "local_ray", "two_node_cluster"):  # one thread per task in each
            rec = runs[way]["records"][i]
            blobs.append(Path(rec["output"]).read_bytes() if rec["status"] == "ok" else None)
        same[name] = all(b is not None and b == blobs[0] for b in blobs)
    lines = [f"# `proxycodec batch encode`, three ways ({machine_info().get('cpu_model', '?')}, "
             f"{machine_info().get('cpu_count')} cores)", "", f"Options: `{args.options}`; one thread per task, except one_by_one_all_cores (each command's own "
             f"default: the machine's cores).", "",
             "| way | wall s | tasks ok | engine |", "|---|---:|---:|---|"]
    for way, r in runs.items():
        lines.append(f"| {way} | {r['wall_seconds']:.1f} | {sum(x['status'] == 'ok' for x in r['records'])}/"
                     f"{len(r['records'])} | {r['how']['engine']}"
                     + (f", {r['how'].get('nodes')} node(s)" if r['how']['engine'] == 'ray' else "") + " |")
    lines += ["", "Containers identical in the three one-thread ways: " + ", ".join(f"{k} {'yes' if v else 'NO'}"
                                                                        for k, v in same.items()), ""]
    for way, r in runs.items():
        lines += [f"## {way}", "", r["markdown"]]
    md = "\n".join(lines) + "\n"
    print(md)
    with atomic_write(out / "batch.json", "w") as fh:
        json.dump({"machine": machine_info(), "versions": versions(), "options": args.options, "inputs": inputs,
                   "identical": same, "runs": {k: {kk: vv for kk, vv in v.items() if kk != "markdown"}
                                               for k, v in runs.items()}}, fh, indent=1)
    with atomic_write(out / "batch.md", "w") as fh:
        fh.write(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
