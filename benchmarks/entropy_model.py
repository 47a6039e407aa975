"""The entropy model against zstd alone, on the same scene, in one run (issue #17).

For each scene given (anchor PLY + weights sidecar, e.g. a ``fit`` output, with or without ``--lambda-rate``):
encode it with ``--entropy zstd`` (scene format 2) and ``--entropy model`` (scene format 4), same options
otherwise, and report

- bytes section by section (positions, split, proxy features, scalings, offsets, decoder and predictor weights,
  the entropy model's nets and escapes, metadata), the ratio to PLY + weights, bits per anchor and bytes per drawn
  Gaussian (the neural Gaussians with positive opacity from the stored cameras at 100%: what a renderer draws);
- encode time (median of ``--repeats``), and fresh-process decode + render of one 30% view
  (``proxycodec decode X --res 0.3 --view 0``: the README's path, torch-free), median of ``--repeats``;
- with ``--dataset``: PSNR / SSIM / LPIPS averaged over 10%..100% on its test views (``proxycodec eval``), and the
  uncompressed scene's, so "below the uncompressed scene" is measured in the same run.

    python benchmarks/entropy_model.py SCENE.ply [SCENE2.ply ...] [--dataset ../shared/data/nerf_synthetic/lego
        --max-width 400] [--repeats 3] [--out benchmarks/results/entropy_model]

Writes ``results.json`` (machine, versions, every figure) and ``entropy_model.md`` into ``--out``.
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
          "offsets": ("anchors/offsets", "proxy/offsets"), "decoder": ("decoder/",), "predictor": ("predictor/",),
          "entropy stream": ("entropy/stream",), "entropy nets + escapes": ("entropy/nets", "entropy/escapes"),
          "metadata + header": ("meta",)}


def _cli(*args, timeout=3600) -> float:
    t = time.perf_counter()
    subprocess.run([sys.executable, "-m", "proxycodec.cli.main", *map(str, args)], check=True, timeout=timeout,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t


def _groups(stats: dict) -> dict[str, int]:
    out = {k: 0 for k in GROUPS}
    out["metadata + header"] = stats["header_and_toc_bytes"]
    for s in stats["sections"]:
        g = next((k for k, pre in GROUPS.items() if any(s["name"].startswith(p) for p in pre)), None)
        if g is None:
            raise KeyError(s["name"])
        out[g] += s["stored_size"]
    return out


def _drawn_gaussians(path: Path) -> int:
    """Neural Gaussians with positive opacity over the stored cameras at 100% (each counted once per camera)."""
    from proxycodec import lite

    s = lite.decode(path)
    cams = lite.default_cameras(s)
    return int(statistics.median(len(s.decode_view(c, 1.0)[0].opacities) for c in cams))


def _eval(path: Path, dataset: str, max_width: int, out: Path) -> dict:
    _cli("eval", path, dataset, "--max-width", max_width, "--res", RES, "-o", out)
    s = json.loads((out / "eval.json").read_text())["summary"]
    return {k: s.get(k) for k in ("psnr_avg", "ssim_avg", "lpips_avg", "psnr_100", "psnr_10")}


def run_scene(ply: Path, args, work: Path) -> dict:
    from proxycodec import codec

    row: dict = {"scene": str(ply)}
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
        r["quant_bits"] = st["quant_bits"]
        if args.dataset:
            r["eval"] = _eval(out, args.dataset, args.max_width, work / f"{ply.stem}_{mode}_eval")
        row[mode] = r
    return row


def table(rows: list[dict]) -> str:
    lines = []
    for row in rows:
        z, m = row["zstd"], row["model"]
        lines += [f"### {Path(row['scene']).name}", "",
                  "| section | zstd only (format 2) | entropy model (format 4) |", "|---|---:|---:|"]
        for g in GROUPS:
            lines.append(f"| {g} | {z['groups'][g]:,} | {m['groups'][g]:,} |")
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
        if "uncompressed" in row:
            u = row["uncompressed"]
            lines.append(f"| PSNR avg 10..100% (uncompressed {u['psnr_avg']:.3f}) | {z['eval']['psnr_avg']:.3f} "
                         f"({z['eval']['psnr_avg'] - u['psnr_avg']:+.3f}) | {m['eval']['psnr_avg']:.3f} "
                         f"({m['eval']['psnr_avg'] - u['psnr_avg']:+.3f}) |")
        lines.append("")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scenes", nargs="+", type=Path)
    ap.add_argument("--dataset", default=None)
    ap.add_argument("--max-width", type=int, default=400)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "entropy_model")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    work = args.out / "work"
    work.mkdir(exist_ok=True)
    import constriction
    import numpy
    import torch

    import proxycodec

    rows = []
    for ply in args.scenes:
        rows.append(run_scene(ply, args, work))
        print(table(rows[-1:]), flush=True)
    res = {"machine": {"platform": platform.platform(), "processor": platform.processor(),
                       "python": platform.python_version(), "cpu_count": __import__("os").cpu_count()},
           "versions": {"proxycodec": getattr(proxycodec, "__version__", "0.1.0"), "torch": torch.__version__,
                        "numpy": numpy.__version__, "constriction": getattr(constriction, "__version__", "?")},
           "seed": 0, "repeats": args.repeats, "rows": rows}
    (args.out / "results.json").write_text(json.dumps(res, indent=1))
    (args.out / "entropy_model.md").write_text(table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
