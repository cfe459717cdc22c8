"""Policies for the batched rollout, behind one interface: the scripted expert, a random policy, pi0-jax checkpoints.

A policy is driven by the rollout (evaluate.py) in two calls, both batched over environments and traced into the
same jitted program as the physics:

  pstate = plan(params, pstate, obs, env_state, rng)   every `replan_steps` steps: e.g. sample an action chunk
  action, pstate = act(pstate, env_state, k)            every step k = 0 .. replan_steps - 1 of the chunk

`params` is a jit argument (a full-size model's weights must not become compile-time constants); obs is the env's
batched observation ({"agentview", "wrist": (B, H, W, 3) uint8, "state": (B, 8)}) or None when the policy does not
look at images (`needs_images` False: the rollout then skips rendering). The expert acts from privileged state
every step, so it ignores replanning; chunked policies return chunk[:, k].

The pi0-jax policy runs `pi0_jax.pipeline.PolicyCore.program` inside the rollout's jit, the same pipeline as
`Policy.infer` and the server: agent view -> `base_0_rgb`, wrist -> `left_wrist_0_rgb` (a right wrist slot is not
encoded at all, as openpi's LIBERO example masks it); the task's prompt tokenised once on the host (or, for π0.5
with the state in the prompt, by a host callback per plan), cut to its prompt bucket; the engine's stages.
"""

from __future__ import annotations

import dataclasses
import os
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from pi0_jax.sim import expert as _expert
from pi0_jax.sim.realtime import hold_chunk
from pi0_jax.sim.tasks import ACTION_DIM, STATE_DIM


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
    stats: Callable | None = None                   # pstate -> {name: (B,) counts}, summed into eval_info
    setup_s: dict = dataclasses.field(default_factory=dict)   # seconds spent building it, by part


def chunked_plan(plan: Callable[..., Any], chunk: int | None, n_dev: int = 1, sharding=None) -> Callable[..., Any]:
    """`plan` run on at most `chunk` environments per device at a time, one chunk after another (a lax.map), so a
    large batch's policy activations (π0.5's prefix MLP: ~60 MB per environment) stay those of one chunk. Every
    argument but params is batch-first with the batch laid out device-major (n_dev blocks of the local batch); each
    chunk takes the same rows of every device's block, so all devices work on every chunk. A local batch that is not
    a multiple of the chunk count is padded by repeating its last row; the padding is dropped from the result.
    sharding: the chunks' (chunk, batch) sharding, e.g. NamedSharding(mesh, P(None, "batch")). chunk None, or a local
    batch no larger than it: `plan` itself."""
    def run(params, *xs):
        local = jax.tree.leaves(xs)[0].shape[0] // n_dev
        if chunk is None or local <= chunk:
            return plan(params, *xs)
        k = -(-local // chunk)
        m = -(-local // k)

        def split(x):   # (n_dev * local, ...) -> (k, n_dev * m, ...)
            x = x.reshape((n_dev, local) + x.shape[1:])
            if k * m > local:
                x = jnp.concatenate([x, jnp.repeat(x[:, -1:], k * m - local, axis=1)], axis=1)
            x = x.reshape((n_dev, k, m) + x.shape[2:]).swapaxes(0, 1).reshape((k, n_dev * m) + x.shape[2:])
            return x if sharding is None else jax.lax.with_sharding_constraint(x, sharding)

        def merge(y):   # the inverse, padding dropped
            y = y.reshape((k, n_dev, m) + y.shape[2:]).swapaxes(0, 1).reshape((n_dev, k * m) + y.shape[2:])
            return y[:, :local].reshape((n_dev * local,) + y.shape[2:])

        return jax.tree.map(merge, jax.lax.map(lambda c: plan(params, *c), jax.tree.map(split, xs)))

    return run


def expert_policy(env, delay: int = 0, pos_gain: float = _expert.POS_GAIN) -> SimPolicy:
    """The scripted expert (privileged state, closed loop every step). delay D > 0: the action computed from the
    state at step t is executed at t + D (a FIFO of D actions; the first D steps hold still: zero motion, gripper
    open), the latency of a policy that replans every step. pos_gain: `expert.act`'s."""
    def expert_act(ps, es):
        return jax.vmap(lambda s, e: _expert.act(env, s, e, pos_gain))(es, ps)

    if not delay:
        return SimPolicy(
            name="expert",
            init=lambda b: jax.tree.map(lambda x: jnp.broadcast_to(x, (b,) + x.shape), _expert.init()),
            plan=lambda params, ps, obs, es, rng: ps,
            act=lambda ps, es, k: expert_act(ps, es))

    def init(b):
        queue = hold_chunk(b, delay)
        return jax.tree.map(lambda x: jnp.broadcast_to(x, (b,) + x.shape), _expert.init()), queue

    def act(ps, es, k):
        ex, queue = ps
        action, ex = expert_act(ex, es)
        return queue[:, 0], (ex, jnp.concatenate([queue[:, 1:], action[:, None]], axis=1))

    return SimPolicy(name=f"expert (latency {delay})", init=init, plan=lambda params, ps, obs, es, rng: ps, act=act)


def random_policy(replan_steps: int) -> SimPolicy:
    """Uniform actions in [-1, 1]^7 (gripper included), a fresh chunk every plan."""
    def plan(params, ps, obs, es, rng):
        return jax.vmap(lambda k: jax.random.uniform(k, (replan_steps, ACTION_DIM), minval=-1.0, maxval=1.0))(rng)

    return SimPolicy(name="random", init=lambda b: jnp.zeros((b, replan_steps, ACTION_DIM)), plan=plan,
                     act=lambda ps, es, k: (ps[:, k], ps), horizon=replan_steps)


def checkpoint_policy(path: str | os.PathLike, env, *, tokenizer_path=None, num_steps: int = 10,
                      norm_stats: str | os.PathLike | None = None, dtype: str | None = None,
                      sampler: str = "engine", realtime=None, replan_steps: int | None = None,
                      quant: str | None = None, gemm: str = "xla", attention: str = "auto") -> SimPolicy:
    """A pi0-jax checkpoint directory (`pi0-jax convert` output) as a batched in-jit policy for `env`'s tasks.
    quant: a number format for the weights (`quantize_for_suite`), None = as stored; gemm, attention: see
    `model_policy`."""
    from pi0_jax.policy import load_parts

    t0 = time.perf_counter()
    config, params, tok, normalizer = load_parts(path, tokenizer_path=tokenizer_path, norm_stats=norm_stats,
                                                 dtype=dtype)
    return _quantized_policy(config, params, tok, normalizer, env, {"load_s": time.perf_counter() - t0},
                             quant=quant, num_steps=num_steps, name=str(path), sampler=sampler, realtime=realtime,
                             replan_steps=replan_steps, gemm=gemm, attention=attention)


def _quantized_policy(config, params, tok, normalizer, env, setup: dict, *, quant, num_steps, calib=None,
                      **kw) -> SimPolicy:
    """`quantize_for_suite`, then `model_policy`; each part's seconds join `setup` (the policy's `setup_s`)."""
    params = quantize_for_suite(config, params, tok, normalizer, quant, num_steps=num_steps, calib=calib,
                                timing=setup)
    t0 = time.perf_counter()
    policy = model_policy(config, params, tok, normalizer, env, num_steps=num_steps, quant=quant, **kw)
    return dataclasses.replace(policy, setup_s={**setup, "policy_s": time.perf_counter() - t0})


def model_policy(config, params, tok, normalizer, env, *, num_steps: int = 10, dynamic_steps: bool = False,
                 name: str = "model", sampler: str = "engine", action_dims: int | None = None, realtime=None,
                 replan_steps: int | None = None, quant: str | None = None, gemm: str = "xla",
                 attention: str = "auto") -> SimPolicy:
    """A π0 / π0.5 with its tokenizer and normaliser as a batched in-jit policy for `env`'s tasks, through the one
    policy pipeline (`pi0_jax.pipeline.PolicyCore.program`: the engine, or the reference sampler when asked).

    dynamic_steps: the flow-step count travels in the policy's params ({..., "num_steps": int32}) instead of the
    program, so one compiled rollout serves every step count up to `PolicyCore.max_dynamic_steps` (same numerics).
    params None: the transforms only (`observation`), e.g. for calibration batches. quant: the number format the
    params were quantised to (`quantize_for_suite`), recorded in the policy's info. gemm: the library of the
    rollout's GEMMs on a GPU (`pi0_jax.ops.matmul.compiler_options`; the rollout compiles with `info["gemm"]`).
    attention: each stage's attention (`pi0_jax.engine.paths.Attention.parse`), recorded in the info.
    realtime: a `pi0_jax.sim.realtime.Realtime` (latency, sync / naive / rtc / conditioned execution, prefix reuse;
    needs replan_steps); the policy state is then a dict (chunk, previous chunk, cached prefix, counters) instead of the
    chunk itself."""
    from pi0_jax import pi0
    from pi0_jax.engine import prompt_bucket
    from pi0_jax.pipeline import PolicyCore

    from pi0_jax import normalize as nz

    action_dims = action_dims or normalizer.dim(nz.ACTIONS) or ACTION_DIM    # no stats: LIBERO's
    core = PolicyCore(config, params, tok, normalizer, num_steps=num_steps, sampler=sampler, action_dims=action_dims,
                      gemm=gemm, attention=attention)
    if core.action_dims != ACTION_DIM:
        raise ValueError(f"{name}: the model's actions have {core.action_dims} dims; this suite needs LIBERO's "
                         f"{ACTION_DIM}")
    if core.reads_state and core.state_dim not in (None, STATE_DIM):
        raise ValueError(f"{name}: the norm stats' state has {core.state_dim} dims; "
                         f"this suite's state has {STATE_DIM}")
    # agent view -> base_0_rgb, wrist -> left_wrist_0_rgb; a right wrist slot is absent, so never encoded
    cameras = tuple(k for k in ("base_0_rgb", "left_wrist_0_rgb") if k in core.slots)
    horizon, adim = config.action_horizon, config.action_dim
    prompts = env.prompts
    in_prompt = config.pi05 and config.discrete_state_input
    tokens, masks = map(np.stack, zip(*(core.tokenize_prompt(p) for p in prompts)))   # (T, L), once per task
    longest = state_prompt_tokens(core, prompts) if in_prompt else int(masks.sum(1).max())
    bucket = prompt_bucket(longest, config.max_token_len)
    tokens, masks = tokens[:, :bucket], masks[:, :bucket]

    def host_tokenize(task, state):   # π0.5 with the state in the prompt: the normalised state, per plan
        out = [core.tokenize(prompts[int(t)], np.asarray(s[:STATE_DIM], np.float64)) for t, s in zip(task, state)]
        tk, tm = np.stack([o[0] for o in out]), np.stack([o[1] for o in out])
        if tm[:, bucket:].any():
            raise ValueError(f"{name}: a state prompt took {int(tm.sum(1).max())} tokens, more than the "
                             f"{bucket} the rollout was compiled for (state_prompt_tokens' bound is too low)")
        return tk[:, :bucket], tm[:, :bucket]

    def inputs(norm, obs, es):
        b = obs["state"].shape[0]
        images = (obs["agentview"], obs["wrist"])[: len(cameras)]
        state = jnp.pad(obs["state"], ((0, 0), (0, adim - obs["state"].shape[1])))
        if in_prompt:
            _, normalised = core.preprocess(norm, (), state)
            shapes = (jax.ShapeDtypeStruct((b, bucket), jnp.int32), jax.ShapeDtypeStruct((b, bucket), jnp.bool_))
            tk, tm = jax.pure_callback(host_tokenize, shapes, es.task, normalised, vmap_method="expand_dims")
        else:
            tk, tm = jnp.asarray(tokens)[es.task], jnp.asarray(masks)[es.task]
        return images, jnp.ones((len(cameras), b), bool), tk, tm, state

    def observation(obs, es):
        """The reference model's pi0.Observation of a batch (calibration)."""
        images, image_masks, tk, tm, state = inputs(core.norm, obs, es)
        pixels, state = core.preprocess(core.norm, images, state)
        b, size = state.shape[0], config.image_size
        by_slot = dict(zip(cameras, pixels))
        return pi0.Observation(images={k: by_slot.get(k, jnp.full((b, size, size, 3), -1.0)) for k in core.slots},
                               image_masks={k: jnp.full((b,), k in by_slot) for k in core.slots}, state=state,
                               tokenized_prompt=tk, tokenized_prompt_mask=tm)

    def plan(params, ps, obs, es, rng):
        noise = jax.vmap(lambda k: jax.random.normal(k, (horizon, adim)))(rng)
        images, image_masks, tk, tm, state = inputs(params["norm"], obs, es)
        return core.program(params["model"], params["norm"], images, cameras, image_masks, tk, tm, state, noise,
                            num_steps=params.get("num_steps"))

    pparams = {"model": core.dynamic_model() if dynamic_steps else core.model, "norm": core.norm}
    if dynamic_steps:
        pparams["num_steps"] = np.int32(num_steps)
    info = {"model": config.name, "pi05": config.pi05, "dtype": config.dtype, "num_steps": num_steps,
            "action_horizon": horizon, "normalization": normalizer.convention.value, "sampler": core.sampler,
            "quant": quant or "none", "gemm": core.gemm, "attention": str(core.attention), "kernels": core.kernels,
            "prompt_tokens": bucket}
    init, act, stats = (lambda b: jnp.zeros((b, horizon, core.action_dims))), (lambda ps, es, k: (ps[:, k], ps)), None
    if realtime is not None and not realtime.is_default:
        from pi0_jax.sim import realtime as rt_lib

        if replan_steps is None:
            raise ValueError("a realtime policy needs replan_steps")
        init, plan, act, stats = rt_lib.make_model_callbacks(core, realtime, replan_steps, inputs, cameras, bucket)
    if realtime is not None:
        info["realtime"] = realtime.describe()
        if in_prompt and realtime.reuse_prefix is not None:
            info["realtime"]["note"] = "π0.5 with the state in the prompt: reused prefixes hold a stale state"
    return SimPolicy(name=name, init=init, plan=plan, act=act, needs_images=True, horizon=horizon,
                     observation=observation, params=pparams, info=info, stats=stats)


def state_prompt_tokens(core, prompts) -> int:
    """The most tokens any of these prompts takes with a discretised state written into it (π0.5): each prompt with
    all STATE_DIM dims in each of the 257 bins in turn, plus one token per dim, in case numbers tokenize longer side
    by side than alone. The suite's π0.5 thus runs a 48- or 64-token prompt bucket instead of all 200 tokens."""
    from pi0_jax.tokenizer import STATE_BIN_EDGES

    values = np.concatenate([[-2.0], STATE_BIN_EDGES])     # one value per bin: -1 (below the range), 0 .. 255
    return max(int(core.tokenize(p, np.full(STATE_DIM, v))[1].sum()) for p in prompts for v in values) + STATE_DIM


def preset_policy(name: str, env, *, num_steps: int = 10, dtype: str | None = None, seed: int = 0,
                  sampler: str = "engine", realtime=None, replan_steps: int | None = None,
                  quant: str | None = None, gemm: str = "xla", attention: str = "auto") -> SimPolicy:
    """Random weights of a preset (`pi0_jax.config`), e.g. a full-size π0.5, with identity normalisation, the
    embedded model's tokenizer and LIBERO's 7 action dims: the protocol's timing without a trained checkpoint
    (the success rate is ~0)."""
    from pi0_jax import normalize as nz
    from pi0_jax import pi0
    from pi0_jax.config import get_config
    from pi0_jax.policy import find_tokenizer
    from pi0_jax.quant import schemes
    from pi0_jax.tokenizer import PaligemmaTokenizer

    config = get_config(name, **({"dtype": dtype} if dtype else {}))
    tok = PaligemmaTokenizer(find_tokenizer(Path(__file__).parents[1] / "assets" / "pi0_small"),
                             config.max_token_len)
    normalizer = nz.Normalizer.identity()
    # an FP8 scheme's calibration frames render (and their programs compile) beside the weights' init: both are
    # mostly compiling, cold (docs/BENCHMARKS.md, "every-gemm's setup, measured by part")
    with ThreadPoolExecutor(1) as pool:
        calib = pool.submit(_timed, calibration_observation, config, tok, normalizer, CALIB_SAMPLES) \
            if quant in schemes.SCHEMES else None
        t0 = time.perf_counter()
        params = jax.block_until_ready(pi0.random_params(config, seed))
        setup = {"random_params_s": time.perf_counter() - t0}
        if calib is not None:
            calib, setup["observations_s"] = calib.result()   # seconds in its thread, beside random_params_s
    return _quantized_policy(config, params, tok, normalizer, env, setup, quant=quant, num_steps=num_steps,
                             calib=calib, name=f"preset:{name} (random weights)", sampler=sampler,
                             realtime=realtime, replan_steps=replan_steps, gemm=gemm, attention=attention)


def _timed(fn, *args):
    t0 = time.perf_counter()
    return fn(*args), time.perf_counter() - t0


def make_policy(spec: str, env, replan_steps: int, **kw) -> SimPolicy:
    """'expert' | 'random' | 'preset:NAME' (random weights) | a checkpoint directory."""
    if spec == "expert":
        return expert_policy(env)
    if spec == "random":
        return random_policy(replan_steps)
    if spec.startswith("preset:"):
        kw = {k: v for k, v in kw.items() if k in ("num_steps", "dtype", "sampler", "realtime", "quant", "gemm",
                                                  "attention")}
        return preset_policy(spec.removeprefix("preset:"), env, replan_steps=replan_steps, **kw)
    if not Path(spec).is_dir():
        raise FileNotFoundError(f"--policy {spec!r}: not 'expert', 'random', 'preset:NAME' or a checkpoint directory")
    return checkpoint_policy(spec, env, replan_steps=replan_steps, **kw)


QUANT_FORMATS = ("nvfp4", "mxfp4")     # weight-only FP4 emulation; the FP8 schemes are pi0_jax.quant.schemes.SCHEMES
CALIB_SAMPLES = 64   # rendered suite observations an FP8 scheme's static scales are calibrated on


def quantize_for_suite(config, params, tok, normalizer, quant: str | None, *, seed: int = 0, calib=None,
                       num_steps: int = 10, timing: dict | None = None):
    """params in number format `quant`: None = unchanged; an FP8 scheme of `pi0_jax.quant.schemes` (real e4m3
    GEMMs where XLA emits them) with static activation scales, amax over CALIB_SAMPLES rendered suite
    observations from initial states 50..99 (never evaluated; seed: their and the calibration's noise draws);
    "nvfp4" / "mxfp4": weight emulation (quantised and dequantised back) of every GEMM the FP8 scheme "all"
    covers. calib: a precomputed `calibration_observation` (then no observations_s here). timing: a dict to receive
    the seconds of each part (observations, the calibration's compile and run, quantising)."""
    if quant is None:
        return params
    from pi0_jax.quant import schemes

    if quant in QUANT_FORMATS:
        return jax.device_put(schemes.fake_quant_fp4_params(params, quant, "all"), jax.devices()[0])
    if quant not in schemes.SCHEMES:
        raise ValueError(f"unknown number format {quant!r}: {', '.join([*schemes.SCHEMES, *QUANT_FORMATS])}")
    timing = {} if timing is None else timing
    if calib is None:
        t0 = time.perf_counter()
        calib = calibration_observation(config, tok, normalizer, CALIB_SAMPLES, seed)
        timing["observations_s"] = time.perf_counter() - t0
    calib_timing = {}
    amax = schemes.calibrate(config, params, [calib], quant, percentile=None, num_steps=num_steps, seed=seed,
                             timing=calib_timing)["amax"]
    timing.update({f"calibrate_{k}": v for k, v in calib_timing.items()})
    t0 = time.perf_counter()
    params = jax.block_until_ready(schemes.quantize_params(params, quant, amax))
    timing["quantize_s"] = time.perf_counter() - t0
    return params


def calibration_observation(config, tok, normalizer, n: int, seed: int = 0):
    """The model's pi0.Observation of n rendered suite observations at initial states 50..99 (never evaluated)."""
    from pi0_jax.sim import tasks
    from pi0_jax.sim.env import Env
    from pi0_jax.sim.render import RenderConfig

    env = Env(tasks.SUITES["all"], RenderConfig(config.image_size, config.image_size), num_init_states=100)
    t = (np.arange(n) % len(env.tasks)).astype(np.int32)
    i = (50 + (np.arange(n) // len(env.tasks)) % 50).astype(np.int32)
    state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.key(seed), n), t, i)
    obs = jax.jit(jax.vmap(env.observe))(state)
    return model_policy(config, None, tok, normalizer, env).observation(obs, state)
