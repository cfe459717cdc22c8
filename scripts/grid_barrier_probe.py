"""What a grid-wide barrier costs inside one Pallas (Triton) kernel, against a kernel boundary inside one XLA program.

The denoise step at B = 1 is about 9 kernels a layer, each paying a launch, a ramp-up and a tail; the last-arrival
epilogue (docs/BENCHMARKS.md, "Runs 16-18") was slower. A persistent kernel (one program per SM, phases separated
by grid-wide barriers) is the remaining way to fewer boundaries. This probe times the two synchronisations alone:

  barrier   one pallas_call, `programs` programs, each crossing R barriers: its threads meet (debug_barrier), one
            increments a global counter (acquire-release, GPU scope), then all spin on volatile loads of the counter
            until every program has arrived; per barrier = the slope over R
  kernels   R tiny pallas_calls in a chain inside one jit (each reads and rewrites a small array, so XLA keeps their
            order); per boundary = the slope over R

GPU only: interpret mode runs the programs one after another, so the first would spin for ever.

    python scripts/grid_barrier_probe.py --out barrier.json
"""

from __future__ import annotations

import argparse
import functools
import json
import time

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as plgpu

LANES = 128  # elements a program writes (one per thread of 4 warps)


def _barrier_kernel(count_ref, x_ref, o_ref, count_out_ref, *, rounds: int, programs: int):
    del count_out_ref  # aliased to count_ref
    pid = pl.program_id(0)
    cols = pl.ds(pid * LANES, LANES)
    v = x_ref[cols]

    def crossing(r, v):
        v = v + 1.0
        o_ref[cols] = v  # a store before the barrier, as a phase's output would be
        plgpu.debug_barrier()
        plgpu.atomic_add(count_ref, (0,), jnp.ones((), jnp.int32))
        target = (r + 1) * programs

        def seen(_):
            return jnp.max(plgpu.load(count_ref.at[pl.ds(0, 16)], volatile=True))

        jax.lax.while_loop(lambda c: c < target, seen, jnp.zeros((), jnp.int32))
        return v

    jax.lax.fori_loop(0, rounds, crossing, v)


def barrier_call(rounds: int, programs: int, warps: int):
    kernel = functools.partial(_barrier_kernel, rounds=rounds, programs=programs)
    out = (jax.ShapeDtypeStruct((programs * LANES,), jnp.float32), jax.ShapeDtypeStruct((16,), jnp.int32))
    call = pl.pallas_call(kernel, grid=(programs,), out_shape=out, input_output_aliases={0: 1},
                          compiler_params=plgpu.CompilerParams(num_warps=warps, num_stages=1),
                          name="grid_barrier")

    @jax.jit
    def run(x):
        return call(jnp.zeros((16,), jnp.int32), x)

    return run


def _tiny_kernel(x_ref, o_ref):
    cols = pl.ds(pl.program_id(0) * LANES, LANES)
    o_ref[cols] = x_ref[cols] + 1.0


def chain_call(kernels: int, programs: int, warps: int):
    call = pl.pallas_call(_tiny_kernel, grid=(programs,),
                          out_shape=jax.ShapeDtypeStruct((programs * LANES,), jnp.float32),
                          compiler_params=plgpu.CompilerParams(num_warps=warps, num_stages=1), name="tiny")

    @jax.jit
    def run(x):
        for _ in range(kernels):
            x = call(x)
        return x

    return run


def median_us(fn, x, iters: int) -> float:
    jax.block_until_ready(fn(x))
    times = []
    for _ in range(iters):
        t = time.perf_counter()
        jax.block_until_ready(fn(x))
        times.append(time.perf_counter() - t)
    return float(np.median(times) * 1e6)


def slope(xs, ys) -> float:
    return float(np.polyfit(np.asarray(xs, float), np.asarray(ys, float), 1)[0])


def measure(programs: int, barrier, chain, counts, x, iters: int) -> dict:
    """One grid size: the call with R barriers (barrier(R)) and with R kernels (chain(R)) for R in counts, each
    synchronisation's cost as the slope; printed and returned as a JSON row."""
    bar = [median_us(barrier(r), x, iters) for r in counts]
    kernels = [max(r, 1) for r in counts]
    links = [median_us(chain(r), x, iters) for r in kernels]
    row = {"programs": programs, "counts": counts, "barrier_call_us": bar, "chain_call_us": links,
           "per_barrier_us": slope(counts, bar), "per_kernel_us": slope(kernels, links)}
    print(f"programs {programs:4d}: barrier {row['per_barrier_us']:.3f} us, kernel boundary "
          f"{row['per_kernel_us']:.3f} us   (calls {[round(b, 1) for b in bar]} / "
          f"{[round(c, 1) for c in links]} us)", flush=True)
    return row


def parser(doc: str, programs: str, counts: str) -> argparse.ArgumentParser:
    """The options both barrier probes take: --out, --programs, --counts, --iters."""
    p = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True, help="JSON file to write")
    p.add_argument("--programs", default=programs, help="comma list of grid sizes (default: %(default)s)")
    p.add_argument("--counts", default=counts, help="comma list of barriers / kernels (default: %(default)s)")
    p.add_argument("--iters", type=int, default=50, help="timed calls per point (default: %(default)s)")
    return p


def main() -> None:
    p = parser(__doc__, "66,132,264", "0,50,200,800")
    p.add_argument("--warps", type=int, default=4, help="warps a program (default: %(default)s)")
    args = p.parse_args()
    if jax.default_backend() != "gpu":
        raise SystemExit("grid_barrier_probe needs a GPU: interpret mode runs programs in turn (the barrier hangs)")
    counts = [int(c) for c in args.counts.split(",")]
    dev = jax.devices()[0]
    sms = getattr(dev, "core_count", None)
    res = {"device": dev.device_kind, "sms": sms, "jax": jax.__version__, "warps": args.warps,
           "date": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()), "rows": []}
    for programs in (int(g) for g in args.programs.split(",")):
        x = jnp.zeros((programs * LANES,), jnp.float32)
        res["rows"].append(measure(programs, lambda r: barrier_call(r, programs, args.warps),
                                   lambda r: chain_call(r, programs, args.warps), counts, x, args.iters))
    with open(args.out, "w") as f:
        json.dump(res, f, indent=1)


if __name__ == "__main__":
    main()
