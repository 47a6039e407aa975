#!/bin/bash
# bonsai 800 px, 1800 s, default density, --lambda-rate 1e-3 (10x the default): does the rate weight move the
# container toward 10x under the SPZ at 30 minutes? Compared with /work/runs/equal1800 (lambda 1e-4).
set -e
cd /work/main
D=/work/shared/data/mipnerf360/bonsai
W=/work/runs/rate1800
R=0.1,0.2,0.3,0.4,0.5,0.6,0.7,0.8,0.9,1.0
date -u +"fit start %FT%TZ"
/usr/bin/time -v proxycodec fit $D -o $W/r1e3.ply --time-budget 1800 --max-width 800 --seed 0 --lambda-rate 1e-3 > $W/r1e3.fit.log 2>&1
date -u +"encode start %FT%TZ"
/usr/bin/time -v proxycodec encode $W/r1e3.ply -o $W/r1e3.pxc > $W/r1e3.encode.log 2>&1
date -u +"eval start %FT%TZ"
proxycodec eval $W/r1e3.pxc $D --max-width 800 --res $R -o $W/r1e3_pxc_eval > $W/r1e3.pxc_eval.log 2>&1
date -u +"done %FT%TZ"
