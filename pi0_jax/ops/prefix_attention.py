"""The prefix fill's attention as one Pallas kernel (Triton on GPU, interpret mode on CPU): every query of an
element over its first kv_len keys, a kv head's query heads folded into rows.

Gemma's prefix attention is multi-query (one kv head), so the G query heads of a token read the same keys and are
G rows of one problem: (T G) rows against S keys, head dim 256. cuDNN's flash kernel runs that problem on 128-row
tiles, 51 programs at π0's 816 tokens, on a GPU of 132 SMs; this kernel runs 64-row tiles (102 programs) and reads
only the key blocks an element has (`kv_len`), the rest of the loop skipped.

Numerics as cuDNN's kernel (`ops.attention.fused`): q arrives scaled, f32 logits, an online softmax in f32 over key
blocks, the probabilities rounded to the activation dtype for the PV product with an f32 accumulator, the output
rounded once. Keys at or past kv_len get the big-negative fill, so a block's masked keys weigh exp(-inf) = 0.

Axis legend: B elements, R query rows an element (T tokens x G heads, token-major), S keys an element, H head dim.
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

from pi0_jax.ops.pallas_base import ALIGN, call, dot, fit

BIG_NEG = -2.3819763e38  # masked logits: the value pi0_jax.gemma fills


@dataclasses.dataclass(frozen=True)
class Blocks:
    """Query rows per program, keys per loop step (powers of two, shrunk to divide R and S) and Triton launch
    parameters."""

    q: int = 64
    kv: int = 64
    num_warps: int = 4
    num_stages: int = 3
    splits: int = 1


def _kernel(len_ref, q_ref, k_ref, v_ref, o_ref, *lse_ref, r, s, bq, bkv, per_split):
    """Program (b, i, p): query rows [i bq, (i + 1) bq) of element b over key blocks [p per_split, (p + 1)
    per_split) that lie below kv_len[b]. One split writes the output; several write each split's normalised output
    (in the dtype) and its log-sum-exp (f32), merged by `_merge`."""
    b, i, sp = pl.program_id(0), pl.program_id(1), pl.program_id(2)
    rows = pl.ds(b * r + i * bq, bq)
    q = q_ref[rows, :]
    n = len_ref[b]
    hd = q.shape[1]

    def body(j, carry):
        o, mx, l = carry
        keys = pl.ds(b * s + j * bkv, bkv)
        valid = (j * bkv + jnp.arange(bkv))[None, :] < n
        logits = jnp.where(valid, dot(q, k_ref[keys, :], trans_b=True), BIG_NEG)
        m_new = jnp.maximum(mx, jnp.max(logits, axis=1))
        corr = jnp.exp(mx - m_new)
        p = jnp.exp(logits - m_new[:, None])
        o = o * corr[:, None] + dot(p.astype(q.dtype), v_ref[keys, :])
        return o, m_new, l * corr + jnp.sum(p, axis=1)

    init = (jnp.zeros((bq, hd), jnp.float32), jnp.full((bq,), BIG_NEG, jnp.float32), jnp.zeros((bq,), jnp.float32))
    blocks = jnp.clip((n + bkv - 1) // bkv, 1, s // bkv)   # at least one block: no 0 / 0 where kv_len is 0
    o, mx, l = jax.lax.fori_loop(sp * per_split, jnp.minimum((sp + 1) * per_split, blocks), body, init)
    if not lse_ref:
        o_ref[rows, :] = (o / l[:, None]).astype(o_ref.dtype)
        return
    out = pl.ds(sp * (pl.num_programs(0) * r) + b * r + i * bq, bq)
    empty = l == 0   # a split past kv_len: weight 0 in the merge
    o_ref[out, :] = jnp.where(empty[:, None], 0.0, o / jnp.where(empty, 1.0, l)[:, None]).astype(o_ref.dtype)
    lse_ref[0][out] = jnp.where(empty, BIG_NEG, mx + jnp.log(jnp.where(empty, 1.0, l)))


def _merge(o, lse):
    """The splits' outputs (S, M, H) in the dtype and log-sum-exps (S, M) f32 -> (M, H): weights exp(lse - max)
    summed in f32, the output rounded once."""
    w = jnp.exp(lse - lse.max(axis=0))
    return (jnp.einsum("sm,smh->mh", w, o.astype(jnp.float32)) / w.sum(axis=0)[:, None]).astype(o.dtype)


def attention(q, k, v, kv_len, *, blocks: Blocks = Blocks()):
    """q (B, R, H) (a kv head's query heads folded into rows, scaled); k, v (B, S, H); kv_len (B,) int32: element b
    attends its keys [0, kv_len[b]). Returns (B, R, H) in q's dtype.

    Under a sharded jit (the simulator's batch mesh) each device attends its own elements: XLA cannot split a kernel
    it does not know, and would otherwise gather every element onto every device."""
    (bsz, r, hd), s = q.shape, k.shape[1]
    if k.shape != (bsz, s, hd) or v.shape != k.shape or kv_len.shape != (bsz,):
        raise ValueError(f"prefix attention: q (B, R, H), k and v (B, S, H), kv_len (B,); got {q.shape}, {k.shape}, "
                         f"{v.shape}, {kv_len.shape}")
    if min(fit(blocks.q, r), fit(blocks.kv, s)) < ALIGN or hd % ALIGN:
        raise ValueError(f"the Pallas prefix attention needs R, S and H divisible by {ALIGN}, got {r}, {s}, {hd}")
    return _partitioned(q, k, v, kv_len.astype(jnp.int32), blocks)


@functools.partial(custom_partitioning, static_argnums=(4,))
def _partitioned(q, k, v, kv_len, blocks):
    return _attention(q, k, v, kv_len, blocks)


def _attention(q, k, v, kv_len, blocks: Blocks):
    (bsz, r, hd), s = q.shape, k.shape[1]
    bq, bkv = fit(blocks.q, r), fit(blocks.kv, s)
    splits = max(1, min(blocks.splits, s // bkv))
    per_split = -(-(s // bkv) // splits)
    kernel = functools.partial(_kernel, r=r, s=s, bq=bq, bkv=bkv, per_split=per_split)
    out = jax.ShapeDtypeStruct((splits * bsz * r, hd), q.dtype)
    if splits > 1:
        out = (out, jax.ShapeDtypeStruct((splits * bsz * r,), jnp.float32))
    res = call(kernel, grid=(bsz, r // bq, splits), out_shape=out, name="prefix_attention",
               num_warps=blocks.num_warps, num_stages=blocks.num_stages)(kv_len, q.reshape(bsz * r, hd),
                                                                         k.reshape(bsz * s, hd),
                                                                         v.reshape(bsz * s, hd))
    if splits > 1:
        res = _merge(res[0].reshape(splits, bsz * r, hd), res[1].reshape(splits, bsz * r))
    return res.reshape(bsz, r, hd)


def _batch(mesh, sharding) -> tuple:
    """(the operands' batch sharding where each device gets whole elements, else replicated; devices)."""
    axes = sharding.spec[0] if len(sharding.spec) else None
    n = math.prod(mesh.shape[a] for a in (axes if isinstance(axes, tuple) else (axes,))) if axes else 1
    return NamedSharding(mesh, P(axes) if n > 1 else P()), n


def _partition(blocks, mesh, arg_shapes, result_shape):
    shard, n = _batch(mesh, arg_shapes[0].sharding)
    if n > 1 and arg_shapes[0].shape[0] % n:
        shard, n = NamedSharding(mesh, P()), 1
    return mesh, functools.partial(_attention, blocks=blocks), shard, (shard,) * 4


def _infer(blocks, mesh, arg_shapes, result_shape):
    return _batch(mesh, arg_shapes[0].sharding)[0]


# need_replication lists the factors in their order of appearance (Shardy's verifier wants them sorted)
_partitioned.def_partition(partition=_partition, infer_sharding_from_operands=_infer,
                           sharding_rule="b r h, b s h, b s h, b -> b r h", need_replication_factors=("r", "h", "s"))
