"""The kernel layout of `pi0_jax.ops.expert_kernels`: weights, KV cache and per-step tables, padded once.

Widths are padded to multiples of 16 (Triton's smallest dot), suffix rows to a power of two Sp >= 16, prefix keys to
a multiple of KEY_PAD, and each head dim H to [x1 | 0 | x2 | 0] with both RoPE halves padded to hp. At π0 / π0.5
full size (D 1024, H 256, F 4096) the weights need no padding: these are reshapes, free in XLA.

One layout is the engine's everywhere, not only here: the fused gate/up weight's columns alternate gate and up in
blocks of GATE_UP_BLOCK units (`gate_up_block`, `split_gate_up`), which the Mosaic GPU GeGLU kernel takes one block
pair a CTA.

Axis legend: L layers, B batch, S suffix tokens, P prefix keys, D width, N query heads, K kv heads, F MLP hidden.
"""

from __future__ import annotations

import einops
import jax.numpy as jnp

from pi0_jax.config import GemmaConfig
from pi0_jax.ops.pallas_base import ALIGN

KEY_PAD = 64  # prefix keys are padded to a multiple of this (the attention kernel's largest key block)
GATE_UP_BLOCK = 32  # hidden units per block of the fused gate/up weight (`gate_up_block`)


def _round_up(n: int, m: int) -> int:
    return -(-n // m) * m


def _pad(x, axis: int, size: int):
    """Zero-pad `axis` of x to `size` (nothing when it is already that size)."""
    axis = axis % x.ndim
    if x.shape[axis] == size:
        return x
    widths = [(0, 0)] * x.ndim
    widths[axis] = (0, size - x.shape[axis])
    return jnp.pad(x, widths)


def gate_up_block(hidden: int) -> int:
    """Units per block of a fused gate/up weight (D, 2F) with F = hidden: its columns are [gate of units 0..u-1 |
    up of the same | gate of units u..2u-1 | ...]. GATE_UP_BLOCK where it divides F (every real size), else F: one
    block, [gate | up]. Block pairs let the Mosaic GPU GeGLU kernel take one pair a CTA into one accumulator
    (`ops.mosaic_gemm`); XLA reads the halves through a reshape (`split_gate_up`)."""
    return GATE_UP_BLOCK if hidden % GATE_UP_BLOCK == 0 else hidden


def split_gate_up(y):
    """x @ gate_up (..., 2F), blocks as `gate_up_block(F)` -> (gate, up), each (..., F)."""
    f = y.shape[-1] // 2
    y = y.reshape(*y.shape[:-1], -1, 2, gate_up_block(f))
    return (y[..., 0, :].reshape(*y.shape[:-3], f), y[..., 1, :].reshape(*y.shape[:-3], f))


def suffix_rows(s: int) -> int:
    """Sp: suffix tokens padded to a power of two >= 16 (the suffix block of the attention kernel is one tile)."""
    return max(ALIGN, 1 << (s - 1).bit_length())


def half_dim(head_dim: int) -> int:
    """hp: one RoPE half of a head, padded."""
    return _round_up(head_dim // 2, ALIGN)


def heads(x, axis: int, head_dim: int):
    """Split `axis` = (heads H) into (heads 2 hp) with each half zero-padded, and merge it back."""
    axis = axis % x.ndim
    shape = x.shape
    x = x.reshape(*shape[:axis], -1, 2, head_dim // 2, *shape[axis + 1:])
    x = _pad(x, axis + 2, half_dim(head_dim))
    return x.reshape(*shape[:axis], -1, *shape[axis + 1:])


def expert_weights(w: dict, cfg: GemmaConfig) -> dict:
    """One expert layer's engine weights (`engine.weights.prepare`) -> kernel layout:
    qkv (D, (N + 2K) 2hp), attn_out (N 2hp, D), gate_up (D, 2F) in `gate_up_block(F)` pairs, down (F, D), and π0's
    norm scales pre_attn / pre_ffw as (1, D)."""
    d, f = _round_up(cfg.width, ALIGN), _round_up(cfg.mlp_dim, ALIGN)
    gate_up = w["gate_up"]
    if f != cfg.mlp_dim:   # padded hidden units: their gate and up columns zero, in f's block pairs
        gate_up = _pad(jnp.stack(split_gate_up(gate_up), axis=1), 2, f)   # (D, two, f)
        gate_up = einops.rearrange(gate_up, "D two (Fb u) -> D (Fb two u)", u=gate_up_block(f))
    out = {
        "qkv": _pad(heads(w["qkv"], -1, cfg.head_dim), 0, d),
        "attn_out": _pad(heads(w["attn_out"], 0, cfg.head_dim), 1, d),
        "gate_up": _pad(gate_up, 0, d),
        "down": _pad(_pad(w["down"], 0, f), 1, d),
    }
    for name in ("pre_attn", "pre_ffw"):
        if name in w:
            out[name] = _pad(w[name][None], 1, d)
    return out


def cache_len(p: int) -> int:
    """Pp: a prefix of p keys padded."""
    return _round_up(p, KEY_PAD)


def unheads(x, head_dim: int):
    """The inverse of `heads` on the last axis: (..., heads 2hp) -> (..., heads H)."""
    hp = half_dim(head_dim)
    x = x.reshape(*x.shape[:-1], -1, 2, hp)[..., : head_dim // 2]
    return x.reshape(*x.shape[:-3], -1)


def cache_kv(x, head_dim: int):
    """A prefix cache's k or v (B, P or Pp, K, H) -> (B, Pp, K, 2hp), or stacked layers (L, B, ...) alike; padded
    keys are masked by `cache_mask`."""
    return _pad(heads(x, -1, head_dim), -3, cache_len(x.shape[-3]))


def cache_mask(mask):
    """(B, P) bool -> (B, Pp), padded keys False."""
    return _pad(mask, 1, cache_len(mask.shape[1]))


def rows(x, sp: int):
    """(B, S, D) activations -> (B Sp, Dpad) kernel rows, zero-padded."""
    x = _pad(_pad(x, 1, sp), 2, _round_up(x.shape[2], ALIGN))
    return x.reshape(-1, x.shape[2])


def mods(m, width: int):
    """A step's π0.5 adaRMS outputs (L, 3D) = [scale | shift | gate] per layer -> (3L, Dpad); layer i's rows are
    3i, 3i + 1, 3i + 2."""
    m = einops.rearrange(m, "L (three D) -> (L three) D", three=3)
    return _pad(m, 1, _round_up(width, ALIGN))


def rope_tables(positions, head_dim: int, max_wavelength: float = 10_000):
    """positions (B, Sp) -> cos, sin (B Sp, hp) f32: the angles of `pi0_jax.gemma.apply_rope` for each row."""
    half = head_dim // 2
    timescale = max_wavelength ** ((2.0 / head_dim) * jnp.arange(half, dtype=jnp.float32))
    radians = positions.reshape(-1)[:, None].astype(jnp.float32) / timescale
    return _pad(jnp.cos(radians), 1, half_dim(head_dim)), _pad(jnp.sin(radians), 1, half_dim(head_dim))
