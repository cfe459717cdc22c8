"""Pallas kernels for one action-expert layer of the denoise step (Triton on GPU, interpret mode on CPU): its GEMMs,
and the launch of every expert kernel (`Blocks`; the attention's kernels are `ops.expert_attention`).

At B = 1 the step is 64 rows against 35 MB of weights per layer: every GEMM streams its weights, and what costs is
latency (few programs walking a long K loop), not FLOPs. So every GEMM is one kernel, split over output columns and
over K (hundreds of short programs, f32 partials), and the cheap elementwise work lands in one XLA fusion after it:

  matmul_partials  [x * (1 + scale)] @ w over one K chunk, plus the chunk's sum of squares (the norm's statistics)
                   and adaRMS's shift @ w: the norm is applied after the GEMM, as a per-row 1 / rms

  norm_qkv_rope    = matmul_partials, then (XLA) the split sum, 1 / rms, RoPE and q's scaling
  norm_geglu       = matmul_partials, then (XLA) the split sum, 1 / rms, GELU-tanh(gate) * up
  matmul_residual  = matmul_partials, then (XLA) the split sum, adaRMS's gate and the residual

Any of the four GEMMs may instead run `ops.mosaic_gemm` (a TMA-pipelined Mosaic GPU kernel, bf16 on Hopper): the
Blocks field mosaic_<gemm> names its launch; gate/up's may end in GeGLU. Its GEMM is plain, so a norm before it is
one XLA fusion in `layers.rms_norm`'s order, and the product is the XLA path's to f32 rounding. (The norm inside
the kernel, as the Triton prologue, cost gate/up 3 us and did not pay for q/k/v: docs/BENCHMARKS.md, "A Mosaic GPU
GEMM".) q/k/v's launch with `rope` is `mosaic_gemm.qkv_rope` instead: the rows' sums of squares, 1 / rms, RoPE
and q's scale inside the kernel, which takes x and x * (1 + scale) (an output of the residual pass before it), and
π0.5's adaRMS shift in a padding row, and leaves no pass after it (π0 151 kernels a step against 169, π0.5 154
against 170, compiled for an H100 or H200; not yet timed).

Kernel layout (`pi0_jax.ops.layout`): rows are (batch, suffix padded to Sp) flattened; each head is stored as
[x1 | 0 | x2 | 0], the two RoPE halves each padded to hp (a multiple of 16); widths are multiples of 16 (Triton's
smallest dot). Padding is zeros, so every valid number is the one the XLA path computes.

Numerics as `pi0_jax.engine.layers`: f32 norm statistics, f32 RoPE; every GEMM output is rounded to the activation
dtype before its epilogue, as XLA's `x @ w` is, and each epilogue op rounds where the XLA op would. Two reorderings,
each within bf16 rounding of the XLA path and within f32 rounding in f32: x * (1 + scale) enters the GEMM and the
row's 1 / rms multiplies its f32 result; adaRMS's shift enters as its own product shift @ w.

Axis legend: M rows (B * Sp), D width, F MLP hidden, N query heads, K kv heads, hp half head dim (padded), S splits.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import pallas as pl

from pi0_jax.ops import layout, mosaic_gemm, pallas_base
from pi0_jax.ops.mosaic_gemm import Launch
from pi0_jax.ops.pallas_base import ALIGN, dot, fit

EPS = 1e-6


@dataclasses.dataclass(frozen=True)
class Gemm:
    """One split-K GEMM's launch: output columns per program, K chunks per output tile (one program each), and
    Triton's software-pipelining depth (a K loop of several steps gets a shared-memory tile pair per stage, so a
    deeper pipeline leaves room for fewer programs per SM)."""

    cols: int
    splits: int
    stages: int = 3


@dataclasses.dataclass(frozen=True)
class Step:
    """A denoise step's rows in a stack of every step's tables (T R, D): the step (an int32 scalar, traced in the
    loop) and a table's rows, R. The split-K kernel takes the stack whole and reads the step's rows in place: a
    step's table sliced out for it would be a copy in every step, as a custom call's operand is a buffer of its own
    (XLA's async memcpy of the slice, docs/BENCHMARKS.md, session 80). XLA's ops read a row as a dynamic index,
    which fuses."""

    index: jax.Array
    rows: int

    def row(self, mods, r: int):
        at = self.index * self.rows + r
        return jax.lax.dynamic_index_in_dim(mods, at, keepdims=False, allow_negative_indices=False)


def table_row(mods, r: int, step: Step | None):
    """Row r of a table (step None), or of the step's table in a stack."""
    return mods[r] if step is None else step.row(mods, r)


@dataclasses.dataclass(frozen=True)
class Blocks:
    """Tile sizes (powers of two; each is shrunk to divide its padded dimension), split counts and Triton launch
    parameters. Defaults: the fastest of the sweeps at π0 full size, B=1, on an H200 (docs/BENCHMARKS.md, "Fused
    kernels"), then of sweeps inside the 10-step denoise on H100s: gate/up at 128 columns without pipelining took
    π0's step 3-4 % faster on two machines and was level on a third and for π0.5 ("Launch parameters inside the
    step"); no other tiling, split count or depth moved the step by more than 1 %. On Hopper, gate/up runs the Mosaic
    GPU kernel with GeGLU in its epilogue: π0's step 4.7 % and π0.5's 9.5 % faster on an H200; the other three
    GEMMs on it were 1-3 % slower, each needing its norm or sum apart ("A Mosaic GPU GEMM"). q/k/v at 4 splits (80
    programs, one wave on 132 SMs, half the partials to sum; 8 splits were 160 programs): π0's 10-step denoise 1.7-3 %
    and π0.5's 4.6-5.2 % faster on an H100 ("Gate/up on 128 CTAs", session 31)."""

    rows: int = 64  # GEMM rows per program
    k: int = 256  # GEMM contraction chunk per loop step
    qkv: Gemm = Gemm(128, 4)
    mlp: Gemm = Gemm(128, 4, 1)  # gate/up
    out: Gemm = Gemm(64, 4)  # the attention's out-projection (at 32 columns its kernel is faster, the call level)
    down: Gemm = Gemm(64, 8)
    q: int = 64  # attention queries per program
    kv: int = 64  # attention keys per loop step
    kv_splits: int = 13  # programs that share one query block's prefix keys (+ one for the suffix keys)
    num_warps: int = 4  # the GEMM kernel's
    attention_warps: int = 8
    attention_stages: int = 3
    # the XLA expert's call (`layers._attend_kernel`): a kv head's query heads folded into its query rows
    fold: bool = False
    # a GEMM as `ops.mosaic_gemm` with this launch where it applies (bf16 on Hopper), None: the Triton kernel
    mosaic_qkv: Launch | None = None
    mosaic_mlp: Launch | None = Launch(64, 1, 6, geglu=True)
    mosaic_out: Launch | None = None
    mosaic_down: Launch | None = None
    # the attention's key splits as `ops.mosaic_attention` (TMA, wgmma) where it applies, and their merge as XLA's ops
    # instead of the Pallas merge kernel: with the four Mosaic GEMMs, an expert that needs no Triton (`TRITON_FREE`)
    mosaic_attention: bool = False
    xla_merge: bool = False

    @classmethod
    def from_dict(cls, d: dict) -> "Blocks":
        """The inverse of `dataclasses.asdict` (a benchmark's JSON)."""
        return cls(**{k: (Launch if k.startswith("mosaic_") else Gemm)(**v) if isinstance(v, dict) else v
                      for k, v in d.items()})


# the XLA expert's attention folds a kv head's query heads into its rows from this batch (`blocks_at`)
FOLD_FROM = 8


def blocks_at(batch: int, blocks: Blocks | None = None) -> Blocks:
    """The XLA expert's launch of the attention kernel at this batch (`engine.layers._attend_kernel`): the key splits
    shared out over the elements, whose (element, head) programs fill the GPU themselves, so the merge reads fewer
    split outputs; 4 warps a program (the 10-step denoise 5.5-9 % faster than with 8 at B = 4, 8 and 16 on an H100,
    level at B = 1: docs/BENCHMARKS.md, "The Pallas attention in the XLA expert"); from B = 8 a kv head's query
    heads folded into its rows (π0's 10-step denoise 1.1-2 % and π0.5's 3.5 % faster at B = 8 on an H200, π0's
    level at B = 16 and 0.8 % slower at B = 4: "Query heads folded into the kernel's rows", session 32). The Mosaic
    kernel instead keeps half the base launch's splits at any batch (π0: two key blocks a CTA), as its ring of two
    slots runs long splits slowly (π0's denoise at B = 8 without Triton 17.70 ms against 18.87 with the Triton
    kernel's 3 parts: "The Mosaic attention with a pipelined key run", session 37). blocks: the base launch (None:
    this jax's, `default_blocks`)."""
    blocks = default_blocks() if blocks is None else blocks
    splits = blocks.kv_splits // 2 if blocks.mosaic_attention else round(blocks.kv_splits / batch)
    return dataclasses.replace(blocks, kv_splits=max(1, splits), attention_warps=4, fold=batch >= FOLD_FROM)


def attention_blocks(batch: int, xla_expert: bool) -> Blocks:
    """The launch the denoise attention takes in a program of this batch: the XLA expert's (`blocks_at`), or the
    Pallas expert's own (`default_blocks`)."""
    return blocks_at(batch) if xla_expert else default_blocks()


# An expert with no Triton kernel: every GEMM on Mosaic GPU at its fastest launch alone (docs/BENCHMARKS.md, "A Mosaic
# GPU GEMM"), the attention on `ops.mosaic_attention`, the splits' merge as XLA's ops (bf16 on Hopper: elsewhere a
# GEMM falls back to the Triton kernel)
TRITON_FREE = Blocks(mosaic_qkv=Launch(64, 2, 6), mosaic_out=Launch(64, 8, 4), mosaic_down=Launch(64, 8, 4),
                     mosaic_attention=True, xla_merge=True)


def default_blocks() -> Blocks:
    """The Pallas expert's launch on this jax: `Blocks()`, or `TRITON_FREE` on a jax without Pallas's Triton backend."""
    return Blocks() if pallas_base.TRITON else TRITON_FREE


def _scaled(x_ref, mod_ref, rows, cols, mod_row, dtype):
    """One tile of x in f32 (for the statistics) and of x * (1 + scale) in the dtype (the GEMM input of a norm, before
    the row's 1 / rms). (1 + scale) is formed in the scale's dtype first, as the reference does. mod_row may be
    traced (a row of a stack of steps' tables)."""
    x = x_ref[rows, cols].astype(jnp.float32)
    return x, (x * (1 + mod_ref[pl.ds(mod_row, 1), cols]).astype(jnp.float32)).astype(dtype)


def _round(acc, dtype):
    """A GEMM's f32 accumulator as XLA returns `x @ w`: rounded to the activation dtype (kept in f32 to compute)."""
    return acc.astype(dtype).astype(jnp.float32)


# -- split-K GEMM (with a norm's prologue) --------------------------------------------------------------------------
def _partials_kernel(*refs, m, bm, bn, bk, chunk, mod_row, scaled, adaptive, step_rows):
    """Program (i, j, s): rows block i, columns block j, K chunk s -> o[s] = y' @ w over the chunk, y' = y, or
    y * (1 + scale) (scaled). Side outputs: the chunk's sum of squares of y per row (scaled; by the j = 0 programs)
    and shift @ w over the chunk (adaptive; by the i = 0 programs, 16 equal rows: a dot needs 16). refs: y, mods
    (scaled only), the step (step_rows only), w, o, the side outputs. step_rows: mods is a stack of steps' tables of
    that many rows, and the scale is row step * step_rows + mod_row."""
    if not scaled:
        refs = (refs[0], None, *refs[1:])
    if not step_rows:
        refs = (*refs[:2], None, *refs[2:])
    y_ref, mod_ref, step_ref, w_ref, o_ref, *side = refs
    if step_rows:
        mod_row = step_ref[0] * step_rows + mod_row
    i, j, s = pl.program_id(0), pl.program_id(1), pl.program_id(2)
    rows, cols = pl.ds(i * bm, bm), pl.ds(j * bn, bn)
    dtype = y_ref.dtype

    def body(kk, acc):
        ks = pl.ds(s * chunk + kk * bk, bk)
        w = w_ref[ks, cols].astype(dtype)   # an e4m3 weight (weight-only FP8) widens exactly
        if not scaled:
            return (acc[0] + dot(y_ref[rows, ks], w),)
        x, h = _scaled(y_ref, mod_ref, rows, ks, mod_row, dtype)
        acc = (acc[0] + dot(h, w), acc[1] + jnp.sum(x * x, axis=1), *acc[2:])
        if adaptive:
            shift = jnp.broadcast_to(mod_ref[pl.ds(mod_row + 1, 1), ks], (ALIGN, bk))
            acc = (*acc[:2], acc[2] + dot(shift, w))
        return acc

    init = (jnp.zeros((bm, bn), jnp.float32),)
    init += (jnp.zeros((bm,), jnp.float32),) if scaled else ()
    init += (jnp.zeros((ALIGN, bn), jnp.float32),) if adaptive else ()
    acc = jax.lax.fori_loop(0, chunk // bk, body, init)
    o_ref[pl.ds(s * m + i * bm, bm), cols] = acc[0]
    if scaled:
        @pl.when(j == 0)
        def _():
            side[0][pl.ds(s * m + i * bm, bm)] = acc[1]
    if adaptive:
        @pl.when(i == 0)
        def _():
            side[1][pl.ds(s * ALIGN, ALIGN), cols] = acc[2]


def matmul_partials(y, w, mods=None, mod_row: int = 0, *, scaled: bool = False, adaptive: bool = False,
                    gemm: Gemm, blocks: Blocks = Blocks(), name: str = "matmul_partials", step: Step | None = None):
    """y (M, E) @ w (E, N) as `gemm.splits` f32 partials over K chunks -> (parts (S, M, N), sums of squares (S, M) or
    None, shift products (S, N) or None). scaled: y * (1 + mods[mod_row]) enters the GEMM (a norm's scale; mods (R, E));
    adaptive: also mods[mod_row + 1] @ w (adaRMS's shift). splits falls back to 1 where E does not split into
    multiples of 16. name: the kernel's (a profile tells the GEMMs apart by it). step: mods is a stack of steps'
    tables (`Step`), read at the step's rows in place."""
    m, e = y.shape
    n = w.shape[1]
    splits = gemm.splits if e % (ALIGN * gemm.splits) == 0 else 1
    chunk = e // splits
    bm, bn, bk = fit(blocks.rows, m), fit(gemm.cols, n), fit(blocks.k, chunk)
    step_rows = step.rows if scaled and step is not None else 0
    kernel = functools.partial(_partials_kernel, m=m, bm=bm, bn=bn, bk=bk, chunk=chunk, mod_row=mod_row,
                               scaled=scaled, adaptive=adaptive, step_rows=step_rows)
    out = [jax.ShapeDtypeStruct((splits * m, n), jnp.float32)]
    out += [jax.ShapeDtypeStruct((splits * m,), jnp.float32)] if scaled else []
    out += [jax.ShapeDtypeStruct((splits * ALIGN, n), jnp.float32)] if adaptive else []
    # mods only where read: a dummy operand would be a broadcast kernel of its own in every denoise step (XLA sinks
    # the constant into the loop's body)
    operands = (y, mods, *([step.index.reshape(1)] if step_rows else []), w) if scaled else (y, w)
    res = pallas_base.call(kernel, grid=(m // bm, n // bn, splits), out_shape=out, name=name,
                           num_warps=blocks.num_warps, num_stages=gemm.stages)(*operands)
    parts = res[0].reshape(splits, m, n)
    ss = res[1].reshape(splits, m) if scaled else None
    shift = res[-1].reshape(splits, ALIGN, n)[:, 0] if adaptive else None
    return parts, ss, shift


def _mosaic(y, w, launch: Launch | None) -> bool:
    return launch is not None and mosaic_gemm.applies(y, w, launch)


def _norm(x, mods, mod_row, adaptive, width, step=None):
    """RMSNorm (or adaRMS) of the rows in `layers.rms_norm`'s order, rounded to the dtype: the input of a plain GEMM."""
    inv = jax.lax.rsqrt(jnp.sum(jnp.square(x.astype(jnp.float32)), axis=1, keepdims=True) / width + EPS)
    h = x * inv * (1 + table_row(mods, mod_row, step))
    return (h + table_row(mods, mod_row + 1, step) if adaptive else h).astype(x.dtype)


def _normed_product(x, mods, mod_row, adaptive, w, *, width, gemm, blocks, name, mosaic=None, step=None):
    """norm(x) @ w as the GEMM's f32 result (before rounding): the split sum times 1 / rms, plus shift @ w. With a
    Mosaic launch: the norm first, in `layers.rms_norm`'s order (one XLA fusion), then the plain GEMM."""
    if _mosaic(x, w, mosaic):
        h = _norm(x, mods, mod_row, adaptive, width, step)
        return sum(list(mosaic_gemm.partials(h, w, mosaic, name=name).astype(jnp.float32)))
    parts, ss, shift = matmul_partials(x, w, mods, mod_row, scaled=True, adaptive=adaptive, gemm=gemm,
                                       blocks=blocks, name=name, step=step)
    inv = jax.lax.rsqrt(sum(list(ss)) / width + EPS)[:, None]
    acc = sum(list(parts)) * inv
    return acc + sum(list(shift))[None] if adaptive else acc


def rope_launch(blocks: Blocks, adaptive: bool, pad_row: bool) -> Launch | None:
    """q/k/v's `mosaic_gemm.qkv_rope` launch where it may take a layer (a `rope` launch; π0.5's only where its adaRMS
    shift has a padding row to ride in), else None. Where it runs, no norm fusion comes before q/k/v."""
    launch = blocks.mosaic_qkv
    return launch if launch is not None and launch.rope and (pad_row or not adaptive) else None


def norm_qkv_rope(x, mods, mod_row: int, adaptive: bool, w_qkv, cos, sin, *, width: int, num_heads: int,
                  num_kv_heads: int, head_dim: int, blocks: Blocks = Blocks(), step: Step | None = None,
                  pad_row: bool = False):
    """x (M, D) -> qkv (M, (N + 2K) * 2hp): normed, projected, q/k rotated, q scaled by head_dim^-0.5.

    mods (R, D): row mod_row is the norm scale, +1 the adaRMS shift (adaptive); with step, every step's tables
    stacked (T R, D), read at the step's; w_qkv (D, (N + 2K) * 2hp); cos / sin (M, hp) f32 (`layout.rope_tables`);
    width: the true D (the mean's divisor); pad_row: the last row of every `mosaic_gemm.ROWS` is padding, which
    π0.5's q/k/v on `mosaic_gemm.qkv_rope` needs (its adaRMS shift rides there).
    """
    m, dtype = x.shape[0], x.dtype
    heads, hp = num_heads + 2 * num_kv_heads, cos.shape[1]
    q_scale = float(np.asarray(head_dim**-0.5, dtype))
    rope = rope_launch(blocks, adaptive, pad_row)
    if rope is not None and mosaic_gemm.applies(x, w_qkv, rope, half=hp):
        xs = (x.astype(jnp.float32) * (1 + table_row(mods, mod_row, step)).astype(jnp.float32)).astype(dtype)
        return mosaic_gemm.qkv_rope(x, xs, w_qkv, cos, sin, rope, width=width, num_heads=num_heads,
                                    num_kv_heads=num_kv_heads, q_scale=q_scale, eps=EPS, name="expert_qkv",
                                    shift=table_row(mods, mod_row + 1, step) if adaptive else None)
    launch = blocks.mosaic_qkv
    acc = _normed_product(x, mods, mod_row, adaptive, w_qkv, width=width, gemm=blocks.qkv, blocks=blocks,
                          name="expert_qkv", mosaic=None if launch is not None and launch.rope else launch, step=step)
    a = _round(acc, dtype).reshape(m, heads, 2, hp)
    a1, a2, c, s = a[:, :, 0], a[:, :, 1], cos[:, None], sin[:, None]
    # RoPE in f32, then the dtype, for q and k heads; q is then scaled in the dtype (q_scale is a dtype value). On a
    # GPU the stack is a kernel of its own; a * c + swap(a) * [-s | s] (a reversed axis, no stack) became two
    # (docs/BENCHMARKS.md, "Launch parameters inside the step")
    rotary = (jnp.arange(heads) < num_heads + num_kv_heads)[None, :, None]
    r1 = jnp.where(rotary, _round(a1 * c - a2 * s, dtype), a1)
    r2 = jnp.where(rotary, _round(a2 * c + a1 * s, dtype), a2)
    scale = jnp.where(jnp.arange(heads) < num_heads, q_scale, 1.0)[None, :, None, None]
    return (jnp.stack([r1, r2], axis=2) * scale).astype(dtype).reshape(m, heads * 2 * hp)


# -- GEMM + (gated) residual, norm + gate/up GEMM + GeGLU --------------------------------------------------------------
def matmul_residual(y, w, x, gate=None, *, gemm: Gemm, blocks: Blocks = Blocks(), name: str = "matmul_partials",
                    mosaic: Launch | None = None):
    """x + (y @ w) [* gate]: y (M, E), w (E, D), x (M, D); gate (D,), π0.5's adaRMS gate. The split sum is rounded to
    the dtype, then the gate and the residual (the XLA path's ops, in its order). mosaic: the GEMM as
    `ops.mosaic_gemm` with this launch, where it applies."""
    if _mosaic(y, w, mosaic):
        parts = mosaic_gemm.partials(y, w, mosaic, name=name).astype(jnp.float32)
    else:
        parts, _, _ = matmul_partials(y, w, gemm=gemm, blocks=blocks, name=name)
    z = sum(list(parts)).astype(x.dtype)
    return x + (z if gate is None else z * gate)


def norm_geglu(x, mods, mod_row: int, adaptive: bool, w_gate_up, *, width: int, blocks: Blocks = Blocks(),
               step: Step | None = None):
    """gelu_tanh(h @ w_gate) * (h @ w_up) with h = norm(x): x (M, D), w_gate_up (D, 2F) in `layout.gate_up_block`
    pairs -> (M, F). mods, step: as `norm_qkv_rope`'s."""
    dtype = x.dtype
    launch = blocks.mosaic_mlp
    if launch is not None and launch.geglu:
        if _mosaic(x, w_gate_up, launch):
            return mosaic_gemm.geglu(_norm(x, mods, mod_row, adaptive, width, step), w_gate_up, launch,
                                     name="expert_gate_up")
        launch = None   # the Triton kernel
    acc = _normed_product(x, mods, mod_row, adaptive, w_gate_up, width=width, gemm=blocks.mlp, blocks=blocks,
                          name="expert_gate_up", mosaic=launch, step=step)
    gate, up = layout.split_gate_up(acc)
    gate = _round(jax.nn.gelu(_round(gate, dtype), approximate=True), dtype)
    return (gate * _round(up, dtype)).astype(dtype)
