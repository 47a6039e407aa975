#!/usr/bin/env bash
# Issue #4 acceptance runs on NeRF-Synthetic lego at a 400 px reference width (2-core CPU).
#   benchmarks/fit_lego.sh [BUDGET_SECONDS] [OUT_DIR]
# Trains the resolution-aware model (FiLM + coverage gate + random resolution + proxies), the same without proxies,
# and the plain Scaffold-GS baseline, one after the other (never two long trainings at once), then evaluates each
# on the 25 test views at 2.5%..150%. Logs go to OUT_DIR/*.log; reports to OUT_DIR/<name>_eval/.
set -euo pipefail
BUDGET=${1:-1800}
OUT=${2:-/tmp/proxycodec_fit_lego}
DATA=${DATA:-$(cd "$(dirname "$0")/../.." && pwd)/shared/data/nerf_synthetic/lego}
mkdir -p "$OUT"
run() {  # name, extra fit options...
  local name=$1; shift
  proxycodec fit "$DATA" --max-width 400 ${BUDGET_ARGS:---time-budget $BUDGET} -o "$OUT/$name.ply" "$@" \
    > "$OUT/$name.fit.log" 2>&1
  proxycodec eval "$OUT/$name.ply" "$DATA" -o "$OUT/${name}_eval" > "$OUT/$name.eval.log" 2>&1
  python - "$OUT/${name}_eval/eval.json" "$name" <<'PY'
import json, sys
s = json.load(open(sys.argv[1]))["summary"]
print(f"{sys.argv[2]:12s} avg PSNR {s['psnr_avg']:.3f}  SSIM {s['ssim_avg']:.4f}  10%: {s['psnr_10']:.3f}  100%: {s['psnr_100']:.3f}")
PY
}
run full
# The proxies' cost is judged against the same run without them: same seed, same iteration count (stage 1 is then
# identical, bit for bit), so the no-proxy run takes the full run's iterations instead of the time budget.
ITERS=$(sed -n 's/.*anchors, \([0-9]*\) iterations.*/\1/p' "$OUT/full.fit.log" | tail -n 1)
run_iters() { local name=$1; shift; BUDGET_ARGS="--iters $ITERS" run "$name" "$@"; }
run_iters noproxy --no-proxies
run plain --fixed-res --no-gate --embedding none --no-proxies
