#!/bin/bash
# bonsai, 600 s on 2 cores at the default --voxel-rule auto; encode; eval on the trade-off map's 4 views (37 too)
set -e
cd /work/runs/auto600
/usr/bin/time -v proxycodec fit /work/shared/data/mipnerf360/bonsai --max-width 800 --time-budget 600 --seed 0 -o auto.ply > fit.log 2>&1
proxycodec encode auto.ply -o auto.pxc > encode.log 2>&1
proxycodec eval auto.pxc /work/shared/data/mipnerf360/bonsai --max-width 800 --views 4 --res 0.1,0.2,0.3,0.4,0.5,0.6,0.7,0.8,0.9,1.0 -o eval4 > eval4.log 2>&1
echo done > status
