"""The XLA expert's denoise attention at B = 8 alone (π0 full size, a kv head's 8 query heads folded into 448 rows an
element, an 832-key prefix cache and the 64-key suffix): the Triton kernel, the Mosaic GPU kernel
(`ops.mosaic_attention`) at several key splits, and jax's own Mosaic GPU flash attention
(`jax.experimental.pallas.ops.gpu.attention_mgpu`: a TMA producer warpgroup and two wgmma warpgroups, no masks, f16)
on the same shapes with its keys split by the batch. Kernel µs per call from a jax.profiler trace
(`profile_engine.kernel_times`). A GPU probe (Hopper), not a test.

    python scripts/attention_probe.py --out attention_probe.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys

import jax
import jax.numpy as jnp

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from profile_engine import kernel_times  # noqa: E402

from pi0_jax.ops import expert_attention as ea  # noqa: E402
from pi0_jax.ops import expert_kernels as ek  # noqa: E402

ROWS, PREFIX, SUFFIX, HEAD_DIM = 448, 832, 64, 256   # π0 at B = 8: 51 x 8 folded rows in whole 64-blocks


def timed(name: str, fn, *args, calls: int) -> dict:
    f = jax.jit(fn)
    kt = kernel_times(lambda: f(*args), calls=calls)
    rows = {r["name"]: round(r["us_per_call"], 2) for r in kt["by_name"]}
    print(f"{name:36s} {kt['kernel_ms'] * 1e3:7.2f} us in kernels  {rows}", flush=True)
    return {"kernel_us": kt["kernel_ms"] * 1e3, "kernels": rows}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--batch", type=int, default=8, help="elements (default: 8)")
    ap.add_argument("--calls", type=int, default=30, help="traced calls of each variant (default: 30)")
    ap.add_argument("--out", default="attention_probe.json", help="JSON results (default: attention_probe.json)")
    args = ap.parse_args()
    from jax.experimental.pallas.ops.gpu import attention_mgpu

    b, bf = args.batch, jnp.bfloat16
    ks = jax.random.split(jax.random.key(0), 6)
    q = (jax.random.normal(ks[0], (b * ROWS, HEAD_DIM)) * 0.06).astype(bf)
    kv = jax.random.normal(ks[1], (b * SUFFIX, 2 * HEAD_DIM)).astype(bf)
    ck, cv = (jax.random.normal(k, (b * PREFIX, HEAD_DIM)).astype(bf) for k in ks[2:4])
    pmask = jnp.ones((b, PREFIX), jnp.int32)
    smask = (jnp.arange(SUFFIX)[None] < 51).astype(jnp.int32).repeat(b * ROWS, 0)   # π0's action rows
    base = ek.blocks_at(b)
    variants = {"triton (the default)": base, "triton, 2 parts": dataclasses.replace(base, kv_splits=1),
                "mosaic, 3 parts": dataclasses.replace(base, mosaic_attention=True),
                "mosaic, 2 parts": dataclasses.replace(base, mosaic_attention=True, kv_splits=1),
                "mosaic, 14 parts": dataclasses.replace(base, mosaic_attention=True, kv_splits=13)}
    res = {"device": jax.devices()[0].device_kind, "jax": jax.__version__, "batch": b}
    for name, blocks in variants.items():
        def attend(q, kv, ck, cv, pm, sm, blocks=blocks):
            return ea.attention(q, ck, cv, pm, sm, batch=b, num_heads=1, num_kv_heads=1, blocks=blocks, kv=kv)
        res[name] = timed(name, attend, q, kv, ck, cv, pmask, smask, calls=args.calls)
    for splits in (1, 2, 7):   # its keys split over the batch axis; 128 query rows a CTA (512 an element)
        keys = (PREFIX + SUFFIX) // splits
        q4 = jnp.full((b * splits, 512, 1, HEAD_DIM), 0.01, jnp.float16)
        k4, v4 = (jax.random.normal(k, (b * splits, keys, 1, HEAD_DIM)).astype(jnp.float16) for k in ks[4:])
        cfg = attention_mgpu.TuningConfig(block_q=64, block_kv=64, max_concurrent_steps=2)
        res[f"jax attention_mgpu, {splits} splits"] = timed(
            f"jax attention_mgpu, {splits} splits", lambda q4, k4, v4: attention_mgpu.attention(q4, k4, v4, cfg),
            q4, k4, v4, calls=args.calls)
    with open(args.out, "w") as f:
        json.dump(res, f, indent=1)


if __name__ == "__main__":
    main()
