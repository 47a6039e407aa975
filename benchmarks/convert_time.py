"""Conversion's quality against its training time: ``benchmarks/convert.py`` on one 3DGS PLY at several time budgets.

    python benchmarks/convert_time.py --input bonsai=3dgs.ply --max-width 800 --budgets 600,1200,2400 --out DIR

Each budget runs ``convert.py --scenes SCENE --input SCENE=PLY --max-width W --fit iters=null --fit time_budget=B
--out DIR/tB`` (a run whose results are complete is not repeated: delete ``DIR/tB`` to redo it). Then one row per
budget: iterations, the container's bytes and its ratio to the SPZ, PSNR against the source's anti-aliased renders
(10%, 100%, the average over 10%..100%) and against the photos, and peak RSS. A least-squares line through (log2
seconds, average PSNR) gives the dB one doubling of the time buys, and the time that line reaches ``--bar`` dB at:
a trend of the points measured, not a promise beyond them. Outputs in ``DIR``: ``convert_time.json`` (machine,
versions, seed, every figure), ``convert_time.md``, ``psnr_vs_time.png``. Each run should be alone on the machine
(the budgets are wall-clock time).
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
from pathlib import Path

from proxycodec.fileio import atomic_write, write_bytes_atomic

REPO = Path(__file__).resolve().parents[1]
CONVERTED = "proxycodec (converted)"


def _done(path: Path, scene: str) -> bool:
    if not path.is_file():
        return False
    steps = json.loads(path.read_text()).get("steps", {})
    return all(steps.get(f"{scene}/vs {ref}: {CONVERTED}", {}).get("status") == "ok" for ref in ("source", "photos"))


def row(results: dict, scene: str, budget: float) -> dict:
    """The figures of one ``convert.py`` run (its results.json)."""
    s = results["steps"]
    conv = s[f"{scene}/convert + encode"]["result"]
    src = s[f"{scene}/vs source: {CONVERTED}"]["result"]
    photos = s[f"{scene}/vs photos: {CONVERTED}"]["result"]
    spz = s.get(f"{scene}/spz", {}).get("result") or {}
    pr = src["per_resolution"]
    return {"budget_s": budget, "iterations": conv["convert"]["iterations"],
            "train_s": conv["convert"]["seconds"]["train"], "convert_encode_s": conv["seconds"],
            "anchors": conv["anchors"], "bytes": conv["bytes"], "spz_bytes": spz.get("bytes"),
            "spz_ratio": spz["bytes"] / conv["bytes"] if spz.get("bytes") else None,
            "psnr_source_avg": src["psnr_avg"], "psnr_source_10": pr[0]["psnr"], "psnr_source_100": pr[-1]["psnr"],
            "psnr_source": {str(p["xi"]): p["psnr"] for p in pr}, "psnr_photos_avg": photos["psnr_avg"],
            "peak_rss_mb": conv["peak_rss_mb"], "machine": results["meta"]["machine"],
            "versions": results["meta"]["versions"], "seed": results["meta"]["seed"]}


def trend(rows: list[dict], bar: float) -> dict | None:
    """Least squares of the average PSNR on log2(training seconds): dB per doubling, and where it reaches ``bar``."""
    if len(rows) < 2:
        return None
    xs = [math.log2(r["train_s"]) for r in rows]
    ys = [r["psnr_source_avg"] for r in rows]
    mx, my = sum(xs) / len(xs), sum(ys) / len(ys)
    sxx = sum((x - mx) ** 2 for x in xs)
    slope = sum((x - mx) * (y - my) for x, y in zip(xs, ys)) / sxx
    out = {"db_per_doubling": slope, "intercept_db_at_1s": my - slope * mx, "bar_db": bar,
           "residuals_db": [y - (my + slope * (x - mx)) for x, y in zip(xs, ys)]}
    out["seconds_to_bar"] = 2.0 ** (mx + (bar - my) / slope) if slope > 0 else None
    return out


def markdown(scene: str, ply: str, rows: list[dict], tr: dict | None) -> str:
    machine = rows[0]["machine"]
    lines = [f"# Conversion against training time ({scene}; benchmarks/convert_time.py)", "",
             f"Input: `{ply}`. Machine: {machine.get('cpu_model')}, {machine['cpu_count']} cores; "
             f"torch {rows[0]['versions']['torch']}; seed {rows[0]['seed']}.", "",
             "| budget (s) | iterations | anchors | bytes | SPZ / container | 10% | 100% | avg vs source "
             "| avg vs photos | peak RSS (MB) |", "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        ratio = f"{r['spz_ratio']:.2f}" if r["spz_ratio"] else "-"
        lines.append(f"| {r['budget_s']:g} | {r['iterations']:,} | {r['anchors']:,} | {r['bytes']:,} | {ratio} | "
                     f"{r['psnr_source_10']:.2f} | {r['psnr_source_100']:.2f} | **{r['psnr_source_avg']:.2f}** | "
                     f"{r['psnr_photos_avg']:.2f} | {r['peak_rss_mb']:,.0f} |")
    if tr:
        reach = (f"{tr['seconds_to_bar']:,.0f} s ({tr['seconds_to_bar'] / 3600:.1f} h) of training"
                 if tr["seconds_to_bar"] else "never (no gain with time)")
        residuals = ", ".join(f"{e:+.2f}" for e in tr["residuals_db"])
        lines += ["", f"Least squares on log2(seconds): **{tr['db_per_doubling']:+.2f} dB per doubling** of the "
                      f"training time (residuals {residuals} dB); the line reaches {tr['bar_db']:g} dB at {reach}, "
                      "a trend of these points, not a measurement."]
    lines += ["", "PSNR in dB against the source's anti-aliased renders on the held-out views (avg over 10%..100%), "
                  "and against the test photos."]
    return "\n".join(lines) + "\n"


def plot(rows: list[dict], tr: dict | None, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    t = [r["train_s"] for r in rows]
    for key, label in (("psnr_source_avg", "avg 10%..100%"), ("psnr_source_10", "10%"),
                       ("psnr_source_100", "100%")):
        ax.plot(t, [r[key] for r in rows], "o-", label=label)
    if tr:
        xs = [min(t), max(max(t), tr["seconds_to_bar"] or 0)]
        ax.plot(xs, [tr["intercept_db_at_1s"] + tr["db_per_doubling"] * math.log2(x) for x in xs], "k:",
                label=f"trend {tr['db_per_doubling']:+.2f} dB / doubling")
        ax.axhline(tr["bar_db"], color="gray", lw=0.8)
    ax.set_xscale("log", base=2)
    ax.set_xlabel("conversion training time (s)")
    ax.set_ylabel("PSNR against the source's renders (dB)")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    with atomic_write(path) as fh:
        fig.savefig(fh, format="png", dpi=120)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--input", required=True, metavar="SCENE=PLY", help="The 3DGS PLY (convert.py's --input).")
    ap.add_argument("--max-width", type=int, required=True, help="The width the PLY was fitted at.")
    ap.add_argument("--budgets", default="600,1200,2400", help="Training seconds, comma-separated.")
    ap.add_argument("--out", required=True)
    ap.add_argument("--bar", type=float, default=30.0, help="The average PSNR the trend line is solved for.")
    a = ap.parse_args(argv)
    scene, _, ply = a.input.partition("=")
    if not scene or not ply:
        ap.error("--input takes SCENE=PLY")
    budgets = [float(b) for b in a.budgets.split(",") if b.strip()]
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for b in budgets:
        run = out / f"t{b:g}"
        if not _done(run / "results.json", scene):
            cmd = [sys.executable, str(REPO / "benchmarks" / "convert.py"), "--scenes", scene, "--input", a.input,
                   "--max-width", str(a.max_width), "--fit", "iters=null", "--fit", f"time_budget={b:g}",
                   "--out", str(run)]
            print("running:", " ".join(cmd), flush=True)
            subprocess.run(cmd, check=True)
        rows.append(row(json.loads((run / "results.json").read_text()), scene, b))
    rows.sort(key=lambda r: r["train_s"])
    tr = trend(rows, a.bar)
    md = markdown(scene, ply, rows, tr)
    write_bytes_atomic(out / "convert_time.md", md.encode())
    write_bytes_atomic(out / "convert_time.json", json.dumps({"scene": scene, "input": ply, "max_width": a.max_width,
                                                              "rows": rows, "trend": tr}, indent=1).encode())
    plot(rows, tr, out / "psnr_vs_time.png")
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
