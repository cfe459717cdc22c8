#!/usr/bin/env bash
# The GPU runs behind docs/RESULTS.md, in phases (device machines are lent per call; runs/ persists while warm):
#
#   bash scripts/gpu_suite.sh demos train export eval   # the embedded model's recipe in one call (~9 min, H100)
#   STOP_AT=5000 bash scripts/gpu_suite.sh demos train  # or split: stop early, then `resume export eval`
#
# Needs the mujoco / mujoco-mjx wheels in .simwhl (see docs/BENCHMARKS.md); writes into $OUT (or ./out).
set -uo pipefail
OUT=${OUT:-out}
W=${WORK:-runs/gpu}
EPISODES=${EPISODES:-100}   # demos per task, initial states 50.. (the evaluation uses 0..49)
STEPS=${STEPS:-10000}
STOP_AT=${STOP_AT:-$STEPS}
mkdir -p "$OUT" "$W"
python3 -c "import mujoco.mjx" 2>/dev/null ||
  python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .simwhl/*.whl
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
PI0="python3 -m pi0_jax.cli"
for phase in "$@"; do
  echo "=== $phase $(date -u +%T)"
  case $phase in
    demos) python3 scripts/sim_demos.py "$W/demos" --suite all --episodes-per-task "$EPISODES" --first-init 50 \
               --resolution 112 --no-compress --batch 256 2>&1 | tail -3 ;;
    train) $PI0 train --config pi0_small_suite --demos "$W/demos" --out "$W/run" --steps "$STEPS" \
               --stop-at "$STOP_AT" 2>&1 | grep -v "^ *$" ;;
    resume) $PI0 train --config pi0_small_suite --demos "$W/demos" --out "$W/run" --steps "$STEPS" --resume 2>&1 ;;
    eval) $PI0 eval --policy "$W/run/checkpoint" --episodes-per-task 50 --batch 550 --videos 0 --no-progress \
              --output-dir "$W/eval" && cp "$W/eval/eval_info.json" "$OUT/" ;;
    export) cp "$W/run/train_log.json" "$W/run/loss.png" "$OUT/" 2>/dev/null
            tar czf "$W/ckpt.tgz" -C "$W/run" checkpoint && split -b 15M "$W/ckpt.tgz" "$OUT/ckpt.tgz." && ls -la "$OUT" ;;
    *) echo "unknown phase $phase"; exit 2 ;;
  esac
done
