"""SigLIP's residual add and the LayerNorm after it as one Pallas kernel (Triton on GPU, interpret mode on CPU).

XLA runs x + (y + b), y a Dense's product and b its bias, and the LayerNorm after it as two or three kernels: the
statistics (with the adds), the normalisation (which reads the rows again), and a bias add of its own where the
Dense is a Triton GEMM. This kernel holds a block of rows in registers from load to store: one launch, x and y read
once, x + (y + b) and its LayerNorm written once. Triton's blocks are powers of two, so a width that is not one
(So400m's 1152) is walked in equal power-of-two column chunks (9 x 128). On the tower it measured 1.5-3 % faster
with XLA's GEMMs and no different with cuBLAS's (docs/BENCHMARKS.md, "SigLIP's LayerNorm as a kernel").

Numerics as `pi0_jax.engine.vision.add_norm`'s XLA path: each add rounded to the dtype, f32 statistics in two
passes (the mean, then the mean of squared deviations), eps inside the rsqrt, scale and bias applied in f32, one
rounding to the output dtype. Only the order of the sums differs (chunk by chunk here), so the two agree to f32
rounding.

Between FP8 GEMMs (`engine.vision`) the kernel also takes the residual's raw product with its f32 output scale and
writes the next GEMM's e4m3 input, so neither needs a pass of its own. Triton divides f32 approximately (within 2
ulp), so a value that close to a rounding boundary of e4m3 may round the other way: rare, one e4m3 step.

Axis legend: R rows, D width.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import pallas as pl
from jax.experimental.custom_partitioning import custom_partitioning

from pi0_jax.ops.formats import E4M3, E4M3_MAX
from pi0_jax.ops.pallas_base import call, fit, row_shardings


@dataclasses.dataclass(frozen=True)
class Blocks:
    """Rows per program and the widest column chunk (powers of two, shrunk to divide R and D), Triton's warps.
    Defaults: the fastest of six settings at 3, 24 and 192 images (H100, docs/BENCHMARKS.md)."""

    rows: int = 8
    cols: int = 128
    num_warps: int = 8


def _kernel(x_ref, *refs, br, bc, chunks, eps, residual, scaled, dtype, rows):
    """Program i: rows block i, the whole width in `chunks` column chunks held in registers between the statistics
    and the store. The chunks are summed elementwise first, so each statistic is one reduction across threads.
    rows: (the scale's row, the bias's row, the residual's bias row) of the vector tables."""
    f_ref, fv_ref, fs_ref, vec_ref, act_ref, *outs = refs if residual else (None, None, None, *refs)
    scale_row, bias_row, f_row = rows
    block = pl.ds(pl.program_id(0) * br, br)
    cols = [pl.ds(c * bc, bc) for c in range(chunks)]

    def vector(ref, row, c):   # (1, bc) in f32
        return ref[pl.ds(row, 1), c].astype(jnp.float32)

    scale = [vector(vec_ref, scale_row, c) for c in cols]
    bias = [vector(vec_ref, bias_row, c) for c in cols]
    xs = [x_ref[block, c] for c in cols]
    if residual:   # x + (f [* f's scale] + f's bias), each op rounded to x's dtype as XLA's; stored, and normalised
        xt = x_ref.dtype

        def product(c):
            y = f_ref[block, c].astype(jnp.float32)
            return (y * fs_ref[c][None, :]).astype(xt).astype(jnp.float32) if scaled else y

        f = [(product(c) + vector(fv_ref, f_row, c).astype(xt).astype(jnp.float32)).astype(xt) for c in cols]
        xs = [(x.astype(jnp.float32) + y.astype(jnp.float32)).astype(xt) for x, y in zip(xs, f)]
        for x, c in zip(xs, cols):
            outs[0][block, c] = x
    xs = [x.astype(jnp.float32) for x in xs]
    n = float(chunks * bc)
    mean = (jnp.sum(sum(xs), axis=1) / n)[:, None]
    xs = [x - mean for x in xs]
    inv = jax.lax.rsqrt(jnp.sum(sum(x * x for x in xs), axis=1) / n + eps)[:, None]
    for x, c, sc, b in zip(xs, cols, scale, bias):
        y = (x * (inv * sc) + b).astype(dtype)
        if outs[-1].dtype != dtype:   # e4m3 as `formats.quantise` (Triton's f32 division: module doc)
            y = jnp.clip(y.astype(jnp.float32) / act_ref[...][None, :], -E4M3_MAX, E4M3_MAX)
        outs[-1][block, c] = y.astype(outs[-1].dtype)


def layer_norm(x, vectors, rows: tuple[int, int], *, residual=None, eps: float = 1e-6, dtype=None, quantise=None,
               blocks: Blocks = Blocks()):
    """x (..., D) -> (..., D) in dtype (default x's): LayerNorm over the last axis with scale vectors[rows[0]] and
    bias vectors[rows[1]] (vectors (R, D), any float dtype: the values are read in f32). With `residual` = (f,
    f_vectors, f_row) or (f, f_vectors, f_row, f_scale), f x's shape, f_vectors (R', D), f_scale (D,) (a Dense's
    product, the table holding its bias at row f_row, and an FP8 GEMM's f32 output scale, `formats.output_scale`):
    the residual add as well, (x + (f [* f_scale] + f's bias), its LayerNorm), f's bias taken in x's dtype and each
    op rounded to x's dtype as XLA rounds them. quantise: an activation scale (f32 scalar, `matmul.input_scale`):
    the LayerNorm, in dtype, then quantised to e4m3 as `formats.quantise` does (the input of an FP8 GEMM).

    The vectors come as tables and rows (the tower's `vectors` as (L R, D), `engine.weights.vision_weights`), so the
    kernel reads them where they are: a vector sliced out before the call would be a copy of its own.

    Under a sharded jit (the simulator's batch mesh) each device normalises its own rows: XLA cannot split a kernel
    it does not know, and would otherwise gather every row onto every device."""
    d = x.shape[-1]
    if vectors.ndim != 2 or vectors.shape[1] != d or not all(0 <= r < vectors.shape[0] for r in rows):
        raise ValueError(f"layer_norm: vectors {vectors.shape} must be (R, {d}) with rows {rows} in it, for x "
                         f"{x.shape}")
    if residual is not None:
        f, f_vectors, f_row, *f_scale = residual
        if (f.shape != x.shape or f_vectors.ndim != 2 or f_vectors.shape[1] != d
                or not 0 <= f_row < f_vectors.shape[0] or any(v.shape != (d,) for v in f_scale)):
            raise ValueError(f"layer_norm: residual {f.shape}, its vectors {f_vectors.shape} (row {f_row}) and "
                             f"scale {[v.shape for v in f_scale]} must be x's shape {x.shape}, (R, {d}) and ({d},)")
    n = math.prod(x.shape[:-1])
    # the unused operands are numpy constants, not traced ops (XLA still fills a splat once a call, a broadcast)
    act = np.ones((1,), np.float32) if quantise is None else jnp.reshape(quantise, (1,)).astype(jnp.float32)
    static = (float(eps), jnp.dtype(dtype or x.dtype), quantise is not None, blocks)
    if residual is None:
        return _norm(x.reshape(n, d), vectors, act, *static, (*rows, 0))[0].reshape(x.shape)
    f_scale = f_scale[0].astype(jnp.float32) if f_scale else np.ones((d,), np.float32)
    return tuple(o.reshape(x.shape) for o in _add_norm(x.reshape(n, d), f.reshape(n, d), f_vectors, f_scale,
                                                         vectors, act, *static, (*rows, f_row), len(residual) == 4))


@functools.partial(custom_partitioning, static_argnums=(3, 4, 5, 6, 7))
def _norm(x, vectors, act, eps, dtype, quantised, blocks, rows):
    return _layer_norm((x,), vectors, act, eps, dtype, quantised, blocks, rows, False)


@functools.partial(custom_partitioning, static_argnums=(6, 7, 8, 9, 10, 11))
def _add_norm(x, f, f_vectors, f_scale, vectors, act, eps, dtype, quantised, blocks, rows, scaled):
    return _layer_norm((x, f, f_vectors, f_scale), vectors, act, eps, dtype, quantised, blocks, rows, scaled)


def _rule(residual: bool):
    """The partitioning of the kernel over x (and the residual f; as many outputs), the residual's vector table and
    f32 scale, the norm's vector table and the quantisation's (1,) scale: rows split as x's, the rest replicated."""
    n = 2 if residual else 1

    def partition(*static_and_shapes):
        *static, mesh, arg_shapes, result_shape = static_and_shapes
        rows, full = row_shardings(mesh, arg_shapes[0].sharding)
        eps, dtype, quantised, blocks, table_rows, *scaled = static   # scaled: _add_norm's only

        def fn(*a):
            return _layer_norm(a[:-2], *a[-2:], eps, dtype, quantised, blocks, table_rows,
                               bool(scaled) and scaled[0])
        operands = (rows, rows, full, full, full, full) if residual else (rows, full, full)
        return mesh, fn, (rows,) * n, operands

    def infer(*static_and_shapes):
        mesh, arg_shapes = static_and_shapes[-3:-1]
        return (row_shardings(mesh, arg_shapes[0].sharding)[0],) * n

    # factors in the order they first appear (Shardy): r d, then u (the residual's table rows), v (the norm's), o
    operands = ["r d", "r d", "u d", "d", "v d", "o"] if residual else ["r d", "v d", "o"]
    need = ("d", "u", "v", "o") if residual else ("d", "v", "o")
    return dict(partition=partition, infer_sharding_from_operands=infer, need_replication_factors=need,
                sharding_rule=", ".join(operands) + " -> " + ", ".join(["r d"] * n))


_norm.def_partition(**_rule(False))
_add_norm.def_partition(**_rule(True))


def _layer_norm(xs: tuple, vectors, act, eps: float, dtype, quantised: bool, blocks: Blocks, rows: tuple,
                scaled: bool) -> tuple:
    r, d = xs[0].shape
    br, bc = fit(blocks.rows, r), fit(blocks.cols, d)
    residual = len(xs) > 1
    kernel = functools.partial(_kernel, br=br, bc=bc, chunks=d // bc, eps=eps, residual=residual, scaled=scaled,
                               dtype=dtype, rows=rows)
    shapes = ((jax.ShapeDtypeStruct((r, d), xs[0].dtype),) if residual else ()) + (
        jax.ShapeDtypeStruct((r, d), E4M3 if quantised else dtype),)
    return call(kernel, grid=(r // br,), out_shape=shapes, name="layer_norm", num_warps=blocks.num_warps,
                num_stages=1)(*xs, vectors, act)
