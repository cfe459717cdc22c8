#!/usr/bin/env bash
# The device runs behind BENCHMARKS' batched-evaluation section (issue 14): `pi0-jax eval` on one GPU and on every
# GPU of the machine, same flags, and what each run wrote into eval_info.json.
#
#   bash scripts/gpu_eval.sh pi05-1 pi05-2          # full-size π0.5 (random weights): 264 episodes on GPU 0, then
#                                                   # 528 on two GPUs (264 per device, the same task mix)
#   bash scripts/gpu_eval.sh pi05-auto              # pi05-1 with --batch auto (N from device memory and a probe)
#   bash scripts/gpu_eval.sh pi05-1001              # 1001 environments on GPU 0 for 120 steps (3 segments): the
#                                                   # steady segment at the batch --batch auto takes for 2000
#                                                   # (the policy in chunks of 256: whole, it needs 61 GiB)
#   bash scripts/gpu_eval.sh embedded-1 embedded-2  # the embedded model's 550 episodes on GPU 0, then on two GPUs
#   DET=1 bash scripts/gpu_eval.sh embedded-1       # the same with --xla_gpu_deterministic_ops=true
#   QUANT=prefix-mlp bash scripts/gpu_eval.sh pi05-fp8   # pi05-1 with FP8 weights and calibrated activation scales
#   QUANT=prefix-mlp bash scripts/gpu_eval.sh embedded-fp8   # embedded-1 likewise (task success under FP8)
#   bash scripts/gpu_eval.sh overlap                # scripts/overlap_probe.py: physics beside the policy on 2 streams
#   TREE=.old_tree TAG=_old bash scripts/gpu_eval.sh pi05-1   # the same with an older package (carried, made by
#                              # `git archive REV pi0_jax converters | tar -x -C .old_tree`, and ':!pi0_jax/assets'
#                              # to fit the carry beside .simwhl: --policy paths name this tree's; a preset:
#                              # policy needs pi0_jax/assets/pi0_small/tokenizer.model copied in); outputs *_old
#   EXTRA="--gemm cublas" TAG=_cublas bash scripts/gpu_eval.sh pi05-1   # pi05-1 with cuBLAS for every GEMM
#   POLICY=preset:dummy PER_TASK=1 EXTRA="--steps 10" bash scripts/gpu_eval.sh pi05-1   # CPU smoke run
#
# Needs the mujoco / mujoco-mjx wheels in .simwhl, or .simwhl/sim.zip of their installed files (carried); writes
# OUT/<phase>.json (the eval_info, per_episode kept) and prints each run's summary line.
set -uo pipefail
OUT=${OUT:-out}
W=${WORK:-runs/gpu_eval}
POLICY=${POLICY:-preset:pi05_libero}
PER_TASK=${PER_TASK:-24}        # π0.5 episodes per task and per device: 11 tasks x 24 = 264
mkdir -p "$OUT" "$W"
python3 -c "import mujoco.mjx" 2>/dev/null || [ -d /tmp/site/mujoco ] || {   # the wheels, or their files unzipped
  ls .simwhl/*.whl >/dev/null 2>&1 && python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site \
      .simwhl/*.whl || python3 -m zipfile -e .simwhl/sim.zip /tmp/site; }
export PYTHONPATH=/tmp/site:${TREE:-$PWD} PYTHONUNBUFFERED=1
[ -n "${DET:-}" ] && export XLA_FLAGS="--xla_gpu_deterministic_ops=true ${XLA_FLAGS:-}"
nvidia-smi -L; date -u
# -P: `python3 -m` would put the working directory first on sys.path, so TREE's package would never be imported
python3 -P -c "import pi0_jax; print('package:', pi0_jax.__file__)"
run() {   # NAME GPUS, then eval flags
  local name=$1${TAG:-} gpus=$2; shift 2
  local t0; t0=$(date +%s.%N)
  CUDA_VISIBLE_DEVICES=$gpus python3 -P -m pi0_jax.cli eval --videos 0 --no-progress --output-dir "$W/$name" "$@" ${EXTRA:-} > "$OUT/$name.log" 2>&1 ||
    { tail -30 "$OUT/$name.log"; return 1; }
  grep -E "\*\*|episodes in" "$OUT/$name.log"
  python3 - "$W/$name/eval_info.json" "$OUT/$name.json" "$t0" "$* ${EXTRA:-}" <<'EOF'
import json, sys, time
src, dst, t0, flags = sys.argv[1:]
info = json.load(open(src))
info["note"] = f"pi0-jax eval {flags}; process wall clock {time.time() - float(t0):.1f} s"
json.dump(info, open(dst, "w"), indent=1)
a, t = info["aggregated"], info["timing"]
print(f"{dst}: {a['n_episodes']} episodes, {a['pc_success']:.1f} %, eval {a['eval_s']:.1f} s, first segment "
      f"{t['first_segment_s']:.1f} s, device wait {t['device_wait_s']:.1f} s, "
      f"{t['episodes_per_min_after_compile']:.0f} ep/min after it; {info['note']}")
if "setup_s" in t:
    print(f"  setup {t['setup_s']:.1f} s: " + ", ".join(f"{k} {v:.1f}" for k, v in t["policy_setup_s"].items()))
if "phases" in t:
    print("  phases:", json.dumps(t["phases"]))
EOF
}
for phase in "$@"; do
  echo "=== $phase $(date -u +%T)"
  case $phase in
    pi05-1) run pi05_1gpu 0 --policy "$POLICY" --episodes-per-task "$PER_TASK" --batch $((11 * PER_TASK)) ;;
    pi05-auto) run pi05_auto_1gpu 0 --policy "$POLICY" --episodes-per-task "$PER_TASK" --batch auto ;;
    pi05-1001) run pi05_1001_1gpu 0 --policy "$POLICY" --episodes-per-task 91 --batch 1001 --steps 120 \
                   --plan-chunk 256 ;;
    pi05-2) run pi05_2gpu 0,1 --policy "$POLICY" --episodes-per-task $((2 * PER_TASK)) --batch $((22 * PER_TASK)) ;;
    pi05-fp8) run "pi05_${QUANT:-prefix-mlp}_1gpu" 0 --policy "$POLICY" --episodes-per-task "$PER_TASK" \
                  --batch $((11 * PER_TASK)) --quant "${QUANT:-prefix-mlp}" ;;
    overlap) python3 scripts/overlap_probe.py --json "$OUT/overlap.json" ;;
    embedded-1) run embedded_1gpu${DET:+_det} 0 --policy pi0_jax/assets/pi0_small --episodes-per-task 50 --batch auto ;;
    embedded-fp8) run "embedded_${QUANT:-prefix-mlp}_1gpu" 0 --policy pi0_jax/assets/pi0_small --episodes-per-task 50 \
                  --batch auto --quant "${QUANT:-prefix-mlp}" ;;
    embedded-2) run embedded_2gpu${DET:+_det} 0,1 --policy pi0_jax/assets/pi0_small --episodes-per-task 50 --batch auto ;;
    *) echo "unknown phase $phase"; exit 2 ;;
  esac
done
echo "=== done $(date -u +%T)"
