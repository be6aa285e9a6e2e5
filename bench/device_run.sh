#!/bin/bash
# The GPU checks of one device session, as one prepared run (about 6 minutes on an H100):
#   1. bench/device_check.py: box bounds on the device vs the CPU vs sampled lam_max(D);
#   2. bench/prove_suite.py --device: whole proofs (2x10 n=4, 5x30 n=2, 2x10 n=6);
#   3. certify run --device on the shipped checkpoints (verdict, exit code, seconds): the grid,
#      falsifier and every branch-and-bound proof on the device, end to end.
# The device machine has no cvxpy: the instances' tuned rates and metrics come from a cache
# made here first (bench/prove_suite.py writes it; copy it into an ignored folder that the
# device call carries). Usage, on the device machine, from the repository root:
#   bash bench/device_run.sh CACHE.json [DEVICE] [OUTDIR]
set -u
CACHE=${1:?instance cache (json) made by bench/prove_suite.py}
DEVICE=${2:-cuda}
OUTDIR=${3:-${OUT:-/tmp/device-run}}
mkdir -p "$OUTDIR"
export PYTHONUNBUFFERED=1 OMP_NUM_THREADS=1 PYTHONPATH=${PYTHONPATH:-}:$(pwd)
PY=${PYTHON:-python3}
{ nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv 2>&1 || true
  $PY -c "import sys, torch; print(sys.version, torch.__version__, torch.cuda.is_available())"
} > "$OUTDIR/env.txt" 2>&1
timeout 90 $PY bench/device_check.py --device "$DEVICE" --n 2 4 6 --boxes 4096 \
    --radii 0.0625 0.0039 --cache "$CACHE" > "$OUTDIR/check.jsonl" 2>&1
S="bench/prove_suite.py --no-baseline --cache $CACHE --device $DEVICE"
{ timeout 150 $PY $S --family 2x10 --n 4 --seeds 0 1 --seconds 60
  timeout 60 $PY $S --family 5x30 --n 2 --margin 0.01 --seeds 0 --seconds 45
  timeout 200 $PY $S --family 2x10 --n 6 --seeds 0 --seconds 180 --max-boxes 100000000
} > "$OUTDIR/prove.jsonl" 2>&1
for ck in vdp_certified vdp; do
  start=$(date +%s%N)
  timeout 120 $PY -m certify run "examples/$ck.ckpt" --device "$DEVICE" --no-config \
      --json "$OUTDIR/$ck.json" > "$OUTDIR/run_$ck.txt" 2>&1
  code=$?
  ms=$(( ($(date +%s%N) - start) / 1000000 ))
  echo "{\"run\": \"$ck\", \"device\": \"$DEVICE\", \"exit\": $code, \"ms\": $ms}" \
      >> "$OUTDIR/runs.jsonl"
done
tail -n 4 "$OUTDIR"/*.jsonl
