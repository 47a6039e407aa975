"""The benchmark's report: Pareto fronts, the markdown tables and the plots (the only module that imports
matplotlib)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from ..fileio import atomic_write

if TYPE_CHECKING:
    from .runner import Runner


def pareto_front(points: Sequence[dict], x: str = "bytes", y: str = "psnr_avg") -> list[int]:
    """Indices (ascending ``x``) of the points no other point dominates: none has ``x`` <= and ``y`` >= with at least
    one strict. Smaller ``x`` and larger ``y`` are better; points missing either value are ignored."""
    ok = [i for i, p in enumerate(points)
          if p.get(x) is not None and p.get(y) is not None and math.isfinite(p[x]) and math.isfinite(p[y])]
    front = []
    for i in ok:
        xi, yi = points[i][x], points[i][y]
        dominated = any(points[j][x] <= xi and points[j][y] >= yi and (points[j][x] < xi or points[j][y] > yi)
                        for j in ok if j != i)
        if not dominated:
            front.append(i)
    return sorted(front, key=lambda i: (points[i][x], -points[i][y]))


def _f(x, spec=".3f", none="n/a") -> str:
    return none if x is None or (isinstance(x, float) and not math.isfinite(x)) else format(x, spec)


def _rss(p: dict) -> str:
    return " / ".join(f"{k} {v:.0f}" for k, v in p.get("peak_rss_mb", {}).items() if v is not None) or "n/a"


def mark_pareto(points: list[dict]) -> None:
    """Sets ``pareto`` (bytes vs average PSNR) on each point, per scene."""
    for scene in sorted({p["scene"] for p in points}):
        ps = [p for p in points if p["scene"] == scene]
        front = set(pareto_front(ps))
        for i, p in enumerate(ps):
            p["pareto"] = i in front


POINT_HEADER = ("| point | bytes | avg PSNR | avg SSIM | avg LPIPS | PSNR 10% | PSNR 100% | fit s | encode s | "
                "decode s | Pareto | peak RSS MB |\n|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|:-:|---|")


def point_row(p: dict, label: str | None = None) -> str:
    name = label or p["id"]
    if p.get("default"):
        name = f"**{name}**"
    if p.get("quality_from"):
        name += f" (quality = {p['quality_from']})"
    if p.get("errors"):
        name += " — " + "; ".join(str(e) for e in p["errors"] if e)
    return (f"| {name} | {_f(p['bytes'], ',')} | {_f(p['psnr_avg'])} | {_f(p['ssim_avg'], '.4f')} | "
            f"{_f(p.get('lpips_avg'), '.4f')} | "
            f"{_f(p['psnr_10'])} | {_f(p['psnr_100'])} | {_f(p['fit_seconds'], '.0f')} | "
            f"{_f(p['encode_seconds'], '.1f')} | {_f(p['decode_seconds'], '.2f')} | "
            f"{'yes' if p.get('pareto') else ''} | {_rss(p)} |")


def step_seconds(step: dict) -> float:
    """A step's own time: its wall seconds, or, for a fit resumed from a checkpoint (whose recorded wall time is the
    resumed part only), at least its whole training time (``result["seconds"]``)."""
    own = step.get("seconds") or 0.0
    res = step.get("result")
    if isinstance(res, dict) and res.get("resumed") and isinstance(res.get("seconds"), (int, float)):
        return max(own, float(res["seconds"]))
    return own


def time_summary(meta: dict) -> str:
    """What the folder's map cost: the recorded steps' own times summed (``step_seconds``: what the map costs from
    scratch, whatever its pauses; a step killed at a pause and run again counts once, a fit resumed from its
    checkpoint its whole training), and the runs' wall time, of the runs that ran to their end (one killed at a
    pause records none)."""
    runs, steps = meta.get("runs") or [], (meta.get("steps") or {}).values()
    ended = [r["wall_seconds"] for r in runs if r.get("wall_seconds") is not None]
    out = (f"step time {_f(sum(step_seconds(s) for s in steps), ',.0f')} s in {len(steps)} step(s); "
           f"wall time {_f(sum(ended), ',.0f')} s over the {len(ended)} of {len(runs)} run(s) of this folder that "
           "ran to their end")
    stopped = len(runs) - len(ended)
    return out + f" ({stopped} stopped early: no wall time recorded)" if stopped else out


def markdown_report(title: str, meta: dict, points: list[dict], extra_sections: Sequence[str] = ()) -> str:
    runs = meta.get("runs") or [{}]
    lines = [f"# {title}", ""]
    m = meta.get("meta", {})
    mach, ver = m.get("machine", {}), m.get("versions", {})
    lines += [
        f"Machine: {mach.get('cpu_count')} CPUs ({mach.get('cpu_model', mach.get('processor', '?'))}), "
        f"{mach.get('memory_gb', '?')} GB; {mach.get('platform', '')}. Versions: "
        + ", ".join(f"{k} {v}" for k, v in ver.items()) + ".",
        f"Seed {m.get('seed')}; load average (1, 5, 15 min) at the start {runs[0].get('loadavg_start')} and at "
        f"the end {runs[-1].get('loadavg_end')}; {time_summary(meta)} (a re-run reuses the steps already done; "
        "every step's own load averages are in the JSON).",
        "",
        "Quality: PSNR / SSIM averaged over the ten resolutions 10%..100% of the 100% reference on the first test "
        "views (count per scene below); render time = mean per view, after one warm-up render. Fit seconds are "
        "training time (setup excluded); encode seconds the `encode` call; decode seconds the container's decode "
        "(leaves regenerated) in a fresh process. Peak RSS per step (its own process). Bytes: the container, the "
        "anchor PLY + weights sidecar, the INRIA PLY or the SPZ file. Pareto: not dominated in (bytes, avg PSNR) "
        "among the scene's points.",
        "",
    ]
    notes = list(dict.fromkeys(p["lpips_note"] for p in points if p.get("lpips_note")))
    if notes:  # LPIPS (AlexNet, v0.1) beside PSNR/SSIM when its weights are installed; one line either way
        lines += ["; ".join(notes) + ".", ""]
    for scene in sorted({p["scene"] for p in points}, key=lambda s: [p["scene"] for p in points].index(s)):
        ps = [p for p in points if p["scene"] == scene]
        spec = m.get("scenes", {}).get(scene, {})
        lines += [f"## {scene}", ""]
        if spec:
            lines += [", ".join(f"{k}: {v}" for k, v in spec.items()), ""]
        main = [p for p in ps if p.get("group") != "encode sweep"]
        lines += ["### Points", "", POINT_HEADER] + [point_row(p) for p in main] + [""]
        sw = {}
        for p in ps:
            for name, label in (p.get("sweeps") or {}).items():
                sw.setdefault(name, []).append((label, p))
        for name, rows in sw.items():
            rows.sort(key=lambda lp: (lp[1].get("sweep_order") or {}).get(name, -1))
            lines += [f"### Sweep: {name}", "", POINT_HEADER]
            lines += [point_row(p, f"{name} {label}" + (" (default)" if p["id"] == "encode default (refit)" else ""))
                      for label, p in rows] + [""]
        timed = [p for p in ps if p.get("render_ms") and _timed(p)]
        if timed:
            xs = sorted({x for p in timed for x in p["render_ms"]}, key=float)
            lines += ["### Render time per resolution (ms, mean per view)", "",
                      "| point | " + " | ".join(f"{float(x) * 100:g}%" for x in xs) + " |",
                      "|---|" + "---:|" * len(xs)]
            lines += [f"| {p['id']} | " + " | ".join(_f(p["render_ms"].get(x), ".1f") for x in xs) + " |"
                      for p in timed] + [""]
        lines += closing_notes(ps) + [""]
    lines += list(extra_sections)
    return "\n".join(lines).rstrip() + "\n"


def closing_notes(ps: list[dict]) -> list[str]:
    """The default's place on the Pareto front and, when measured, the container against SPZ of 3DGS."""
    out = []
    d = next((p for p in ps if p.get("default") and p["kind"] == "container"), None)
    if d is not None and d.get("psnr_avg") is not None:
        if d.get("pareto"):
            out.append(f"- Default settings ({d['id']}): {_f(d['bytes'], ',')} B, {_f(d['psnr_avg'])} dB: "
                       "on the Pareto front.")
        else:
            dom = [p for p in ps if p.get("pareto") and p["bytes"] <= d["bytes"] and p["psnr_avg"] >= d["psnr_avg"]]
            out.append(f"- Default settings ({d['id']}): {_f(d['bytes'], ',')} B, {_f(d['psnr_avg'])} dB: not on "
                       "the Pareto front; dominated by " + ", ".join(
                           f"{p['id']} ({_f(p['bytes'], ',')} B, {_f(p['psnr_avg'])} dB)" for p in dom[:3]) + ".")
    spz = next((p for p in ps if p["kind"] == "spz" and p.get("psnr_avg") is not None), None)
    if d is not None and spz is not None and d.get("bytes") and spz.get("bytes"):
        out.append(f"- Container vs SPZ of the 3DGS baseline: {_f(d['bytes'], ',')} B vs {_f(spz['bytes'], ',')} B "
                   f"({spz['bytes'] / d['bytes']:.2f}x), {_f(d['psnr_avg'])} vs {_f(spz['psnr_avg'])} dB "
                   f"({d['psnr_avg'] - spz['psnr_avg']:+.3f} dB).")
    return ["### Notes", ""] + out if out else []


def _timed(p: dict) -> bool:
    """Points whose render times are shown: everything but the encode sweeps (whose renders equal the default's up
    to quantisation), plus the sweeps' centre; fit-budget points other than the default too."""
    return p.get("group") not in ("encode sweep", "fit budget") or p["id"] == "encode default (refit)"


def _scene_colors(points):
    groups = sorted({p.get("group", p["kind"]) for p in points})
    import matplotlib

    cmap = matplotlib.colormaps["tab10"]
    return {g: cmap(i % 10) for i, g in enumerate(groups)}


def plot_report(points: list[dict], out_dir: Path) -> dict[str, Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    scenes = list(dict.fromkeys(p["scene"] for p in points))
    paths = {"psnr_vs_bytes": out_dir / "psnr_vs_bytes.png", "psnr_vs_time": out_dir / "psnr_vs_time.png",
             "render_time": out_dir / "render_time_vs_resolution.png"}
    colors = _scene_colors(points)

    def scatter(ax, ps, xkey, xlabel, front: bool):
        good = [p for p in ps if p.get(xkey) and p.get("psnr_avg") is not None]
        for g in sorted({p.get("group", p["kind"]) for p in good}):
            sel = [p for p in good if p.get("group", p["kind"]) == g]
            ax.scatter([p[xkey] for p in sel], [p["psnr_avg"] for p in sel], s=22, color=colors[g], label=g,
                       zorder=3)
        if front:
            idx = pareto_front(good, x=xkey)
            ax.plot([good[i][xkey] for i in idx], [good[i]["psnr_avg"] for i in idx], "-", color="0.3", lw=1,
                    zorder=2, label="Pareto front")
            ax.scatter([good[i][xkey] for i in idx], [good[i]["psnr_avg"] for i in idx], s=70, facecolors="none",
                       edgecolors="0.2", zorder=4)
        for p in good:
            if p.get("default"):
                ax.scatter([p[xkey]], [p["psnr_avg"]], marker="*", s=220, color="gold", edgecolors="k", zorder=5,
                           label="default settings")
            if p["kind"] != "container" or p.get("default"):
                ax.annotate(p["id"], (p[xkey], p["psnr_avg"]), fontsize=6, xytext=(3, 3),
                            textcoords="offset points")
        ax.set_xscale("log")
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.set_xlabel(xlabel)
        ax.set_ylabel("avg PSNR 10%..100% (dB)")
        h, lab = ax.get_legend_handles_labels()
        keep = dict(zip(lab, h))
        ax.legend(keep.values(), keep.keys(), fontsize=6, loc="best")

    for key, xkey, xlabel, front in (("psnr_vs_bytes", "bytes", "bytes on disk", True),
                                     ("psnr_vs_time", "production_seconds", "fit + encode time (s)", False)):
        fig, axes = plt.subplots(1, len(scenes), figsize=(6.5 * len(scenes), 4.8), dpi=110, squeeze=False)
        for ax, scene in zip(axes[0], scenes):
            scatter(ax, [p for p in points if p["scene"] == scene], xkey, xlabel, front)
            ax.set_title(f"{scene}: PSNR vs {'bytes' if front else 'fit + encode time'}")
        fig.tight_layout()
        with atomic_write(paths[key]) as fh:
            fig.savefig(fh, format="png")
        plt.close(fig)

    fig, axes = plt.subplots(1, len(scenes), figsize=(6.5 * len(scenes), 4.4), dpi=110, squeeze=False)
    for ax, scene in zip(axes[0], scenes):
        for p in points:
            if p["scene"] != scene or not p.get("render_ms") or not _timed(p):
                continue
            xs = sorted(p["render_ms"], key=float)
            ax.plot([float(x) * 100 for x in xs], [p["render_ms"][x] for x in xs], "o-", ms=3, label=p["id"])
        ax.set_xlabel("resolution (% of the 100% reference)")
        ax.set_ylabel("render time per view (ms)")
        ax.set_yscale("log")
        ax.set_title(f"{scene}: render time vs resolution")
        ax.legend(fontsize=6)
    fig.tight_layout()
    with atomic_write(paths["render_time"]) as fh:
        fig.savefig(fh, format="png")
    plt.close(fig)
    return paths


def write_report(runner: Runner, title: str, points: list[dict], extra_sections: Sequence[str] = (),
                 extra_json: dict | None = None, markdown_name: str = "tradeoff.md") -> dict[str, Path]:
    """Mark the Pareto fronts, then write ``results.json`` (steps, points, meta), the markdown and the plots."""
    mark_pareto(points)
    runner.finish()
    runner.save({"points": points, **(extra_json or {})})
    md = runner.out / markdown_name
    with atomic_write(md, "w") as fh:
        fh.write(markdown_report(title, runner.state, points, extra_sections))
    paths = {"json": runner.path, "markdown": md}
    paths.update(plot_report(points, runner.out))
    return paths


