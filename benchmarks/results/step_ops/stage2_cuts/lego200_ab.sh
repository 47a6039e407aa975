#!/bin/bash
# The same lego fit (200 px, 1500 iterations, seed 0; stage 2 with the rate term from iteration 750), encode and eval
# at two commits, one after the other on one machine. BASE: a folder holding the earlier commit as a package
# (`git archive ea3fcee proxycodec formats cli | tar -x -C BASE`, then formats/ and cli/ moved into BASE/proxycodec/),
# put first on PYTHONPATH; the other run uses the installed proxycodec. Usage: lego200_ab.sh WORK_DIR BASE
set -e
LEGO=$(cd "$(dirname "$0")/../../../../../shared/data/nerf_synthetic/lego" && pwd)
WORK=${1:?work dir}; BASE=${2:?base package folder}
mkdir -p "$WORK" && cd "$WORK"
for v in base new; do
  if [ $v = base ]; then export PYTHONPATH=$BASE; else unset PYTHONPATH; fi
  mkdir -p $v && cd $v
  /usr/bin/time -v python -m proxycodec.cli fit "$LEGO" -o lego.ply --max-width 200 --iters 1500 --seed 0 > fit.log 2> fit.err
  python -m proxycodec.cli encode lego.ply -o lego.pxc > enc.log 2>&1
  python -m proxycodec.cli eval lego.pxc "$LEGO" --max-width 200 --res 0.1,0.2,0.3,0.4,0.5,0.6,0.7,0.8,0.9,1.0 \
    --json > eval.json 2> eval.err
  cd ..
done
