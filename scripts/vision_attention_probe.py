"""SigLIP's attention alone at the tower's shape (π0 and π0.5 So400m: 16 heads of 72, 256 tokens an image, 3 images
at B = 1): the Pallas kernel (`ops.vision_attention`) at several block settings, against cuDNN's fused attention on
the same q/k/v (three copies first, as the engine's cuDNN path) and XLA's. Kernel µs per call from a jax.profiler
trace (`profile_engine.kernel_times`), and each output's largest difference from XLA's in f32 of the same bf16
inputs. A GPU probe, not a test.

    python scripts/vision_attention_probe.py --images 3 --blocks 128,64,4,2 --blocks 64,256,4,1 --out va.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import einops
import jax
import jax.numpy as jnp
import numpy as np
from flax import linen as nn

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from profile_engine import kernel_times, write_json  # noqa: E402

from pi0_jax.ops import attention as ops_attention, vision_attention  # noqa: E402

HEADS, HEAD_DIM, TOKENS = 16, 72, 256
DEFAULT_BLOCKS = ("128,64,4,2", "64,64,4,2", "64,128,4,2", "64,256,4,1", "64,256,8,1", "32,256,4,1", "32,256,2,1",
                  "32,128,4,2", "16,256,4,1", "128,256,8,1")


def split(qkv, images):
    q, k, v = einops.rearrange(qkv.reshape(images, TOKENS, -1), "B T (three N H) -> three B T N H", three=3, N=HEADS)
    return q, k, v


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--images", type=int, action="append", default=None, help="repeatable (default: 3)")
    p.add_argument("--blocks", action="append", default=None, metavar="Q,KV,WARPS,STAGES",
                   help=f"repeatable Pallas block settings (default: {' '.join(DEFAULT_BLOCKS)})")
    p.add_argument("--calls", type=int, default=30, help="traced calls per variant (default: %(default)s)")
    p.add_argument("--out", type=Path, default=None, help="JSON of every row")
    args = p.parse_args()
    rows = []
    for images in args.images or [3]:
        qkv = jax.random.normal(jax.random.PRNGKey(images), (images * TOKENS, 3 * HEADS * HEAD_DIM), jnp.bfloat16)
        q, k, v = split(qkv, images)
        ref = np.asarray(nn.dot_product_attention(*(a.astype(jnp.float32) for a in (q, k, v))), np.float32)
        ref = ref.reshape(images * TOKENS, -1)
        fns = {"xla": jax.jit(lambda x: nn.dot_product_attention(*split(x, images), dtype=jnp.bfloat16)),
               "cudnn": jax.jit(lambda x: ops_attention.fused(*split(x, images)))}
        for spec in args.blocks or DEFAULT_BLOCKS:
            bq, bkv, warps, stages = (int(s) for s in spec.split(","))
            blocks = vision_attention.Blocks(q=bq, kv=bkv, num_warps=warps, num_stages=stages)
            fns[f"pallas-{spec}"] = jax.jit(lambda x, b=blocks: vision_attention.attention(
                x, images=images, num_heads=HEADS, blocks=b))
        for name, fn in fns.items():
            try:
                out = np.asarray(jax.block_until_ready(fn(qkv)), np.float32).reshape(images * TOKENS, -1)
            except Exception as e:   # a setting Triton cannot compile (registers, shared memory)
                rows.append({"images": images, "variant": name, "error": str(e)[:300]})
                print(json.dumps(rows[-1]), flush=True)
                continue
            t = kernel_times(lambda: fn(qkv), args.calls)
            rows.append({"images": images, "variant": name, "kernel_us": t["kernel_ms"] * 1e3,
                         "kernels_per_call": t["kernels_per_call"], "wall_ms": t["wall_ms"],
                         "max_abs_vs_f32": float(np.max(np.abs(out - ref))),
                         "top": t["by_name"][:4]})
            print(json.dumps({k: rows[-1][k] for k in ("images", "variant", "kernel_us", "kernels_per_call",
                                                        "max_abs_vs_f32")}), flush=True)
    write_json(args.out, {"rows": rows})


if __name__ == "__main__":
    main()
