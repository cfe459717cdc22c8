"""Inference latency, asynchronous execution and prefix reuse for a model policy in the jitted rollout.

Latency. A chunk planned from the observation at control step t is first usable at t + D (`latency_steps`; one step
is 50 ms at the suite's 20 Hz, so D = 4 is 200 ms). Chunk index i is the action meant for step t + i. With
`replan_steps` r, plans start at t = 0, r, 2r, ... and `execution` says what the robot does while one runs:

  sync   the world waits for the chunk (today's protocol; D has no effect): steps t .. t+r-1 execute chunk[0:r].
  naive  the robot keeps executing the previous chunk: steps t .. t+D-1 execute prev[r : r+D] (the previous chunk was
         planned at t - r), steps t+D .. t+r-1 the new chunk[D:r]. The first plan of an episode has no previous
         chunk: its first D steps hold still (zero motion, gripper open: the episode's initial command).
  rtc    as naive, but the new chunk is sampled with real-time chunking (Black, Galliker, Levine 2025): its first D
         actions are frozen to the committed prev[r : r+D], the overlap after them (indices D .. H-r-1, where the
         previous chunk still has actions) is guided with exponentially decaying weights, and the rest is free
         (`engine.guidance.guided_denoise`, ΠGDM guidance clipped at beta). The frozen actions are written into the
         returned chunk exactly; they are never executed from it (they lie in the past when it arrives).
  conditioned  as naive, with training-time action conditioning (Black, Ren, Equi, Levine 2025, arXiv 2512.05964):
         the committed prev[r : r+D] enter the new chunk's first D actions as clean inputs (flow time 0) and the
         model samples the rest given them, with no guidance and no extra compute. Meant for a model trained so
         (`pi0-jax train --max-delay`); an episode's first plan is conditioned on the hold chunk it executes.

Every mode steps the environment once per control step, so episode lengths and LIBERO's step limits mean the same.
Requires D <= r (one plan in flight) and r + D <= H (the previous chunk covers the wait). With D = 0 the four modes
are the same policy: rtc then has nothing committed and samples without guidance (the paper's soft overlap weights
alone are not applied at D = 0, so D = 0 is exactly the synchronous baseline), and conditioned gives nothing.

Prefix reuse. `reuse_prefix` K recomputes vision and the prefix KV cache only at every K-th plan and otherwise runs
only the denoise program on the cached prefix. π0 feeds the state through the suffix, so the fresh state still
enters; π0.5 with the state in the prompt (`discrete_state_input`) would use the state of the cached plan (stale), and
π0.5 without state input has no state at all. "auto:THRESH" recomputes an environment's prefix when its camera
images moved more than THRESH since the frame its cache was computed from: the larger over cameras of the mean
absolute difference of 16 x 16 area-downsampled frames in [0, 1], measured before the vision tower. Selection is per
environment (`jnp.where`), and the batch's vision + prefix programs run (`lax.cond`) when any live environment needs
them, so success is the single-robot policy's; the compute saving of a batched simulator is only an upper bound of a
single robot's, which `prefix_recompute_fraction` (recomputes / plans of live episodes, in eval_info) measures.

Normalised model space. The rtc target is the previous chunk as the model sampled it (normalised, all action_dim
dims, before slicing and un-normalising), kept in the policy state: the same numbers that were committed, without
inverting the (un)normalisation; padding dims beyond the 7 executed ones get weight 0.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

EXECUTIONS = ("sync", "naive", "rtc", "conditioned")
CONTROL_HZ = 20          # the suite's control rate: D steps = 50 D ms
THUMB = 16               # side of the downsampled frames of the auto reuse rule


@dataclasses.dataclass(frozen=True)
class Realtime:
    """execution: sync | naive | rtc | conditioned; latency_steps: D; reuse_prefix: None (recompute every plan), "K" or
    "auto:THRESH"; rtc_beta: rtc's guidance weight's clip (the paper's β, 5 there and by default; 0: no guidance,
    rtc's sample is naive's)."""

    execution: str = "sync"
    latency_steps: int = 0
    reuse_prefix: str | None = None
    rtc_beta: float = 5.0

    def __post_init__(self):
        if self.execution not in EXECUTIONS:
            raise ValueError(f"execution must be one of {EXECUTIONS}, got {self.execution!r}")
        if self.latency_steps < 0:
            raise ValueError(f"latency_steps must be >= 0, got {self.latency_steps}")
        if not 0.0 <= self.rtc_beta < float("inf"):
            raise ValueError(f"rtc_beta must be finite and >= 0, got {self.rtc_beta}")
        parse_reuse(self.reuse_prefix)

    @property
    def delay(self) -> int:
        """The delay that shapes execution: D, or 0 under sync (the world waits)."""
        return 0 if self.execution == "sync" else self.latency_steps

    @property
    def latency_ms(self) -> float:
        return 1000.0 * self.latency_steps / CONTROL_HZ

    @property
    def is_default(self) -> bool:
        return self.delay == 0 and self.reuse_prefix is None and self.execution == "sync"

    def check(self, replan_steps: int, horizon: int) -> None:
        d = self.delay
        if d and not (d <= replan_steps and replan_steps + d <= horizon):
            raise ValueError(f"--latency-steps {d} with --replan-steps {replan_steps} and horizon {horizon}: need "
                             f"D <= replan_steps (one plan in flight) and replan_steps + D <= horizon")

    def describe(self) -> dict:
        every, thresh = parse_reuse(self.reuse_prefix)
        return {"execution": self.execution, "latency_steps": self.latency_steps, "latency_ms": self.latency_ms,
                "reuse_prefix": self.reuse_prefix, "reuse_every": every, "reuse_threshold": thresh,
                **({"rtc_beta": self.rtc_beta} if self.execution == "rtc" else {})}


def parse_reuse(spec: str | None) -> tuple[int, float | None]:
    """None -> (1, None); "K" -> (K, None); "auto:THRESH" -> (0, THRESH)."""
    if spec is None:
        return 1, None
    spec = str(spec)
    if spec.startswith("auto:"):
        try:
            thresh = float(spec.removeprefix("auto:"))
        except ValueError:
            thresh = float("nan")
        if not thresh >= 0:
            raise ValueError(f"--reuse-prefix auto:THRESH needs a number THRESH >= 0, got {spec!r}")
        return 0, thresh
    if not spec.isdigit() or int(spec) < 1:
        raise ValueError(f"--reuse-prefix must be a positive integer K or auto:THRESH, got {spec!r}")
    return int(spec), None


def rtc_weights(horizon: int, delay: int, replan_steps: int) -> np.ndarray:
    """(H,) guidance weights of the RTC paper's eq. 5: 1 for i < d; c_i (e^c_i - 1) / (e - 1) with
    c_i = (H - s - i) / (H - s - d + 1) for d <= i < H - s; 0 from H - s on (s = replan_steps)."""
    i = np.arange(horizon, dtype=np.float64)
    end = horizon - replan_steps
    c = np.clip((end - i) / (end - delay + 1), 0.0, 1.0)
    w = np.where(i < delay, 1.0, c * np.expm1(c) / (np.e - 1.0))
    return np.where(i >= end, 0.0, w).astype(np.float32)


def hold_chunk(batch: int, horizon: int, dims: int = 7) -> jax.Array:
    """The chunk before the first plan: zero motion, gripper open (-1), the command an episode starts with."""
    return jnp.zeros((batch, horizon, dims), jnp.float32).at[..., 6].set(-1.0)


def thumbnails(images) -> jax.Array:
    """C camera frames (B, h, w, 3) uint8 -> (B, C, 16, 16, 3) f32 in [0, 1] (area averaging; batch first, as
    every leaf of the sharded policy state)."""
    x = jnp.stack([jnp.asarray(im) for im in images], axis=1).astype(jnp.float32) / 255.0
    b, c, h, w, _ = x.shape
    if h % THUMB == 0 and w % THUMB == 0:
        return x.reshape(b, c, THUMB, h // THUMB, THUMB, w // THUMB, 3).mean(axis=(3, 5))
    return jax.image.resize(x, (b, c, THUMB, THUMB, 3), "linear", antialias=True)


def image_change(ref, now) -> jax.Array:
    """(B,) the larger over cameras of the mean absolute difference of two thumbnail stacks."""
    return jnp.abs(now - ref).mean(axis=(2, 3, 4)).max(axis=1)


def _where_batch(pick, a, b):
    return jax.tree.map(lambda x, y: jnp.where(pick.reshape((-1,) + (1,) * (x.ndim - 1)), x, y), a, b)


def make_model_callbacks(core, rt: Realtime, replan_steps: int, inputs, cameras, bucket: int):
    """(init, plan, act, stats) of a model policy under `rt`, on the engine's programs (`core`: a PolicyCore with
    the engine sampler; `inputs(norm, obs, es)` -> (images, image_masks, tokens, token_mask, raw padded state);
    `bucket` the prompt length `inputs` returns)."""
    from pi0_jax.engine import guidance, programs

    if core.sampler != "engine" or core.kernels == "pallas":
        raise ValueError("--execution / --latency-steps / --reuse-prefix run on the engine sampler with XLA "
                         f"kernels, not {core.sampler!r} / {core.kernels!r}")
    cfg, horizon, adim, dims = core.config, core.config.action_horizon, core.config.action_dim, core.action_dims
    r, d = replan_steps, rt.delay
    rt.check(r, horizon)
    every, thresh = parse_reuse(rt.reuse_prefix)
    reuse, rtc = rt.reuse_prefix is not None, rt.execution == "rtc" and d > 0
    conditioned = rt.execution == "conditioned" and d > 0
    size, n_cam = cfg.image_size, len(cameras)

    def attention(b: int):   # guided denoising differentiates the velocity: no Pallas attention, in its cache too
        return core.attention.at_batch(b, suffix_mask=not cfg.pi05, differentiable=rtc)

    def prefix(model, pixels, image_masks, tokens, token_mask):
        w = model["weights"]
        image_tokens = programs.encode_images(cfg, w, pixels, unroll=core.unroll, attention=core.attention,
                                              kernels=core.kernels)
        return programs.fill_prefix_cache(cfg, w, image_tokens, image_masks, tokens, token_mask, unroll=core.unroll,
                                          attention=attention(tokens.shape[0]))

    def init(b: int) -> dict:
        ps = {"chunk": hold_chunk(b, horizon, dims), "count": jnp.zeros((b,), jnp.int32),
              "plans": jnp.zeros((b,), jnp.int32), "recomputed": jnp.zeros((b,), jnp.int32)}
        if d:
            ps["prev"] = ps["chunk"]
        if rtc:
            ps["raw"] = jnp.zeros((b, horizon, adim), jnp.float32)
            ps["fresh"] = jnp.zeros((b,), bool)     # "raw" holds a planned chunk (not the hold chunk)
        if reuse:
            spec = jax.ShapeDtypeStruct
            shapes = jax.eval_shape(prefix, core.model, spec((n_cam, b, size, size, 3), jnp.float32),
                                    spec((n_cam, b), bool), spec((b, bucket), jnp.int32), spec((b, bucket), bool))
            ps["cache"] = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)
            if every == 0:
                ps["thumbs"] = jnp.zeros((b, n_cam, THUMB, THUMB, 3), jnp.float32)
        return ps

    def plan(params, ps, obs, es, rng):
        model, norm = params["model"], params["norm"]
        num_steps = params.get("num_steps", core.num_steps)
        sched = core._schedule(model, num_steps)
        noise = jax.vmap(lambda k: jax.random.normal(k, (horizon, adim)))(rng)
        images, image_masks, tokens, token_mask, state = inputs(norm, obs, es)
        pixels, state = core.preprocess(norm, images, state)
        pixels = jnp.stack(pixels)
        live = ~es.done
        out = dict(ps)

        def fresh():
            return prefix(model, pixels, image_masks, tokens, token_mask)

        if reuse:
            if every:
                need = ps["count"] % every == 0
            else:
                thumbs = thumbnails(images)
                need = (ps["count"] == 0) | (image_change(ps["thumbs"], thumbs) > thresh)
                out["thumbs"] = _where_batch(need, thumbs, ps["thumbs"])
            cache = jax.lax.cond(jnp.any(need & live), lambda: _where_batch(need, fresh(), ps["cache"]),
                                 lambda: ps["cache"])
            out["cache"] = cache
        else:
            need, cache = jnp.ones_like(live), fresh()
        if rtc:
            target = jnp.concatenate([ps["raw"][:, r:], jnp.zeros_like(ps["raw"][:, :r])], axis=1)
            weight = (jnp.asarray(rtc_weights(horizon, d, r))[None, :, None]
                      * (jnp.arange(adim) < dims)[None, None, :] * ps["fresh"][:, None, None])
            raw = guidance.guided_denoise(cfg, model["weights"], sched, cache, state, noise, target, weight,
                                          num_steps=num_steps, beta=rt.rtc_beta, unroll=core.unroll,
                                          attention=attention(noise.shape[0]))
            frozen = (jnp.arange(horizon) < d)[None, :, None] & ps["fresh"][:, None, None]
            raw = jnp.where(frozen, target, raw)
            out["raw"], out["fresh"] = raw, jnp.ones_like(ps["fresh"])
        elif conditioned:   # the committed actions, as executed, back in model space (padding dims 0)
            executed = ps["chunk"][:, r:r + d]
            scale = norm["action_scale"]
            given = (executed - norm["action_offset"]) / jnp.where(scale == 0, 1.0, scale)
            given = jnp.pad(given, ((0, 0), (0, horizon - d), (0, adim - dims)))
            raw = programs.denoise(cfg, model["weights"], sched, cache, state, noise, num_steps=num_steps,
                                   unroll=core.unroll, unroll_steps=False, attention=attention(noise.shape[0]),
                                   committed=given, num_committed=jnp.full((noise.shape[0],), d))
        else:
            raw = programs.denoise(cfg, model["weights"], sched, cache, state, noise, num_steps=num_steps,
                                   unroll=core.unroll, unroll_steps=False, attention=attention(noise.shape[0]))
        if d:
            out["prev"] = ps["chunk"]
        out["chunk"] = raw[..., :dims].astype(jnp.float32) * norm["action_scale"] + norm["action_offset"]
        if conditioned:   # exactly the committed actions (the round trip through model space rounds)
            out["chunk"] = out["chunk"].at[:, :d].set(ps["chunk"][:, r:r + d])
        out["count"] = ps["count"] + 1
        out["plans"] = ps["plans"] + live
        out["recomputed"] = ps["recomputed"] + (live & need)
        return out

    def act(ps, es, k):
        if not d:
            return ps["chunk"][:, k], ps
        return jnp.where(k < d, ps["prev"][:, jnp.minimum(r + k, horizon - 1)], ps["chunk"][:, k]), ps

    def stats(ps) -> dict:
        return {"plans": ps["plans"], "prefix_recomputed": ps["recomputed"]}

    return init, plan, act, stats
