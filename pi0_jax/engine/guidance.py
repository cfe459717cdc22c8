"""Real-time chunking's program: the denoise loop guided towards committed actions through the vector-Jacobian product
of the action expert's velocity (`pi0_jax.sim.realtime`'s "rtc" execution)."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from pi0_jax.config import Pi0Config
from pi0_jax.engine import programs
from pi0_jax.engine.paths import Attention
from pi0_jax.engine.programs import PrefixCache


def guided_denoise(config: Pi0Config, weights: dict, sched: dict, cache: PrefixCache, state, noise, target,
                   weight, *, num_steps: int, beta: float = 5.0, unroll: bool,
                   attention: Attention = Attention()) -> jax.Array:
    """Real-time chunking (Black, Galliker, Levine 2025, arXiv 2506.07339): `programs.denoise` with ΠGDM-style
    inpainting guidance towards `target` (B, H, action_dim), weighted per action and dim by `weight` (B, H,
    action_dim) in [0, 1] (1: frozen, 0: free), in normalised model space.

    Time runs as openpi's (t = 1 noise, t = 0 data), so the denoised estimate is x̂ = x_t - t v(x_t) and the paper's
    update A += (1/n)(v_π + w g), with v_π = -v in its τ = 1 - t, becomes x += dt (v - w g), where
    g = [(target - x̂) * weight]ᵀ ∂x̂/∂x_t (one vector-Jacobian product through the velocity) and
    w = min(beta, (t² + (1 - t)²) / (t (1 - t))), = beta at t = 1. weight = 0 everywhere gives `denoise` exactly
    up to the VJP's extra arithmetic (g = 0)."""
    attention = attention.at_batch(noise.shape[0], suffix_mask=not config.pi05, differentiable=True)
    if attention.denoise == "pallas" or (attention.denoise == "cudnn" and jax.default_backend() == "gpu"):
        raise ValueError(f"real-time chunking differentiates the velocity: its denoise attention must be 'xla', not "
                         f"{attention.denoise!r} (the Pallas kernel has no VJP; cuDNN's flash attention refuses a "
                         "backward pass at the suffix's sequence lengths); fill its cache with attention.at_batch(..., "
                         "differentiable=True)")
    dt = -1.0 / num_steps
    if not isinstance(num_steps, int):
        dt = jnp.asarray(dt, jnp.float32)
    target, weight = target.astype(jnp.float32), weight.astype(jnp.float32)
    # what every step reads alike, made once before the loop, as `programs.denoise` does
    fixed, cache, kv = programs.step_inputs(config, weights, cache, state, noise.shape[0], "xla", attention,
                                            unroll=unroll)

    def step(i, x_t):
        t = 1.0 + i.astype(jnp.float32) * dt    # f32 as the schedule's step_times, to rounding

        def denoised(x):   # v(x_t, t_step) over the cache, on XLA's expert: differentiated by the VJP below
            v = programs.step_velocity(config, weights, sched, i, cache, fixed, x, kv, unroll=unroll,
                                       attention=attention, kernels="xla", frozen=None)[0]
            v = v.astype(jnp.float32)
            return x - t * v, v

        x_hat, vjp, v = jax.vjp(denoised, x_t, has_aux=True)
        (g,) = vjp((target - x_hat) * weight)
        w = jnp.minimum(beta, (t * t + (1.0 - t) ** 2) / jnp.maximum(t * (1.0 - t), 1e-12))
        return x_t + dt * (v - w * g)

    return jax.lax.fori_loop(0, num_steps, step, noise.astype(jnp.float32))
