"""The engine's SigLIP: plain jnp over `weights.vision_weights`, the same function as `pi0_jax.siglip.Siglip`.

What differs from the Flax module is the grouping of matmuls and the weights' layout: q/k/v are one (D, 3 N H) GEMM
with one bias, the attention output one (N H, D) GEMM, and every matmul goes through the engine's one entry point
(`layers._mm`), so FP8 weights sit (out, in) as cuBLASLt's FP8 GEMM reads them. (One q/k/v GEMM measured faster
than three at every batch but bf16 from ~96 images, where cutting its output in three for cuDNN costs copies:
docs/BENCHMARKS.md.) Numerics as Flax computes them: the
patch convolution and the position add in f32; LayerNorm statistics in f32 (Flax's fast variance, E[x²] - E[x]²,
eps 1e-6), the normalised value cast to the activation dtype; each Dense in the activation dtype with its bias added
in it; GELU-tanh; attention as Flax's `dot_product_attention` ("xla"), cuDNN's fused kernel ("cudnn"), or a Pallas
kernel that reads q, k and v in place from the fused GEMM's output ("pallas", `ops.vision_attention`). Each residual
add is done with the LayerNorm after it (`add_norm`): XLA's ops, or one Pallas kernel (norm="pallas",
`ops.layer_norm`), so a block hands the next its MLP output with the bias not yet added.

Axis legend: B images, T tokens (256 patches), D width, N heads, H head dim.
"""

from __future__ import annotations

import einops
import flax.linen as nn
import jax
import jax.numpy as jnp

from pi0_jax.config import SiglipConfig
from pi0_jax.engine import layers
from pi0_jax.ops import attention as ops_attention
from pi0_jax.ops import layer_norm as ops_layer_norm
from pi0_jax.ops import vision_attention


def layer_norm(x, p, dtype):
    xf = x.astype(jnp.float32)
    mean = jnp.mean(xf, axis=-1, keepdims=True)
    var = jnp.maximum(jnp.mean(jnp.square(xf), axis=-1, keepdims=True) - jnp.square(mean), 0.0)
    return ((xf - mean) * (jax.lax.rsqrt(var + 1e-6) * p["scale"]) + p["bias"]).astype(dtype)


def add_norm(x, f, p, dtype, norm: str):
    """(x', LayerNorm(x')), x' = x + (y + b) for f = (y, b), a Dense's product and bias not yet added (x' = x for f
    None): the residual add and the norm after it, one kernel with norm="pallas" (`ops.layer_norm`) where XLA runs
    two or three."""
    if norm == "pallas":
        if f is None:
            return x, ops_layer_norm.layer_norm(x, p["scale"], p["bias"], eps=1e-6, dtype=dtype)
        return ops_layer_norm.layer_norm(x, p["scale"], p["bias"], residual=f, eps=1e-6, dtype=dtype)
    x = x if f is None else x + (f[0] + f[1])
    return x, layer_norm(x, p, dtype)


def _dense(x, w, b):
    return layers._mm(x, w) + b


def block(cfg: SiglipConfig, w, x, f, *, attention: str, norm: str = "xla"):
    """One pre-LN encoder block. x (B, T, D) the residual stream in the activation dtype, f the previous block's
    MLP output (product, bias) not yet added to it (None before the first block) -> (x, f) likewise: each residual
    add runs with the norm after it."""
    dtype = x.dtype
    b, t = x.shape[:2]
    x, h = add_norm(x, f, w["ln1"], dtype, norm)
    qkv = _dense(h, w["qkv"], w["qkv_bias"])
    if attention == "pallas":   # reads q, k, v in place: no copies
        y = vision_attention.attention(qkv.reshape(b * t, -1), images=b, num_heads=cfg.num_heads).reshape(b, t, -1)
    else:
        q, k, v = einops.rearrange(qkv, "B T (three N H) -> three B T N H", three=3, N=cfg.num_heads)
        y = ops_attention.fused(q, k, v) if attention == "cudnn" else nn.dot_product_attention(q, k, v, dtype=dtype)
        y = einops.rearrange(y, "B T N H -> B T (N H)")
    x, h = add_norm(x, (layers._mm(y, w["out"]), w["out_bias"]), w["ln2"], dtype, norm)
    h = nn.gelu(_dense(h, w["fc1"], w["fc1_bias"]), approximate=True)
    return x, (layers._mm(h, w["fc2"]), w["fc2_bias"])


def encode(cfg: SiglipConfig, w: dict, images, *, dtype, unroll: bool, attention: str = "xla", norm: str = "xla"):
    """images (B, S, S, 3) in [-1, 1] -> tokens (B, 256, out_dim) in dtype (image tokens are not scaled by
    sqrt(width), spec §3.8). w["blocks"]: a list of per-block dicts (unroll) or one stacked dict (lax.scan).
    norm: "xla" or "pallas" (`add_norm`)."""
    p = cfg.patch_size
    x = jax.lax.conv_general_dilated(jnp.asarray(images, jnp.float32), w["embedding"]["kernel"].astype(jnp.float32),
                                     (p, p), "VALID", dimension_numbers=("NHWC", "HWIO", "NHWC"))
    x = x + w["embedding"]["bias"].astype(jnp.float32)
    x = x.reshape(x.shape[0], -1, x.shape[-1])  # row-major: token = row * (S / 14) + col
    x = (x + w["pos"].astype(jnp.float32)).astype(dtype)
    blocks = w["blocks"]
    if unroll:   # the first block has no MLP output to add
        x, f = block(cfg, blocks[0], x, None, attention=attention, norm=norm)
        blocks = blocks[1:]
    else:        # lax.scan's carry keeps one structure: a zero MLP output (x + 0 is x)
        f = (jnp.zeros_like(x), jnp.zeros(x.shape[-1:], dtype))
    (x, f), _ = layers.run_layers(lambda wi, c: (block(cfg, wi, *c, attention=attention, norm=norm),), blocks,
                                  (x, f), unroll=unroll)
    _, x = add_norm(x, f, w["norm"], dtype, norm)
    return _dense(x, w["head"]["kernel"], w["head"]["bias"])
