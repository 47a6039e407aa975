#!/usr/bin/env bash
# Bonsai at 600 s with --no-decoder-lr-restart, seeds 0..2, as ../run_seed.sh runs the defaults (benchmarks/README.md,
# "Measurement log", 2026-11-29). As run, each fit alone on the machine:
#   benchmarks/results/bonsai800/equal_time_600/no_decoder_lr_restart/run.sh [OUT]
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/../../../../.." && pwd)
D=${DATA:-$(cd "$ROOT/.." && pwd)/shared/data/mipnerf360/bonsai}
BASE=${1:-/tmp/bonsai_no_decoder_lr_restart}
for SEED in 0 1 2; do
  OUT=$BASE/s$SEED; mkdir -p "$OUT"
  /usr/bin/time -v proxycodec fit "$D" --max-width 800 --time-budget 600 --seed $SEED --no-decoder-lr-restart \
    -o "$OUT/bonsai_s$SEED.ply" > "$OUT/fit.log" 2>&1
  proxycodec encode "$OUT/bonsai_s$SEED.ply" -o "$OUT/bonsai_s$SEED.pxc" > "$OUT/encode.log" 2>&1
  proxycodec stats "$OUT/bonsai_s$SEED.pxc" > "$OUT/stats.txt"
  proxycodec eval "$OUT/bonsai_s$SEED.pxc" "$D" --res 0.1,0.2,0.3,0.4,0.5,0.6,0.7,0.8,0.9,1.0 -o "$OUT/eval" \
    > "$OUT/eval.log" 2>&1
done
