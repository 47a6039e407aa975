#!/usr/bin/env bash
# Our bonsai fit of the 600-s equal-time comparison at seed 2 (benchmarks/README.md, "Measurement log", 2026-11-29),
# encoded with the defaults and scored on the 37 held-out views at 10%..100%; run alone (a wall-time budget).
# Plain 3DGS at seed 2: SEED=2 benchmarks/bonsai_equal_time.sh 600 DIR 3dgs. Then
#   python benchmarks/compare_evals.py container_s0=../eval_container_lr0.01.json container_s1=../seed1/eval_container_seed1.json container_s2=OUT/eval/eval.json
#   3dgs_s0=../eval_3dgs.json 3dgs_s1=../seed1/eval_3dgs_seed1.json 3dgs_s2=DIR/3dgs_eval/eval.json --baseline 3dgs_s2 (--bytes as in compare.md)
#   --out OUT/compare
set -euo pipefail
D=${DATA:-../shared/data/mipnerf360/bonsai}
OUT=${1:-/tmp/bonsai_seed2}
mkdir -p "$OUT"
proxycodec fit "$D" --max-width 800 --time-budget 600 --seed 2 -o "$OUT/bonsai_s2.ply"
proxycodec encode "$OUT/bonsai_s2.ply" -o "$OUT/bonsai_s2.pxc"
proxycodec stats "$OUT/bonsai_s2.pxc" > "$OUT/stats.txt"
proxycodec eval "$OUT/bonsai_s2.pxc" "$D" --res 0.1,0.2,0.3,0.4,0.5,0.6,0.7,0.8,0.9,1.0 -o "$OUT/eval"
