"""π0 / π0.5: prefix (images + prompt) through the VLM, suffix (state + noisy actions) through the action expert.

Time convention (as openpi, the reverse of the paper): t = 1 is pure noise, t = 0 is data. The sampler integrates
dx/dt = v(x_t, t) with Euler steps of dt = -1/num_steps from t = 1 down to t = 0.

All public functions are pure: `config` (a frozen, hashable dataclass) and `num_steps` are static under jit;
params are the openpi param tree (a plain nested dict); noise is always passed in.
"""

from __future__ import annotations

import functools

import einops
import flax.linen as nn
import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from pi0_jax import gemma, siglip
from pi0_jax.config import IMAGE_KEYS, Pi0Config
from pi0_jax.gemma import KVCache


@flax.struct.dataclass
class Observation:
    """Model-ready inputs (after the policy's transforms).

    images: {key: (B, H, W, 3) f32 in [-1, 1]} for key in IMAGE_KEYS; image_masks: {key: (B,) bool};
    state: (B, action_dim) f32, normalised and zero-padded; tokenized_prompt: (B, L) int32;
    tokenized_prompt_mask: (B, L) bool.
    """

    images: dict[str, jax.Array]
    image_masks: dict[str, jax.Array]
    state: jax.Array
    tokenized_prompt: jax.Array
    tokenized_prompt_mask: jax.Array


def make_attn_mask(input_mask: jax.Array, ar_mask: jax.Array) -> jax.Array:
    """big_vision mask semantics. input_mask: (B, N) bool valid tokens; ar_mask: (N,) or (B, N) bool.

    Token i may attend token j iff cumsum(ar)[j] <= cumsum(ar)[i] and both are valid. An ar flag of True starts a
    new block that earlier tokens cannot see. Examples:
      ar = [0 0 0 1 1 1]: a bidirectional prefix of 3 followed by 3 causal tokens;
      ar = [0 0 0 1 0 0]: a prefix of 3, then a block of 3 that is bidirectional within itself and sees the prefix.
    Returns (B, N, N) bool.
    """
    ar_mask = jnp.broadcast_to(ar_mask, input_mask.shape)
    cum = jnp.cumsum(ar_mask, axis=1)
    causal = cum[:, None, :] <= cum[:, :, None]
    valid = input_mask[:, None, :] & input_mask[:, :, None]
    return causal & valid


def posemb_sincos(t: jax.Array, dim: int, min_period: float = 4e-3, max_period: float = 4.0) -> jax.Array:
    """Sinusoidal embedding of times t (B,) or (B, H) -> (..., dim), [sin | cos]. fp32 island, HIGHEST precision."""
    fraction = jnp.linspace(0.0, 1.0, dim // 2)
    period = min_period * (max_period / min_period) ** fraction
    arg = jnp.einsum("...,j->...j", t, 1.0 / period * 2 * jnp.pi, precision=jax.lax.Precision.HIGHEST)
    return jnp.concatenate([jnp.sin(arg), jnp.cos(arg)], axis=-1)


class PaliGemma(nn.Module):
    """Container so the tree reads PaliGemma/{llm,img}/... exactly as openpi's."""

    config: Pi0Config

    def setup(self):
        cfg = self.config
        dtype = jnp.dtype(cfg.dtype)
        self.llm = gemma.Gemma(configs=(cfg.paligemma, cfg.action_expert), vocab_size=cfg.vocab_size, embed_dtype=dtype)
        self.img = siglip.Siglip(cfg.siglip, out_dim=cfg.paligemma.width, dtype_mm=dtype)


class Pi0(nn.Module):
    """The whole network; methods are the pieces the pure functions below compose."""

    config: Pi0Config

    def setup(self):
        cfg = self.config
        expert = cfg.action_expert
        self.PaliGemma = PaliGemma(cfg)
        # Projections compute in the promoted dtype (openpi's nnx.Linear with dtype=None): f32 for f32 inputs.
        self.action_in_proj = nn.Dense(expert.width, name="action_in_proj")
        if cfg.pi05:
            self.time_mlp_in = nn.Dense(expert.width, name="time_mlp_in")
            self.time_mlp_out = nn.Dense(expert.width, name="time_mlp_out")
        else:
            self.state_proj = nn.Dense(expert.width, name="state_proj")
            self.action_time_mlp_in = nn.Dense(expert.width, name="action_time_mlp_in")
            self.action_time_mlp_out = nn.Dense(expert.width, name="action_time_mlp_out")
        self.action_out_proj = nn.Dense(cfg.action_dim, name="action_out_proj")

    def embed_images(self, images: jax.Array) -> jax.Array:
        return self.PaliGemma.img(images)[0]

    def embed_prefix(self, obs: Observation):
        tokens, input_mask, ar = [], [], []
        for key in IMAGE_KEYS[: self.config.num_cameras]:
            t = self.embed_images(obs.images[key])
            tokens.append(t)
            input_mask.append(einops.repeat(obs.image_masks[key], "b -> b s", s=t.shape[1]))
            ar += [False] * t.shape[1]
        tokens.append(self.PaliGemma.llm.embed(obs.tokenized_prompt))
        input_mask.append(obs.tokenized_prompt_mask)
        ar += [False] * obs.tokenized_prompt.shape[1]
        return jnp.concatenate(tokens, axis=1), jnp.concatenate(input_mask, axis=1), jnp.asarray(ar)

    def embed_suffix(self, state: jax.Array | None, x_t: jax.Array, t: jax.Array):
        cfg = self.config
        tokens, ar = [], []
        if not cfg.pi05:
            tokens.append(self.state_proj(state)[:, None, :])
            ar += [True]
        action_tokens = self.action_in_proj(x_t)
        time_emb = posemb_sincos(t, cfg.action_expert.width)
        if cfg.pi05:
            cond = nn.swish(self.time_mlp_out(nn.swish(self.time_mlp_in(time_emb))))   # (B, D) or per token
            tokens.append(action_tokens)
        else:
            time_tokens = time_emb if t.ndim == 2 else einops.repeat(time_emb, "b d -> b s d", s=cfg.action_horizon)
            h = jnp.concatenate([action_tokens, time_tokens], axis=-1)  # action first, then time
            tokens.append(self.action_time_mlp_out(nn.swish(self.action_time_mlp_in(h))))
            cond = None
        ar += [True] + [False] * (cfg.action_horizon - 1)
        tokens = jnp.concatenate(tokens, axis=1)
        return tokens, jnp.ones(tokens.shape[:2], bool), jnp.asarray(ar), cond

    def prefix_pass(self, obs: Observation):
        tokens, input_mask, ar = self.embed_prefix(obs)
        positions = jnp.cumsum(input_mask, axis=1) - 1
        _, (k, v) = self.PaliGemma.llm([tokens, None], positions, make_attn_mask(input_mask, ar))
        return KVCache(k=k, v=v, mask=input_mask, state=obs.state)

    def velocity(self, cache: KVCache, x_t: jax.Array, t: jax.Array) -> jax.Array:
        """v(x_t, t) over a filled prefix cache. x_t: (B, H, action_dim) f32; t: (B,), or (B, H) a time per action
        (training-time action conditioning: committed actions ride at t = 0)."""
        tokens, suffix_mask, ar, cond = self.embed_suffix(cache.state, x_t, t)
        s = tokens.shape[1]
        mask = jnp.concatenate(
            [einops.repeat(cache.mask, "b p -> b s p", s=s), make_attn_mask(suffix_mask, ar)], axis=-1
        )
        # The suffix continues right after the number of *valid* prefix tokens.
        positions = jnp.sum(cache.mask, axis=-1, keepdims=True) + jnp.cumsum(suffix_mask, axis=1) - 1
        (_, out), _ = self.PaliGemma.llm([None, tokens], positions, mask, adarms_cond=[None, cond], kv_cache=(cache.k, cache.v))
        return self.action_out_proj(out[:, -self.config.action_horizon :])

    def joint_velocity(self, obs: Observation, x_t: jax.Array, t: jax.Array) -> jax.Array:
        """One pass over prefix + suffix together (the training path)."""
        prefix, prefix_mask, prefix_ar = self.embed_prefix(obs)
        suffix, suffix_mask, suffix_ar, cond = self.embed_suffix(obs.state, x_t, t)
        input_mask = jnp.concatenate([prefix_mask, suffix_mask], axis=1)
        ar = jnp.concatenate([prefix_ar, suffix_ar])
        positions = jnp.cumsum(input_mask, axis=1) - 1
        (_, out), _ = self.PaliGemma.llm([prefix, suffix], positions, make_attn_mask(input_mask, ar), adarms_cond=[None, cond])
        return self.action_out_proj(out[:, -self.config.action_horizon :])

    def __call__(self, obs: Observation, x_t: jax.Array, t: jax.Array) -> jax.Array:
        return self.joint_velocity(obs, x_t, t)


def fake_observation(config: Pi0Config, batch_size: int = 1) -> Observation:
    s = config.image_size
    return Observation(
        images={k: jnp.zeros((batch_size, s, s, 3), jnp.float32) for k in IMAGE_KEYS[: config.num_cameras]},
        image_masks={k: jnp.ones((batch_size,), bool) for k in IMAGE_KEYS[: config.num_cameras]},
        state=jnp.zeros((batch_size, config.action_dim), jnp.float32),
        tokenized_prompt=jnp.zeros((batch_size, config.max_token_len), jnp.int32),
        tokenized_prompt_mask=jnp.ones((batch_size, config.max_token_len), bool),
    )


@functools.partial(jax.jit, static_argnums=0)
def init_params(config: Pi0Config, rng: jax.Array) -> dict:
    """Random params in openpi's tree layout (f32). Note: like openpi, norms and adaRMS Dense start at zero."""
    obs = fake_observation(config)
    x = jnp.zeros((1, config.action_horizon, config.action_dim), jnp.float32)
    variables = Pi0(config).init(rng, obs, x, jnp.ones((1,), jnp.float32))
    return variables["params"]


def random_params(config: Pi0Config, seed: int) -> dict:
    """Random weights in the config's dtype, drawn on the device leaf by leaf (no f32 copy of the whole tree), with
    norms and adaRMS made non-zero too: for timing full-size models and for throughput runs without a checkpoint."""
    leaves, treedef = jax.tree.flatten(param_shapes(config))
    keys = jax.random.split(jax.random.key(seed), len(leaves))
    dtype = jnp.dtype(config.dtype)
    return jax.tree.unflatten(treedef, [_draw_normal(k, tuple(x.shape), dtype) for k, x in zip(keys, leaves)])


@functools.partial(jax.jit, static_argnums=(1, 2))
def _draw_normal(key, shape, dtype):
    """random_params' leaf: N(0, 1/fan_in) (0.1 for vectors), drawn flat and reshaped. The same bits as drawing at
    `shape` (threefry numbers the elements in row-major order either way), but XLA:CPU compiles the rank-1 draw in
    ~0.2 s against 1-3 s for a rank-4/5 one (random_params of a dummy preset: ~6 s instead of ~26 s on 2 cores)."""
    std = 1.0 / np.sqrt(shape[-2]) if len(shape) >= 2 else 0.1
    return (jax.random.normal(key, (int(np.prod(shape)),), jnp.float32) * std).astype(dtype).reshape(shape)


@functools.lru_cache(maxsize=32)
def param_shapes(config: Pi0Config) -> dict:
    """The param tree as jax.ShapeDtypeStruct leaves, computed without allocating (works for full-size presets).

    Cached per config (tracing the full model takes ~1 s); treat the result as read-only."""
    return jax.eval_shape(functools.partial(init_params, config), jax.random.key(0))


def _apply(config: Pi0Config, params: dict, *args, method):
    return Pi0(config).apply({"params": params}, *args, method=method)


def embed_images(config: Pi0Config, params: dict, images: jax.Array) -> jax.Array:
    """SigLIP + projector: (B, H, W, 3) in [-1, 1] -> (B, 256, VLM width)."""
    return _apply(config, params, images, method=Pi0.embed_images)


def embed_prefix(config: Pi0Config, params: dict, obs: Observation):
    """-> (tokens (B, P, D), input_mask (B, P) bool, ar_mask (P,) bool)."""
    return _apply(config, params, obs, method=Pi0.embed_prefix)


def fill_prefix_cache(config: Pi0Config, params: dict, obs: Observation) -> KVCache:
    """The prefix pass through the VLM expert alone; returns the KV-cache pytree the denoiser reads."""
    return _apply(config, params, obs, method=Pi0.prefix_pass)


def denoise_step(config: Pi0Config, params: dict, cache: KVCache, x_t: jax.Array, t: jax.Array) -> jax.Array:
    """The velocity v(x_t, t): (B, H, action_dim) f32. t: scalar, (B,) or (B, H) (one time per action)."""
    t = jnp.asarray(t, jnp.float32)
    t = t if t.ndim == 2 else jnp.broadcast_to(t, x_t.shape[:1])
    return _apply(config, params, cache, x_t, t, method=Pi0.velocity)


def sample_actions(config: Pi0Config, params: dict, obs: Observation, noise: jax.Array, num_steps: int = 10,
                   committed: jax.Array | None = None, num_committed: jax.Array | None = None):
    """Euler flow-matching sampler: noise (B, H, action_dim) at t = 1 -> actions at t = 0.

    Runs exactly num_steps steps at t = 1, 1 - 1/n, ..., 1/n: a fixed trip count for a Python int, a while loop
    for a traced int32 (same arithmetic: dt = -1/n rounded to f32 once).

    Training-time action conditioning (Black, Ren, Equi, Levine 2025, arXiv 2512.05964): with `committed`
    (B, H, action_dim) and `num_committed` d (B,) int, actions i < d are the committed ones, clean (time 0) at every
    step, and returned as given; the model must have been trained that way (`TrainConfig.max_delay`).
    """
    cache = fill_prefix_cache(config, params, obs)
    dt = -1.0 / num_steps
    x = noise.astype(jnp.float32)
    frozen = None
    if num_committed is not None:
        frozen = committed_mask(config.action_horizon, num_committed)
        x = jnp.where(frozen[..., None], committed.astype(jnp.float32), x)

    def step(_, carry):
        x_t, t = carry  # t accumulates in f32 exactly as openpi's while_loop does
        if frozen is None:
            return x_t + dt * denoise_step(config, params, cache, x_t, t), t + dt
        v = denoise_step(config, params, cache, x_t, jnp.where(frozen, 0.0, t))
        return jnp.where(frozen[..., None], x_t, x_t + dt * v), t + dt

    x_0, _ = jax.lax.fori_loop(0, num_steps, step, (x, jnp.float32(1.0)))
    return x_0


def committed_mask(horizon: int, num_committed) -> jax.Array:
    """(B, H) bool: action i of element b is committed (given clean, at t = 0) when i < num_committed[b]."""
    return jnp.arange(horizon)[None, :] < jnp.asarray(num_committed)[:, None]


def compute_loss(config: Pi0Config, params: dict, obs: Observation, actions: jax.Array, noise: jax.Array,
                 t: jax.Array) -> jax.Array:
    """Flow-matching loss per (B, H): mean over action dims of (v - (noise - actions))^2.

    x_t = t * noise + (1 - t) * actions; t: (B,), sampled by the caller (openpi: Beta(1.5, 1) * 0.999 + 0.001,
    see `sample_time`), or (B, H) one time per action (committed actions at t = 0: see `sample_actions`).
    """
    t_ = t[..., None] if t.ndim == 2 else t[:, None, None]
    x_t = t_ * noise + (1 - t_) * actions
    v_t = _apply(config, params, obs, x_t, t, method=Pi0.joint_velocity)
    return jnp.mean(jnp.square(v_t - (noise - actions)), axis=-1)


def sample_time(rng: jax.Array, batch_size: int) -> jax.Array:
    return jax.random.beta(rng, 1.5, 1.0, (batch_size,)) * 0.999 + 0.001
