"""One fused program against the three stage programs chained without a host round trip between them.

At B = 1 a call pays the host for every weight buffer it takes before its first kernel runs (`dispatch_probe.py`),
and the fused program takes all of them. Chained, each stage program takes only its own weights, the host
dispatches the next program while the GPU runs the one before, and each program may have its own compile options
(cuBLAS for the vision tower, where it measured 20 % less kernel time at B = 1). Variants, timed round-robin in one
process on the same weights and inputs, each call blocked on its actions:

  fused            the engine's fused program (`Engine.sample_actions`), the whole weights tree
  chain_tree       vision -> prefix -> denoise as the engine's stage programs, each taking the whole tree
  chain_sub        the same three programs, each taking only its weights
  chain_sub_cublas chain_sub with the vision program's GEMMs on cuBLAS
  two_sub_cublas   vision (cuBLAS, its weights) -> prefix and denoise as one program (their weights)
  call             `Engine.sample_packed`, the engine's call since this probe: two_sub_cublas through the engine

It also times the vision program alone (synchronised, as the benchmark's stage row) on its weights, with XLA's
GEMMs and with cuBLAS, and traces each chained variant for the device's span and idle time (`profile_engine.idle`).

    python scripts/chain_probe.py --preset pi0_base --iters 40 --out chain.json
"""

from __future__ import annotations

import functools
import json

import jax
import numpy as np

from pi0_jax import benchmark
from pi0_jax.engine import programs
# scripts/ is on the path when this runs as a script
from profile_engine import kernel_times, looping, probe_arguments, probe_engine, round_robin, write_json

CUBLAS = {"xla_gpu_enable_triton_gemm": False}


def main() -> None:
    p = probe_arguments(__doc__, iters=40, out="the times and traces")
    p.add_argument("--loop", type=int, default=0,
                   help="also time the call and the fused program in blocks of this many calls in a row "
                        "(`profile_engine.looping`), round-robin")
    args = p.parse_args()

    config, engine, noise, cameras, bucket, packed = probe_engine(args)
    images, image_masks, tokens, token_mask, state = packed
    w, sched, b, n = engine.weights, engine.schedule(args.steps), args.batch, args.steps
    fused = engine.executable("infer", b, n, cameras, bucket)   # its Program hands it every engine weight
    kw = {"unroll": engine.unroll, "attention": engine.attention, "kernels": engine.kernels}
    den_kw = {**kw, "num_steps": n, "unroll_steps": False}
    w_img = {"img": w["img"]}
    w_pre = {"embedding": w["embedding"], "vlm": w["vlm"]}
    w_den = {k: w[k] for k in ("expert", "top", "final_norm_1") if k in w}

    def enc_fn(wi, images):
        return programs.encode_images(config, wi, images, **kw)

    def pre_fn(wp, it, im, t, tm):   # without the expert's weights: given the cache layout its kernels take
        return programs.fill_prefix_cache(config, wp, it, im, t, tm, **{**kw, "kernels": engine.kernels_for(b)})

    def den_fn(wd, sc, cache, st, nz):
        return programs.denoise(config, wd, sc, cache, st, nz, **den_kw)

    def tail_fn(wp, wd, sc, it, im, t, tm, st, nz):
        return programs.prefix_denoise(config, {**wp, **wd}, sc, it, im, t, tm, st, nz, **den_kw)

    def compile_(fn, args_, options=None):
        return jax.jit(fn).lower(*args_).compile(options)

    enc_t = compile_(lambda w, images: programs.encode_images(config, w, images, **kw), (w, images))
    pre_t = compile_(lambda w, *a: programs.fill_prefix_cache(config, w, *a, **kw),
                     (w, enc_t(w, images), image_masks, tokens, token_mask))
    den_t = compile_(lambda w, *a: programs.denoise(config, w, *a, **den_kw),
                     (w, sched, pre_t(w, enc_t(w, images), image_masks, tokens, token_mask), state, noise))
    enc_x = compile_(enc_fn, (w_img, images))
    enc_c = compile_(enc_fn, (w_img, images), CUBLAS)
    it = enc_x(w_img, images)
    pre = compile_(pre_fn, (w_pre, it, image_masks, tokens, token_mask))
    cache = pre(w_pre, it, image_masks, tokens, token_mask)
    den = compile_(den_fn, (w_den, sched, cache, state, noise))
    tail = compile_(tail_fn, (w_pre, w_den, sched, it, image_masks, tokens, token_mask, state, noise))

    def chain_tree():
        i = enc_t(w, images)
        c = pre_t(w, i, image_masks, tokens, token_mask)
        return den_t(w, sched, c, state, noise)

    def chain_sub(enc):
        i = enc(w_img, images)
        c = pre(w_pre, i, image_masks, tokens, token_mask)
        return den(w_den, sched, c, state, noise)

    calls = {
        "fused": lambda: fused(w, sched, images, image_masks, tokens, token_mask, state, noise),
        "chain_tree": chain_tree,
        "chain_sub": functools.partial(chain_sub, enc_x),
        "chain_sub_cublas": functools.partial(chain_sub, enc_c),
        "two_sub_cublas": lambda: tail(w_pre, w_den, sched, enc_c(w_img, images), image_masks, tokens, token_mask,
                                       state, noise),
        "call": lambda: engine.sample_packed((images, image_masks, tokens, token_mask, state), noise, n,
                                             cameras, bucket),
        "vision_sub": lambda: enc_x(w_img, images),
        "vision_sub_cublas": lambda: enc_c(w_img, images),
        "vision_tree": lambda: enc_t(w, images),
    }
    ref = np.asarray(calls["fused"](), np.float64)
    rel = {}
    for name, fn in calls.items():
        if not name.startswith("vision"):
            out = np.asarray(fn(), np.float64)
            rel[name] = float(np.linalg.norm(out - ref) / np.linalg.norm(ref))
    buffers = {"tree": len(jax.tree.leaves(w)), "vision": len(jax.tree.leaves(w_img)),
               "prefix": len(jax.tree.leaves(w_pre)), "denoise": len(jax.tree.leaves(w_den))}
    print("buffers", json.dumps(buffers), "rel L2 vs fused", json.dumps(rel), flush=True)
    times = round_robin(calls, args.iters)
    report = {"preset": args.preset, "batch": b, "steps": n, "prompt_tokens": args.prompt_tokens,
              "env": benchmark.environment(), "buffers": buffers, "rel_l2_vs_fused": rel,
              "median_ms": {k: float(np.median(v)) for k, v in times.items()},
              "p10_p90_ms": {k: [float(np.percentile(v, q)) for q in (10, 90)] for k, v in times.items()},
              "trace": {}}
    print(json.dumps({k: round(v, 3) for k, v in report["median_ms"].items()}, indent=1), flush=True)
    if args.loop:
        looped = round_robin({k: looping(calls[k], args.loop) for k in ("call", "fused")}, args.iters,
                             settle=0)   # a loop settles itself
        report["in_a_loop_ms"] = {k: float(np.median(v)) / args.loop for k, v in looped.items()}
        print("in a loop:", json.dumps({k: round(v, 3) for k, v in report["in_a_loop_ms"].items()}), flush=True)
    for name, fn in calls.items():
        t = kernel_times(fn, 5)
        report["trace"][name] = {k: t[k] for k in ("kernels_per_call", "kernel_ms", "wall_ms", "span_ms", "idle_ms",
                                                   "idle_max_us")}
        print(f"{name:18s} {t['kernels_per_call']:.0f} kernels, {t['kernel_ms']:.3f} ms in kernels; span "
              f"{t['span_ms']:.3f} ms, idle {t['idle_ms']:.3f} (largest gap {t['idle_max_us']:.1f} us); traced wall "
              f"{t['wall_ms']:.3f} ms", flush=True)
    write_json(args.out, report)


if __name__ == "__main__":
    main()
