#!/usr/bin/env bash
# Bonsai at 600 s with the anchors' new start (SfM colours, Gaussians as large as at the spacing density; the
# defaults since), seeds 0..2, then plain 3DGS again for the same seeds on the same days' machine (benchmarks/README.md,
# "Measurement log", 2026-11-29, "How anchors start"). As run, each fit alone on the machine:
#   benchmarks/results/bonsai800/equal_time_600/how_anchors_start/run.sh [OUT]
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/../../../../.." && pwd)
D=${DATA:-$(cd "$ROOT/.." && pwd)/shared/data/mipnerf360/bonsai}
BASE=${1:-/tmp/bonsai_how_anchors_start}
for SEED in 0 1 2; do
  OUT=$BASE/s$SEED; mkdir -p "$OUT"
  /usr/bin/time -v proxycodec fit "$D" --max-width 800 --time-budget 600 --seed $SEED -o "$OUT/bonsai_s$SEED.ply" \
    > "$OUT/fit.log" 2>&1
  proxycodec encode "$OUT/bonsai_s$SEED.ply" -o "$OUT/bonsai_s$SEED.pxc" > "$OUT/encode.log" 2>&1
  proxycodec stats "$OUT/bonsai_s$SEED.pxc" > "$OUT/stats.txt"
  proxycodec eval "$OUT/bonsai_s$SEED.pxc" "$D" --res 0.1,0.2,0.3,0.4,0.5,0.6,0.7,0.8,0.9,1.0 -o "$OUT/eval" \
    > "$OUT/eval.log" 2>&1
done
for SEED in 0 1 2; do
  SEED=$SEED DATA=$D "$ROOT/benchmarks/bonsai_equal_time.sh" 600 "$BASE/3dgs_s$SEED" 3dgs
done
