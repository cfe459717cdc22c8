"""The MJX environment end to end, kept small for CPU CI (MJX compiles slowly: 32 x 32 cameras, few environments).

* Smoke test over every registered task, through the demonstration writer: one expert episode per task, jitted
  reset / step / observe every step, observation shapes and dtypes, no NaN, the expert succeeds (under DART action
  noise), npz layout, and the recorded actions are the expert's clean ones.
* The scripted expert through `pi0-jax eval`: two episodes of every task, eval_info.json, videos, the table.
"""

import dataclasses
import json

import numpy as np
import pytest

from pi0_jax import cli
from pi0_jax.sim import demos, expert, tasks

RES = 32
NOISE = 0.1


@pytest.fixture(scope="module")
def demo_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("demos")
    n = len(tasks.TASKS)
    demos.write_demos(out, "all", episodes_per_task=1, batch=n, resolution=RES, keep_failures=True, log=lambda _: 0,
                      action_noise=NOISE)
    return out


def test_every_task_steps_renders_and_the_expert_solves_it(demo_dir):
    meta = json.loads((demo_dir / "meta.json").read_text())
    assert meta["fps"] == 20 and meta["suite_version"] == tasks.SUITE_VERSION and meta["action_noise"] == NOISE
    noise = [row["noise"] for row in meta["episodes"]]
    assert all(0 <= s <= NOISE for s in noise) and max(noise) > NOISE / 4, noise   # per-episode scales, recorded
    assert sorted(e["task"] for e in meta["episodes"]) == sorted(tasks.SUITES["all"])
    for row in meta["episodes"]:
        ep = np.load(demo_dir / row["file"])
        t = int(ep["length"])
        assert row["success"] and bool(ep["success"]), row
        assert 0 < t < tasks.get_task(row["task"]).max_steps
        assert str(ep["prompt"]) == tasks.get_task(row["task"]).prompt == row["prompt"]
        assert ep["agentview"].shape == ep["wrist"].shape == (t, RES, RES, 3) and ep["agentview"].dtype == np.uint8
        assert ep["state"].shape == (t, 8) and ep["actions"].shape == (t, 7)
        assert np.isfinite(ep["state"]).all() and np.isfinite(ep["actions"]).all()
        assert np.abs(ep["actions"]).max() <= 1.0
        # the labels are the expert's clean actions (it clips motion at MAX_ACTION); the executed ones were noisy
        assert np.abs(ep["actions"][:, :6]).max() <= expert.MAX_ACTION + 1e-6
        assert abs(float(ep["noise"]) - row["noise"]) < 1e-4        # meta.json rounds to 4 decimals
        assert ep["agentview"][0].std() > 5 and ep["wrist"][0].std() > 5          # not blank frames
        # LIBERO's 8-D state at the start: gripper open (+0.04, -0.04), pointing down (axis-angle norm ~ pi)
        np.testing.assert_allclose(ep["state"][0, 6:], [0.04, -0.04], atol=1e-6)
        assert abs(np.linalg.norm(ep["state"][0, 3:6]) - np.pi) < 0.1
        assert (ep["actions"][:, 6] > 0).any()                                     # it closed the gripper
        assert not np.array_equal(ep["agentview"][0], ep["agentview"][-1])         # the scene changed


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


def test_freed_slots_take_the_next_episodes(tmp_path):
    """With fewer environments than episodes, a finished episode's slot starts the next one (the video slots only
    once their videos end): every episode's result equals the one it gets in a single batch of all episodes."""
    from pi0_jax.sim.evaluate import EvalConfig, evaluate

    cfg = EvalConfig(suite="goal", episodes_per_task=3, max_steps=120, resolution=RES, videos=1)
    whole = evaluate("expert", dataclasses.replace(cfg, batch=1000), tmp_path / "whole", progress=False)
    slots = evaluate("expert", dataclasses.replace(cfg, batch=4), tmp_path / "slots", progress=False)
    n = whole["aggregated"]["n_episodes"]
    assert whole["timing"]["refilled_episodes"] == 0 and slots["timing"]["refilled_episodes"] == n - 4
    assert slots["timing"]["segments"] > whole["timing"]["segments"]
    key = [(e["episode_ix"], e["task"], e["success"], e["length"]) for e in whole["per_episode"]]
    assert [(e["episode_ix"], e["task"], e["success"], e["length"]) for e in slots["per_episode"]] == key
    assert len({e["length"] for e in whole["per_episode"]}) > 1       # episodes end at different steps
    assert len(slots["video_paths"]) == 1


def test_two_devices_with_a_padding_slot(tmp_path):
    """Three episodes on two devices: four slots, the fourth a padding dummy that takes no episode. The results equal
    one device's."""
    import os
    import subprocess
    import sys

    args = ["eval", "--policy", "expert", "--suite", "goal/red_block_on_plate", "--episodes-per-task", "3",
            "--steps", "60", "--resolution", str(RES), "--videos", "0", "--no-progress"]
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "XLA_FLAGS": "--xla_force_host_platform_device_count=2"}
    out = subprocess.run([sys.executable, "-m", "pi0_jax.cli", *args, "--batch", "4", "--output-dir",
                          str(tmp_path / "two")], env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    assert cli.main([*args, "--batch", "3", "--output-dir", str(tmp_path / "one")]) == 0
    two, one = (json.loads((tmp_path / d / "eval_info.json").read_text()) for d in ("two", "one"))
    assert two["config"]["devices"] == 2 and two["config"]["batch_rounded"] == 4
    assert [(e["success"], e["length"]) for e in two["per_episode"]] == [
        (e["success"], e["length"]) for e in one["per_episode"]]


def test_substep_is_mjx_step_with_its_kinematics_last():
    """`Env._substep` (MJX's step with its kinematics, centres of mass and cameras moved to the end) against
    `mjx.step` then `Env._refresh`, 10 substeps from every task's first initial state under new servo targets. The
    arm (in free space) agrees to rounding. The resting blocks agree to 0.1 mm: on ties in the broad phase's 10
    nearest pairs, a rounding difference picks other pairs, and the contact solver's micro-motion follows."""
    import jax
    import jax.numpy as jnp

    from pi0_jax.sim.env import Env

    env = Env(tasks.SUITES["all"])
    n = len(tasks.TASKS)
    state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.key(0), n), jnp.arange(n), jnp.zeros(n, int))
    data = state.data.replace(ctrl=state.data.ctrl + 0.05)

    def reference(d):
        return env._refresh(jax.lax.fori_loop(0, 10, lambda _, x: env._mjx.step(env.model, x), d))

    ref = jax.jit(jax.vmap(reference))(data)
    out = jax.jit(jax.vmap(lambda d: jax.lax.fori_loop(0, 10, lambda _, x: env._substep(x), d)))(data)
    arm = 9   # 7 arm joints, 2 fingers: the first qpos / qvel entries (scene.build asserts the arm comes first)
    np.testing.assert_allclose(out.qpos[:, :arm], ref.qpos[:, :arm], atol=1e-6)
    np.testing.assert_allclose(out.qvel[:, :arm], ref.qvel[:, :arm], atol=1e-5)
    np.testing.assert_allclose(out.qpos, ref.qpos, atol=1e-4)
    np.testing.assert_allclose(out.site_xpos, ref.site_xpos, atol=1e-6)   # refreshed for the new qpos, as _refresh
    np.testing.assert_allclose(out.cam_xpos, ref.cam_xpos, atol=1e-6)
    assert np.abs(np.asarray(out.qvel[:, :arm] - data.qvel[:, :arm])).max() > 1e-2   # the servos did move the arm


def test_the_cpu_flags_are_set_only_where_jax_runs_on_the_cpu():
    """Importing `pi0_jax.sim` (the `pi0-jax` command does, for its parser) appends the XLA:CPU flags MJX needs to
    XLA_FLAGS when JAX will run on the CPU, and leaves XLA_FLAGS alone where a GPU platform comes first: the flags
    are part of every program's cache key, so a GPU `pi0-jax serve` and a script must not differ by them."""
    import os
    import subprocess
    import sys

    code = "import os, pi0_jax.sim; print(os.environ.get('XLA_FLAGS', ''))"
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    cpu = subprocess.run([sys.executable, "-c", code], env={**env, "JAX_PLATFORMS": "cpu"}, capture_output=True,
                         text=True, timeout=120)
    gpu = subprocess.run([sys.executable, "-c", code], env={**env, "JAX_PLATFORMS": "cuda,cpu"},
                         capture_output=True, text=True, timeout=120)
    assert cpu.returncode == 0 and gpu.returncode == 0, cpu.stderr[-2000:] + gpu.stderr[-2000:]
    assert "--xla_cpu_enable_concurrency_optimized_scheduler=false" in cpu.stdout
    assert gpu.stdout.strip() == ""
