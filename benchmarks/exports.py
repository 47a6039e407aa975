"""What exporting a container to plain 3DGS costs and keeps: colour choices, formats, LOD sets, third-party readers.

    python benchmarks/exports.py lego.pxc converted.pxc [--res 1,0.25] [--levels 1,0.5,0.25,0.125]

For each container and each resolution in ``--res``:
- **colour choices** (``decode --bake-view`` / ``--sh-degree 0..3``): Gaussians, SPZ bytes, bake seconds, PSNR of
  the baked set rendered by our 3DGS renderer against the container's own render at that resolution, on the stored
  cameras (the views the bake decoded) and on held-out views between them (``export.held_out_cameras``);
- **formats** (the default colour): PLY, SPZ and GLB bytes and write seconds, each file read back by our readers and
  rendered (PSNR as above);
- **third-party readers**: splat-transform converts our SPZ back to PLY (Gaussian count), gltf-validator's errors
  on our GLB (those about the extension's attribute names, which it does not know, counted apart).
Then the **LOD set** (``decode --lod``): per level, Gaussians, bytes and held-out PSNR at the level's resolution.

Outputs in ``--out`` (default ``benchmarks/results/exports``): ``exports.json`` (every figure, machine, versions,
peak RSS), ``exports.md`` and ``exports.png`` (PSNR against bake time per colour choice; Gaussians and bytes per
LOD level).
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
CHOICES = (("view 0", {"view": 0}), ("sh0", {"sh_degree": 0}), ("sh1", {"sh_degree": 1}),
           ("sh2", {"sh_degree": 2}), ("sh3", {"sh_degree": 3}))


def _psnrs(model, ply, xi, stored, held) -> dict:
    from proxycodec.export import export_psnr

    return {"stored": float(np.mean(export_psnr(model, ply, xi, stored))),
            "held_out": float(np.mean(export_psnr(model, ply, xi, held)))}


def measure(container: str, resolutions, levels, tmp: Path, n_views: int) -> dict:
    from proxycodec import codec
    from proxycodec.bench import node_tools
    from proxycodec.export import BakeConfig, bake, held_out_cameras, write_gaussians, write_lod
    from proxycodec.formats.splats import read_splats

    model = codec.decode(container)
    cams = list(model.cameras or [])
    stored = [cams[i] for i in np.linspace(0, len(cams) - 1, min(n_views, len(cams))).round().astype(int)]
    held = held_out_cameras(model, n_views)
    row = {"container": container, "bytes": Path(container).stat().st_size, "anchors": model.scene.num_anchors,
           "stored_cameras": len(cams), "views_measured": {"stored": len(stored), "held_out": len(held)},
           "resolutions": []}
    for xi in resolutions:
        r = {"xi": xi, "choices": [], "formats": []}
        default = None
        for name, kw in CHOICES:
            t0 = time.perf_counter()
            b = bake(model, BakeConfig(xi=xi, **kw))
            secs = time.perf_counter() - t0
            nbytes = write_gaussians(tmp / "c.spz", b.ply)
            c = {"colour": name, "gaussians": b.ply.n_gaussians, "spz_bytes": nbytes, "bake_s": secs,
                 **_psnrs(model, b.ply, xi, stored, held)}
            r["choices"].append(c)
            print(f"{Path(container).name} xi {xi:g} {name}: {c['gaussians']:,} Gaussians, {nbytes:,} B SPZ, "
                  f"bake {secs:.1f} s, {c['stored']:.2f} dB stored / {c['held_out']:.2f} dB held-out", flush=True)
            if name == "sh1":
                default = b
        for fmt in ("ply", "spz", "glb"):
            path = tmp / f"e_{xi:g}.{fmt}"
            t0 = time.perf_counter()
            nbytes = write_gaussians(path, default.ply)
            w = time.perf_counter() - t0
            back, _ = read_splats(path)
            f = {"format": fmt, "bytes": nbytes, "write_s": w, "gaussians": back.n_gaussians,
                 **_psnrs(model, back, xi, stored, held)}
            r["formats"].append(f)
            print(f"  {fmt}: {nbytes:,} B in {w:.2f} s, read back: {f['stored']:.2f} / {f['held_out']:.2f} dB",
                  flush=True)
        third = {}
        why = node_tools.splat_transform_unavailable()
        if why:
            third["splat_transform"] = {"skipped": why}
        else:
            p = node_tools.splat_transform("-w", tmp / f"e_{xi:g}.spz", tmp / "back.ply")
            from proxycodec.formats.inria_ply import read_inria_ply

            ok = p.returncode == 0
            third["splat_transform"] = {"tool": node_tools.SPLAT_TRANSFORM, "returncode": p.returncode,
                                        "gaussians": read_inria_ply(tmp / "back.ply").n_gaussians if ok else None}
        pkg, why = node_tools.gltf_validator()
        if pkg is None:
            third["gltf_validator"] = {"skipped": why}
        else:
            rep = node_tools.validate_glb(pkg, tmp / f"e_{xi:g}.glb")
            known, other = node_tools.known_extension_errors(rep)
            third["gltf_validator"] = {"tool": node_tools.GLTF_VALIDATOR, "errors": rep["issues"]["numErrors"],
                                       "extension_name_errors": len(known), "other_errors": len(other),
                                       "warnings": rep["issues"]["numWarnings"],
                                       "other": [m["code"] for m in other]}
        r["third_party"] = third
        print(f"  third-party: {json.dumps(third)}", flush=True)
        row["resolutions"].append(r)
    lod = []
    t0 = time.perf_counter()
    man = write_lod(model, tmp / "lod", levels, fmt="spz")
    lod_s = time.perf_counter() - t0
    for e in man["levels"]:
        ply, _ = read_splats(tmp / "lod" / e["file"])
        lod.append({**{k: e[k] for k in ("lod", "resolution", "count", "bytes")},
                    **_psnrs(model, ply, e["resolution"], stored, held)})
        print(f"  LOD {e['lod']} ({e['resolution']:g}): {e['count']:,} Gaussians, {e['bytes']:,} B, "
              f"{lod[-1]['held_out']:.2f} dB held-out", flush=True)
    row["lod"] = {"levels": lod, "seconds": lod_s, "format": "spz"}
    return row


def markdown(rows: list[dict], meta: dict) -> str:
    m = meta["machine"]
    out = ["# Exports to plain 3DGS", "",
           f"PSNR of the exported set rendered by our 3DGS renderer against the container's own render at the same "
           f"resolution (mean over {rows[0]['views_measured']['stored']} stored and "
           f"{rows[0]['views_measured']['held_out']} held-out views); {m.get('cpu_model', '?')}, "
           f"{m.get('cpu_count')} cores; peak RSS {meta['peak_rss_mb']:.0f} MB.", ""]
    for row in rows:
        name = Path(row["container"]).name
        out += [f"## {name} ({row['anchors']:,} anchors, {row['bytes']:,} B, {row['stored_cameras']} stored cameras)",
                "", "| resolution | colour | Gaussians | SPZ bytes | bake s | PSNR stored | PSNR held-out |",
                "|---:|---|---:|---:|---:|---:|---:|"]
        for r in row["resolutions"]:
            for c in r["choices"]:
                out.append(f"| {r['xi']:g} | {c['colour']} | {c['gaussians']:,} | {c['spz_bytes']:,} | "
                           f"{c['bake_s']:.1f} | {c['stored']:.2f} | {c['held_out']:.2f} |")
        out += ["", "| resolution | format | bytes | write s | PSNR stored | PSNR held-out |",
                "|---:|---|---:|---:|---:|---:|"]
        for r in row["resolutions"]:
            for f in r["formats"]:
                out.append(f"| {r['xi']:g} | {f['format']} | {f['bytes']:,} | {f['write_s']:.2f} | "
                           f"{f['stored']:.2f} | {f['held_out']:.2f} |")
        out += [""]
        for r in row["resolutions"]:
            out.append(f"- third-party readers at {r['xi']:g}: `{json.dumps(r['third_party'])}`")
        out += ["", f"LOD set ({row['lod']['format']}, {row['lod']['seconds']:.1f} s):", "",
                "| LOD | resolution | Gaussians | bytes | PSNR stored | PSNR held-out |", "|---:|---:|---:|---:|---:|---:|"]
        for e in row["lod"]["levels"]:
            out.append(f"| {e['lod']} | {e['resolution']:g} | {e['count']:,} | {e['bytes']:,} | {e['stored']:.2f} | "
                       f"{e['held_out']:.2f} |")
        out.append("")
    return "\n".join(out) + "\n"


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.2))
    for row in rows:
        name = Path(row["container"]).stem
        for r in row["resolutions"]:
            xs = [c["bake_s"] for c in r["choices"]]
            ys = [c["held_out"] for c in r["choices"]]
            a.plot(xs, ys, "o-", label=f"{name} @ {r['xi']:g}")
            for c in r["choices"]:
                a.annotate(c["colour"], (c["bake_s"], c["held_out"]), fontsize=7, xytext=(3, 3),
                           textcoords="offset points")
        lv = row["lod"]["levels"]
        b.plot([e["resolution"] for e in lv], [e["count"] for e in lv], "o-", label=f"{name}: Gaussians")
        b.plot([e["resolution"] for e in lv], [e["bytes"] / 20 for e in lv], "s--", label=f"{name}: bytes / 20")
    a.set_xlabel("bake seconds (2 cores)")
    a.set_ylabel("held-out PSNR vs the container (dB)")
    a.set_title("colour: one view baked vs SH degree 0..3")
    a.legend(fontsize=8)
    b.set_xscale("log", base=2)
    b.set_xlabel("LOD level's resolution")
    b.set_title("LOD set: what each level holds")
    b.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("containers", nargs="+")
    ap.add_argument("--res", default="1,0.25")
    ap.add_argument("--levels", default="1,0.5,0.25,0.125")
    ap.add_argument("--views", type=int, default=8, help="stored and held-out views measured (each)")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    if str(REPO) not in sys.path:
        sys.path.insert(0, str(REPO))
    from proxycodec.bench import machine_info, versions
    from proxycodec.export import parse_levels
    from proxycodec.fileio import write_bytes_atomic

    out = Path(args.out) if args.out else REPO / "benchmarks" / "results" / "exports"
    out.mkdir(parents=True, exist_ok=True)
    resolutions = [float(x) for x in args.res.split(",")]
    rows = []
    for c in args.containers:
        with tempfile.TemporaryDirectory() as tmp:
            rows.append(measure(c, resolutions, parse_levels(args.levels), Path(tmp), args.views))
    meta = {"machine": machine_info(), "versions": versions(),
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, "date": time.strftime("%Y-%m-%d"),
            "command": "python benchmarks/exports.py " + " ".join(argv if argv is not None else sys.argv[1:])}
    write_bytes_atomic(out / "exports.json", json.dumps({"meta": meta, "rows": rows}, indent=1).encode())
    md = markdown(rows, meta)
    write_bytes_atomic(out / "exports.md", md.encode())
    plot(rows, out / "exports.png")
    print("\n" + md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
