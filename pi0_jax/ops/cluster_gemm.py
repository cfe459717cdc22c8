"""A split-K GEMM whose K chunks meet in one thread-block cluster (Pallas Mosaic GPU, Hopper), with the residual epilogue.

The denoise step's GEMMs at B = 1 split K over several CTAs for bandwidth (`ops.expert_kernels`), and their f32
partials then took an XLA kernel of their own to sum, gate and add the residual: about 2 us and a launch a GEMM.
Here the CTAs of one output tile's K chunks form a cluster: each leaves its f32 accumulator in its shared memory,
the cluster meets at a barrier, the other CTAs store their accumulators into CTA 0's shared memory over the
cluster (asynchronous distributed shared memory stores), and CTA 0 sums them and writes x + gate * sum itself. One kernel, nothing through global memory but the output.

Numerics as `expert_kernels.matmul_residual`: the chunks' f32 sums in chunk order, rounded to the dtype, times the
gate (rounded), plus the residual (rounded), each op rounding where XLA's bf16 op would.

Axis legend: M rows, K contraction, N output columns, S the cluster's K chunks.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.experimental.pallas as pl
import jax.experimental.pallas.mosaic_gpu as plgpu
import jax.numpy as jnp
from jax import lax

from pi0_jax.ops.mosaic_gemm import ROWS, TK, _interpret


@dataclasses.dataclass(frozen=True)
class ClusterLaunch:
    """Output columns per cluster, K chunks (the cluster's CTAs, at most 8 on Hopper), TMA pipeline depth, and the
    contraction rows a pipeline step brings."""

    cols: int = 64
    splits: int = 4
    stages: int = 4
    tk: int = TK
    ablate: str = ""  # probe only: "launch" (no barrier, no reduction), "sync" (the barrier, no reduction)


def _transforms(minor, dt):
    size = jnp.dtype(dt).itemsize
    swizzle = plgpu.find_swizzle(minor * size * 8)
    return plgpu.TilingTransform((8, swizzle // size)), plgpu.SwizzleTransform(swizzle)


@functools.lru_cache(maxsize=None)
def _call(m: int, k: int, n: int, dtype, launch: ClusterLaunch, gated: bool, name: str):
    cols, splits, tk = launch.cols, launch.splits, launch.tk
    chunk = k // splits

    def pipeline(body, context):
        spec = functools.partial(plgpu.BlockSpec, memory_space=plgpu.SMEM)
        return plgpu.emit_pipeline_warp_specialized(
            body, grid=(chunk // tk,), memory_registers=40, wg_axis="wg", num_compute_wgs=1,
            max_concurrent_steps=launch.stages, compute_context=context,
            in_specs=[spec((ROWS, tk), lambda kk: (0, kk), transforms=_transforms(tk, dtype)),
                      spec((tk, cols), lambda kk: (kk, 0), transforms=_transforms(cols, dtype))])

    def kernel(y_gmem, w_gmem, x_gmem, g_gmem, o_gmem):
        j, i, s = lax.axis_index("n"), lax.axis_index("m"), lax.axis_index("s")
        ks, rows, out_cols = pl.ds(s * chunk, chunk), pl.ds(i * ROWS, ROWS), pl.ds(j * cols, cols)
        w_tile = w_gmem.at[ks, out_cols]

        def nothing(*_, **__):
            return None

        @functools.partial(
            pl.run_scoped, allocs=pipeline(nothing, nothing).get_allocations(y_gmem, w_tile),
            slots=plgpu.SMEM((max(1, splits - 1), ROWS, cols), jnp.float32, transforms=_transforms(cols, jnp.float32)),
            res_smem=plgpu.SMEM((ROWS, cols), dtype, transforms=_transforms(cols, dtype)),
            gate_smem=plgpu.SMEM((cols,), dtype),
            loaded=plgpu.Barrier(num_arrivals=1 + gated),
            arrived=plgpu.Barrier(num_arrivals=max(1, splits - 1)),
            met=plgpu.ClusterBarrier(collective_axes=("s",)),
            collective_axes="wg")
        def scope(allocs, slots, res_smem, gate_smem, loaded, arrived, met):
            def context(run):
                @pl.when(s == 0)
                def _():   # the residual (and gate) arrive while the GEMM runs
                    plgpu.copy_gmem_to_smem(x_gmem.at[rows, out_cols], res_smem, loaded)
                    if gated:
                        plgpu.copy_gmem_to_smem(g_gmem.at[out_cols], gate_smem, loaded)

                @functools.partial(pl.run_scoped, acc=plgpu.ACC((ROWS, cols), jnp.float32))
                def accumulate(acc):
                    run(acc)
                    total = acc[...]
                    if launch.ablate != "launch":
                        plgpu.barrier_arrive(met)   # every CTA's barriers are live before a peer stores into them
                        plgpu.barrier_wait(met)

                    if not launch.ablate:
                        @pl.when(s > 0)
                        def _():   # a K chunk's f32 sum into CTA 0's slot for it, by the cluster's async stores
                            plgpu.async_store_smem(total, slots.at[s - 1], arrived, cluster_idx=0, cluster_dim="s")

                    @pl.when(s == 0)
                    def _():
                        out = total
                        if splits > 1 and not launch.ablate:
                            plgpu.barrier_wait(arrived)
                            for t in range(splits - 1):
                                out = out + slots[t]
                        plgpu.barrier_wait(loaded)
                        z = out.astype(dtype)
                        if gated:
                            z = (z.astype(jnp.float32) * gate_smem[...].astype(jnp.float32)[None, :]).astype(dtype)
                        res_smem[...] = (res_smem[...].astype(jnp.float32) + z.astype(jnp.float32)).astype(dtype)
                        plgpu.commit_smem()
                        plgpu.copy_smem_to_gmem(res_smem, o_gmem.at[rows, out_cols])
                        plgpu.wait_smem_to_gmem(0)

            def step(_, y_smem, w_smem, acc):
                plgpu.wgmma(acc, y_smem, w_smem)
                plgpu.wgmma_wait(0)
                return acc

            pipeline(step, context)(y_gmem.at[rows, ks], w_tile, allocations=allocs)

    on_cpu = jax.default_backend() == "cpu"
    return plgpu.kernel(kernel, out_type=jax.ShapeDtypeStruct((m, n), dtype),
                        grid=(n // cols, m // ROWS), grid_names=("n", "m"), cluster=(splits,), cluster_names=("s",),
                        num_threads=2, thread_name="wg", kernel_name=name,
                        compiler_params=plgpu.CompilerParams(lowering_semantics=plgpu.LoweringSemantics.Warpgroup),
                        **({"interpret": _interpret()} if on_cpu else {}))


def matmul_residual(y, w, x, gate=None, launch: ClusterLaunch = ClusterLaunch(), name: str = "cluster_gemm"):
    """x + (y @ w) [* gate]: y (M, K), w (K, N), x (M, N) in one dtype, M a multiple of 64; gate None or (N,)."""
    m, k = y.shape
    n = w.shape[1]
    g = jnp.zeros((n,), x.dtype) if gate is None else gate.astype(x.dtype)
    return _call(m, k, n, x.dtype, launch, gate is not None, name)(y, w, x, g)
