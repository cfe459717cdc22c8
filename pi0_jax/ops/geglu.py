"""The Gemma MLP's gate/up GEMM with GeGLU in its epilogue: one Pallas Mosaic GPU kernel (Hopper: wgmma, TMA,
warp-specialised, persistent), for the prefix fill at every batch on a GPU.

XLA runs x @ [gate | up] in cuBLAS, which writes gate and up (2 x M x F in the activation dtype), then a fusion reads
both back to write GELU-tanh(gate) * up. This kernel keeps a gate and an up accumulator for the same hidden units in
registers and writes only the product: one pass over 2 x M x F bf16 less per layer (docs/BENCHMARKS.md, "GeGLU").

A CTA runs two compute warpgroups over 2 x TILE_M rows; each holds gate and up accumulators of TILE_M x TILE_N f32
and, per K step of TILE_K, issues one wgmma for each against the two weight tiles, which a producer warpgroup streams
into shared memory by TMA (STAGES deep). CTAs walk the output tiles in a snake order of SNAKE row blocks.

Numerics as `pi0_jax.engine.layers._mlp`: each accumulator is rounded to the activation dtype (as XLA's GEMM output
is), GELU-tanh and the product run in f32 and are rounded once. XLA's fusion rounds after each bf16 op, so the two
agree to bf16 rounding, not bit for bit. Activations bf16 only (wgmma would take f32 as tf32).
"""

from __future__ import annotations

import functools

import jax
import jax.experimental.pallas as pl
import jax.experimental.pallas.mosaic_gpu as plgpu
import jax.numpy as jnp
import numpy as np
from jax import lax

# H200, π0.5's prefix MLP (K = 2048, F = 16384): 11.02 against XLA's 11.31 ms at M = 51200, 31.26 against 33.64 ms
# at M = 143616 (scripts/geglu_probe.py)
TILE_M, TILE_N, TILE_K, STAGES, SNAKE = 64, 128, 64, 4, 8

# tests set a Mosaic GPU `InterpretGPUParams` here to run the kernel on a CPU (slow: a check of its indexing)
INTERPRET = None


def applies(x_dtype, w, platform: str | None = None) -> bool:
    """Whether the kernel takes this GEMM: one GPU (or the interpreter), bf16 activations and a plain bf16 (K, 2F)
    weight (not FP8 or a calibration tap: they keep XLA's path) whose K and F tile. With several devices a program
    may be partitioned, and XLA's partitioner would gather a custom call's operands onto every device: XLA's path."""
    one_gpu = (platform or jax.default_backend()) == "gpu" and jax.device_count() == 1
    on_gpu = one_gpu or INTERPRET is not None
    plain = isinstance(w, jax.Array) and w.ndim == 2 and w.dtype == jnp.bfloat16
    return (on_gpu and plain and jnp.dtype(x_dtype) == jnp.bfloat16 and w.shape[0] % TILE_K == 0
            and w.shape[1] % (2 * TILE_N) == 0)


def _geglu(g, u, dtype):
    g, u = (a.astype(dtype).astype(jnp.float32) for a in (g, u))
    c = 0.5 * (1.0 + jnp.tanh(np.float32(np.sqrt(2 / np.pi)) * (g + np.float32(0.044715) * g * g * g)))
    return (g * c * u).astype(dtype)


def geglu_matmul(x, w):
    """x (..., K) @ w (K, 2F) [gate | up] -> GELU-tanh(gate) * up (..., F). Rows are padded to the CTA's 2 x TILE_M
    (and the product cut back) when they do not tile."""
    lead, k = x.shape[:-1], x.shape[-1]
    f = w.shape[1] // 2
    rows = int(np.prod(lead))
    x = x.reshape(rows, k)
    padded = -(-rows // (2 * TILE_M)) * 2 * TILE_M
    if padded != rows:
        x = jnp.pad(x, ((0, padded - rows), (0, 0)))
    out = _call(padded, k, f, x.dtype)(x, w)
    return out[:rows].reshape(*lead, f)


def _call(m, k, f, dtype):
    cta_m = 2 * TILE_M
    m_iters, n_iters, k_iters = m // cta_m, f // TILE_N, k // TILE_K
    item = jnp.dtype(dtype).itemsize

    def transforms(minor):   # TMA tiles of 8 rows, swizzled by the row's width in bytes (at most 128)
        swizzle = plgpu.find_swizzle(minor * item * 8)
        return plgpu.TilingTransform((8, swizzle // item)), plgpu.SwizzleTransform(swizzle)

    def pipeline(body, context):
        spec = functools.partial(plgpu.BlockSpec, memory_space=plgpu.SMEM)
        return plgpu.emit_pipeline_warp_specialized(
            body, grid=(k_iters,), memory_registers=40, wg_axis="wg", num_compute_wgs=2,
            max_concurrent_steps=STAGES, compute_context=context,
            in_specs=[spec((cta_m, TILE_K), lambda kk: (0, kk), transforms=transforms(TILE_K)),
                      spec((TILE_K, TILE_N), lambda kk: (kk, 0), transforms=transforms(TILE_N)),
                      spec((TILE_K, TILE_N), lambda kk: (kk, 0), transforms=transforms(TILE_N))])

    def kernel(x_gmem, w_gmem, out_gmem):
        def nothing(*_, **__):
            return None

        @functools.partial(pl.run_scoped, allocs=pipeline(nothing, nothing).get_allocations(x_gmem, w_gmem, w_gmem),
                           out_smem=plgpu.SMEM((2, TILE_M, TILE_N), dtype, transforms=transforms(TILE_N)),
                           collective_axes="wg")
        def scope(allocs, out_smem):
            wg = lax.axis_index("wg")
            wg_rows = pl.ds(wg * TILE_M, TILE_M)

            @plgpu.nd_loop((m_iters * n_iters,), collective_axes="cluster_grid")
            def tiles(info):
                mi, ni = plgpu.planar_snake(info.index[0], (m_iters, n_iters), 0, SNAKE)
                rows, cols = pl.ds(mi * cta_m, cta_m), pl.ds(ni * TILE_N, TILE_N)

                def context(run):
                    @functools.partial(pl.run_scoped, acc_g=plgpu.ACC((TILE_M, TILE_N), jnp.float32),
                                       acc_u=plgpu.ACC((TILE_M, TILE_N), jnp.float32))
                    def accumulate(acc_g, acc_u):
                        run((acc_g, acc_u))
                        y = _geglu(acc_g[...], acc_u[...], dtype)
                        plgpu.wait_smem_to_gmem(0, wait_read_only=True)   # the previous tile's store has read it
                        out_smem[wg] = y
                        plgpu.commit_smem()
                        plgpu.copy_smem_to_gmem(out_smem.at[wg], out_gmem.at[rows, cols].at[wg_rows])

                def step(_, a_smem, g_smem, u_smem, accs):
                    plgpu.wgmma(accs[0], a_smem.at[wg_rows], g_smem)
                    plgpu.wgmma(accs[1], a_smem.at[wg_rows], u_smem)
                    plgpu.wgmma_wait(0)
                    return accs

                pipeline(step, context)(x_gmem.at[rows, :], w_gmem.at[:, cols],
                                        w_gmem.at[:, pl.ds(f + ni * TILE_N, TILE_N)], allocations=allocs)
        plgpu.wait_smem_to_gmem(0, wait_read_only=True)

    sms = 2 if INTERPRET is not None else jax.devices()[0].core_count
    return plgpu.kernel(kernel, out_type=jax.ShapeDtypeStruct((m, f), dtype), grid=(sms,),
                        grid_names=("cluster_grid",), num_threads=3, thread_name="wg",
                        compiler_params=plgpu.CompilerParams(lowering_semantics=plgpu.LoweringSemantics.Warpgroup),
                        **({"interpret": INTERPRET} if INTERPRET is not None else {}))
