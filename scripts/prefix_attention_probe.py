"""The prefix fill's attention alone: cuDNN's flash kernel (the engine's `ops.attention.fused`, a kv head's query
heads folded into rows) against the Pallas kernel (`ops.prefix_attention`) at several launches, at π0's and π0.5's
prefix shapes.

Each variant runs as a chain of `--layers` calls in one jit (the output is the next call's q, as the layers feed
each other), timed round-robin over the variants (one call each per round, the order reversed every other round),
so drift hits all alike; the figure is the chain's median over rounds divided by its length. Outputs are compared
with cuDNN's (relative L2 of one call, bf16).

    python scripts/prefix_attention_probe.py --batch 1,8 --blocks 64,64,4,2 --blocks 128,64,8,2 --out pa.json
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import jax.numpy as jnp
import numpy as np

from pi0_jax.ops import attention, prefix_attention

SHAPES = {"pi0": (816, 832, 816), "pi05": (968, 1024, 968)}   # (tokens, keys as the cache pads them, valid keys)


def variants(blocks: list[str]) -> dict:
    def cudnn(q, k, v, n):
        return attention.fused(q[:, :, None], k[:, :, None], v[:, :, None], scale=1.0, kv_len=n)[:, :, 0]

    out = {"cudnn": cudnn}
    for spec in blocks:
        b = prefix_attention.Blocks(*map(int, spec.split(",")))
        out[f"pallas-{spec}"] = lambda q, k, v, n, b=b: prefix_attention.attention(q, k, v, n, blocks=b)
    return out


def chain(fn, layers: int):
    @jax.jit
    def run(q, k, v, n):
        for _ in range(layers):
            q = fn(q, k, v, n)
        return q
    return run


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--batch", default="1,8", help="comma-separated batch sizes (default 1,8)")
    p.add_argument("--shapes", default="pi0,pi05", help=f"comma-separated prefix shapes of {sorted(SHAPES)}")
    p.add_argument("--heads", type=int, default=8, help="query heads a kv head (Gemma 2B: 8)")
    p.add_argument("--head-dim", type=int, default=256, help="head dim (Gemma 2B: 256)")
    p.add_argument("--blocks", action="append", default=[],
                   help="a Pallas launch Q,KV,WARPS,STAGES (repeatable; default 64,64,4,2)")
    p.add_argument("--layers", type=int, default=18, help="calls chained in one jit (default 18, Gemma 2B's layers)")
    p.add_argument("--rounds", type=int, default=30, help="timed rounds (default 30)")
    p.add_argument("--out", help="write the results as JSON here")
    args = p.parse_args()
    fns = variants(args.blocks or ["64,64,4,2"])
    results = []
    for shape in args.shapes.split(","):
        t, s, valid = SHAPES[shape]
        for batch in map(int, args.batch.split(",")):
            ks = jax.random.split(jax.random.PRNGKey(batch), 3)
            q = (jax.random.normal(ks[0], (batch, t * args.heads, args.head_dim)) * args.head_dim ** -0.5)
            k = jax.random.normal(ks[1], (batch, s, args.head_dim))
            v = jax.random.normal(ks[2], (batch, s, args.head_dim))
            q, k, v = (x.astype(jnp.bfloat16) for x in (q, k, v))
            n = jnp.full((batch,), valid, jnp.int32)
            ref = np.asarray(fns["cudnn"](q, k, v, n), np.float32)
            runs, err = {}, {}
            for name, fn in fns.items():
                try:
                    one = np.asarray(jax.jit(fn)(q, k, v, n), np.float32)
                    runs[name] = chain(fn, args.layers)
                    runs[name](q, k, v, n).block_until_ready()
                    err[name] = float(np.linalg.norm(one - ref) / np.linalg.norm(ref))
                except Exception as e:  # noqa: BLE001 - a launch that does not compile is a result too
                    print(f"{shape} B={batch} {name}: {type(e).__name__}: {str(e)[:300]}")
            times = {name: [] for name in runs}
            for i in range(args.rounds):
                for name in (list(runs) if i % 2 == 0 else list(runs)[::-1]):
                    t0 = time.perf_counter()
                    runs[name](q, k, v, n).block_until_ready()
                    times[name].append(time.perf_counter() - t0)
            flops = 4 * batch * t * args.heads * valid * args.head_dim
            for name in runs:
                us = float(np.median(times[name])) / args.layers * 1e6
                row = {"shape": shape, "batch": batch, "variant": name, "us_per_call": us,
                       "tflops": flops / us / 1e6, "rel_l2_vs_cudnn": err[name]}
                results.append(row)
                print(f"{shape:5s} B={batch:<3d} {name:22s} {us:8.2f} us  {row['tflops']:6.1f} TFLOP/s  "
                      f"rel L2 {err[name]:.2e}", flush=True)
    if args.out:
        env = {"device": str(jax.devices()[0].device_kind), "jax": jax.__version__}
        with open(args.out, "w") as f:
            json.dump({"env": env, "args": vars(args), "results": results}, f, indent=1)


if __name__ == "__main__":
    main()
