#!/bin/bash
# bonsai at 800 px, 1800 s: the scene's density (default) against --voxel-rule extent, each fit alone
set -e
cd /work/main
D=../shared/data/mipnerf360/bonsai
W=/work/runs/density1800
R=0.1,0.2,0.3,0.4,0.5,0.6,0.7,0.8,0.9,1.0
for name in spacing extent; do
  extra=""; [ $name = extent ] && extra="--voxel-rule extent"
  date -u +"$name fit start %FT%TZ"
  [ -f $W/$name.ply ] || /usr/bin/time -v proxycodec fit $D -o $W/$name.ply --time-budget 1800 --max-width 800 --seed 0 $extra > $W/$name.fit.log 2>&1
  date -u +"$name encode start %FT%TZ"
  [ -f $W/$name.pxc ] || /usr/bin/time -v proxycodec encode $W/$name.ply -o $W/$name.pxc > $W/$name.encode.log 2>&1
  date -u +"$name eval start %FT%TZ"
  [ -f $W/${name}_eval/eval.json ] || proxycodec eval $W/$name.ply $D --max-width 800 --views 4 --res $R -o $W/${name}_eval > $W/$name.eval.log 2>&1
  [ -f $W/${name}_pxc_eval/eval.json ] || proxycodec eval $W/$name.pxc $D --max-width 800 --views 4 --res $R -o $W/${name}_pxc_eval > $W/$name.pxc_eval.log 2>&1
done
date -u +"done %FT%TZ"
