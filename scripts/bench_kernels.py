"""The fused expert kernels (`pi0_jax.ops`) against the XLA path on one GPU: correctness, per-stage timings with a
block-size sweep, the denoise step of both paths on the same weights and cache, and the pallas engine's whole call.

Per-stage times are medians over calls of one program that runs the stage on `--copies` independent inputs (separate
buffers, so nothing is copied or de-duplicated), divided by the copies: one launch each, inside one executable.

    python scripts/bench_kernels.py --out kernels.json
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import os
import sys
import time
import traceback
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from pi0_jax import benchmark
from pi0_jax.config import get_config
from pi0_jax.engine import Engine, layers, programs
from pi0_jax.ops import expert_kernels as ek, layout

sys.path.insert(0, str(Path(__file__).parent))
from profile_engine import count_ops, kernel_times  # noqa: E402


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
    """stage(v, *fixed) on each of the independent inputs `varying`, one program; ms per call."""
    fn = jax.jit(lambda vs, fx: [stage(v, *fx) for v in vs])
    return median_ms(fn, (varying, fixed), iters) / len(varying)


def rel_l2(a, b) -> float:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


def xla_stages(cfg, out, xs, w, pos, ck, cv, pmask, ys, hs, s, p, rnd, args):
    """The engine's own XLA ops for each stage, at the unpadded shapes."""
    dt, h, nk = jnp.bfloat16, cfg.head_dim, cfg.num_kv_heads
    x3 = [x[None, :s] for x in xs]
    positions = pos[:, :s]
    out["xla"]["norm_qkv_rope"] = stage_ms(
        lambda x, w: layers._qkv(layers.rms_norm(x, w["pre_attn"])[0], w["qkv"], cfg, positions), x3, (w,),
        args.iters)
    q5 = [layers._qkv(x, w["qkv"], cfg, positions)[0] for x in x3]
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
            jnp.split(layers.rms_norm(x, w["pre_attn"])[0] @ w["gate_up"], 2, axis=-1)), x3, (w,), args.iters)
    out["xla"]["down_residual"] = stage_ms(lambda hh, w, x: x + hh @ w["down"], [hh[None, :s] for hh in hs],
                                           (w, x3[0]), args.iters)
    out["xla"]["layer"] = stage_ms(
        lambda x, w, kc, vc: layers.suffix_layer(cfg, w, x, positions, kc, vc, pm3, sm3)[0], x3,
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

    out = {"xla": {}, "pallas": {}}
    if args.xla_stages:
        xla_stages(cfg, out, xs, w, pos, ck, cv, pmask, ys, hs, s, p, rnd, args)
    # runs 1-3 (commits f0fa40a, 139b35b) swept warps, q / kv blocks and split-K of the residual GEMMs; run 4 the key
    # splits of attention; these sweep the split-K GEMMs behind the norm kernels and the attention splits again
    sweeps = {
        "norm_qkv_rope": [dict(qkv_cols=a, qkv_splits=sp) for a, sp in
                          ((64, 4), (64, 8), (32, 4), (32, 8), (128, 4), (128, 8), (64, 2))],
        "attention": [dict(q=q, kv_splits=sp, attention_warps=wp) for q, sp, wp in
                      ((64, 8, 8), (64, 4, 8), (64, 13, 8), (16, 4, 4), (32, 8, 4), (64, 8, 4))],
        "out_residual": [dict(out_cols=a, out_splits=sp) for a, sp in ((32, 4), (32, 8), (64, 4), (16, 4))],
        "norm_geglu": [dict(mlp_cols=a, mlp_splits=sp) for a, sp in
                       ((64, 4), (64, 8), (128, 4), (32, 4), (64, 2), (128, 8))] + [dict(k=256), dict(num_warps=8)],
        "down_residual": [dict(out_cols=a, down_splits=sp) for a, sp in ((32, 8), (32, 16), (64, 8), (16, 8))],
    }
    calls = {
        "norm_qkv_rope": (lambda bl: lambda x, w: ek.norm_qkv_rope(x, scale, 0, False, w, cos, sin, width=d,
                                                                   head_dim=h, blocks=bl, **kw), xs, (w["qkv"],)),
        "attention": (lambda bl: lambda q, ck, cv: ek.attention(q, ck, cv, pmask, smask, batch=1, blocks=bl, **kw),
                      qkvs, (ck, cv)),
        "out_residual": (lambda bl: lambda y, w, x: ek.matmul_residual(y, w, x, splits=bl.out_splits, blocks=bl), ys,
                         (w["attn_out"], xs[0])),
        "norm_geglu": (lambda bl: lambda x, w: ek.norm_geglu(x, scale, 0, False, w, width=d, blocks=bl), xs,
                       (w["gate_up"],)),
        "down_residual": (lambda bl: lambda hh, w, x: ek.matmul_residual(hh, w, x, splits=bl.down_splits, blocks=bl),
                          hs,
                          (w["down"], xs[0])),
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
        out["pallas"][name] = [{"ms": t, **v} for t, v in rows]
        best[name] = rows[0]
        xla_us = out["xla"].get(name, float("nan")) * 1e3
        print(f"{name:14s} xla {xla_us:7.1f} us   pallas best {rows[0][0] * 1e3:7.1f} us "
              f"{rows[0][1]}", flush=True)
    # shared fields (k, num_stages, out_cols) come from the stage that reads the most bytes
    take = {"norm_qkv_rope": ("qkv_cols", "qkv_splits"), "attention": ("q", "kv", "kv_splits", "attention_warps"),
            "out_residual": ("out_splits",), "norm_geglu": ("mlp_cols", "mlp_splits", "k", "num_stages", "num_warps"),
            "down_residual": ("out_cols", "down_splits")}
    fields = {}
    for name, keys in take.items():
        fields.update({k: v for k, v in best[name][1].items() if k in keys})
    blocks = dataclasses.replace(ek.Blocks(), **fields)
    out["best_blocks"] = dataclasses.asdict(blocks)
    print("best blocks", blocks, flush=True)
    return out, blocks


def engine_runs(config, args, blocks, out):
    """The engine with kernels="pallas" at B=1, and the XLA denoise program on the same weights and cache (at full
    size the kernels' weight layout is the XLA one, and padded prefix keys are masked): correctness and timings."""
    if time.perf_counter() - T0 > args.engine_before_s:
        out[config.name] = "skipped: out of time"
        return
    params = benchmark.random_params(config, 0)
    prompt = 200 if config.pi05 else 48
    obs, noise = benchmark.make_inputs(config, 1, 3, prompt, 0)
    layers.suffix_layers_pallas.__defaults__ = (None, blocks)
    engine = Engine(config, params, kernels="pallas", cache_dir=False)
    del params
    cams, bucket = engine.plan(obs)
    packed = engine.pack(obs, cams, bucket)
    w = engine.weights
    tokens = engine.executable("encode_images", 1, 0, cams, bucket)(w, packed[0])
    cache = engine.executable("fill_prefix_cache", 1, 0, cams, bucket)(w, tokens, *packed[1:4])
    res, actions = {"prefix_keys": int(cache.mask.shape[1]), "blocks": dataclasses.asdict(blocks)}, {}
    for kernels in ("xla", "pallas"):
        r = {}
        for steps in (1, 10):
            sched = engine.schedule(steps)
            t0 = time.perf_counter()
            if kernels == "pallas":
                den = engine.executable("denoise", 1, steps, cams, bucket)
            else:
                fn = functools.partial(programs.denoise, config, num_steps=steps, unroll=True, unroll_steps=False)
                den = jax.jit(fn).lower(w, sched, cache, packed[4], noise).compile()
            r[f"compile_denoise_{steps}_s"] = time.perf_counter() - t0
            r[f"denoise_{steps}_ms"] = median_ms(lambda: den(w, sched, cache, packed[4], jnp.copy(noise)), (),
                                                 args.iters)
            if steps == 10 and args.trace:
                try:
                    r["trace"] = kernel_times(lambda: den(w, sched, cache, packed[4], jnp.copy(noise)), 5)
                    t = r["trace"]
                    print(f"{config.name} {kernels} trace: {t['kernels_per_call']:.0f} kernels, {t['kernel_ms']:.2f} "
                          f"ms in kernels of {t['wall_ms']:.2f} ms ({t['busy']:.0%} busy); lines "
                          f"{t['device_lines']}", flush=True)
                    for row in t["by_name"][:25]:
                        print(f"   {row['us_per_call']:9.1f} us  x{row['per_call']:6.1f}  {row['name'][:90]}",
                              flush=True)
                except Exception:
                    r["trace"] = traceback.format_exc()[-2000:]
                    print(r["trace"], flush=True)
            if steps == 10:
                actions[kernels] = np.asarray(den(w, sched, cache, packed[4], jnp.copy(noise)))
                counts = count_ops(den.as_text())
                body = {k: v for k, v in counts.items() if not k.startswith("ENTRY")}
                big = max(body.items(), key=lambda kv: kv[1]["fusion"] + kv[1]["custom-call"])
                r["loop_body_ops"] = big[1]
                r["kernels_per_step"] = big[1]["fusion"] + big[1]["custom-call"] + big[1]["copy"]
        r["per_step_ms"] = (r["denoise_10_ms"] - r["denoise_1_ms"]) / 9
        res[kernels] = r
        print(config.name, kernels, json.dumps(r), flush=True)
    res["pallas_vs_xla_rel_l2"] = rel_l2(actions["pallas"], actions["xla"])
    print(config.name, "pallas vs xla rel L2 (bf16, 10 steps):", res["pallas_vs_xla_rel_l2"], flush=True)
    out[config.name] = res
    sched = engine.schedule(10)
    fused = engine.executable("infer", 1, 10, cams, bucket)
    res["pallas"]["infer_10_ms"] = median_ms(lambda: fused(w, sched, *packed, jnp.copy(noise)), (), args.iters)
    print(config.name, "pallas infer 10 steps ms", res["pallas"]["infer_10_ms"], flush=True)


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


T0 = time.perf_counter()


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--iters", type=int, default=30)
    p.add_argument("--copies", type=int, default=16)
    p.add_argument("--engine-before-s", type=float, default=150.0, help="start an engine run only before this")
    p.add_argument("--xla-stages", action="store_true", help="also time each stage's XLA ops (the first run did)")
    p.add_argument("--skip-sweep", action="store_true")
    p.add_argument("--blocks", type=Path, default=None,
                   help="a previous run's JSON: its best_blocks for the engine runs (with --skip-sweep)")
    p.add_argument("--skip-parity", action="store_true", help="skip the f32 parity of the dummy presets")
    p.add_argument("--trace", action="store_true", help="sum the 10-step denoise's GPU kernels from a profiler trace")
    p.add_argument("--max-variants", type=int, default=100, help="block variants per stage in the sweep")
    p.add_argument("--presets", default="pi0_base,pi05_base", help="engine runs (the sweep uses the first)")
    p.add_argument("--out", type=Path, default=Path("kernels.json"))
    args = p.parse_args()
    dev = jax.devices()[0]
    out = {"device": dev.device_kind, "jax": jax.__version__, "xla_flags": os.environ.get("XLA_FLAGS", ""),
           "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
    print(out, flush=True)
    sections = [] if args.skip_parity else [("f32_parity", lambda: f32_parity(out))]
    blocks = ek.Blocks(**json.loads(args.blocks.read_text())["stages"]["best_blocks"]) if args.blocks else ek.Blocks()
    out["blocks_given"] = dataclasses.asdict(blocks)
    if not args.skip_sweep:
        def sweep():
            nonlocal blocks
            config = get_config(args.presets.split(",")[0], dtype="bfloat16")
            out["stages"], blocks = stages(config, args, jax.random.key(0))
        sections.append(("sweep", sweep))
    sections += [(name, lambda name=name: engine_runs(get_config(name, dtype="bfloat16"), args, blocks, out))
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
