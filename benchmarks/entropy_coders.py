"""Arithmetic / ANS coders for issue #17's entropy model, chosen by measurement: constriction, CompressAI's rANS and
torchac on the same symbols and the same integer CDF tables.

The symbols stand in for what the entropy model will code: N integers, each with its own predicted distribution,
here a zero-mean Gaussian quantised to the integers -32..32 with one of 64 scales (geometric, 0.11..10; the
scale index per symbol is what the decoder would predict). The tables are 16-bit integer CDFs built once, the way
CompressAI builds them (``pmf_to_quantized_cdf``: every symbol at least one count, the rest by rounding), and fed to
each coder in its own form:

- CompressAI (``compressai.ans``, rANS, the C++ extension its wheel ships): the tables and a table index per symbol;
- torchac (a C++ extension compiled at import time by ``torch.utils.cpp_extension``: needs a compiler): one int16 CDF
  row per symbol;
- constriction (Rust, ANS ``stack.AnsCoder``): the same tables as ``Categorical`` models (one per table, symbols
  coded table by table in a fixed order), and, for reference, its native ``QuantizedGaussian`` with per-symbol
  scales, whose CDF it evaluates in floating point inside the coder.

Per coder: compressed bytes, bits per symbol against the ideal (the sum of -log2 p under the same 16-bit tables),
median encode and decode time over ``--repeats`` runs, and whether the decode is exact. The packages are optional:
a coder that cannot be imported is reported with the reason. ``--compressai-so`` loads CompressAI's extension
directly from its wheel's folder when the package itself cannot be imported (its ``__init__`` pulls in
torchvision and torch_geometric).

    python benchmarks/entropy_coders.py [--n 500000] [--repeats 3] [--out benchmarks/results/entropy_coders]
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
SUPPORT = 32  # symbols -32..32
LEVELS = 64
PRECISION = 16


def scale_table() -> np.ndarray:
    return np.exp(np.linspace(math.log(0.11), math.log(10.0), LEVELS))


def quantized_cdfs(scales: np.ndarray) -> np.ndarray:
    """[LEVELS, 2 * SUPPORT + 2] int32 CDFs (0 .. 2^16) of N(0, s) on the integers -SUPPORT..SUPPORT (the tails folded
    into the end symbols), every symbol at least one count: CompressAI's ``pmf_to_quantized_cdf`` rule, in numpy."""
    total = 1 << PRECISION
    k = np.arange(-SUPPORT, SUPPORT + 1, dtype=np.float64)
    out = np.zeros((len(scales), 2 * SUPPORT + 2), np.int64)
    erf = np.vectorize(math.erf)
    for i, s in enumerate(scales):
        c = 0.5 * (1 + erf((k + 0.5) / (s * math.sqrt(2))))
        pmf = np.diff(np.concatenate([[0.0], c]))
        pmf[-1] += 1.0 - c[-1]
        freq = np.maximum(1, np.round(pmf * (total - len(pmf)))).astype(np.int64)
        # hand the rounding error to the most likely symbols (never below 1)
        err = total - freq.sum()
        order = np.argsort(-freq, kind="stable")
        j = 0
        while err != 0:
            step = 1 if err > 0 else -1
            if freq[order[j % len(freq)]] + step >= 1:
                freq[order[j % len(freq)]] += step
                err -= step
            j += 1
        out[i, 1:] = np.cumsum(freq)
    return out.astype(np.int32)


def ideal_bits(cdfs: np.ndarray, idx: np.ndarray, sym: np.ndarray) -> float:
    f = (cdfs[idx, sym + SUPPORT + 1] - cdfs[idx, sym + SUPPORT]).astype(np.float64)
    return float(-np.log2(f / (1 << PRECISION)).sum())


def timed(fn, repeats: int):
    ts, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        ts.append(time.perf_counter() - t0)
    return out, statistics.median(ts)


# ------------------------------------------------------------------------------------------------ the coders
def run_compressai(so_dir: str | None, cdfs, idx, sym, repeats):
    if so_dir:
        paths = sorted(Path(so_dir).glob("ans.*.so"))
        if not paths:
            return {"skipped": f"no ans.*.so in {so_dir}"}
        spec = importlib.util.spec_from_file_location("ans", paths[0])
        ans = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(ans)
    else:
        try:
            from compressai import ans  # type: ignore[import-not-found]
        except Exception as e:  # noqa: BLE001 - any import failure is a finding
            return {"skipped": f"import compressai failed: {type(e).__name__}: {e}"}
    # CompressAI's layout: per table its CDF (length 2 * SUPPORT + 2 here, no escape symbol needed since the tails
    # are folded), its length and its offset (the value of the first symbol)
    cdf_list = [list(map(int, c)) for c in cdfs]
    lengths = [len(c) for c in cdf_list]
    offsets = [-SUPPORT] * len(cdf_list)

    def enc():  # its API takes Python lists: the conversion is part of the cost
        return ans.RansEncoder().encode_with_indexes(sym.tolist(), idx.tolist(), cdf_list, lengths, offsets)

    data, t_enc = timed(enc, repeats)
    dec, t_dec = timed(lambda: np.asarray(ans.RansDecoder().decode_with_indexes(data, idx.tolist(), cdf_list,
                                                                                 lengths, offsets)), repeats)
    return {"bytes": len(data), "encode_s": t_enc, "decode_s": t_dec, "exact": bool((dec == sym).all()),
            "input": "integer CDF tables + a table index per symbol (Python lists)"}


def run_torchac(cdfs, idx, sym, repeats):
    try:
        import torch
        import torchac  # type: ignore[import-not-found]
    except Exception as e:  # noqa: BLE001
        return {"skipped": f"import torchac failed (it compiles a C++ extension at import): {type(e).__name__}: {e}"}
    # torchac wants one CDF row per symbol, int16 "normalized" (values 0..2^16 stored modulo 2^16), symbols 0-based
    table16 = torch.from_numpy(np.where(cdfs >= 1 << 15, cdfs - (1 << 16), cdfs).astype(np.int16))
    ti = torch.from_numpy(idx)
    s = torch.from_numpy((sym + SUPPORT).astype(np.int16))
    # the per-symbol rows are built inside the timing: they are part of the cost (N x 66 int16)
    data, t_enc = timed(lambda: torchac.encode_int16_normalized_cdf(table16[ti], s), repeats)
    dec, t_dec = timed(lambda: torchac.decode_int16_normalized_cdf(table16[ti], data), repeats)
    return {"bytes": len(data), "encode_s": t_enc, "decode_s": t_dec, "exact": bool((dec == s).all()),
            "input": "one int16 CDF row per symbol", "row_table_mb": len(idx) * cdfs.shape[1] * 2 / 1e6}


def run_constriction(cdfs, idx, sym, scales, repeats):
    try:
        import constriction  # type: ignore[import-not-found]
    except Exception as e:  # noqa: BLE001
        return {"skipped": f"import constriction failed: {type(e).__name__}: {e}"}
    model = constriction.stream.model
    # the same integer tables as categorical models, symbols grouped by table (the decoder knows every index)
    probs = np.diff(cdfs, axis=1).astype(np.float64) / (1 << PRECISION)  # k / 2^16: exact in float64
    vals = (sym + SUPPORT).astype(np.int32)

    def setup():  # the models and the grouping by table are part of the cost, on both sides
        order = np.argsort(idx, kind="stable")
        bounds = np.searchsorted(idx[order], np.arange(len(cdfs) + 1))
        return ([model.Categorical(p, perfect=False) for p in probs],
                [order[bounds[t]:bounds[t + 1]] for t in range(len(cdfs))])

    def enc():
        cats, groups = setup()
        coder = constriction.stream.stack.AnsCoder()
        for t in reversed(range(len(cdfs))):  # a stack: encode in reverse of the decode order
            if len(groups[t]):
                coder.encode_reverse(vals[groups[t]], cats[t])
        return coder.get_compressed()

    data, t_enc = timed(enc, repeats)

    def dec():
        cats, groups = setup()
        coder = constriction.stream.stack.AnsCoder(data)
        out = np.empty_like(vals)
        for t in range(len(cdfs)):
            if len(groups[t]):
                out[groups[t]] = coder.decode(cats[t], len(groups[t]))
        return out

    out, t_dec = timed(dec, repeats)
    res = {"bytes": int(data.nbytes), "encode_s": t_enc, "decode_s": t_dec, "exact": bool((out == vals).all()),
           "input": "the integer tables as 64 Categorical models (float probabilities, re-quantised inside)"}
    # native parametric family: the CDF is evaluated in floating point inside the coder, per symbol
    fam = model.QuantizedGaussian(-SUPPORT, SUPPORT)
    means = np.zeros(len(sym), np.float64)
    stds = scales[idx].astype(np.float64)
    s32 = sym.astype(np.int32)

    def enc2():
        coder = constriction.stream.stack.AnsCoder()
        coder.encode_reverse(s32, fam, means, stds)
        return coder.get_compressed()

    data2, t_enc2 = timed(enc2, repeats)
    out2, t_dec2 = timed(lambda: constriction.stream.stack.AnsCoder(data2).decode(fam, means, stds), repeats)
    res["native_quantized_gaussian"] = {"bytes": int(data2.nbytes), "encode_s": t_enc2, "decode_s": t_dec2,
                                        "exact": bool((out2 == s32).all())}
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=500_000, help="symbols [default: 500000]")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--compressai-so", default=None, help="folder holding CompressAI's ans.*.so (see above)")
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "entropy_coders"))
    args = ap.parse_args(argv)
    sys.path.insert(0, str(REPO))
    from proxycodec.bench import machine_info, versions

    rng = np.random.default_rng(args.seed)
    scales = scale_table()
    cdfs = quantized_cdfs(scales)
    idx = rng.integers(0, LEVELS, args.n)
    sym = np.clip(np.rint(rng.normal(0.0, scales[idx])), -SUPPORT, SUPPORT).astype(np.int64)
    ideal = ideal_bits(cdfs, idx, sym)
    res = {
        "compressai_rans": run_compressai(args.compressai_so, cdfs, idx, sym, args.repeats),
        "torchac": run_torchac(cdfs, idx, sym, args.repeats),
        "constriction_ans": run_constriction(cdfs, idx, sym, scales, args.repeats),
    }
    vers = {}
    for pkg in ("constriction", "compressai", "torchac"):
        try:
            from importlib.metadata import version

            vers[pkg] = version(pkg)
        except Exception:  # noqa: BLE001
            vers[pkg] = None
    meta = {"machine": machine_info(), "versions": {**versions(), **vers}, "python": platform.python_version(),
            "seed": args.seed, "n": args.n, "repeats": args.repeats, "support": [-SUPPORT, SUPPORT],
            "levels": LEVELS, "precision_bits": PRECISION, "ideal_bytes": ideal / 8}
    lines = [f"# Entropy coders on {args.n:,} symbols (64 quantised-Gaussian tables, 16-bit CDFs)", "",
             f"Ideal (sum of -log2 p under the tables): {ideal / 8:,.0f} B = {ideal / args.n:.4f} bits/symbol.", "",
             "| coder | bytes | bits/symbol | over ideal | encode (ms) | decode (ms) | Msym/s dec | exact |",
             "|---|---:|---:|---:|---:|---:|---:|:-:|"]
    rows = [(k, v) for k, v in res.items()]
    if "native_quantized_gaussian" in res["constriction_ans"]:
        rows.append(("constriction, native QuantizedGaussian (float CDF in the coder)",
                     res["constriction_ans"]["native_quantized_gaussian"]))
    for name, r in rows:
        if "skipped" in r:
            lines.append(f"| {name} | skipped: {r['skipped'][:120]} | | | | | | |")
            continue
        lines.append(f"| {name} | {r['bytes']:,} | {8 * r['bytes'] / args.n:.4f} | "
                     f"{100 * (8 * r['bytes'] / ideal - 1):+.2f}% | {1000 * r['encode_s']:.1f} | "
                     f"{1000 * r['decode_s']:.1f} | {args.n / r['decode_s'] / 1e6:.1f} | "
                     f"{'yes' if r['exact'] else '**no**'} |")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "entropy_coders.json").write_text(json.dumps({"meta": meta, "results": res}, indent=1))
    (out / "entropy_coders.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
