"""The engine's SigLIP: plain jnp over `weights.vision_weights`, the same function as `pi0_jax.siglip.Siglip`.

What differs from the Flax module is the grouping of matmuls and the weights' layout: q/k/v are one (D, 3 N H) GEMM
with one bias, the attention output one (N H, D) GEMM, and every matmul goes through the one entry point
(`ops.matmul`), so FP8 weights sit (out, in) as cuBLASLt's FP8 GEMM reads them. (One q/k/v GEMM measured faster
than three at every batch but bf16 from ~96 images, where cutting its output in three for cuDNN costs copies:
docs/BENCHMARKS.md.) Numerics as Flax computes them: the
patch convolution and the position add in f32; LayerNorm statistics in f32, eps 1e-6, the normalised value cast
to the activation dtype (the variance in two passes, the mean then the mean of squared deviations, where Flax takes
E[x²] - E[x]²: equal to f32 rounding, and XLA makes it one kernel where it made two, docs/BENCHMARKS.md); each
Dense in the activation dtype with its bias added in it; GELU-tanh; attention as Flax's `dot_product_attention`
("xla"), cuDNN's fused kernel ("cudnn"), or a Pallas kernel that reads q, k and v in place from the fused GEMM's
output ("pallas", `ops.vision_attention`). Each residual add is done with the LayerNorm after it (`add_norm`): XLA's
ops, or one Pallas kernel (norm="pallas", `ops.layer_norm`), so a block hands the next its MLP output with the bias
not yet added.

FP8 x FP8 GEMMs (`matmul.raw_matmul`) take an e4m3 input and give a raw product whose f32 output scale is applied by
whoever reads it. With the kernels, that is no pass of its own: the LayerNorm kernel writes the next GEMM's e4m3
input and scales the residual's product as it adds it, and the Pallas attention scales and biases q, k and v as it
reads them and writes the out-projection's e4m3 input. XLA's path computes the same ops (`formats.quantise`,
`_finish`); the kernels agree with it to rounding (their module docs say where they reorder).

Axis legend: B images, T tokens (256 patches), D width, N heads, H head dim.
"""

from __future__ import annotations

import einops
import flax.linen as nn
import jax
import jax.numpy as jnp

from pi0_jax.config import SiglipConfig
from pi0_jax.engine import layers
from pi0_jax.engine.weights import FC1_BIAS, FC2_BIAS, LN1_BIAS, LN1_SCALE, LN2_BIAS, LN2_SCALE, OUT_BIAS, QKV_BIAS
from pi0_jax.ops import attention as ops_attention
from pi0_jax.ops import formats, fp8_geglu, matmul
from pi0_jax.ops import layer_norm as ops_layer_norm
from pi0_jax.ops import vision_attention
from pi0_jax.siglip import patch_embed


# FP8 x FP8 fc1: its GEMM, bias, GELU-tanh and fc2's e4m3 input as one Mosaic GPU kernel (`ops.fp8_geglu.gelu`, f32
# in the epilogue) from this many rows (images x 256) where `layers.fp8_mlp_kernel()` holds; else cuBLASLt's GEMM and
# XLA's pass (in the dtype). Alone it was 11 % faster at 6,144 rows (3 cameras, B = 8) and 22 % at 49,152, 10 %
# slower at 768; π0's every-gemm call 2.3 % faster at B = 64 (H200, docs/BENCHMARKS.md, session 57; with session 61's
# launch, `fp8_geglu.GELU_LAUNCH`, 24 % and 29 % faster than XLA's path at 6,144 and 49,152 rows, H100). From 3,072
# rows (B = 4) since session 62: π0's every-gemm call at B = 4 0.6 % faster, its kernel time 1.2 % (H100). None: never.
FP8_GELU_ROWS = 3072


def layer_norm(x, vectors, rows, dtype):
    """LayerNorm with scale vectors[rows[0]] and bias vectors[rows[1]] (a `weights.vision_weights` table); the
    variance from the deviations (module doc)."""
    xf = x.astype(jnp.float32)
    xc = xf - jnp.mean(xf, axis=-1, keepdims=True)
    var = jnp.mean(jnp.square(xc), axis=-1, keepdims=True)
    scale, bias = vectors[rows[0]], vectors[rows[1]]
    return (xc * (jax.lax.rsqrt(var + 1e-6) * scale) + bias).astype(dtype)


def _finish(y, b, scale=None):
    """A Dense's output from its raw product: the FP8 output scale (if any, `matmul.raw_matmul`), then the bias,
    each rounded to the dtype."""
    return y + b if scale is None else vision_attention.scale_bias(y, scale, b)


def add_norm(x, f, norm_vectors, dtype, norm: str, quantise=None):
    """(x', LayerNorm(x')), x' = x + f's Dense output for f = (y, (table, row)[, scale]), a raw product, where its
    bias sits and its FP8 output scale, not yet applied (`_finish`; x' = x for f None): the residual add and the norm
    after it, one kernel with norm="pallas" (`ops.layer_norm`) where XLA runs two or three. norm_vectors: (table,
    (scale row, bias row)). The kernel reads the tables' rows in place. quantise: the next GEMM's
    `matmul.input_scale`; the norm then comes as that GEMM's e4m3 input (in the kernel: no pass of its own)."""
    table, rows = norm_vectors
    if f is not None:
        y, (f_table, f_row), *scale = f
        scale = [v for v in scale if v is not None]
    if norm == "pallas":
        if f is None:
            return x, ops_layer_norm.layer_norm(x, table, rows, eps=1e-6, dtype=dtype, quantise=quantise)
        return ops_layer_norm.layer_norm(x, table, rows, residual=(y, f_table, f_row, *scale), eps=1e-6, dtype=dtype,
                                         quantise=quantise)
    if f is not None:
        x = x + _finish(y, f_table[f_row].astype(x.dtype), *scale)
    h = layer_norm(x, table, rows, dtype)
    return x, (h if quantise is None else formats.quantise(h, quantise))


def _bias(vectors, row: int, n: int, dtype):
    """n values of a `weights.vision_weights` table from its row `row` on (over ceil(n / D) rows), in dtype."""
    rows = -(-n // vectors.shape[-1])
    return vectors[row:row + rows].reshape(-1)[:n].astype(dtype)


def _dense(x, w, b):
    return layers._mm(x, w) + b


def block(cfg: SiglipConfig, w, x, f, vectors, *, attention: str, norm: str = "xla"):
    """One pre-LN encoder block. x (B, T, D) the residual stream in the activation dtype, f the previous block's
    MLP output (raw product, (table, row) of its bias, FP8 output scale or None) not yet added to it (None before
    the first block); vectors: (table, first row) of this block's LayerNorm parameters and biases (the tower's
    `vectors` as (L R, D), or one block's (R, D) rows with first row 0) ->
    (x, f) likewise: each residual add runs with the norm after it. With FP8 weights the activations' quantisation
    happens inside the kernels where there are kernels (the norms' and the Pallas attention's outputs, the
    attention's q/k/v scaling as it reads them)."""
    dtype = x.dtype
    b, t, d = x.shape
    table, first = vectors
    qkv_bias = _bias(table, first + QKV_BIAS, 3 * d, dtype)
    x, h = add_norm(x, f, (table, (first + LN1_SCALE, first + LN1_BIAS)), dtype, norm, matmul.input_scale(w["qkv"]))
    qkv, scale = layers.raw_mm(h, w["qkv"], dtype)
    if attention == "pallas":   # reads q, k, v in place: no copies
        args = {} if scale is None else dict(col_scale=scale, bias=qkv_bias)
        qkv = qkv if scale is not None else qkv + qkv_bias
        y = vision_attention.attention(qkv.reshape(b * t, -1), images=b, num_heads=cfg.num_heads,
                                       quantise=matmul.input_scale(w["out"]), **args).reshape(b, t, -1)
    else:
        qkv = _finish(qkv, qkv_bias, scale)
        q, k, v = einops.rearrange(qkv, "B T (three N H) -> three B T N H", three=3, N=cfg.num_heads)
        y = ops_attention.fused(q, k, v) if attention == "cudnn" else nn.dot_product_attention(q, k, v, dtype=dtype)
        y = einops.rearrange(y, "B T N H -> B T (N H)")
    out, scale = layers.raw_mm(y, w["out"], dtype)
    x, h = add_norm(x, (out, (table, first + OUT_BIAS), scale), (table, (first + LN2_SCALE, first + LN2_BIAS)),
                    dtype, norm, matmul.input_scale(w["fc1"]))
    fc1_bias = _bias(table, first + FC1_BIAS, cfg.mlp_dim, dtype)
    if (FP8_GELU_ROWS is not None and b * t >= FP8_GELU_ROWS and layers.fp8_mlp_kernel()
            and fp8_geglu.gelu_applies(w["fc1"], w["fc2"])):   # h came quantised for fc1 (add_norm)
        h = fp8_geglu.gelu(h.reshape(b * t, -1), w["fc1"], fc1_bias, w["fc2"].act_scale).reshape(b, t, -1)
    else:
        y, scale = layers.raw_mm(h, w["fc1"], dtype)
        h = nn.gelu(_finish(y, fc1_bias, scale), approximate=True)
    y, scale = layers.raw_mm(h, w["fc2"], dtype)
    return x, (y, (table, first + FC2_BIAS), scale)


def _table(w: dict):
    """The tower's `vectors` (L, R, D) as one (L R, D) table and its rows a block."""
    vectors = w["vectors"]
    return vectors.reshape(-1, vectors.shape[-1]), vectors.shape[1]


def encode(cfg: SiglipConfig, w: dict, images, *, dtype, unroll: bool, attention: str = "xla", norm: str = "xla"):
    """images (B, S, S, 3) in [-1, 1] -> tokens (B, 256, out_dim) in dtype (image tokens are not scaled by
    sqrt(width), spec §3.8). w["blocks"]: a list of per-block dicts (unroll) or one stacked dict (lax.scan).
    norm: "xla" or "pallas" (`add_norm`). Unrolled, `encode_head` then `encode_tail` (which the engine's call may
    run as two programs)."""
    if unroll:
        x, f = encode_head(cfg, w, images, dtype=dtype, attention=attention, norm=norm)
        return encode_tail(cfg, {**w, "blocks": []}, x, f, dtype=dtype, attention=attention, norm=norm)
    x = _embed(cfg, w, images, dtype)
    # lax.scan's carry keeps one structure: a zero MLP output (x + 0 is x) with its block's rows, the bias row fixed
    fp8 = matmul.input_scale(w["blocks"]["fc2"]) is not None
    f = (jnp.zeros_like(x), jnp.zeros(w["vectors"].shape[1:], jnp.float32),
         jnp.ones(x.shape[-1:], jnp.float32) if fp8 else None)

    def body(wi, carry):
        x, (y, rows, scale) = carry
        x, (y, (rows, _), scale) = block(cfg, wi["block"], x, (y, (rows, FC2_BIAS), scale), (wi["vectors"], 0),
                                         attention=attention, norm=norm)
        return ((x, (y, rows, scale)),)

    (x, (y, rows, scale)), _ = layers.run_layers(body, {"block": w["blocks"], "vectors": w["vectors"]}, (x, f),
                                                 unroll=False)
    return _project(w, x, (y, (rows, FC2_BIAS), scale), dtype, norm)


def _embed(cfg: SiglipConfig, w: dict, images, dtype):
    x = patch_embed(images, w["embedding"]["kernel"], w["embedding"]["bias"], cfg.patch_size)
    return (x + w["pos"].astype(jnp.float32)).astype(dtype)


def _project(w: dict, x, f, dtype, norm: str):
    """The last MLP output added, the final LayerNorm and the projection to the VLM's width."""
    _, x = add_norm(x, f, (w["norm"], (0, 1)), dtype, norm)
    return _dense(x, w["head"]["kernel"], w["head"]["bias"])


def encode_head(cfg: SiglipConfig, w: dict, images, *, dtype, attention: str = "xla", norm: str = "xla") -> tuple:
    """The tower's first part: the patch embedding and the blocks of w["blocks"] (a list: the tower's first blocks)
    -> (x, f), the residual stream and the last block's MLP output not yet added, as (raw product, FP8 output scale
    or None), its bias left in the table (None without blocks)."""
    x, f = _embed(cfg, w, images, dtype), None   # the first block has no MLP output to add
    table, rows = _table(w)
    for i, wi in enumerate(w["blocks"]):
        x, f = block(cfg, wi, x, f, (table, i * rows), attention=attention, norm=norm)
    return x, None if f is None else (f[0], f[2])


def encode_tail(cfg: SiglipConfig, w: dict, x, f, *, dtype, attention: str = "xla", norm: str = "xla"):
    """The tower after `encode_head`, from its (x, f): the blocks of w["blocks"] (a list, maybe empty: the tower's
    last blocks), the final norm and the projection -> tokens (B, 256, out_dim)."""
    first = w["vectors"].shape[0] - len(w["blocks"])   # the tower's blocks before these
    x, f = blocks_from(cfg, w, x, f, first, attention=attention, norm=norm)
    return _project(w, x, f, dtype, norm)


def blocks_from(cfg: SiglipConfig, w: dict, x, f, first: int, *, attention: str, norm: str) -> tuple:
    """Blocks first, first + 1, ... (w["blocks"]) from the (x, f) of the blocks before them (`encode_head`'s) -> (x,
    f) with f as `block` gives it."""
    table, rows = _table(w)
    if f is not None:   # block first - 1's MLP output
        f = (f[0], (table, (first - 1) * rows + FC2_BIAS), f[1])
    for i, wi in enumerate(w["blocks"], first):
        x, f = block(cfg, wi, x, f, (table, i * rows), attention=attention, norm=norm)
    return x, f
