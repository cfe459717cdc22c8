#!/usr/bin/env bash
# The demo model end to end on one GPU: expert demos -> pi0-jax train -> pi0-jax eval.
#
#   bash scripts/train_suite.sh [WORKDIR] [extra pi0-jax train flags, e.g. --steps 8000]
#
# 1. demos: 50 expert episodes per task on initial states 50..99 (the evaluation uses 0..49), both cameras at the
#    model's 112 px, uncompressed npz (~8 GB for 11 tasks; compressing it would take longer than rendering it);
# 2. train pi0_small from scratch (pi0_jax/train/config.py: pi0_small_suite), RUN/checkpoint at the end;
# 3. evaluate RUN/checkpoint on the suite, 50 episodes per task, bf16, 10 flow steps.
set -euo pipefail
WORK=${1:-runs/pi0_small_suite}
shift || true
DEMOS=$WORK/demos
RUN=$WORK/run
mkdir -p "$WORK"
if [ ! -f "$DEMOS/meta.json" ]; then
  python scripts/sim_demos.py "$DEMOS" --suite all --episodes-per-task 50 --first-init 50 --resolution 112 \
      --no-compress --batch 128
fi
pi0-jax train --config pi0_small_suite --demos "$DEMOS" --out "$RUN" "$@"
pi0-jax eval --policy "$RUN/checkpoint" --resolution 112 --episodes-per-task 50 --batch 128 \
    --output-dir "$RUN/eval"
