"""What a CUDA graph's launch costs the host, by the kind of kernel in it: one program per kind, a chain of N
kernels that XLA puts in one command buffer, and the host's time from the call to its return (the dispatch, not
the GPU's work), after the GPU has gone idle (as a robot's call finds it) and back to back. Kinds: XLA fusions
(`optimization_barrier` keeps each op a kernel of its own), cuBLAS GEMMs, XLA's Triton GEMMs (no cuBLAS fallback)
and Pallas (Triton) kernels, at SigLIP's GEMM shape (768 x 1152 x 1152, bf16). A GPU probe, not a test.

    python scripts/graph_launch_probe.py --kernels 16 --kernels 64 --out graph_launch_probe.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import pallas as pl

sys.path.insert(0, str(Path(__file__).resolve().parent))
from profile_engine import write_json  # noqa: E402

ROWS, WIDTH = 768, 1152
CUBLAS = {"xla_gpu_enable_triton_gemm": False}
TRITON = {"xla_gpu_enable_triton_gemm": True, "xla_gpu_cublas_fallback": False}


def _add_one(x_ref, o_ref):
    o_ref[...] = x_ref[...] + 1


def pallas_add(x):
    return pl.pallas_call(_add_one, out_shape=jax.ShapeDtypeStruct(x.shape, x.dtype),
                          grid=(x.shape[0] // 64, x.shape[1] // 128),
                          in_specs=[pl.BlockSpec((64, 128), lambda i, j: (i, j))],
                          out_specs=pl.BlockSpec((64, 128), lambda i, j: (i, j)),
                          interpret=jax.default_backend() == "cpu")(x)


def chain(kind: str, n: int):
    """fn(x, w) -> x after n kernels of this kind, each on the previous one's output."""
    def fn(x, w):
        for _ in range(n):
            if kind == "fusion":
                x = jax.lax.optimization_barrier(jnp.sin(x) * 0.5)
            elif kind == "pallas":
                x = pallas_add(x)
            else:
                x = (x @ w).astype(x.dtype)
        return x
    return fn


def dispatch_us(fn, args, iters: int, blocked: bool) -> float:
    times = []
    out = fn(*args)
    for _ in range(iters):
        if blocked:
            jax.block_until_ready(out)
        start = time.perf_counter()
        out = fn(*args)
        times.append(time.perf_counter() - start)
    jax.block_until_ready(out)
    return float(np.median(times) * 1e6)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--kernels", type=int, action="append", default=None,
                   help="kernels in each program's chain, repeatable (default: 1, 16 and 64)")
    p.add_argument("--iters", type=int, default=50, help="timed calls of each program (default: %(default)s)")
    p.add_argument("--out", type=Path, default=None, help="JSON of every row")
    args = p.parse_args()
    x = jax.random.normal(jax.random.PRNGKey(0), (ROWS, WIDTH), jnp.bfloat16)
    w = jax.random.normal(jax.random.PRNGKey(1), (WIDTH, WIDTH), jnp.bfloat16) * WIDTH**-0.5
    rows = []
    for n in args.kernels or [1, 16, 64]:
        for kind, options in (("fusion", None), ("pallas", None), ("cublas", CUBLAS), ("triton-gemm", TRITON)):
            compiled = jax.jit(chain(kind, n)).lower(x, w).compile(compiler_options=options)
            row = {"kind": kind, "kernels": n,
                   "after_idle_us": dispatch_us(compiled, (x, w), args.iters, True),
                   "back_to_back_us": dispatch_us(compiled, (x, w), args.iters, False)}
            rows.append(row)
            print(json.dumps(row), flush=True)
    write_json(args.out, {"rows": rows})


if __name__ == "__main__":
    main()
