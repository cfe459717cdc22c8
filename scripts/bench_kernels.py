"""The fused expert kernels (`pi0_jax.ops`) against the XLA path on one GPU: correctness, launch-parameter sweeps,
the denoise step of both paths on the same weights and cache (kernel counts, a trace per kernel name), and the
pallas engine's whole call.

Two sweeps. The per-stage one (the default) times each stage as one program that runs it on `--copies` independent
inputs, each with its own weights (one launch each, divided by the copies). Its ranking did not hold inside the step
(run 19), so `--step-sweep NAME` (a set of STEP_SWEEPS) compiles the 10-step denoise program once per variant and
times the variants interleaved. Two probes: `--gemm-probe` runs each GEMM kernel once for a kernel profiler (ncu), and
`--graph-probe` compiles the Pallas step with XLA's command buffers as default, off and all, and with programmatic
dependent launch off and on.

    python scripts/bench_kernels.py --out kernels.json
    python scripts/bench_kernels.py --step-sweep splits --trace --skip-parity --presets pi0_base --out k.json
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import inspect
import json
import os
import sys
import time
import traceback
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from pi0_jax import benchmark, gemma
from pi0_jax.config import get_config
from pi0_jax.engine import Engine, layers, programs
from pi0_jax.ops import expert_attention as ea, expert_kernels as ek, layout

sys.path.insert(0, str(Path(__file__).parent))
from profile_engine import count_ops, kernel_times  # noqa: E402

G, L = ek.Gemm, ek.Launch
# The launch variants of `step_sweep`, each one change from the defaults: run 20 swept the pipelining depth, run 22
# the split-K counts (their f32 partials are written and read again: gate/up at 4 splits writes 8.4 MB beside its
# 16.8 MB of weights). Neither moved the step by more than 1.1 % (docs/BENCHMARKS.md, "Launch parameters"). Runs 23
# and 25 put gate/up at 128 columns without pipelining (3-4 % for π0); `gate_up` times it against the old default.
# Run 27 timed gate/up + GeGLU and q/k/v + RoPE each as one kernel walking all of K (no partials, no epilogue): the
# step 13-74 % slower for every launch tried, so those kernels were removed ("One pass per GEMM, measured").
# Since run 30 gate/up runs the Mosaic GPU kernel on Hopper, so the `mlp` variants above change nothing there unless
# they also set mosaic_mlp=None.
STEP_SWEEPS = {
    "depths": {"default": {}, "qkv 128x8 s1": dict(qkv=G(128, 8, 1)), "qkv 128x8 s2": dict(qkv=G(128, 8, 2)),
               "mlp 64x4 s3": dict(mlp=G(64, 4, 3)), "mlp 64x4 s1": dict(mlp=G(64, 4, 1)),
               "mlp 64x4 s2": dict(mlp=G(64, 4, 2)), "mlp 64x8 s1": dict(mlp=G(64, 8, 1)),
               "out 128x8 s1": dict(out=G(128, 8, 1)), "out 64x4 s1": dict(out=G(64, 4, 1)),
               "down 64x8 s1": dict(down=G(64, 8, 1)), "down 64x8 s2": dict(down=G(64, 8, 2)),
               "attention s1": dict(attention_stages=1), "attention s2": dict(attention_stages=2)},
    "splits": {"default": {}, "mlp 64x2": dict(mlp=G(64, 2)), "mlp 128x2": dict(mlp=G(128, 2)),
               "mlp 64x1": dict(mlp=G(64, 1)), "mlp 32x2": dict(mlp=G(32, 2)), "qkv 64x4": dict(qkv=G(64, 4)),
               "qkv 64x2": dict(qkv=G(64, 2)), "qkv 32x4": dict(qkv=G(32, 4)), "down 64x4": dict(down=G(64, 4)),
               "down 32x4": dict(down=G(32, 4)), "out 64x2": dict(out=G(64, 2)), "out 32x2": dict(out=G(32, 2))},
    "gate_up": {"default": {}, "mlp 64x4 s3": dict(mlp=G(64, 4, 3)), "mlp 256x4 s1": dict(mlp=G(256, 4, 1))},
    # each GEMM as the TMA-pipelined Mosaic GPU kernel (`ops.mosaic_gemm`), at the launches that led
    # scripts/mgpu_gemm_probe.py (cols per warpgroup, splits, stages, warpgroups)
    # (q/k/v and plain gate/up with the norm before the kernel as XLA's fusion; run 33 had it inside the kernel,
    # `git show 092647b:pi0_jax/ops/mosaic_gemm.py`, and was no faster)
    "mosaic": {"default": {}, "mlp mosaic 64 1s 8st": dict(mosaic_mlp=L(64, 1, 8)),
               "qkv mosaic 64 2s 6st": dict(mosaic_qkv=L(64, 2, 6)),
               "qkv mosaic 128 4s 4st": dict(mosaic_qkv=L(128, 4, 4)),
               "qkv mosaic 128 2s 6st": dict(mosaic_qkv=L(128, 2, 6)),
               "out mosaic 64 8s 4st": dict(mosaic_out=L(64, 8, 4)),
               "down mosaic 64 8s 4st": dict(mosaic_down=L(64, 8, 4))},
    # gate/up: the Triton kernel, the Mosaic kernel plain (XLA's GeGLU after it), or with GeGLU in its epilogue (the
    # default since run 30; 32 hidden units per CTA failed Mosaic's layout inference there). Since session 31 a GeGLU
    # CTA takes one block pair of 32 units (cols 64): "geglu 128" no longer applies and runs the Triton kernel
    "mosaic_geglu": {"default": {}, "mlp triton": dict(mosaic_mlp=None),
                     "mlp mosaic 64 1s 8st": dict(mosaic_mlp=L(64, 1, 8)),
                     "mlp geglu 64 8st": dict(mosaic_mlp=L(64, 1, 8, geglu=True)),
                     "mlp geglu 128 4st": dict(mosaic_mlp=L(128, 1, 4, geglu=True))},
    # session 41: how many programs each GEMM and the attention run, at the defaults of session 31 (gate/up on Mosaic
    # GPU, q/k/v at 4 splits): q/k/v 80, out 64, down 128, the attention 112 programs at B = 1
    "fill": {"default": {}, "qkv 64x4": dict(qkv=G(64, 4)), "qkv 128x2": dict(qkv=G(128, 2)),
             "qkv 128x4 s1": dict(qkv=G(128, 4, 1)), "out 32x4": dict(out=G(32, 4)), "out 64x8": dict(out=G(64, 8)),
             "out 64x4 s1": dict(out=G(64, 4, 1)), "down 64x4": dict(down=G(64, 4)), "down 32x8": dict(down=G(32, 8)),
             "down 64x8 s1": dict(down=G(64, 8, 1)), "attention 7 splits": dict(kv_splits=7),
             "attention 26 splits": dict(kv=32, kv_splits=26), "attention w4": dict(attention_warps=4)},
    # the attention's query rows a program (a 64 x 256 f32 accumulator is 128 registers a thread at 4 warps)
    "query_rows": {"default": {}, "q32": dict(q=32), "q32 w4": dict(q=32, attention_warps=4),
                   "q16 w4": dict(q=16, attention_warps=4),
                   "q32 w4 7 splits": dict(q=32, attention_warps=4, kv_splits=7),
                   "q32 w4 s2": dict(q=32, attention_warps=4, attention_stages=2)},
    # the attention's key splits on Mosaic GPU (`ops.mosaic_attention`), the merge as XLA's ops, and the expert with no
    # Triton kernel (`ek.TRITON_FREE`); the Mosaic attention also at 7 prefix splits (2 key blocks a CTA through its
    # ring of shared-memory slots)
    "mosaic_attention": {"default": {}, "mosaic attention": dict(mosaic_attention=True),
                         "xla merge": dict(xla_merge=True),
                         "mosaic attention, xla merge": dict(mosaic_attention=True, xla_merge=True),
                         "mosaic attention 7 splits": dict(mosaic_attention=True, kv_splits=7),
                         "triton-free": {f.name: getattr(ek.TRITON_FREE, f.name)
                                         for f in dataclasses.fields(ek.Blocks)
                                         if getattr(ek.TRITON_FREE, f.name) != getattr(ek.Blocks(), f.name)}},
    # the same with the next step's wgmma issued before the last one finished (`Launch.delay`)
    "mosaic_delay": {"default": {}, "mlp geglu 64 6st d1": dict(mosaic_mlp=L(64, 1, 6, geglu=True, delay=1)),
                     "mlp geglu 64 8st d1": dict(mosaic_mlp=L(64, 1, 8, geglu=True, delay=1)),
                     "mlp geglu 64 8st d2": dict(mosaic_mlp=L(64, 1, 8, geglu=True, delay=2)),
                     "mlp mosaic 64 1s 8st d1": dict(mosaic_mlp=L(64, 1, 8, delay=1))},
    # more contraction rows per pipeline step (`Launch.tk`, session 30: gate/up + GeGLU alone 9.76 -> 9.27 us with 128
    # rows a step at depth 3, the same shared memory as 64 at depth 6; q/k/v on the Mosaic kernel 7.03 -> 6.71 us)
    "mosaic_tk": {"default": {}, "mlp geglu 64 3st tk128": dict(mosaic_mlp=L(64, 1, 3, geglu=True, tk=128)),
                  "mlp geglu 64 2st tk256": dict(mosaic_mlp=L(64, 1, 2, geglu=True, tk=256)),
                  "qkv mosaic 64 4s 2st tk128": dict(mosaic_qkv=L(64, 4, 2, tk=128))},
    # the GeGLU kernel on 128 CTAs (session 31, one block pair of 32 units a CTA): its pipeline depth and delay
    "mosaic_pair": {"default": {}, "mlp geglu 64 4st": dict(mosaic_mlp=L(64, 1, 4, geglu=True)),
                    "mlp geglu 64 8st": dict(mosaic_mlp=L(64, 1, 8, geglu=True)),
                    "mlp geglu 64 8st d1": dict(mosaic_mlp=L(64, 1, 8, geglu=True, delay=1))},
    # q/k/v with its norm's statistics, 1/rms, RoPE and q's scale in one Mosaic GPU kernel (`mosaic_gemm.qkv_rope`: 20
    # CTAs at π0's shapes, 151 kernels a step against 169, π0.5 154 against 170; at most 5 deep in shared memory),
    # against the plain Mosaic GEMM in one and two K chunks (its norm and epilogue apart); prepared in session 84,
    # which had no GPU
    "mosaic_qkv_rope": {"default": {}, "qkv rope 64 3st": dict(mosaic_qkv=L(64, 1, 3, rope=True)),
                        "qkv rope 64 4st": dict(mosaic_qkv=L(64, 1, 4, rope=True)),
                        "qkv rope 64 5st": dict(mosaic_qkv=L(64, 1, 5, rope=True)),
                        "qkv mosaic 64 1s 8st": dict(mosaic_qkv=L(64, 1, 8)),
                        "qkv mosaic 64 2s 6st": dict(mosaic_qkv=L(64, 2, 6))},
    # programs a GEMM launches against the SMs (session 31: q/k/v at 128 x 8 is 160 programs on 132 SMs, 1.2 waves)
    "waves": {"default": {}, "qkv 128x4": dict(qkv=G(128, 4)), "qkv 128x2": dict(qkv=G(128, 2)),
              "qkv 256x4": dict(qkv=G(256, 4)), "qkv 64x4": dict(qkv=G(64, 4)), "out 64x8": dict(out=G(64, 8)),
              "out 128x8": dict(out=G(128, 8))},
    # the attention's key splits since its splits are merged by one Pallas kernel (session 28: XLA's merge had been
    # two fusions), and its key block
    "kv_splits": {"default": {}, "kv splits 7": dict(kv_splits=7), "kv splits 10": dict(kv_splits=10),
                  "kv splits 16": dict(kv_splits=16), "kv 32 splits 13": dict(kv=32),
                  "kv 32 splits 26": dict(kv=32, kv_splits=26), "attention warps 4": dict(attention_warps=4)},
    # π0.5 with a 200-token prompt (run it with --presets pi05_base first): 1,024 prefix keys are 16 blocks of 64, so
    # the default 13 splits take two blocks each in 8 programs and leave 5 empty (session 50)
    "kv_splits_long": {"default": {}, "kv splits 8": dict(kv_splits=8), "kv splits 16": dict(kv_splits=16),
                       "kv splits 16 w4": dict(kv_splits=16, attention_warps=4),
                       "kv 32 splits 32": dict(kv=32, kv_splits=32),
                       "kv 32 splits 32 s2 w4": dict(kv=32, kv_splits=32, attention_stages=2, attention_warps=4),
                       # one 128-key block a split (π0's 832 keys do not split into 128s and keep 64: `fit`)
                       "kv 128 splits 8 s1": dict(kv=128, kv_splits=8, attention_stages=1),
                       "kv 128 splits 8 s2": dict(kv=128, kv_splits=8, attention_stages=2),
                       "kv 128 splits 8 s1 w4": dict(kv=128, kv_splits=8, attention_stages=1, attention_warps=4)},
}


def set_blocks(blocks: ek.Blocks) -> None:
    """The Blocks the programs traced from now on take: `layers.suffix_layers_pallas`' default (by name; a 2-tuple
    of defaults, written before its `tables` parameter came, set blocks=None and failed every variant)."""
    fn = layers.suffix_layers_pallas
    names = [p.name for p in inspect.signature(fn).parameters.values() if p.default is not inspect.Parameter.empty]
    fn.__defaults__ = tuple(blocks if n == "blocks" else d for n, d in zip(names, fn.__defaults__))


def median_ms(fn, args, iters: int, warmup: int = 3) -> float:
    for _ in range(warmup):
        jax.block_until_ready(fn(*args))
    times = []
    for _ in range(iters):
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - start)
    return float(np.median(times)) * 1e3


def stage_ms(stage, varying: list, fixed: tuple, iters: int) -> float:
    """stage(*v, *fixed) on each of the independent inputs `varying` (an array or a tuple of them each), one program;
    ms per call."""
    fn = jax.jit(lambda vs, fx: [stage(*(v if isinstance(v, tuple) else (v,)), *fx) for v in vs])
    return median_ms(fn, (varying, fixed), iters) / len(varying)


def rel_l2(a, b) -> float:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


def xla_stages(cfg, out, xs, w, pos, ck, cv, pmask, ys, hs, s, p, rnd, args):
    """The engine's own XLA ops for each stage, at the unpadded shapes."""
    dt, h, nk = jnp.bfloat16, cfg.head_dim, cfg.num_kv_heads
    x3 = [x[None, :s] for x in xs]
    angles = gemma.rope_angles(pos[:, :s], h)
    out["xla"]["norm_qkv_rope"] = stage_ms(
        lambda x, w: layers._qkv(layers.rms_norm(x, w["pre_attn"])[0], w["qkv"], cfg, angles), x3, (w,),
        args.iters)
    q5 = [layers._qkv(x, w["qkv"], cfg, angles)[0] for x in x3]
    kc, vc = ck[:p].reshape(1, p, nk, h), cv[:p].reshape(1, p, nk, h)
    km, vm = rnd(1, s, nk, h), rnd(1, s, nk, h)
    pm3 = jnp.broadcast_to(pmask[:, None, :p] != 0, (1, s, p))
    sm3 = jnp.tril(jnp.ones((1, s, s), bool))
    out["xla"]["attention"] = stage_ms(lambda q, kc, vc, km, vm: layers._attend(q, [kc, km], [vc, vm], [pm3, sm3], dt),
                                       q5, (kc, vc, km, vm), args.iters)
    out["xla"]["out_residual"] = stage_ms(lambda y, w, x: x + y @ w["attn_out"], [y[None, :s] for y in ys],
                                          (w, x3[0]), args.iters)
    out["xla"]["norm_geglu"] = stage_ms(
        lambda x, w: (lambda g: jax.nn.gelu(g[0], approximate=True) * g[1])(
            layout.split_gate_up(layers.rms_norm(x, w["pre_attn"])[0] @ w["gate_up"])), x3, (w,), args.iters)
    out["xla"]["down_residual"] = stage_ms(lambda hh, w, x: x + hh @ w["down"], [hh[None, :s] for hh in hs],
                                           (w, x3[0]), args.iters)
    out["xla"]["layer"] = stage_ms(
        lambda x, w, kc, vc: layers.suffix_layer(cfg, w, x, angles, kc, vc, pm3, sm3)[0], x3,
        ({k: w[k] for k in ("qkv", "attn_out", "gate_up", "down", "pre_attn")} | {"pre_ffw": w["pre_attn"]}, kc, vc),
        args.iters)


def stages(config, args, key):
    """Per-stage timings of one expert layer at full size (B=1): XLA ops vs each kernel over a block sweep."""
    cfg, dt = config.action_expert, jnp.bfloat16
    s = config.suffix_len
    sp, d, f, h = layout.suffix_rows(s), cfg.width, cfg.mlp_dim, cfg.head_dim
    p = 768 + (200 if config.pi05 else 48)
    pp = -(-p // layout.KEY_PAD) * layout.KEY_PAD
    n, nk = cfg.num_heads, cfg.num_kv_heads
    ks = iter(jax.random.split(key, 256))

    def rnd(*shape, scale=1.0, dtype=dt):
        return (jax.random.normal(next(ks), shape, jnp.float32) * scale).astype(dtype)

    c = args.copies
    xs = [rnd(sp, d) for _ in range(c)]
    w = {"qkv": rnd(d, (n + 2 * nk) * h, scale=d**-0.5), "attn_out": rnd(n * h, d, scale=(n * h) ** -0.5),
         "gate_up": rnd(d, 2 * f, scale=d**-0.5), "down": rnd(f, d, scale=f**-0.5), "pre_attn": rnd(d, scale=0.1)}
    scale = w["pre_attn"][None]
    pos = jnp.arange(p - 100, p - 100 + sp)[None]
    cos, sin = layout.rope_tables(pos, h)
    qkvs = [rnd(sp, (n + 2 * nk) * h) for _ in range(c)]
    ck, cv = rnd(pp, nk * h), rnd(pp, nk * h)
    pmask = (jnp.arange(pp) < p).at[300:556].set(False).astype(jnp.int32)[None]  # a masked camera, padded keys
    smask = jnp.tril(jnp.ones((sp, sp), jnp.int32))
    ys = [rnd(sp, n * h) for _ in range(c)]
    hs = [rnd(sp, f) for _ in range(c)]
    kw = {"num_heads": n, "num_kv_heads": nk}
    # the kernels' inputs: every copy has its own weights and cache, as every layer of the step does (one shared
    # weight would stay in L2 across the copies: 16.8 MB of gate/up fits the H100's 50 MB)
    ws = [{k: rnd(*v.shape, scale=float(jnp.std(v.astype(jnp.float32)))) for k, v in w.items() if k != "pre_attn"}
          for _ in range(c)]
    caches = [(rnd(pp, nk * h), rnd(pp, nk * h)) for _ in range(c)]

    out = {"xla": {}, "pallas": {}}
    if args.xla_stages:
        xla_stages(cfg, out, xs, w, pos, ck, cv, pmask, ys, hs, s, p, rnd, args)
    # runs 1-3 (commits f0fa40a, 139b35b) swept warps, q / kv blocks and split-K of the residual GEMMs; runs 4-5 the
    # key splits of attention and the split-K GEMMs behind the norm kernels; session 20 (run 19) the pipelining depth
    # with them (ncu: a K loop of one step keeps one tile pair at any depth; the out- and down-projections' loops of
    # two steps take three pairs at depth 3, 197 KB, one program per SM). The default comes first.
    attn = ("q", "kv", "kv_splits", "attention_warps", "attention_stages")
    sweeps = {
        "norm_qkv_rope": [dict(qkv=G(*g)) for g in ((128, 8, 3), (128, 8, 1), (128, 8, 2), (64, 8, 1), (64, 4, 1),
                                                    (128, 16, 1), (64, 16, 1))],
        "attention": [dict(zip(attn, a)) for a in ((64, 64, 13, 8, 3), (64, 64, 13, 8, 1), (64, 64, 7, 8, 1),
                                                   (64, 64, 7, 8, 2), (32, 64, 7, 4, 1), (16, 64, 4, 4, 1),
                                                   (16, 64, 4, 4, 2), (64, 32, 26, 4, 1))],
        "out_residual": [dict(out=G(*g)) for g in ((64, 4, 3), (64, 4, 1), (64, 8, 1), (32, 8, 1), (32, 16, 1),
                                                   (64, 16, 1), (128, 8, 1))],
        "norm_geglu": [dict(mlp=G(*g)) for g in ((64, 4, 3), (64, 4, 2), (64, 4, 1), (128, 4, 1), (128, 4, 2),
                                                 (128, 8, 1), (64, 8, 1), (256, 4, 1), (256, 8, 1), (32, 8, 1))],
        "down_residual": [dict(down=G(*g)) for g in ((64, 8, 3), (64, 8, 2), (64, 8, 1), (64, 16, 1), (32, 16, 1),
                                                     (128, 16, 1), (64, 32, 1))],
    }
    def each(inputs, key):
        return [(a, wi[key]) for a, wi in zip(inputs, ws)]

    calls = {
        "norm_qkv_rope": (lambda bl: lambda x, w: ek.norm_qkv_rope(x, scale, 0, False, w, cos, sin, width=d,
                                                                   head_dim=h, blocks=bl, **kw), each(xs, "qkv"), ()),
        "attention": (lambda bl: lambda q, ck, cv: ea.attention(q, ck, cv, pmask, smask, batch=1, blocks=bl, **kw),
                      [(q, *kv) for q, kv in zip(qkvs, caches)], ()),
        "out_residual": (lambda bl: lambda y, w, x: ek.matmul_residual(y, w, x, gemm=bl.out, blocks=bl),
                         each(ys, "attn_out"), (xs[0],)),
        "norm_geglu": (lambda bl: lambda x, w: ek.norm_geglu(x, scale, 0, False, w, width=d, blocks=bl),
                       each(xs, "gate_up"), ()),
        "down_residual": (lambda bl: lambda hh, w, x: ek.matmul_residual(hh, w, x, gemm=bl.down, blocks=bl),
                          each(hs, "down"), (xs[0],)),
    }
    best = {}
    for name, variants in sweeps.items():
        make, varying, fixed = calls[name]
        rows = []
        for v in variants[: args.max_variants]:
            try:
                rows.append((stage_ms(make(dataclasses.replace(ek.Blocks(), **v)), varying, fixed, args.iters), v))
            except Exception as e:  # a variant Triton rejects (e.g. out of shared memory) is reported, not fatal
                rows.append((float("inf"), {**v, "error": f"{type(e).__name__}: {str(e)[:200]}"}))
        rows.sort(key=lambda r: r[0])
        out["pallas"][name] = [{"ms": t, **{k: dataclasses.asdict(x) if dataclasses.is_dataclass(x) else x
                                            for k, x in v.items()}} for t, v in rows]
        best[name] = rows[0]
        xla_us = out["xla"].get(name, float("nan")) * 1e3
        default = next((t for t, v in rows if v is variants[0]), float("inf"))
        print(f"{name:14s} xla {xla_us:7.1f} us   pallas default {default * 1e3:7.1f} us   best "
              f"{rows[0][0] * 1e3:7.1f} us {rows[0][1]}", flush=True)
    take = {"norm_qkv_rope": ("qkv",), "attention": ("q", "kv", "kv_splits", "attention_warps", "attention_stages"),
            "out_residual": ("out",), "norm_geglu": ("mlp",), "down_residual": ("down",)}
    fields = {}
    for name, keys in take.items():
        fields.update({k: v for k, v in best[name][1].items() if k in keys})
    blocks = dataclasses.replace(ek.Blocks(), **fields)
    out["best_blocks"] = dataclasses.asdict(blocks)
    print("best blocks", blocks, flush=True)
    return out, blocks


def interleaved_ms(fns: dict, iters: int, warmup: int = 3) -> dict:
    """Median ms of each no-argument call, timed one call of each per round (the order reversed every other round),
    so drift between variants cannot decide an A/B."""
    for fn in fns.values():
        for _ in range(warmup):
            jax.block_until_ready(fn())
    times = {name: [] for name in fns}
    for i in range(iters):
        for name in (list(fns) if i % 2 == 0 else list(fns)[::-1]):
            start = time.perf_counter()
            jax.block_until_ready(fns[name]())
            times[name].append(time.perf_counter() - start)
    return {name: float(np.median(t)) * 1e3 for name, t in times.items()}


def pallas_engine(config):
    """The engine with kernels="pallas" on random full-size weights at B=1 (3 cameras, a 48-token prompt, 200 for
    π0.5) and its inputs: (engine, cameras, bucket, packed observation, noise, prefix cache)."""
    params = benchmark.random_params(config, 0)
    obs, noise = benchmark.make_inputs(config, 1, 3, 200 if config.pi05 else 48, 0)
    engine = Engine(config, params, kernels="pallas", cache_dir=False)
    del params
    cams, bucket = engine.plan(obs)
    packed = engine.pack(obs, cams, bucket)
    tokens = engine.executable("encode_images", 1, 0, cams, bucket)(engine.weights, packed[0])
    cache = engine.executable("fill_prefix_cache", 1, 0, cams, bucket)(engine.weights, tokens, *packed[1:4])
    return engine, cams, bucket, packed, noise, cache


def denoise_program(config, engine, cache, packed, noise, steps: int, kernels: str = "pallas", options=None):
    """The `steps`-step denoise program on the engine's weights and this cache, compiled (with XLA `options`) under
    the kernels' current default blocks: (compiled, a no-argument call)."""
    w, sched = engine.weights, engine.schedule(steps)
    fn = functools.partial(programs.denoise, config, num_steps=steps, unroll=True, unroll_steps=False, kernels=kernels)
    den = jax.jit(fn).lower(w, sched, cache, packed[4], noise).compile(options)
    return den, lambda: den(w, sched, cache, packed[4], noise)


def step_ops(den) -> dict:
    """The op counts of a compiled denoise program's loop body (its largest computation but the entry), and the
    kernels per step (fusions, custom calls and copies)."""
    body = {k: v for k, v in count_ops(den.as_text()).items() if not k.startswith("ENTRY")}
    ops = max(body.values(), key=lambda v: v["fusion"] + v["custom-call"])
    return {"loop_body_ops": ops, "kernels_per_step": ops["fusion"] + ops["custom-call"] + ops["copy"]}


def engine_runs(config, args, variants: dict, out):
    """The engine at B=1 with the XLA denoise program and each Pallas block variant on the same weights and cache (at
    full size the kernels' weight layout is the XLA one, and padded prefix keys are masked): correctness, timings
    (interleaved), kernel counts and traces, and the fused whole call of each Pallas variant."""
    if time.perf_counter() - T0 > args.engine_before_s:
        out[config.name] = "skipped: out of time"
        return
    engine, cams, bucket, packed, noise, cache = pallas_engine(config)
    w = engine.weights
    res = {"prefix_keys": int(cache.mask.shape[1]),
           "blocks": {name: dataclasses.asdict(b) for name, b in variants.items() if b is not None}}
    calls, fused, actions = {}, {}, {}
    for name, blocks in variants.items():
        kernels = "xla" if blocks is None else "pallas"
        if blocks is not None:
            set_blocks(blocks)
        r = res[name] = {}
        for steps in (1, 10):
            t0 = time.perf_counter()
            den, calls[f"{name}/denoise_{steps}"] = denoise_program(config, engine, cache, packed, noise, steps,
                                                                    kernels)
            r[f"compile_denoise_{steps}_s"] = time.perf_counter() - t0
        r.update(step_ops(den))
        actions[name] = np.asarray(calls[f"{name}/denoise_10"]())
        if blocks is not None:
            engine._executables.pop(("infer", 1, 10, tuple(cams), bucket), None)  # recompiled with these blocks
            fused[name] = engine.executable("infer", 1, 10, cams, bucket)
    sched10 = engine.schedule(10)
    for name, fn in fused.items():
        calls[f"{name}/infer_10"] = functools.partial(lambda fn: fn(w, sched10, *packed, noise), fn)
    timed = interleaved_ms(calls, args.iters)
    for key, ms in timed.items():
        name, what = key.split("/")
        res[name][f"{what}_ms"] = ms
    for name in variants:
        r = res[name]
        r["per_step_ms"] = (r["denoise_10_ms"] - r["denoise_1_ms"]) / 9
        r["rel_l2_vs_xla"] = rel_l2(actions[name], actions["xla"]) if "xla" in actions else None
        if args.trace:
            try:
                r["trace"] = t = kernel_times(calls[f"{name}/denoise_10"], 5)
                print(f"{config.name} {name} trace: {t['kernels_per_call']:.0f} kernels, {t['kernel_ms']:.2f} ms in "
                      f"kernels of {t['wall_ms']:.2f} ms ({t['busy']:.0%} busy)", flush=True)
                for row in t["by_name"][:12]:
                    print(f"   {row['us_per_call']:9.1f} us  x{row['per_call']:6.1f}  {row['name'][:90]}", flush=True)
            except Exception:
                r["trace"] = traceback.format_exc()[-2000:]
                print(r["trace"], flush=True)
        print(f"{config.name} {name}: " + json.dumps({k: v for k, v in r.items() if k != "trace"}), flush=True)
    out[config.name] = res


def step_sweep(config, args, out) -> ek.Blocks:
    """Launch variants of the kernels timed where they run: the 10-step denoise program (π0 B=1, the engine's
    weights and cache), one compile per variant, interleaved timing. Each variant changes one GEMM or the attention
    from the defaults; then the fields that beat the defaults are combined and timed again beside the best single
    change. Returns the fastest Blocks. (A stage timed alone, as `stages` does, ranked them differently: run 19.)"""
    base, singles = ek.Blocks(), STEP_SWEEPS[args.step_sweep]
    engine, cams, bucket, packed, noise, cache = pallas_engine(config)
    res = out["step_sweep"] = {"model": config.name, "rounds": []}

    def timed(variants: dict) -> dict:
        calls, kernels, outs = {}, {}, {}
        for name, fields in list(variants.items()):
            set_blocks(dataclasses.replace(base, **fields))
            try:
                den, calls[name] = denoise_program(config, engine, cache, packed, noise, 10)
            except Exception as e:  # noqa: BLE001  (e.g. a tile over the shared memory: recorded, not timed)
                res.setdefault("failed", {})[name] = f"{type(e).__name__}: {str(e)[:300]}"
                print(f"  {name:28s} failed: {res['failed'][name]}", flush=True)
                variants = {k: v for k, v in variants.items() if k != name}
                continue
            kernels[name] = step_ops(den)["kernels_per_step"]
            outs[name] = np.asarray(jax.block_until_ready(calls[name]()), np.float32)
        set_blocks(base)
        ms = interleaved_ms(calls, args.iters)
        ref = outs["default"]
        rows = [{"variant": n, "denoise_10_ms": ms[n], "vs_default": ms[n] / ms["default"],
                 "rel_l2_vs_default": float(np.linalg.norm(outs[n] - ref) / np.linalg.norm(ref)),
                 "kernels_per_step": kernels[n], "fields": {k: dataclasses.asdict(v) if dataclasses.is_dataclass(v)
                                                            else v for k, v in variants[n].items()}}
                for n in variants]
        if args.trace:   # did the changed kernel get faster inside the step, and did the step follow it?
            for r in rows:
                t = kernel_times(calls[r["variant"]], 5)
                r["trace"] = {"kernel_ms": t["kernel_ms"], "wall_ms": t["wall_ms"], "busy": t["busy"],
                              "us_per_call": {row["name"]: row["us_per_call"] for row in t["by_name"][:12]}}
        res["rounds"].append(rows)
        for r in sorted(rows, key=lambda r: r["denoise_10_ms"]):
            traced = (f"  {r['trace']['kernel_ms']:.2f} ms in kernels, {r['trace']['busy']:.0%} busy"
                      if "trace" in r else "")
            print(f"  {r['variant']:28s} {r['denoise_10_ms']:7.3f} ms  {r['vs_default']:.3f}  "
                  f"{r['kernels_per_step']} kernels/step  rel L2 {r['rel_l2_vs_default']:.1e}{traced}", flush=True)
        return {r["variant"]: r for r in rows}

    first = timed(singles)
    winners = {}   # per field, the single change that beat the default by more than 0.5 %
    for name, r in sorted(first.items(), key=lambda kv: kv[1]["denoise_10_ms"]):
        field = next(iter(singles[name]), None)
        if field and r["vs_default"] < 0.995 and field not in winners:
            winners[field] = singles[name][field]
    best_single = min(first, key=lambda n: first[n]["denoise_10_ms"])
    second = {"default": {}, best_single: singles[best_single]}
    if len(winners) > 1:
        second["combined"] = winners
    second = timed(second) if len(second) > 1 else first
    best = min(second, key=lambda n: second[n]["denoise_10_ms"])
    blocks = dataclasses.replace(base, **(winners if best == "combined" else singles[best]))
    res["best"] = {"variant": best, "blocks": dataclasses.asdict(blocks)}
    print("step sweep best:", best, blocks, flush=True)
    return blocks


def f32_parity(out):
    """Dummy presets in f32 on the GPU: the engine with kernels vs the reference sampler, highest precision."""
    sys.path.insert(0, str(Path(__file__).parents[1] / "tests"))
    from test_model import make_obs, randomize
    from pi0_jax import pi0

    with jax.default_matmul_precision("highest"):
        for name in ("dummy", "dummy_pi05"):
            config = get_config(name)
            params = randomize(pi0.init_params(config, jax.random.key(0)))
            obs = make_obs(config)
            noise = jax.random.normal(jax.random.key(1), (2, config.action_horizon, config.action_dim))
            ref = np.asarray(jax.jit(pi0.sample_actions, static_argnums=(0, 4))(config, params, obs, noise, 3))
            got = np.asarray(Engine(config, params, kernels="pallas", cache_dir=False).sample_actions(
                obs, jnp.array(noise), 3))
            out[f"f32_{name}_max_abs"] = float(np.abs(got - ref).max())
            print(name, "f32 pallas vs reference max abs", out[f"f32_{name}_max_abs"], flush=True)


def graph_probe(config, args, out):
    """Is the Pallas step paced by the host or by the gaps between kernels? The 10-step Pallas denoise (B=1)
    compiled several ways in one process: XLA's default command buffers (CUDA graphs), none, every command type
    including the loop, and programmatic dependent launch (PDL) off and on; interleaved timing, a trace of each, and
    each variant's actions against the default's (a launch that overlapped a kernel with its producer would show).
    A variant this jaxlib does not know is recorded as an error."""
    engine, cams, bucket, packed, noise, cache = pallas_engine(config)
    everything = "FUSION,CUBLAS,CUBLASLT,CUSTOM_CALL,CUDNN,WHILE,CONDITIONAL"
    variants = {"default": None, "no graphs": {"xla_gpu_enable_command_buffer": ""},
                "all commands": {"xla_gpu_enable_command_buffer": everything, "xla_gpu_graph_min_graph_size": 1},
                "pdl off": {"xla_gpu_enable_pdl": False}, "pdl on": {"xla_gpu_enable_pdl": True}}
    calls, res = {}, {}
    out["graph_probe"] = res
    for name, options in variants.items():
        try:
            _, calls[name] = denoise_program(config, engine, cache, packed, noise, 10, options=options)
        except Exception as e:  # noqa: BLE001  (an option this jaxlib does not define)
            res[name] = {"error": f"{type(e).__name__}: {str(e)[:300]}", "options": options}
            print(f"{name:14s} failed: {res[name]['error']}", flush=True)
    want = np.asarray(calls["default"](), np.float32)
    for name, ms in interleaved_ms(calls, args.iters).items():
        t = kernel_times(calls[name], 5)
        diff = float(np.abs(np.asarray(calls[name](), np.float32) - want).max())
        res[name] = {"denoise_10_ms": ms, "kernels_per_call": t["kernels_per_call"], "kernel_ms": t["kernel_ms"],
                     "trace_wall_ms": t["wall_ms"], "max_abs_vs_default": diff, "options": variants[name]}
        print(f"{name:14s} {ms:7.3f} ms   {t['kernels_per_call']:.0f} kernels, {t['kernel_ms']:.2f} ms in kernels, "
              f"trace wall {t['wall_ms']:.2f} ms, max |actions - default| {diff:.2e}", flush=True)


def gemm_probe(config):
    """Each of the expert's four GEMM kernels once at full size (B=1), π0's norms, for a kernel profiler:
    `ncu --clock-control none --kernel-name regex:expert_ --launch-skip 12 python3 scripts/bench_kernels.py
    --gemm-probe`. Then the gate/up GEMM alone under other launch parameters."""
    cfg, dt = config.action_expert, jnp.bfloat16
    sp, d, f = layout.suffix_rows(config.suffix_len), cfg.width, cfg.mlp_dim
    hd = 2 * layout.half_dim(cfg.head_dim)   # a head in the kernels' layout (= head_dim at full size)
    heads, attn = (cfg.num_heads + 2 * cfg.num_kv_heads) * hd, cfg.num_heads * hd
    ks = iter(jax.random.split(jax.random.key(0), 16))

    def rnd(*shape):
        return jax.random.normal(next(ks), shape, jnp.float32).astype(dt) * shape[0] ** -0.5

    x, scale = rnd(sp, d), rnd(1, d)
    cos, sin = layout.rope_tables(jnp.arange(sp)[None] + 800, cfg.head_dim)
    kw = {"num_heads": cfg.num_heads, "num_kv_heads": cfg.num_kv_heads, "head_dim": cfg.head_dim}
    blocks = ek.Blocks()
    calls = [jax.jit(lambda x, w: ek.norm_qkv_rope(x, scale, 0, False, w, cos, sin, width=d, **kw)),
             jax.jit(lambda y, w: ek.matmul_residual(y, w, x, gemm=blocks.out, name="expert_attn_out")),
             jax.jit(lambda x, w: ek.norm_geglu(x, scale, 0, False, w, width=d)),
             jax.jit(lambda h, w: ek.matmul_residual(h, w, x, gemm=blocks.down, name="expert_down"))]
    inputs = [(x, rnd(d, heads)), (rnd(sp, attn), rnd(attn, d)),
              (x, rnd(d, 2 * f)), (rnd(sp, f), rnd(f, d))]
    # and the gate/up kernel alone under other launches (named apart): does the tiling move its time?
    for g, warps in ((G(64, 4, 3), 4), (G(128, 4, 1), 4), (G(128, 4, 1), 8), (G(64, 8, 1), 4), (G(128, 8, 1), 4),
                     (G(64, 2, 3), 4), (G(256, 4, 1), 8), (G(32, 4, 1), 4)):
        calls.append(jax.jit(functools.partial(
            lambda x, w, g, warps: ek.matmul_partials(x, w, scale, scaled=True, gemm=g, name=f"expert_mlp_{g.cols}x"
                                                      f"{g.splits}s{g.stages}w{warps}",
                                                      blocks=dataclasses.replace(blocks, num_warps=warps))[0],
            g=g, warps=warps)))
        inputs.append(inputs[2])
    for _ in range(2):   # the second round is the one to read (module load and autotuning are past)
        for fn, args in zip(calls, inputs):
            jax.block_until_ready(fn(*args))


T0 = time.perf_counter()


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--iters", type=int, default=30, help="timed calls per median (default: %(default)s)")
    p.add_argument("--copies", type=int, default=16,
                   help="independent inputs per stage program in the per-stage sweep (default: %(default)s)")
    p.add_argument("--engine-before-s", type=float, default=150.0, help="start an engine run only before this")
    p.add_argument("--xla-stages", action="store_true", help="also time each stage's XLA ops (the first run did)")
    p.add_argument("--skip-sweep", action="store_true", help="no sweep: the engine runs with the default blocks")
    p.add_argument("--step-sweep", choices=sorted(STEP_SWEEPS), default=None,
                   help="sweep these launch variants inside the 10-step denoise program (instead of the per-stage "
                        "sweep, whose ranking did not hold in the step)")
    p.add_argument("--graph-probe", action="store_true",
                   help="only time the Pallas 10-step denoise with XLA's command buffers as default, off and all, "
                        "and with PDL off and on")
    p.add_argument("--gemm-probe", action="store_true",
                   help="only run each expert GEMM kernel twice at full size (for ncu), then exit")
    p.add_argument("--blocks", type=Path, default=None,
                   help="a previous run's JSON: its best_blocks for the engine runs (with --skip-sweep)")
    p.add_argument("--skip-parity", action="store_true", help="skip the f32 parity of the dummy presets")
    p.add_argument("--trace", action="store_true", help="sum the 10-step denoise's GPU kernels from a profiler trace")
    p.add_argument("--max-variants", type=int, default=100, help="block variants per stage in the sweep")
    p.add_argument("--presets", default="pi0_base,pi05_base",
                   help="engine runs (the sweeps and probes use the first; default: %(default)s)")
    p.add_argument("--out", type=Path, default=Path("kernels.json"), help="JSON results (default: %(default)s)")
    args = p.parse_args()
    if args.gemm_probe:
        return gemm_probe(get_config(args.presets.split(",")[0], dtype="bfloat16"))
    if args.graph_probe:
        out = {"device": jax.devices()[0].device_kind, "jax": jax.__version__}
        graph_probe(get_config(args.presets.split(",")[0], dtype="bfloat16"), args, out)
        return args.out.write_text(json.dumps(out, indent=1, default=str))
    dev = jax.devices()[0]
    out = {"device": dev.device_kind, "jax": jax.__version__, "xla_flags": os.environ.get("XLA_FLAGS", ""),
           "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
    print(out, flush=True)
    sections = [] if args.skip_parity else [("f32_parity", lambda: f32_parity(out))]
    blocks = ek.Blocks.from_dict(json.loads(args.blocks.read_text())["stages"]["best_blocks"]) if args.blocks \
        else ek.Blocks()
    out["blocks_given"] = dataclasses.asdict(blocks)
    best = None
    if args.step_sweep:
        def sweep():
            nonlocal best
            best = step_sweep(get_config(args.presets.split(",")[0], dtype="bfloat16"), args, out)
        sections.append(("step_sweep", sweep))
    elif not args.skip_sweep:
        def sweep():
            nonlocal best
            config = get_config(args.presets.split(",")[0], dtype="bfloat16")
            out["stages"], best = stages(config, args, jax.random.key(0))
        sections.append(("sweep", sweep))
    def variants():   # the given blocks, and the sweep's best where it differs
        return {"xla": None, "pallas": blocks} | ({"pallas_best": best} if best not in (None, blocks) else {})

    sections += [(name, lambda name=name: engine_runs(get_config(name, dtype="bfloat16"), args, variants(), out))
                 for name in args.presets.split(",")]
    for name, fn in sections:
        try:
            fn()
        except Exception:
            out[f"{name}_error"] = traceback.format_exc()[-3000:]
            print(out[f"{name}_error"], flush=True)
        args.out.write_text(json.dumps(out, indent=1, default=str))
        print(f"[{time.perf_counter() - T0:.0f}s] {name} done", flush=True)


if __name__ == "__main__":
    main()
