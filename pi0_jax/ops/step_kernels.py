"""Pallas kernels at the two ends of a denoise step (Triton on GPU, interpret mode on CPU): the noisy actions into
the expert's rows, and the expert's last rows into the next actions.

Between one step's last layer and the next step's first layer XLA ran 13 small kernels, about 30 µs of kernels and
as many gaps on an H100 (docs/BENCHMARKS.md, "The denoise loop as a program of its own"): the action
out-projection, the Euler update, the in-projection and its bias, the time MLP's two GEMMs with the time row and
swish, the carry's copies and the rows' padding. Here they are two kernels (the final norm stays in the XLA fusion
of the last layer's residual):

  expert_rows  action rows x -> the expert's input rows in the dtype: π0: swish(x @ w_in + table[step]) @ w_out +
               b_out (the time MLP), its state token's row before the actions; π0.5: x @ w_in + table[0]
  euler        the final-normed rows h -> x + dt (h @ w + b) on the action rows

Action rows: the loop carries the actions as (B Sp, Ap) f32, element b's action a at row b Sp + offset + a (offset
1 for π0, whose row 0 is its state token; 0 for π0.5), every other row and column zero, the expert's own row
layout (`ops.layout.rows`), so neither end needs a pad, a slice or a copy.

Numerics as the XLA path's (`engine.programs.step_velocity`): every product in f32 (a dtype operand is promoted
first), with the dot precision XLA gives an f32 GEMM by default (TF32 on a GPU: `pallas_base.dot`), the biases and
the time row added in f32, swish in f32, the rows rounded to the dtype last. The time MLP's first GEMM has the
in-projection folded into it (`engine.weights.prepare`: w_in = in-projection @ the MLP's action half, its bias into
the table), so K is the action dim.

Axis legend: B batch, Sp suffix rows an element (padded), A action dim (Ap padded), D width (Dp padded), T steps.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl

from pi0_jax.ops import layout, pallas_base
from pi0_jax.ops.pallas_base import dot, fit


def action_rows(x, sp: int, offset: int):
    """Actions (B, H, A) -> action rows (B Sp, Ap) f32: rows [offset, offset + H) of each element, zeros elsewhere."""
    b, h, a = x.shape
    x = jnp.pad(x.astype(jnp.float32), ((0, 0), (offset, sp - offset - h), (0, layout.padded(a) - a)))
    return x.reshape(b * sp, -1)


def actions(rows, batch: int, horizon: int, action_dim: int, offset: int):
    """The inverse of `action_rows`: (B Sp, Ap) -> (B, H, A)."""
    return rows.reshape(batch, -1, rows.shape[1])[:, offset:offset + horizon, :action_dim]


def _action_mask(first_row, n: int, sp: int, offset: int, horizon: int):
    """(n, 1) bool: which of the n rows from first_row hold an action."""
    r = (first_row + jax.lax.broadcasted_iota(jnp.int32, (n, 1), 0)) % sp
    return (r >= offset) & (r < offset + horizon)


def _rows_kernel(step_ref, x_ref, w_in_ref, table_ref, *refs, sp, bn, bk, k_in, offset, horizon, mlp, state):
    """Program (b, j): element b's Sp rows, output columns block j. With the MLP the hidden units run in chunks of
    bk: each chunk's swish(x @ w_in + table row) @ w_out adds into the block (the chunk is recomputed by every
    column block: its K is the action dim)."""
    o_ref = refs[-1]
    b, j = pl.program_id(0), pl.program_id(1)
    rows, cols = pl.ds(b * sp, sp), pl.ds(j * bn, bn)
    x = x_ref[rows, :]
    t = step_ref[0]
    if mlp:
        w_out_ref, b_out_ref = refs[:2]

        def body(kk, acc):
            ks = pl.ds(kk * bk, bk)
            h = dot(x, w_in_ref[:, ks]) + table_ref[pl.ds(t, 1), ks]
            return acc + dot(h * jax.nn.sigmoid(h), w_out_ref[ks, cols])

        y = jax.lax.fori_loop(0, k_in // bk, body, jnp.zeros((sp, bn), jnp.float32)) + b_out_ref[:, cols]
    else:
        y = dot(x, w_in_ref[:, cols]) + table_ref[pl.ds(t, 1), cols]
    y = y.astype(o_ref.dtype)
    keep = _action_mask(0, sp, sp, offset, horizon)
    out = jnp.where(keep, y, jnp.zeros_like(y))
    if state:
        first = jax.lax.broadcasted_iota(jnp.int32, (sp, 1), 0) == 0
        out = jnp.where(first, refs[-2][pl.ds(b, 1), cols].astype(o_ref.dtype), out)
    o_ref[rows, cols] = out


def expert_rows(x, w_in, table, step, *, batch: int, horizon: int, offset: int, dtype, mlp=None, state=None,
                cols: int = 32, k: int = 128, num_warps: int = 4):
    """Action rows x (B Sp, Ap) f32 -> the expert's input rows (B Sp, Dp) in `dtype`, zero but for the actions' (and
    the state's) rows.

    w_in (Ap, Dp) f32; table (T, Dp) f32, its row `step` (an int32 scalar, traced or not) added to x @ w_in;
    mlp: None (π0.5: the rows are x @ w_in + table[step]) or π0's time MLP (w_out (Dp, Dp), b_out (1, Dp)) f32:
    swish(x @ w_in + table[step]) @ w_out + b_out; state (B, Dp) f32 or None: π0's state token, row offset - 1 = 0.
    cols: output columns a program; k: hidden units a step of the MLP's loop."""
    m, dp = x.shape[0], w_in.shape[1]
    sp = m // batch
    if state is not None and offset != 1:
        raise ValueError(f"the state token is row 0 of an element: its actions start at row 1, not {offset}")
    bn, bk = fit(cols, dp), fit(k, dp)
    kernel = functools.partial(_rows_kernel, sp=sp, bn=bn, bk=bk, k_in=dp, offset=offset, horizon=horizon,
                               mlp=mlp is not None, state=state is not None)
    args = (jnp.asarray(step, jnp.int32).reshape(1), x, w_in, table, *(mlp or ()),
            *(() if state is None else (state,)))
    out = jax.ShapeDtypeStruct((m, dp), dtype)
    return pallas_base.call(kernel, grid=(batch, dp // bn), out_shape=out, name="expert_rows",
                            num_warps=num_warps, num_stages=2)(*args)


def _euler_kernel(h_ref, x_ref, w_ref, b_ref, o_ref, *, bm, bk, k_in, sp, offset, horizon, dt):
    """Program i: rows block i: x + dt (h @ w + b) on its action rows, zero elsewhere."""
    i = pl.program_id(0)
    rows = pl.ds(i * bm, bm)

    def body(kk, acc):
        ks = pl.ds(kk * bk, bk)
        return acc + dot(h_ref[rows, ks].astype(jnp.float32), w_ref[ks, :])

    v = jax.lax.fori_loop(0, k_in // bk, body, jnp.zeros((bm, w_ref.shape[1]), jnp.float32)) + b_ref[...]
    x = x_ref[rows, :]
    nxt = x + jnp.float32(dt) * v   # dt * v in f32, then the add: the XLA path's order
    o_ref[rows, :] = jnp.where(_action_mask(i * bm, bm, sp, offset, horizon), nxt, jnp.zeros_like(nxt))


def euler(h, x, w, b, dt: float, *, batch: int, horizon: int, offset: int, rows: int = 16, k: int = 128,
          num_warps: int = 4):
    """One Euler step on the action rows: h (B Sp, D) the expert's final-normed rows in the dtype, x (B Sp, Ap) f32
    action rows, w (D, Ap) and b (1, Ap) f32 the action out-projection -> x + dt (h @ w + b), zero but for the
    action rows. rows: rows a program; k: a step of its K loop."""
    m, d = h.shape
    bm, bk = fit(rows, m), fit(k, d)
    kernel = functools.partial(_euler_kernel, bm=bm, bk=bk, k_in=d, sp=m // batch, offset=offset, horizon=horizon,
                               dt=float(dt))
    out = jax.ShapeDtypeStruct(x.shape, jnp.float32)
    return pallas_base.call(kernel, grid=(m // bm,), out_shape=out, name="expert_euler", num_warps=num_warps,
                            num_stages=2)(h, x, w, b)
