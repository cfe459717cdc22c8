"""The denoise step's GEMM kernels at B = 1 with bf16 weights against e4m3 weights widened inside the kernel
(weight-only FP8: half the bytes each GEMM streams). π0's expert shapes, 64 rows; each program runs a GEMM on
`--layers` weight copies in a chain (each input depends on the previous product, as the step's layers do), so the
weights stream from HBM, not L2. Kernel µs per GEMM from a jax.profiler trace (`profile_engine.kernel_times`), and
each e4m3 chain's output against the same chain at the engine's launch on the weights widened to bf16 first (the
kernel's own inputs). A GPU probe (Hopper), not a test.

    python scripts/fp8_expert_probe.py --out fp8_expert_probe.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from profile_engine import kernel_times, write_json  # noqa: E402

from pi0_jax.ops import expert_kernels as ek  # noqa: E402
from pi0_jax.ops.formats import E4M3  # noqa: E402

ROWS, WIDTH = 64, 1024
# name: (K, N, the engine's launch, other launches to try with e4m3 weights)
SHAPES = {
    "qkv": (1024, 2560, ek.Gemm(128, 4), (ek.Gemm(128, 8), ek.Gemm(256, 4), ek.Gemm(128, 4, 4))),
    "out": (2048, 1024, ek.Gemm(64, 4), (ek.Gemm(64, 8), ek.Gemm(128, 4), ek.Gemm(32, 4))),
    "gate_up": (1024, 8192, ek.Gemm(128, 4, 1), (ek.Gemm(128, 2, 1), ek.Gemm(256, 4, 1), ek.Gemm(128, 4, 3))),
    "down": (4096, 1024, ek.Gemm(64, 8), (ek.Gemm(64, 16), ek.Gemm(128, 8), ek.Gemm(64, 8, 4))),
}


def chain(name, gemm, mosaic_geglu=False):
    """fn(x, ws) -> the last product: each layer's GEMM on the previous one's rows (a cheap dependency)."""
    blocks = ek.Blocks() if mosaic_geglu else dataclasses.replace(ek.Blocks(), mosaic_mlp=None)

    def fn(x, mods, ws):
        out = None
        for w in ws:
            if name == "gate_up":
                out = ek.norm_geglu(x, mods, 0, False, w, width=WIDTH,
                                    blocks=dataclasses.replace(blocks, mlp=gemm))
            else:
                parts, _, _ = ek.matmul_partials(x, w, mods, 0, scaled=name == "qkv", gemm=gemm, blocks=blocks,
                                                 name=f"expert_{name}")
                out = sum(list(parts))
            x = x + (out[0, 0] * 0).astype(x.dtype)   # the next layer waits for this one
        return out

    return jax.jit(fn)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--layers", type=int, default=18, help="weight copies a program (default: %(default)s)")
    p.add_argument("--calls", type=int, default=20, help="traced calls per variant (default: %(default)s)")
    p.add_argument("--gemm", action="append", choices=list(SHAPES), default=None, help="repeatable (default: all)")
    p.add_argument("--out", type=Path, default=None, help="JSON of every row")
    args = p.parse_args()
    rows = []
    key = jax.random.PRNGKey(0)
    for name in args.gemm or list(SHAPES):
        k_dim, n, launch, others = SHAPES[name]
        x = jax.random.normal(key, (ROWS, WIDTH if name != "out" and name != "down" else k_dim), jnp.bfloat16)
        if name in ("out", "down"):
            x = x[:, :k_dim]
        mods = jnp.zeros((2, x.shape[1]), jnp.bfloat16)
        w32 = [jax.random.normal(jax.random.fold_in(key, i), (k_dim, n), jnp.float32) * 0.02
               for i in range(args.layers)]
        bf = [w.astype(jnp.bfloat16) for w in w32]
        scale = [jnp.max(jnp.abs(w), axis=0) / 448.0 for w in w32]
        q8 = [(w / s).astype(E4M3) for w, s in zip(w32, scale)]
        variants = [("bf16", launch, bf, False), *(("e4m3", g, q8, False) for g in (launch, *others))]
        if name == "gate_up":
            variants.insert(0, ("bf16-mosaic", launch, bf, True))
        ref = None
        for dtype, gemm, ws, mosaic in variants:
            fn = chain(name, gemm, mosaic)
            try:
                out = np.asarray(jax.block_until_ready(fn(x, mods, ws)), np.float32)
            except Exception as e:   # a launch Triton cannot compile
                rows.append({"gemm": name, "weights": dtype, "launch": dataclasses.asdict(gemm), "error": str(e)[:300]})
                print(json.dumps(rows[-1]), flush=True)
                continue
            t = kernel_times(lambda: fn(x, mods, ws), args.calls)
            mine = [r for r in t["by_name"] if r["name"].startswith("expert_")]
            row = {"gemm": name, "weights": dtype, "mosaic": mosaic, "launch": dataclasses.asdict(gemm),
                   "gemm_us": sum(r["us_per_call"] for r in mine) / args.layers,
                   "layer_us": t["kernel_ms"] * 1e3 / args.layers, "kernels_per_layer": t["kernels_per_call"] / args.layers,
                   "mb_per_gemm": k_dim * n * (1 if dtype == "e4m3" else 2) / 1e6}
            if dtype == "e4m3":   # against the same chain on the widened weights in bf16 (the kernel's own inputs)
                ref = np.asarray(chain(name, launch)(x, mods, [q.astype(jnp.bfloat16) for q in q8]), np.float32)
                row["max_abs_vs_widened"] = float(np.max(np.abs(out - ref)))
            rows.append(row)
            print(json.dumps(row), flush=True)
    write_json(args.out, {"rows": rows})


if __name__ == "__main__":
    main()
