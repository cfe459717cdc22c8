"""End-effector delta control, LIBERO-style: a 7-D action in [-1, 1] -> joint position targets.

Action layout (LIBERO / robosuite OSC_POSE): a[0:3] translation of the tool centre point in the world frame, scaled
by POS_SCALE metres per 50 ms control step; a[3:6] a rotation vector (axis-angle) in the world frame, scaled by
ROT_SCALE radians; a[6] the gripper, -1 open ... +1 closed.

The arm has position servos, so the controller turns the pose twist into a joint increment with one damped
least-squares step on MJX's geometric Jacobian at the current configuration,
    dq = J^T (J J^T + lambda^2 I)^-1 [dp; dw] + (I - J^+ J) k_null (q_home - q),
and commands q + dq. The null-space term keeps the redundant 7th degree of freedom near the home posture, so the
elbow does not drift over an episode. Closed loop at 20 Hz, one step is enough: the servo lag and the small
linearisation error are corrected at the next step, as an operational-space controller would.

Rotation helpers (quaternions w-first, as MuJoCo) live here because the state, the expert and the controller share
them.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

POS_SCALE = 0.05      # m per step at |a| = 1 (robosuite OSC output_max)
ROT_SCALE = 0.5       # rad per step at |a| = 1
DLS_DAMPING = 0.05
NULL_GAIN = 0.2


def skew(v: jax.Array) -> jax.Array:
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    o = jnp.zeros_like(x)
    return jnp.stack([jnp.stack([o, -z, y], -1), jnp.stack([z, o, -x], -1), jnp.stack([-y, x, o], -1)], -2)


def axis_angle_to_mat(w: jax.Array) -> jax.Array:
    """Rodrigues: rotation vector (..., 3) -> rotation matrix (..., 3, 3); exact near 0."""
    theta2 = jnp.sum(w * w, -1)[..., None, None]
    theta = jnp.sqrt(jnp.maximum(theta2, 1e-24))
    small = theta2 < 1e-8
    a = jnp.where(small, 1.0 - theta2 / 6.0, jnp.sin(theta) / theta)
    b = jnp.where(small, 0.5 - theta2 / 24.0, (1.0 - jnp.cos(theta)) / jnp.maximum(theta2, 1e-24))
    k = skew(w)
    return jnp.eye(3) + a * k + b * (k @ k)


def mat_to_quat(r: jax.Array) -> jax.Array:
    """Rotation matrix (3, 3) -> unit quaternion (w, x, y, z) with w >= 0 (Shepperd's method, branch-free)."""
    tr = r[0, 0] + r[1, 1] + r[2, 2]
    cands = jnp.stack([
        jnp.stack([1 + tr, r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]]),
        jnp.stack([r[2, 1] - r[1, 2], 1 + r[0, 0] - r[1, 1] - r[2, 2], r[0, 1] + r[1, 0], r[0, 2] + r[2, 0]]),
        jnp.stack([r[0, 2] - r[2, 0], r[0, 1] + r[1, 0], 1 - r[0, 0] + r[1, 1] - r[2, 2], r[1, 2] + r[2, 1]]),
        jnp.stack([r[1, 0] - r[0, 1], r[0, 2] + r[2, 0], r[1, 2] + r[2, 1], 1 - r[0, 0] - r[1, 1] + r[2, 2]]),
    ])
    # the candidate whose pivot (its own diagonal term) is largest is the well-conditioned one
    q = cands[jnp.argmax(jnp.stack([cands[0, 0], cands[1, 1], cands[2, 2], cands[3, 3]]))]
    q = q / jnp.linalg.norm(q)
    return q * jnp.where(q[0] < 0, -1.0, 1.0)


def quat_to_axis_angle(q: jax.Array) -> jax.Array:
    """Unit quaternion (w, x, y, z) -> rotation vector (3,), angle in [0, pi] (w made non-negative first)."""
    q = q * jnp.where(q[0] < 0, -1.0, 1.0)
    s = jnp.linalg.norm(q[1:])
    angle = 2.0 * jnp.arctan2(s, q[0])
    return q[1:] * jnp.where(s > 1e-9, angle / jnp.maximum(s, 1e-12), 2.0)


def mat_to_axis_angle(r: jax.Array) -> jax.Array:
    return quat_to_axis_angle(mat_to_quat(r))


def rotation_error(r_goal: jax.Array, r: jax.Array) -> jax.Array:
    """World-frame rotation vector taking r to r_goal (log map of r_goal r^T)."""
    return mat_to_axis_angle(r_goal @ r.T)


def yaw_of_quat(q: jax.Array) -> jax.Array:
    """Heading of the body x axis in the world xy plane, for bodies that stay (roughly) upright."""
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return jnp.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def dls_step(jac: jax.Array, twist: jax.Array, q: jax.Array, q_home: jax.Array) -> jax.Array:
    """One damped least-squares step. jac (6, n) [linear; angular], twist (6,), q/q_home (n,) -> dq (n,)."""
    jjt = jac @ jac.T + DLS_DAMPING**2 * jnp.eye(6)
    pinv = jac.T @ jnp.linalg.solve(jjt, jnp.eye(6))          # damped pseudo-inverse (n, 6)
    null = jnp.eye(jac.shape[1]) - pinv @ jac
    return pinv @ twist + null @ (NULL_GAIN * (q_home - q))


def arm_targets(jac: jax.Array, q: jax.Array, q_home: jax.Array, action: jax.Array,
                q_low: jax.Array, q_high: jax.Array) -> jax.Array:
    """Action (7,) in [-1, 1] -> arm joint targets (n,), clipped to the joint ranges."""
    a = jnp.clip(action, -1.0, 1.0)
    twist = jnp.concatenate([a[:3] * POS_SCALE, a[3:6] * ROT_SCALE])
    return jnp.clip(q + dls_step(jac, twist, q, q_home), q_low, q_high)


def gripper_target(action: jax.Array, open_width: float) -> jax.Array:
    """a[6] in [-1 (open), +1 (closed)] -> each finger's slide target in [0, open_width]."""
    return open_width * (1.0 - jnp.clip(action[6], -1.0, 1.0)) / 2.0
