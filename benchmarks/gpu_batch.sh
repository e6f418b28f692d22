#!/usr/bin/env bash
# The GPU measurements recorded in benchmarks/RESULTS.md, in one batch (device machine, after
# ../shared/tools/device-warp.sh has installed warp-lang under /tmp/site and the pure-Python wheels
# in .whl/ were installed to /tmp/site too). Usage: bash benchmarks/gpu_batch.sh OUT_DIR [parts]
set -uo pipefail
OUT_DIR=${1:?output directory}
PARTS=${2:-"gputests mpm env ppo"}
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
mkdir -p "$OUT_DIR"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv | tee "$OUT_DIR/gpu.txt"
for part in $PARTS; do
  case $part in
    gputests) python3 -m pytest -q -p no:cacheprovider tests/sim/test_gpu.py 2>&1 | tail -3 | tee "$OUT_DIR/gputests.txt" ;;
    mpm) python3 benchmarks/bench_mpm.py --device cuda:0 --sizes 1e3,1e4,1e5,1e6,2e6 \
           --batches 1024x2000,4096x2000 --grad-max 3e6 2>&1 | tee "$OUT_DIR/bench_mpm.txt" ;;
    env) timeout 240 python3 benchmarks/bench_env.py --device cuda:0 --sizes 1,16,256,1024,4096 2>&1 \
           | tee "$OUT_DIR/bench_env.txt" ;;
    ppo) timeout 300 python3 examples/train_ppo.py --device cuda:0 --num-envs 1024 --n-steps 32 \
           --batch-size 4096 --total-steps 1000000 --out "$OUT_DIR/ppo" 2>&1 | tail -25 | tee "$OUT_DIR/ppo.txt" ;;
    identify) timeout 300 python3 benchmarks/bench_identify.py --device cuda:0 2>&1 | tee "$OUT_DIR/bench_identify.txt" ;;
  esac
done
