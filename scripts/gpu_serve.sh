#!/usr/bin/env bash
# Issue 12's GPU numbers in one device call: Policy.infer from host numpy against the engine alone, then the policy
# server (one client's round trip; 8 clients one at a time vs through dynamic batching), π0 full size (random
# weights), 3 cameras, B=1, 10 steps, bf16. Needs a websockets wheel in .whl/ (README of the device tool).
#   OUT=out bash scripts/gpu_serve.sh
set -euo pipefail
OUT=${OUT:-out}
mkdir -p "$OUT"
if ! python3 -c "import websockets" 2>/dev/null; then
  python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .whl/websockets-*.whl
  export PYTHONPATH=/tmp/site${PYTHONPATH:+:$PYTHONPATH}
fi
export PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH} PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,driver_version,clocks.sm,clocks.mem --format=csv | tee "$OUT/gpu.txt"
python3 scripts/policy_bench.py --preset "${PRESET:-pi0_base}" --dtype bfloat16 --steps 10 --cameras 3 --batch 8 \
  --iters 50 --out "$OUT/policy_bench.json" 2>&1 | tee "$OUT/policy_bench.log"
python3 scripts/serve_bench.py --preset "${PRESET:-pi0_base}" --dtype bfloat16 --num-steps 10 --all-cameras \
  --clients 8 --requests "${REQUESTS:-40}" --out "$OUT/serve_bench.json" 2>&1 | tee "$OUT/serve_bench.log"
