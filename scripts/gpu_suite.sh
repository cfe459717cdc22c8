#!/usr/bin/env bash
# The GPU runs behind docs/RESULTS.md, in phases (device machines are lent per call; runs/ persists while warm):
#
#   bash scripts/gpu_suite.sh demos train export eval eval1   # the embedded model's recipe
#   STOP_AT=5000 bash scripts/gpu_suite.sh demos train        # or split: stop early, then `resume export eval`
#   BG=1 bash scripts/gpu_suite.sh demos train export eval    # detached (setsid): outlives a 10-minute call while
#                                                             # the machine stays warm; log in $W/suite.log
#   EPISODES=100 bash scripts/gpu_suite.sh latency demos distill distill2l grid-extra   # RESULTS.md's other tables
#                                                             # (teacher: $TEACHER, default the embedded model)
#   EPISODES=100 BG=1 bash scripts/gpu_suite.sh demos h20 rtc20    # issue 15: $TEACHER fine-tuned to 20 actions per
#                                                             # chunk ($FSTEPS steps), then the latency cells on it
#   EPISODES=100 BG=1 bash scripts/gpu_suite.sh demos cond rtc-cond   # issue 15: $TEACHER fine-tuned with committed
#                                                             # actions given (--max-delay $MAXD), then its cells
#   GAIN=0.5 EPISODES=100 BG=1 bash scripts/gpu_suite.sh demos slow rtc-slow cond rtc-cond expert-latency
#                                                             # the same on demos of a slower expert, which
#                                                             # tolerates latency (scripts/expert_latency.py)
#   GAIN=0.5 BG=1 bash scripts/gpu_suite.sh demos train rtc-run   # a model trained from scratch on the slower
#                                                             # expert's demos (the embedded recipe), its cells
#
# Needs the mujoco / mujoco-mjx wheels in .simwhl, or .simwhl/sim.zip of their installed files (see docs/BENCHMARKS.md;
# the zip fits the 64 MiB carry without mujoco's experimental/ and mjx's test data); writes into $OUT (or ./out).
set -uo pipefail
OUT=${OUT:-out}
W=${WORK:-runs/gpu}
EPISODES=${EPISODES:-400}   # demos per task, initial states 50.. (the evaluation uses 0..49)
NOISE=${NOISE:-0.2}         # DART: largest per-episode action-noise scale of the demos (pi0_jax/sim/demos.py)
STEPS=${STEPS:-22000}
STOP_AT=${STOP_AT:-$STEPS}
CONFIG=${CONFIG:-pi0_small_suite}
TEACHER=${TEACHER:-pi0_jax/assets/pi0_small}
DSTEPS=${DSTEPS:-3000}      # distillation steps
FSTEPS=${FSTEPS:-4000}      # fine-tune steps of h20 and cond
MAXD=${MAXD:-4}             # cond: the largest number of committed actions trained on
mkdir -p "$OUT" "$W"
if [ -n "${BG:-}" ]; then
  BG= setsid nohup bash "$0" "$@" > "$W/suite.log" 2>&1 < /dev/null &
  echo "detached: $W/suite.log"; exit 0
fi
python3 -c "import mujoco.mjx" 2>/dev/null || [ -d /tmp/site/mujoco ] || {   # the wheels, or their files unzipped
  ls .simwhl/*.whl >/dev/null 2>&1 && python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site \
      .simwhl/*.whl || python3 -m zipfile -e .simwhl/sim.zip /tmp/site; }
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
PI0="python3 -m pi0_jax.cli"
evaluate() {   # NAME POLICY, then extra eval flags; 550 episodes on held-out initial states 0..49
  local name=$1 policy=$2; shift 2
  $PI0 eval --policy "$policy" --episodes-per-task 50 --batch 550 --videos 0 --no-progress \
      --output-dir "$W/$name" "$@" 2>&1 | grep -E "\*\*|episodes in" &&
    cp "$W/$name/eval_info.json" "$OUT/$name.json"
}
finetune() {   # NAME, then extra train flags: $TEACHER fine-tuned on $W/demos for $FSTEPS steps into $W/NAME
  local name=$1; shift
  $PI0 train --config "$CONFIG" --init "$TEACHER" --demos "$W/demos" --out "$W/$name" --steps "$FSTEPS" --lr 1e-4 \
      --warmup 100 "$@" 2>&1 | grep -E "data:|first step|exported|step [0-9]*000/" &&
    cp "$W/$name/train_log.json" "$OUT/${name}_log.json"
}
latency_cells() {   # MODEL (a fine-tune in $W) RESULT CELLS: roadmap cells on it, without the cost column
  python3 scripts/roadmap_grid.py --checkpoint "$W/$1/checkpoint" --out "$W/$2" --no-timing \
      --budget-s "${BUDGET:-500}" --cells "$3" 2>&1 | grep -E "^\||Error"   # a failed cell says why
  cp "$W/$2/roadmap.json" "$OUT/$2.json"
}
for phase in "$@"; do
  echo "=== $phase $(date -u +%T)"
  case $phase in
    demos) python3 scripts/sim_demos.py "$W/demos" --suite all --episodes-per-task "$EPISODES" --first-init 50 \
               --resolution 112 --no-compress --batch 550 --action-noise "$NOISE" ${GAIN:+--gain "$GAIN"} 2>&1 |
               tail -3 ;;
    train) $PI0 train --config "$CONFIG" --demos "$W/demos" --out "$W/run" --steps "$STEPS" \
               --stop-at "$STOP_AT" 2>&1 | grep -v "^ *$" ;;
    resume) $PI0 train --config "$CONFIG" --demos "$W/demos" --out "$W/run" --steps "$STEPS" --resume 2>&1 ;;
    eval) evaluate eval "$W/run/checkpoint" ;;              # 10 flow steps, bf16, 5 of 10 actions per call
    eval1) evaluate eval1 "$W/run/checkpoint" --num-steps 1 ;;
    eval-replan2) evaluate eval_replan2 "$W/run/checkpoint" --replan-steps 2 ;;
    latency)   # B = 1 and 64, the suite's 2 cameras and 16 prompt tokens, for the small and the full-size π0
      $PI0 benchmark --preset pi0_small --checkpoint "$TEACHER" --cameras 2 --prompt-tokens 16 --steps 1,2,3,5,10 \
          --batch 1,64 --iters 50 --out "$OUT/latency_pi0_small.json" 2>&1 | grep "^|"
      $PI0 benchmark --preset pi0_base --cameras 2 --prompt-tokens 16 --steps 1,2,3,5,10 --batch 1 --iters 20 \
          --out "$OUT/latency_pi0_base.json" 2>&1 | grep "^|" ;;
    distill)   # 10-step teacher -> 1-step student, same depth
      $PI0 distill --config pi0_small_distill --teacher "$TEACHER" --demos "$W/demos" --out "$W/distill1" \
          --student-steps 1 --steps "$DSTEPS" 2>&1 | grep -E "data:|first step|exported|step [0-9]*000/" &&
        cp "$W/distill1/train_log.json" "$OUT/distill1_log.json" &&
        evaluate distill1 "$W/distill1/checkpoint" --replan-steps 2 ;;
    distill2l)   # 10-step teacher -> 1-step student with 2 of the 4 layers (the 18 -> 12 layer idea, small)
      $PI0 distill --config pi0_small_distill --teacher "$TEACHER" --demos "$W/demos" --out "$W/distill2l" \
          --student-steps 1 --layers 2 --steps "$DSTEPS" 2>&1 | grep -E "data:|first step|exported|step [0-9]*000/" &&
        cp "$W/distill2l/train_log.json" "$OUT/distill2l_log.json" &&
        evaluate distill2l "$W/distill2l/checkpoint" --replan-steps 2 &&
        $PI0 benchmark --preset pi0_small --checkpoint "$W/distill2l/checkpoint" --cameras 2 --prompt-tokens 16 \
            --steps 1 --batch 1,64 --iters 50 --out "$OUT/latency_distill2l.json" 2>&1 | grep "^|" ;;
    h20) finetune h20 --horizon 20 ;;   # a 20-action horizon: D = 4 then leaves RTC 11 guided actions, not 1
    rtc20)   # sync / naive / rtc at D = 1, 2, 4 on the 20-action model (the cost column is the 10-action one's)
      latency_cells h20 roadmap20 "${CELLS:-sync,rtc,naive,rtc-d1,naive-d1,rtc-d2,naive-d2}" ;;
    cond) finetune cond --max-delay "$MAXD" ;;   # training-time action conditioning: d ~ U{0..$MAXD} given
    slow) finetune slow ;;   # on $W/demos as they are (GAIN=0.5: a slower expert's), no conditioning
    rtc-slow) latency_cells slow roadmap_slow "${SLOW_CELLS:-sync,rtc,naive,rtc-d2}" ;;
    rtc-run)   # the cells on the model `train` made from scratch ($W/run; GAIN=0.5: on the slower expert's demos)
      latency_cells run roadmap_run "${RUN_CELLS:-sync,rtc,naive}" && cp "$W/run/train_log.json" "$OUT/run_log.json" ;;
    expert-latency)   # the scripted expert with its actions D steps late, at several gains (no learning involved)
      python3 scripts/expert_latency.py --out "$W/expert_latency" --delays 0,2,4,8 --gains 1.5,1.0,0.5 2>&1 |
        grep -E "^gain|^\|" && cp "$W/expert_latency/expert_latency.json" "$OUT/" ;;
    rtc-cond)   # the conditioned model: its own baseline, then conditioned / naive / rtc at D = 4, 2, 1
      latency_cells cond roadmap_cond "${CELLS:-cond,sync,cond-d2,cond-d1,naive,rtc}" ;;
    grid-extra)   # the cells the first grid left out (replan 2 as the grid)
      python3 scripts/results_grid.py --checkpoint "$TEACHER" --out "$W/grid_extra" --replan-steps 2 \
          --schemes prefix-all:10,vision:10,expert-weights:10,all:1,nvfp4:1,mxfp4:1 2>&1 | grep -E "steps|^\|" &&
        cp "$W/grid_extra/results.json" "$OUT/grid_extra.json" ;;
    export) cp "$W/run/train_log.json" "$W/run/loss.png" "$OUT/" 2>/dev/null
            tar czf "$W/ckpt.tgz" -C "$W/run" checkpoint && split -b 15M "$W/ckpt.tgz" "$OUT/ckpt.tgz." && ls -la "$OUT" ;;
    *) echo "unknown phase $phase"; exit 2 ;;
  esac
done
echo "=== done $(date -u +%T)"
