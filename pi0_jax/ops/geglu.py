"""Gemma's GeGLU between the MLP's gate/up and down GEMMs as one Pallas kernel (Triton on a GPU, interpret mode on a
CPU), for the prefix's FP8 MLP.

There the gate/up GEMM writes its raw e4m3 x e4m3 product, and one pass reads it: the per-column output scale,
GELU-tanh(gate) * up, and the down GEMM's input quantisation. As XLA's fusion that pass runs at about half a copy's
bandwidth, bound by GELU's arithmetic (0.44 of its 1.85 ms over the product of π0's prefix at B = 64 on an H200,
against a copy of the same bytes; docs/BENCHMARKS.md). This kernel holds a block in f32 registers from its load to
one rounding at its store: 1.42 ms there.

Numerics: GELU-tanh written as x sigmoid(2 z) (the same function: 1 + tanh z = 2 sigmoid(2 z)); the scale, GELU,
product and quantisation (x * (1 / s), clipped to ±448, rounded to nearest even) in f32. XLA's path (`geglu_xla`, as
`engine.layers` runs it) rounds the scaled product, GELU and the product to the activation dtype between them and
divides by s. In f32 the two agree to f32 rounding; in bf16 an e4m3 output differs by one step in about 6 % of its
elements.

Axis legend: R rows, F hidden units, u units a block of the fused gate/up product (`layout.gate_up_block`).
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl

from pi0_jax.ops import layout
from pi0_jax.ops.formats import E4M3, E4M3_MAX, quantise
from pi0_jax.ops.pallas_base import call, fit

_SQRT_2_OVER_PI = 0.7978845608028654


@dataclasses.dataclass(frozen=True)
class Blocks:
    """Rows and hidden units a program (powers of two, shrunk to divide R and F), Triton's warps. Defaults: the
    fastest of seven settings at 816, 6,528 and 51,200 rows (H200, docs/BENCHMARKS.md)."""

    rows: int = 8
    units: int = 1024
    num_warps: int = 4


def _kernel(y_ref, *refs, br: int, nb: int, scaled: bool, quantised: bool):
    """Program (i, j): rows block i, block pairs j * nb ... of y (R, F / u, 2, u); col (1, F / u, 2, u), s (1, 1)."""
    col_ref, refs = (refs[0], refs[1:]) if scaled else (None, refs)
    s_ref, o_ref = refs if quantised else (None, refs[0])
    rows, pairs = pl.ds(pl.program_id(0) * br, br), pl.ds(pl.program_id(1) * nb, nb)
    gate, up = (y_ref[rows, pairs, half, :].astype(jnp.float32) for half in (0, 1))
    if scaled:
        gate = gate * col_ref[pl.ds(0, 1), pairs, 0, :]
        up = up * col_ref[pl.ds(0, 1), pairs, 1, :]
    z = _SQRT_2_OVER_PI * (gate + 0.044715 * gate * gate * gate)
    h = gate / (1.0 + jnp.exp(-2.0 * z)) * up
    if quantised:
        h = jnp.clip(h * (1.0 / s_ref[0, 0]), -E4M3_MAX, E4M3_MAX)
    o_ref[rows, pairs, :] = h.astype(o_ref.dtype)


def geglu(y: jax.Array, col_scale: jax.Array | None = None, act_scale: jax.Array | None = None, *,
          blocks: Blocks = Blocks()) -> jax.Array:
    """GELU-tanh(gate) * up of a fused gate/up product y (..., 2F), its columns in `layout.gate_up_block(F)` pairs,
    -> (..., F). col_scale (2F,) f32: a factor on y's columns first (an FP8 GEMM's output scale). act_scale () f32:
    the result quantised to e4m3 with it, the down GEMM's input (`formats.quantise`); else in y's dtype."""
    *lead, two_f = y.shape
    f = two_f // 2
    u = layout.gate_up_block(f)
    r = y.size // two_f
    quantised, scaled = act_scale is not None, col_scale is not None
    if quantised and act_scale.size != 1:
        raise ValueError(f"geglu quantises with one scale, got act_scale of shape {act_scale.shape}")
    if scaled and col_scale.shape != (two_f,):
        raise ValueError(f"col_scale must be ({two_f},) for y of shape {y.shape}, got {col_scale.shape}")
    br, nb = fit(blocks.rows, r), fit(max(blocks.units // u, 1), f // u)
    args = [y.reshape(r, f // u, 2, u)]
    if scaled:
        args.append(col_scale.astype(jnp.float32).reshape(1, f // u, 2, u))
    if quantised:
        args.append(act_scale.astype(jnp.float32).reshape(1, 1))
    out = jax.ShapeDtypeStruct((r, f // u, u), E4M3 if quantised else y.dtype)
    kernel = functools.partial(_kernel, br=br, nb=nb, scaled=scaled, quantised=quantised)
    h = call(kernel, grid=(r // br, f // u // nb), out_shape=out, name="geglu", num_warps=blocks.num_warps,
             num_stages=1)(*args)
    return h.reshape(*lead, f)


def geglu_xla(y: jax.Array, col_scale: jax.Array | None = None, act_scale: jax.Array | None = None) -> jax.Array:
    """`geglu` as XLA's ops, with `engine.layers`' roundings: the scaled product, GELU-tanh and the product in y's
    dtype, then the quantisation."""
    if col_scale is not None:
        y = (y.astype(jnp.float32) * col_scale.astype(jnp.float32)).astype(y.dtype)
    gate, up = layout.split_gate_up(y)
    h = jax.nn.gelu(gate, approximate=True) * up
    return h if act_scale is None else quantise(h, act_scale)
