#!/usr/bin/env bash
# One device run: HLO kernel counts, the engine benchmark, the reference and LeRobot in the same process.
# Usage (device tool, repo root, with .whl carried): bash scripts/gpu_bench.sh PHASE...
set -uo pipefail
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
  >/dev/null 2>&1 || echo "wheel install failed"
export PYTHONPATH=/tmp/site:$PWD XLA_PYTHON_CLIENT_PREALLOCATE=false PYTHONUNBUFFERED=1
export HF_HUB_OFFLINE=1 TRANSFORMERS_OFFLINE=1
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"
nvidia-smi -L; date -u; git rev-parse --short HEAD 2>/dev/null
for phase in "$@"; do
  echo "=== $phase"; start=$(date +%s)
  case $phase in
    hlo_pi05) python3 scripts/profile_engine.py --preset pi05_base --steps 10 --out "$OUT/hlo_pi05.json" ;;
    pi05_b1) python3 -m pi0_jax.cli benchmark --preset pi05_base --steps 1,10 --batch 1 --reference --warm-start \
               --compare lerobot --iters 50 --out "$OUT/pi05_b1.json" ;;
    pi05_scan) python3 -m pi0_jax.cli benchmark --preset pi05_base --steps 10 --batch 1 --no-unroll --iters 30 \
               --out "$OUT/pi05_scan.json" ;;
    pi05_unroll_steps) python3 -m pi0_jax.cli benchmark --preset pi05_base --steps 10 --batch 1 --unroll-steps \
               --iters 30 --out "$OUT/pi05_unroll_steps.json" ;;
    pi0_table) python3 -m pi0_jax.cli benchmark --preset pi0_base --steps 1,2,3,5,10 --batch 1,8,64 \
               --fused-steps 1,10 --reference --compare lerobot --iters 50 --out "$OUT/pi0_table.json" ;;
    pi05_table) python3 -m pi0_jax.cli benchmark --preset pi05_base --steps 1,2,3,5,10 --batch 1,8,64 \
               --fused-steps 1,10 --reference --iters 50 --out "$OUT/pi05_table.json" ;;
    fp32) python3 -m pi0_jax.cli benchmark --preset pi0_base --dtype float32 --steps 1,10 --batch 1,8 \
               --fused-steps 1,10 --iters 30 --out "$OUT/pi0_fp32.json" ;;
  esac
  echo "=== $phase took $(( $(date +%s) - start )) s"
done
