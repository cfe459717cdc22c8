"""Can the first denoise step run beside the prefix fill? Its layer i reads only the cache's layer i, but inside the
denoise loop it waits for the whole prefix. Here the first step is peeled out of the loop (`programs.denoise`'s
`peel_first`), and XLA's command buffers run their kernels by buffer dependencies instead of one after another
(`xla_gpu_command_buffer_scheduling_mode=CONCURRENT`; XLA's default, LHS, keeps the scheduler's order). Variants,
timed round-robin in one process as the whole call (the vision program, then prefix + denoise):

  engine            the engine's programs with `overlap="off"` (the default before it): the tower as one program,
                    then prefix + denoise
  concurrent        both programs in CONCURRENT mode
  peel              the first step peeled, default mode
  peel_concurrent   peeled and CONCURRENT
  peel_concurrent_act  the same, the vision program in the default mode
  loop_graph        the denoise loop inside the command buffer too (WHILE, CONDITIONAL: a device-side loop)
  loop_unrolled     the same, its known trip count unrolled in the graph (`xla_gpu_command_buffer_unroll_loops`)
  split_vision      peel_concurrent_act, and the vision program's cameras as separate chains in CONCURRENT mode (each
                    camera's 256 tokens a tower of its own, so one camera's small kernels can run beside another's
                    GEMMs; the batched tower runs M = 768 GEMMs on under one wave of CTAs)

Each variant's kernels from a profiler trace: with kernels running side by side, their summed time exceeds the
device's span.

    python scripts/concurrent_probe.py --preset pi0_base --prompt-tokens 20 --iters 40 --out concurrent.json \
        [--variants loop_graph,loop_unrolled] [--check-calls 500]

--check-calls N also compares each variant's actions with the engine's on N calls of fresh noise, dispatched back to
back and read only at the end (a race between kernels that CONCURRENT mode runs side by side would show as a
difference in some call, where one comparison could miss it), then runs each variant N times on the first call's
input: `max_abs` and `min_abs` over the calls, `calls_differing`, and `repeat_max_abs` (0 where every repeat equals
the first, as a program without a race gives).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

# scripts/ is on the path when this runs as a script
from profile_engine import kernel_times, probe_arguments, probe_engine, round_robin, write_json

from pi0_jax.engine.paths import CONCURRENT
from pi0_jax.engine.runtime import Program
from pi0_jax.engine.store import shapes
from pi0_jax.ops import matmul

# XLA's default command types on jax 0.11.2, and a device-side loop
LOOP = {"xla_gpu_enable_command_buffer": "FUSION,CUBLAS,CUBLASLT,CUSTOM_CALL,CUDNN,DYNAMIC_SLICE_FUSION,WHILE,CONDITIONAL"}
# variant: (vision program's extra options or None for the engine's, prefix + denoise's options, peel_first,
# the vision program's cameras as separate chains)
VARIANTS = {"concurrent": (CONCURRENT, CONCURRENT, False, False), "peel": (None, {}, True, False),
            "peel_concurrent": (CONCURRENT, CONCURRENT, True, False),
            "peel_concurrent_act": (None, CONCURRENT, True, False), "loop_graph": (None, LOOP, False, False),
            "loop_unrolled": (None, {**LOOP, "xla_gpu_command_buffer_unroll_loops": True}, False, False),
            "split_vision": (CONCURRENT, CONCURRENT, True, True)}


def main() -> None:
    p = probe_arguments(__doc__, 40, "the variants' times and kernels")
    p.add_argument("--variants", default="concurrent,peel,peel_concurrent",
                   help=f"comma-separated, of {', '.join(VARIANTS)} (default: %(default)s)")
    p.add_argument("--check-calls", type=int, default=0,
                   help="also compare each variant's actions with the engine's on this many calls of fresh noise")
    args = p.parse_args()
    config, engine, noise, cameras, bucket, packed = probe_engine(args, overlap="off")
    images, image_masks, tokens, token_mask, state = packed
    act = engine.call_programs(args.batch, args.steps, cameras, bucket)[-1]   # overlap off: the prefix and the loop
    vision = engine.executable("encode_images", args.batch, args.steps, cameras, bucket)   # the tower as one program
    sched = engine.schedule(args.steps)

    def compile_stage(stage, extra, split=False, **kw):
        weights = engine.stage_weights(stage)
        fn, specs = engine._stage(stage, shapes(weights), args.batch, args.steps, cameras, bucket)
        if kw:
            fn = functools.partial(fn, **kw)
        if split:
            tower = fn

            def fn(w, im):   # (C, B, ...) images -> each camera's tokens from a tower of its own, camera-major
                return jnp.concatenate([tower(w, im[i:i + 1]) for i in range(im.shape[0])], axis=1)
        opts = {**(matmul.compiler_options(weights, engine.gemm, vision_tower=stage == "encode_images") or {}),
                **extra}
        return Program(jax.jit(fn).lower(*specs).compile(compiler_options=opts), tuple(weights), stage,
                       engine.vision_split)

    variants = {}
    for name in args.variants.split(","):
        vision_opts, opts, peel, split = VARIANTS[name]
        variants[name] = (vision if vision_opts is None else compile_stage("encode_images", vision_opts, split),
                          compile_stage("prefix_denoise", opts, **({"peel_first": True} if peel else {})))
    w = engine.weights

    def call(pair):
        v, a = pair
        return a(w, sched, v(w, images), image_masks, tokens, token_mask, state, noise)

    want = np.asarray(call((vision, act)), np.float32)
    temp = {"engine": act.compiled.memory_analysis().temp_size_in_bytes,
            **{name: a.compiled.memory_analysis().temp_size_in_bytes for name, (_, a) in variants.items()}}
    report = {"max_abs_vs_engine": {name: float(np.max(np.abs(np.asarray(call(p), np.float32) - want)))
                                    for name, p in variants.items()},
              "prefix_denoise_temp_bytes": temp}
    if args.check_calls:
        keys = jax.random.split(jax.random.key(1), args.check_calls)
        noises = [jax.random.normal(k, noise.shape, noise.dtype) for k in keys]
        wants = [engine.sample_packed(packed, n, args.steps, cameras, bucket) for n in noises]
        report["check"] = {"calls": args.check_calls}
        for name, (v, a) in variants.items():
            outs = [a(w, sched, v(w, images), image_masks, tokens, token_mask, state, n) for n in noises]
            diffs = [float(jnp.max(jnp.abs(o - x))) for o, x in zip(outs, wants)]
            again = [a(w, sched, v(w, images), image_masks, tokens, token_mask, state, noises[0])
                     for _ in range(args.check_calls)]   # one input repeated: a race shows as outputs that differ
            report["check"][name] = {"max_abs": max(diffs), "min_abs": min(diffs),
                                     "calls_differing": sum(d > 0 for d in diffs),
                                     "repeat_max_abs": max(float(jnp.max(jnp.abs(o - again[0]))) for o in again)}
    calls = {"engine": lambda: engine.sample_packed(packed, noise, args.steps, cameras, bucket),
             **{name: functools.partial(call, p) for name, p in variants.items()}}
    times = round_robin(calls, args.iters)
    report["call_ms"] = {k: {"median": float(np.median(v)), "p10": float(np.percentile(v, 10))}
                         for k, v in times.items()}
    report["kernels"] = {}
    for name, fn in calls.items():
        kt = kernel_times(fn, calls=5)
        report["kernels"][name] = {**{k: kt[k] for k in ("kernels_per_call", "kernel_ms", "span_ms", "idle_ms",
                                                         "wall_ms")}, "idle_before": kt["idle_before"][:6]}
    for k, v in report.items():
        print(k, v, flush=True)
    write_json(args.out, report)


if __name__ == "__main__":
    main()
