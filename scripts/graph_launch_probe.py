"""What a program in one CUDA graph costs the host to dispatch, by the kind of kernel in it: one program per kind, a
chain of N kernels that XLA puts in one command buffer, and the host's time from the call to its return (the
dispatch, not the GPU's work), after the GPU has gone idle (as a robot's call finds it) and back to back. Each call
keeps the previous output alive, so XLA also updates the graph's nodes whose buffers moved; most of the time is
jax's, PjRt's and XLA's work before the graph's launch (`launch_lead_probe.py`). Kinds: XLA fusions (`optimization_barrier` keeps
each op a kernel of its own), cuBLAS GEMMs, XLA's Triton GEMMs (no cuBLAS fallback) and Pallas (Triton) kernels,
at SigLIP's GEMM shape (768 x 1152 x 1152, bf16); `--graph` compiles each with XLA's options for the command
buffer's form (`GRAPHS`). A GPU probe, not a test. What the driver alone takes to launch a graph of as many
kernels: `cuda_graph_launch.cu` and `torch_graph_launch.py`.

    python scripts/graph_launch_probe.py --kernels 16 --kernels 64 --out graph_launch_probe.json
    python scripts/graph_launch_probe.py --kernels 128 --kind fusion --graph default --graph serialize-nopdl
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
KINDS = {"fusion": {}, "pallas": {}, "cublas": CUBLAS, "triton-gemm": TRITON}   # each kind's XLA options
# the command buffer's form: without PDL's programmatic edges, its commands in one order (a straight line), both, or
# XLA's concurrent regions (jaxlib 0.11.2 has no `xla_gpu_experimental_enable_command_buffer_on_thunks`)
GRAPHS = {"default": {}, "nopdl": {"xla_gpu_enable_pdl": False},
          "serialize": {"xla_gpu_command_buffer_scheduling_mode": "SERIALIZE"},
          "serialize-nopdl": {"xla_gpu_command_buffer_scheduling_mode": "SERIALIZE", "xla_gpu_enable_pdl": False},
          "concurrent-region": {"xla_gpu_graph_enable_concurrent_region": True}}


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
    p.add_argument("--graph", action="append", choices=list(GRAPHS), default=None,
                   help="the command buffer's XLA options, repeatable (default: default)")
    p.add_argument("--kind", action="append", choices=list(KINDS), default=None,
                   help="repeatable (default: all)")
    p.add_argument("--out", type=Path, default=None, help="JSON of every row")
    args = p.parse_args()
    x = jax.random.normal(jax.random.PRNGKey(0), (ROWS, WIDTH), jnp.bfloat16)
    w = jax.random.normal(jax.random.PRNGKey(1), (WIDTH, WIDTH), jnp.bfloat16) * WIDTH**-0.5
    rows = []
    for n in args.kernels or [1, 16, 64]:
        for kind, graph in ((k, g) for k in args.kind or list(KINDS) for g in args.graph or ["default"]):
            try:
                compiled = jax.jit(chain(kind, n)).lower(x, w).compile(
                    compiler_options={**KINDS[kind], **GRAPHS[graph]} or None)
            except Exception as e:   # an option this jaxlib does not define
                print(json.dumps({"kind": kind, "kernels": n, "graph": graph, "error": str(e)[:300]}), flush=True)
                continue
            row = {"kind": kind, "kernels": n, "graph": graph,
                   "after_idle_us": dispatch_us(compiled, (x, w), args.iters, True),
                   "back_to_back_us": dispatch_us(compiled, (x, w), args.iters, False)}
            rows.append(row)
            print(json.dumps(row), flush=True)
    write_json(args.out, {"rows": rows})


if __name__ == "__main__":
    main()
