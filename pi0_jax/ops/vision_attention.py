"""SigLIP's self-attention as one Pallas kernel (Triton on GPU, interpret mode on CPU) that reads q, k and v where
the fused q/k/v GEMM wrote them and writes the heads side by side, as the out-projection reads them.

cuDNN's fused attention takes q, k and v as three buffers, so feeding it from one (D, 3 N H) GEMM costs three copies
per layer (81 of the tower's 386 kernels at B = 1, docs/BENCHMARKS.md) and a memset. This kernel reads each head's
columns in place. Triton's blocks are powers of two, so a head dim that is not one (So400m's 72) is read as two
pieces that are, both inside the head: [0, 64) and the last 16 columns [56, 72). The second piece's first 8 columns
repeat the first piece's: they are zeroed in q, so each product counts once, and left out of the second piece's
store.

Numerics as cuDNN's kernel (`ops.attention.fused`): f32 logits scaled by 1 / sqrt(H), an online softmax in f32 over
key blocks, the probabilities rounded to the activation dtype for the PV product with an f32 accumulator, the output
rounded once. Flax's XLA attention (the "xla" path) scales q in the dtype and forms the logits in it; in f32 the
two agree to rounding.

Between FP8 GEMMs (`engine.vision`) the kernel reads the q/k/v GEMM's raw product, whose per-column output scale
and bias XLA would apply in a pass of its own, and writes the out-projection's e4m3 input. Scaling every k and v
tile as it is read took the kernel 40 % longer (its tiles no longer go straight from memory to the dot), so each
lands where it is cheap, exact in real arithmetic: q gets its own scale and bias, then k's scale (q·(s ⊙ k) =
(s ⊙ q)·k); k's bias adds the same q·b to every logit of a row, which the softmax cancels; v's scale and bias apply
to the normalised output (the weights sum to 1). So the kernel agrees with XLA's order to f32 rounding in f32 and
to bf16 rounding in bf16. Triton divides f32 approximately (within 2 ulp), so a value that close to a rounding
boundary of e4m3 may round the other way: rare, one e4m3 step.

Axis legend: R rows (images x T tokens, image-major), T tokens per image, N heads, H head dim.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import pallas as pl
from jax.experimental.custom_partitioning import custom_partitioning
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P

from pi0_jax.ops.formats import E4M3, E4M3_MAX
from pi0_jax.ops.pallas_base import ALIGN, call, dot, fit, plgpu

NEG = float(np.finfo(np.float32).min)  # the running max before any key (no key is masked here)


@dataclasses.dataclass(frozen=True)
class Blocks:
    """Queries per program, keys per loop step (powers of two, shrunk to divide T) and Triton launch parameters.
    Defaults: of six settings, the one within noise of the best at 3 and 24 images and the best at 192 (H100,
    docs/BENCHMARKS.md)."""

    q: int = 128
    kv: int = 64
    num_warps: int = 4
    num_stages: int = 2


def pieces(head_dim: int) -> tuple:
    """(offset, width, repeated) column pieces of one head: power-of-two widths >= 16 inside [0, head_dim) that cover
    it; `repeated` leading columns of a piece are the previous piece's last ones."""
    if head_dim < ALIGN:
        raise ValueError(f"the Pallas vision attention needs a head dim >= {ALIGN}, got {head_dim}")
    first = 1 << (head_dim.bit_length() - 1)
    if first == head_dim:
        return ((0, head_dim, 0),)
    width = max(ALIGN, 1 << (head_dim - first - 1).bit_length())
    return (0, first, 0), (head_dim - width, width, first - (head_dim - width))


def _kernel(qkv_ref, cs_ref, b_ref, act_ref, o_ref, *, t, bq, bkv, width, hd, parts, scale, scaled):
    """Program (i, n, qi): query block qi of image i, head n, over all T keys of image i."""
    i, n, qi = pl.program_id(0), pl.program_id(1), pl.program_id(2)
    rows = pl.ds(i * t + qi * bq, bq)
    dtype = qkv_ref.dtype

    def cols(base, part):
        return pl.ds(base + n * hd + part[0], part[1])

    def vector(ref, base, part):
        return ref[cols(base, part)].astype(jnp.float32)[None, :]

    qs = []
    for part in parts:
        q = qkv_ref[rows, cols(0, part)]
        if scaled:   # the raw product: q's scale and bias (`scale_bias`), then k's scale folded into q (module doc)
            q = (q.astype(jnp.float32) * vector(cs_ref, 0, part)).astype(dtype).astype(jnp.float32)
            q = ((q + vector(b_ref, 0, part)).astype(dtype).astype(jnp.float32) * vector(cs_ref, width, part))
            q = q.astype(dtype)
        if part[2]:
            q = jnp.where(jnp.arange(part[1])[None, :] >= part[2], q, jnp.zeros_like(q))
        qs.append(q)

    def body(j, carry):
        o, mx, l = carry
        keys = pl.ds(i * t + j * bkv, bkv)
        logits = sum(dot(q, qkv_ref[keys, cols(width, part)], trans_b=True) for q, part in zip(qs, parts)) * scale
        m_new = jnp.maximum(mx, jnp.max(logits, axis=1))
        corr = jnp.exp(mx - m_new)
        p = jnp.exp(logits - m_new[:, None])
        pv = p.astype(dtype)
        o = tuple(acc * corr[:, None] + dot(pv, qkv_ref[keys, cols(2 * width, part)]) for acc, part in zip(o, parts))
        return o, m_new, l * corr + jnp.sum(p, axis=1)

    init = (tuple(jnp.zeros((bq, part[1]), jnp.float32) for part in parts), jnp.full((bq,), NEG, jnp.float32),
            jnp.zeros((bq,), jnp.float32))
    o, _, l = jax.lax.fori_loop(0, t // bkv, body, init)
    for acc, part in zip(o, parts):
        out = acc / l[:, None]
        if scaled:   # v's scale and bias, on the weighted sum of raw v (the weights sum to 1)
            out = out * vector(cs_ref, 2 * width, part) + vector(b_ref, 2 * width, part)
        out = out.astype(dtype)
        if o_ref.dtype != dtype:   # e4m3 as `formats.quantise` (Triton's f32 division: module doc)
            out = jnp.clip(out.astype(jnp.float32) / act_ref[...][None, :], -E4M3_MAX, E4M3_MAX)
        out = out.astype(o_ref.dtype)
        if part[2]:
            plgpu.store(o_ref.at[rows, cols(0, part)], out, mask=jnp.arange(part[1])[None, :] >= part[2])
        else:
            o_ref[rows, cols(0, part)] = out


def attention(qkv, *, images: int, num_heads: int, col_scale=None, bias=None, quantise=None,
              blocks: Blocks = Blocks()):
    """Softmax attention within each image: qkv (R, 3 N H), each row [q | k | v] with heads side by side (the fused
    GEMM's output, bias added), rows image-major -> (R, N H) in qkv's dtype.

    An FP8 GEMM's raw product instead (`formats.fp8_product`), with its col_scale (3 N H,) f32
    (`formats.output_scale`) and the Dense's bias (3 N H,), which XLA would apply first (`scale_bias`); the kernel
    applies them where they cost least (module doc). quantise: the out-projection's activation scale
    (`matmul.input_scale`): the output, in qkv's dtype, quantised to e4m3 as `formats.quantise` does.

    Under a sharded jit (the simulator's batch mesh) each device runs the kernel on its own images: XLA cannot split
    a kernel it does not know, and would otherwise gather every image onto every device."""
    r, c = qkv.shape
    hd, t = c // (3 * num_heads), r // images
    if hd * 3 * num_heads != c or t * images != r:
        raise ValueError(f"qkv {qkv.shape} is not {images} images x T rows of 3 x {num_heads} heads")
    scaled = col_scale is not None
    if scaled != (bias is not None) or (scaled and (col_scale.shape, bias.shape) != ((c,), (c,))):
        raise ValueError(f"vision attention: col_scale and bias go together, each ({c},); got "
                         f"{getattr(col_scale, 'shape', None)} and {getattr(bias, 'shape', None)}")
    pieces(hd)
    if min(fit(blocks.q, t), fit(blocks.kv, t)) < ALIGN:
        raise ValueError(f"the Pallas vision attention needs T divisible by {ALIGN}, got {t}")
    # the unused operands are numpy constants, not traced ops (XLA still fills a splat once a call, a broadcast)
    cs = col_scale.astype(jnp.float32) if scaled else np.ones((c,), np.float32)
    b = bias if scaled else np.zeros((c,), qkv.dtype)
    act = np.ones((1,), np.float32) if quantise is None else jnp.reshape(quantise, (1,)).astype(jnp.float32)
    return _partitioned(qkv, cs, b, act, images, num_heads, blocks, scaled, quantise is not None)


def scale_bias(qkv, col_scale, bias):
    """qkv * col_scale + bias: XLA's form of what the kernel does to a raw product as it reads it (`qmatmul`'s
    scaling, then the Dense's bias, each rounded to the dtype)."""
    return (qkv.astype(jnp.float32) * col_scale).astype(qkv.dtype) + bias


@functools.partial(custom_partitioning, static_argnums=(4, 5, 6, 7, 8))
def _partitioned(qkv, cs, b, act, images, num_heads, blocks, scaled, quantised):
    return _attention(qkv, cs, b, act, images, num_heads, blocks, scaled, quantised)


def _rows(mesh, sharding, images: int) -> tuple:
    """(the rows' sharding, devices over them): qkv's row sharding where each device gets whole images, else none."""
    axes = sharding.spec[0] if len(sharding.spec) else None
    n = math.prod(mesh.shape[a] for a in (axes if isinstance(axes, tuple) else (axes,))) if axes else 1
    if n == 1 or images % n:
        return NamedSharding(mesh, P()), 1
    return NamedSharding(mesh, P(axes, None)), n


def _partition(images, num_heads, blocks, scaled, quantised, mesh, arg_shapes, result_shape):
    rows, n = _rows(mesh, arg_shapes[0].sharding, images)
    fn = functools.partial(_attention, images=images // n, num_heads=num_heads, blocks=blocks, scaled=scaled,
                           quantised=quantised)
    return mesh, fn, rows, (rows,) + (NamedSharding(mesh, P()),) * 3


def _infer(images, num_heads, blocks, scaled, quantised, mesh, arg_shapes, result_shape):
    return _rows(mesh, arg_shapes[0].sharding, images)[0]


# need_replication lists the factors in their order of appearance (Shardy's verifier wants them sorted)
_partitioned.def_partition(partition=_partition, infer_sharding_from_operands=_infer,
                           sharding_rule="r c, c, c, o -> r d", need_replication_factors=("c", "o", "d"))


def _attention(qkv, cs, b, act, images: int, num_heads: int, blocks: Blocks, scaled: bool, quantised: bool):
    r, c = qkv.shape
    hd, t = c // (3 * num_heads), r // images
    bq, bkv = fit(blocks.q, t), fit(blocks.kv, t)
    kernel = functools.partial(_kernel, t=t, bq=bq, bkv=bkv, width=num_heads * hd, hd=hd, parts=pieces(hd),
                               scale=float(hd) ** -0.5, scaled=scaled)
    out = jax.ShapeDtypeStruct((r, num_heads * hd), E4M3 if quantised else qkv.dtype)
    return call(kernel, grid=(images, num_heads, t // bq), out_shape=out, name="vision_attention",
                num_warps=blocks.num_warps, num_stages=blocks.num_stages)(qkv, cs, b, act)
