"""SigLIP ViT (So400m/14) as openpi instantiates it: no pooling, per-token linear head to the VLM width.

Param names and the scanned (stacked) layer layout mirror openpi / big_vision, so released checkpoints load as is:
`embedding/{kernel,bias}`, `pos_embedding`, `Transformer/encoderblock/...` (leading axis = depth),
`Transformer/encoder_norm`, `head`.
"""

from __future__ import annotations

import einops
import flax.linen as nn
import jax.numpy as jnp
import numpy as np

from pi0_jax.config import SiglipConfig
from pi0_jax.ops import matmul as ops_matmul


def patch_embed(images, kernel, bias, p: int):
    """The patch convolution (kernel p x p, stride p, VALID, bias) in f32 as one dot: (B, S, S, C) -> (B, T, D), tokens
    row-major (token = row * (S / p) + col). The patches do not overlap, so the convolution is a reshape and a dot over
    (p, p, C), the kernel's HWIO order: the convolution's sums in another order (at default precision a GPU runs both
    in TF32). The reference module and the engine share it, so they sum alike."""
    b, s, _, c = images.shape
    g = s // p
    x = jnp.asarray(images, jnp.float32)[:, :g * p, :g * p].reshape(b, g, p, g, p, c)   # VALID: drop a remainder
    x = einops.rearrange(x, "B gh ph gw pw C -> B (gh gw) (ph pw C)")
    return x @ kernel.astype(jnp.float32).reshape(p * p * c, -1) + bias.astype(jnp.float32)


class PatchEmbedding(nn.Module):
    """`nn.Conv(width, (p, p), strides=(p, p), padding="VALID", dtype=float32)`'s parameters (kernel (p, p, C, D),
    bias (D,)) and function, as `patch_embed`."""

    width: int
    patch: int

    @nn.compact
    def __call__(self, images):
        p = self.patch
        kernel = self.param("kernel", nn.initializers.lecun_normal(), (p, p, images.shape[-1], self.width), jnp.float32)
        bias = self.param("bias", nn.initializers.zeros, (self.width,), jnp.float32)
        return patch_embed(images, kernel, bias, p)


class MlpBlock(nn.Module):
    mlp_dim: int
    dtype_mm: jnp.dtype

    @nn.compact
    def __call__(self, x):
        inits = {"kernel_init": nn.initializers.xavier_uniform(), "bias_init": nn.initializers.normal(stddev=1e-6)}
        d = x.shape[-1]
        x = nn.Dense(self.mlp_dim, dtype=self.dtype_mm, **inits)(x)
        x = nn.gelu(x)  # approximate=True: the tanh GELU (HF `gelu_pytorch_tanh`)
        return nn.Dense(d, dtype=self.dtype_mm, **inits)(x)


class Encoder1DBlock(nn.Module):
    """Pre-LN block. LayerNorm statistics are computed in >= f32 by Flax; eps 1e-6."""

    mlp_dim: int
    num_heads: int
    dtype_mm: jnp.dtype

    @nn.compact
    def __call__(self, x, _):
        y = nn.LayerNorm(dtype=self.dtype_mm)(x)
        y = nn.MultiHeadDotProductAttention(
            num_heads=self.num_heads, kernel_init=nn.initializers.xavier_uniform(), deterministic=True,
            dtype=self.dtype_mm,
        )(y, y)
        x = x + y
        y = nn.LayerNorm(dtype=self.dtype_mm)(x)
        x = x + MlpBlock(mlp_dim=self.mlp_dim, dtype_mm=self.dtype_mm)(y)
        return x, None


class Encoder(nn.Module):
    """One `encoderblock` scanned over depth, its params stacked on a leading axis (openpi's layout)."""

    cfg: SiglipConfig
    dtype_mm: jnp.dtype

    @nn.compact
    def __call__(self, x):
        blocks = nn.scan(
            Encoder1DBlock, variable_axes={"params": 0}, split_rngs={"params": True}, length=self.cfg.depth,
        )(mlp_dim=self.cfg.mlp_dim, num_heads=self.cfg.num_heads, dtype_mm=self.dtype_mm, name="encoderblock")
        x, _ = blocks(x, None)
        return nn.LayerNorm(name="encoder_norm", dtype=self.dtype_mm)(x)


class Siglip(nn.Module):
    """Images (B, H, W, 3) float in [-1, 1] -> tokens (B, (H/14)*(W/14), out_dim).

    Returns `(tokens, intermediates)`; intermediates hold the patch embedding and the encoder output. The engine's
    copy of this function is `pi0_jax.engine.vision`.
    """

    cfg: SiglipConfig
    out_dim: int
    dtype_mm: jnp.dtype = jnp.bfloat16

    @nn.compact
    def __call__(self, image):
        # fp32 island: the patch conv and the position-embedding add run in f32, then cast to dtype_mm.
        x = PatchEmbedding(self.cfg.width, self.cfg.patch_size, name="embedding")(image)
        _, t, c = x.shape
        pos = self.param("pos_embedding", nn.initializers.normal(stddev=1 / np.sqrt(c)), (1, t, c), jnp.float32)
        x = x + pos
        stem = x
        x = x.astype(self.dtype_mm)
        with nn.intercept_methods(ops_matmul.dense_interceptor):  # quantised kernels take their op
            encoded = Encoder(self.cfg, self.dtype_mm, name="Transformer")(x)
            # Image tokens are *not* scaled by sqrt(width) (spec §3.8).
            tokens = nn.Dense(self.out_dim, dtype=self.dtype_mm, kernel_init=nn.initializers.zeros,
                              name="head")(encoded)
        return tokens, {"stem": stem, "encoded": encoded}
