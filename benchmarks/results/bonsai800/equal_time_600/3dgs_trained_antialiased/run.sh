#!/usr/bin/env bash
# plain 3DGS trained with the antialiased filter (fit --explicit --antialiased), bonsai, 600 s, seed 0, as
# bonsai_equal_time.sh's 3dgs step; evaluated with its compensation (eval --antialiased on) and without
set -euo pipefail
D=${DATA:-../shared/data/mipnerf360/bonsai}
OUT=${1:-.}
RES=0.1,0.2,0.3,0.4,0.5,0.6,0.7,0.8,0.9,1.0
/usr/bin/time -v proxycodec --threads 2 fit "$D" --max-width 800 --time-budget 600 --seed 0 --explicit --antialiased \
  -o "$OUT/3dgs_aa.ply" > "$OUT/3dgs_aa.fit.log" 2>&1
proxycodec eval "$OUT/3dgs_aa.ply" "$D" --res $RES --max-width 800 --antialiased on -o "$OUT/eval_aa" \
  > "$OUT/eval_aa.log" 2>&1
proxycodec eval "$OUT/3dgs_aa.ply" "$D" --res $RES --max-width 800 -o "$OUT/eval_plain" > "$OUT/eval_plain.log" 2>&1
