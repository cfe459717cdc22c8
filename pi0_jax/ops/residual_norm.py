"""The action expert's residual add and the RMSNorm (or π0.5's adaRMS) after it as one Pallas kernel (Triton on GPU,
interpret mode on CPU), for the XLA expert's layers (B > 2).

In a layer XLA runs x + y [* gate] and the norm of the sum as two kernels: the add writes the new residual stream,
and the norm's reduction reads it back. At B = 8 that pair took 6.1 us of a layer's 84 (4.1 + 2.0; H200,
docs/BENCHMARKS.md, session 32), for 408 rows of 1,024. This kernel holds a block of rows in registers from load to
store: x and y read once, the sum and its norm written once.

Numerics as `engine.layers.rms_norm` and `suffix_layer`'s residual: y * gate rounded to the dtype, the sum rounded,
f32 statistics (mean of squares, eps inside the rsqrt), x * rsqrt times (1 + scale) formed in the scale's dtype
(adaRMS: plus shift), one rounding to the dtype. Only the order of the sum of squares differs (chunk by chunk here),
so the two agree to f32 rounding.

The norm's vectors come as a (1, E) table: a weight (1, D), or π0.5's adaRMS row (1, 3D) [scale | shift | gate] of
a step, the same for every token (the gate of the sub-block before from another such row). Axis legend: R rows,
D width.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import pallas as pl
from jax.experimental.custom_partitioning import custom_partitioning
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P

from pi0_jax.ops.pallas_base import call, fit

EPS = 1e-6


@dataclasses.dataclass(frozen=True)
class Blocks:
    """Rows per program and the widest column chunk (powers of two, shrunk to divide the rows per table row and D),
    Triton's warps."""

    rows: int = 8
    cols: int = 256
    num_warps: int = 4


def _kernel(x_ref, y_ref, norm_ref, gate_ref, xo_ref, h_ref, *, br, bc, chunks, width, adaptive, gated, gate_col,
            eps):
    """Program i: rows block i, the width in `chunks` column chunks held in registers between the statistics and
    the store."""
    block = pl.ds(pl.program_id(0) * br, br)
    d = chunks * bc
    dt, nt = x_ref.dtype, norm_ref.dtype

    def vector(ref, col):   # (1, bc) of a table from column col, in the table's dtype
        return ref[:, pl.ds(col, bc)]

    xs = []
    for c in range(chunks):
        cols = pl.ds(c * bc, bc)
        y = y_ref[block, cols]
        if gated:
            y = (y.astype(jnp.float32) * vector(gate_ref, gate_col + c * bc).astype(jnp.float32)).astype(dt)
        x = (x_ref[block, cols].astype(jnp.float32) + y.astype(jnp.float32)).astype(dt)
        xo_ref[block, cols] = x
        xs.append(x.astype(jnp.float32))
    inv = jax.lax.rsqrt(jnp.sum(sum(x * x for x in xs), axis=1) / width + eps)[:, None]
    for c, x in enumerate(xs):
        h = x * inv * (1 + vector(norm_ref, c * bc)).astype(nt).astype(jnp.float32)
        if adaptive:
            h = h + vector(norm_ref, d + c * bc).astype(jnp.float32)
        h_ref[block, pl.ds(c * bc, bc)] = h.astype(h_ref.dtype)


def add_norm(x, y, norm, gate=None, *, adaptive: bool, gate_col: int = 0, eps: float = EPS,
             blocks: Blocks = Blocks()):
    """(x + y [* gate], its RMSNorm or adaRMS): x, y (B, S, D) in one dtype. norm (1, E): the scale in columns
    [0, D) (a weight), with `adaptive` also the shift in [D, 2D) (π0.5's adaRMS row [scale | shift | gate], the same
    for every token of a step). gate: None, or a (1, E') table whose columns [gate_col, gate_col + D) are the gate
    that multiplies y (π0.5's adaRMS gate of the sub-block that made y). Returns (x + ..., h), both (B, S, D) in x's
    dtype.

    Under a sharded jit (the simulator's batch mesh) each device takes its own elements: XLA cannot split a kernel it
    does not know, and would otherwise gather every row onto every device."""
    b, s, d = x.shape
    bad = (y.shape != x.shape or norm.ndim != 2 or norm.shape[0] != 1 or norm.shape[1] < (2 if adaptive else 1) * d
           or (gate is not None and (gate.ndim != 2 or gate.shape[0] != 1 or gate.shape[1] < gate_col + d)))
    if bad:
        raise ValueError(f"add_norm: y {y.shape} must be x's shape {x.shape}, the norm's table {norm.shape} (1, >= "
                         f"{(2 if adaptive else 1) * d}) and the gate's {None if gate is None else gate.shape} (1, >= "
                         f"{gate_col + d})")
    gated = gate is not None
    gate = np.zeros((1, 1), np.float32) if gate is None else gate   # unread
    static = (float(eps), bool(adaptive), gated, int(gate_col), blocks)
    xo, h = _partitioned(x.reshape(b * s, d), y.reshape(b * s, d), norm, gate, *static)
    return xo.reshape(x.shape), h.reshape(x.shape)


def _add_norm(x, y, norm, gate, eps, adaptive, gated, gate_col, blocks):
    r, d = x.shape
    br, bc = fit(blocks.rows, r), fit(blocks.cols, d)
    kernel = functools.partial(_kernel, br=br, bc=bc, chunks=d // bc, width=float(d), adaptive=adaptive,
                               gated=gated, gate_col=gate_col, eps=eps)
    shape = jax.ShapeDtypeStruct((r, d), x.dtype)
    return call(kernel, grid=(r // br,), out_shape=(shape, shape), name="residual_norm",
                num_warps=blocks.num_warps, num_stages=1)(x, y, norm, gate)


@functools.partial(custom_partitioning, static_argnums=(4, 5, 6, 7, 8))
def _partitioned(x, y, norm, gate, eps, adaptive, gated, gate_col, blocks):
    return _add_norm(x, y, norm, gate, eps, adaptive, gated, gate_col, blocks)


def _shardings(mesh, x_sharding) -> tuple:
    """(rows as x has them, whole columns; the tables: replicated)."""
    axes = x_sharding.spec[0] if len(x_sharding.spec) else None
    return NamedSharding(mesh, P(axes, None)), NamedSharding(mesh, P())


def _partition(eps, adaptive, gated, gate_col, blocks, mesh, arg_shapes, result_shape):
    rows, table = _shardings(mesh, arg_shapes[0].sharding)

    def fn(x, y, norm, gate):
        return _add_norm(x, y, norm, gate, eps, adaptive, gated, gate_col, blocks)
    return mesh, fn, (rows, rows), (rows, rows, table, table)


def _infer(eps, adaptive, gated, gate_col, blocks, mesh, arg_shapes, result_shape):
    rows, _ = _shardings(mesh, arg_shapes[0].sharding)
    return rows, rows


# factors in the order they first appear (Shardy)
_partitioned.def_partition(partition=_partition, infer_sharding_from_operands=_infer,
                           sharding_rule="r d, r d, g e, h f -> r d, r d",
                           need_replication_factors=("d", "g", "e", "h", "f"))
