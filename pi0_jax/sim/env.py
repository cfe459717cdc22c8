"""The environment: pure `reset(rng)` / `step(state, action)` over a struct State, for one environment; `vmap` outside.

    env = Env(tasks.SUITES["all"], RenderConfig(224, 224))
    state = jax.vmap(env.reset)(jax.random.split(rng, n), task_ids, init_ids)
    state = jax.vmap(env.step)(state, actions)                  # actions (n, 7)
    obs = jax.vmap(env.observe)(state)          # {"agentview", "wrist": (n, H, W, 3) uint8, "state": (n, 8)}

One control step is 50 ms (20 Hz): the controller turns the 7-D action into servo targets once, then MJX integrates
`substeps` physics steps. After them the kinematics are refreshed, so positions in the state, the observation and the
success check all belong to the same instant. Each substep is `mjx.step` with its kinematics moved to its end
(`_substep`), so a step's program holds MJX's kinematics once instead of twice. Rendering is separate from stepping
(`observe`), so callers render only when something will look at the images.

Episode bookkeeping follows LIBERO: an episode is done at its first success or at the task's step limit; `success`
latches. Steps after `done` still simulate (batched rollouts keep a fixed shape) but change no bookkeeping.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from pi0_jax.sim import controller, scene, tasks
from pi0_jax.sim.render import RenderConfig, Scene, render


def import_mjx():
    """`mujoco.mjx`, without the "Failed to import warp" lines it prints on machines without the Warp backend."""
    import contextlib
    import io

    with contextlib.redirect_stdout(io.StringIO()):
        from mujoco import mjx
    return mjx


@struct.dataclass
class State:
    data: object              # mjx.Data
    task: jax.Array           # () int32, index into Env.tasks
    init: jax.Array           # () int32, index of the initial state
    t: jax.Array              # () int32, control steps taken
    success: jax.Array        # () bool, succeeded at some step so far (latched)
    done: jax.Array           # () bool, success or t reached the task's step limit (latched)
    length: jax.Array         # () int32, steps until done (== t while running)


class Env:
    """A batch-agnostic environment over the tasks `task_names` (one compiled model serves them all)."""

    def __init__(self, task_names, render_cfg: RenderConfig = RenderConfig(),
                 num_init_states: int = tasks.NUM_INIT_STATES, max_steps: int | None = None):
        import mujoco

        mjx = import_mjx()

        self.task_names = tuple(task_names)
        self.table = tasks.task_table(self.task_names, num_init_states)
        self.tasks = self.table.tasks
        # per-task step limits (LIBERO's), or one override for every task
        self.max_steps = (self.table.max_steps if max_steps is None
                          else np.full(len(self.tasks), max_steps, np.int32))
        self.render_cfg, self.scene_cfg = render_cfg, scene.SceneConfig()
        self.mj_model, self.index = scene.build(self.scene_cfg)
        # on this process's first device: under jax.distributed, jax.devices()[0] may belong to another host
        device = jax.local_devices()[0]
        self.model = mjx.put_model(self.mj_model, device=device)
        self.render_scene = Scene.from_model(self.mj_model)
        with jax.default_device(device):   # one program: MJX's make_data runs 15 eager ops, each compiled apart
            self._data0 = jax.jit(lambda: mjx.make_data(self.model))()
        self._mjx = mjx
        self.num_init_states = num_init_states
        self.q_home = jnp.asarray(scene.home_qpos(), jnp.float32)
        self.q_low = jnp.asarray(self.mj_model.jnt_range[:7, 0], jnp.float32)
        self.q_high = jnp.asarray(self.mj_model.jnt_range[:7, 1], jnp.float32)
        assert self.mj_model.nmocap == len(scene.FIXTURES)  # the fixtures are the only mocap bodies
        assert self.mj_model.opt.integrator == mujoco.mjtIntegrator.mjINT_IMPLICITFAST   # `_substep`'s integrator

    @property
    def prompts(self) -> tuple[str, ...]:
        return tuple(t.prompt for t in self.tasks)

    # --- state construction ---------------------------------------------------------------------------------------

    def _layout_qpos(self, task, init):
        """qpos, mocap_pos and ctrl of initial state `init` of task `task` (traced ints)."""
        idx, tb = self.index, self.table
        blocks = jnp.asarray(tb.block)[task, init]                         # (5, 4) x y z yaw
        yaw = blocks[:, 3]
        quat = jnp.stack([jnp.cos(yaw / 2), jnp.zeros_like(yaw), jnp.zeros_like(yaw), jnp.sin(yaw / 2)], -1)
        arm = jnp.asarray(tb.arm_q)[task, init]
        qpos = self._data0.qpos.at[jnp.asarray(idx.arm_qpos)].set(arm)
        qpos = qpos.at[jnp.asarray(idx.finger_qpos)].set(scene.FINGER_OPEN)
        adr = np.asarray(idx.block_qpos)[:, None] + np.arange(7)[None]
        qpos = qpos.at[adr].set(jnp.concatenate([blocks[:, :3], quat], -1))
        mocap = self._data0.mocap_pos.at[jnp.asarray(idx.fixture_mocap)].set(jnp.asarray(tb.fixture)[task, init])
        ctrl = jnp.concatenate([arm, jnp.full((2,), scene.FINGER_OPEN)])
        return qpos, mocap, ctrl

    def reset(self, rng: jax.Array, task: jax.Array | int | None = None, init: jax.Array | int | None = None) -> State:
        """Initial state `init` of task `task` (indices into self.tasks / its initial states); either one left out
        is drawn from `rng`. Deterministic given (task, init)."""
        k1, k2 = jax.random.split(rng)
        task = jax.random.randint(k1, (), 0, len(self.tasks)) if task is None else jnp.asarray(task, jnp.int32)
        init = jax.random.randint(k2, (), 0, self.num_init_states) if init is None else jnp.asarray(init, jnp.int32)
        qpos, mocap, ctrl = self._layout_qpos(task, init)
        data = self._refresh(self._data0.replace(qpos=qpos, mocap_pos=mocap, ctrl=ctrl))
        z = jnp.zeros((), jnp.int32)
        return State(data=data, task=task, init=init, t=z, success=jnp.zeros((), bool), done=jnp.zeros((), bool),
                     length=z)

    # --- dynamics ---------------------------------------------------------------------------------------------------

    def _refresh(self, d):
        """Positions (bodies, geoms, sites, cameras) and the Jacobian's inputs for the current qpos. mj_step leaves
        them at the start of its last substep, and a reset needs nothing more (the next step runs the full
        pipeline, contacts included), so this is all that a state ever needs between steps."""
        mjx, m = self._mjx, self.model
        return mjx.camlight(m, mjx.com_pos(m, mjx.kinematics(m, d)))

    def _substep(self, d):
        """`mjx.step` on data refreshed for its qpos (`_refresh`), returning data refreshed for the new qpos.

        MuJoCo 3.17's `mjx.step` is `forward` (whose position stage starts with kinematics, centres of mass and
        cameras) and then, for this scene, the implicitfast integrator. Here those three stages run after the
        integrator instead of before the rest: on a refreshed input they would recompute what it holds, and after
        the last substep the state needs them anyway. So the substep loop holds the kinematics (12k of the 36k
        HLO instructions one control step had, docs/BENCHMARKS.md) once. `tests/test_sim_env.py` checks this against
        `mjx.step` and `_refresh`."""
        from mujoco.mjx._src import collision_driver, constraint, forward, sensor, smooth, solver

        m = self.model
        for stage in (smooth.tendon, smooth.crb, smooth.tendon_armature, smooth.factor_m, collision_driver.collision,
                      constraint.make_constraint, smooth.transmission, sensor.sensor_pos, forward.fwd_velocity,
                      sensor.sensor_vel, forward.fwd_actuation, forward.fwd_acceleration):
            d = stage(m, d)
        if d._impl.efc_J.size == 0:
            d = d.replace(qacc=d.qacc_smooth)
        else:
            d = sensor.sensor_acc(m, solver.solve(m, d))
        return self._refresh(forward.implicit(m, d))

    def tcp_jacobian(self, data) -> jax.Array:
        """(6, 7) geometric Jacobian of the tool centre point w.r.t. the arm joints: rows [linear; angular]."""
        jacp, jacr = self._mjx.jac(self.model, data, data.site_xpos[self.index.tcp_site], self.index.hand_body)
        return jnp.concatenate([jacp[:7].T, jacr[:7].T], 0)

    def step(self, state: State, action: jax.Array) -> State:
        """Apply a 7-D action (see controller.py) for one 50 ms control step."""
        d = state.data
        q = d.qpos[:7]
        q_target = controller.arm_targets(self.tcp_jacobian(d), q, self.q_home, action, self.q_low, self.q_high)
        grip = controller.gripper_target(action, scene.FINGER_OPEN)
        d = d.replace(ctrl=jnp.concatenate([q_target, jnp.stack([grip, grip])]))
        d = jax.lax.fori_loop(0, self.scene_cfg.substeps, lambda _, x: self._substep(x), d)
        t = state.t + 1
        ok = state.success | (~state.done & self.success(state.task, d))
        limit = jnp.asarray(self.max_steps)[state.task]
        done = state.done | ok | (t >= limit)
        return state.replace(data=d, t=t, success=ok, done=done, length=jnp.where(state.done, state.length, t))

    # --- observations -----------------------------------------------------------------------------------------------

    def block_pos(self, data) -> jax.Array:
        return data.xpos[jnp.asarray(self.index.block_body)]

    def fixture_pos(self, data) -> jax.Array:
        return data.mocap_pos[jnp.asarray(self.index.fixture_mocap)]

    def success(self, task, data) -> jax.Array:
        tb = self.table
        return tasks.success(jnp.asarray(tb.kind)[task], jnp.asarray(tb.obj)[task], jnp.asarray(tb.target)[task],
                             self.block_pos(data), self.fixture_pos(data))

    def robot_state(self, data) -> jax.Array:
        """LIBERO's 8-D state: tool centre point position (3), its orientation as axis-angle (3), finger joint
        positions (left, -right) as robosuite reports the Panda's (open: (+0.04, -0.04))."""
        i = self.index
        rot = data.site_xmat[i.tcp_site].reshape(3, 3)
        fingers = data.qpos[jnp.asarray(i.finger_qpos)] * jnp.array([1.0, -1.0])
        return jnp.concatenate([data.site_xpos[i.tcp_site], controller.mat_to_axis_angle(rot), fingers])

    def observe(self, state: State, depth: bool = False) -> dict:
        """{"agentview", "wrist": (H, W, 3) uint8, "state": (8,) f32} (+ "depth", "segmentation" (2, H, W))."""
        out = render(self.render_scene, self.render_cfg, state.data, self.index.camera)
        obs = {"agentview": out["rgb"][0], "wrist": out["rgb"][1], "state": self.robot_state(state.data)}
        if depth:
            obs.update(depth=out["depth"], segmentation=out["segmentation"])
        return obs

