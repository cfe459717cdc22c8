"""The action expert's attention in the denoise step as Pallas kernels (Triton on GPU, interpret mode on CPU): the
suffix queries over [cached prefix | suffix] keys, flash-decoding style.

  attention  an online softmax over each of several key splits in parallel (the prefix's key blocks shared out over
             `Blocks.kv_splits` programs a query block, the suffix's keys in one more), each split's normalised
             output and log-sum-exp written apart
  merge      the splits' softmaxes as one, weighted by their log-sum-exp in f32 (it can also cut each element's pad
             rows and write an FP8 out-projection's e4m3 input, so neither is a kernel of its own)

At B = 1 the step's attention reads under a megabyte of keys and values: what costs is latency, so the keys are split
over many short programs. `ops.mosaic_attention` is the same split softmax on Mosaic GPU (TMA, wgmma), for a jax
without Pallas's Triton backend (`expert_kernels.TRITON_FREE`).

Layout (`pi0_jax.ops.layout`): rows are (batch, suffix padded to Sp) flattened; each head is stored as
[x1 | 0 | x2 | 0], the two RoPE halves each padded to hp (a multiple of 16); padded keys are masked, so every valid
number is the one the XLA path computes. Numerics as `pi0_jax.engine.layers`: f32 logits and softmax with the same
big-negative fill; each key split's normalised output is rounded to the dtype and the splits are merged in f32 (within
bf16 rounding of the XLA path, within f32 rounding in f32).

Axis legend: M query rows (B * Sp), N query heads, K kv heads, hp half head dim (padded), P keys, S splits.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl
from jax.experimental.custom_partitioning import custom_partitioning
from jax.sharding import NamedSharding, PartitionSpec as P

from pi0_jax.ops import formats, mosaic_attention, pallas_base
from pi0_jax.ops.expert_kernels import Blocks
from pi0_jax.ops.pallas_base import dot, fit

BIG_NEG = -2.3819763e38  # masked logits: the value pi0_jax.gemma fills (a test checks they agree)


def _attention_kernel(q_ref, kv_ref, ck_ref, cv_ref, pmask_ref, smask_ref, o_ref, lse_ref, *, m, bq, bkv, sq, sk, pp,
                      hd, num_heads, num_kv_heads, splits, per_split, kv_cols, strides):
    """Program (b, n, qi, s): query block qi of head n over prefix key blocks [s * per_split, (s + 1) * per_split)
    (s < splits; blocks past the cache are masked), or over the suffix keys (s == splits). Writes the split's
    normalised output (in the dtype) and its log-sum-exp (f32). An element's sq queries are rows from b qs of q, its
    sk suffix keys and values rows from b ks + ko of kv at columns kv_cols (+ the kv head's offset); strides =
    (qs, ks, ko), (sq, sk, 0) unless q and kv are views of one packed buffer (`attention`'s packed)."""
    b, n, qi, s = pl.program_id(0), pl.program_id(1), pl.program_id(2), pl.program_id(3)
    kh = jax.lax.div(n, num_heads // num_kv_heads) if num_kv_heads > 1 else 0  # this query head's kv head
    rows = pl.ds(b * sq + qi * bq, bq)
    q = q_ref[pl.ds(b * strides[0] + qi * bq, bq), pl.ds(n * hd, hd)]
    dtype = q.dtype
    blocks = pp // bkv

    def update(carry, k, v, valid):
        o, mx, l = carry
        logits = jnp.where(valid, dot(q, k, trans_b=True), BIG_NEG)  # f32
        m_new = jnp.maximum(mx, jnp.max(logits, axis=1))
        corr = jnp.exp(mx - m_new)
        p = jnp.exp(logits - m_new[:, None])
        return o * corr[:, None] + dot(p.astype(dtype), v), m_new, l * corr + jnp.sum(p, axis=1)

    def write(carry):
        o, mx, l = carry
        out_rows = pl.ds(s * m + b * sq + qi * bq, bq)
        o_ref[out_rows, pl.ds(n * hd, hd)] = (o / l[:, None]).astype(o_ref.dtype)
        lse_ref[out_rows, pl.ds(n, 1)] = (mx + jnp.log(l))[:, None]

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
        suffix = pl.ds(b * strides[1] + strides[2], sk)
        k_col, v_col = kv_cols[0] + kh * hd, kv_cols[1] + kh * hd
        write(update(init, kv_ref[suffix, pl.ds(k_col, hd)], kv_ref[suffix, pl.ds(v_col, hd)],
                     smask_ref[rows, :] != 0))


def attention(qkv, cache_k, cache_v, prefix_mask, suffix_mask, *, batch: int, num_heads: int, num_kv_heads: int,
              blocks: Blocks = Blocks(), kv=None, packed: bool = False, out_rows: int | None = None,
              out_scale=None):
    """Softmax attention of the suffix queries over [cached prefix | suffix] keys -> (M, N * 2hp).

    qkv (M, (N + 2K) * 2hp) from `norm_qkv_rope`; cache_k / cache_v (B * P, K * 2hp); prefix_mask (B, P) int32, the
    same for every query; suffix_mask (M, Sp) int32, query row -> suffix key. The prefix keys are split over
    `blocks.kv_splits` programs per query block, the suffix keys take one more; the splits' softmaxes are merged
    by their log-sum-exp. A split whose keys are all masked has a log-sum-exp of about BIG_NEG and weight 0.

    kv: None, or the suffix's keys and values (B * Sp, 2K * 2hp) as rows of their own, qkv then only queries
    (M, N * 2hp) with M / B rows an element. That is how a kv head's query heads folded into rows arrive (the caller
    passes num_heads = num_kv_heads; `layers._attend_kernel`).

    packed: the same with both in one buffer, qkv (B (R + 2 Sp), K * 2hp): an element's R = M / B query rows, then its
    Sp suffix rows of [k | v] as 2 Sp rows (R even). One XLA fusion then makes the kernel's two inputs (the kernel
    reads kv as a view of rows twice as wide, at a row offset); the Triton kernel only (not `ops.mosaic_attention`).

    out_rows: only each element's first out_rows query rows come out, (B out_rows, N * 2hp); out_scale: an f32
    scalar, the output e4m3 with it (`formats.quantise`: the input of an FP8 out-projection). Both in the splits'
    merge (`merge`), no kernel of their own.

    Under a sharded jit (the simulator's batch mesh) each device attends its own elements: every operand is
    batch-major, and XLA cannot split a kernel it does not know (it would gather every row onto every device).
    """
    (m, sp), strides = suffix_mask.shape, None
    if packed:
        r = m // batch
        if kv is not None or num_heads != num_kv_heads or r % 2 or qkv.shape[0] != batch * (r + 2 * sp):
            raise ValueError(f"packed takes qkv of batch * ({r} + 2 * {sp}) rows (an even query count), one head "
                             f"per kv head and no kv, got qkv {qkv.shape}, {num_heads} heads, kv "
                             f"{None if kv is None else kv.shape}")
        kv, strides = qkv.reshape(-1, 2 * qkv.shape[1]), (r + 2 * sp, r // 2 + sp, r // 2)
    hd = qkv.shape[1] // (num_heads + (0 if kv is not None else 2 * num_kv_heads))
    kv_cols = (num_heads * hd, (num_heads + num_kv_heads) * hd) if kv is None else (0, num_kv_heads * hd)
    if kv is not None and not packed and kv.shape != (batch * sp, 2 * num_kv_heads * hd):
        raise ValueError(f"kv must be (batch * {sp}, {2 * num_kv_heads * hd}) suffix rows of [k | v], got {kv.shape}")
    scale = jnp.zeros((1, 1), jnp.float32) if out_scale is None else out_scale.astype(jnp.float32).reshape(1, 1)
    return _partitioned(qkv, qkv if kv is None else kv, cache_k, cache_v, prefix_mask, suffix_mask, scale, batch,
                        num_heads, num_kv_heads, kv_cols, blocks, strides, out_rows, out_scale is not None)


def key_splits(key_blocks: int, wanted: int) -> tuple[int, int]:
    """(splits, key blocks a split) for the prefix's key blocks shared out over at most `wanted` splits: each split
    takes the same count and none lies wholly past the cache. π0.5's 200-token prompt makes 1,024 prefix keys, 16
    blocks: asked into 13 splits they run as 8 of 2 blocks, not 8 of 2 and 5 empty programs whose parts the merge
    reads too (its 10-step denoise 0.9-1.8 % faster on an H200, bit-equal: docs/BENCHMARKS.md, session 50)."""
    key_blocks = max(1, key_blocks)
    per_split = -(-key_blocks // max(1, min(wanted, key_blocks)))
    return -(-key_blocks // per_split), per_split


def attention_launch(blocks: Blocks, prefix_keys: int) -> dict:
    """The Triton attention's launch over a cache of `prefix_keys` (its kernel layout's padded length), as `_attention`
    makes it: the key splits asked for, the splits and key blocks a split it runs (`key_splits`), for a JSON. With
    `mosaic` the Mosaic GPU kernel runs instead where it applies (`mosaic_attention.applies`), in kv_splits + 1
    parts."""
    bkv = fit(blocks.kv, prefix_keys)
    splits, per_split = key_splits(prefix_keys // bkv, blocks.kv_splits)
    return {"kv_splits": blocks.kv_splits, "splits": splits, "key_blocks_per_split": per_split, "kv_block": bkv,
            "attention_warps": blocks.attention_warps, "fold": blocks.fold, "mosaic": blocks.mosaic_attention}


def _attention(q, kv, cache_k, cache_v, prefix_mask, suffix_mask, scale, batch, num_heads, num_kv_heads, kv_cols,
               blocks, strides=None, kept=None, quantise=False):
    (m, sk), hd = suffix_mask.shape, (kv_cols[1] - kv_cols[0]) // num_kv_heads
    sq, pp = m // batch, prefix_mask.shape[1]
    if strides is None and blocks.mosaic_attention and mosaic_attention.applies(
            q.dtype, head_dim=hd, query_rows=sq, suffix_keys=sk, prefix_keys=pp):
        o, lse = mosaic_attention.attention(q, kv, cache_k, cache_v, prefix_mask,
                                            mosaic_attention.suffix_ends(suffix_mask), batch=batch,
                                            num_heads=num_heads, num_kv_heads=num_kv_heads, kv_cols=kv_cols, sk=sk,
                                            splits=blocks.kv_splits + 1)   # the Triton kernel's parts
    else:
        bq, bkv = fit(blocks.q, sq), fit(blocks.kv, pp)
        splits, per_split = key_splits(pp // bkv, blocks.kv_splits)
        kernel = functools.partial(_attention_kernel, m=m, bq=bq, bkv=bkv, sq=sq, sk=sk, pp=pp, hd=hd,
                                   num_heads=num_heads, num_kv_heads=num_kv_heads, splits=splits,
                                   per_split=per_split, kv_cols=kv_cols, strides=strides or (sq, sk, 0))
        out = (jax.ShapeDtypeStruct(((splits + 1) * m, num_heads * hd), q.dtype),
               jax.ShapeDtypeStruct(((splits + 1) * m, num_heads), jnp.float32))
        o, lse = pallas_base.call(kernel, grid=(batch, num_heads, sq // bq, splits + 1), out_shape=out,
                                  name="expert_attention", num_warps=blocks.attention_warps,
                                  num_stages=blocks.attention_stages)(q, kv, cache_k, cache_v, prefix_mask,
                                                                      suffix_mask)
    ends = dict(parts=o.shape[0] // m, num_heads=num_heads, batch=batch, kept=kept, scale=scale if quantise else None)
    return (merge_xla if blocks.xla_merge or not pallas_base.TRITON else merge)(o, lse, **ends)


@functools.partial(custom_partitioning, static_argnums=tuple(range(7, 15)))
def _partitioned(q, kv, cache_k, cache_v, prefix_mask, suffix_mask, scale, batch, num_heads, num_kv_heads, kv_cols,
                 blocks, strides, kept, quantise):
    return _attention(q, kv, cache_k, cache_v, prefix_mask, suffix_mask, scale, batch, num_heads, num_kv_heads,
                      kv_cols, blocks, strides, kept, quantise)


def _batch_rows(batch, mesh, sharding) -> tuple:
    """(the operands' sharding: batch-major rows as qkv's, whole elements per device, else replicated; devices)."""
    axes = sharding.spec[0] if len(sharding.spec) else None
    n = math.prod(mesh.shape[a] for a in (axes if isinstance(axes, tuple) else (axes,))) if axes else 1
    if n == 1 or batch % n:
        return NamedSharding(mesh, P()), 1
    return NamedSharding(mesh, P(axes, None)), n


def _partition(batch, num_heads, num_kv_heads, kv_cols, blocks, strides, kept, quantise, mesh, arg_shapes,
               result_shape):
    rows, n = _batch_rows(batch, mesh, arg_shapes[0].sharding)
    fn = functools.partial(_attention, batch=batch // n, num_heads=num_heads, num_kv_heads=num_kv_heads,
                           kv_cols=kv_cols, blocks=blocks, strides=strides, kept=kept, quantise=quantise)
    return mesh, fn, rows, (rows,) * 6 + (NamedSharding(mesh, P()),)   # strides and kept are an element's


def _infer(batch, num_heads, num_kv_heads, kv_cols, blocks, strides, kept, quantise, mesh, arg_shapes, result_shape):
    return _batch_rows(batch, mesh, arg_shapes[0].sharding)[0]


# need_replication lists the factors in their order of appearance (Shardy's verifier wants them sorted)
_partitioned.def_partition(partition=_partition, infer_sharding_from_operands=_infer,
                           sharding_rule="r c, u f, k e, k e, b p, r s, o z -> r d",
                           need_replication_factors=("c", "f", "e", "p", "s", "o", "z", "d"))


def _merge_kernel(o_ref, lse_ref, scale_ref, out_ref, *, m, bm, bd, hd, parts, by_head, per, kept, quantise):
    """Program (i, n, c): rows block i, head n, columns block c of the head: the splits' outputs weighted by
    exp(lse_s - max_s lse_s), in f32, over their sum. by_head: lse is (parts, N, M), else (parts M, N). An element's
    first `kept` of its `per` rows are written, packed (a block past them writes nothing); quantise: rounded to o's
    dtype, then over the scale (scale_ref (1, 1) f32) into e4m3, as `formats.quantise`."""
    i, n, c = pl.program_id(0), pl.program_id(1), pl.program_id(2)
    b, r = jax.lax.div(i * bm, per), jax.lax.rem(i * bm, per)

    @pl.when(r < kept)
    def _():
        if by_head:
            lse = [lse_ref[s, n, pl.ds(i * bm, bm)][:, None] for s in range(parts)]
        else:
            lse = [lse_ref[pl.ds(s * m + i * bm, bm), pl.ds(n, 1)] for s in range(parts)]
        top = functools.reduce(jnp.maximum, lse)
        weights = [jnp.exp(x - top) for x in lse]
        cols = pl.ds(n * hd + c * bd, bd)
        acc = sum(w * o_ref[pl.ds(s * m + i * bm, bm), cols].astype(jnp.float32) for s, w in enumerate(weights))
        y = (acc / sum(weights)).astype(o_ref.dtype)
        if quantise:
            y = jnp.clip(y.astype(jnp.float32) / scale_ref[...], -formats.E4M3_MAX, formats.E4M3_MAX)
        out_ref[pl.ds(b * kept + r, bm), cols] = y.astype(out_ref.dtype)


def merge(o, lse, *, parts: int, num_heads: int, rows: int = 16, cols: int = 64, batch: int = 1,
          kept: int | None = None, scale=None):
    """The key splits' softmaxes as one: o (parts * M, N * hd) normalised per split, lse (parts * M, N) f32 (or
    (parts, N, M): `mosaic_attention`'s) -> (M, N * hd) = sum_s exp(lse_s - top) o_s / sum_s exp(lse_s - top),
    top = max_s lse_s, in f32 (in the splits' order). One kernel of many small programs (rows x cols of one head):
    XLA made it two (the max apart).

    kept: only each element's first `kept` rows of its M / batch (B kept rows out: a cut of the pad rows that would
    be a kernel of its own). scale: (1, 1) f32, the output e4m3 with it (`formats.quantise` of the output in o's
    dtype: the next GEMM's FP8 input). Row blocks shrink to cut the rows (with wider column blocks: as many values a
    program); where blocks of 4 cannot, XLA's ops cut them after."""
    m, hd = o.shape[0] // parts, o.shape[1] // num_heads
    per, kept = m // batch, m // batch if kept is None else kept
    bm = fit(rows, math.gcd(per, kept))
    bd = fit(cols * max(1, rows // bm), hd)
    if bm < min(rows, 4):   # rows blocks too small to cut: the kernel keeps every row
        y = merge(o, lse, parts=parts, num_heads=num_heads, rows=rows, cols=cols, batch=batch, scale=scale)
        return y.reshape(batch, per, -1)[:, :kept].reshape(batch * kept, -1)
    kernel = functools.partial(_merge_kernel, m=m, bm=bm, bd=bd, hd=hd, parts=parts, by_head=lse.ndim == 3, per=per,
                               kept=kept, quantise=scale is not None)
    out = jax.ShapeDtypeStruct((batch * kept, num_heads * hd), o.dtype if scale is None else formats.E4M3)
    scale = jnp.zeros((1, 1), jnp.float32) if scale is None else scale   # read only to quantise
    return pallas_base.call(kernel, grid=(m // bm, num_heads, hd // bd), out_shape=out, name="expert_attention_merge",
                            num_warps=4, num_stages=1)(o, lse, scale)


def merge_xla(o, lse, *, parts: int, num_heads: int, batch: int = 1, kept: int | None = None, scale=None):
    """`merge` as XLA's ops (no Pallas kernel), the same sums in f32."""
    m, hd = o.shape[0] // parts, o.shape[1] // num_heads
    lse = lse.reshape(parts, num_heads, m).transpose(0, 2, 1) if lse.ndim == 3 else lse.reshape(parts, m, num_heads)
    weights = jnp.exp(lse - jnp.max(lse, axis=0))[..., None]   # (parts, M, N, 1)
    acc = jnp.sum(weights * o.reshape(parts, m, num_heads, hd).astype(jnp.float32), axis=0)
    y = (acc / jnp.sum(weights, axis=0)).astype(o.dtype).reshape(batch, m // batch, num_heads * hd)
    y = y[:, : m // batch if kept is None else kept]
    if scale is not None:
        y = formats.quantise(y, scale)
    return y.reshape(-1, y.shape[-1])
