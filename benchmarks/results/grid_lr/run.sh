#!/usr/bin/env bash
# The grids' learning rate (fit --lr-quant-step), benchmarks/README.md "The grids' learning rate": the trade-off
# map's main fits (bonsai 800 px / 600 s, lego 400 px / 900 s, seed 0, the defaults otherwise) at the former
# default 2e-3 and at 1e-2, each encoded with the defaults and scored on the map's first test views (4 / 8).
# One fit at a time, nothing else running (wall-time budgets). As run 2026-11-29 (the 1e-2 fits by a script
# passing FitConfig(lr_quant_step=...) before the option existed; the same configuration).
set -euo pipefail
S=${SHARED:-../shared/data}
OUT=${1:-/tmp/grid_lr}
RES=0.1,0.2,0.3,0.4,0.5,0.6,0.7,0.8,0.9,1.0
mkdir -p "$OUT"
for lr in 0.01 0.002; do
  for spec in "bonsai $S/mipnerf360/bonsai 800 600 4" "lego $S/nerf_synthetic/lego 400 900 8"; do
    read -r name data width budget views <<< "$spec"
    o=$OUT/${name}_lr$lr
    proxycodec fit "$data" --max-width "$width" --time-budget "$budget" --seed 0 --lr-quant-step "$lr" -o "$o.ply"
    proxycodec encode "$o.ply" -o "$o.pxc"
    proxycodec stats "$o.pxc" > "$o.stats.txt"
    proxycodec eval "$o.pxc" "$data" --max-width "$width" --views "$views" --res $RES -o "${o}_eval"
  done
done
