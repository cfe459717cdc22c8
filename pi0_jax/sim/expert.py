"""A scripted pick-and-place expert for every task, from privileged state, in pure JAX (vmap it like the env).

A small state machine per environment, advanced once per control step:

  0 REACH    above the object (10 cm), jaw open, yaw aligned to the nearest face of the block
  1 DESCEND  to grasp height (tool centre point at the block's centre)
  2 CLOSE    close the jaw and wait GRASP_STEPS steps
  3 LIFT     straight up to CARRY_Z (LIFT tasks stay here, holding)
  4 CARRY    over the destination (fixture centre, or the block to stack on)
  5 LOWER    down until the object is RELEASE_GAP above its resting height there
  6 RELEASE  open the jaw and wait RELEASE_STEPS steps
  7 RETREAT  up to RETREAT_Z, jaw open

and recovers: if the object leaves the jaw while lifting, carrying or lowering, or moves while descending, it
restarts from REACH. Motion commands are proportional (position error / POS_SCALE, clipped to MAX_ACTION), so the
actions live in the same [-1, 1] space a learned LIBERO policy outputs.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from pi0_jax.sim import controller, scene, tasks

REACH, DESCEND, CLOSE, LIFT, CARRY, LOWER, RELEASE, RETREAT = range(8)
HOVER = 0.10
CARRY_Z = 0.16
RETREAT_Z = 0.20
RELEASE_GAP = 0.012
GRASP_STEPS = 6
RELEASE_STEPS = 4
MAX_ACTION = 0.8
POS_GAIN = 1.5
ROT_GAIN = 1.0

# the tool frame at home: x = -world x, y = world y (jaw closing axis), z = -world z (pointing down)
_R_HOME = jnp.array([[-1.0, 0, 0], [0, 1, 0], [0, 0, -1]])


@struct.dataclass
class ExpertState:
    phase: jax.Array          # () int32
    count: jax.Array          # () int32, steps spent in a timed phase


def init() -> ExpertState:
    return ExpertState(phase=jnp.zeros((), jnp.int32), count=jnp.zeros((), jnp.int32))


def _rz(yaw):
    c, s = jnp.cos(yaw), jnp.sin(yaw)
    return jnp.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def _wrap_quarter(a):
    """Angle -> the equivalent angle modulo pi/2 in [-pi/4, pi/4) (a cube looks the same every quarter turn)."""
    return (a + jnp.pi / 4) % (jnp.pi / 2) - jnp.pi / 4


def gains(pos_gain: float = POS_GAIN) -> tuple[float, float]:
    """(position, rotation) gains for a position gain; the rotation gain keeps the defaults' ratio."""
    return pos_gain, ROT_GAIN * pos_gain / POS_GAIN


def act(env, state, es: ExpertState, pos_gain: float = POS_GAIN) -> tuple[jax.Array, ExpertState]:
    """One environment's action (7,) and the expert's next state. `env` is a pi0_jax.sim.env.Env. pos_gain scales
    the proportional commands (`gains`): per control step, a gain g moves g times the error (before clipping)."""
    pos_gain, rot_gain = gains(pos_gain)
    d, tb, idx = state.data, env.table, env.index
    kind, obj, target = (jnp.asarray(a)[state.task] for a in (tb.kind, tb.obj, tb.target))
    blocks, fixtures = env.block_pos(d), env.fixture_pos(d)
    p_obj = blocks[obj]
    obj_yaw = controller.yaw_of_quat(d.xquat[jnp.asarray(idx.block_body)][obj])
    tcp = d.site_xpos[idx.tcp_site]
    rot = d.site_xmat[idx.tcp_site].reshape(3, 3)

    # where the object goes: its centre's xy and resting height at the destination
    fix = fixtures[jnp.clip(target, 0, fixtures.shape[0] - 1)]
    half_h = jnp.where(target == scene.FIXTURES.index("bowl"), scene.BOWL_BASE_HALF_H, scene.PLATE_HALF_H)
    other = blocks[jnp.clip(target, 0, blocks.shape[0] - 1)]
    dest_xy = jnp.where(kind == tasks.STACK, other[:2], fix[:2])
    rest_z = jnp.where(kind == tasks.STACK, other[2] + 2 * scene.BLOCK_HALF, fix[2] + 2 * half_h + scene.BLOCK_HALF)

    held = jnp.linalg.norm(p_obj - tcp) < 0.03
    ph, n = es.phase, es.count
    goal = jnp.select(
        [ph == REACH, ph == DESCEND, ph == CLOSE, ph == LIFT, ph == CARRY, ph == LOWER, ph == RELEASE],
        [p_obj + jnp.array([0, 0, HOVER]), p_obj, tcp,
         jnp.concatenate([p_obj[:2], jnp.array([CARRY_Z])]),
         jnp.concatenate([dest_xy, jnp.array([CARRY_Z])]),
         jnp.concatenate([dest_xy, (rest_z + RELEASE_GAP)[None]]), tcp],
        jnp.concatenate([tcp[:2], jnp.array([RETREAT_Z])]))
    err = goal - tcp
    close = (ph >= CLOSE) & (ph <= LOWER)

    # orientation: point down; before the grasp, turn the jaw to the block's nearest face; after, keep the yaw
    tool_yaw = jnp.arctan2(rot[1, 1], rot[0, 1]) - jnp.pi / 2            # heading of the jaw axis (tool y) - 90°
    yaw_goal = jnp.where(ph <= DESCEND, tool_yaw + _wrap_quarter(obj_yaw - tool_yaw), tool_yaw)
    rot_err = controller.rotation_error(_rz(yaw_goal) @ _R_HOME, rot)

    # transitions
    xy_err, z_err = jnp.linalg.norm(err[:2]), jnp.abs(err[2])
    nxt = jnp.select(
        [ph == REACH, ph == DESCEND, ph == CLOSE, ph == LIFT, ph == CARRY, ph == LOWER, ph == RELEASE],
        [jnp.where((xy_err < 0.01) & (z_err < 0.02) & (jnp.linalg.norm(rot_err) < 0.08), DESCEND, REACH),
         jnp.where(jnp.linalg.norm(p_obj[:2] - tcp[:2]) > 0.02, REACH, jnp.where(z_err < 0.006, CLOSE, DESCEND)),
         jnp.where(n + 1 >= GRASP_STEPS, LIFT, CLOSE),
         jnp.where(~held, REACH, jnp.where((kind != tasks.LIFT) & (tcp[2] > CARRY_Z - 0.02), CARRY, LIFT)),
         jnp.where(~held, REACH, jnp.where(xy_err < 0.008, LOWER, CARRY)),
         jnp.where(~held, REACH, jnp.where(z_err < 0.006, RELEASE, LOWER)),
         jnp.where(n + 1 >= RELEASE_STEPS, RETREAT, RELEASE)],
        RETREAT).astype(jnp.int32)
    count = jnp.where(nxt == ph, n + 1, 0).astype(jnp.int32)

    action = jnp.concatenate([
        jnp.clip(pos_gain * err / controller.POS_SCALE, -MAX_ACTION, MAX_ACTION),
        jnp.clip(rot_gain * rot_err / controller.ROT_SCALE, -MAX_ACTION, MAX_ACTION),
        jnp.where(close, 1.0, -1.0)[None]])
    return action, ExpertState(phase=nxt, count=count)
