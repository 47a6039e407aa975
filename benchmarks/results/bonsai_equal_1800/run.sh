#!/bin/bash
# bonsai at 800 px, 1800 s each on 2 cores: ours (the 1800-s spacing fit of benchmarks/results/bonsai_density_1800,
# linked as ours.*), plain 3DGS, and ours trained at 100% only (--fixed-res: single-scale train, multi-scale test)
cd /work/main
date -u +"start %FT%TZ"
/usr/bin/time -v benchmarks/bonsai_equal_time.sh 1800 /work/runs/equal1800 ours,3dgs,fixedres,encode,compare
date -u +"done %FT%TZ"
