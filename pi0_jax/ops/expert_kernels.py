"""Fused Pallas kernels for one action-expert layer of the denoise step (Triton on GPU, interpret mode on CPU).

One expert layer is five kernels (seven launches with split-K) instead of ~23 XLA kernels:
  norm_qkv_rope    RMSNorm / adaRMS + the fused q/k/v GEMM + RoPE + q scaling
  attention        the suffix queries over [cached prefix | suffix] keys, one online softmax
  matmul_residual  out-projection + (gated) residual; again for the MLP's down-projection + (gated) residual
                   (split-K: f32 partials, then one XLA fusion for the sum, gate and residual)
  norm_geglu       RMSNorm / adaRMS + the gate/up GEMM + GELU-tanh(gate) * up

Kernel layout (`pi0_jax.ops.layout`): rows are (batch, suffix padded to Sp) flattened; each head is stored as
[x1 | 0 | x2 | 0], the two RoPE halves each padded to hp (a multiple of 16), so the program that owns a block of x1
columns also owns the matching x2 columns; widths are multiples of 16 (Triton's smallest dot). Padding is zeros and
padded keys are masked, so every valid number is the one the XLA path computes.

Numerics as `pi0_jax.engine.layers`: f32 norm statistics, f32 RoPE, f32 logits and softmax with the same big-negative
fill; every GEMM output is rounded to the activation dtype before its epilogue, as XLA's `x @ w` is, and each
epilogue op rounds where the XLA op would.

Axis legend: M rows (B * Sp), D width, F MLP hidden, N query heads, K kv heads, hp half head dim (padded), P keys.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as plgpu

BIG_NEG = -2.3819763e38  # masked logits: the value pi0_jax.gemma fills (a test checks they agree)
EPS = 1e-6
ALIGN = 16  # Triton's smallest dot dimension


@dataclasses.dataclass(frozen=True)
class Blocks:
    """Tile sizes (powers of two; each is shrunk to divide its padded dimension) and Triton launch parameters.
    Defaults: the fastest of a sweep at π0 full size, B=1, on an H200 (docs/BENCHMARKS.md, "Fused kernels")."""

    rows: int = 64  # GEMM rows per program
    k: int = 128  # GEMM contraction chunk
    qkv_cols: int = 32  # columns of each RoPE half per norm_qkv_rope program
    out_cols: int = 64  # output columns per matmul_residual program
    out_splits: int = 8  # split-K programs of the out-projection (partials summed by XLA with the residual)
    down_splits: int = 8  # the same for the down-projection
    mlp_cols: int = 32  # hidden columns (of gate and of up) per norm_geglu program
    q: int = 16  # attention queries per program
    kv: int = 64  # attention keys per loop step
    num_warps: int = 4  # the GEMM kernels'
    attention_warps: int = 4
    num_stages: int = 3


def _fit(block: int, n: int) -> int:
    """The largest power of two <= block that divides n."""
    while n % block:
        block //= 2
    return block


def _call(kernel, grid, out_shape, blocks: Blocks, name: str, num_warps: int | None = None):
    on_cpu = jax.default_backend() == "cpu"
    params = None if on_cpu else plgpu.CompilerParams(num_warps=num_warps or blocks.num_warps,
                                                      num_stages=blocks.num_stages)
    return pl.pallas_call(kernel, grid=grid, out_shape=out_shape, interpret=on_cpu, compiler_params=params,
                          name=name)


def _inv_rms(x_ref, rows, bm, width, bk, n_true):
    """1 / sqrt(mean(x^2) + eps) per row, in f32 over the true width (padded columns are zero)."""

    def body(i, acc):
        x = x_ref[rows, pl.ds(i * bk, bk)].astype(jnp.float32)
        return acc + jnp.sum(x * x, axis=1)

    ss = jax.lax.fori_loop(0, width // bk, body, jnp.zeros((bm,), jnp.float32))
    return jax.lax.rsqrt(ss / n_true + EPS)[:, None]


def _normed(x_ref, mod_ref, rows, cols, inv, mod_row, adaptive, dtype):
    """(x * inv) * (1 + scale) [+ shift] in f32, then the activation dtype: `layers.rms_norm` on one tile.
    (1 + scale) is formed in the scale's dtype first, as the reference does."""
    h = x_ref[rows, cols].astype(jnp.float32) * inv
    h = h * (1 + mod_ref[pl.ds(mod_row, 1), cols]).astype(jnp.float32)
    if adaptive:
        h = h + mod_ref[pl.ds(mod_row + 1, 1), cols].astype(jnp.float32)
    return h.astype(dtype)


def _dot(a, b, trans_b: bool = False):
    """a @ b (or a @ b.T) with an f32 accumulator; f32 operands multiply in full f32 (Triton's IEEE mode)."""
    dims = (((1,), (1 if trans_b else 0,)), ((), ()))
    return jax.lax.dot_general(a, b, dims, preferred_element_type=jnp.float32)


def _round(acc, dtype):
    """A GEMM's f32 accumulator as XLA returns `x @ w`: rounded to the activation dtype (kept in f32 to compute)."""
    return acc.astype(dtype).astype(jnp.float32)


# -- norm + q/k/v GEMM + RoPE -----------------------------------------------------------------------------------------
def _norm_qkv_rope_kernel(x_ref, mod_ref, w_ref, cos_ref, sin_ref, o_ref, *, m, bm, bk, bh, hp, width, n_true,
                          mod_row, adaptive, num_heads, num_kv_heads, q_scale):
    i, n, j = pl.program_id(0), pl.program_id(1), pl.program_id(2)
    rows = pl.ds(i * bm, bm)
    dtype = x_ref.dtype
    inv = _inv_rms(x_ref, rows, bm, width, bk, n_true)
    c1, c2 = (2 * n) * hp + j * bh, (2 * n + 1) * hp + j * bh

    def body(kk, acc):
        ks = pl.ds(kk * bk, bk)
        h = _normed(x_ref, mod_ref, rows, ks, inv, mod_row, adaptive, dtype)
        return acc[0] + _dot(h, w_ref[ks, pl.ds(c1, bh)]), acc[1] + _dot(h, w_ref[ks, pl.ds(c2, bh)])

    zero = jnp.zeros((bm, bh), jnp.float32)
    a1, a2 = jax.lax.fori_loop(0, width // bk, body, (zero, zero))
    a1, a2 = _round(a1, dtype), _round(a2, dtype)
    # RoPE in f32, then the dtype; v heads read the tables' identity rows (cos 1, sin 0: a1, a2 come back exactly).
    # q is then scaled in the dtype: the blend 1 + (q_scale - 1) * is_q is exact (q_scale is a dtype value in (0, 1]).
    # Integer arithmetic on the head index, not selects: Triton rejects a select with a scalar predicate.
    is_v = jnp.minimum(jnp.maximum(n - (num_heads + num_kv_heads) + 1, 0), 1)
    is_q = jnp.minimum(jnp.maximum(num_heads - n, 0), 1)
    t_rows = pl.ds(is_v * m + i * bm, bm)
    cos, sin = cos_ref[t_rows, pl.ds(j * bh, bh)], sin_ref[t_rows, pl.ds(j * bh, bh)]
    scale = 1.0 + (q_scale - 1.0) * is_q.astype(jnp.float32)
    o_ref[rows, pl.ds(c1, bh)] = (_round(a1 * cos - a2 * sin, dtype) * scale).astype(o_ref.dtype)
    o_ref[rows, pl.ds(c2, bh)] = (_round(a2 * cos + a1 * sin, dtype) * scale).astype(o_ref.dtype)


def norm_qkv_rope(x, mods, mod_row: int, adaptive: bool, w_qkv, cos, sin, *, width: int, num_heads: int,
                  num_kv_heads: int, head_dim: int, blocks: Blocks = Blocks()):
    """x (M, D) -> qkv (M, (N + 2K) * 2hp): normed, projected, q/k rotated, q scaled by head_dim^-0.5.

    mods (R, D): row mod_row is the norm scale, +1 the adaRMS shift (adaptive); w_qkv (D, (N + 2K) * 2hp);
    cos / sin (2M, hp) f32 (`layout.rope_tables`: the rows' angles, then identity rows); width: the true D (the
    mean's divisor).
    """
    m, d = x.shape
    hp = cos.shape[1]
    heads = num_heads + 2 * num_kv_heads
    bm, bk, bh = _fit(blocks.rows, m), _fit(blocks.k, d), _fit(blocks.qkv_cols, hp)
    q_scale = float(np.asarray(head_dim**-0.5, x.dtype))  # the reference scales q in the activation dtype
    kernel = functools.partial(_norm_qkv_rope_kernel, m=m, bm=bm, bk=bk, bh=bh, hp=hp, width=d, n_true=width,
                               mod_row=mod_row, adaptive=adaptive, num_heads=num_heads, num_kv_heads=num_kv_heads,
                               q_scale=q_scale)
    out = jax.ShapeDtypeStruct((m, heads * 2 * hp), x.dtype)
    return _call(kernel, (m // bm, heads, hp // bh), out, blocks, "norm_qkv_rope")(x, mods, w_qkv, cos, sin)


# -- attention over [cached prefix | suffix] ---------------------------------------------------------------------------
def _attention_kernel(qkv_ref, ck_ref, cv_ref, pmask_ref, smask_ref, o_ref, *, bq, bkv, sp, pp, hd, num_heads,
                      num_kv_heads):
    b, n, qi = pl.program_id(0), pl.program_id(1), pl.program_id(2)
    kh = jax.lax.div(n, num_heads // num_kv_heads) if num_kv_heads > 1 else 0  # this query head's kv head
    rows = pl.ds(b * sp + qi * bq, bq)
    q = qkv_ref[rows, pl.ds(n * hd, hd)]
    dtype = q.dtype

    def update(carry, k, v, valid):
        o, m, l = carry
        logits = jnp.where(valid, _dot(q, k, trans_b=True), BIG_NEG)  # f32
        m_new = jnp.maximum(m, jnp.max(logits, axis=1))
        corr = jnp.exp(m - m_new)
        p = jnp.exp(logits - m_new[:, None])
        return o * corr[:, None] + _dot(p.astype(dtype), v), m_new, l * corr + jnp.sum(p, axis=1)

    def prefix_block(t, carry):
        keys = pl.ds(b * pp + t * bkv, bkv)
        valid = pmask_ref[pl.ds(b, 1), pl.ds(t * bkv, bkv)] != 0
        return update(carry, ck_ref[keys, pl.ds(kh * hd, hd)], cv_ref[keys, pl.ds(kh * hd, hd)], valid)

    init = (jnp.zeros((bq, hd), jnp.float32), jnp.full((bq,), BIG_NEG, jnp.float32), jnp.zeros((bq,), jnp.float32))
    carry = jax.lax.fori_loop(0, pp // bkv, prefix_block, init)
    suffix = pl.ds(b * sp, sp)
    k_col, v_col = (num_heads + kh) * hd, (num_heads + num_kv_heads + kh) * hd
    o, _, l = update(carry, qkv_ref[suffix, pl.ds(k_col, hd)], qkv_ref[suffix, pl.ds(v_col, hd)],
                     smask_ref[rows, :] != 0)
    o_ref[rows, pl.ds(n * hd, hd)] = (o / l[:, None]).astype(o_ref.dtype)


def attention(qkv, cache_k, cache_v, prefix_mask, suffix_mask, *, batch: int, num_heads: int, num_kv_heads: int,
              blocks: Blocks = Blocks()):
    """Softmax attention of the suffix queries over [cached prefix | suffix] keys -> (M, N * 2hp).

    qkv (M, (N + 2K) * 2hp) from `norm_qkv_rope`; cache_k / cache_v (B * P, K * 2hp); prefix_mask (B, P) int32, the
    same for every query; suffix_mask (M, Sp) int32, query row -> suffix key.
    """
    m, sp = suffix_mask.shape
    hd = qkv.shape[1] // (num_heads + 2 * num_kv_heads)
    pp = prefix_mask.shape[1]
    bq, bkv = _fit(blocks.q, sp), _fit(blocks.kv, pp)
    kernel = functools.partial(_attention_kernel, bq=bq, bkv=bkv, sp=sp, pp=pp, hd=hd, num_heads=num_heads,
                               num_kv_heads=num_kv_heads)
    out = jax.ShapeDtypeStruct((m, num_heads * hd), qkv.dtype)
    return _call(kernel, (batch, num_heads, sp // bq), out, blocks, "expert_attention", blocks.attention_warps)(
        qkv, cache_k, cache_v, prefix_mask, suffix_mask)


# -- GEMM + (gated) residual -------------------------------------------------------------------------------------------
def _matmul_residual_kernel(y_ref, w_ref, x_ref, mod_ref, o_ref, *, bm, bn, bk, depth, gate_row):
    i, j = pl.program_id(0), pl.program_id(1)
    rows, cols = pl.ds(i * bm, bm), pl.ds(j * bn, bn)

    def body(kk, acc):
        ks = pl.ds(kk * bk, bk)
        return acc + _dot(y_ref[rows, ks], w_ref[ks, cols])

    dtype = x_ref.dtype
    y = _round(jax.lax.fori_loop(0, depth // bk, body, jnp.zeros((bm, bn), jnp.float32)), dtype)
    if gate_row is not None:
        y = _round(y * mod_ref[pl.ds(gate_row, 1), cols].astype(jnp.float32), dtype)
    o_ref[rows, cols] = (x_ref[rows, cols].astype(jnp.float32) + y).astype(o_ref.dtype)


def _matmul_partial_kernel(y_ref, w_ref, o_ref, *, m, bm, bn, bk, chunk):
    i, j, s = pl.program_id(0), pl.program_id(1), pl.program_id(2)
    rows, cols = pl.ds(i * bm, bm), pl.ds(j * bn, bn)

    def body(kk, acc):
        ks = pl.ds(s * chunk + kk * bk, bk)
        return acc + _dot(y_ref[rows, ks], w_ref[ks, cols])

    o_ref[pl.ds(s * m + i * bm, bm), cols] = jax.lax.fori_loop(0, chunk // bk, body, jnp.zeros((bm, bn), jnp.float32))


def matmul_residual(y, w, x, mods=None, gate_row: int | None = None, *, splits: int = 1,
                    blocks: Blocks = Blocks()):
    """x + (y @ w) [* mods[gate_row]]: y (M, E), w (E, D), x (M, D); the π0.5 adaRMS gate is a row of mods (R, D).

    splits > 1 (where E splits into multiples of 16): split-K, so that a B=1 GEMM fills the GPU; the kernel writes
    f32 partials and one XLA fusion sums them, rounds to the dtype and applies the gate and the residual (the XLA
    path's ops, in its order).
    """
    m, e = y.shape
    d = w.shape[1]
    if splits > 1 and e % (ALIGN * splits) == 0:
        chunk = e // splits
        bm, bn, bk = _fit(blocks.rows, m), _fit(blocks.out_cols, d), _fit(blocks.k, chunk)
        kernel = functools.partial(_matmul_partial_kernel, m=m, bm=bm, bn=bn, bk=bk, chunk=chunk)
        out = jax.ShapeDtypeStruct((splits * m, d), jnp.float32)
        part = _call(kernel, (m // bm, d // bn, splits), out, blocks, "matmul_partial")(y, w)
        z = part.reshape(splits, m, d).sum(axis=0).astype(x.dtype)
        return x + (z if gate_row is None else z * mods[gate_row])
    bm, bn, bk = _fit(blocks.rows, m), _fit(blocks.out_cols, d), _fit(blocks.k, e)
    kernel = functools.partial(_matmul_residual_kernel, bm=bm, bn=bn, bk=bk, depth=e, gate_row=gate_row)
    mods = jnp.zeros((1, d), x.dtype) if mods is None else mods
    out = jax.ShapeDtypeStruct(x.shape, x.dtype)
    return _call(kernel, (m // bm, d // bn), out, blocks, "matmul_residual")(y, w, x, mods)


# -- norm + gate/up GEMM + GeGLU ---------------------------------------------------------------------------------------
def _norm_geglu_kernel(x_ref, mod_ref, w_ref, o_ref, *, bm, bn, bk, width, n_true, hidden, mod_row, adaptive):
    i, j = pl.program_id(0), pl.program_id(1)
    rows = pl.ds(i * bm, bm)
    dtype = x_ref.dtype
    inv = _inv_rms(x_ref, rows, bm, width, bk, n_true)

    def body(kk, acc):
        ks = pl.ds(kk * bk, bk)
        h = _normed(x_ref, mod_ref, rows, ks, inv, mod_row, adaptive, dtype)
        return (acc[0] + _dot(h, w_ref[ks, pl.ds(j * bn, bn)]),
                acc[1] + _dot(h, w_ref[ks, pl.ds(hidden + j * bn, bn)]))

    zero = jnp.zeros((bm, bn), jnp.float32)
    gate, up = jax.lax.fori_loop(0, width // bk, body, (zero, zero))
    gate = _round(jax.nn.gelu(_round(gate, dtype), approximate=True), dtype)
    o_ref[rows, pl.ds(j * bn, bn)] = (gate * _round(up, dtype)).astype(o_ref.dtype)


def norm_geglu(x, mods, mod_row: int, adaptive: bool, w_gate_up, *, width: int, blocks: Blocks = Blocks()):
    """gelu_tanh(h @ w_gate) * (h @ w_up) with h = norm(x): x (M, D), w_gate_up (D, 2F) = [gate | up] -> (M, F)."""
    m, d = x.shape
    hidden = w_gate_up.shape[1] // 2
    bm, bn, bk = _fit(blocks.rows, m), _fit(blocks.mlp_cols, hidden), _fit(blocks.k, d)
    kernel = functools.partial(_norm_geglu_kernel, bm=bm, bn=bn, bk=bk, width=d, n_true=width, hidden=hidden,
                               mod_row=mod_row, adaptive=adaptive)
    out = jax.ShapeDtypeStruct((m, hidden), x.dtype)
    return _call(kernel, (m // bm, hidden // bn), out, blocks, "norm_geglu")(x, mods, w_gate_up)
