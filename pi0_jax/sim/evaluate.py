"""Batched, sharded evaluation: N environments vmapped, sharded over every device (all hosts), scanned on device.

Layout of one evaluation:
  episodes   K per task, ordered init-major (episode e = task e % T, initial state (e // T) % 50), so a batch
             mixes tasks. Episode e's randomness (policy noise) comes from fold_in(key(seed), e) only, so results do
             not depend on batch size or device count.
  batch      N environment slots as one global jax.Array per field, sharded on a 1-D mesh ("batch") over
             jax.devices(): the same code runs on one CPU, k GPUs, or several hosts (jax.distributed), with no
             collectives inside the rollout (every environment is independent). Slots start episodes 0 .. N-1
             (beyond the suite: masked dummies, to a multiple of the device count); between segments, each slot
             whose episode has ended starts the next one, so the batch stays full until the suite runs out.
  segment    one jitted call: `segment_replans` x [policy.plan on the current observation (in chunks of
             `plan_chunk` environments per device), then lax.scan of `replan_steps` x (policy.act, env.step)]. The
             host loops over segments until every episode is done (first success or step limit), recording finished
             episodes and updating the progress bar in between.
  videos     the first `videos` slots also render both cameras after every step while their first episodes run
             (no other episode enters them meanwhile); agent view and wrist view are written side by side as MP4
             (20 fps).

Results (eval_info.json) follow LeRobot's eval_info: per_episode, per_task, per_group (family), aggregated
{pc_success, eval_s, eval_ep_s, ...}, video_paths; plus the config and timings (compile vs rollout).
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import json
import math
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from pi0_jax.ops import matmul
from pi0_jax.sim import tasks as _tasks
from pi0_jax.sim.batching import (auto_ray_chunk, balanced_batch, barrier, collectives, episode_plan, every_process,
                                   fetch, free_device_bytes, program_bytes)
from pi0_jax.sim.env import Env
from pi0_jax.sim.policies import SimPolicy, chunked_plan, make_policy
from pi0_jax.sim.render import RenderConfig, write_video


AUTO_MAX_PER_DEVICE = 1024      # --batch auto: the largest batch tried, per device
AUTO_MEMORY_FRACTION = 0.85     # ... and the share of the free device memory its segment program may take
AUTO_MIN_PLAN_CHUNK = 128       # ... the policy's chunk halved down to this before the batch is


@dataclasses.dataclass(frozen=True)
class EvalConfig:
    suite: str = "all"
    episodes_per_task: int = 10
    batch: int | str = 32             # or "auto": the largest that fits (AUTO_*, the compile loop in evaluate)
    plan_chunk: int | None = None     # the policy plans at most this many environments per device at a time
    replan_steps: int = 5
    max_steps: int | None = None      # None: each task's own limit (LIBERO's 220 / 280 / 300)
    resolution: int = 224
    seed: int = 0
    videos: int = 4
    segment_replans: int = 8
    num_steps: int = 10               # flow-matching steps of a checkpoint policy
    # Model policies in time (pi0_jax/sim/realtime.py): sync | naive | rtc | conditioned, the delay D in control
    # steps (50 ms each), prefix reuse None | "K" | "auto:THRESH", rtc's guidance clip β.
    execution: str = "sync"
    latency_steps: int = 0
    reuse_prefix: str | None = None
    rtc_beta: float = 5.0


@struct.dataclass
class Carry:
    state: object                     # env State, batched
    pstate: object
    keys: jax.Array                   # (N,) per-episode PRNG keys


def segment_replans(cfg: EvalConfig, env: Env) -> int:
    """Plans per segment: cfg.segment_replans, but no more than the longest episode needs."""
    return max(1, min(cfg.segment_replans, math.ceil(int(env.max_steps.max()) / cfg.replan_steps)))


def make_segment(env: Env, policy: SimPolicy, cfg: EvalConfig, n_video: int, mesh: Mesh | None = None):
    """A jitted (params, carry) -> (carry, frames, frame_done) running `segment_replans(cfg, env)` plans.

    mesh: the 1-D "batch" mesh the carry is sharded on (every leaf batch-first). The output carry is pinned to its
    batch sharding, since it goes back into the same ahead-compiled program, which takes only the shardings it was
    compiled for; unpinned, the partitioner replicates MJX's zero-size `Data` fields. (A `shard_map` segment, with no
    collectives at all, crashed XLA's GPU compiler on two H200s with jax 0.11.2; see docs/BENCHMARKS.md.)"""
    r, n_replans = cfg.replan_steps, segment_replans(cfg, env)
    plan = chunked_plan(policy.plan, cfg.plan_chunk, 1 if mesh is None else mesh.size,
                        None if mesh is None else NamedSharding(mesh, P(None, "batch")))

    def observe(state, images: bool):
        if images:
            return jax.vmap(env.observe)(state)
        return {"state": jax.vmap(lambda s: env.robot_state(s.data))(state)}

    def replan(params, carry: Carry, _):
        split = jax.vmap(jax.random.split)(carry.keys)
        keys, sub = split[:, 0], split[:, 1]
        ps = plan(params, carry.pstate, observe(carry.state, policy.needs_images), carry.state, sub)

        def inner(c, k):
            state, ps = c
            action, ps = policy.act(ps, state, k)
            state = jax.vmap(env.step)(state, action)
            frames = done = None
            if n_video:
                head = jax.tree.map(lambda x: x[:n_video], state)
                obs = jax.vmap(env.observe)(head)
                frames, done = jnp.concatenate([obs["agentview"], obs["wrist"]], axis=2), head.done
            return (state, ps), (frames, done)

        (state, ps), out = jax.lax.scan(inner, (carry.state, ps), jnp.arange(r))
        return Carry(state=state, pstate=ps, keys=keys), out

    def segment(params, carry):
        carry, (frames, done) = jax.lax.scan(lambda c, x: replan(params, c, x), carry, None, length=n_replans)
        if n_video:   # (replans, r, V, ...) -> (steps, V, ...)
            frames, done = (x.reshape((-1,) + x.shape[2:]) for x in (frames, done))
        return carry, frames, done

    if mesh is None:
        return jax.jit(segment, donate_argnums=1)
    return jax.jit(segment, donate_argnums=1, out_shardings=(NamedSharding(mesh, P("batch")), None, None))


def evaluate(policy_spec, cfg: EvalConfig, output_dir: str | Path | None = None, *, progress: bool = True,
             policy_kwargs: dict | None = None, profile: bool = False) -> dict:
    """Run the evaluation; returns eval_info (also written to output_dir/eval_info.json with videos).

    policy_spec: 'expert', 'random', 'preset:NAME', a checkpoint directory, or a callable env -> SimPolicy.
    profile: also time physics, rendering and the policy apart (`profile_phases`), into eval_info's timing."""
    t_start = time.perf_counter()
    names = _tasks.suite_tasks(cfg.suite)
    names = tuple(t.name for t in names)
    devices = jax.devices()
    n_dev, n_local = len(devices), len(jax.local_devices())
    n_episodes = len(names) * cfg.episodes_per_task
    auto = cfg.batch == "auto"
    if not auto and (not isinstance(cfg.batch, int) or cfg.batch < 1):
        raise ValueError(f"batch {cfg.batch!r}: a positive number of environments or 'auto'")
    if cfg.plan_chunk is not None and cfg.plan_chunk < 1:
        raise ValueError(f"plan_chunk {cfg.plan_chunk}: a positive number of environments per device, or None")
    batch = (balanced_batch(n_episodes, AUTO_MAX_PER_DEVICE * n_dev, n_dev) if auto
             else math.ceil(min(cfg.batch, n_episodes) / n_dev) * n_dev)      # a multiple of the device count
    mesh = Mesh(np.array(devices), ("batch",))
    shard, repl = NamedSharding(mesh, P("batch")), NamedSharding(mesh, P())

    def make_env(batch: int) -> Env:
        render_cfg = RenderConfig(cfg.resolution, cfg.resolution,
                                  auto_ray_chunk(cfg.resolution, cfg.resolution, batch // n_dev))
        return Env(names, render_cfg, max_steps=cfg.max_steps)

    env = make_env(batch)
    from pi0_jax.sim.realtime import Realtime

    realtime = Realtime(cfg.execution, cfg.latency_steps, cfg.reuse_prefix, cfg.rtc_beta)
    if callable(policy_spec):
        policy = policy_spec(env)
        have = policy.info.get("realtime", Realtime().describe())
        keys = ("execution", "latency_steps", "reuse_prefix") + (("rtc_beta",) if cfg.execution == "rtc" else ())
        if {k: have.get(k) for k in keys} != {k: getattr(realtime, k) for k in keys}:
            raise ValueError(f"the policy's realtime settings {have} differ from the EvalConfig's {realtime}")
    elif policy_spec in ("expert", "random"):
        if not realtime.is_default:
            raise ValueError("--execution, --latency-steps and --reuse-prefix apply to model policies only")
        policy = make_policy(policy_spec, env, cfg.replan_steps)
    else:
        kw = {"num_steps": cfg.num_steps, "realtime": realtime, **(policy_kwargs or {})}
        policy = make_policy(policy_spec, env, cfg.replan_steps, **kw)
    if policy.horizon is not None and cfg.replan_steps > policy.horizon:
        raise ValueError(f"replan_steps {cfg.replan_steps} > the policy's action horizon {policy.horizon}")

    task_of, init_of = episode_plan(names, cfg.episodes_per_task, env.num_init_states)
    n_ep = len(task_of)
    steps_per_segment = segment_replans(cfg, env) * cfg.replan_steps
    base_key = jax.random.key(cfg.seed)

    def global_array(host, sharding=shard):
        """Every process holds the same host value; each device takes its slice (works across hosts too)."""
        host = np.asarray(host)
        return jax.make_array_from_callback(host.shape, sharding, lambda idx: host[idx])

    params = jax.tree.map(lambda x: global_array(x, repl), policy.params)
    ep_keys = jax.jit(lambda e: jax.vmap(lambda i: jax.random.fold_in(base_key, i))(e), out_shardings=shard)
    bar = None
    if progress and jax.process_index() == 0:   # up before the compile, which takes 30-60 s on a GPU
        from tqdm import tqdm
        bar = tqdm(total=n_ep, unit="ep", desc=f"eval {cfg.suite}: compiling", dynamic_ncols=True)
    t_compile = time.perf_counter()
    tried, chunk, carry0, shrank = [], cfg.plan_chunk, None, None
    # The segment compiled ahead; --batch auto halves the plan's chunk (while that shrinks it), then the batch, to fit
    while True:
        if carry0 is None:    # a new batch
            n_video = min(cfg.videos, batch) if output_dir is not None else 0
            reset = jax.jit(lambda keys, t, i, env=env: jax.vmap(env.reset)(keys, t, i), out_shardings=shard)
            init_pstate = jax.jit(lambda b=batch: policy.init(b), out_shardings=shard)

            def fresh_carry(eps: np.ndarray) -> Carry:
                """Slot k at the start of episode eps[k] (past the suite: a dummy, in the last episode's state)."""
                keys, e = ep_keys(global_array(eps.astype(np.int32))), np.minimum(eps, n_ep - 1)
                state = reset(keys, global_array(task_of[e]), global_array(init_of[e]))
                return Carry(state=state, pstate=init_pstate(), keys=keys)

            # The segment compiles in a thread while the first batch's reset compiles and runs (XLA's compiler
            # drops the GIL), from the carry's shapes: every leaf batch-first under the batch sharding, as carry0's.
            keys_spec, ints_spec = (jax.ShapeDtypeStruct((batch,), t) for t in (base_key.dtype, jnp.int32))
            carry_spec = jax.tree.map(
                lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=shard, weak_type=x.weak_type),
                jax.eval_shape(lambda keys, t, i: Carry(
                    state=jax.vmap(env.reset)(keys, t, i), pstate=policy.init(batch), keys=keys),
                    keys_spec, ints_spec, ints_spec))
        run_cfg = dataclasses.replace(cfg, plan_chunk=chunk)

        def compile_segment():
            t0 = time.perf_counter()
            exe = make_segment(env, policy, run_cfg, n_video, mesh).lower(params, carry_spec).compile(
                matmul.compiler_options(params, policy.info.get("gemm", "xla")))
            return exe, time.perf_counter() - t0

        with concurrent.futures.ThreadPoolExecutor(1) as pool:
            compiling = pool.submit(compile_segment)
            carry0 = fresh_carry(np.arange(batch)) if carry0 is None else carry0
            segment, seconds = compiling.result()
        need, free = program_bytes(segment), free_device_bytes(jax.local_devices()[0])
        tried.append({"batch": batch, "plan_chunk": chunk, "program_bytes": need, "free_bytes": free,
                      "compile_s": seconds})
        if not auto or batch <= n_dev:
            break
        fits = need is None or free is None or need <= AUTO_MEMORY_FRACTION * free
        if every_process(fits, f"pi0_jax.sim.evaluate: batch {batch} (plan chunk {chunk}) fits"):
            break
        del segment
        local = min(chunk or batch // n_dev, batch // n_dev)
        if local > AUTO_MIN_PLAN_CHUNK and (shrank is None or need < 0.75 * shrank):
            chunk, shrank = -(-local // 2), need
        else:
            carry0, shrank = None, None
            batch = balanced_batch(n_episodes, batch // 2, n_dev)
            env = make_env(batch)
    n_batches = math.ceil(n_ep / batch)
    success, length = np.zeros(n_ep, bool), np.zeros(n_ep, np.int32)
    policy_stats: dict[str, int] = {}
    video_frames, video_done = [], []
    compile_s, wait_s, done_count = 0.0, 0.0, 0
    if bar is not None:
        bar.set_description(f"eval {cfg.suite}")
    # Slots: environment k runs episode slot_ep[k] (>= n_ep: a padding dummy, never recorded). After each segment,
    # finished episodes are recorded and their slots start the next episodes (the video slots once their videos
    # end), so the batch stays full until the suite runs out. Each episode starts from its own key and state.
    slot_ep, next_ep = np.arange(batch), batch
    running = slot_ep < n_ep
    merge = jax.jit(lambda mask, new, old: jax.tree.map(
        lambda a, b: jnp.where(mask.reshape(mask.shape + (1,) * (b.ndim - 1)), a, b), new, old),
        donate_argnums=2, out_shardings=shard)
    carry, t_roll, s, filming = carry0, t_compile, 0, bool(n_video)
    while True:
        t0 = time.perf_counter()
        carry, frames, fdone = segment(params, carry)
        if s == 0:
            barrier("pi0_jax.sim.evaluate: compiled")
        done = fetch(carry.state.done)
        if s == 0:
            compile_s = time.perf_counter() - t_compile
        else:
            wait_s += time.perf_counter() - t0
        if filming:    # the first n_video slots' first episodes, which no other episode replaces until they end
            video_frames.append(fetch(frames))
            video_done.append(fetch(fdone))
            filming = not done[:n_video].all()
        finished = running & done
        if finished.any():
            ok, steps = fetch(carry.state.success), fetch(carry.state.length)
            success[slot_ep[finished]], length[slot_ep[finished]] = ok[finished], steps[finished]
            done_count += int(finished.sum())
            if policy.stats is not None:
                for k, v in policy.stats(carry.pstate).items():
                    policy_stats[k] = policy_stats.get(k, 0) + int(fetch(v)[finished].sum())
            running &= ~finished
            if bar is not None:
                bar.update(int(finished.sum()))
                # episodes/min after the first segment (eval_info's episodes_per_min_after_compile): none before
                after = time.perf_counter() - t_roll - compile_s
                per_min = f", {60.0 * done_count / after:.0f} ep/min" if s else ""
                bar.set_postfix_str(f"success {100 * success.sum() / done_count:.1f}% of {done_count}{per_min}")
        free = np.flatnonzero(~running & (np.arange(batch) >= (n_video if filming else 0)))[: max(n_ep - next_ep, 0)]
        if free.size:
            slot_ep[free] = np.arange(next_ep, next_ep + free.size)
            next_ep += free.size
            running[free] = True
            carry = merge(global_array(np.isin(np.arange(batch), free)), fresh_carry(slot_ep), carry)
        if not running.any():
            break
        s += 1
    if bar is not None:
        bar.close()
    rollout_s = time.perf_counter() - t_roll
    eval_s = time.perf_counter() - t_start

    info = _eval_info(env, run_cfg, policy, task_of, init_of, success, length, eval_s, rollout_s, compile_s, batch,
                      n_dev, n_local)
    if auto:
        info["config"]["batch_auto"] = {"tried": tried, "max_per_device": AUTO_MAX_PER_DEVICE,
                                        "memory_fraction": AUTO_MEMORY_FRACTION}
    info["timing"] = timing_section(info, rollout_s, compile_s, wait_s, n_batches, steps_per_segment, cfg)
    # before the rollout: the policy's build (weights, FP8 calibration and quantisation) and the environments'
    info["timing"].update(setup_s=t_compile - t_start, policy_setup_s=policy.setup_s)
    # segments run, and episodes begun in freed slots
    info["timing"].update(segments=s + 1, refilled_episodes=next_ep - batch)
    info["timing"]["segment_collectives"] = collectives(segment.as_text()) if n_dev > 1 else 0   # (text: MBs)
    if "realtime" in policy.info:
        info["realtime"] = {**policy.info["realtime"], **policy_stats}
        if policy_stats.get("plans"):
            info["realtime"]["prefix_recompute_fraction"] = policy_stats["prefix_recomputed"] / policy_stats["plans"]
    if profile:
        state = fresh_carry(np.arange(batch)).state
        info["timing"]["phases"] = profile_phases(env, policy, run_cfg, params, state, batch)
    if output_dir is not None and jax.process_index() == 0:
        out = Path(output_dir)
        out.mkdir(parents=True, exist_ok=True)
        paths = []
        if n_video:
            frames, fdone = np.concatenate(video_frames), np.concatenate(video_done)
            (out / "videos").mkdir(exist_ok=True)
            for v in range(min(n_video, n_ep)):
                stop = int(np.argmax(fdone[:, v])) + 1 if fdone[:, v].any() else len(frames)
                p = out / "videos" / f"episode_{v:04d}_{names[task_of[v]].replace('/', '__')}.mp4"
                write_video(p, frames[: min(stop + 10, len(frames)), v])   # 0.5 s past the end
                paths.append(str(p))
        info["video_paths"] = paths
        (out / "eval_info.json").write_text(json.dumps(info, indent=2) + "\n")
    return info


def timing_section(info, rollout_s, compile_s, wait_s, n_batches, steps_per_segment, cfg) -> dict:
    """Where the wall time went. device_wait_s: the host blocked on segments after the first (whose time, compile
    included, is first_segment_s); host_s: the rest of the rollout (resets, fetches, videos, the progress bar);
    batches: episodes over environment slots, rounded up (slots take the next episode as soon as theirs ends)."""
    a = info["aggregated"]
    run_s = max(rollout_s - compile_s, 1e-9)
    return {"first_segment_s": compile_s, "rollout_s": rollout_s, "device_wait_s": wait_s,
            "host_s": max(run_s - wait_s, 0.0), "episodes_per_min": 60.0 * a["n_episodes"] / max(rollout_s, 1e-9),
            "episodes_per_min_after_compile": 60.0 * a["n_episodes"] / run_s,
            "env_steps_per_s": a["env_steps"] / max(rollout_s, 1e-9), "batches": n_batches,
            "steps_per_segment": steps_per_segment, "replan_steps": cfg.replan_steps}


def profile_phases(env: Env, policy: SimPolicy, cfg: EvalConfig, params, state, batch: int, reps: int = 3) -> dict:
    """Physics, rendering and the policy of one replan cycle, each jitted and timed apart on a batch of `batch`
    environments (ms, median of `reps` after a warm-up): the sum approximates one cycle of the fused segment."""
    r = cfg.replan_steps

    def physics(state):
        zero = jnp.zeros((state.done.shape[0], 7))
        return jax.lax.scan(lambda st, _: (jax.vmap(env.step)(st, zero), None), state, None, length=r)[0]

    def render(state):
        return jax.vmap(env.observe)(state)

    def plan(params, state, obs):
        keys = jax.random.split(jax.random.key(0), batch)
        return chunked_plan(policy.plan, cfg.plan_chunk, jax.device_count())(params, policy.init(batch), obs, state,
                                                                               keys)

    def timed(fn, *args) -> float:
        jax.block_until_ready(fn(*args))
        times = []
        for _ in range(reps):
            t0 = time.perf_counter()
            jax.block_until_ready(fn(*args))
            times.append(1e3 * (time.perf_counter() - t0))
        return float(np.median(times))

    out = {"batch": batch, "physics_ms": timed(jax.jit(physics), state)}
    if policy.needs_images:
        obs = jax.jit(render)(state)
        out["render_ms"] = timed(jax.jit(render), state)
    else:
        obs = {"state": jax.vmap(lambda s: env.robot_state(s.data))(state)}
    out["policy_ms"] = timed(jax.jit(plan), params, state, obs)
    cycle = sum(v for k, v in out.items() if k.endswith("_ms"))
    out["share"] = {k[:-3]: v / cycle for k, v in out.items() if k.endswith("_ms")} if cycle else {}
    return out


def _eval_info(env, cfg, policy, task_of, init_of, success, length, eval_s, rollout_s, compile_s, batch, n_dev,
               n_local) -> dict:
    tasks = env.tasks
    per_episode = [{"episode_ix": int(e), "task": tasks[t].name, "task_index": int(t), "family": tasks[t].family,
                    "init_state": int(i), "success": bool(s), "sum_reward": float(s), "max_reward": float(s),
                    "length": int(n), "max_steps": int(env.max_steps[t]), "seed": cfg.seed}
                   for e, (t, i, s, n) in enumerate(zip(task_of, init_of, success, length))]

    def summary(mask) -> dict:
        n = int(mask.sum())
        return {"n_episodes": n, "n_success": int(success[mask].sum()),
                "pc_success": float(100 * success[mask].mean()) if n else float("nan"),
                "avg_length": float(length[mask].mean()) if n else float("nan")}

    per_task = [{"task": t.name, "family": t.family, "prompt": t.prompt, **summary(task_of == k)}
                for k, t in enumerate(tasks)]
    families = sorted({t.family for t in tasks}, key=[t.family for t in tasks].index)
    fam_of = np.array([tasks[t].family for t in task_of])
    per_group = [{"group": f, **summary(fam_of == f)} for f in families]
    n_ep = len(task_of)
    return {
        "per_episode": per_episode, "per_task": per_task, "per_group": per_group,
        "aggregated": {**summary(np.ones(n_ep, bool)), "eval_s": eval_s, "eval_ep_s": eval_s / max(n_ep, 1),
                       "rollout_s": rollout_s, "first_segment_s": compile_s,
                       "env_steps": int(length.sum())},
        "config": {**dataclasses.asdict(cfg), "policy": policy.name, "policy_info": policy.info,
                   "batch_rounded": batch, "suite_version": _tasks.SUITE_VERSION,
                   "devices": n_dev, "local_devices": n_local, "processes": jax.process_count(),
                   "backend": jax.default_backend()},
    }


def format_table(info: dict) -> str:
    """Per-task, per-family and overall success as a markdown table."""
    rows = ["| task | family | episodes | success |", "|---|---|---:|---:|"]
    rows += [f"| {t['task']} | {t['family']} | {t['n_episodes']} | {t['pc_success']:.1f}% |" for t in info["per_task"]]
    rows += [f"| **{g['group']}** | | {g['n_episodes']} | {g['pc_success']:.1f}% |" for g in info["per_group"]]
    a = info["aggregated"]
    rows.append(f"| **overall** | | {a['n_episodes']} | {a['pc_success']:.1f}% |")
    return "\n".join(rows)
