"""What the Pallas kernels of `pi0_jax.ops` share: Triton's smallest dot, block sizes that divide a dimension, an
f32-accumulating dot, the call itself (Triton with its launch parameters on a GPU, interpret mode on a CPU), and the
shardings of a kernel partitioned by rows (`row_shardings`).

JAX 0.11 deprecated Pallas's Triton backend ("will be removed in a future JAX version") and warns at every lowering
of a Triton kernel. `TRITON` says whether this jax still has it: where it does not, the "auto" choices
(`engine.programs`) run every stage on XLA's and cuDNN's kernels, and a kernel asked for by name on a GPU raises
before it is lowered. The warning is filtered once a kernel runs on a GPU (only that message, only as a
DeprecationWarning): it is raised while the jit around the kernel lowers, after `call` has returned, so a filter
around the call would not see it.
"""

from __future__ import annotations

import functools
import warnings

import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P

try:
    from jax.experimental.pallas import triton as plgpu
except ImportError:   # a jax without Pallas's Triton backend
    plgpu = None

TRITON = plgpu is not None
TRITON_DEPRECATION = r"The Pallas Triton backend is deprecated"
ALIGN = 16  # Triton's smallest dot dimension


def row_shardings(mesh, sharding) -> tuple:
    """A kernel partitioned by rows under a sharded jit (`custom_partitioning`): (its row operands' and outputs'
    sharding: rows split as `sharding`'s first axis, columns whole; its other operands': replicated)."""
    axes = sharding.spec[0] if len(sharding.spec) else None
    return NamedSharding(mesh, P(axes, None)), NamedSharding(mesh, P())


def fit(block: int, n: int) -> int:
    """The largest power of two <= block that divides n."""
    while n % block:
        block //= 2
    return block


def dot(a, b, trans_b: bool = False):
    """a @ b (or a @ b.T) with an f32 accumulator. f32 operands multiply at the default precision, which Pallas's
    Triton lowering makes TF32, as XLA's f32 GEMMs on a GPU are by default (full f32 in interpret mode)."""
    dims = (((1,), (1 if trans_b else 0,)), ((), ()))
    return jax.lax.dot_general(a, b, dims, preferred_element_type=jnp.float32)


@functools.cache
def _quiet_deprecation() -> None:
    warnings.filterwarnings("ignore", message=TRITON_DEPRECATION, category=DeprecationWarning)


def call(kernel, *, grid, out_shape, name: str, num_warps: int, num_stages: int):
    """`pl.pallas_call` on the default backend: Triton on a GPU, interpreted on a CPU."""
    on_cpu = jax.default_backend() == "cpu"
    if not on_cpu and not TRITON:
        raise RuntimeError(f"the Pallas kernel {name!r} runs on Pallas's Triton backend, which jax {jax.__version__} "
                           "does not have: choose kernels='xla' and attention='auto' (or cudnn / xla per stage)")
    if not on_cpu:
        _quiet_deprecation()
    params = None if on_cpu else plgpu.CompilerParams(num_warps=num_warps, num_stages=num_stages)
    return pl.pallas_call(kernel, grid=grid, out_shape=out_shape, interpret=on_cpu, compiler_params=params,
                          name=name)
