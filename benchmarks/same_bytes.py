"""Behaviour held fixed, shown by bytes: run the same commands at two commits and compare what they write.

    python benchmarks/same_bytes.py run OUT_DIR [--full] [--inputs DIR]   # writes OUT_DIR/hashes.json
    python benchmarks/same_bytes.py compare A/hashes.json B/hashes.json    # exit 1 when anything differs

`run` writes, with the installed `proxycodec`: the sample scene twice (must be identical); containers encoded from
the sample files in --inputs (default: the ones written here; give the other commit's OUT_DIR to encode the very same
input files) with the default and with --predict-offsets --drop-dead-offsets --weights-dtype f16 (no distillation:
the L_recon path); a 300-iteration explicit 3DGS fit and a 400-iteration stage-2 fit (predicted offsets, predictor
context 4, spread proxies) at 100 px; with --full, the 3000-iteration lego fit at 200 px and its container. It records
the sha1 of every file, and for containers the sha1 of their arrays (a weights sidecar's metadata records wall-clock
seconds, so its file differs between identical fits; a container records its source's size, which therefore may
too). Needs ../shared/data/nerf_synthetic/lego for the fits.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import subprocess
import sys
from pathlib import Path

LEGO = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "nerf_synthetic" / "lego"


def hashes(path: Path) -> dict:
    from proxycodec.formats.container import read_container

    out = {"file": hashlib.sha1(path.read_bytes()).hexdigest()}
    if path.suffix == ".pxc":
        c = read_container(path)
        h = hashlib.sha1()
        for name in sorted(c.arrays):
            h.update(name.encode())
            h.update(c.arrays[name].tobytes())
        out["arrays"] = h.hexdigest()
        out["n_arrays"] = len(c.arrays)
    return out


def run(out: Path, full: bool, inputs: Path | None) -> dict:
    out.mkdir(parents=True, exist_ok=True)

    def pc(*args):
        subprocess.run(["proxycodec", *map(str, args)], check=True, cwd=out, stdout=subprocess.DEVNULL,
                       stderr=subprocess.DEVNULL)

    pc("sample", "s1.ply", "--seed", "0")
    pc("sample", "s2.ply", "--seed", "0")
    src = inputs or out
    if src != out:  # the same file name: a container records its source's name
        (out / "in").mkdir(exist_ok=True)
        for f in ("s1.ply", "s1.weights.pxc"):
            shutil.copy(src / f, out / "in" / f)
        scene = "in/s1.ply"
    else:
        scene = "s1.ply"
    helptext = subprocess.run(["proxycodec", "encode", "--help"], capture_output=True, text=True).stdout
    plain = ["--no-distill"] if "--no-distill" in helptext else []  # older versions: the only path
    pc("encode", scene, "-o", "s.pxc", *plain)
    pc("encode", scene, "-o", "s_po.pxc", *plain, "--predict-offsets", "--drop-dead-offsets", "--weights-dtype", "f16")
    files = ["s1.ply", "s1.weights.pxc", "s2.ply", "s2.weights.pxc", "s.pxc", "s_po.pxc"]
    if LEGO.is_dir():
        pc("fit", LEGO, "--explicit", "--max-width", "100", "--iters", "300", "--seed", "0", "-o", "ex.ply")
        pc("fit", LEGO, "--max-width", "100", "--iters", "400", "--seed", "1", "--predict-offsets",
           "--predictor-context", "4", "--proxy-selection", "spread", "-o", "small.ply")
        files += ["ex.ply", "small.ply", "small.weights.pxc"]
        if full:
            pc("fit", LEGO, "--max-width", "200", "--iters", "3000", "--seed", "0", "-o", "lego.ply")
            pc("encode", "lego.ply", "-o", "lego.pxc")
            files += ["lego.ply", "lego.weights.pxc", "lego.pxc"]
    result = {f: hashes(out / f) for f in files}
    result["sample_deterministic"] = result["s1.ply"] == result["s2.ply"] and \
        result["s1.weights.pxc"] == result["s2.weights.pxc"]
    (out / "hashes.json").write_text(json.dumps(result, indent=1, sort_keys=True))
    return result


def compare(a: dict, b: dict) -> list[str]:
    """What differs, ignoring the files whose metadata records wall-clock time (their arrays must match)."""
    diffs = []
    for name in sorted(set(a) & set(b)):
        x, y = a[name], b[name]
        if not isinstance(x, dict):
            continue
        keys = ["arrays"] if "weights" in name else ["file", "arrays"]
        diffs += [f"{name}: {k} {x.get(k)} != {y.get(k)}" for k in keys if x.get(k) != y.get(k)]
    return diffs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("out", type=Path)
    r.add_argument("--full", action="store_true")
    r.add_argument("--inputs", type=Path, default=None)
    c = sub.add_parser("compare")
    c.add_argument("a", type=Path)
    c.add_argument("b", type=Path)
    args = ap.parse_args()
    if args.cmd == "run":
        res = run(args.out, args.full, args.inputs)
        print(json.dumps(res, indent=1, sort_keys=True))
        return
    diffs = compare(json.loads(args.a.read_text()), json.loads(args.b.read_text()))
    print("\n".join(diffs) if diffs else "identical")
    sys.exit(1 if diffs else 0)


if __name__ == "__main__":
    main()
