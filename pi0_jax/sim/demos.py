"""Demonstrations from the scripted expert: one npz per episode, for training or fine-tuning a policy.

Layout of OUT/:
  meta.json                      suite version, fps, resolution, tasks and prompts, one row per episode file
  episode_000000.npz ...         per step t (observation before action t, as LeRobot datasets pair them):
      agentview (T, H, W, 3) uint8    agent-view camera           (LIBERO `image`, model slot base_0_rgb)
      wrist     (T, H, W, 3) uint8    wrist camera                (LIBERO `wrist_image`, left_wrist_0_rgb)
      state     (T, 8) float32        eef position, axis-angle, gripper (LIBERO's 8-D state)
      actions   (T, 7) float32        EE delta (pos 3, axis-angle 3) + gripper, in [-1, 1]
      prompt    () str                the task's instruction (the same at every step)
      task, init_state, success, length, noise   scalars (noise: the episode's action-noise scale, below)
Episodes stop at the first success (the success step is the last one kept). Failed episodes are dropped unless
`keep_failures`. Episode k of a task starts from its initial state first_init + k, so training demos can avoid the
evaluation's states 0..49 (first_init=50); tasks.init_states makes state i the same whatever their number.

Noise injection (DART, Laskey et al. 2017; `action_noise` > 0): the environment executes the expert's action plus
Gaussian noise on the six motion dims (not the gripper), while the file records the expert's clean action. The
demonstrations then visit states off the expert's own path, labelled with the expert's correction, which is what a
cloned policy needs once its own small errors compound. The noise scale is drawn per episode, uniform in
[0, action_noise], from the episode's (task, initial state) alone, so clean and noisy episodes are mixed and the
files are reproducible; it is stored per episode (`noise`, in the npz and in meta.json).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from pi0_jax.sim import expert as _expert
from pi0_jax.sim import tasks as _tasks
from pi0_jax.sim.batching import episode_plan
from pi0_jax.sim.env import Env
from pi0_jax.sim.render import RenderConfig

FPS = 20


_MOTION = jnp.array([1.0] * 6 + [0.0])   # noise on translation and rotation, never on the gripper


def _segment(env: Env, steps: int, pos_gain: float):
    """Jitted (state, expert state, keys, noise scale) -> next carry and per-step records of `steps` steps,
    batched. The executed action is the expert's plus N(0, sigma^2) on the motion dims; the record is the expert's."""
    def one(carry, _):
        state, es, keys, sigma = carry
        obs = jax.vmap(env.observe)(state)
        action, es = jax.vmap(lambda s, e: _expert.act(env, s, e, pos_gain))(state, es)
        split = jax.vmap(jax.random.split)(keys)
        noise = jax.vmap(lambda k: jax.random.normal(k, (7,)))(split[:, 1]) * sigma[:, None] * _MOTION
        nxt = jax.vmap(env.step)(state, jnp.clip(action + noise, -1.0, 1.0))
        rec = {"agentview": obs["agentview"], "wrist": obs["wrist"], "state": obs["state"], "actions": action}
        return (nxt, es, split[:, 0], sigma), rec

    return jax.jit(lambda *carry: jax.lax.scan(one, carry, None, length=steps))


def write_demos(out_dir: str | Path, suite: str = "all", episodes_per_task: int = 50, batch: int = 32,
                resolution: int = 224, keep_failures: bool = False, segment_steps: int = 40, log=print,
                first_init: int = 0, compress: bool = True, action_noise: float = 0.0,
                pos_gain: float = _expert.POS_GAIN) -> dict:
    """Roll the expert out on initial states first_init .. first_init + episodes_per_task - 1 of every task of
    `suite`; returns meta.json. compress=False writes plain npz (np.savez): compressing gigabytes of frames takes
    longer than rendering them on a GPU. action_noise: the largest per-episode noise scale (module docstring).
    pos_gain: the expert's position gain (`expert.gains`)."""
    if first_init < 0 or episodes_per_task <= 0:
        raise ValueError(f"need first_init >= 0 and episodes_per_task > 0, got {first_init}, {episodes_per_task}")
    if not 0.0 <= action_noise <= 1.0:
        raise ValueError(f"action_noise must be in [0, 1] (action units), got {action_noise}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    names = tuple(t.name for t in _tasks.suite_tasks(suite))
    env = Env(names, RenderConfig(resolution, resolution), num_init_states=first_init + episodes_per_task)
    task_of, init_of = episode_plan(names, episodes_per_task, episodes_per_task)
    init_of = init_of + np.int32(first_init)
    save = np.savez_compressed if compress else np.savez
    reset = jax.jit(jax.vmap(env.reset))
    segment = _segment(env, segment_steps, pos_gain)
    rows, n_written = [], 0
    for start in range(0, len(task_of), batch):
        t_ids, i_ids = task_of[start:start + batch], init_of[start:start + batch]
        n = len(t_ids)
        t_pad, i_pad = np.pad(t_ids, (0, batch - n)), np.pad(i_ids, (0, batch - n))   # one compiled shape
        # (task, init) fix the episode: the expert and the physics are deterministic, and the noise comes from
        # key(task, init) (reset's key is unused when both are given)
        keys = jax.vmap(lambda t, i: jax.random.fold_in(jax.random.fold_in(jax.random.key(0), t), i))(
            jnp.asarray(t_pad), jnp.asarray(i_pad))
        split = jax.vmap(jax.random.split)(keys)
        sigma = action_noise * jax.vmap(jax.random.uniform)(split[:, 1])
        state = reset(keys, jnp.asarray(t_pad), jnp.asarray(i_pad))
        carry = (state, jax.tree.map(lambda x: jnp.broadcast_to(x, (batch,) + x.shape), _expert.init()),
                 split[:, 0], sigma)
        recs = []
        for _ in range(math.ceil(int(env.max_steps.max()) / segment_steps)):
            carry, rec = segment(*carry)
            recs.append(jax.device_get(rec))
            if bool(np.asarray(carry[0].done)[:n].all()):
                break
        rec = {k: np.concatenate([r[k] for r in recs]) for k in recs[0]}      # (T, batch, ...)
        success, length = np.asarray(carry[0].success), np.asarray(carry[0].length)
        sigma_host = np.asarray(sigma)
        for j in range(n):
            if not (success[j] or keep_failures):
                continue
            t = int(length[j])
            task = env.tasks[t_ids[j]]
            path = out / f"episode_{n_written:06d}.npz"
            save(path, agentview=rec["agentview"][:t, j], wrist=rec["wrist"][:t, j],
                 state=rec["state"][:t, j].astype(np.float32), actions=rec["actions"][:t, j].astype(np.float32),
                 prompt=np.array(task.prompt), task=np.array(task.name), init_state=np.int32(i_ids[j]),
                 success=np.bool_(success[j]), length=np.int32(t), noise=np.float32(sigma_host[j]))
            rows.append({"file": path.name, "task": task.name, "prompt": task.prompt, "init_state": int(i_ids[j]),
                         "success": bool(success[j]), "length": t, "noise": round(float(sigma_host[j]), 4)})
            n_written += 1
        log(f"{min(start + batch, len(task_of))}/{len(task_of)} episodes rolled out, {n_written} written")
    meta = {"format": "pi0_jax.sim demos v1", "suite": suite, "suite_version": _tasks.SUITE_VERSION, "fps": FPS,
            "resolution": resolution, "first_init": first_init, "action_noise": action_noise,
            "expert_gains": list(_expert.gains(pos_gain)),
            "state": "eef pos (3), axis-angle (3), gripper (left, -right)",
            "actions": "EE delta pos (3) x 0.05 m, axis-angle (3) x 0.5 rad, gripper (-1 open, +1 closed)",
            "tasks": [{"task": t.name, "family": t.family, "prompt": t.prompt} for t in env.tasks],
            "episodes": rows}
    (out / "meta.json").write_text(json.dumps(meta, indent=2) + "\n")
    return meta
