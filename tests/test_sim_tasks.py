"""The task registry, initial states, success predicate, rotation helpers and policy normalisation (no physics)."""

import itertools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from pi0_jax import normalize as nz
from pi0_jax.sim import controller, scene, tasks

# sha256 prefixes of every task's 50 initial states (suite version 1). A change here means the generator changed:
# bump tasks.SUITE_VERSION, since published success rates refer to these exact states.
DIGESTS = {
    "spatial/left_black_block_on_plate": "c55e512399b9",
    "spatial/right_black_block_on_plate": "c25eaf1b5b84",
    "spatial/nearest_black_block_on_plate": "e4d4a29bd9ac",
    "spatial/black_block_by_bowl_on_plate": "623f51daac12",
    "object/red_block_in_bowl": "9f9b2a8313c2",
    "object/green_block_in_bowl": "871df27b82eb",
    "object/blue_block_in_bowl": "3c340072cf98",
    "goal/red_block_on_plate": "5e6f87c5d777",
    "goal/blue_block_in_bowl": "8d0db453d84a",
    "goal/stack_green_on_blue": "eccfcbde5d0c",
    "goal/lift_red_block": "43edbd2b725e",
}


def test_registry():
    assert tasks.SUITE_VERSION == 1
    assert len(tasks.TASKS) >= 8
    families = {t.family for t in tasks.TASKS}
    assert families == {"spatial", "object", "goal"}
    assert len({t.name for t in tasks.TASKS}) == len({t.prompt for t in tasks.TASKS}) == len(tasks.TASKS)
    assert set(tasks.SUITES["all"]) == {t.name for t in tasks.TASKS}
    assert tasks.suite_tasks("goal/lift_red_block")[0].kind == tasks.LIFT
    with pytest.raises(KeyError):
        tasks.suite_tasks("libero_90")


@pytest.mark.parametrize("name", sorted(DIGESTS))
def test_init_states_are_fixed_and_valid(name):
    task = tasks.get_task(name)
    lay = tasks.init_states(name)
    assert lay.block.shape == (50, 5, 4) and lay.fixture.shape == (50, 2, 3) and lay.arm_q.shape == (50, 7)
    assert tasks.init_states_digest(name).startswith(DIGESTS[name])
    head = tasks.init_states(name, 5)                        # state i does not depend on how many are drawn
    np.testing.assert_array_equal(head.block, lay.block[:5])
    for i in range(50):
        xy = lay.block[i, :, :2]
        assert (xy[:, 0] > 0.3).all() and (xy[:, 0] < 0.65).all() and (np.abs(xy[:, 1]) < 0.28).all()
        for a, b in itertools.combinations(range(5), 2):
            assert np.linalg.norm(xy[a] - xy[b]) >= 0.09      # an open jaw fits between neighbours
        one = tasks.Layout(lay.block[i], lay.fixture[i], lay.arm_q[i])
        assert task.accept(one)                               # the spatial relation named in the prompt holds
    solved = jax.jit(jax.vmap(tasks.success, (None, None, None, 0, 0)), static_argnums=(0, 1, 2))(
        task.kind, task.obj_index, task.target_index, jnp.asarray(lay.block[..., :3]), jnp.asarray(lay.fixture))
    assert not np.asarray(solved).any()                       # nothing starts out solved


def test_success_predicate():
    blocks = np.array([[0.4, 0.0, 0.02], [0.5, 0.1, 0.02], [0.4, -0.2, 0.02], [0.6, 0.2, 0.02], [0.3, 0.2, 0.02]])
    fixtures = np.array([[0.55, -0.15, 0.0], [0.45, 0.2, 0.0]])       # bowl, plate
    bowl, plate = scene.FIXTURES.index("bowl"), scene.FIXTURES.index("plate")

    def ok(kind, obj, target, b):
        return bool(tasks.success(kind, obj, target, jnp.asarray(b), jnp.asarray(fixtures)))

    on_plate = blocks.copy()
    on_plate[2] = [0.46, 0.21, 2 * scene.PLATE_HALF_H + scene.BLOCK_HALF]
    assert ok(tasks.PLACE, 2, plate, on_plate) and not ok(tasks.PLACE, 2, bowl, on_plate)
    assert not ok(tasks.PLACE, 2, plate, blocks)
    hovering = on_plate.copy()
    hovering[2, 2] += 0.05
    assert not ok(tasks.PLACE, 2, plate, hovering)
    in_bowl = blocks.copy()
    in_bowl[3] = [0.56, -0.16, 2 * scene.BOWL_BASE_HALF_H + scene.BLOCK_HALF]
    assert ok(tasks.PLACE, 3, bowl, in_bowl)
    stacked = blocks.copy()
    stacked[3] = blocks[2] + [0.005, 0.0, 0.04]
    assert ok(tasks.STACK, 3, 2, stacked) and not ok(tasks.STACK, 3, 1, stacked)
    lifted = blocks.copy()
    lifted[2, 2] = 0.15
    assert ok(tasks.LIFT, 2, 0, lifted) and not ok(tasks.LIFT, 2, 0, blocks)


def test_rotation_helpers_match_mujoco():
    rng = np.random.default_rng(0)
    vecs = rng.normal(size=(64, 3))
    vecs = vecs / np.linalg.norm(vecs, axis=1, keepdims=True) * rng.uniform(0, np.pi, (64, 1))
    vecs[:4] = [[np.pi, 0, 0], [0, np.pi - 1e-6, 0], [0, 0, 0], [1e-7, 0, 0]]   # near pi and near zero
    for w in vecs:
        quat = np.zeros(4)
        mujoco.mju_axisAngle2Quat(quat, w / max(np.linalg.norm(w), 1e-12), np.linalg.norm(w))
        mat = np.zeros(9)
        mujoco.mju_quat2Mat(mat, quat)
        np.testing.assert_allclose(controller.axis_angle_to_mat(jnp.asarray(w)), mat.reshape(3, 3), atol=1e-5)
        q = np.asarray(controller.mat_to_quat(jnp.asarray(mat.reshape(3, 3))))
        assert abs(abs(q @ quat) - 1) < 1e-5                   # same rotation (up to sign)
        back = np.asarray(controller.mat_to_axis_angle(jnp.asarray(mat.reshape(3, 3))))
        if np.linalg.norm(w) < np.pi - 1e-3:                  # at pi, w and -w are the same rotation
            np.testing.assert_allclose(back, w, atol=2e-4)


def test_dls_step_moves_along_the_twist():
    rng = np.random.default_rng(1)
    jac = jnp.asarray(rng.normal(size=(6, 7)))
    twist = jnp.asarray(rng.normal(size=6) * 0.01)
    q = jnp.zeros(7)
    dq = controller.dls_step(jac, twist, q, q)
    # damped least squares shrinks each singular direction by s^2 / (s^2 + lambda^2): the error is bounded by that
    s_min = float(np.linalg.svd(np.asarray(jac), compute_uv=False).min())
    bound = controller.DLS_DAMPING**2 / (s_min**2 + controller.DLS_DAMPING**2) * float(jnp.linalg.norm(twist))
    assert float(jnp.linalg.norm(jac @ dq - twist)) <= bound + 1e-6


@pytest.mark.parametrize("convention,mode", [("openpi", "QUANTILES"), ("openpi", "MEAN_STD"),
                                             ("lerobot", "MEAN_STD"), ("lerobot", "QUANTILES"),
                                             ("lerobot", "MIN_MAX")])
def test_affine_normalisation_equals_the_elementwise_functions(convention, mode):
    """The device path's per-dim scale and offset (`Normalizer.affine`) against the host's elementwise normalise /
    unnormalise (which tests/test_normalize.py checks against openpi's and LeRobot's formulas)."""
    rng = np.random.default_rng(2)
    lo, hi = rng.normal(size=7) - 2, rng.normal(size=7) + 2
    stats = nz.NormStats(mean=rng.normal(size=7), std=rng.uniform(0.1, 2, 7), q01=lo, q99=hi, min=lo, max=hi)
    x = rng.normal(size=(16, 7))
    normalizer = nz.Normalizer(stats={"state": stats}, modes={"state": mode}, convention=convention)
    for inverse, fn in ((False, nz.normalize), (True, nz.unnormalize)):
        scale, offset = normalizer.affine("state", 7, inverse=inverse)
        np.testing.assert_allclose(np.asarray(jnp.asarray(x, jnp.float32) * scale + offset),
                                   fn(x, stats, mode, convention), rtol=1e-5, atol=1e-5)


def test_eval_help_explains_every_flag(capsys, cli_options):
    from pi0_jax import cli

    with pytest.raises(SystemExit) as e:
        cli.main(["eval", "--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    flags = ("--policy", "--suite", "--episodes-per-task", "--batch", "--replan-steps", "--steps", "--output-dir",
             "--resolution", "--videos", "--seed", "--coordinator", "--execution", "--latency-steps", "--rtc-beta",
             "--reuse-prefix")
    for flag in flags:
        assert flag in out
    cli_options("eval", flags)     # each flag defined by the parser, every option with help


def test_servos_hold_the_home_pose_and_objects_rest():
    """MuJoCo (C) on the scene: with the servo targets at the initial pose, 1 s later the tool has not sagged (body
    gravity compensation) and the blocks have not moved (they start resting on the table)."""
    model, idx = scene.build()
    data = mujoco.MjData(model)
    lay = tasks.init_states("goal/stack_green_on_blue")
    data.qpos[:7], data.qpos[7:9] = lay.arm_q[0], scene.FINGER_OPEN
    for b, adr in enumerate(idx.block_qpos):
        x, y, z, yaw = lay.block[0, b]
        data.qpos[adr:adr + 7] = [x, y, z, np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)]
    data.mocap_pos[:] = lay.fixture[0]
    data.ctrl[:] = np.concatenate([lay.arm_q[0], [scene.FINGER_OPEN] * 2])
    mujoco.mj_forward(model, data)
    tcp0, blocks0 = data.site_xpos[idx.tcp_site].copy(), data.xpos[list(idx.block_body)].copy()
    for _ in range(round(1.0 / model.opt.timestep)):
        mujoco.mj_step(model, data)
    assert np.linalg.norm(data.site_xpos[idx.tcp_site] - tcp0) < 1e-3
    assert np.abs(data.xpos[list(idx.block_body)] - blocks0).max() < 1e-3
