"""What encode's own knobs cost and buy on scenes as fitted: bytes, quality and encode seconds, one knob at a time.

    python benchmarks/encode_knobs.py \\
        --fit lego=FIT.ply@../shared/data/nerf_synthetic/lego:8 \\
        --converted bonsai-conv=ANCHORS.ply@POINT_CLOUD.ply@CAMERAS.json:4 \\
        --knob weights_dtype=q8,q6,q5 --knob entropy_iters=3000,4000

Every point is ``proxycodec encode SCENE`` (the scene's stage-2 proxies and predictor as fitted) with the defaults
plus one knob changed; the defaults themselves are the first point of each scene, so every difference is against a
baseline measured in the same run. Quality:

- ``--fit NAME=PLY@DATASET[:VIEWS]``: the container against the dataset's photos on its first VIEWS held-out views
  (default 4), at 10%..100% (``proxycodec eval``);
- ``--converted NAME=PLY@SOURCE@CAMERAS[:VIEWS]``: a conversion's anchor scene, its container against the source
  3DGS PLY's supersampled renders on the held-out cameras (what ``convert`` reports; black background).

Encodes that decode to the same scene (``bench.steps._content_key``: e.g. entropy iterations, which are lossless)
share one quality evaluation. Outputs in ``--out`` (default ``benchmarks/results/encode_knobs``): ``results.json``
(every figure, machine, versions, seed, peak RSS of each step), ``encode_knobs.md`` and ``encode_knobs.png`` (bytes
against quality, and bytes against encode seconds, per scene). Each step runs in its own process
(``proxycodec.bench.runner.spawn_step``, its log beside the container in ``work/``), one at a time.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
RES = [round(0.1 * i, 1) for i in range(1, 11)]


def worker(kind: str, args: dict, log: Path) -> dict:
    """One step in a fresh process (``bench.runner.spawn_step``: its own peak RSS, its stderr in ``log``)."""
    from proxycodec.bench.runner import spawn_step

    rec = spawn_step(str(log), kind, args, timeout=7200)
    if rec["status"] != "ok":
        raise SystemExit(f"{kind} step failed: {rec['error']}")
    return rec["result"]


def parse_knobs(specs: list[str]) -> list[tuple[str, object]]:
    from proxycodec.codec import EncodeConfig

    out = []
    fields = EncodeConfig.__dataclass_fields__
    for spec in specs:
        name, _, values = spec.partition("=")
        if name not in fields or not values:
            raise SystemExit(f"--knob {spec!r}: expected FIELD=V1,V2 with FIELD one of EncodeConfig's")
        kind = type(getattr(EncodeConfig(), name))
        for v in values.split(","):
            if kind is bool:
                if v.lower() not in ("true", "false"):
                    raise SystemExit(f"--knob {spec!r}: {name} takes true or false")
                out.append((name, v.lower() == "true"))
            else:
                out.append((name, kind(v) if kind in (int, float) else v))
    return out


def scenes(args) -> list[dict]:
    out = []
    for spec in args.fit:
        name, _, rest = spec.partition("=")
        rest, _, views = rest.partition(":")
        ply, dataset = rest.split("@")
        out.append({"name": name, "kind": "fit", "ply": str(Path(ply).resolve()), "dataset": str(Path(dataset).resolve()),
                    "views": int(views or 4)})
    for spec in args.converted:
        name, _, rest = spec.partition("=")
        rest, _, views = rest.partition(":")
        ply, source, cameras = rest.split("@")
        out.append({"name": name, "kind": "converted", "ply": str(Path(ply).resolve()),
                    "source": str(Path(source).resolve()), "cameras": str(Path(cameras).resolve()),
                    "views": int(views or 4)})
    return out


def quality(scene: dict, pxc: Path) -> dict:
    log = pxc.with_suffix(".quality.log")
    if scene["kind"] == "converted":
        return worker("vs_source", {"model": str(pxc), "source": scene["source"], "cameras": scene["cameras"],
                                    "background": [0, 0, 0], "views": scene["views"]}, log)
    from proxycodec.formats.container import read_container
    from proxycodec.model import weights_path_for

    fit_meta = read_container(weights_path_for(scene["ply"])).meta.get("fit") or {}
    max_width = (fit_meta.get("config") or {}).get("max_width") or 1600  # as proxycodec bench reads it
    return worker("eval", {"model": str(pxc), "dataset": scene["dataset"], "max_width": max_width,
                           "views": scene["views"], "resolutions": RES}, log)


def plot(points: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = sorted({p["scene"] for p in points})
    fig, axes = plt.subplots(2, len(names), figsize=(5 * len(names), 8), squeeze=False)
    for col, name in enumerate(names):
        ps = [p for p in points if p["scene"] == name]
        for row, (key, label) in enumerate((("psnr_avg", "avg PSNR 10%..100% (dB)"),
                                             ("encode_seconds", "encode seconds"))):
            ax = axes[row][col]
            for knob in sorted({p["knob"] for p in ps if p["knob"]}):
                kp = [p for p in ps if p["knob"] == knob]
                ax.plot([p["bytes"] / 1e3 for p in kp], [p[key] for p in kp], "o-", label=knob)
                for p in kp:
                    ax.annotate(str(p["value"]), (p["bytes"] / 1e3, p[key]), fontsize=7)
            d = ps[0]
            ax.plot([d["bytes"] / 1e3], [d[key]], "k*", ms=12, label="defaults")
            ax.set_xlabel("container KB")
            ax.set_ylabel(label)
            ax.set_title(name)
            ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--fit", action="append", default=[])
    ap.add_argument("--converted", action="append", default=[])
    ap.add_argument("--knob", action="append", default=[])
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "encode_knobs"))
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    from proxycodec.bench.runner import machine_info, versions
    from proxycodec.bench.steps import _content_key

    out = Path(args.out)
    (out / "work").mkdir(parents=True, exist_ok=True)
    knobs = parse_knobs(args.knob)
    points: list[dict] = []
    t_run = time.perf_counter()
    runs = scenes(args)
    for sc in runs:
        evaluated: dict[str, dict] = {}
        for knob, value in [(None, None), *knobs]:
            tag = "defaults" if knob is None else f"{knob}={value}"
            pxc = out / "work" / f"{sc['name']}_{tag}.pxc"
            k = {"seed": args.seed} if knob is None else {"seed": args.seed, knob: value}
            enc = worker("encode", {"source": sc["ply"], "out": str(pxc), "knobs": k}, pxc.with_suffix(".encode.log"))
            key = _content_key(pxc)
            shared = key in evaluated
            if not shared:
                evaluated[key] = quality(sc, pxc)
            q = evaluated[key]
            p = {"scene": sc["name"], "knob": knob, "value": value, "bytes": enc["bytes"],
                 "encode_seconds": enc["seconds"], "psnr_avg": q["psnr_avg"], "ssim_avg": q.get("ssim_avg"),
                 "per_resolution": q["per_resolution"], "quality_shared": shared,
                 "peak_rss_mb": {"encode": enc["peak_rss_mb"], "quality": q["peak_rss_mb"]}}
            base = next((b for b in points if b["scene"] == sc["name"] and b["knob"] is None), p)
            p["d_bytes"], p["d_psnr"] = p["bytes"] - base["bytes"], p["psnr_avg"] - base["psnr_avg"]
            p["d_seconds"] = p["encode_seconds"] - base["encode_seconds"]
            points.append(p)
            print(f"{sc['name']:>14} {tag:<22} {p['bytes']:>10,} B {p['d_bytes']:>+9,} {p['psnr_avg']:8.3f} dB "
                  f"{p['d_psnr']:+7.3f} {p['encode_seconds']:7.1f} s", flush=True)
    doc = {"kind": "proxycodec.encode_knobs", "seed": args.seed, "machine": machine_info(), "versions": versions(),
           "scenes": runs, "knobs": [[k, v] for k, v in knobs], "points": points,
           "wall_seconds": time.perf_counter() - t_run}
    (out / "results.json").write_text(json.dumps(doc, indent=1))
    lines = ["| scene | knob | bytes | vs defaults | avg PSNR | vs defaults | encode s | vs defaults | peak RSS MB |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    for p in points:
        tag = "**defaults**" if p["knob"] is None else f"{p['knob']}={p['value']}"
        lines.append(f"| {p['scene']} | {tag} | {p['bytes']:,} | {p['d_bytes']:+,} | {p['psnr_avg']:.3f} | "
                     f"{p['d_psnr']:+.3f} | {p['encode_seconds']:.1f} | {p['d_seconds']:+.1f} | "
                     f"{max(p['peak_rss_mb'].values()):.0f} |")
    (out / "encode_knobs.md").write_text("\n".join(lines) + "\n")
    plot(points, out / "encode_knobs.png")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
