"""A longer fuzz run over every file reader: seeded mutations of valid seed files.

    python benchmarks/fuzz_long.py [--inputs 12000] [--seed 0] [--json out.json] [--mem-gib 3]
    python benchmarks/fuzz_long.py --atheris READER [RUNS]     # coverage-guided, needs `pip install atheris`

Seeds and mutations are those of ``tests/test_fuzz_readers.py`` (truncations, bit flips, huge counts/sizes written
over aligned slots, NaN/Inf payloads, number tokens replaced in text formats, splices of other seed files, inserted,
deleted and duplicated chunks), plus, for containers, forged tables of contents with valid CRCs. Every input is
classified: accepted, our error (``ProxycodecError``), or anything else (a bug). The address space is capped
(``--mem-gib``) so that a reader that tries to allocate without bound fails with MemoryError (counted as a bug)
instead of taking the machine down. Prints a table, writes JSON (machine, versions, seed, counts, wall time, peak
RSS) and keeps every bug input under ``--bugs`` for triage. Exit status 1 when a bug was found.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import platform
import random
import resource
import sys
import tempfile
import time
import traceback
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

import test_fuzz_readers as F


def _forged_container(rng: random.Random) -> bytes:
    """A container whose table of contents has hostile fields but valid CRCs."""
    def u64():
        return rng.choice([rng.randrange(0, 64), rng.choice(F.HUGE), rng.getrandbits(64)])

    meta = rng.choice([b'{"kind":"x"}', b"[]", b'{"a": NaN}', b"\xff", b"{" * 50])
    m, stored = F._meta_entry(meta, 0, rng.choice([0, 1]))
    entries = [m]
    for k in range(rng.randint(0, 3)):
        entries.append({"name": rng.choice(["s", "meta", "a/b", "x" * 64, "é"]) + str(k), "codec": rng.randrange(3),
                        "dtype": rng.randrange(13), "shape": tuple(u64() for _ in range(rng.randrange(4))),
                        "offset": u64(), "stored": u64(), "raw": u64(), "crc": rng.getrandbits(32)})
    m["offset"] = 32 + F._toc_size(entries)
    return F.forge_container(entries, stored + rng.randbytes(rng.randrange(64)),
                             version=rng.choice([1, 1, 1, 0, 2]), n_sections=len(entries) + rng.choice([0, 0, 1]))


def run_atheris(reader: str, runs: int, mem_gib: float) -> int:
    """Coverage-guided fuzzing of one reader with atheris (optional: ``pip install atheris``).

    libFuzzer ends the process with C ``exit()``: its working folder (``/tmp/pxc-atheris-*``) may be left behind.
    """
    import atheris

    seeds = F.make_seeds()
    work = Path(tempfile.mkdtemp(prefix="pxc-atheris-"))
    corpus = work / "corpus"
    corpus.mkdir()
    (corpus / "seed").write_bytes(seeds[reader])
    counts = collections.Counter()

    def one_input(data: bytes) -> None:
        out, exc = F.run_reader(reader, data, work)
        counts[out] += 1
        if out == F.BUG:
            raise exc
        for p in work.iterdir():
            if p.is_dir() and p.name != "corpus":
                for q in sorted(p.rglob("*"), reverse=True):
                    q.unlink() if q.is_file() else q.rmdir()
                p.rmdir()

    import inspect

    for mod_name, mod in list(sys.modules.items()):  # instrument our readers only (not torch and friends)
        if mod_name.startswith("proxycodec.formats") and mod is not None:
            for k, v in list(vars(mod).items()):
                if inspect.isfunction(v) and v.__module__ == mod_name:
                    setattr(mod, k, atheris.instrument_func(v))
                elif inspect.isclass(v) and v.__module__ == mod_name:
                    for kk, vv in list(vars(v).items()):
                        if inspect.isfunction(vv):
                            setattr(v, kk, atheris.instrument_func(vv))
    F.READERS.update({k: getattr(sys.modules[f.__module__], f.__name__, f) if hasattr(f, "__module__") and
                      f.__module__ in sys.modules and f.__module__.startswith("proxycodec.formats") else f
                      for k, f in F.READERS.items()})
    cap = int(mem_gib * (1 << 30))
    resource.setrlimit(resource.RLIMIT_AS, (cap, cap))
    atheris.Setup([sys.argv[0], f"-runs={runs}", str(corpus)], one_input)
    try:
        atheris.Fuzz()
    except SystemExit:
        pass
    finally:
        import shutil

        shutil.rmtree(work, ignore_errors=True)
        print(f"atheris on {reader}: {dict(counts)}", file=sys.stderr)
    return 0


def main() -> int:
    if "--atheris" in sys.argv:  # python benchmarks/fuzz_long.py --atheris READER [RUNS]
        i = sys.argv.index("--atheris")
        return run_atheris(sys.argv[i + 1], int(sys.argv[i + 2]) if len(sys.argv) > i + 2 else 5000, 3.0)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--inputs", type=int, default=12000, help="total number of fuzz inputs (all readers)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", default="fuzz_long.json", help="where to write the results")
    ap.add_argument("--bugs", default="fuzz_bugs", help="folder for inputs that triggered bugs")
    ap.add_argument("--mem-gib", type=float, default=3.0, help="address-space cap (GiB)")
    args = ap.parse_args()

    seeds = F.make_seeds()
    all_seeds = list(seeds.values())
    names = sorted(F.READERS)
    cap = int(args.mem_gib * (1 << 30))
    resource.setrlimit(resource.RLIMIT_AS, (cap, cap))
    rng = random.Random(args.seed)
    counts: dict[str, collections.Counter] = {n: collections.Counter() for n in names}
    bug_kinds: dict[str, dict] = {}
    bugs_dir = Path(args.bugs)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="pxc-fuzz-long-") as d:
        work = Path(d)
        for n in names:  # the seeds themselves must be accepted
            out, exc = F.run_reader(n, seeds[n], work)
            if out != F.OK:
                raise SystemExit(f"seed for {n} is not accepted: {exc!r}")
        for i in range(args.inputs):
            name = names[i % len(names)]
            kind = "mutation"
            if name == "container" and rng.random() < 0.3:
                data, kind = _forged_container(rng), "forged"
            else:
                data = F.mutate(seeds[name], rng, all_seeds)
            out, exc = F.run_reader(name, data, work)
            counts[name][out] += 1
            if out == F.BUG:
                tb = traceback.extract_tb(exc.__traceback__) if exc.__traceback__ else []
                where = f"{Path(tb[-1].filename).name}:{tb[-1].lineno}" if tb else "?"
                key = f"{name}|{type(exc).__name__}|{where}"
                if key not in bug_kinds:
                    bugs_dir.mkdir(exist_ok=True)
                    p = bugs_dir / f"{name}_{len(bug_kinds):03d}.bin"
                    p.write_bytes(data)
                    bug_kinds[key] = {"reader": name, "exception": type(exc).__name__, "message": str(exc)[:200],
                                      "where": where, "input": str(p), "kind": kind, "count": 0}
                bug_kinds[key]["count"] += 1
            if (i + 1) % 2000 == 0:
                print(f"  {i + 1:6d} inputs  {time.perf_counter() - t0:6.1f} s", file=sys.stderr, flush=True)
            if i % 500 == 0:  # keep the temporary folder small
                for p in work.iterdir():
                    if p.is_dir():
                        for q in p.rglob("*"):
                            if q.is_file():
                                q.unlink()
    wall = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024

    print(f"{'reader':18s} {'inputs':>7s} {'accepted':>9s} {'our_error':>10s} {'bug':>5s}")
    tot = collections.Counter()
    for n in names:
        c = counts[n]
        tot.update(c)
        print(f"{n:18s} {sum(c.values()):7d} {c[F.OK]:9d} {c[F.OURS]:10d} {c[F.BUG]:5d}")
    print(f"{'total':18s} {sum(tot.values()):7d} {tot[F.OK]:9d} {tot[F.OURS]:10d} {tot[F.BUG]:5d}")
    print(f"wall {wall:.1f} s, peak RSS {peak / 2**20:.0f} MiB, seed {args.seed}")
    for b in bug_kinds.values():
        print(f"BUG {b['reader']}: {b['exception']} at {b['where']} x{b['count']}: {b['message'][:100]} ({b['input']})")

    import numpy
    import zstandard

    try:
        import torch
        torch_v = torch.__version__
    except ImportError:  # pragma: no cover
        torch_v = None
    result = {
        "machine": {"platform": platform.platform(), "processor": platform.processor() or platform.machine(),
                    "cpus": os.cpu_count(), "python": platform.python_version()},
        "versions": {"numpy": numpy.__version__, "zstandard": zstandard.__version__, "torch": torch_v},
        "seed": args.seed, "inputs": sum(tot.values()), "mem_cap_bytes": cap,
        "counts": {n: dict(counts[n]) for n in names},
        "totals": dict(tot), "bugs": list(bug_kinds.values()), "wall_seconds": wall, "peak_rss_bytes": peak,
        "command": " ".join([Path(sys.executable).name] + sys.argv),
    }
    Path(args.json).write_text(json.dumps(result, indent=2))
    print(f"wrote {args.json}")
    return 1 if tot[F.BUG] else 0


if __name__ == "__main__":
    sys.exit(main())
