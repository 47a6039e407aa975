#!/bin/bash
# conversion of bonsai's 30-min 3DGS PLY (equal1800, 299k Gaussians) at 800 px for 1200 s of training, with and without
# the rate term; each converted, encoded and scored by benchmarks/convert.py
cd /work/main
for lam in 0 1e-4; do
  /usr/bin/time -v python benchmarks/convert.py --scenes bonsai --input bonsai=/work/runs/equal1800/3dgs.ply --max-width 800 \
    --fit iters=null --fit time_budget=1200 --fit lambda_rate=$lam \
    --out /work/main/benchmarks/results/convert_rate_bonsai/lambda_$lam > /work/runs/convrate/lambda_$lam.log 2>&1
done
echo done > /work/runs/convrate/status
