"""The measurement behind ``encode``'s choice of path, and its time price, on scenes without a stage-2 predictor.

    python benchmarks/encode_choice.py sample.ply                      # the built-in scene (proxycodec sample)
    python benchmarks/encode_choice.py lego_np.ply --distilled lego_np.pxc
    python benchmarks/encode_choice.py converted.ply --distill-iters 600

For each scene: the L_recon encode (encode's defaults with the stage-2 predictor, if any, ignored: what ``encode``
does first for a scene without one), measured against the source as ``encode`` measures it (``codec.against_source``:
held-out views, 10/30/100%, same-resolution renders of the source), with the seconds of the encode and of the
measurement; then the distilled scene under the same measurement, either a container made beforehand
(``--distilled``: ``proxycodec encode SCENE --distill``) or one distilled here (``--distill-iters N``). Also the
demo's own figure for each encode: decoded vs original on views 0 and 3 at 100/30/10% through 8-bit PNGs, as
``proxycodec demo`` prints it. The choice at ``--threshold`` (encode's default) is what ``encode`` would take.

Outputs in ``--out`` (default ``benchmarks/results/encode_choice``): ``encode_choice.json`` (every figure, machine,
versions, seed, peak RSS) and ``encode_choice.md``.
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DEMO_VIEWS = (0, 3)
DEMO_RES = (1.0, 0.3, 0.1)


def demo_psnr(decoded, source) -> list[dict]:
    """Decoded vs original on the demo's views and resolutions, both rendered and rounded to 8 bits as the demo's
    PNGs are (views the scene does not have are skipped)."""
    from proxycodec.metrics import psnr
    from proxycodec.model import image_to_uint8

    rows = []
    cams = source.cameras or []
    for v in DEMO_VIEWS:
        if v >= len(cams):
            continue
        for xi in DEMO_RES:
            a = image_to_uint8(decoded.render(cams[v], xi).image).astype(np.float32) / 255.0
            b = image_to_uint8(source.render(cams[v], xi).image).astype(np.float32) / 255.0
            rows.append({"view": v, "xi": xi, "psnr": psnr(a, b)})
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scenes", nargs="+", help="anchor PLYs (+ weights sidecars)")
    ap.add_argument("--distilled", action="append", default=[],
                    help="SCENE=CONTAINER or CONTAINER (for the scene in the same position): a distilled encode of it")
    ap.add_argument("--distill-iters", type=int, default=None, help="distil each scene here for this many iterations")
    ap.add_argument("--threshold", type=float, default=None, help="dB [default: encode's]")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    if str(REPO) not in sys.path:
        sys.path.insert(0, str(REPO))
    from proxycodec import codec
    from proxycodec.bench import machine_info, versions
    from proxycodec.fileio import atomic_write
    from proxycodec.model import SceneModel

    cfg = codec.EncodeConfig(seed=args.seed)
    threshold = cfg.distill_threshold if args.threshold is None else args.threshold
    distilled_given = {}
    for i, d in enumerate(args.distilled):
        scene, _, pxc = d.rpartition("=")
        distilled_given[scene or args.scenes[i]] = pxc
    out = Path(args.out) if args.out else REPO / "benchmarks" / "results" / "encode_choice"
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for scene in args.scenes:
        source = SceneModel.load(scene)
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            # the L_recon encode encode makes first (a fitted predictor ignored, the choice forced to keep it)
            r = codec.encode(scene, Path(tmp) / "l.pxc", seed=args.seed, use_fitted=False, distill=False)
            t_encode = time.perf_counter() - t0
            lrecon = codec.against_source(r.model, source, cfg)
            row = {"scene": scene, "anchors": r.anchors, "l_recon": {
                "bytes": r.file_bytes, "encode_s": t_encode, "predictor_s": r.seconds["predictor"], **lrecon,
                "demo_psnr": demo_psnr(r.model, source)}}
            print(f"{scene}: L_recon encode {t_encode:.1f} s ({r.file_bytes:,} B): {lrecon['measured']:.2f} dB "
                  f"against the source (" + ", ".join(f"{x['xi']:g}: {x['psnr']:.2f}" for x in
                                                       lrecon["per_resolution"]) +
                  f"), measured in {lrecon['seconds']:.1f} s", flush=True)
            dist = None
            if scene in distilled_given:
                dist = {"container": distilled_given[scene], "model": codec.decode(distilled_given[scene])}
            elif args.distill_iters:
                t0 = time.perf_counter()
                rd = codec.encode(scene, Path(tmp) / "d.pxc", seed=args.seed, distill=True,
                                  distill_iters=args.distill_iters, progress=None)
                dist = {"iterations": args.distill_iters, "encode_s": time.perf_counter() - t0, "model": rd.model,
                        "bytes": rd.file_bytes}
            if dist is not None:
                model = dist.pop("model")
                dist.update(codec.against_source(model, source, cfg), demo_psnr=demo_psnr(model, source))
                row["distilled"] = dist
                print(f"{scene}: distilled {dist['measured']:.2f} dB against the source", flush=True)
        row["choice"] = "L_recon" if lrecon["measured"] >= threshold else "distill"
        rows.append(row)
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    meta = {"threshold": threshold, "seed": args.seed, "resolutions": list(cfg.choice_resolutions),
            "views": cfg.choice_views, "machine": machine_info(), "versions": versions(), "peak_rss_mb": rss}
    res = cfg.choice_resolutions
    lines = [f"# encode's choice of path (threshold {threshold:g} dB)", "",
             f"PSNR against the source rendered at the same resolution, mean of {cfg.choice_views} views spread over "
             f"the teacher's, "
             f"seed {args.seed}; {meta['machine'].get('cpu_model', '?')}, {meta['machine'].get('cpu_count')} cores; "
             f"peak RSS {rss:.0f} MB.", "",
             "| scene | anchors | L_recon: " + " / ".join(f"{x:.0%}" for x in res) + " | L_recon mean | encode s "
             "(of which predictor; measurement) | distilled: " + " / ".join(f"{x:.0%}" for x in res) +
             " | distilled mean | choice |", "|---|---:|---:|---:|---:|---:|---:|---|"]
    for r in rows:
        lr, d = r["l_recon"], r.get("distilled")
        lines.append(
            f"| {Path(r['scene']).name} | {r['anchors']:,} | "
            + " / ".join(f"{x['psnr']:.2f}" for x in lr["per_resolution"]) + f" | {lr['measured']:.2f} | "
            f"{lr['encode_s']:.1f} ({lr['predictor_s']:.1f}; {lr['seconds']:.1f}) | "
            + (" / ".join(f"{x['psnr']:.2f}" for x in d["per_resolution"]) + f" | {d['measured']:.2f}"
               if d else "n/a | n/a") + f" | {r['choice']} |")
    lines += ["", "Decoded vs original as `proxycodec demo` prints it (8-bit renders; views 0 and 3 at "
              "100 / 30 / 10%):", ""]
    for r in rows:
        for what in ("l_recon", "distilled"):
            if what in r and r[what]["demo_psnr"]:
                lines.append(f"- {Path(r['scene']).name}, {what}: " + "; ".join(
                    f"view {v}: " + " / ".join(f"{x['psnr']:.2f}" for x in r[what]["demo_psnr"] if x["view"] == v)
                    for v in DEMO_VIEWS))
    md = "\n".join(lines) + "\n"
    print("\n" + md)
    with atomic_write(out / "encode_choice.json") as f:
        f.write(json.dumps({**meta, "rows": rows}, indent=2).encode())
    with atomic_write(out / "encode_choice.md") as f:
        f.write(md.encode())
    return 0


if __name__ == "__main__":
    sys.exit(main())
