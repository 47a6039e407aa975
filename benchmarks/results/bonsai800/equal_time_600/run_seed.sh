#!/usr/bin/env bash
# One seed of the 600-s equal-time comparison on bonsai (benchmarks/README.md, "Measurement log", 2026-11-29): our fit
# encoded with the defaults and plain 3DGS, each for 600 s, each alone (wall-time budgets), scored on the 37
# held-out views at 10%..100%. As run for seeds 1 and 2 (seed0's files are this folder's own).
#   benchmarks/results/bonsai800/equal_time_600/run_seed.sh SEED [OUT]
# Then, from the repository root: python benchmarks/compare_evals.py container_sK=OUT/eval/eval.json
#   3dgs_sK=OUT/3dgs/3dgs_eval/eval.json ... --baseline 3dgs_sK --bytes ... --out OUT/compare
set -euo pipefail
SEED=${1:?usage: run_seed.sh SEED [OUT]}
OUT=${2:-/tmp/bonsai_seed$SEED}
ROOT=$(cd "$(dirname "$0")/../../../.." && pwd)
D=${DATA:-$(cd "$ROOT/.." && pwd)/shared/data/mipnerf360/bonsai}
mkdir -p "$OUT"
proxycodec fit "$D" --max-width 800 --time-budget 600 --seed "$SEED" -o "$OUT/bonsai_s$SEED.ply"
proxycodec encode "$OUT/bonsai_s$SEED.ply" -o "$OUT/bonsai_s$SEED.pxc"
proxycodec stats "$OUT/bonsai_s$SEED.pxc" > "$OUT/stats.txt"
proxycodec eval "$OUT/bonsai_s$SEED.pxc" "$D" --res 0.1,0.2,0.3,0.4,0.5,0.6,0.7,0.8,0.9,1.0 -o "$OUT/eval"
SEED=$SEED DATA=$D "$ROOT/benchmarks/bonsai_equal_time.sh" 600 "$OUT/3dgs" 3dgs
