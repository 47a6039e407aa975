#!/bin/bash
# fit --target-size, measured (Intel Xeon, 2 cores, each run alone): lego at 200 px, 1500 iterations, 80,000 B;
# bonsai at 800 px, 600 s, 250,000 B. Each: fit, encode with the defaults, eval at 10%..100% on the held-out views.
set -e
DATA=$(cd "$(dirname "$0")/../../../../../shared/data" && pwd)
OUT=${1:?out dir}
mkdir -p "$OUT/lego80k" "$OUT/bonsai250k"
cd "$OUT/lego80k"
proxycodec fit "$DATA/nerf_synthetic/lego" -o lego.ply --max-width 200 --iters 1500 --seed 0 \
  --target-size 80000 2> fit.err
proxycodec encode lego.ply -o lego.pxc > enc.log 2>&1
proxycodec eval lego.pxc "$DATA/nerf_synthetic/lego" --max-width 200 --res 0.1,0.2,0.3,0.4,0.5,0.6,0.7,0.8,0.9,1.0 \
  --json > eval.json
cd "$OUT/bonsai250k"
proxycodec fit "$DATA/mipnerf360/bonsai" -o bonsai.ply --max-width 800 --time-budget 600 --seed 0 \
  --target-size 250000 2> fit.err
proxycodec encode bonsai.ply -o bonsai.pxc > enc.log 2>&1
proxycodec eval bonsai.pxc "$DATA/mipnerf360/bonsai" --max-width 800 --res 0.1,0.2,0.3,0.4,0.5,0.6,0.7,0.8,0.9,1.0 \
  --json > eval.json
