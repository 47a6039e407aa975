"""What the position codings cost: bytes and time of ``delta`` (zstd) against ``octree`` on real containers.

    python benchmarks/positions.py A.pxc [B.pxc ...] [--repeats 5] [--out benchmarks/results/positions]

For each container with grid positions, its anchors' grid coordinates are coded both ways (``sections.encode_positions``
with ``coding="delta"`` then zstd at the container's level, and ``coding="octree"``) and decoded back
(``octree.decode``; the deltas' cumulative sum): bytes, and median encode / decode seconds over the repeats, measured
in the same run. Lossless both ways (checked). Writes ``positions.json`` (machine, versions, every figure, peak RSS),
``positions.md`` and ``positions.png`` (bytes per anchor and milliseconds, both codings); prints the table.
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import zstandard

REPO = Path(__file__).resolve().parents[1]


def measure(path: Path, repeats: int) -> dict:
    from proxycodec import octree
    from proxycodec.errors import ProxycodecError
    from proxycodec.formats.container import read_container
    from proxycodec.sections import GRID, encode_positions, grid_to_xyz

    c = read_container(path)
    info = c.meta["positions"]
    if info.get("mode") != "grid":
        return {"path": str(path), "skipped": f"positions are {info.get('mode')}, not on a grid"}
    if info.get("coding") == "octree":
        rel = octree.decode(c.arrays, info["depth"], int(c.meta["anchors"]["count"]), ProxycodecError)
    else:
        rel = np.cumsum(c.arrays[GRID].astype(np.int64), axis=1).T
    ii = rel + np.asarray(info["origin"], np.int64)
    pos = grid_to_xyz(ii, float(info["step"]), info["rule"])
    voxel = float(c.meta["voxel_size"])
    level = int(c.meta.get("encoder", {}).get("zstd_level", 19))
    z = zstandard.ZstdCompressor(level=level)
    out = {"path": str(path), "anchors": len(pos), "zstd_level": level}
    for coding in ("delta", "octree"):
        enc, dec = [], []
        for _ in range(repeats):
            t0 = time.perf_counter()
            pc = encode_positions(pos, voxel, coding)
            stored = {k: (v if k == octree.STREAM else z.compress(np.ascontiguousarray(v).tobytes()))
                      for k, v in pc.sections.items()}
            t1 = time.perf_counter()
            if coding == "octree":
                back = octree.decode(pc.sections, pc.info["depth"], len(pos), ProxycodecError)
            else:
                back = np.cumsum(pc.sections[GRID].astype(np.int64), axis=1).T
            t2 = time.perf_counter()
            enc.append(t1 - t0)
            dec.append(t2 - t1)
        assert np.array_equal(back, rel), coding  # lossless, and the same (Morton) order
        out[coding] = {"bytes": sum(v.nbytes if isinstance(v, np.ndarray) else len(v) for v in stored.values()),
                       "encode_ms": 1000 * statistics.median(enc), "decode_ms": 1000 * statistics.median(dec)}
    out["container_bytes"] = path.stat().st_size
    out["saved_share_of_container"] = (out["delta"]["bytes"] - out["octree"]["bytes"]) / out["container_bytes"]
    return out


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in rows if "skipped" not in r]
    names = [Path(r["path"]).stem for r in rows]
    x = np.arange(len(rows))
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.8))
    for j, coding in enumerate(("delta", "octree")):
        a.bar(x + 0.4 * j, [8 * r[coding]["bytes"] / r["anchors"] for r in rows], 0.4, label=coding)
        b.bar(x + 0.4 * j, [r[coding]["encode_ms"] + r[coding]["decode_ms"] for r in rows], 0.4, label=coding)
    for ax, lab in ((a, "bits per anchor"), (b, "encode + decode (ms, median)")):
        ax.set_xticks(x + 0.2, names, fontsize=8)
        ax.set_ylabel(lab)
        ax.grid(alpha=0.3, axis="y")
        ax.legend(fontsize=8)
    a.set_title("position bytes")
    b.set_title("their price in time")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("containers", nargs="+", type=Path)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "positions")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(REPO))
    from proxycodec.bench import machine_info, versions
    from proxycodec.threads import set_threads

    threads = set_threads()
    rows = [measure(p, args.repeats) for p in args.containers]
    lines = ["| container | anchors | delta (zstd) B | octree B | saved, of the container | encode ms delta / octree "
             "| decode ms delta / octree |", "|---|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        if "skipped" in r:
            lines.append(f"| {Path(r['path']).name} | {r['skipped']} | | | | | |")
            continue
        d, o = r["delta"], r["octree"]
        lines.append(f"| {Path(r['path']).name} | {r['anchors']:,} | {d['bytes']:,} | {o['bytes']:,} | "
                     f"{d['bytes'] - o['bytes']:,} B ({100 * r['saved_share_of_container']:.1f}%) | "
                     f"{d['encode_ms']:.0f} / {o['encode_ms']:.0f} | {d['decode_ms']:.1f} / {o['decode_ms']:.1f} |")
    md = "\n".join(lines) + "\n"
    res = {"kind": "proxycodec.positions", "machine": machine_info(), "versions": versions(), "threads": threads,
           "seed": None, "repeats": args.repeats, "rows": rows,
           "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
           "generated": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "positions.json").write_text(json.dumps(res, indent=1))
    (args.out / "positions.md").write_text("# Position codings\n\n" + md)
    plot(rows, args.out / "positions.png")
    print(md)
    print(f"wrote {args.out}/positions.json, positions.md, positions.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
