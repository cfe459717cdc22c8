"""SigLIP's self-attention as one Pallas Mosaic GPU kernel (Hopper: TMA, wgmma), bf16, where the Triton kernel of
`ops.vision_attention` is the rest's: read in place from the fused q/k/v GEMM's output, the heads written side by
side as the out-projection reads them.

At B = 1 the Triton kernel runs 48 (image, head) pairs as 96 programs, each a serial loop of small dots over the
head's two power-of-two pieces (So400m's head dim 72 as [0, 64) and [56, 72)): 10-12 µs a layer for 0.9 GFLOP
(docs/BENCHMARKS.md, "SigLIP's attention alone, at other blocks"). Here a CTA takes 64 query rows of one image and
a pair of heads, one warpgroup a head, and all of the image's keys at once: TMA brings the pair's keys and values
(shared) and its queries (a copy a warpgroup), one wgmma makes a head's (64, T) logits, the softmax runs on the
accumulator in registers in one pass (no key blocks, nothing rescaled), and a second wgmma takes p from registers
against v.

A pair of heads, not one: Mosaic GPU's layout inference takes a TMA copy into swizzled tiles only at column offsets
it can prove whole tiles (16 columns at So400m's 32-byte swizzle), which 72 n is not and 144 n is. TMA brings the
pair's 2 H columns; each warpgroup takes its head's window of them, the head dim rounded up to whole tiles (`_window`:
the first head's [0, 80), the second's [64, 144)), with the other head's columns zeroed in its q copy (the logits are
exact); of its p v product it stores the head's columns.

Numerics as the Triton kernel's: f32 logits of the bf16 q and k times 1 / sqrt(H), the row maximum subtracted, exp
in f32 (approximate on a GPU, ex2.approx as Triton's), the row sum in f32 from the unrounded p, p rounded to the
dtype for PV with an f32 accumulator, the output divided by the row sum and rounded once. On a CPU the kernel runs in
Mosaic GPU's interpreter (tests), where jax 0.10's takes no transposed operand: there q k^T is a dot of the loaded
tiles.

Axis legend: R rows (images x T tokens, image-major), T tokens per image, N heads, H head dim.
"""

from __future__ import annotations

import functools

import jax
import jax.experimental.pallas as pl
import jax.experimental.pallas.mosaic_gpu as plgpu
import jax.numpy as jnp
from jax import lax

from pi0_jax.ops.mosaic_attention import _iota, _old_interpreter
from pi0_jax.ops.mosaic_gemm import _interpret, hopper, transforms

ROWS = 64   # a warpgroup's query rows (wgmma's M)
SMEM_BYTES = 227 * 1024


def _smem(tokens: int, head_dim: int, itemsize: int) -> int:
    """Shared memory bytes of a CTA, at most: the pair's keys and values, and per warpgroup its queries (no wider
    than the pair) and output."""
    return itemsize * (2 * tokens * 2 * head_dim + 2 * ROWS * (2 * head_dim + head_dim))


def applies(dtype, *, tokens: int, num_heads: int, head_dim: int) -> bool:
    """Whether the kernel takes this attention: whole warpgroups of query rows, at most 256 keys (one wgmma's N), heads
    in pairs whose columns take a swizzle (32 bytes at least, wgmma's) and a head's a 16-byte store (TMA's unit),
    everything in one CTA's shared memory, and bf16 on a Hopper GPU (any float in the CPU interpreter)."""
    size = jnp.dtype(dtype).itemsize
    fits = (tokens % ROWS == 0 and tokens <= 256 and num_heads % 2 == 0 and (2 * head_dim * size) % 32 == 0
            and (head_dim * size) % 16 == 0 and 2 * head_dim <= 256 and _smem(tokens, head_dim, size) <= SMEM_BYTES)
    if jax.default_backend() == "cpu":
        return fits
    return fits and hopper() and jnp.dtype(dtype) == jnp.bfloat16


def _window(hd: int, dtype) -> int:
    """A head's columns as its warpgroup reads them from the pair's: the head dim rounded up to whole swizzle tiles
    (80 of So400m's 144: the first head's [0, 80), the second's [64, 144))."""
    tile = transforms(2 * hd, dtype)[0].tiling[1]
    return -(-hd // tile) * tile


@functools.lru_cache(maxsize=None)
def _call(images: int, tokens: int, num_heads: int, hd: int, dtype):
    pair, width, win = 2 * hd, num_heads * hd, _window(hd, dtype)
    step = pair - win   # the second head's window starts here
    tiles = transforms(pair, dtype)   # q, k and v share a swizzle: wgmma takes one for both operands
    size = jnp.dtype(dtype).itemsize
    out_tiles = (plgpu.TilingTransform((8, 16 // size)),)   # a head's 16-byte column pieces, unswizzled
    scale = float(hd) ** -0.5

    def kernel(qkv_gmem, o_gmem, q_smem, k_smem, v_smem, o_smem, q_bar, k_bar, v_bar):
        wg = lax.axis_index("wg")   # the pair's head this warpgroup takes
        img, n, qi = lax.axis_index("i"), lax.axis_index("n"), lax.axis_index("q")
        keys, rows = pl.ds(img * tokens, tokens), pl.ds(img * tokens + qi * ROWS, ROWS)
        own = pl.ds(wg * step, win)   # the warpgroup's window of the pair's columns
        q = q_smem.at[wg]
        plgpu.copy_gmem_to_smem(qkv_gmem.at[rows, pl.ds(n * pair + wg * step, win)], q, q_bar.at[wg])

        @pl.when(wg == 0)
        def _():   # the pair's keys, then its values: the logits start when the keys are in
            plgpu.copy_gmem_to_smem(qkv_gmem.at[keys, pl.ds(width + n * pair, pair)], k_smem, k_bar)
            plgpu.copy_gmem_to_smem(qkv_gmem.at[keys, pl.ds(2 * width + n * pair, pair)], v_smem, v_bar)

        plgpu.barrier_wait(q_bar.at[wg])
        col = _iota((ROWS, win), 1) - wg * (win - hd)   # the window's columns, the head's at [0, hd)
        q[...] = jnp.where((col >= 0) & (col < hd), q[...], jnp.zeros((), dtype))
        plgpu.commit_smem()
        plgpu.barrier_wait(k_bar)

        if _old_interpreter():
            s = lax.dot_general(q[...], k_smem[:, own], (((1,), (1,)), ((), ())), preferred_element_type=jnp.float32)
        else:
            def qk(acc_ref):
                plgpu.wgmma(acc_ref, q, k_smem.at[:, own].transpose((1, 0)))
                return acc_ref[...]
            s = pl.run_scoped(qk, plgpu.ACC((ROWS, tokens), jnp.float32))
        s = s * scale
        p = jnp.exp(s - lax.broadcast_in_dim(s.max(axis=1), s.shape, [0]))
        l = p.sum(axis=1)
        plgpu.barrier_wait(v_bar)
        if _old_interpreter():
            o = jnp.dot(p.astype(dtype), v_smem[:, own], preferred_element_type=jnp.float32)
        else:   # p from registers
            def pv(acc_ref):
                plgpu.wgmma(acc_ref, p.astype(dtype), v_smem.at[:, own])
                return acc_ref[...]
            o = pl.run_scoped(pv, plgpu.ACC((ROWS, win), jnp.float32))
        o = (o / lax.broadcast_in_dim(l, o.shape, [0])).astype(dtype)
        for head in range(2):   # a static slice of the registers: the head's columns of the window
            @pl.when(wg == head)
            def _():
                o_smem.at[head][...] = o[:, head * (win - hd):head * (win - hd) + hd]
        plgpu.commit_smem()
        plgpu.copy_smem_to_gmem(o_smem.at[wg], o_gmem.at[rows, pl.ds(n * pair + wg * hd, hd)])
        plgpu.wait_smem_to_gmem(0)

    scratch = dict(
        q_smem=plgpu.SMEM((2, ROWS, win), dtype, transforms=tiles),
        k_smem=plgpu.SMEM((tokens, pair), dtype, transforms=tiles),
        v_smem=plgpu.SMEM((tokens, pair), dtype, transforms=tiles),
        o_smem=plgpu.SMEM((2, ROWS, hd), dtype, transforms=out_tiles),
        q_bar=plgpu.Barrier(num_arrivals=1, num_barriers=2),
        k_bar=plgpu.Barrier(num_arrivals=1), v_bar=plgpu.Barrier(num_arrivals=1))

    def entry(*refs):
        pl.run_scoped(lambda **scoped: kernel(*refs, **scoped), **scratch, collective_axes="wg")

    on_cpu = jax.default_backend() == "cpu"
    return plgpu.kernel(entry, out_type=jax.ShapeDtypeStruct((images * tokens, width), dtype),
                        grid=(images, num_heads // 2, tokens // ROWS), grid_names=("i", "n", "q"),
                        num_threads=2, thread_name="wg", kernel_name="vision_attention_mosaic",
                        compiler_params=plgpu.CompilerParams(lowering_semantics=plgpu.LoweringSemantics.Warpgroup,
                                                             approx_math=True),
                        **({"interpret": _interpret()} if on_cpu else {}))


def attention(qkv, *, images: int, num_heads: int):
    """Softmax attention within each image: qkv (R, 3 N H), each row [q | k | v] with heads side by side (the fused
    GEMM's output, bias added), rows image-major -> (R, N H) in qkv's dtype. `applies` must hold."""
    r, c = qkv.shape
    hd, t = c // (3 * num_heads), r // images
    if hd * 3 * num_heads != c or t * images != r or not applies(qkv.dtype, tokens=t, num_heads=num_heads,
                                                                   head_dim=hd):
        raise ValueError(f"qkv {qkv.shape} ({images} images, {num_heads} heads): the Mosaic GPU vision attention "
                         f"does not take it")
    return _call(images, t, num_heads, hd, jnp.dtype(qkv.dtype))(qkv)
