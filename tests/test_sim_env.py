"""The MJX environment: a smoke test over every registered task, and the scripted expert through `pi0-jax eval`.

Small on purpose (CPU CI: MJX compiles slowly): 32 x 32 cameras, one environment per task, a few steps; the compiled
functions are shared through module-scoped fixtures.
"""

import json

import pi0_jax.sim  # noqa: F401  (XLA flags first)

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pi0_jax import cli
from pi0_jax.sim import tasks
from pi0_jax.sim.env import Env
from pi0_jax.sim.render import RenderConfig

RES = 32


@pytest.fixture(scope="module")
def rollout():
    """Every task's initial state 0, stepped 4 times with small random actions, observed before and after."""
    env = Env(tasks.SUITES["all"], RenderConfig(RES, RES))
    n = len(env.tasks)

    @jax.jit
    def run(actions):
        s0 = jax.vmap(env.reset)(jax.random.split(jax.random.key(0), n), jnp.arange(n), jnp.zeros(n, jnp.int32))
        s = jax.lax.fori_loop(0, actions.shape[0], lambda i, s: jax.vmap(env.step)(s, actions[i]), s0)
        return s0, s, jax.vmap(env.observe)(s0), jax.vmap(env.observe)(s)

    actions = np.random.default_rng(0).uniform(-0.3, 0.3, (4, n, 7)).astype(np.float32)
    actions[..., 6] = -1.0
    still = np.zeros_like(actions)
    still[..., 6] = -1.0
    return env, jax.device_get(run(actions)), jax.device_get(run(still))


def test_every_task_resets_steps_and_renders(rollout):
    env, (s0, s, o0, o), _ = rollout
    n = len(env.tasks)
    for obs in (o0, o):
        assert obs["agentview"].shape == obs["wrist"].shape == (n, RES, RES, 3)
        assert obs["agentview"].dtype == np.uint8
        assert obs["state"].shape == (n, 8) and np.isfinite(obs["state"]).all()
        assert (obs["agentview"].reshape(n, -1).std(1) > 5).all()        # not a blank frame
    assert np.isfinite(s.data.qpos).all() and np.isfinite(s.data.qvel).all()
    assert (s.t == 4).all() and not s0.success.any() and not s.done.any()
    # the 8-D state: tool centre point, axis-angle (pointing down: angle ~ pi), fingers open (+0.04, -0.04)
    np.testing.assert_allclose(o0["state"][:, 6:], np.tile([0.04, -0.04], (n, 1)), atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(o0["state"][:, 3:6], axis=1), np.pi, atol=0.1)
    blocks = np.asarray(s0.data.xpos)[:, np.asarray(env.index.block_body)]
    np.testing.assert_allclose(blocks, env.table.block[np.arange(n), 0, :, :3], atol=1e-6)


def test_zero_action_holds_the_arm_still(rollout):
    env, _, (s0, s, o0, o) = rollout
    drift = np.linalg.norm(o["state"][:, :3] - o0["state"][:, :3], axis=1)
    assert drift.max() < 2e-3, drift                                  # gravity-compensated servos hold the pose
    blocks0 = np.asarray(s0.data.xpos)[:, np.asarray(env.index.block_body)]
    blocks = np.asarray(s.data.xpos)[:, np.asarray(env.index.block_body)]
    assert np.abs(blocks - blocks0).max() < 1e-3                      # objects rest on the table


def test_expert_succeeds_via_eval_cli(tmp_path, capsys):
    """Two episodes of every task with the scripted expert; eval_info.json, videos and the table."""
    out = tmp_path / "eval"
    assert cli.main(["eval", "--policy", "expert", "--suite", "all", "--episodes-per-task", "2", "--batch", "22",
                     "--resolution", str(RES), "--videos", "2", "--output-dir", str(out), "--no-progress"]) == 0
    info = json.loads((out / "eval_info.json").read_text())
    assert info["aggregated"]["n_episodes"] == 22
    assert info["aggregated"]["pc_success"] == 100.0, [e for e in info["per_episode"] if not e["success"]]
    assert {t["task"] for t in info["per_task"]} == set(tasks.SUITES["all"])
    assert all(t["n_episodes"] == 2 for t in info["per_task"])
    assert [g["group"] for g in info["per_group"]] == ["spatial", "object", "goal"]
    for key in ("pc_success", "eval_s", "eval_ep_s"):
        assert key in info["aggregated"]
    ep = info["per_episode"][0]
    assert {"episode_ix", "task", "success", "sum_reward", "max_reward", "seed", "length"} <= set(ep)
    assert all(0 < e["length"] < e["max_steps"] for e in info["per_episode"])
    assert len(info["video_paths"]) == 2
    for p in info["video_paths"]:
        assert p.endswith(".mp4") and (out / "videos").joinpath(p.rsplit("/", 1)[-1]).stat().st_size > 1000
    printed = capsys.readouterr().out
    assert "| **overall** | | 22 | 100.0% |" in printed
