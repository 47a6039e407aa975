"""The table of benchmarks/README.md, "Measurement log", 2026-11-29, "How anchors start", from the eval reports here
and in equal_time_600/:

    python benchmarks/results/bonsai800/equal_time_600/how_anchors_start/table.py
"""
import json
from pathlib import Path

E = Path(__file__).resolve().parents[1]  # equal_time_600/
def row(p):
    r = json.load(open(p))["per_resolution"]
    return [x["psnr"] for x in r]
ours = {s: row(f"{E}/how_anchors_start/s{s}/eval.json") for s in (0, 1, 2)}
old_ours = {0: row(f"{E}/eval_container_lr0.01.json"), 1: row(f"{E}/seed1/eval_container_seed1.json"),
            2: row(f"{E}/seed2/eval_container_seed2.json")}
g_old = {0: row(f"{E}/eval_3dgs.json"), 1: row(f"{E}/seed1/eval_3dgs_seed1.json"),
         2: row(f"{E}/seed2/eval_3dgs_seed2.json")}
g_new = {}
for s in (0, 1, 2):
    try:
        g_new[s] = row(f"{E}/how_anchors_start/3dgs_s{s}/eval.json")
    except FileNotFoundError:
        pass
def fmt(name, v, bold=True, sign=False):
    f = (lambda x: f"{x:+.2f}") if sign else (lambda x: f"{x:.2f}")
    m = sum(v) / len(v)
    extra = f" (min {min(v):+.2f})" if sign else ""
    return f"| {name} | " + " | ".join(f(x) for x in v) + f" | **{f(m)}**{extra} |"
def mean(rows):
    return [sum(c) / len(c) for c in zip(*rows)]
def diff(a, b):
    return [x - y for x, y in zip(a, b)]
print("| | 10% | 20% | 30% | 40% | 50% | 60% | 70% | 80% | 90% | 100% | mean |")
print("|---|" + "---:|" * 11)
for s in (0, 1, 2): print(fmt(f"ours, new start, seed {s}", ours[s]))
for s in (0, 1, 2): print(fmt(f"ours, former start, seed {s} (above)", old_ours[s]))
for s in (0, 1, 2): print(fmt(f"plain 3DGS, seed {s} (above)", g_old[s]))
for s in g_new: print(fmt(f"plain 3DGS, seed {s}, run again", g_new[s]))
for s in (0, 1, 2): print(fmt(f"seed {s}: new start - 3DGS (above)", diff(ours[s], g_old[s]), sign=True))
for s in g_new: print(fmt(f"seed {s}: new start - 3DGS run again", diff(ours[s], g_new[s]), sign=True))
print(fmt("three seeds: new start - 3DGS (above)", mean([diff(ours[s], g_old[s]) for s in (0, 1, 2)]), sign=True))
if len(g_new) == 3:
    print(fmt("three seeds: new start - 3DGS run again", mean([diff(ours[s], g_new[s]) for s in (0, 1, 2)]), sign=True))
    print(fmt("three seeds: new start - all six 3DGS runs",
              mean([diff(ours[s], g) for s in (0, 1, 2) for g in (g_old[s], g_new[s])]), sign=True))
print(fmt("three seeds: new start - former start", mean([diff(ours[s], old_ours[s]) for s in (0, 1, 2)]), sign=True))
