"""The denoise step's split-key attention as one Pallas Mosaic GPU kernel (Hopper: TMA, wgmma), the form of
`expert_attention.attention` that needs no Triton.

A CTA takes one head's block of 64 query rows and one split of the keys: a run of consecutive 64-key blocks, the
cached prefix's and then the suffix's own 64 keys (the last block of the last split). TMA brings each block into a
ring of shared-memory slots, the next ones in flight while one is computed. QK^T and PV run on wgmma, the softmax on
the accumulator in registers, online across the run's blocks (each block's row maximum taken first, what came
before rescaled to it). It writes the split's normalised output in the dtype and its log-sum-exp in f32, as the
Triton kernel does; `expert_attention.merge` (or `merge_xla`) makes them one.

Masks, in the layout the accumulator's rows and columns take: the prefix mask as the element's int32 row of keys
(one TMA-loaded vector a block), and the suffix mask as each query row's count of visible suffix keys: π0's and
π0.5's block-causal suffix masks show a row a prefix of the suffix (`suffix_ends`), so an iota and one compare make
the tile (no 2-D mask load).

Numerics as the Triton kernel: f32 logits (q comes scaled), the same big-negative fill, p rounded to the dtype for
PV, l summed in f32 from unrounded p, the split's output rounded once. On a CPU the kernel runs in Mosaic GPU's
interpreter (tests). Axis legend: M rows (B Sq), N query heads, K kv heads, P prefix keys, S splits.
"""

from __future__ import annotations

import functools

import jax
import jax.experimental.pallas as pl
import jax.experimental.pallas.mosaic_gpu as plgpu
import jax.numpy as jnp
from jax import lax

from pi0_jax.ops.mosaic_gemm import hopper, transforms, warpgroup_kernel

BLOCK = 64   # query rows and keys a block: one warpgroup's wgmma rows, and the kernels' prefix key padding
SMEM_BYTES = 220 * 1024   # a Hopper CTA's shared memory (227 KB), less the masks' and barriers'
BIG_NEG = -2.3819763e38  # expert_attention.BIG_NEG (a test checks they agree)


def applies(dtype, *, head_dim: int, query_rows: int, suffix_keys: int, prefix_keys: int) -> bool:
    """Whether the kernel takes this attention: head_dim, query rows and prefix keys in whole 64-blocks, the suffix
    one block (π0's 51 tokens and π0.5's 50 pad to 64), and bf16 on a Hopper GPU (any float in the CPU
    interpreter)."""
    tiles = all(d % BLOCK == 0 for d in (head_dim, query_rows, prefix_keys)) and suffix_keys == BLOCK
    tiles = tiles and head_dim <= 256
    if jax.default_backend() == "cpu":
        return tiles
    return tiles and hopper() and jnp.dtype(dtype) == jnp.bfloat16


def max_slots(head_dim: int, dtype) -> int:
    """Key blocks a CTA holds at once in shared memory (each block's keys and values; q and p once)."""
    size = jnp.dtype(dtype).itemsize
    return (SMEM_BYTES // size - BLOCK * head_dim - BLOCK * BLOCK) // (2 * BLOCK * head_dim)


def suffix_ends(suffix_mask):
    """(M, Sp) int32 row -> suffix key mask -> (M,) int32: each row's count of visible suffix keys (the kernel's
    form; exact for masks whose rows are prefixes of the keys, which π0's and π0.5's are)."""
    sp = suffix_mask.shape[1]
    return jnp.max(jnp.where(suffix_mask != 0, jnp.arange(1, sp + 1, dtype=jnp.int32), 0), axis=1)


# jax 0.10's Mosaic GPU interpreter (CI's, on Python 3.11) takes no transposed shared-memory operand, so there QK^T
# is the same product as a dot of the loaded tiles; jax 0.11's interpreter runs the kernel's wgmma
def _old_interpreter() -> bool:
    return jax.default_backend() == "cpu" and jax.__version_info__ < (0, 11)


def _in_layout(x, layout):
    """x in the register layout the accumulator's rows or columns take. A cast, the identity on values: jax 0.10's
    CPU interpreter has no rule for it, so the interpreter goes without."""
    return x if jax.default_backend() == "cpu" else plgpu.layout_cast(x, layout)


def _iota(shape, dim):
    """An int32 iota along dim in the accumulator's layout (a plain iota in the CPU interpreter, as `_in_layout`)."""
    if jax.default_backend() == "cpu":
        return lax.broadcasted_iota(jnp.int32, shape, dim)
    return plgpu.broadcasted_iota(jnp.int32, shape, dim, layout=plgpu.Layout.WGMMA)


@functools.lru_cache(maxsize=None)
def _call(m: int, sq: int, sk: int, pp: int, hd: int, batch: int, num_heads: int, num_kv_heads: int,
          kv_cols: tuple, parts: int, per_split: int, slots: int, dtype):
    bq = bkv = BLOCK
    blocks = pp // bkv   # the prefix's; key block `blocks` is the suffix's
    group = num_heads // num_kv_heads
    tiles = transforms(hd, dtype)

    def kernel(q_gmem, kv_gmem, ck_gmem, cv_gmem, pmask_gmem, ends_gmem, o_gmem, lse_gmem,
               q_smem, k_smem, v_smem, p_smem, pmask_smem, ends_smem, lse_smem, q_bar, kv_bar):
        hq, s, b = lax.axis_index("h"), lax.axis_index("s"), lax.axis_index("b")
        n, qi = lax.div(hq, sq // bq), lax.rem(hq, sq // bq)
        kh = lax.div(n, group)
        rows = b * sq + qi * bq
        plgpu.copy_gmem_to_smem(q_gmem.at[pl.ds(rows, bq), pl.ds(n * hd, hd)], q_smem, q_bar)
        plgpu.copy_gmem_to_smem(ends_gmem.at[pl.ds(rows, bq)], ends_smem, q_bar)

        def load(t):
            """Key block j = s per_split + t into slot t % slots: a prefix block, the suffix's keys (j = blocks), or
            past them (the suffix's again, masked). The slot's barrier counts three copies (keys, values, mask)."""
            slot, j = t % slots, s * per_split + t
            tc = jnp.minimum(j, blocks - 1)

            @pl.when(j < blocks)
            def _prefix():
                keys = pl.ds(b * pp + tc * bkv, bkv)
                plgpu.copy_gmem_to_smem(ck_gmem.at[keys, pl.ds(kh * hd, hd)], k_smem[slot], kv_bar.at[slot])
                plgpu.copy_gmem_to_smem(cv_gmem.at[keys, pl.ds(kh * hd, hd)], v_smem.at[slot], kv_bar.at[slot])

            @pl.when(j >= blocks)
            def _suffix():
                suffix = pl.ds(b * sk, sk)
                k_col, v_col = kv_cols[0] + kh * hd, kv_cols[1] + kh * hd
                plgpu.copy_gmem_to_smem(kv_gmem.at[suffix, pl.ds(k_col, hd)], k_smem[slot], kv_bar.at[slot])
                plgpu.copy_gmem_to_smem(kv_gmem.at[suffix, pl.ds(v_col, hd)], v_smem.at[slot], kv_bar.at[slot])
            plgpu.copy_gmem_to_smem(pmask_gmem.at[b, pl.ds(tc * bkv, bkv)], pmask_smem.at[slot], kv_bar.at[slot])

        def logits(slot):
            if _old_interpreter():
                return lax.dot_general(q_smem[...], k_smem[slot][...], (((1,), (1,)), ((), ())),
                                       preferred_element_type=jnp.float32)

            def qk(acc_ref):
                plgpu.wgmma(acc_ref, q_smem, k_smem[slot].transpose((1, 0)))
                return acc_ref[...]
            return pl.run_scoped(qk, plgpu.ACC((bq, bkv), jnp.float32))

        def pv(p, slot, acc):
            """acc + p V (acc None: p V). On a GPU the wgmma accumulates into acc's own registers (a second 64 x 256
            f32 result beside it spills); Mosaic's interpreter runs no wgmma into a given accumulator, so there it is
            a fresh product added."""
            p_smem[...] = p.astype(dtype)   # wgmma's A from shared memory (Mosaic's interpreter takes no other)
            plgpu.commit_smem()
            if _old_interpreter():
                o = jnp.dot(p_smem[...], v_smem[slot], preferred_element_type=jnp.float32)
                return o if acc is None else acc + o

            def product(acc_ref):
                plgpu.wgmma(acc_ref, p_smem, v_smem.at[slot])

            def fresh(acc_ref):
                product(acc_ref)
                return acc_ref[...]
            if acc is not None and jax.default_backend() != "cpu":
                return pl.run_state(product)(plgpu.ACC.init(acc))
            o = pl.run_scoped(fresh, plgpu.ACC((bq, hd), jnp.float32))
            return o if acc is None else acc + o

        for t in range(min(slots, per_split)):   # the ring's first blocks in flight while q arrives
            load(t)
        plgpu.barrier_wait(q_bar)
        ends = _in_layout(ends_smem[...], plgpu.Layout.WGMMA.reduce(1))
        suffix_ok = _iota((bq, bkv), 1) < lax.broadcast_in_dim(ends, (bq, bkv), [0])
        acc = mx = l = None
        for t in range(per_split):
            slot, j = t % slots, s * per_split + t
            plgpu.barrier_wait(kv_bar.at[slot])
            key_ok = (_in_layout(pmask_smem[slot], plgpu.Layout.WGMMA.reduce(0)) != 0) & (j < blocks)
            valid = lax.broadcast_in_dim(key_ok, (bq, bkv), [1]) | (suffix_ok & (j == blocks))
            x = jnp.where(valid, logits(slot), BIG_NEG)
            top = x.max(axis=1) if mx is None else jnp.maximum(mx, x.max(axis=1))
            p = jnp.exp(x - lax.broadcast_in_dim(top, x.shape, [0]))
            if mx is None:
                acc, l = pv(p, slot, None), p.sum(axis=1)
            else:   # the online softmax: what came before, rescaled to the new row maximum
                alpha = jnp.exp(mx - top)
                acc = pv(p, slot, acc * lax.broadcast_in_dim(alpha, acc.shape, [0]))
                l = l * alpha + p.sum(axis=1)
            mx = top
            if t + slots < per_split:   # the slot's wgmmas are done (their results read): refill it
                load(t + slots)

        q_smem[...] = (acc / lax.broadcast_in_dim(l, acc.shape, [0])).astype(dtype)
        lse_smem[...] = mx + jnp.log(l)
        plgpu.commit_smem()
        plgpu.copy_smem_to_gmem(q_smem, o_gmem.at[pl.ds(s * m + rows, bq), pl.ds(n * hd, hd)])
        plgpu.copy_smem_to_gmem(lse_smem, lse_gmem.at[s, n, pl.ds(rows, bq)])
        plgpu.wait_smem_to_gmem(0)

    scratch = dict(
        q_smem=plgpu.SMEM((bq, hd), dtype, transforms=tiles),
        k_smem=[plgpu.SMEM((bkv, hd), dtype, transforms=tiles) for _ in range(slots)],   # one ref a slot: the 0.10
        # interpreter cannot transpose an indexed ref
        v_smem=plgpu.SMEM((slots, bkv, hd), dtype, transforms=tiles),
        p_smem=plgpu.SMEM((bq, bkv), dtype, transforms=transforms(bkv, dtype)),
        pmask_smem=plgpu.SMEM((slots, bkv), jnp.int32),
        ends_smem=plgpu.SMEM((bq,), jnp.int32),
        lse_smem=plgpu.SMEM((bq,), jnp.float32),
        q_bar=plgpu.Barrier(num_arrivals=2),
        kv_bar=plgpu.Barrier(num_arrivals=3, num_barriers=slots))

    def entry(*refs):
        pl.run_scoped(lambda **scoped: kernel(*refs, **scoped), **scratch, collective_axes="wg")

    out = (jax.ShapeDtypeStruct((parts * m, num_heads * hd), dtype),
           jax.ShapeDtypeStruct((parts, num_heads, m), jnp.float32))
    return warpgroup_kernel(entry, out, (num_heads * (sq // bq), parts, batch), ("h", "s", "b"), 1,
                            "expert_attention_mosaic")


def attention(q, kv, cache_k, cache_v, prefix_mask, ends, *, batch: int, num_heads: int, num_kv_heads: int,
              kv_cols: tuple, sk: int, splits: int):
    """The split-key softmaxes of `expert_attention.attention`'s kernel: q (M, >= N hd) query rows (an element's M / B
    rows), kv (B sk, .) holding the suffix's keys and values at kv_cols[0] and [1] (+ the kv head's offset), cache_k /
    cache_v (B P, K hd), prefix_mask (B, P) int32, ends (M,) int32 (`suffix_ends`) -> (o (S M, N hd) in the dtype,
    normalised per split; lse (S, N, M) f32). The key blocks, the prefix's 64-key blocks and then the suffix's, run
    in `splits` runs of equal length (fewer where a run would be empty), each through a ring of as many blocks as
    fit a CTA's shared memory (`max_slots`)."""
    m = q.shape[0]
    hd = (kv_cols[1] - kv_cols[0]) // num_kv_heads
    pp = prefix_mask.shape[1]
    total = pp // BLOCK + 1
    fit = max_slots(hd, q.dtype)
    if fit < 1:
        raise ValueError(f"one key block of {BLOCK} at head_dim {hd} does not fit a CTA's shared memory")
    per_split = -(-total // max(1, min(splits, total)))
    parts = -(-total // per_split)
    call = _call(m, m // batch, sk, pp, hd, batch, num_heads, num_kv_heads, tuple(kv_cols), parts, per_split,
                 min(per_split, fit), jnp.dtype(q.dtype))
    return call(q, kv, cache_k, cache_v, prefix_mask, ends)
