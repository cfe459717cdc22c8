"""Fused attention: `jax.nn.dot_product_attention` as cuDNN's flash kernel on a GPU, and its XLA form elsewhere.

The same function either way (softmax statistics in f32 inside the kernel), so CPU tests run the fused path's code
(lengths, masks, GQA) exactly as a GPU does, only not as one kernel. Masking is by lengths: keys [0, kv_len) of each
element are attended, and an optional boolean mask (B, 1, T, S) removes more.
"""

from __future__ import annotations

import jax


def implementation() -> str:
    """"cudnn" on a GPU, else "xla" (cuDNN has no other backend)."""
    return "cudnn" if jax.default_backend() == "gpu" else "xla"


def fused(q, k, v, *, scale: float | None = None, kv_len=None, mask=None):
    """q (B, T, N, H); k, v (B, S, K, H) with N a multiple of K (grouped queries); kv_len (B,) int32 or None;
    mask (B, 1, T, S) bool or None; scale None: 1/sqrt(H). Returns (B, T, N, H) in q's dtype."""
    return jax.nn.dot_product_attention(q, k, v, mask=mask, scale=scale, key_value_seq_lengths=kv_len,
                                        implementation=implementation())
