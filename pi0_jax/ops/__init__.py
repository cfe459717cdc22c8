"""Low-level ops the model and engine modules build on: fused Pallas kernels with their layouts."""

from pi0_jax.ops.expert_kernels import Blocks

__all__ = ["Blocks"]
