"""SigLIP's residual add and the LayerNorm after it as one Pallas kernel (Triton on GPU, interpret mode on CPU).

XLA runs x + (y + b), y a Dense's product and b its bias, and the LayerNorm after it as two or three kernels: the
statistics (with the adds), the normalisation (which reads the rows again), and a bias add of its own where the
Dense is a Triton GEMM. This kernel holds a block of rows in registers from load to store: one launch, x and y read
once, x + (y + b) and its LayerNorm written once. Triton's blocks are powers of two, so a width that is not one
(So400m's 1152) is walked in equal power-of-two column chunks (9 x 128). On the tower it measured 1.5-3 % faster
with XLA's GEMMs and no different with cuBLAS's (docs/BENCHMARKS.md, "SigLIP's LayerNorm as a kernel").

Numerics as `pi0_jax.engine.vision.add_norm`'s XLA path (Flax's): each add rounded to the dtype, f32 statistics,
the fast variance E[x²] - E[x]² clamped at 0, eps inside the rsqrt, scale and bias applied in f32, one rounding to
the output dtype. Only the order of the sums differs (chunk by chunk here), so the two agree to f32 rounding.

Axis legend: R rows, D width.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl
from jax.experimental.custom_partitioning import custom_partitioning
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P

from pi0_jax.ops.pallas_base import call, fit


@dataclasses.dataclass(frozen=True)
class Blocks:
    """Rows per program and the widest column chunk (powers of two, shrunk to divide R and D), Triton's warps.
    Defaults: the fastest of six settings at 3, 24 and 192 images (H100, docs/BENCHMARKS.md)."""

    rows: int = 8
    cols: int = 128
    num_warps: int = 8


def _kernel(x_ref, *refs, br, bc, chunks, eps, residual):
    """Program i: rows block i, the whole width in `chunks` column chunks held in registers between the statistics
    and the store. The chunks are summed elementwise first, so each statistic is one reduction across threads."""
    f_ref, fb_ref, scale_ref, bias_ref, *outs = refs if residual else (None, None, *refs)
    rows = pl.ds(pl.program_id(0) * br, br)
    cols = [pl.ds(c * bc, bc) for c in range(chunks)]
    scale = [scale_ref[c].astype(jnp.float32)[None, :] for c in cols]
    bias = [bias_ref[c].astype(jnp.float32)[None, :] for c in cols]
    xs = [x_ref[rows, c] for c in cols]
    if residual:   # x + (f + f's bias), each add rounded to x's dtype as XLA's; stored, and normalised
        dtype = x_ref.dtype
        f = [(f_ref[rows, c].astype(jnp.float32) + fb_ref[c].astype(jnp.float32)[None, :]).astype(dtype)
             for c in cols]
        xs = [(x.astype(jnp.float32) + y.astype(jnp.float32)).astype(dtype) for x, y in zip(xs, f)]
        for x, c in zip(xs, cols):
            outs[0][rows, c] = x
    xs = [x.astype(jnp.float32) for x in xs]
    n = float(chunks * bc)
    mean = jnp.sum(sum(xs), axis=1) / n
    var = jnp.maximum(jnp.sum(sum(x * x for x in xs), axis=1) / n - mean * mean, 0.0)
    inv = jax.lax.rsqrt(var + eps)[:, None]
    for x, c, sc, b in zip(xs, cols, scale, bias):
        outs[-1][rows, c] = ((x - mean[:, None]) * (inv * sc) + b).astype(outs[-1].dtype)


def layer_norm(x, scale, bias, *, residual=None, eps: float = 1e-6, dtype=None, blocks: Blocks = Blocks()):
    """x (..., D) -> (..., D) in dtype (default x's): LayerNorm over the last axis with scale and bias (D,).
    With `residual` = (f, f_bias), f x's shape and f_bias (D,) (a Dense's product and its bias): the residual add
    as well, (x + (f + f_bias), its LayerNorm), each add rounded to x's dtype as XLA rounds them.

    Under a sharded jit (the simulator's batch mesh) each device normalises its own rows: XLA cannot split a kernel
    it does not know, and would otherwise gather every row onto every device."""
    d = x.shape[-1]
    if scale.shape != (d,) or bias.shape != (d,):
        raise ValueError(f"layer_norm: scale {scale.shape} and bias {bias.shape} must be ({d},) for x {x.shape}")
    if residual is not None and (residual[0].shape != x.shape or residual[1].shape != (d,)):
        raise ValueError(f"layer_norm: residual {residual[0].shape} and its bias {residual[1].shape} must be x's "
                         f"shape {x.shape} and ({d},)")
    rows = math.prod(x.shape[:-1])
    static = (float(eps), jnp.dtype(dtype or x.dtype), blocks)
    if residual is None:
        return _norm(x.reshape(rows, d), scale, bias, *static)[0].reshape(x.shape)
    f, f_bias = residual
    return tuple(o.reshape(x.shape) for o in _add_norm(x.reshape(rows, d), f.reshape(rows, d), f_bias, scale, bias,
                                                         *static))


@functools.partial(custom_partitioning, static_argnums=(3, 4, 5))
def _norm(x, scale, bias, eps, dtype, blocks):
    return _layer_norm((x,), scale, bias, eps, dtype, blocks)


@functools.partial(custom_partitioning, static_argnums=(5, 6, 7))
def _add_norm(x, f, f_bias, scale, bias, eps, dtype, blocks):
    return _layer_norm((x, f, f_bias), scale, bias, eps, dtype, blocks)


def _shardings(mesh, sharding) -> tuple:
    """(the rows' sharding: as x has them, columns whole; the vectors': replicated)."""
    axes = sharding.spec[0] if len(sharding.spec) else None
    return NamedSharding(mesh, P(axes, None)), NamedSharding(mesh, P())


def _rule(n: int):
    """The partitioning of a kernel over n row arrays (x, or x and the residual; n outputs likewise) and n + 1
    vectors (the residual's bias, the scale and the bias)."""
    def partition(eps, dtype, blocks, mesh, arg_shapes, result_shape):
        rows, full = _shardings(mesh, arg_shapes[0].sharding)
        fn = lambda *a: _layer_norm(a[:-2], *a[-2:], eps, dtype, blocks)  # noqa: E731
        return mesh, fn, (rows,) * n, (rows,) * n + (full,) * (n + 1)

    def infer(eps, dtype, blocks, mesh, arg_shapes, result_shape):
        return (_shardings(mesh, arg_shapes[0].sharding)[0],) * n

    return dict(partition=partition, infer_sharding_from_operands=infer, need_replication_factors=("d",),
                sharding_rule=", ".join(["r d"] * n + ["d"] * (n + 1)) + " -> " + ", ".join(["r d"] * n))


_norm.def_partition(**_rule(1))
_add_norm.def_partition(**_rule(2))


def _layer_norm(xs: tuple, scale, bias, eps: float, dtype, blocks: Blocks) -> tuple:
    r, d = xs[0].shape
    br, bc = fit(blocks.rows, r), fit(blocks.cols, d)
    kernel = functools.partial(_kernel, br=br, bc=bc, chunks=d // bc, eps=eps, residual=len(xs) == 3)
    shapes = ((jax.ShapeDtypeStruct((r, d), xs[0].dtype),) if len(xs) == 3 else ()) + (
        jax.ShapeDtypeStruct((r, d), dtype),)
    return call(kernel, grid=(r // br,), out_shape=shapes, name="layer_norm", num_warps=blocks.num_warps,
                num_stages=1)(*xs, scale, bias)
