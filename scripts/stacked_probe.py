"""Does the host's dispatch of the vision program shrink with fewer weight buffers? The engine passes SigLIP's 27
blocks as 4 matrices each and one table of every block's vectors (109 of the vision program's arguments; the host
pays about 1-1.7 µs per buffer per call before the first kernel, docs/BENCHMARKS.md "The host's share of a call").
Here the matrices stay stacked too, (27, ...) per weight, and the unrolled program slices each layer's weights
inside itself. Variants, timed round-robin in one process as the whole call (vision program, then the engine's own
prefix + denoise program):

  engine       the engine's call (`Engine.sample_packed`)
  stacked      the vision program on the stacked blocks (XLA's default options)
  stacked_dsf  the same with `xla_gpu_enable_dynamic_slice_fusion` (GEMMs read their operand slices in place)

Each vision program's kernels from a profiler trace (a slice XLA copies shows as extra kernels and time). Session
37 also had the vectors alone stacked, which the engine's layout now is (session 72).

    python scripts/stacked_probe.py --preset pi0_base --iters 40 --out stacked.json
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

# scripts/ is on the path when this runs as a script
from profile_engine import kernel_times, probe_arguments, probe_engine, round_robin, write_json

from pi0_jax.engine import programs
from pi0_jax.engine import weights as weights_lib
from pi0_jax.ops import matmul


def main() -> None:
    args = probe_arguments(__doc__, 40, "the variants' times and kernels").parse_args()
    config, engine, noise, cameras, bucket, packed = probe_engine(args)
    images, image_masks, tokens, token_mask, state = packed
    # the call as two programs, the tower as one (the engine's call at the time of this probe, session 37)
    vision, act = (engine.executable(s, args.batch, args.steps, cameras, bucket)
                   for s in ("encode_images", "prefix_denoise"))
    sched = engine.schedule(args.steps)
    img = engine.weights["img"]
    depth = config.siglip.depth
    trees = {"stacked": {"img": {**img, "blocks": jax.tree.map(lambda *xs: jnp.stack(xs), *img["blocks"])}}}

    def encode(w, images):
        blocks = weights_lib.unstack(w["img"]["blocks"], depth)
        return programs.encode_images(config, {"img": {**w["img"], "blocks": blocks}}, images, unroll=True,
                                      attention=engine.attention, kernels=engine.kernels)

    base_opts = matmul.compiler_options(engine.stage_weights("encode_images"), engine.gemm, vision_tower=True) or {}
    variants = {"stacked": ("stacked", base_opts),
                "stacked_dsf": ("stacked", {**base_opts, "xla_gpu_enable_dynamic_slice_fusion": True})}
    compiled = {name: (jax.jit(encode).lower(trees[tree], images).compile(compiler_options=opts), trees[tree])
                for name, (tree, opts) in variants.items()}
    want = np.asarray(vision(engine.weights, images), np.float32)
    report = {"buffers": {"engine": len(jax.tree.leaves(engine.stage_weights("encode_images"))),
                          **{k: len(jax.tree.leaves(t)) for k, t in trees.items()}}, "max_abs_vs_engine": {}}
    for name, (fn, tree) in compiled.items():
        report["max_abs_vs_engine"][name] = float(np.max(np.abs(np.asarray(fn(tree, images), np.float32) - want)))

    calls = {"engine": lambda: act(engine.weights, sched, vision(engine.weights, images), image_masks, tokens,
                                   token_mask, state, noise)}
    for name, (fn, tree) in compiled.items():
        calls[name] = lambda fn=fn, tree=tree: act(engine.weights, sched, fn(tree, images), image_masks, tokens,
                                                   token_mask, state, noise)
    times = round_robin(calls, args.iters)
    report["call_ms"] = {k: {"median": float(np.median(v)), "p10": float(np.percentile(v, 10))}
                         for k, v in times.items()}
    visions = {"engine": lambda: vision(engine.weights, images),
               **{name: lambda fn=fn, tree=tree: fn(tree, images) for name, (fn, tree) in compiled.items()}}
    report["vision_ms"] = {k: float(np.median(v)) for k, v in round_robin(visions, args.iters).items()}
    report["vision_kernels"] = {}
    for name, fn in visions.items():
        kt = kernel_times(fn, calls=5)
        report["vision_kernels"][name] = {k: kt[k] for k in ("kernels_per_call", "kernel_ms", "span_ms", "wall_ms")}
    for k, v in report.items():
        print(k, v, flush=True)
    write_json(args.out, report)


if __name__ == "__main__":
    main()
