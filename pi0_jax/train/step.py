"""The jitted train step: batch assembly on device, the flow-matching loss (spec §7), AdamW, EMA.

The whole dataset lives on every device (replicated, uint8 images); each step draws its batch from
`fold_in(key(seed), step)`, so a run is a pure function of (seed, data, step) and resumes bit-identically. Data
parallel over a 1-D mesh of the local devices (axis "data"): params, optimizer state and EMA are replicated, the
batch is sharded along "data", and XLA's partitioner turns the gradient's batch mean into an all-reduce. The same
code runs on one CPU and on k GPUs.

Precision (spec §8): master params, AdamW moments and EMA are f32; with the model's dtype "bfloat16" the
transformers compute in bf16 (`ops.matmul.matmul` / SigLIP cast the f32 weights to the activation dtype), and the
gradients flow back to the f32 masters.
"""

from __future__ import annotations

import functools
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from pi0_jax import pi0
from pi0_jax.config import IMAGE_KEYS, Pi0Config
from pi0_jax.preprocess import resize_with_pad
from pi0_jax.train.augment import augment
from pi0_jax.train.config import TrainConfig
from pi0_jax.train.data import Dataset

_EPS = 1e-6          # openpi's z-score eps: (x - mean) / (std + eps)
DATA_AXIS = "data"
_INIT_SALT = 0x7FFFFFFF   # init key = fold_in(key(seed), salt); step s uses fold_in(key(seed), s), s < salt


@flax.struct.dataclass
class TrainState:
    step: jax.Array              # () int32: steps taken
    params: Any                  # f32 master weights
    opt_state: Any
    ema: Any                     # f32 EMA of params, or None


def make_mesh(devices=None) -> Mesh:
    return Mesh(np.asarray(devices if devices is not None else jax.local_devices()), (DATA_AXIS,))


def replicated(mesh: Mesh) -> NamedSharding:
    return NamedSharding(mesh, P())


def schedule(cfg: TrainConfig) -> optax.Schedule:
    # openpi's CosineDecaySchedule: linear warm-up from peak / (warmup + 1), cosine down to decay_lr at `steps`.
    return optax.warmup_cosine_decay_schedule(init_value=cfg.lr / (cfg.warmup_steps + 1), peak_value=cfg.lr,
                                              warmup_steps=cfg.warmup_steps, decay_steps=max(cfg.steps, cfg.warmup_steps + 1),
                                              end_value=cfg.decay_lr)


def optimizer(cfg: TrainConfig) -> optax.GradientTransformation:
    return optax.chain(optax.clip_by_global_norm(cfg.clip_norm),
                       optax.adamw(schedule(cfg), b1=0.9, b2=cfg.b2, eps=1e-8, weight_decay=cfg.weight_decay))


def state_from_params(cfg: TrainConfig, params) -> TrainState:
    """A step-0 state over f32 `params` (the EMA, when on, starts equal to them)."""
    ema = jax.tree.map(jnp.copy, params) if cfg.ema_decay is not None else None
    return TrainState(step=jnp.zeros((), jnp.int32), params=params, opt_state=optimizer(cfg).init(params), ema=ema)


def init_state(cfg: TrainConfig, model: Pi0Config) -> TrainState:
    return state_from_params(cfg, pi0.init_params(model, jax.random.fold_in(jax.random.key(cfg.seed), _INIT_SALT)))


def step_key(cfg: TrainConfig, step: jax.Array) -> jax.Array:
    """The key of everything step `step` draws (batch, noise, t): a run is a pure function of (seed, data, step)."""
    return jax.random.fold_in(jax.random.key(cfg.seed), step)


def batch_sharder(mesh: Mesh):
    """x -> x constrained to be split along its leading (batch) axis over the mesh."""
    sharding = NamedSharding(mesh, P(DATA_AXIS))
    return lambda x: jax.lax.with_sharding_constraint(x, sharding)


def device_data(ds: Dataset, stats: dict, mesh: Mesh) -> dict[str, jax.Array]:
    """The dataset and its z-score stats as replicated device arrays (the jitted step's `data` argument)."""
    host = {"images": ds.images, "state": ds.state, "actions": ds.actions, "end": ds.end, "task": ds.task,
            "tokens": ds.tokens, "masks": ds.masks,
            "state_mean": stats["state"].mean, "state_std": stats["state"].std,
            "actions_mean": stats["actions"].mean, "actions_std": stats["actions"].std}
    host = {k: v.astype(np.float32) if v.dtype == np.float64 else v for k, v in host.items()}
    return jax.device_put(host, replicated(mesh))


def make_batch(cfg: TrainConfig, model: Pi0Config, data: dict, rng: jax.Array, shard) -> tuple[pi0.Observation, jax.Array]:
    """Sample `cfg.batch_size` frames and build the model's inputs: (Observation, actions (B, horizon, action_dim))."""
    b, horizon, size = cfg.batch_size, model.action_horizon, model.image_size
    k_idx, k_base, k_wrist = jax.random.split(rng, 3)
    idx = shard(jax.random.randint(k_idx, (b,), 0, data["state"].shape[0]))
    # action chunk: actions t .. t + horizon - 1, the episode's last action repeated past its end (as LeRobot)
    chunk = jnp.minimum(idx[:, None] + jnp.arange(horizon), data["end"][idx][:, None] - 1)
    actions = (data["actions"][chunk] - data["actions_mean"]) / (data["actions_std"] + _EPS)
    state = (data["state"][idx] - data["state_mean"]) / (data["state_std"] + _EPS)
    pad = lambda x: jnp.pad(x, [(0, 0)] * (x.ndim - 1) + [(0, model.action_dim - x.shape[-1])])

    def camera(c: int, key, geometric: bool):
        x = data["images"][idx, c].astype(jnp.float32) / 255.0 * 2.0 - 1.0
        if x.shape[1:3] != (size, size):
            x = resize_with_pad(x, size, size)      # as the policy pipeline does at evaluation
        return augment(key, x, geometric=geometric) if cfg.augment else x

    cams = {"base_0_rgb": camera(0, k_base, True), "left_wrist_0_rgb": camera(1, k_wrist, False)}
    slots = IMAGE_KEYS[: model.num_cameras]
    task = data["task"][idx]
    obs = pi0.Observation(
        images={k: shard(cams[k]) if k in cams else jnp.full((b, size, size, 3), -1.0) for k in slots},
        image_masks={k: jnp.full((b,), k in cams) for k in slots},
        state=shard(pad(state)), tokenized_prompt=data["tokens"][task], tokenized_prompt_mask=data["masks"][task])
    return obs, shard(pad(actions))


def optimizer_step(cfg: TrainConfig, state: TrainState, loss_fn) -> tuple[TrainState, dict]:
    """One AdamW step on `loss_fn(params) -> scalar` at state.params, then the EMA update.
    -> (new state, {"loss", "grad_norm", "lr"} as device scalars)."""
    loss, grads = jax.value_and_grad(loss_fn)(state.params)
    updates, opt_state = optimizer(cfg).update(grads, state.opt_state, state.params)
    params = optax.apply_updates(state.params, updates)
    ema = state.ema
    if ema is not None:
        # warm-up of the decay (as TF's ExponentialMovingAverage with num_updates): early EMAs follow the params
        d = jnp.minimum(cfg.ema_decay, (1.0 + state.step) / (10.0 + state.step))
        ema = jax.tree.map(lambda e, p: d * e + (1 - d) * p, ema, params)
    metrics = {"loss": loss, "grad_norm": optax.tree.norm(grads), "lr": schedule(cfg)(state.step)}
    return TrainState(step=state.step + 1, params=params, opt_state=opt_state, ema=ema), metrics


def flow_loss(cfg: TrainConfig, model: Pi0Config, params, obs, actions, noise, t, rng) -> jax.Array:
    """The mean flow-matching loss; with cfg.max_delay, each sample's first d ~ U{0..max_delay} actions ride at
    t = 0 (given, clean) and the mean runs over the others only (training-time action conditioning)."""
    if not cfg.max_delay:
        return jnp.mean(pi0.compute_loss(model, params, obs, actions, noise, t))
    if cfg.max_delay >= actions.shape[1]:
        raise ValueError(f"max_delay {cfg.max_delay} must be below the action horizon {actions.shape[1]}")
    d = jax.random.randint(rng, (actions.shape[0],), 0, cfg.max_delay + 1)
    free = ~pi0.committed_mask(actions.shape[1], d)                                    # (B, H)
    loss = pi0.compute_loss(model, params, obs, actions, noise, jnp.where(free, t[:, None], 0.0))
    return jnp.sum(loss * free) / jnp.sum(free)


def train_step(cfg: TrainConfig, model: Pi0Config, mesh: Mesh, state: TrainState, data: dict):
    """One flow-matching AdamW step on one batch. -> (new state, {"loss", "grad_norm", "lr"} as device scalars)."""
    shard = batch_sharder(mesh)
    k_batch, k_noise, k_time = jax.random.split(step_key(cfg, state.step), 3)
    obs, actions = make_batch(cfg, model, data, k_batch, shard)
    noise = shard(jax.random.normal(k_noise, actions.shape, jnp.float32))
    t = shard(pi0.sample_time(k_time, cfg.batch_size))
    k_delay = jax.random.fold_in(k_time, 1)
    return optimizer_step(cfg, state, lambda params: flow_loss(cfg, model, params, obs, actions, noise, t, k_delay))


def batch_loss(cfg: TrainConfig, model: Pi0Config, params, data: dict, rng: jax.Array) -> jax.Array:
    """The mean flow-matching loss of `params` on one batch drawn as a train step draws it from `rng` (no
    sharding constraint): for comparing weights on the same inputs."""
    k_batch, k_noise, k_time = jax.random.split(rng, 3)
    obs, actions = make_batch(cfg, model, data, k_batch, lambda x: x)
    noise = jax.random.normal(k_noise, actions.shape, jnp.float32)
    return jnp.mean(pi0.compute_loss(model, params, obs, actions, noise, pi0.sample_time(k_time, cfg.batch_size)))


@functools.lru_cache(maxsize=8)
def jitted_step(cfg: TrainConfig, model: Pi0Config, mesh: Mesh):
    """`step(state, data) -> (state, metrics)`, compiled once per (config, mesh); the state's buffers are donated."""
    rep = replicated(mesh)
    return jax.jit(functools.partial(train_step, cfg, model, mesh), out_shardings=(rep, rep), donate_argnums=0)
