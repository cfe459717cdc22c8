"""The engine's SigLIP: plain jnp over `weights.vision_weights`, the same function as `pi0_jax.siglip.Siglip`.

What differs from the Flax module is the grouping of matmuls and the weights' layout: q/k/v are one (D, 3 N H) GEMM
with one bias, the attention output one (N H, D) GEMM, and every matmul goes through the engine's one entry point
(`layers._mm`), so FP8 weights sit (out, in) as cuBLASLt's FP8 GEMM reads them. (One q/k/v GEMM measured faster
than three at every batch but bf16 from ~96 images, where cutting its output in three for cuDNN costs copies:
docs/BENCHMARKS.md.) Numerics as Flax computes them: the
patch convolution and the position add in f32; LayerNorm statistics in f32 (Flax's fast variance, E[x²] - E[x]²,
eps 1e-6), the normalised value cast to the activation dtype; each Dense in the activation dtype with its bias added
in it; GELU-tanh; attention as Flax's `dot_product_attention` ("xla"), cuDNN's fused kernel ("cudnn"), or a Pallas
kernel that reads q, k and v in place from the fused GEMM's output ("pallas", `ops.vision_attention`).

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
from pi0_jax.ops import vision_attention


def layer_norm(x, p, dtype):
    xf = x.astype(jnp.float32)
    mean = jnp.mean(xf, axis=-1, keepdims=True)
    var = jnp.maximum(jnp.mean(jnp.square(xf), axis=-1, keepdims=True) - jnp.square(mean), 0.0)
    return ((xf - mean) * (jax.lax.rsqrt(var + 1e-6) * p["scale"]) + p["bias"]).astype(dtype)


def _dense(x, w, b):
    return layers._mm(x, w) + b


def block(cfg: SiglipConfig, w, x, *, attention: str):
    """One pre-LN encoder block. x (B, T, D) in the activation dtype."""
    dtype = x.dtype
    b, t = x.shape[:2]
    h = layer_norm(x, w["ln1"], dtype)
    qkv = _dense(h, w["qkv"], w["qkv_bias"])
    if attention == "pallas":   # reads q, k, v in place: no copies
        y = vision_attention.attention(qkv.reshape(b * t, -1), images=b, num_heads=cfg.num_heads).reshape(b, t, -1)
    else:
        q, k, v = einops.rearrange(qkv, "B T (three N H) -> three B T N H", three=3, N=cfg.num_heads)
        y = ops_attention.fused(q, k, v) if attention == "cudnn" else nn.dot_product_attention(q, k, v, dtype=dtype)
        y = einops.rearrange(y, "B T N H -> B T (N H)")
    x = x + _dense(y, w["out"], w["out_bias"])
    h = layer_norm(x, w["ln2"], dtype)
    h = nn.gelu(_dense(h, w["fc1"], w["fc1_bias"]), approximate=True)
    return x + _dense(h, w["fc2"], w["fc2_bias"])


def encode(cfg: SiglipConfig, w: dict, images, *, dtype, unroll: bool, attention: str = "xla"):
    """images (B, S, S, 3) in [-1, 1] -> tokens (B, 256, out_dim) in dtype (image tokens are not scaled by
    sqrt(width), spec §3.8). w["blocks"]: a list of per-block dicts (unroll) or one stacked dict (lax.scan)."""
    p = cfg.patch_size
    x = jax.lax.conv_general_dilated(jnp.asarray(images, jnp.float32), w["embedding"]["kernel"].astype(jnp.float32),
                                     (p, p), "VALID", dimension_numbers=("NHWC", "HWIO", "NHWC"))
    x = x + w["embedding"]["bias"].astype(jnp.float32)
    x = x.reshape(x.shape[0], -1, x.shape[-1])  # row-major: token = row * (S / 14) + col
    x = (x + w["pos"].astype(jnp.float32)).astype(dtype)
    x, _ = layers.run_layers(lambda wi, x: (block(cfg, wi, x, attention=attention),), w["blocks"], x,
                             unroll=unroll)
    x = layer_norm(x, w["norm"], dtype)
    return _dense(x, w["head"]["kernel"], w["head"]["bias"])
