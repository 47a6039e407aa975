"""Several ``proxycodec eval`` reports side by side: PSNR per resolution, the mean, and each one's margin over a baseline.

    python benchmarks/compare_evals.py ours=runs/bonsai800/eval10/eval.json 3dgs=runs/bonsai3dgs/eval10/eval.json \\
        --baseline 3dgs --paper mipnerf360 --out benchmarks/results/bonsai800/equal_time

Each argument is LABEL=EVAL_JSON (an ``eval`` report's ``eval.json``); every report must cover the same resolutions
and test views (refused otherwise, with the file named). ``--baseline LABEL`` adds, per report, the PSNR margin over
that report at each resolution, its minimum and its mean (the equal-time acceptance of a comparison reads those).
``--paper mipnerf360`` adds the paper's Mip-NeRF 360 rows (supplement Table 12, mean of 9 scenes) for reference.
``--bytes LABEL=N`` records a stored size per report (shown, and in the JSON).

Writes ``compare.json`` (every figure, the inputs' paths and summaries), ``compare.md`` (the table) and
``psnr_vs_resolution.png`` in ``--out``; prints the table. Reads nothing but the reports: no scene, no GPU, seconds.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

#: The paper's per-resolution PSNR on Mip-NeRF 360, 10%..100% (supplement Table 12, mean of 9 scenes).
PAPER = {
    "mipnerf360": {
        "paper: ours (Mip-NeRF 360 mean)": [29.74, 30.31, 29.45, 28.68, 28.08, 27.64, 27.31, 27.06, 26.87, 26.71],
        "paper: 3D-GS (Mip-NeRF 360 mean)": [21.78, 24.97, 26.46, 27.05, 27.21, 27.17, 27.02, 26.84, 26.65, 26.47],
    },
}
PAPER_XI = [0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0]


def load_report(label: str, path: Path) -> dict:
    """The per-resolution PSNR/SSIM of one ``eval.json``; one-line errors naming the file."""
    try:
        rep = json.loads(path.read_text())
        per = rep["per_resolution"]
        xi = [round(float(d["xi"]), 6) for d in per]
        psnr = [float(d["psnr"]) for d in per]
        ssim = [float(d["ssim"]) for d in per]
        views = rep.get("views")
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise SystemExit(f"error: {path}: not a proxycodec eval report ({type(e).__name__}: {e})") from None
    if not all(math.isfinite(v) for v in psnr):
        raise SystemExit(f"error: {path}: non-finite PSNR in the report")
    return {"label": label, "path": str(path), "xi": xi, "psnr": psnr, "ssim": ssim, "views": views,
            "summary": rep.get("summary", {}), "scene": rep.get("scene"), "dataset": rep.get("dataset")}


def compare(reports: list[dict], baseline: str | None = None) -> dict:
    """Means and, against ``baseline``, the margins per resolution (their minimum and mean)."""
    xi = reports[0]["xi"]
    for r in reports[1:]:
        if r["xi"] != xi:
            raise SystemExit(f"error: {r['path']}: resolutions {r['xi']} differ from {reports[0]['path']}'s {xi}")
        if r["views"] != reports[0]["views"]:
            raise SystemExit(f"error: {r['path']}: test views differ from {reports[0]['path']}'s")
    base = None
    if baseline is not None:
        base = next((r for r in reports if r["label"] == baseline), None)
        if base is None:
            raise SystemExit(f"error: --baseline {baseline!r} is none of the labels {[r['label'] for r in reports]}")
    for r in reports:
        r["psnr_mean"] = sum(r["psnr"]) / len(r["psnr"])
        r["ssim_mean"] = sum(r["ssim"]) / len(r["ssim"])
        if base is not None and r is not base:
            m = [a - b for a, b in zip(r["psnr"], base["psnr"])]
            r["margin"] = {"baseline": baseline, "per_resolution": m, "min": min(m), "mean": sum(m) / len(m)}
    return {"xi": xi, "baseline": baseline, "reports": reports}


def markdown(res: dict, paper: dict[str, list[float]], sizes: dict[str, int]) -> str:
    xi = res["xi"]
    head = "| | " + " | ".join(f"{round(x * 100)}%" for x in xi) + " | mean | bytes |"
    lines = [head, "|---|" + "---:|" * (len(xi) + 2)]
    for r in res["reports"]:
        b = sizes.get(r["label"])
        lines.append(f"| {r['label']} | " + " | ".join(f"{v:.2f}" for v in r["psnr"])
                     + f" | **{r['psnr_mean']:.2f}** | {'' if b is None else f'{b:,}'} |")
    for r in res["reports"]:
        if "margin" in r:
            m = r["margin"]
            lines.append(f"| {r['label']} - {m['baseline']} | " + " | ".join(f"{v:+.2f}" for v in m["per_resolution"])
                         + f" | **{m['mean']:+.2f}** (min {m['min']:+.2f}) | |")
    if paper and xi == PAPER_XI:
        for name, row in paper.items():
            lines.append(f"| {name} | " + " | ".join(f"{v:.2f}" for v in row) + f" | {sum(row) / len(row):.2f} | |")
    return "\n".join(lines) + "\n"


def plot(res: dict, paper: dict[str, list[float]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    pct = [x * 100 for x in res["xi"]]
    for r in res["reports"]:
        ax.plot(pct, r["psnr"], marker="o", label=f"{r['label']} (mean {r['psnr_mean']:.2f})")
    if paper and res["xi"] == PAPER_XI:
        for name, row in paper.items():
            ax.plot(pct, row, linestyle="--", color="grey" if "3D-GS" in name else "black", alpha=0.6, label=name)
    ax.set_xlabel("resolution (% of the reference width)")
    ax.set_ylabel("PSNR (dB), held-out views")
    first = res["reports"][0]  # titled by the dataset (its folder's name), else the evaluated file's stem
    name = Path(first["dataset"]).name if first.get("dataset") else (first.get("scene") or "")
    ax.set_title(f"{name}: PSNR against resolution")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    tmp = path.with_suffix(".tmp.png")
    fig.savefig(tmp, dpi=120)
    plt.close(fig)
    tmp.replace(path)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("reports", nargs="+", metavar="LABEL=EVAL_JSON")
    ap.add_argument("--baseline", default=None, help="label whose PSNR the others' margins are measured against")
    ap.add_argument("--paper", choices=sorted(PAPER), default=None, help="add the paper's rows for this dataset")
    ap.add_argument("--bytes", action="append", default=[], metavar="LABEL=N", help="stored size of a report's scene")
    ap.add_argument("--out", required=True, help="folder for compare.json, compare.md, psnr_vs_resolution.png")
    a = ap.parse_args(argv)
    reports = []
    for spec in a.reports:
        label, sep, path = spec.partition("=")
        if not sep or not label or not path:
            raise SystemExit(f"error: {spec!r}: expected LABEL=EVAL_JSON")
        reports.append(load_report(label, Path(path)))
    sizes = {}
    for spec in a.bytes:
        label, sep, n = spec.partition("=")
        if not sep or not n.isdigit():
            raise SystemExit(f"error: --bytes {spec!r}: expected LABEL=N")
        sizes[label] = int(n)
    res = compare(reports, a.baseline)
    paper = PAPER.get(a.paper, {}) if a.paper else {}
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    md = markdown(res, paper, sizes)
    (out / "compare.md").write_text(md)
    doc = {**res, "bytes": sizes, "paper": paper}
    tmp = out / "compare.json.tmp"
    tmp.write_text(json.dumps(doc, indent=1))
    tmp.replace(out / "compare.json")
    plot(res, paper, out / "psnr_vs_resolution.png")
    sys.stdout.write(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
