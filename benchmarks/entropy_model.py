"""The entropy model against zstd alone, on the same scene, in one run (issue #17).

For each scene given (anchor PLY + weights sidecar, e.g. a ``fit`` output, with or without ``--lambda-rate``):
encode it with ``--entropy zstd`` (scene format 2) and ``--entropy model`` (scene format 4; both format 5 for a scene
fitted with ``--quant-cells``), same options otherwise, and report

- bytes section by section (positions, split, proxy features, scalings, offsets, per-cell levels, decoder and predictor weights,
  the entropy model's nets and escapes, metadata), the ratio to PLY + weights, bits per anchor and bytes per drawn
  Gaussian (the neural Gaussians with positive opacity from the stored cameras at 100%: what a renderer draws);
- encode time (median of ``--repeats``), and fresh-process decode + render of one 30% view
  (``proxycodec decode X --res 0.3 --view 0``: the README's path, torch-free), median of ``--repeats``;
- with ``--dataset``: PSNR / SSIM / LPIPS averaged over 10%..100% on its test views (``proxycodec eval``), and the
  uncompressed scene's, so "below the uncompressed scene" is measured in the same run.

    python benchmarks/entropy_model.py SCENE.ply [SCENE2.ply ...] [--dataset ../shared/data/nerf_synthetic/lego
        --max-width 400] [--repeats 3] [--out benchmarks/results/entropy_model]

Writes ``results.json`` (machine, versions, every figure), ``entropy_model.md`` and, with ``--dataset``,
``rd_curve.png`` (PSNR averaged over 10%..100% against bytes: each scene's containers, zstd and entropy model, and
the uncompressed PLY + weights) into ``--out``. ``--labels`` names the scenes in the table and the plot (e.g. their
``--lambda-rate``).
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
RES = ",".join(f"{r / 10:.1f}" for r in range(1, 11))
GROUPS = {"positions": ("anchors/grid", "anchors/xyz"), "split": ("anchors/proxy_mask",),
          "proxy features": ("proxy/features",), "scalings": ("anchors/scalings",),
          "offsets": ("anchors/offsets", "proxy/offsets"), "quant levels": ("quant/levels",),
          "decoder": ("decoder/",), "predictor": ("predictor/",),
          "entropy stream": ("entropy/stream",), "entropy nets + escapes": ("entropy/nets", "entropy/escapes"),
          "metadata + header": ("meta",)}


def _cli(*args, timeout=3600) -> float:
    t = time.perf_counter()
    subprocess.run([sys.executable, "-c", "from proxycodec.cli.main import main; main()", *map(str, args)],
                   check=True, timeout=timeout,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t


def _groups(stats: dict) -> dict[str, int]:
    out = {k: 0 for k in GROUPS}
    out["metadata + header"] = stats["header_and_toc_bytes"]
    for s in stats["sections"]:
        g = next((k for k, pre in GROUPS.items() if any(s["name"].startswith(p) for p in pre)), None)
        if g is None:
            raise KeyError(s["name"])
        out[g] += s["stored_bytes"]
    return out


def _drawn_gaussians(path: Path) -> int:
    """Neural Gaussians with positive opacity over the stored cameras at 100% (each counted once per camera)."""
    from proxycodec import lite

    s = lite.decode(path)
    cams = lite.default_cameras(s)
    return int(statistics.median(len(s.decode_view(c, 1.0)[0].opacities) for c in cams))


def dead_slot_bits(path: Path) -> dict:
    """Where the offsets' bits go: never-drawn slots (``encode --drop-dead-offsets``'s liveness test: opacity <=
    -0.02 from every sampled viewpoint and resolution) against drawn ones, under the container's own model."""
    import numpy as np

    from proxycodec import codec, entropy
    from proxycodec.codec import _live_slots
    from proxycodec.sections import read_scene_container, stored_anchors

    c = read_scene_container(path)
    m = c.meta
    err = ValueError
    a = stored_anchors(m, dict(c.arrays), err)  # (decodes the stream)
    F, K = a.features.shape[1], a.offsets.shape[1]
    bits = {k: m["quant"][k]["bits"] for k in entropy.NETS}
    ctx = entropy.Context.of(a.positions, a.voxel_size, a.proxy_mask)
    syms = entropy.decode(m["entropy"], c.arrays, ctx, F, K, bits, err)
    nets = entropy.unpack_nets(m["entropy"]["nets"], c.arrays, err)
    lengths = entropy.code_lengths(ctx, nets, syms).offsets.reshape(len(ctx.posn), K, 3).sum(2)  # [M, K]
    live = _live_slots(codec.decode(path), -0.02)
    dead = ~live
    return {"slots": int(live.size), "dead_slots": int(dead.sum()), "dead_share": float(dead.mean()),
            "offset_bytes_dead": float(lengths[dead].sum() / 8), "offset_bytes_live": float(lengths[live].sum() / 8),
            "bits_per_dead_slot": float(lengths[dead].mean()) if dead.any() else None,
            "bits_per_live_slot": float(lengths[live].mean()) if live.any() else None,
            "live_mask_bound_bytes": float(live.size * _h2(float(dead.mean())) / 8)}


def _h2(p: float) -> float:
    import math

    return 0.0 if p <= 0 or p >= 1 else -(p * math.log2(p) + (1 - p) * math.log2(1 - p))


def _eval(path: Path, dataset: str, max_width: int, out: Path) -> dict:
    _cli("eval", path, dataset, "--max-width", max_width, "--res", RES, "-o", out)
    s = json.loads((out / "eval.json").read_text())["summary"]
    return {k: s.get(k) for k in ("psnr_avg", "ssim_avg", "lpips_avg", "psnr_100", "psnr_10")}


def run_scene(ply: Path, args, work: Path) -> dict:
    from proxycodec import codec

    from proxycodec.model import weights_path_for

    row: dict = {"scene": str(ply), "uncompressed_bytes": ply.stat().st_size + weights_path_for(ply).stat().st_size}
    if args.dataset:
        row["uncompressed"] = _eval(ply, args.dataset, args.max_width, work / f"{ply.stem}_eval")
    for mode in ("zstd", "model"):
        out = work / f"{ply.stem}.{mode}.pxc"
        enc = [_cli("encode", ply, "-o", out, "--entropy", mode) for _ in range(args.repeats)]
        dec = [_cli("decode", out, "--res", "0.3", "--view", "0", "-o", work / f"{ply.stem}_{mode}_r")
               for _ in range(args.repeats)]
        st = codec.stats(out)
        r = {"bytes": st["file_bytes"], "ratio": st["ratio"], "bits_per_anchor": st["bits_per_anchor"],
             "anchors": st["anchors"], "scene_format": st["scene_format"], "groups": _groups(st),
             "encode_s": statistics.median(enc), "decode_render_30_s": statistics.median(dec),
             "decode_render_30_all_s": dec, "drawn_gaussians": _drawn_gaussians(out)}
        r["bytes_per_drawn_gaussian"] = r["bytes"] / max(1, r["drawn_gaussians"])
        meta = st["metadata"]
        if "entropy" in meta:
            r["entropy_bytes"] = meta["entropy"]["bytes"]
            r["entropy_zstd_bytes"] = meta["entropy"]["zstd_bytes"]
            if args.dead_slots:
                r["dead_slots"] = dead_slot_bits(out)
        r["quant_bits"] = st["quant_bits"]
        if args.dataset:
            r["eval"] = _eval(out, args.dataset, args.max_width, work / f"{ply.stem}_{mode}_eval")
        row[mode] = r
    return row


def table(rows: list[dict]) -> str:
    lines = []
    for row in rows:
        z, m = row["zstd"], row["model"]
        lines += [f"### {row.get('label', Path(row['scene']).stem)} ({Path(row['scene']).name}"
                  f"{', ' + row['curve'] if row.get('curve') else ''})", "",
                  f"| section | zstd only (format {z.get('scene_format', 2)}) | entropy model (format "
                  f"{m.get('scene_format', 4)}) |", "|---|---:|---:|"]
        for g in GROUPS:
            if g in z["groups"] or g in m["groups"]:  # (rows of older runs lack the newer groups)
                lines.append(f"| {g} | {z['groups'].get(g, 0):,} | {m['groups'].get(g, 0):,} |")
        if "entropy_bytes" in m:
            eb = m["entropy_bytes"]
            lines.append(f"| (in the stream: features / scalings / offsets) | | "
                         f"{eb['features']:,.0f} / {eb['scalings']:,.0f} / {eb['offsets']:,.0f} |")
        lines += [f"| **total** | **{z['bytes']:,}** ({z['ratio']:.2f}x) | **{m['bytes']:,}** ({m['ratio']:.2f}x) |",
                  f"| bits per anchor | {z['bits_per_anchor']:.1f} | {m['bits_per_anchor']:.1f} |",
                  f"| bytes per drawn Gaussian (median over stored cameras) | {z['bytes_per_drawn_gaussian']:.2f} | "
                  f"{m['bytes_per_drawn_gaussian']:.2f} |",
                  f"| encode (s, median) | {z['encode_s']:.1f} | {m['encode_s']:.1f} |",
                  f"| fresh-process decode + render of a 30% view (s, median) | {z['decode_render_30_s']:.2f} | "
                  f"{m['decode_render_30_s']:.2f} |"]
        if "dead_slots" in m:
            d = m["dead_slots"]
            lines.append(f"| never-drawn offset slots: share, bits per slot (drawn: {d['bits_per_live_slot']:.1f}), "
                         f"offset bytes on them | | {d['dead_share']:.1%}, {d['bits_per_dead_slot']:.1f}, "
                         f"{d['offset_bytes_dead']:,.0f} (a live mask: >= {d['live_mask_bound_bytes']:,.0f}) |")
        if "uncompressed" in row:
            u = row["uncompressed"]
            lines.append(f"| PSNR avg 10..100% (uncompressed {u['psnr_avg']:.3f}) | {z['eval']['psnr_avg']:.3f} "
                         f"({z['eval']['psnr_avg'] - u['psnr_avg']:+.3f}) | {m['eval']['psnr_avg']:.3f} "
                         f"({m['eval']['psnr_avg'] - u['psnr_avg']:+.3f}) |")
        lines.append("")
    return "\n".join(lines)


def rd_plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 4.5))
    # rows with a "curve" key (e.g. fits made with older code) form their own, fainter curve
    curves = list(dict.fromkeys(r.get("curve", "") for r in rows))
    for mode, marker, name, color in (("zstd", "s", "zstd only (format 2)", "C0"),
                                      ("model", "o", "entropy model (format 4)", "C1")):
        for c in curves:
            pts = sorted((r[mode]["bytes"] / 1e3, r[mode]["eval"]["psnr_avg"], r["label"]) for r in rows
                         if r.get("curve", "") == c)
            ax.plot([p[0] for p in pts], [p[1] for p in pts], marker=marker, color=color, alpha=0.4 if c else 1.0,
                    ls="--" if c else "-", label=name + (f", {c}" if c else ""))
            if mode == "model":
                for x, y, lab in pts:
                    ax.annotate(lab, (x, y), textcoords="offset points", xytext=(8, -3), fontsize=7, ha="left")
    ax.scatter([r["uncompressed_bytes"] / 1e3 for r in rows], [r["uncompressed"]["psnr_avg"] for r in rows],
               marker="x", color="k", label="uncompressed (PLY + weights)")
    ax.set_xscale("log")
    ax.set_xlabel("bytes (kB, log)")
    ax.set_ylabel("PSNR, average over 10%..100% (dB)")
    ax.set_title("lego 400 px: rate-distortion")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scenes", nargs="+", type=Path)
    ap.add_argument("--dataset", default=None)
    ap.add_argument("--max-width", type=int, default=400)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "entropy_model")
    ap.add_argument("--labels", default=None, help="comma-separated names of the scenes [default: file stems]")
    ap.add_argument("--dead-slots", action="store_true",
                    help="also measure the offsets' bits on never-drawn slots (~100 s per scene)")
    ap.add_argument("--append", action="store_true",
                    help="keep the rows of an earlier run in --out (a scene measured again replaces its row)")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    work = args.out / "work"
    work.mkdir(exist_ok=True)
    import constriction
    import numpy
    import torch

    import proxycodec

    labels = args.labels.split(",") if args.labels else [p.stem for p in args.scenes]
    rows = []
    if args.append and (args.out / "results.json").is_file():
        rows = [r for r in json.loads((args.out / "results.json").read_text())["rows"]
                if r["scene"] not in {str(p) for p in args.scenes}]
    for ply, label in zip(args.scenes, labels):
        rows.append(run_scene(ply, args, work))
        rows[-1]["label"] = label
        print(table(rows[-1:]), flush=True)
    res = {"machine": {"platform": platform.platform(), "processor": platform.processor(),
                       "python": platform.python_version(), "cpu_count": __import__("os").cpu_count()},
           "versions": {"proxycodec": getattr(proxycodec, "__version__", "0.1.0"), "torch": torch.__version__,
                        "numpy": numpy.__version__, "constriction": getattr(constriction, "__version__", "?")},
           "seed": 0, "repeats": args.repeats, "rows": rows}
    (args.out / "results.json").write_text(json.dumps(res, indent=1))
    (args.out / "entropy_model.md").write_text(table(rows))
    if args.dataset:
        rd_plot(rows, args.out / "rd_curve.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
