"""What the Pallas kernels of `pi0_jax.ops` share: Triton's smallest dot, block sizes that divide a dimension, an
f32-accumulating dot, and the call itself (Triton with its launch parameters on a GPU, interpret mode on a CPU)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as plgpu

ALIGN = 16  # Triton's smallest dot dimension


def fit(block: int, n: int) -> int:
    """The largest power of two <= block that divides n."""
    while n % block:
        block //= 2
    return block


def dot(a, b, trans_b: bool = False):
    """a @ b (or a @ b.T) with an f32 accumulator; f32 operands multiply in full f32 (Triton's IEEE mode)."""
    dims = (((1,), (1 if trans_b else 0,)), ((), ()))
    return jax.lax.dot_general(a, b, dims, preferred_element_type=jnp.float32)


def call(kernel, *, grid, out_shape, name: str, num_warps: int, num_stages: int):
    """`pl.pallas_call` on the default backend: Triton on a GPU, interpreted on a CPU."""
    on_cpu = jax.default_backend() == "cpu"
    params = None if on_cpu else plgpu.CompilerParams(num_warps=num_warps, num_stages=num_stages)
    return pl.pallas_call(kernel, grid=grid, out_shape=out_shape, interpret=on_cpu, compiler_params=params,
                          name=name)
