#!/bin/bash
# bonsai's 600-s 3DGS PLY converted with a 16,000-s training budget (BUDGET overrides it; 13,000 from the
# 2026-11-29 13:27 UTC resume on), resumable: the checkpoint,
# converted_anchors.ckpt.pxc, is written every 300 s of training. To pause: `kill -TERM` the python process right
# after the checkpoint's mtime changes (a background job ignores SIGINT, so no checkpoint is written on SIGINT here);
# at most 300 s of training are lost otherwise. Done when converted_anchors.ply exists and the checkpoint is gone.
cd /work/runs/long
R=""
BUDGET=${BUDGET:-13000}
[ -f converted_anchors.ckpt.pxc ] && R="--resume"
echo "=== $(date -u +%FT%TZ) start $R budget $BUDGET (commit $(git -C /work/main rev-parse --short HEAD))" >> convert.log
/usr/bin/time -v proxycodec convert point_cloud.ply -o converted_anchors.ply --time-budget ${BUDGET:-16000} --max-width 800 \
    --background black $R >> convert.log 2>&1
if [ -f converted_anchors.ply ] && [ ! -f converted_anchors.ckpt.pxc ]; then s=finished; else s=paused; fi
echo "=== $(date -u +%FT%TZ) $s" >> convert.log
