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
    kernels_graph) python3 scripts/bench_kernels.py --graph-probe --presets pi0_base --iters 30 \
               --out "$OUT/graph_probe.json" ;;   # the Pallas step: command buffers default / off / all, PDL off / on
    kernels_ncu) ncu --clock-control none --kernel-name regex:expert_ --launch-skip 12 --launch-count 12 \
               --section SpeedOfLight --section LaunchStats --section Occupancy \
               python3 scripts/bench_kernels.py --gemm-probe --presets pi0_base > "$OUT/ncu_gemms.txt" 2>&1
               grep -E "^  expert_|Duration|DRAM Throughput|Registers Per|Waves Per SM" "$OUT/ncu_gemms.txt" ;;
    kernels_sweep) python3 scripts/bench_kernels.py --step-sweep "${SWEEP:-splits}" --trace --skip-parity \
               --presets pi0_base --iters 30 --out "$OUT/step_sweep.json" ;;   # launch variants inside the step
    stages_b1) python3 scripts/profile_engine.py --preset pi0_base --batch 1 --prompt-tokens 48 --attention xla \
               --attention vision=cudnn --attention vision=cudnn,prefix=cudnn --attention cudnn --time --iters 30 \
               --trace-stages --out "$OUT/stages_b1.json" ;;
    gaps_b1) python3 scripts/profile_engine.py --preset pi0_base --batch 1 --prompt-tokens 48 --steps 10 --time \
               --iters 20 --trace-stages --out "$OUT/gaps_b1.json" ;;   # each stage's device span and idle gaps
    edges_b1) python3 scripts/profile_engine.py --preset pi0_base --batch 1 --prompt-tokens 20 --steps 10 \
               --trace-stages --host-events --stages call,encode_images,denoise --out "$OUT/edges_b1.json" \
               | grep -E "kernels,|host to first|lead |==" ;;   # the call's lead, tail and gaps; the host's lead
    chain_b1) for m in pi0 pi05; do   # fused program against the stage programs chained (own weights, cuBLAS vision)
               python3 scripts/chain_probe.py --preset ${m}_base --iters 40 --out "$OUT/chain_${m}_b1.json"; done ;;
    call_pi0|call_pi05) m=${phase#call_}; python3 -m pi0_jax.cli benchmark --preset ${m}_base --steps 1,10 \
               --batch ${BATCH:-1,8} --fused-steps 1,10 --one-program --reference --iters 30 --prompt-tokens 48 \
               --out "$OUT/call_${m}.json" > "$OUT/call_${m}.log" 2>&1; grep -E "^\||reference" "$OUT/call_${m}.log"
               python3 - "$OUT/call_${m}.json" <<'PY'   # the call against the one fused program, same process
import json, sys
for r in json.load(open(sys.argv[1]))["rows"]:
    if "one_program" in r:
        print(f"B={r['batch']} S={r['steps']}: call {r['total']['median_ms']:.2f} ms, one program "
              f"{r['one_program']['median_ms']:.2f} ms")
PY
               ;;
    stages_b8) python3 scripts/profile_engine.py --preset pi0_base --batch 8 --prompt-tokens 48 --attention xla \
               --attention vision=cudnn,prefix=cudnn --time --iters 20 --out "$OUT/stages_b8.json" ;;
    hlo_pi05) python3 scripts/profile_engine.py --preset pi05_base --steps 10 --out "$OUT/hlo_pi05.json" ;;
    profile_pi05_b64) python3 scripts/profile_engine.py --preset pi05_base --batch 64 --prompt-tokens 20 --steps 10 \
               --time --iters 10 --trace-stages --out "$OUT/profile_pi05_b64.json" ;;
    ab_pi05|ab_pi0) for b in ${AB_BATCHES:-64 8}; do   # this tree against .old_tree, carried:
                 for tree in "$PWD" "$PWD/.old_tree"; do   # `git archive REV pi0_jax | tar -x -C .old_tree`
                 echo "== B=$b $tree"
                 PYTHONPATH=/tmp/site:$tree python3 scripts/profile_engine.py --preset ${phase#ab_}_base --batch $b \
                   --steps 10 --time --iters 10 --out "$OUT/${phase}_$(basename "$tree")_b$b.json" | grep "median"
                 done; done ;;
    pi0_denoise_attn) for b in ${ATTN_BATCHES:-3 4 8 16}; do   # π0's denoise attention by batch, one process each
                 python3 scripts/profile_engine.py --preset pi0_base --batch $b --prompt-tokens 48 --steps 10 --time \
                   --iters 10 --attention vision=pallas,prefix=cudnn,denoise=pallas \
                   --attention vision=pallas,prefix=cudnn,denoise=cudnn \
                   --attention vision=pallas,prefix=cudnn,denoise=xla \
                   --out "$OUT/pi0_denoise_attn_b$b.json" | grep -E "median|relative"; done ;;
    geglu_probe) python3 scripts/geglu_probe.py --rows 8192,51200,143616 --iters 15 --out "$OUT/geglu_probe.json" ;;
    pi0_b3_attn) python3 scripts/profile_engine.py --preset pi0_base --batch 3 --prompt-tokens 48 --time --iters 20 \
               --attention vision=cudnn,prefix=cudnn,denoise=xla --attention vision=cudnn,prefix=cudnn,denoise=cudnn \
               --out "$OUT/pi0_b3_attn.json" | grep -E "^==|median|relative" ;;
    pi0_b1b8) python3 -m pi0_jax.cli benchmark --preset pi0_base --steps 1,10 --batch 1,8 --fused-steps 1,10 --reference \
               --iters 30 --out "$OUT/pi0_b1b8.json" > "$OUT/pi0_b1b8.log" 2>&1; tail -30 "$OUT/pi0_b1b8.log" ;;
    pi0_b8_attn) for a in auto cudnn; do
                 python3 -m pi0_jax.cli benchmark --preset pi0_base --steps 10 --batch 8 --fused-steps 10 --iters 20 \
                   --attention $a --out "$OUT/pi0_b8_$a.json" > "$OUT/pi0_b8_$a.log" 2>&1; tail -3 "$OUT/pi0_b8_$a.log"; done ;;
    pi05_denoise_attn) for a in xla cudnn; do   # π0.5's denoise attention below CUDNN_DENOISE_MIN_BATCH
                 python3 -m pi0_jax.cli benchmark --preset pi05_base --steps 10 --batch 2,4,6,8 --iters 20 \
                   --attention denoise=$a --out "$OUT/pi05_denoise_$a.json" > "$OUT/pi05_denoise_$a.log" 2>&1
                 tail -6 "$OUT/pi05_denoise_$a.log"; done ;;
    pi0_fp8) python3 -m pi0_jax.cli benchmark --preset pi0_base --steps 10 --batch 1,8 --fused-steps 10 --iters 20 \
               --quant prefix-vision --out "$OUT/pi0_fp8.json" > "$OUT/pi0_fp8.log" 2>&1; tail -8 "$OUT/pi0_fp8.log" ;;
    fp8_table) for q in none every-gemm; do   # bf16 and FP8 at B = 1, 8, 64, one process each; prefix-all at B = 1
                 timeout -k 10 230 python3 -m pi0_jax.cli benchmark --preset pi0_base --steps 10 --batch 1,8,64 \
                   --fused-steps 10 --iters 20 $([ $q = none ] || echo --quant $q) --out "$OUT/fp8_table_pi0_$q.json" \
                   > "$OUT/fp8_table_pi0_$q.log" 2>&1; grep -E "^\|" "$OUT/fp8_table_pi0_$q.log" | tail -4; done
               timeout -k 10 110 python3 -m pi0_jax.cli benchmark --preset pi0_base --steps 10 --batch 1 \
                 --fused-steps 10 --iters 30 --quant prefix-all --reference --out "$OUT/fp8_table_pi0_prefix-all.json" \
                 > "$OUT/fp8_table_pi0_prefix-all.log" 2>&1
               grep -E "^\||reference" "$OUT/fp8_table_pi0_prefix-all.log" | tail -4 ;;
    pi05_b1) python3 -m pi0_jax.cli benchmark --preset pi05_base --steps 1,10 --batch 1 --reference --warm-start \
               --compare lerobot --iters 50 --out "$OUT/pi05_b1.json" ;;
    pi05_scan) python3 -m pi0_jax.cli benchmark --preset pi05_base --steps 10 --batch 1 --no-unroll --iters 30 \
               --out "$OUT/pi05_scan.json" ;;
    pi05_unroll_steps) python3 -m pi0_jax.cli benchmark --preset pi05_base --steps 10 --batch 1 --unroll-steps \
               --iters 30 --out "$OUT/pi05_unroll_steps.json" ;;
    pi0_table) python3 -m pi0_jax.cli benchmark --preset pi0_base --steps 1,2,3,5,10 --batch 1,8,64 \
               --fused-steps 1,10 --reference --compare lerobot --warm-start --iters 50 --out "$OUT/pi0_table.json" ;;
    pi05_table) python3 -m pi0_jax.cli benchmark --preset pi05_base --steps 1,2,3,5,10 --batch 1,8,64 \
               --fused-steps 1,10 --reference --compare lerobot --peer-batch 1 --iters 50 --out "$OUT/pi05_table.json" ;;
    lerobot_compile) timeout -k 15 540 python3 -m pi0_jax.cli benchmark --preset pi0_base --steps 10 --batch 1 \
               --fused-steps 10 --compare lerobot --torch-compile --torch-compile-mode default \
               --torch-compile-scope stages --peer-batch 1 --peer-iters 10 --iters 30 --reference \
               --out "$OUT/lerobot_compile.json" 2>&1 | tee "$OUT/lerobot_compile.log" ;;   # LeRobot prints each row
    fp32) python3 -m pi0_jax.cli benchmark --preset pi0_base --dtype float32 --steps 1,10 --batch 1 \
               --reference --iters 30 --out "$OUT/pi0_fp32.json" ;;
    cudnn_b1) python3 -m pi0_jax.cli benchmark --preset pi05_base --steps 1,10 --batch 1 --attention cudnn \
               --reference --iters 50 --out "$OUT/pi05_cudnn.json" ;;
    cmdbuf_b1) XLA_FLAGS="--xla_gpu_enable_command_buffer=FUSION,CUBLAS,CUBLASLT,CUSTOM_CALL,CUDNN,WHILE,CONDITIONAL \
               --xla_gpu_graph_min_graph_size=1" python3 -m pi0_jax.cli benchmark --preset pi05_base --steps 1,10 \
               --batch 1 --iters 50 --out "$OUT/pi05_cmdbuf.json" ;;
    cmdbuf_cudnn_b1) XLA_FLAGS="--xla_gpu_enable_command_buffer=FUSION,CUBLAS,CUBLASLT,CUSTOM_CALL,CUDNN,WHILE,CONDITIONAL \
               --xla_gpu_graph_min_graph_size=1" python3 -m pi0_jax.cli benchmark --preset pi05_base --steps 1,10 \
               --batch 1 --attention cudnn --iters 50 --out "$OUT/pi05_cmdbuf_cudnn.json" ;;
    vision_ab) python3 scripts/vision_probe.py --old-siglip .old/siglip.py --batch ${VISION_BATCH:-1,8,64} --fp8 --trace --iters 30 \
               --out "$OUT/vision_ab.json" ;;  # .old/siglip.py: `git show 7799238:pi0_jax/siglip.py`, carried
    pi05_b64_fp8) for q in none prefix-mlp prefix-vision; do
                 python3 -m pi0_jax.cli benchmark --preset pi05_base --steps 10 --batch 64 --fused-steps 10 --iters 10 \
                   $([ $q = none ] || echo --quant $q) --out "$OUT/pi05_b64_$q.json" > "$OUT/pi05_b64_$q.log" 2>&1
                 tail -4 "$OUT/pi05_b64_$q.log"; done ;;
    flags_b1) i=0; for f in "" "--xla_gpu_graph_min_graph_size=100000" \
                 "--xla_gpu_enable_command_buffer=FUSION,CUBLAS,CUBLASLT,CUSTOM_CALL,CUDNN --xla_gpu_graph_min_graph_size=1" \
                 "--xla_gpu_enable_triton_gemm=false" "--xla_gpu_enable_triton_gemm=false --xla_gpu_enable_cublaslt=true"; do
                 echo "== XLA_FLAGS=$f"; XLA_FLAGS="$f" python3 scripts/profile_engine.py --preset pi0_base --batch 1 \
                   --prompt-tokens 48 --time --iters 30 --trace-stages --out "$OUT/flags_b1_$i.json" \
                   | grep -E "kernels,|median"; i=$((i + 1)); done ;;   # XLA's launch options at B = 1, one process each
    gemm_b1b8) for b in 1 8; do python3 scripts/profile_engine.py --preset pi0_base --batch $b --prompt-tokens 48 \
                 --gemm xla --gemm cublas --time --iters 30 --trace-stages --out "$OUT/gemm_pi0_b$b.json" \
                 | grep -E "^==|kernels,|median|relative"; done ;;   # XLA's GEMM choice against cuBLAS, one process
    gemm_b64) for p in pi05 pi0; do python3 scripts/profile_engine.py --preset ${p}_base --batch 64 --prompt-tokens 20 \
                 --gemm xla --gemm cublas --time --iters 10 --out "$OUT/gemm_${p}_b64.json" \
                 | grep -E "^==|median|relative"; done ;;
    dump_hlo) python3 - <<'PY'   # the optimized HLO of each (preset, stage) in DUMP, e.g. "pi05_base:denoise"
import os
from pi0_jax import benchmark
from pi0_jax.config import get_config
from pi0_jax.engine import Engine
for item in os.environ.get("DUMP", "pi05_base:encode_images pi05_base:denoise").split():
    preset, stage = item.split(":")
    cfg = get_config(preset)
    e = Engine(cfg, benchmark.random_params(cfg, 0), cache_dir=False)
    obs, _ = benchmark.make_inputs(cfg, 1, 3, 20, 0)
    text = e.executable(stage, 1, int(os.environ.get("DUMP_STEPS", 1)), *e.plan(obs)).as_text()
    open(os.path.join(os.environ["OUT"], f"{preset}_{stage}.hlo.txt"), "w").write(text)
PY
    ;;
  esac
  echo "=== $phase took $(( $(date +%s) - start )) s"
done
