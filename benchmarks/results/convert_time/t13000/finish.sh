#!/bin/bash
# After run.sh has finished: encode with the defaults and score against the source's renders on the 4 held-out views
# that benchmarks/convert_time.py uses, and against the photos; then the q6 / 4000-entropy-iteration encode.
set -e
cd /work/runs/long
W=/work/runs/long/
/usr/bin/time -v proxycodec encode converted_anchors.ply -o converted.pxc > encode.log 2>&1
proxycodec stats converted.pxc > stats.txt
python - <<'PY' > vs_source.json
import json
from proxycodec.bench.steps import run_worker
W = "/work/runs/long/"
r = run_worker("vs_source", {"model": W + "converted.pxc", "source": W + "point_cloud.ply",
                             "cameras": W + "cameras.json", "background": [0, 0, 0], "views": 4})
print(json.dumps(r, indent=1))
PY
python -c "import json; r=json.load(open('vs_source.json')); print('vs source', r['psnr_avg'], [round(p['psnr'],2) for p in r['per_resolution']])"
ls -l converted.pxc
python - <<'PY' > vs_photos.json
import json
from proxycodec.bench.steps import run_worker
W = "/work/runs/long/"
r = run_worker("eval", {"model": W + "converted.pxc", "dataset": "/work/shared/data/mipnerf360/bonsai", "max_width": 800,
                        "views": 4, "test_every": 8, "resolutions": [0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0]})
print(json.dumps(r, indent=1, default=str))
PY
echo "vs photos done"
/usr/bin/time -v proxycodec encode converted_anchors.ply -o converted_q6e4000.pxc --weights-dtype q6 --entropy-iters 4000 \
    > encode_q6e4000.log 2>&1
python - <<'PY' > vs_source_q6e4000.json
import json
from proxycodec.bench.steps import run_worker
W = "/work/runs/long/"
r = run_worker("vs_source", {"model": W + "converted_q6e4000.pxc", "source": W + "point_cloud.ply",
                             "cameras": W + "cameras.json", "background": [0, 0, 0], "views": 4})
print(json.dumps(r, indent=1))
PY
python -c "import json; r=json.load(open('vs_source_q6e4000.json')); print('q6e4000 vs source', r['psnr_avg'])"
ls -l converted_q6e4000.pxc
echo "finish done"
