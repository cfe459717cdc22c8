"""The multi-expert Gemma transformer of π0 / π0.5 (spec §4).

Einsum axis legend:
  B batch, T query tokens, S key tokens (cache + current), L layers, D model width (per expert),
  N query heads, K kv heads (1: MQA), G query heads per kv head (N // K), H head dim, F MLP hidden dim.

Several token streams ("experts") share one joint self-attention per layer; each expert has its own projections,
norms and MLP. Stream 0 is the PaliGemma VLM (prefix), stream 1 the action expert (suffix). A stream may be None,
in which case its weights are not run. Param names equal openpi's JAX tree (expert i > 0 carries the suffix `_i`) and
layers are stacked by `nn.scan` along a leading L axis.
"""

from __future__ import annotations

from collections.abc import Sequence

import einops
import flax.linen as nn
import flax.struct
import jax
import jax.numpy as jnp

from pi0_jax.config import GemmaConfig
from pi0_jax.ops.matmul import matmul

# openpi's mask fill: finite, so a fully-masked (padded) query row softmaxes to a uniform, finite distribution.
_BIG_NEG = -2.3819763e38


@flax.struct.dataclass
class KVCache:
    """Prefix keys/values of every layer, post-RoPE, read-only during denoising.

    k, v: (L, B, P, K, H). mask: (B, P) bool, which prefix tokens are valid (keys the suffix may attend to).
    state: (B, action_dim) f32, the observation's state, which the π0 suffix embeds as its first token.
    """

    k: jax.Array
    v: jax.Array
    mask: jax.Array
    state: jax.Array | None = None


def _name(name: str, i: int) -> str:
    return name if i == 0 else f"{name}_{i}"


class Einsum(nn.Module):
    shape: tuple[int, ...]
    init_fn: nn.initializers.Initializer = nn.initializers.zeros

    @nn.compact
    def __call__(self, eqn: str, x: jax.Array) -> jax.Array:
        return matmul(eqn, x, self.param("w", self.init_fn, self.shape))


class RMSNorm(nn.Module):
    """RMSNorm with weight applied as (1 + scale); with `cond`, adaRMS: scale/shift/gate from a Dense of `cond`.

    Statistics and normalisation are computed in f32 (fp32 island), the result is cast back to the input dtype.
    Returns (y, gate); gate is None for the plain norm.
    """

    @nn.compact
    def __call__(self, x: jax.Array, cond: jax.Array | None):
        dtype = x.dtype
        var = jnp.mean(jnp.square(x.astype(jnp.float32)), axis=-1, keepdims=True)
        normed = x * jax.lax.rsqrt(var + 1e-6)
        if cond is None:
            scale = self.param("scale", nn.initializers.zeros_init(), (x.shape[-1],))
            return (normed * (1 + scale)).astype(dtype), None
        mod = nn.Dense(x.shape[-1] * 3, kernel_init=nn.initializers.zeros, dtype=dtype)(cond)
        scale, shift, gate = jnp.split(mod if mod.ndim == 3 else mod[:, None, :], 3, axis=-1)  # per sample or token
        return (normed * (1 + scale) + shift).astype(dtype), gate


class FeedForward(nn.Module):
    """GeGLU: gelu_tanh(x W_gate) * (x W_up), then W_down. Params `gating_einsum` (2, D, F) and `linear` (F, D)."""

    width: int
    hidden: int

    @nn.compact
    def __call__(self, x):
        w_gating = self.param(
            "gating_einsum", nn.initializers.lecun_normal(in_axis=-2, out_axis=-1, batch_axis=(0,)),
            (2, self.width, self.hidden),
        )
        gate = nn.gelu(matmul("BTD,DF->BTF", x, w_gating[0]))  # approximate=True (tanh)
        up = matmul("BTD,DF->BTF", x, w_gating[1])
        w_linear = self.param("linear", nn.initializers.lecun_normal(), (self.hidden, self.width))
        return matmul("BTF,FD->BTD", gate * up, w_linear)


def rope_angles(positions: jax.Array, head_dim: int, max_wavelength: float = 10_000) -> tuple:
    """RoPE's (sin, cos) for positions (B, T): (B, T, 1, H/2) f32 each, the 1 broadcasting over heads. Angles in f32
    (an fp32 island: bf16 positions up to ~1000 would lose integers)."""
    half = head_dim // 2
    timescale = max_wavelength ** ((2.0 / head_dim) * jnp.arange(half, dtype=jnp.float32))
    radians = positions[..., None].astype(jnp.float32) / timescale  # (B, T, H/2)
    radians = radians[..., None, :]  # broadcast over heads
    return jnp.sin(radians), jnp.cos(radians)


def rotate(x: jax.Array, angles: tuple) -> jax.Array:
    """x (B, T, N, H) rotated by `rope_angles`' (sin, cos), half-split convention (= HF rotate_half), in f32."""
    sin, cos = angles
    x1, x2 = jnp.split(x.astype(jnp.float32), 2, axis=-1)
    return jnp.concatenate([x1 * cos - x2 * sin, x2 * cos + x1 * sin], axis=-1).astype(x.dtype)


def apply_rope(x: jax.Array, positions: jax.Array, max_wavelength: float = 10_000) -> jax.Array:
    """Rotary embedding of x (B, T, N, H) at positions (B, T): `rotate` by `rope_angles`."""
    return rotate(x, rope_angles(positions, x.shape[-1], max_wavelength))


class Attention(nn.Module):
    configs: Sequence[GemmaConfig]

    @nn.compact
    def __call__(self, xs, positions, attn_mask, kv_cache):
        cfg0 = self.configs[0]
        dtype = next(x.dtype for x in xs if x is not None)
        qkvs = []
        for i, (x, cfg) in enumerate(zip(xs, self.configs)):
            if x is None:
                continue
            q = Einsum(
                (cfg.num_heads, cfg.width, cfg.head_dim), name=_name("q_einsum", i),
                init_fn=nn.initializers.lecun_normal(in_axis=-2, out_axis=-1, batch_axis=(0,)),
            )("BTD,NDH->BTNH", x)
            k, v = Einsum(
                (2, cfg.num_kv_heads, cfg.width, cfg.head_dim), name=_name("kv_einsum", i),
                init_fn=nn.initializers.lecun_normal(in_axis=-2, out_axis=-1, batch_axis=(0, 1)),
            )("BSD,2KDH->2BSKH", x)
            qkvs.append((q, k, v))
        q, k, v = (jnp.concatenate(y, axis=1) for y in zip(*qkvs))

        q = apply_rope(q, positions)
        q = q * jnp.asarray(cfg0.head_dim**-0.5, q.dtype)
        k = apply_rope(k, positions)  # keys are cached post-RoPE
        if kv_cache is not None:
            cache_k, cache_v = kv_cache
            k = jnp.concatenate([cache_k.astype(dtype), k], axis=1)
            v = jnp.concatenate([cache_v.astype(dtype), v], axis=1)

        q = einops.rearrange(q, "B T (K G) H -> B T K G H", K=cfg0.num_kv_heads)
        # fp32 island: logits accumulate and softmax in f32, probabilities return to the activation dtype.
        logits = jnp.einsum("BTKGH,BSKH->BKGTS", q, k, preferred_element_type=jnp.float32)
        if attn_mask.shape != (q.shape[0], q.shape[1], k.shape[1]):
            raise ValueError(f"attn_mask shape {attn_mask.shape} != (B, T, S) = {(q.shape[0], q.shape[1], k.shape[1])}")
        logits = jnp.where(attn_mask[:, None, None, :, :], logits, _BIG_NEG)
        probs = jax.nn.softmax(logits, axis=-1).astype(dtype)
        encoded = jnp.einsum("BKGTS,BSKH->BTKGH", probs, v)
        encoded = einops.rearrange(encoded, "B T K G H -> B T (K G) H")

        out, start = [], 0
        for i, (x, cfg) in enumerate(zip(xs, self.configs)):
            if x is None:
                out.append(None)
                continue
            end = start + x.shape[1]
            out.append(Einsum(
                (cfg.num_heads, cfg.head_dim, cfg.width), name=_name("attn_vec_einsum", i),
                init_fn=nn.initializers.lecun_normal(in_axis=(-3, -2), out_axis=-1),
            )("BTNH,NHD->BTD", encoded[:, start:end]))
            start = end
        return out, (k, v)


def _gated_residual(x, y, gate):
    if x is None:
        return None
    return x + y if gate is None else x + y * gate


class Block(nn.Module):
    configs: Sequence[GemmaConfig]

    @nn.compact
    def __call__(self, xs, kv_cache, positions, attn_mask, adarms_cond):
        normed, gates = [], []
        for i, x in enumerate(xs):
            h, g = RMSNorm(name=_name("pre_attention_norm", i))(x, adarms_cond[i]) if x is not None else (None, None)
            normed.append(h)
            gates.append(g)
        attn_out, kv = Attention(self.configs, name="attn")(normed, positions, attn_mask, kv_cache)
        xs = [_gated_residual(x, y, g) for x, y, g in zip(xs, attn_out, gates)]

        mlp_out, gates = [], []
        for i, (x, cfg) in enumerate(zip(xs, self.configs)):
            if x is None:
                mlp_out.append(None)
                gates.append(None)
                continue
            h, g = RMSNorm(name=_name("pre_ffw_norm", i))(x, adarms_cond[i])
            mlp_out.append(FeedForward(cfg.width, cfg.mlp_dim, name=_name("mlp", i))(h))
            gates.append(g)
        xs = [_gated_residual(x, y, g) for x, y, g in zip(xs, mlp_out, gates)]
        return xs, kv


class Gemma(nn.Module):
    """Multi-expert Gemma. `__call__(xs, positions, mask, adarms_cond, kv_cache) -> (outs, (k, v))`.

    xs: per-expert token streams (B, T_e, D_e) or None. positions: (B, T) for the concatenated present streams.
    mask: (B, T, S) bool, S = cached prefix length + T. Returned k, v: (L, B, S, K, H), cache included.
    """

    configs: Sequence[GemmaConfig]
    vocab_size: int
    embed_dtype: jnp.dtype = jnp.bfloat16

    def setup(self):
        self.embedder = Embedder(self.vocab_size, self.configs[0].width, name="embedder")
        self.layers = nn.scan(
            Block, variable_axes={"params": 0}, split_rngs={"params": True},
            in_axes=(0, nn.broadcast, nn.broadcast, nn.broadcast), length=self.configs[0].depth,
        )(configs=tuple(self.configs), name="layers")
        self.final_norms = [RMSNorm(name=_name("final_norm", i)) for i in range(len(self.configs))]

    def embed(self, tokens: jax.Array) -> jax.Array:
        return self.embedder(tokens).astype(self.embed_dtype)

    def __call__(self, xs, positions, mask, adarms_cond=None, kv_cache=None):
        xs = [x.astype(self.embed_dtype) if x is not None else None for x in xs]
        if adarms_cond is None:
            adarms_cond = [None] * len(self.configs)
        xs, kv = self.layers(xs, kv_cache, positions, mask, adarms_cond)
        outs = [f(x, c)[0] if x is not None else None for f, x, c in zip(self.final_norms, xs, adarms_cond)]
        return outs, kv


class Embedder(nn.Module):
    vocab_size: int
    width: int

    @nn.compact
    def __call__(self, tokens):
        table = self.param("input_embedding", nn.initializers.normal(), (self.vocab_size, self.width))
        x = table[tokens]
        # The sqrt(width) scale is cast to the table dtype first: bf16(45.2548) = 45.25, as in openpi.
        return x * jnp.sqrt(self.width).astype(x.dtype)
