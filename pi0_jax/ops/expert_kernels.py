"""Pallas kernels for one action-expert layer of the denoise step (Triton on GPU, interpret mode on CPU).

At B = 1 the step is 64 rows against 35 MB of weights per layer: every GEMM streams its weights, and what costs is
latency (few programs walking a long K loop, and each launch), not FLOPs. So every GEMM is one kernel split over
output columns and over K (hundreds of short programs, f32 partials), and the program that finishes an output tile
last sums the tile's partials and applies the epilogue (split-K with a last-arrival reduction: one counter per
tile). A layer is five kernels and nothing else:

  norm_qkv_rope    [x * (1 + scale)] @ w_qkv (+ adaRMS's shift @ w), then 1 / rms from the chunks' sums of
                   squares, RoPE on q and k, q's scaling; a program computes a block of one RoPE half and its partner
  attention        the suffix queries over [cached prefix | suffix] keys: an online softmax over each of several key
                   splits in parallel (flash-decoding); the last split of a query block merges them by log-sum-exp
  matmul_residual  y @ w, then adaRMS's gate and the residual (the out-projection and the down-projection)
  norm_geglu       [x * (1 + scale)] @ [w_gate | w_up], then 1 / rms and GELU-tanh(gate) * up; a program computes a
                   block of gate columns and its up partner

The counters: `counters()` is zeros; every kernel takes them and hands them back zeroed (aliased in place, the last
program of a tile resets its counter), so one array threads through a chain of calls. Ordering: a program stores its
partials, then its threads meet at a barrier, then one increments the tile's counter (acquire-release, GPU scope);
the program that sees the count complete reads the partials after that.

Kernel layout (`pi0_jax.ops.layout`): rows are (batch, suffix padded to Sp) flattened; each head is stored as
[x1 | 0 | x2 | 0], the two RoPE halves each padded to hp (a multiple of 16); widths are multiples of 16 (Triton's
smallest dot). Padding is zeros and padded keys are masked, so every valid number is the one the XLA path computes.

Numerics as `pi0_jax.engine.layers`: f32 norm statistics, f32 RoPE, f32 logits and softmax with the same big-negative
fill; every GEMM output is rounded to the activation dtype before its epilogue, as XLA's `x @ w` is, and each
epilogue op rounds where the XLA op would. Three reorderings, each within bf16 rounding of the XLA path and within f32
rounding in f32: x * (1 + scale) enters the GEMM and the row's 1 / rms multiplies its f32 result; adaRMS's shift
enters as its own product shift @ w; attention rounds each key split's normalised output to the dtype and merges the
splits in f32. Partials are summed in split order, as XLA's sum of the list was.

Axis legend: M rows (B * Sp), D width, F MLP hidden, N query heads, K kv heads, hp half head dim (padded), P keys,
S splits.
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
COUNTERS = 4096  # arrival counters: one per output tile of a kernel call


@dataclasses.dataclass(frozen=True)
class Blocks:
    """Tile sizes (powers of two; each is shrunk to divide its padded dimension), split counts and Triton launch
    parameters. Defaults: the fastest of the sweeps at π0 full size, B=1, on an H200 (docs/BENCHMARKS.md, "Fused
    kernels")."""

    rows: int = 64  # GEMM rows per program
    k: int = 256  # GEMM contraction chunk per loop step
    qkv_cols: int = 128  # output columns per program of the q/k/v GEMM (half from each RoPE half)
    qkv_splits: int = 8  # split-K programs per output tile of the q/k/v GEMM
    mlp_cols: int = 64  # the same for the gate/up GEMM (half gate, half up)
    mlp_splits: int = 4
    out_cols: int = 64  # the same for the out-projection and the down-projection
    out_splits: int = 4
    down_splits: int = 8
    q: int = 64  # attention queries per program
    kv: int = 64  # attention keys per loop step
    kv_splits: int = 13  # programs that share one query block's prefix keys (+ one for the suffix keys)
    num_warps: int = 4  # the GEMM kernel's
    attention_warps: int = 8
    num_stages: int = 3


def counters():
    """Zeroed arrival counters for a chain of kernel calls."""
    return jnp.zeros((COUNTERS,), jnp.int32)


def _on_cpu() -> bool:
    return jax.default_backend() == "cpu"


def _fit(block: int, n: int) -> int:
    """The largest power of two <= block that divides n."""
    while n % block:
        block //= 2
    return block


def _call(kernel, grid, tiles: int, inputs, out_shape, blocks: Blocks, name: str, num_warps: int | None = None):
    """pallas_call with the counters as the last input and the first output (aliased)."""
    if tiles > COUNTERS:
        raise ValueError(f"{name}: {tiles} output tiles need more than COUNTERS = {COUNTERS} arrival counters")
    on_cpu = _on_cpu()
    params = None if on_cpu else plgpu.CompilerParams(num_warps=num_warps or blocks.num_warps,
                                                      num_stages=blocks.num_stages)
    out_shape = [jax.ShapeDtypeStruct((COUNTERS,), jnp.int32), *out_shape]
    return pl.pallas_call(kernel, grid=grid, out_shape=out_shape, interpret=on_cpu, compiler_params=params,
                          name=name, input_output_aliases={len(inputs) - 1: 0})(*inputs)


def _arrived_last(count_ref, tile, arrivals: int):
    """Counts this program's arrival at `tile`: true in the last of `arrivals` programs (which then `_reset`s)."""
    if not _on_cpu():
        plgpu.debug_barrier()  # every thread's stores of this program before its arrival
    return plgpu.atomic_add(count_ref, (tile,), jnp.ones((), jnp.int32)) == arrivals - 1


def _reset(count_ref, tile, arrivals: int):
    plgpu.atomic_add(count_ref, (tile,), jnp.full((), -arrivals, jnp.int32))


def _total(ref, index, splits: int):
    """sum over t < splits of ref[index(t)] in f32, in split order. Unrolled, so that every load is in flight at once
    (a loop waits for each). Plain loads: only this program reads the tile's partials, once, so its SM's L1 holds no
    stale copy (volatile loads, tried, were slower)."""
    return functools.reduce(lambda a, t: a + ref[index(t)], range(1, splits), ref[index(0)])


def _scaled(x_ref, mod_ref, rows, cols, mod_row, dtype):
    """One tile of x in f32 (for the statistics) and of x * (1 + scale) in the dtype (the GEMM input of a norm, before
    the row's 1 / rms). (1 + scale) is formed in the scale's dtype first, as the reference does."""
    x = x_ref[rows, cols].astype(jnp.float32)
    return x, (x * (1 + mod_ref[pl.ds(mod_row, 1), cols]).astype(jnp.float32)).astype(dtype)


def _dot(a, b, trans_b: bool = False):
    """a @ b (or a @ b.T) with an f32 accumulator; f32 operands multiply in full f32 (Triton's IEEE mode)."""
    dims = (((1,), (1 if trans_b else 0,)), ((), ()))
    return jax.lax.dot_general(a, b, dims, preferred_element_type=jnp.float32)


def _round(acc, dtype):
    """A GEMM's f32 accumulator as XLA returns `x @ w`: rounded to the activation dtype (kept in f32 to compute)."""
    return acc.astype(dtype).astype(jnp.float32)


def _select(flag, a, b):
    """flag ? a : b for a scalar flag by arithmetic, exact for finite a and b (Triton rejects a select whose predicate
    is a scalar and whose operands are tiles)."""
    f = flag.astype(jnp.float32)
    return f * a + (1 - f) * b


# -- split-K GEMM with a norm's prologue and one of three epilogues -------------------------------------------------
def _gemm_kernel(y_ref, mod_ref, w_ref, cos_ref, sin_ref, x_ref, _, count_ref, out_ref, parts_ref, ss_ref, shift_ref,
                 *, m, bm, bn, bk, chunk, splits, nj, pair, mod_row, gate_row, scaled, adaptive, epilogue, width,
                 num_heads, num_rotary, q_scale):
    """Program (i, j, s): rows block i, output tile j, K chunk s. A tile is bn columns, or with `pair` the bn columns
    at c and their partners at c + pair (c in the first half of a 2 * pair group: a RoPE half, or gate vs up). The
    program stores y' @ w over its chunk (y' = y, or y * (1 + scale) when scaled), the chunk's sum of squares of y per
    row (scaled) and shift @ w (adaptive: 16 equal rows, a dot needs 16); the tile's last program applies `epilogue`."""
    i, j, s = pl.program_id(0), pl.program_id(1), pl.program_id(2)
    ni = m // bm
    rows = pl.ds(i * bm, bm)
    dtype = y_ref.dtype
    if pair:
        first = jax.lax.div(j * bn, pair) * 2 * pair + jax.lax.rem(j * bn, pair)
        cols = (pl.ds(first, bn), pl.ds(first + pair, bn))
    else:
        cols = (pl.ds(j * bn, bn),)

    def body(kk, acc):
        prods, ss, shifts = acc
        ks = pl.ds(s * chunk + kk * bk, bk)
        ws = [w_ref[ks, c] for c in cols]
        if scaled:
            x, h = _scaled(y_ref, mod_ref, rows, ks, mod_row, dtype)
            ss = ss + jnp.sum(x * x, axis=1)
        else:
            h = y_ref[rows, ks]
        prods = tuple(p + _dot(h, w) for p, w in zip(prods, ws))
        if adaptive:
            shift = jnp.broadcast_to(mod_ref[pl.ds(mod_row + 1, 1), ks], (ALIGN, bk))
            shifts = tuple(a + _dot(shift, w) for a, w in zip(shifts, ws))
        return prods, ss, shifts

    zeros = tuple(jnp.zeros((bm, bn), jnp.float32) for _ in cols)
    shifts0 = tuple(jnp.zeros((ALIGN, bn), jnp.float32) for _ in cols) if adaptive else ()
    prods, ss, shifts = jax.lax.fori_loop(0, chunk // bk, body, (zeros, jnp.zeros((bm,), jnp.float32), shifts0))
    for c, p in zip(cols, prods):
        parts_ref[pl.ds(s * m + i * bm, bm), c] = p
    if scaled:
        ss_ref[pl.ds((s * nj + j) * m + i * bm, bm)] = ss
    for c, a in zip(cols, shifts):
        shift_ref[pl.ds((s * ni + i) * ALIGN, ALIGN), c] = a

    tile = i * nj + j

    @pl.when(_arrived_last(count_ref, tile, splits))
    def _epilogue():
        _reset(count_ref, tile, splits)
        accs = [_total(parts_ref, lambda t, c=c: (pl.ds(t * m + i * bm, bm), c), splits) for c in cols]
        if scaled:
            ss_sum = _total(ss_ref, lambda t: (pl.ds((t * nj + j) * m + i * bm, bm),), splits)
            inv = jax.lax.rsqrt(ss_sum / width + EPS)[:, None]
            accs = [a * inv for a in accs]
        if adaptive:
            accs = [a + _total(shift_ref, lambda t, c=c: (pl.ds((t * ni + i) * ALIGN, 1), c), splits)
                    for a, c in zip(accs, cols)]
        if epilogue == "rope":
            # RoPE in f32, then the dtype, for q and k heads (v heads take cos 1, sin 0: exactly the identity);
            # q is then scaled in the dtype (q_scale is a dtype value)
            head, off = jax.lax.div(j * bn, pair), jax.lax.rem(j * bn, pair)
            a1, a2 = (_round(a, dtype) for a in accs)
            rotary = head < num_rotary
            c = _select(rotary, cos_ref[rows, pl.ds(off, bn)], 1.0)
            sn = _select(rotary, sin_ref[rows, pl.ds(off, bn)], 0.0)
            scale = _select(head < num_heads, q_scale, 1.0)
            out_ref[rows, cols[0]] = (_round(a1 * c - a2 * sn, dtype) * scale).astype(out_ref.dtype)
            out_ref[rows, cols[1]] = (_round(a2 * c + a1 * sn, dtype) * scale).astype(out_ref.dtype)
        elif epilogue == "geglu":
            gate = _round(jax.nn.gelu(_round(accs[0], dtype), approximate=True), dtype)
            out_ref[rows, pl.ds(j * bn, bn)] = (gate * _round(accs[1], dtype)).astype(out_ref.dtype)
        else:  # residual: the split sum in the dtype, adaRMS's gate, the residual (the XLA path's ops, in its order)
            z = accs[0].astype(out_ref.dtype)
            if gate_row is not None:
                z = z * mod_ref[pl.ds(gate_row, 1), cols[0]]
            out_ref[rows, cols[0]] = x_ref[rows, cols[0]] + z


def _gemm(y, w, counts, *, epilogue: str, cols: int, splits: int, blocks: Blocks, mods=None, mod_row: int = 0,
          gate_row: int | None = None, scaled: bool = False, adaptive: bool = False, pair: int = 0, cos=None,
          sin=None, x=None, width: int = 0, num_heads: int = 0, num_rotary: int = 0, q_scale: float = 1.0):
    """y (M, E) @ w (E, N) split over K into `splits` chunks (1 where E does not split into multiples of 16), each
    program `cols` output columns (half of them partners with pair), then the epilogue -> (out, counts)."""
    m, e = y.shape
    n = w.shape[1]
    splits = splits if e % (ALIGN * splits) == 0 else 1
    chunk = e // splits
    bm, bk = _fit(blocks.rows, m), _fit(blocks.k, chunk)
    bn = _fit(cols // 2, pair) if pair else _fit(cols, n)
    nj = (n // 2 if pair else n) // bn
    out_cols = n // 2 if epilogue == "geglu" else n
    out_dtype = x.dtype if epilogue == "residual" else y.dtype
    dummy = jnp.zeros((1, ALIGN), jnp.float32)
    kernel = functools.partial(
        _gemm_kernel, m=m, bm=bm, bn=bn, bk=bk, chunk=chunk, splits=splits, nj=nj, pair=pair, mod_row=mod_row,
        gate_row=gate_row, scaled=scaled, adaptive=adaptive, epilogue=epilogue, width=width, num_heads=num_heads,
        num_rotary=num_rotary, q_scale=q_scale)
    out = [jax.ShapeDtypeStruct((m, out_cols), out_dtype), jax.ShapeDtypeStruct((splits * m, n), jnp.float32),
           jax.ShapeDtypeStruct((splits * nj * m,) if scaled else (ALIGN,), jnp.float32),
           jax.ShapeDtypeStruct((splits * (m // bm) * ALIGN, n) if adaptive else (ALIGN, ALIGN), jnp.float32)]
    mods = jnp.zeros((1, ALIGN), y.dtype) if mods is None else mods
    inputs = (y, mods, w, dummy if cos is None else cos, dummy if sin is None else sin, dummy if x is None else x,
              counts)
    counts, res, *_ = _call(kernel, (m // bm, nj, splits), (m // bm) * nj, inputs, out, blocks, f"gemm_{epilogue}")
    return res, counts


def norm_qkv_rope(x, mods, mod_row: int, adaptive: bool, w_qkv, cos, sin, *, counts, width: int, num_heads: int,
                  num_kv_heads: int, head_dim: int, blocks: Blocks = Blocks()):
    """x (M, D) -> (qkv (M, (N + 2K) * 2hp), counts): normed, projected, q/k rotated, q scaled by head_dim^-0.5.

    mods (R, D): row mod_row is the norm scale, +1 the adaRMS shift (adaptive); w_qkv (D, (N + 2K) * 2hp);
    cos / sin (M, hp) f32 (`layout.rope_tables`); width: the true D (the mean's divisor).
    """
    return _gemm(x, w_qkv, counts, epilogue="rope", cols=blocks.qkv_cols, splits=blocks.qkv_splits, blocks=blocks,
                 mods=mods, mod_row=mod_row, scaled=True, adaptive=adaptive, pair=cos.shape[1], cos=cos, sin=sin,
                 width=width, num_heads=num_heads, num_rotary=num_heads + num_kv_heads,
                 q_scale=float(np.asarray(head_dim**-0.5, x.dtype)))


def matmul_residual(y, w, x, mods=None, gate_row: int | None = None, *, counts, splits: int,
                    blocks: Blocks = Blocks()):
    """(x + (y @ w) [* mods[gate_row]], counts): y (M, E), w (E, D), x (M, D); the π0.5 adaRMS gate is a row of
    mods (R, D)."""
    return _gemm(y, w, counts, epilogue="residual", cols=blocks.out_cols, splits=splits, blocks=blocks, mods=mods,
                 gate_row=gate_row, x=x)


def norm_geglu(x, mods, mod_row: int, adaptive: bool, w_gate_up, *, counts, width: int, blocks: Blocks = Blocks()):
    """(gelu_tanh(h @ w_gate) * (h @ w_up), counts) with h = norm(x): x (M, D), w_gate_up (D, 2F) = [gate | up] ->
    (M, F)."""
    return _gemm(x, w_gate_up, counts, epilogue="geglu", cols=blocks.mlp_cols, splits=blocks.mlp_splits,
                 blocks=blocks, mods=mods, mod_row=mod_row, scaled=True, adaptive=adaptive,
                 pair=w_gate_up.shape[1] // 2, width=width)


# -- attention over [cached prefix | suffix] ---------------------------------------------------------------------------
def _attention_kernel(qkv_ref, ck_ref, cv_ref, pmask_ref, smask_ref, _, count_ref, y_ref, o_ref, lse_ref, *, m, bq,
                      bkv, sp, pp, hd, num_heads, num_kv_heads, splits, per_split):
    """Program (b, n, qi, s): query block qi of head n over prefix key blocks [s * per_split, (s + 1) * per_split)
    (s < splits; blocks past the cache are masked), or over the suffix keys (s == splits). Stores the split's
    normalised output (in the dtype) and its log-sum-exp (f32); the block's last program merges the splits."""
    b, n, qi, s = pl.program_id(0), pl.program_id(1), pl.program_id(2), pl.program_id(3)
    kh = jax.lax.div(n, num_heads // num_kv_heads) if num_kv_heads > 1 else 0  # this query head's kv head
    rows = pl.ds(b * sp + qi * bq, bq)
    head = pl.ds(n * hd, hd)
    q = qkv_ref[rows, head]
    dtype = q.dtype
    blocks = pp // bkv

    def update(carry, k, v, valid):
        o, mx, l = carry
        logits = jnp.where(valid, _dot(q, k, trans_b=True), BIG_NEG)  # f32
        m_new = jnp.maximum(mx, jnp.max(logits, axis=1))
        corr = jnp.exp(mx - m_new)
        p = jnp.exp(logits - m_new[:, None])
        return o * corr[:, None] + _dot(p.astype(dtype), v), m_new, l * corr + jnp.sum(p, axis=1)

    def part(t):
        return pl.ds(t * m + b * sp + qi * bq, bq)

    def write(carry):
        o, mx, l = carry
        o_ref[part(s), head] = (o / l[:, None]).astype(o_ref.dtype)
        lse_ref[part(s), pl.ds(n, 1)] = (mx + jnp.log(l))[:, None]

    init = (jnp.zeros((bq, hd), jnp.float32), jnp.full((bq,), BIG_NEG, jnp.float32), jnp.zeros((bq,), jnp.float32))

    @pl.when(s < splits)
    def _prefix():
        def block(t, carry):
            t = s * per_split + t
            tc = jnp.minimum(t, blocks - 1)  # a block past the cache reads the last one, all masked
            keys = pl.ds(b * pp + tc * bkv, bkv)
            valid = (pmask_ref[pl.ds(b, 1), pl.ds(tc * bkv, bkv)] != 0) & (t < blocks)
            return update(carry, ck_ref[keys, pl.ds(kh * hd, hd)], cv_ref[keys, pl.ds(kh * hd, hd)], valid)

        write(jax.lax.fori_loop(0, per_split, block, init))

    @pl.when(s == splits)
    def _suffix():
        suffix = pl.ds(b * sp, sp)
        k_col, v_col = (num_heads + kh) * hd, (num_heads + num_kv_heads + kh) * hd
        write(update(init, qkv_ref[suffix, pl.ds(k_col, hd)], qkv_ref[suffix, pl.ds(v_col, hd)],
                     smask_ref[rows, :] != 0))

    tile = (b * num_heads + n) * (sp // bq) + qi

    @pl.when(_arrived_last(count_ref, tile, splits + 1))
    def _merge():  # sum_s exp(lse_s - max) o_s / sum_s exp(lse_s - max); a split with every key masked weighs 0
        _reset(count_ref, tile, splits + 1)

        def lse(t):
            return lse_ref[part(t), pl.ds(n, 1)]

        lses = [lse(t) for t in range(splits + 1)]  # unrolled: every load in flight at once
        top = functools.reduce(jnp.maximum, lses)
        weights = [jnp.exp(x - top) for x in lses]
        num = functools.reduce(lambda a, t: a + weights[t] * o_ref[part(t), head].astype(jnp.float32),
                                range(1, splits + 1), weights[0] * o_ref[part(0), head].astype(jnp.float32))
        den = functools.reduce(lambda a, w: a + w, weights[1:], weights[0])
        y_ref[rows, head] = (num / den).astype(y_ref.dtype)


def attention(qkv, cache_k, cache_v, prefix_mask, suffix_mask, *, counts, batch: int, num_heads: int,
              num_kv_heads: int, blocks: Blocks = Blocks()):
    """Softmax attention of the suffix queries over [cached prefix | suffix] keys -> ((M, N * 2hp), counts).

    qkv (M, (N + 2K) * 2hp) from `norm_qkv_rope`; cache_k / cache_v (B * P, K * 2hp); prefix_mask (B, P) int32, the
    same for every query; suffix_mask (M, Sp) int32, query row -> suffix key. The prefix keys are split over
    `blocks.kv_splits` programs per query block, the suffix keys take one more; the splits' softmaxes are merged
    by their log-sum-exp. A split whose keys are all masked has a log-sum-exp of about BIG_NEG and weight 0.
    """
    m, sp = suffix_mask.shape
    hd = qkv.shape[1] // (num_heads + 2 * num_kv_heads)
    pp = prefix_mask.shape[1]
    bq, bkv = _fit(blocks.q, sp), _fit(blocks.kv, pp)
    splits = max(1, min(blocks.kv_splits, pp // bkv))
    per_split = -(-(pp // bkv) // splits)
    kernel = functools.partial(_attention_kernel, m=m, bq=bq, bkv=bkv, sp=sp, pp=pp, hd=hd, num_heads=num_heads,
                               num_kv_heads=num_kv_heads, splits=splits, per_split=per_split)
    out = (jax.ShapeDtypeStruct((m, num_heads * hd), qkv.dtype),
           jax.ShapeDtypeStruct(((splits + 1) * m, num_heads * hd), qkv.dtype),
           jax.ShapeDtypeStruct(((splits + 1) * m, num_heads), jnp.float32))
    inputs = (qkv, cache_k, cache_v, prefix_mask, suffix_mask, counts)
    counts, y, *_ = _call(kernel, (batch, num_heads, sp // bq, splits + 1), batch * num_heads * (sp // bq), inputs,
                          out, blocks, "expert_attention", blocks.attention_warps)
    return y, counts
