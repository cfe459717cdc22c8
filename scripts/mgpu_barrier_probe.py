"""A grid-wide barrier inside one Pallas Mosaic GPU kernel, against a Mosaic GPU kernel boundary.

Session 30 measured why the denoise step costs what it does: past its first microseconds a GEMM kernel streams the
weights at 70-90 % of the bandwidth, and each kernel pays 3-4 us whatever its work (`mgpu_gemm_probe.py --k-sweep`,
docs/BENCHMARKS.md). A persistent kernel whose phases are TMA pipelines could issue a phase's first weight copies
before it waits for the previous phase, which Triton's register loads could not (`persistent_probe.py`). That needs a
grid barrier in Mosaic GPU. This probe builds one from a GPU-scope semaphore in global memory: every CTA signals it
once a round and waits, without taking it, until it holds (round + 1) x CTAs; after the last round every CTA signals
once more and CTA 0 takes the whole count back (the semaphore ends at zero). Timed as the slope over R rounds in one
call, against a chain of R of the same kernel with no round (a kernel boundary each) in one jit.

GPU only (Hopper), like `grid_barrier_probe.py`. Session 30's version hung (280 s on an H100, `c1916d7`): it took
the semaphore from `scratch_types`, which gives each CTA its own, so no count ever reached (round + 1) x CTAs. A
semaphore shared by the grid comes from `pl.get_global` (JAX's Pallas Mosaic GPU reference, "Global (grid-wide)
allocations"). With it (session 31): 1.36-1.51 us a barrier on an H100 at 66 and 132 CTAs, against 6.7 us for a
boundary between two of these kernels (on an H200 with XLA's command buffers off: 1.35 against 12.7 us), whose every
call also syncs the grid once to reset the semaphore.

    python scripts/mgpu_barrier_probe.py --out mgpu_barrier.json
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import jax
import jax.experimental.pallas as pl
import jax.experimental.pallas.mosaic_gpu as plgpu
import jax.numpy as jnp
from jax import lax

sys.path.insert(0, str(Path(__file__).parent))
from grid_barrier_probe import measure, parser  # noqa: E402


def barrier_kernel(rounds: int, programs: int):
    def kernel(o_gmem):
        del o_gmem   # nothing written: the rounds are the work
        sem = pl.get_global(plgpu.SemaphoreType.REGULAR)   # one for the grid (scratch_types' is one per CTA)

        def crossing(r, carry):
            plgpu.semaphore_signal(sem, 1, memory_scope="gpu")
            plgpu.semaphore_wait(sem, (r + 1) * programs, decrement=False, memory_scope="gpu")
            return carry

        lax.fori_loop(0, rounds, crossing, jnp.int32(0))
        plgpu.semaphore_signal(sem, 1, memory_scope="gpu")

        @pl.when(lax.axis_index("b") == 0)
        def _():
            plgpu.semaphore_wait(sem, (rounds + 1) * programs, decrement=True, memory_scope="gpu")

    return plgpu.kernel(kernel, out_type=jax.ShapeDtypeStruct((16,), jnp.int32), grid=(programs,),
                        grid_names=("b",), kernel_name="mgpu_barrier",
                        compiler_params=plgpu.CompilerParams(lowering_semantics=plgpu.LoweringSemantics.Warpgroup))


def barrier_call(rounds: int, programs: int):
    call = barrier_kernel(rounds, programs)
    return jax.jit(lambda x: (x, call()))   # the kernel's output returned, so XLA keeps the kernel


def chain_call(kernels: int, programs: int):
    call = barrier_kernel(0, programs)
    return jax.jit(lambda x: (x, [call() for _ in range(kernels)]))


def main() -> None:
    args = parser(__doc__, "66,132", "0,25,100,200").parse_args()
    if jax.default_backend() != "gpu":
        raise SystemExit("mgpu_barrier_probe needs a GPU (Hopper)")
    counts = [int(c) for c in args.counts.split(",")]
    res = {"device": jax.devices()[0].device_kind, "jax": jax.__version__,
           "date": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()), "rows": []}
    x = jnp.zeros((), jnp.int32)
    for programs in (int(g) for g in args.programs.split(",")):
        res["rows"].append(measure(programs, lambda r: barrier_call(r, programs),
                                   lambda r: chain_call(r, programs), counts, x, args.iters))
    with open(args.out, "w") as f:
        json.dump(res, f, indent=1)


if __name__ == "__main__":
    main()
