"""Policies for the batched rollout, behind one interface: the scripted expert, a random policy, pi0-jax checkpoints.

A policy is driven by the rollout (evaluate.py) in two calls, both batched over environments and traced into the
same jitted program as the physics:

  pstate = plan(params, pstate, obs, env_state, rng)   every `replan_steps` steps: e.g. sample an action chunk
  action, pstate = act(pstate, env_state, k)            every step k = 0 .. replan_steps - 1 of the chunk

`params` is a jit argument (a full-size model's weights must not become compile-time constants); obs is the env's
batched observation ({"agentview", "wrist": (B, H, W, 3) uint8, "state": (B, 8)}) or None when the policy does not
look at images (`needs_images` False: the rollout then skips rendering). The expert acts from privileged state
every step, so it ignores replanning; chunked policies return chunk[:, k].

The pi0-jax policy reproduces `pi0_jax.policy.Policy`'s LIBERO transforms inside jit: agent view -> `base_0_rgb`,
wrist -> `left_wrist_0_rgb`, `right_wrist_0_rgb` black and masked (as openpi's LIBERO example); uint8 -> [-1, 1],
resize-with-pad to the model's 224 when the env renders at another size; state normalised and zero-padded; the
task's prompt tokenised once on the host (or, for π0.5 with the state in the prompt, by a host callback per plan);
actions sliced to the dataset's dims and un-normalised. Every normalisation mode of `pi0_jax.normalize` is affine
per dimension, so its exact numpy formulas are evaluated once at x = 0 and x = 1 and applied as x * scale + offset.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from pi0_jax.sim import expert as _expert


@dataclasses.dataclass(frozen=True, eq=False)
class SimPolicy:
    name: str
    init: Callable[[int], Any]                      # batch size -> pstate
    plan: Callable[..., Any]                        # (params, pstate, obs, env_state, rng) -> pstate
    act: Callable[..., tuple[jax.Array, Any]]       # (pstate, env_state, k) -> ((B, 7) action, pstate)
    params: Any = None
    needs_images: bool = False
    horizon: int | None = None                      # longest usable chunk; None: any replan_steps
    observation: Callable | None = None             # model policies: (obs, env_state) -> pi0.Observation
    info: dict = dataclasses.field(default_factory=dict)


def expert_policy(env) -> SimPolicy:
    """The scripted expert (privileged state, closed loop every step)."""
    return SimPolicy(
        name="expert",
        init=lambda b: jax.tree.map(lambda x: jnp.broadcast_to(x, (b,) + x.shape), _expert.init()),
        plan=lambda params, ps, obs, es, rng: ps,
        act=lambda ps, es, k: jax.vmap(lambda s, e: _expert.act(env, s, e))(es, ps))


def random_policy(replan_steps: int) -> SimPolicy:
    """Uniform actions in [-1, 1]^7 (gripper included), a fresh chunk every plan."""
    def plan(params, ps, obs, es, rng):
        return jax.vmap(lambda k: jax.random.uniform(k, (replan_steps, 7), minval=-1.0, maxval=1.0))(rng)

    return SimPolicy(name="random", init=lambda b: jnp.zeros((b, replan_steps, 7)), plan=plan,
                     act=lambda ps, es, k: (ps[:, k], ps), horizon=replan_steps)


def _affine(fn: Callable[[np.ndarray], np.ndarray], dim: int) -> tuple[np.ndarray, np.ndarray]:
    """An affine per-dim map (every pi0_jax.normalize mode is one) as (scale, offset), from its value at 0 and 1."""
    zero, one = np.asarray(fn(np.zeros(dim)), np.float64), np.asarray(fn(np.ones(dim)), np.float64)
    return (one - zero).astype(np.float32), zero.astype(np.float32)


def _find_tokenizer(ckpt: Path, explicit) -> Path:
    from pi0_jax.policy import TOKENIZER_FILE

    candidates = [Path(explicit)] if explicit else [ckpt / TOKENIZER_FILE, ckpt / "assets" / TOKENIZER_FILE]
    for c in candidates:
        if c.is_file():
            return c
    raise FileNotFoundError(f"tokenizer model not found (tried {[str(c) for c in candidates]}); pass --tokenizer")


def checkpoint_policy(path: str | os.PathLike, env, *, tokenizer_path=None, num_steps: int = 10,
                      norm_stats: str | os.PathLike | None = None, dtype: str | None = None) -> SimPolicy:
    """A pi0-jax checkpoint directory (`pi0-jax convert` output) as a batched in-jit policy for `env`'s tasks."""
    from pi0_jax import checkpoint
    from pi0_jax import normalize as nz
    from pi0_jax.tokenizer import PaligemmaTokenizer

    path = Path(path)
    config, params = checkpoint.load_checkpoint(path, dtype=dtype)
    if dtype is not None:   # params and compute: bf16 on CPU is emulated and slower than f32
        config = config.replace(dtype=dtype)
    tok = PaligemmaTokenizer(_find_tokenizer(path, tokenizer_path), config.max_token_len)
    if norm_stats == "identity":
        normalizer = nz.Normalizer.identity()
    else:
        normalizer = nz.load_normalizer(path if norm_stats is None else norm_stats, use_quantiles=config.pi05)
    return model_policy(config, params, tok, normalizer, env, num_steps=num_steps, name=str(path))


def model_policy(config, params, tok, normalizer, env, *, num_steps: int = 10, dynamic_steps: bool = False,
                 name: str = "model") -> SimPolicy:
    """A π0 / π0.5 (pi0_jax.pi0) with its tokenizer and normaliser as a batched in-jit policy for `env`'s tasks.

    dynamic_steps: the flow-step count travels in the policy's params ({"model": params, "num_steps": int32}) instead
    of the program, so one compiled rollout serves every step count (same numerics: dt = -1/n in f32 either way)."""
    from pi0_jax import normalize as nz
    from pi0_jax import pi0
    from pi0_jax.config import IMAGE_KEYS
    from pi0_jax.preprocess import _resize_with_pad

    action_dims = normalizer.dim(nz.ACTIONS) or 7
    if action_dims != 7:
        raise ValueError(f"{name}: the model's actions have {action_dims} dims; this suite needs LIBERO's 7")
    reads_state = not config.pi05 or config.discrete_state_input
    try:
        s_scale, s_offset = _affine(lambda x: normalizer.normalize(nz.STATE, x), 8)
    except KeyError:
        if reads_state:
            raise
        s_scale, s_offset = np.zeros(8, np.float32), np.zeros(8, np.float32)   # the model never reads it
    a_scale, a_offset = _affine(lambda x: normalizer.unnormalize(nz.ACTIONS, x), action_dims)
    slots = IMAGE_KEYS[: config.num_cameras]
    size, horizon, adim = config.image_size, config.action_horizon, config.action_dim
    prompts = env.prompts
    tokens, masks = map(np.stack, zip(*(tok.tokenize(p) for p in prompts)))   # (T, L) each, once per task
    in_prompt = config.pi05 and config.discrete_state_input

    # π0.5 with the state in the prompt: tokenised per plan on the host. As pi0_jax.policy: LeRobot pads the state
    # to action_dim before discretising it (32 numbers in the prompt), openpi does not.
    pad_state = normalizer.convention is nz.Convention.LEROBOT

    def host_tokenize(task, state):
        state = np.asarray(state, np.float64)
        if pad_state:
            state = np.pad(state, ((0, 0), (0, adim - state.shape[1])))
        out = [tok.tokenize(prompts[int(t)], s) for t, s in zip(task, state)]
        return np.stack([o[0] for o in out]), np.stack([o[1] for o in out])

    def image(x):
        x = x.astype(jnp.float32) / 255.0 * 2.0 - 1.0
        return x if x.shape[1:3] == (size, size) else _resize_with_pad(x, size, size, True)

    def observation(obs, es):
        b = obs["state"].shape[0]
        cams = {"base_0_rgb": image(obs["agentview"]), "left_wrist_0_rgb": image(obs["wrist"])}
        images = {k: cams.get(k, jnp.full((b, size, size, 3), -1.0)) for k in slots}
        image_masks = {k: jnp.full((b,), k in cams) for k in slots}
        state = obs["state"] * s_scale + s_offset
        if in_prompt:
            shapes = (jax.ShapeDtypeStruct((b, config.max_token_len), jnp.int32),
                      jax.ShapeDtypeStruct((b, config.max_token_len), jnp.bool_))
            tk, tm = jax.pure_callback(host_tokenize, shapes, es.task, state, vmap_method="expand_dims")
        else:
            tk, tm = jnp.asarray(tokens)[es.task], jnp.asarray(masks)[es.task]
        return pi0.Observation(images=images, image_masks=image_masks,
                               state=jnp.pad(state, ((0, 0), (0, adim - state.shape[1]))),
                               tokenized_prompt=tk, tokenized_prompt_mask=tm)

    def plan(params, ps, obs, es, rng):
        noise = jax.vmap(lambda k: jax.random.normal(k, (horizon, adim)))(rng)
        if dynamic_steps:
            params, steps = params["model"], params["num_steps"]
        else:
            steps = num_steps
        actions = pi0.sample_actions(config, params, observation(obs, es), noise, num_steps=steps)
        return actions[..., :action_dims].astype(jnp.float32) * a_scale + a_offset

    return SimPolicy(name=name, init=lambda b: jnp.zeros((b, horizon, action_dims)), plan=plan,
                     act=lambda ps, es, k: (ps[:, k], ps), needs_images=True, horizon=horizon, observation=observation,
                     params={"model": params, "num_steps": np.int32(num_steps)} if dynamic_steps else params,
                     info={"model": config.name, "pi05": config.pi05, "dtype": config.dtype, "num_steps": num_steps,
                           "action_horizon": horizon, "normalization": normalizer.convention.value})


def make_policy(spec: str, env, replan_steps: int, **kw) -> SimPolicy:
    """'expert' | 'random' | a checkpoint directory."""
    if spec == "expert":
        return expert_policy(env)
    if spec == "random":
        return random_policy(replan_steps)
    if not Path(spec).is_dir():
        raise FileNotFoundError(f"--policy {spec!r}: not 'expert', 'random' or a checkpoint directory")
    return checkpoint_policy(spec, env, **kw)
