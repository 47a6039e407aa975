#!/usr/bin/env bash
# bonsai at 600 s with --no-decoder-lr-restart, seeds 0..2, as equal_time_600/run_seed.sh does for the defaults
set -euo pipefail
D=/work/shared/data/mipnerf360/bonsai
for SEED in 0 1 2; do
  OUT=/work/runs/declr600/s$SEED; mkdir -p $OUT
  /usr/bin/time -v proxycodec fit "$D" --max-width 800 --time-budget 600 --seed $SEED --no-decoder-lr-restart -o "$OUT/bonsai_s$SEED.ply" > $OUT/fit.log 2>&1
  proxycodec encode "$OUT/bonsai_s$SEED.ply" -o "$OUT/bonsai_s$SEED.pxc" > $OUT/encode.log 2>&1
  proxycodec stats "$OUT/bonsai_s$SEED.pxc" > "$OUT/stats.txt"
  proxycodec eval "$OUT/bonsai_s$SEED.pxc" "$D" --res 0.1,0.2,0.3,0.4,0.5,0.6,0.7,0.8,0.9,1.0 -o "$OUT/eval" > $OUT/eval.log 2>&1
done
