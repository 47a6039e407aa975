#!/bin/bash
# anchor budgets with the rate term in conversion: the built-in scene's 3DGS export, 1000 conversion iterations
cd /work/runs/budget
for t in 250000 150000; do
  /usr/bin/time -v proxycodec encode splats.ply -o t$t.pxc --distill-iters 1000 --target-size $t > t$t.log 2>&1
done
echo done > status
