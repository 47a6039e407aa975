#!/usr/bin/env bash
# Bonsai (Mip-NeRF 360, rebuilt poses) at its 800 px reference: our fit against plain 3DGS, a Scaffold-GS-style fit and
# our fit trained at 100% only (single-scale train, multi-scale test), and our fit at the former default anchor
# density (--voxel-rule extent: a quarter of the anchors), each for the same wall-time budget on the same
# machine, then evaluated on the 37 held-out views at 10%..100%, with the container and the 3DGS PLY's SPZ.
#   benchmarks/bonsai_equal_time.sh [BUDGET_SECONDS] [OUT_DIR] [STEPS]
# STEPS: a comma-separated subset of ours,3dgs,scaffold,fixedres,encode,extent,compare,supersample [default: all
# but extent and supersample, in that order; extent fits, evaluates, encodes and evaluates its container;
# supersample prices --supersample 2 (every size) and 3 (up to 50%) for ours and 3DGS on every third held-out
# view: benchmarks/supersample.py].
# Re-runnable: a finished step (its output present) is skipped; an interrupted fit (ours or 3DGS) continues with
# --resume (Ctrl-C writes its checkpoint; a SIGSTOPped step counts its pause, so resume with the budget plus the
# pause). One training at a time (never two at once). SEED (default 0) is every fit's --seed.
set -euo pipefail
BUDGET=${1:-7200}
OUT=${2:-/tmp/proxycodec_bonsai_equal_time}
STEPS=${3:-ours,3dgs,scaffold,fixedres,encode,compare}
HERE=$(cd "$(dirname "$0")" && pwd)
DATA=${DATA:-$(cd "$HERE/../.." && pwd)/shared/data/mipnerf360/bonsai}
RES=0.1,0.2,0.3,0.4,0.5,0.6,0.7,0.8,0.9,1.0
PC="proxycodec --threads ${THREADS:-2}"
[ -d "$DATA" ] || { echo "error: $DATA: no bonsai dataset (../shared/data/mipnerf360/bonsai)" >&2; exit 2; }
mkdir -p "$OUT"
want() { [[ ",$STEPS," == *",$1,"* ]]; }

fit() {  # name, extra fit options...
  local name=$1; shift
  if [ ! -f "$OUT/$name.ply" ]; then
    local resume=()
    [ -f "$OUT/$name.ckpt.pxc" ] && resume=(--resume)
    $PC fit "$DATA" --max-width 800 --time-budget "$BUDGET" --seed "${SEED:-0}" -o "$OUT/$name.ply" --keep-checkpoint \
      "${resume[@]}" "$@" \
      >> "$OUT/$name.fit.log" 2>&1
  fi
  evaluate "$name" "$OUT/$name.ply" $([[ " $* " == *" --explicit "* ]] && echo --max-width 800)
}
evaluate() {  # name, scene, extra eval options...
  local name=$1 scene=$2; shift 2
  [ -f "$OUT/${name}_eval/eval.json" ] || \
    $PC eval "$scene" "$DATA" --res $RES -o "$OUT/${name}_eval" "$@" > "$OUT/$name.eval.log" 2>&1
  python - "$OUT/${name}_eval/eval.json" "$name" <<'PY'
import json, sys
s = json.load(open(sys.argv[1]))["summary"]
print(f"{sys.argv[2]:10s} mean PSNR {s['psnr_avg']:.2f}  10%: {s['psnr_10']:.2f}  100%: {s['psnr_100']:.2f}")
PY
}

want ours && fit ours
if want 3dgs; then
  fit 3dgs --explicit
  [ -f "$OUT/3dgs.spz" ] || python -c "
import sys
from proxycodec.formats.inria_ply import read_inria_ply
from proxycodec.formats.spz import write_spz
print('3dgs.spz', write_spz(sys.argv[2], read_inria_ply(sys.argv[1])), 'B')" "$OUT/3dgs.ply" "$OUT/3dgs.spz"
fi
want scaffold && fit scaffold --no-proxies --no-gate --embedding none --fixed-res --voxel-rule spacing \
  --color-init-steps 0 --init-gaussian-scale 1
want fixedres && fit fixedres --fixed-res
if want encode; then
  [ -f "$OUT/ours.pxc" ] || $PC encode "$OUT/ours.ply" -o "$OUT/ours.pxc" ${ENCODE_ARGS:-} > "$OUT/encode.log" 2>&1
  evaluate ours_pxc "$OUT/ours.pxc"
fi
if want extent; then
  fit extent --voxel-rule extent
  [ -f "$OUT/extent.pxc" ] || $PC encode "$OUT/extent.ply" -o "$OUT/extent.pxc" ${ENCODE_ARGS:-} \
    > "$OUT/extent.encode.log" 2>&1
  evaluate extent_pxc "$OUT/extent.pxc"
fi
if want compare; then
  args=()
  for n in ours ours_pxc extent extent_pxc 3dgs scaffold fixedres; do
    [ -f "$OUT/${n}_eval/eval.json" ] && args+=("$n=$OUT/${n}_eval/eval.json")
  done
  sizes=()
  [ -f "$OUT/ours.pxc" ] && sizes+=(--bytes "ours_pxc=$(stat -L -c %s "$OUT/ours.pxc")")
  [ -f "$OUT/extent.pxc" ] && sizes+=(--bytes "extent_pxc=$(stat -L -c %s "$OUT/extent.pxc")")
  [ -f "$OUT/3dgs.spz" ] && sizes+=(--bytes "3dgs=$(stat -L -c %s "$OUT/3dgs.spz")")
  base=()
  [ -f "$OUT/3dgs_eval/eval.json" ] && base=(--baseline 3dgs)
  python "$HERE/compare_evals.py" "${args[@]}" "${base[@]}" "${sizes[@]}" --paper mipnerf360 --out "$OUT/compare"
fi
if want supersample; then
  PROXYCODEC_THREADS=${THREADS:-2} python "$HERE/supersample.py" ours="$OUT/ours.ply" 3dgs="$OUT/3dgs.ply" \
    --dataset "$DATA" --max-width 800 --res $RES --factors 1,2,3:0.5 --views-every 3 --out "$OUT/supersample" \
    > "$OUT/supersample.log" 2>&1
  tail -n 8 "$OUT/supersample.log"
fi
