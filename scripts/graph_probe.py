"""XLA options per compiled program, in one process on one set of weights: each variant is an Engine whose programs
compile with extra XLA options on top of the engine's own (`matmul.compiler_options`: cuBLAS in the vision program
under gemm="auto"), or, for "conv", with SigLIP's patch embedding as cuDNN's convolution (the engine's form until
2026-11-26) instead of the f32 GEMM, or an Engine built another way (`ENGINE_KW`, `SCHEDULING`, `STAGES`,
`STEP_ENDS`, `RUNTIME`, `PATCHES`: the denoise loop unrolled, the first step's overlap and its programs, π0's
in-projection unfolded, the FP8 expert's rows unpadded, the vision tower as one program, GELU-tanh as jax writes
it, the FP8 MLP on XLA, in its earlier XLA form, on another launch of the kernel, the expert's FP8 MLPs and SigLIP's
FP8 fc1 on XLA's paths, FP8 output scales computed in the programs); the "vision-" variants set their options on
the vision programs alone, "vhead-" on the first of them, "loop-" on the denoise programs without the prefix (the
expert's weights alone).
Stage medians (round-robin over the variants), kernels per call, device span and idle time (by the kernel that
waited) from a trace, and the fused program's actions against the first variant.

    python scripts/graph_probe.py --preset pi0_base --batch 1 --variant default --variant conv --out graph_probe.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import types
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
import profile_engine  # noqa: E402

from pi0_jax import benchmark  # noqa: E402
from pi0_jax.config import get_config  # noqa: E402
from pi0_jax.engine import Engine, layers, paths, programs, runtime, vision  # noqa: E402
from pi0_jax.ops import expert_kernels, formats, fp8_geglu, layout  # noqa: E402
from pi0_jax.quant.schemes import SCHEMES  # noqa: E402

GRAPHS = {"xla_gpu_graph_min_graph_size": 1}
COMMANDS = "FUSION,CUBLAS,CUBLASLT,CUSTOM_CALL,CUDNN"
VARIANTS = {
    "default": {},
    "conv": {},   # the patch embedding as cuDNN's convolution (below)
    "cublas": {"xla_gpu_enable_triton_gemm": False},
    "graphs1": GRAPHS,
    "cudnn-graphs": {"xla_gpu_enable_command_buffer": COMMANDS},
    "cudnn-graphs1": {"xla_gpu_enable_command_buffer": COMMANDS, **GRAPHS},
    # the vision program alone: its kernels launched one by one (no CUDA graph to update before the first one)
    "vision-nographs": {"xla_gpu_enable_command_buffer": ""},
    "vision-graphmin": {"xla_gpu_graph_min_graph_size": 1_000_000},
    # the vision programs' CUDA graphs (their launch is most of the call's lead): cuBLAS outside them, no PDL, and
    # the command buffers' other schedules
    "vision-graphs-nocublas": {"xla_gpu_enable_command_buffer": "FUSION,CUSTOM_CALL"},
    "vision-nopdl": {"xla_gpu_enable_pdl": False},
    "vision-serialize": {"xla_gpu_command_buffer_scheduling_mode": "SERIALIZE"},
    "vision-concurrent": {"xla_gpu_command_buffer_scheduling_mode": "CONCURRENT"},
    # GEMM libraries: cuBLASLt's heuristics (other tiles, stream-K), cuDNN's GEMM fusions beside XLA's Triton ones
    "lt": {"xla_gpu_enable_cublaslt": True},
    "cudnn-gemm": {"xla_gpu_cudnn_gemm_fusion_level": 2},
    "vision-lt": {"xla_gpu_enable_cublaslt": True},
    "vision-xla": {"xla_gpu_enable_triton_gemm": True},
    "vision-cudnn-gemm": {"xla_gpu_enable_triton_gemm": True, "xla_gpu_cudnn_gemm_fusion_level": 2},
    # the programs with the VLM's weights (the prefix fill, with the first step or the loop): cuBLAS for every GEMM
    # (XLA gave the prefix's q/k/v to a Triton GEMM, 17.5 µs a layer; cuBLAS took 14.2 in session 27)
    "prefix-cublas": {"xla_gpu_enable_triton_gemm": False},
    # the same programs on XLA's choice (the engine until session 48, where `matmul.PREFIX_CUBLAS_MAX_BATCH` applies)
    "prefix-xla": {"xla_gpu_enable_triton_gemm": True},
    # the denoise loop: unrolled (ENGINE_KW), or its while loop inside the command buffers
    "unroll-steps": {},
    "while-graphs": {"xla_gpu_enable_command_buffer": COMMANDS + ",WHILE,CONDITIONAL"},
    # the first denoise step beside the prefix fill: off, on at any batch (ENGINE_KW), in XLA's default command-buffer
    # order ("LHS", SCHEDULING) instead of CONCURRENT, or with the other steps' loop inside its program (STAGES: the
    # call until session 45) instead of a third program
    "no-overlap": {},
    "overlap-on": {},
    "overlap-lhs": {},
    "one-loop-program": {},
    # the denoise step's ends (STEP_ENDS): π0's in-projection and time MLP as two products, not folded into one
    "unfolded": {},
    # with FP8 expert weights (`every-gemm`) on the Pallas attention (π0 at B = 3-16): the step's rows as they are
    # (STEP_ENDS), where `programs.FP8_ROW_PAD` pads each element's to make them a multiple of 16 (π0 at B = 8: 51
    # -> 52 rows, 36 of XLA's pads a step gone)
    "fp8-row-pad-off": {},
    # the XLA expert's attention kernel (π0 at B = 3-16) with its ends as XLA fusions (PATCHES): the folded queries
    # and the suffix's keys and values as two buffers, where `layers.PACK_ATTENTION_INPUT` makes them one; the merge
    # writing every padded row in the activation dtype, a fusion after it cutting them and quantising for an FP8
    # out-projection, where `layers.ATTENTION_ENDS_IN_MERGE` does both in the merge (two fusions a layer fewer at B = 8)
    "attention-ends-off": {},
    # the same kernel with a kv head's query heads folded into its rows from B = 4 (`expert_kernels.FOLD_FROM`), not 8
    "fold-from-4": {},
    # the call's vision tower as one program (RUNTIME), not two, or cut after 5, 7 or 13 blocks, not 9
    "one-vision-program": {}, "vision-split-5": {}, "vision-split-7": {}, "vision-split-13": {},
    # every GEMM a Triton GEMM (no cuBLAS fallback) in the vision head's program ("vhead-") or both vision programs:
    # the head's dispatch was longer with Triton GEMMs, the call slower (docs/BENCHMARKS.md, session 49; the host's
    # time grows by 1.4-6 µs a command of any kind, in XLA's work before the graph's launch, not in it: session 69)
    "vhead-triton": {"xla_gpu_enable_triton_gemm": True, "xla_gpu_cublas_fallback": False},
    "vision-triton": {"xla_gpu_enable_triton_gemm": True, "xla_gpu_cublas_fallback": False},
    # the denoise loop's GEMMs on cuBLAS, as `Policy`'s loop program chose them under an FP8 prefix until session 50
    "loop-cublas": {"xla_gpu_enable_triton_gemm": False},
    # the engine's GeGLU with jax's GELU-tanh (PATCHES), where `layers.gelu_tanh` writes it as x sigmoid(2 z)
    "gelu-tanh": {},
    # with FP8 weights (--quant): the prefix's FP8 MLPs on XLA's GEMM and a pass of its own (PATCHES), not on the
    # engine's Mosaic GPU kernel of gate/up GEMM, GeGLU and the down GEMM's e4m3 input (`ops.fp8_geglu`; the
    # variant "fp8-geglu" of session 56's runs, when the kernel was off by default)
    "fp8-geglu-off": {},
    # with FP8 weights: the action expert's FP8 MLPs on XLA's path (`every-gemm`; layers.FP8_GEGLU_EXPERT_ROWS), SigLIP's
    # fc1 on XLA's GEMM and pass (`every-gemm`, `prefix-vision`; vision.FP8_GELU_ROWS), where the kernels run them from
    # B = 8 (the variants "fp8-geglu-expert" and "fp8-gelu-vision" of session 57's runs, when both were off), and the
    # kernel's launch with 3 pipeline stages and a snake of 16 tiles (fp8_geglu.LAUNCH; 2-4 % faster alone in session
    # 56, level in π0's call at B = 1 in session 57)
    "fp8-geglu-expert-off": {},
    # ... and from 128 rows a step (π0 at B = 4 too)
    "fp8-geglu-expert-128": {},
    "fp8-gelu-vision-off": {},
    "fp8-geglu-3stages": {},
    # with FP8 weights: SigLIP's GELU kernel at its launch until session 61 (fp8_geglu.GELU_LAUNCH: 256-column tiles,
    # 3 stages, GELU as x sigmoid(2 z) with the exp's range reduction)
    "fp8-gelu-launch-60": {},
    # with FP8 weights: the GeGLU kernel (the prefix's and the expert's FP8 MLPs) at its launch until session 62 (GELU
    # as x sigmoid(2 z) with the exp's range reduction, where fp8_geglu.LAUNCH folds it as the GELU kernel does), and
    # both FP8 kernels' launches as session 60 had them
    "fp8-geglu-launch-61": {},
    "fp8-launches-60": {},
    # with FP8 weights: both FP8 kernels' GELU written with one tanh (fp8_geglu.Launch.tanh: one tanh.approx.f32 a
    # value, where the folded form takes an exp2 and a reciprocal)
    "fp8-tanh": {},
    "fp8-gelu-tanh": {},   # SigLIP's GELU kernel alone
    # with FP8 weights: both FP8 kernels without clusters of two sharing each weight tile's loads
    # (`fp8_geglu.Launch.cluster`, on since session 66), or one
    "fp8-no-cluster": {},
    "fp8-geglu-no-cluster": {},
    "fp8-gelu-no-cluster": {},
    # with FP8 weights: SigLIP's GELU kernel from 3 cameras at B = 8, as until session 62 (vision.FP8_GELU_ROWS: B = 4)
    "fp8-gelu-rows-6144": {},
    # with FP8 weights: the FP8 MLP as the engine ran it until session 56 (PATCHES: gate and up scaled and rounded to
    # the activation dtype, GeGLU in it), and every FP8 product's output scale computed in the program (PATCHES: not
    # folded into the weights, `formats.fold_scales`)
    "geglu-bf16": {},
    "scales-apart": {},
    # every program called through jax's own call (`dispatch.Dispatch.direct` off), where the engine hands the
    # executable its buffers without jax's checks of weights it was given before
    "jax-dispatch": {},
}
ENGINE_KW = {"unroll-steps": {"unroll_steps": True}, "no-overlap": {"overlap": "off"}, "overlap-on": {"overlap": "on"}}
SCHEDULING = {"overlap-lhs": {"xla_gpu_command_buffer_scheduling_mode": "LHS"}}
STAGES = {"one-loop-program": lambda self, batch, num_steps: (
    *(s for s in Engine.call_stages(self, batch, num_steps) if s in runtime.VISION_STAGES), "prefix_denoise")}
STEP_ENDS = {"unfolded": {"FOLD_ACTION_IN": False}, "fp8-row-pad-off": {"FP8_ROW_PAD": False}}
# the tower cut after other blocks than `runtime.VISION_SPLIT` (0: one program)
RUNTIME = {"one-vision-program": {"VISION_SPLIT": 0}, "vision-split-5": {"VISION_SPLIT": 5},
           "vision-split-7": {"VISION_SPLIT": 7}, "vision-split-13": {"VISION_SPLIT": 13}}


def scaled_geglu(h, w, kernel=False):
    """The engine's MLP until session 56: FP8 gate and up scaled and rounded to h's dtype (`formats.qmatmul`), GeGLU
    in h's dtype, the down GEMM quantising its input."""
    gate, up = layout.split_gate_up(layers._mm(h, w["gate_up"]))
    return layers._mm(layers.gelu_tanh(gate) * up, w["down"])


# module attributes a variant sets (each restored to the engine's own for every other variant)
PATCHES = {"gelu-tanh": (layers, {"gelu_tanh": lambda x: jax.nn.gelu(x, approximate=True)}),
           "attention-ends-off": (layers, {"PACK_ATTENTION_INPUT": False, "ATTENTION_ENDS_IN_MERGE": False}),
           "fp8-geglu-off": (layers, {"FP8_GEGLU": False}), "geglu-bf16": (layers, {"_mlp": scaled_geglu}),
           "fp8-geglu-expert-off": (layers, {"FP8_GEGLU_EXPERT_ROWS": None}),
           "fp8-geglu-expert-128": (layers, {"FP8_GEGLU_EXPERT_ROWS": 128}),
           "fold-from-4": (expert_kernels, {"FOLD_FROM": 4}),
           "fp8-gelu-vision-off": (vision, {"FP8_GELU_ROWS": None}),
           "fp8-geglu-3stages": (fp8_geglu, {"LAUNCH": fp8_geglu.Launch(stages=3, snake=16)}),
           "fp8-gelu-launch-60": (fp8_geglu, {"GELU_LAUNCH": fp8_geglu.Launch(stages=3)}),
           "fp8-geglu-launch-61": (fp8_geglu, {"LAUNCH": fp8_geglu.Launch()}),
           "fp8-launches-60": (fp8_geglu, {"LAUNCH": fp8_geglu.Launch(), "GELU_LAUNCH": fp8_geglu.Launch(stages=3)}),
           "fp8-gelu-rows-6144": (vision, {"FP8_GELU_ROWS": 6144}),
           "fp8-gelu-tanh": (fp8_geglu, {"GELU_LAUNCH": dataclasses.replace(fp8_geglu.GELU_LAUNCH, tanh=True)}),
           "fp8-no-cluster": (fp8_geglu, {"LAUNCH": dataclasses.replace(fp8_geglu.LAUNCH, cluster=False),
                                          "GELU_LAUNCH": dataclasses.replace(fp8_geglu.GELU_LAUNCH, cluster=False)}),
           "fp8-geglu-no-cluster": (fp8_geglu, {"LAUNCH": dataclasses.replace(fp8_geglu.LAUNCH, cluster=False)}),
           "fp8-gelu-no-cluster": (fp8_geglu, {"GELU_LAUNCH": dataclasses.replace(fp8_geglu.GELU_LAUNCH,
                                                                                  cluster=False)}),
           "fp8-tanh": (fp8_geglu, {"LAUNCH": dataclasses.replace(fp8_geglu.LAUNCH, tanh=True),
                                    "GELU_LAUNCH": dataclasses.replace(fp8_geglu.GELU_LAUNCH, tanh=True)}),
           "scales-apart": (formats, {"fold_scales": lambda tree: tree})}


def conv_patch_embed(images, kernel, bias, p: int):
    """The patch embedding as the f32 convolution it replaced (cuDNN's on a GPU)."""
    x = jax.lax.conv_general_dilated(jnp.asarray(images, jnp.float32), kernel.astype(jnp.float32), (p, p), "VALID",
                                     dimension_numbers=("NHWC", "HWIO", "NHWC"))
    return x.reshape(x.shape[0], -1, x.shape[-1]) + bias.astype(jnp.float32)


LOOPED = ("encode_images", "call")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", default="pi0_base")
    p.add_argument("--batch", type=int, action="append", default=None, help="repeatable (default: 1)")
    p.add_argument("--prompt-tokens", type=int, default=48)
    p.add_argument("--steps", type=int, default=10, help="denoise steps of each call (default: %(default)s)")
    p.add_argument("--iters", type=int, default=30, help="timed rounds (one call of every variant's stage each)")
    p.add_argument("--loop", type=int, default=0,
                   help="also time each variant's vision program and call (the engine's two programs) in blocks of this "
                        "many calls in a row, as a robot's loop runs them, the blocks alternating for --iters rounds")
    p.add_argument("--variant", action="append", choices=list(VARIANTS), default=None,
                   help="repeatable, in this order (default: all)")
    p.add_argument("--stage", action="append", default=None,
                   choices=("encode_images", "fill_prefix_cache", "denoise", "infer", "call"),
                   help="repeatable: only these programs (default: all; the actions compared are infer's, else call's)")
    p.add_argument("--settle", type=int, default=1,
                   help="untimed calls of a variant's stage right before each timed one, so that its buffers lie "
                        "where its CUDA graphs last saw them (after another variant's call XLA may update the graphs' "
                        "nodes first: 0.3-1.4 ms on the call's median on two H100s, docs/BENCHMARKS.md, session "
                        "78; 0: as the probe timed before it; default: %(default)s)")
    p.add_argument("--sequence", action="store_true", help="keep each stage's kernels in launch order (one call)")
    p.add_argument("--marks", action="store_true",
                   help="with the call stage: the host's untraced time to each program's dispatch and to the call's "
                        "end (`profile_engine.call_marks`, medians in µs)")
    p.add_argument("--host-events", action="store_true",
                   help="also the host's traced events in each stage's lead (`profile_engine.edges`: summed by "
                        "name, and the first call's in order)")
    p.add_argument("--quant", default=None, choices=sorted(SCHEMES),
                   help="FP8 weights of this scheme for every variant, calibrated as the benchmark's --quant")
    p.add_argument("--trace-max-batch", type=int, default=8,
                   help="trace 3 calls of each stage (kernels, kernel time, span, idle) up to this batch, e.g. 64 to "
                        "compare variants by their kernel time there; larger batches get only the medians "
                        "(default: %(default)s)")
    p.add_argument("--out", type=Path, default=None, help="JSON of every variant's row")
    args = p.parse_args()
    config = get_config(args.preset, dtype="bfloat16")
    params = benchmark.random_params(config, 0)
    if args.quant:
        params = benchmark.fp8_params(config, params, args.quant, num_steps=args.steps)
    report = {"preset": args.preset, "quant": args.quant, "settle": args.settle, "env": benchmark.environment(),
              "rows": []}
    own_options, own_embed, own_concurrent = runtime.matmul.compiler_options, vision.patch_embed, paths.CONCURRENT
    own_ends = {k: getattr(programs, k) for k in ("FOLD_ACTION_IN", "FP8_ROW_PAD")}
    own_split = runtime.VISION_SPLIT
    own_attrs = {(m, k): getattr(m, k) for m, d in PATCHES.values() for k in d}
    for batch in args.batch or [1]:
        obs, noise = benchmark.make_inputs(config, batch, 3, args.prompt_tokens, 0)
        rows, timed, first = [], {}, None
        for name in args.variant or list(VARIANTS):
            extra = VARIANTS[name]
            only = name.split("-")[0] if name.startswith(("vision-", "prefix-", "vhead-", "loop-")) else None

            def applies(tree, vision_tower=False, only=only):
                keys = tree if isinstance(tree, dict) else {}
                head = vision_tower and "embedding" in keys.get("img", {})
                return (only is None or (only == "vision" and vision_tower) or (only == "vhead" and head)
                        or (only == "prefix" and "vlm" in keys) or (only == "loop" and "expert" in keys
                                                                     and "vlm" not in keys))

            runtime.matmul.compiler_options = (
                lambda *a, o=extra, f=applies, **kw: {**(own_options(*a, **kw) or {}),
                                                      **(o if f(a[0], kw.get("vision_tower", False)) else {})} or None)
            vision.patch_embed = conv_patch_embed if name == "conv" else own_embed
            paths.CONCURRENT = SCHEDULING.get(name, own_concurrent)
            for k, v in {**own_ends, **STEP_ENDS.get(name, {})}.items():
                setattr(programs, k, v)
            runtime.VISION_SPLIT = RUNTIME.get(name, {}).get("VISION_SPLIT", own_split)
            patch = PATCHES.get(name, (None, {}))
            for (m, k), v in {**own_attrs, **{(patch[0], k): v for k, v in patch[1].items()}}.items():
                setattr(m, k, v)
            engine = Engine(config, params, cache_dir=False, **ENGINE_KW.get(name, {}))
            if name in STAGES:   # this engine's calls only
                engine.call_stages = types.MethodType(STAGES[name], engine)
            cameras, bucket = engine.plan(obs)
            calls = profile_engine.stage_calls(engine, batch, args.steps, cameras, bucket,
                                               engine.pack(obs, cameras, bucket), noise)
            calls = {k: v for k, v in calls.items() if k in (args.stage or calls)}
            try:
                for fn in calls.values():   # compile every program while this variant's options are set
                    jax.block_until_ready(fn())
            except Exception as e:   # an option this jaxlib does not define
                print(json.dumps({"variant": name, "batch": batch, "error": str(e)[:400]}), flush=True)
                report.setdefault("errors", []).append({"variant": name, "batch": batch, "error": str(e)[:2000]})
                continue
            for prog in engine._executables.values():
                prog.dispatch.direct = name != "jax-dispatch"
            row = {"variant": name, "options": extra, "batch": batch, "kernels_per_call": {}, "span_ms": {},
                   "idle_ms": {}, "compile_s": {k[0]: round(v, 2) for k, v in engine.compile_seconds.items()}}
            if batch <= args.trace_max_batch:
                for stage, fn in calls.items():
                    t = profile_engine.kernel_times(fn, 3, sequence=args.sequence, host=args.host_events)
                    if args.host_events:
                        row.setdefault("lead", {})[stage] = {k: t.get(k) for k in ("lead_us", "tail_us", "gaps_us",
                                                                                   "lead_events", "lead_timeline",
                                                                                   "call_events")}
                    row["kernels_per_call"][stage] = t["kernels_per_call"]
                    row["span_ms"][stage], row["idle_ms"][stage] = t["span_ms"], t["idle_ms"]
                    row.setdefault("kernel_ms", {})[stage] = t["kernel_ms"]
                    row.setdefault("top_kernels", {})[stage] = t["by_name"][:20]
                    row.setdefault("idle_before", {})[stage] = t["idle_before"][:12]
                    if args.sequence:
                        row.setdefault("sequence", {})[stage] = t["sequence"]
            if args.marks and "call" in calls:
                row["marks_us"] = profile_engine.call_marks(engine, batch, args.steps, cameras, bucket,
                                                            engine.pack(obs, cameras, bucket), noise, args.iters)
            actions = next((calls[k] for k in ("infer", "call") if k in calls), None)
            if actions is not None:
                out = np.asarray(actions(), np.float64)
                first = out if first is None else first
                row["rel_l2_vs_first"] = float(np.linalg.norm(out - first) / np.linalg.norm(first))
            rows.append(row)
            timed.update({(name, stage): fn for stage, fn in calls.items()})
        runtime.matmul.compiler_options, vision.patch_embed = own_options, own_embed
        paths.CONCURRENT, runtime.VISION_SPLIT = own_concurrent, own_split
        for k, v in own_ends.items():
            setattr(programs, k, v)
        for (m, k), v in own_attrs.items():
            setattr(m, k, v)
        times = profile_engine.round_robin(timed, args.iters, settle=args.settle)
        if args.loop:
            loops = {(row["variant"], stage): profile_engine.looping(timed[row["variant"], stage], args.loop)
                     for row in rows for stage in LOOPED if (row["variant"], stage) in timed}
            looped = profile_engine.round_robin(loops, args.iters, settle=0)   # a loop settles itself
        for row in rows:
            row["median_ms"] = {stage: float(np.median(t)) for (name, stage), t in times.items()
                                if name == row["variant"]}
            row["p90_ms"] = {stage: float(np.percentile(t, 90)) for (name, stage), t in times.items()
                             if name == row["variant"]}
            if args.loop:
                row["in_a_loop_ms"] = {stage: float(np.median(looped[row["variant"], stage])) / args.loop
                                       for stage in LOOPED if (row["variant"], stage) in looped}
            shown = ("variant", "batch", "median_ms", "p90_ms", "in_a_loop_ms", "marks_us", "kernels_per_call",
                     "kernel_ms", "span_ms", "idle_ms", "rel_l2_vs_first")
            print(json.dumps({k: row[k] for k in shown if k in row}), flush=True)
        report["rows"] += rows
    profile_engine.write_json(args.out, report)


if __name__ == "__main__":
    main()
