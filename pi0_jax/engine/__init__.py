"""Compiled static-shape inference: vision encoder, prefix KV-cache fill, fixed-step denoise (a call runs the first as
one program and the other two as a second), and the three fused as one program."""

from pi0_jax.engine.runtime import Engine, enable_compilation_cache, engine_weights, prompt_bucket

__all__ = ["Engine", "enable_compilation_cache", "engine_weights", "prompt_bucket"]
