"""The table-top scene as an MJCF string built from primitives: a 7-DoF arm with a parallel-jaw gripper, a table,
five blocks (two identical black ones, red, green, blue), a bowl and a plate, an agent-view and a wrist camera.

Geoms are boxes, capsules, cylinders, spheres and one plane only (no meshes), so the JAX ray caster
(`pi0_jax.sim.render`) and MJX collision stay analytic and cheap. One scene serves every task, so the whole suite
compiles once; tasks differ only in initial states, prompts and success predicates.

Frames: world z up, the table top is the plane z = 0, the robot base sits at the origin and reaches forward along
+x; the workspace is x in [0.30, 0.65], y in [-0.28, 0.28]. The arm is anthropomorphic with no link offsets:
yaw (z) / pitch (y) / roll / pitch / roll / pitch / roll, shoulder at z = SHOULDER_Z, links UPPER and FORE long;
the gripper's closing axis is the hand's local y and it points along the hand's local +z (straight down at home).

Contacts are filtered by bits (contype = own bit, conaffinity = bits it touches) so MJX only builds the pairs that
matter: blocks touch everything, fingers touch blocks and the table, the bowl and plate (mocap "fixtures": posed per
episode, never pushed) touch blocks only; arm links touch nothing. Their collision boxes live in geom group 3,
which neither renderer draws; the bowl's rim is drawn but does not collide (blocks are placed in it from above).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import re

import numpy as np

SHOULDER_Z = 0.35
UPPER = 0.40
FORE = 0.40
HAND = 0.125          # wrist pitch axis -> tool centre point (between the finger pads)
FINGER_OPEN = 0.04    # each finger's slide range; jaw gap = 2 * q
BLOCK_HALF = 0.02     # blocks are 4 cm cubes
PLATE_RADIUS = 0.075
PLATE_HALF_H = 0.006
BOWL_RADIUS = 0.07    # inner radius of the rim
BOWL_BASE_HALF_H = 0.006
CONTROL_DT = 0.05     # 20 Hz
PHYSICS_DT = 0.005

# contact bits
_TABLE, _BLOCK, _FINGER, _FIXTURE = 1, 2, 4, 8

ARM_JOINTS = tuple(f"joint{i}" for i in range(1, 8))
FINGER_JOINTS = ("finger_left", "finger_right")
BLOCKS = ("black_block_a", "black_block_b", "red_block", "green_block", "blue_block")
FIXTURES = ("bowl", "plate")
BLOCK_RGBA = {"black_block_a": (0.12, 0.12, 0.12, 1), "black_block_b": (0.12, 0.12, 0.12, 1),
              "red_block": (0.85, 0.15, 0.12, 1), "green_block": (0.15, 0.65, 0.2, 1),
              "blue_block": (0.15, 0.3, 0.85, 1)}
CAMERAS = ("agentview", "wrist")


def _f(*xs) -> str:
    return " ".join(f"{x:.6g}" for x in xs)


def lookat_xyaxes(pos, target, up=(0.0, 0.0, 1.0)) -> tuple[float, ...]:
    """MuJoCo camera `xyaxes` for a camera at `pos` looking at `target` (camera looks along its local -z)."""
    pos, target, up = (np.asarray(v, np.float64) for v in (pos, target, up))
    fwd = target - pos
    fwd /= np.linalg.norm(fwd)
    x = np.cross(fwd, up)
    x /= np.linalg.norm(x)
    y = np.cross(x, fwd)
    return tuple(x) + tuple(y)


def home_qpos() -> np.ndarray:
    """Arm joint angles with the tool centre point at (0.45, 0, 0.20), gripper pointing down, jaw across y.

    Closed-form planar two-link IK in the x-z plane: rotations about +y tilt +z towards +x, so a link at pitch a
    points along (sin a, cos a) and the wrist pitch closes the sum of pitches to pi (pointing down)."""
    x, z = 0.45, 0.20 + HAND - SHOULDER_Z          # wrist position relative to the shoulder
    d = math.hypot(x, z)
    elbow = math.pi - math.acos((UPPER**2 + FORE**2 - d**2) / (2 * UPPER * FORE))
    shoulder = math.atan2(x, z) - math.acos((UPPER**2 + d**2 - FORE**2) / (2 * UPPER * d))
    wrist = math.pi - shoulder - elbow
    return np.array([0.0, shoulder, 0.0, elbow, 0.0, wrist, 0.0])


@dataclasses.dataclass(frozen=True)
class SceneConfig:
    """What changes the compiled model. Resolution lives in the renderer, not here."""
    timestep: float = PHYSICS_DT
    solver_iterations: int = 6
    ls_iterations: int = 8
    max_geom_pairs: int = 10       # MJX broad phase: only the 10 nearest box-box pairs run narrow phase per step
    agent_fovy: float = 50.0
    wrist_fovy: float = 70.0

    @property
    def substeps(self) -> int:
        n = round(CONTROL_DT / self.timestep)
        assert abs(n * self.timestep - CONTROL_DT) < 1e-9, "timestep must divide the 50 ms control period"
        return n


def _contact(own: int, touches: int) -> str:
    return f'contype="{own}" conaffinity="{touches}"'


# the wrist camera sits on the side of the hand and looks past the fingers, image "up" = the hand's +x
_WRIST_XYAXES = lookat_xyaxes((0.07, 0, 0.03), (0, 0, 0.22), up=(1, 0, 0))


def _arm_xml() -> str:
    """The kinematic chain; link geoms are visual only (contype 0)."""
    cap = 'class="link" type="capsule"'
    xml = f"""
    <body name="base" pos="0 0 0">
      <geom class="link" type="cylinder" size="0.07 0.04" pos="0 0 0.04" rgba="0.25 0.25 0.28 1"/>
      <body name="link1" pos="0 0 0.08">
        <joint name="joint1" axis="0 0 1" range="-2.8 2.8"/>
        <geom {cap} size="0.055" fromto="0 0 0 0 0 {SHOULDER_Z - 0.08:.4f}"/>
        <body name="link2" pos="0 0 {SHOULDER_Z - 0.08:.4f}">
          <joint name="joint2" axis="0 1 0" range="-1.8 1.8"/>
          <geom class="link" type="sphere" size="0.065" rgba="0.9 0.9 0.92 1"/>
          <body name="link3">
            <joint name="joint3" axis="0 0 1" range="-2.8 2.8"/>
            <geom {cap} size="0.045" fromto="0 0 0.04 0 0 {UPPER - 0.04:.4f}"/>
            <body name="link4" pos="0 0 {UPPER:.4f}">
              <joint name="joint4" axis="0 1 0" range="-0.1 3.0"/>
              <geom class="link" type="sphere" size="0.055" rgba="0.9 0.9 0.92 1"/>
              <body name="link5">
                <joint name="joint5" axis="0 0 1" range="-2.8 2.8"/>
                <geom {cap} size="0.04" fromto="0 0 0.04 0 0 {FORE - 0.04:.4f}"/>
                <body name="link6" pos="0 0 {FORE:.4f}">
                  <joint name="joint6" axis="0 1 0" range="-0.5 3.6"/>
                  <geom class="link" type="sphere" size="0.045" rgba="0.25 0.25 0.28 1"/>
                  <body name="hand">
                    <joint name="joint7" axis="0 0 1" range="-2.9 2.9"/>
                    <geom class="link" type="cylinder" size="0.035 0.02" pos="0 0 0.03" rgba="0.9 0.9 0.92 1"/>
                    <geom class="link" type="box" size="0.025 0.06 0.012" pos="0 0 0.062" rgba="0.9 0.9 0.92 1"/>
                    <site name="tcp" pos="0 0 {HAND:.4f}" size="0.005"/>
                    <camera name="wrist" pos="0.07 0 0.03" xyaxes="{_f(*_WRIST_XYAXES)}" fovy="__WRIST_FOVY__"/>
                    <body name="finger_left" pos="0 0 0.074">
                      <joint name="finger_left" type="slide" axis="0 1 0" range="0 {FINGER_OPEN}"/>
                      <geom class="finger" size="0.012 0.005 0.032" pos="0 0.005 0.032"/>
                    </body>
                    <body name="finger_right" pos="0 0 0.074">
                      <joint name="finger_right" type="slide" axis="0 -1 0" range="0 {FINGER_OPEN}"/>
                      <geom class="finger" size="0.012 0.005 0.032" pos="0 -0.005 0.032"/>
                    </body>
                  </body>
                </body>
              </body>
            </body>
          </body>
        </body>
      </body>
    </body>"""
    # gravity compensation on every moving arm body (MuJoCo's body gravcomp, supported by MJX), so the position
    # servos only fight inertia and contacts and hold still under a zero action
    return re.sub(r'<body name="(link\d|hand|finger_\w+)"', r'<body name="\1" gravcomp="1"', xml)


def _objects_xml() -> str:
    blocks = "".join(f"""
    <body name="{name}" pos="{0.4 + 0.06 * i:.3f} 0.35 {BLOCK_HALF}">
      <freejoint name="{name}"/>
      <geom name="{name}" class="block" rgba="{_f(*BLOCK_RGBA[name])}"/>
    </body>""" for i, name in enumerate(BLOCKS))
    # Bowl: a drawn base disc and a rim of 8 boxes around it; one collision box under the disc.
    rim = "".join(
        f'\n      <geom class="visual" type="box" size="0.008 0.03 0.022" pos="{_f(r * math.cos(a), r * math.sin(a))} '
        f'0.022" euler="0 0 {a:.6f}" rgba="0.55 0.35 0.2 1"/>'
        for a, r in ((2 * math.pi * k / 8, BOWL_RADIUS + 0.008) for k in range(8)))
    return blocks + f"""
    <body name="bowl" mocap="true" pos="0.5 -0.4 0">
      <geom name="bowl" class="visual" type="cylinder" size="{BOWL_RADIUS + 0.012} {BOWL_BASE_HALF_H}"
            pos="0 0 {BOWL_BASE_HALF_H}" rgba="0.6 0.4 0.22 1"/>{rim}
      <geom class="fixture" size="{BOWL_RADIUS} {BOWL_RADIUS} {BOWL_BASE_HALF_H}" pos="0 0 {BOWL_BASE_HALF_H}"/>
    </body>
    <body name="plate" mocap="true" pos="0.6 -0.4 0">
      <geom name="plate" class="visual" type="cylinder" size="{PLATE_RADIUS} {PLATE_HALF_H}"
            pos="0 0 {PLATE_HALF_H}" rgba="0.92 0.92 0.88 1"/>
      <geom class="fixture" size="{PLATE_RADIUS * 0.8} {PLATE_RADIUS * 0.8} {PLATE_HALF_H}" pos="0 0 {PLATE_HALF_H}"/>
    </body>"""


def build_mjcf(cfg: SceneConfig = SceneConfig()) -> str:
    """The scene's MJCF text (deterministic in `cfg`)."""
    agent_pos, agent_target = (0.92, 0.0, 0.52), (0.44, 0.0, 0.0)
    xml = f"""<mujoco model="pi0jax_tabletop">
  <compiler angle="radian" autolimits="true"/>
  <option timestep="{cfg.timestep}" iterations="{cfg.solver_iterations}" ls_iterations="{cfg.ls_iterations}"
          integrator="implicitfast" cone="pyramidal"/>
  <custom><numeric name="max_geom_pairs" data="{cfg.max_geom_pairs}"/></custom>
  <visual><global offwidth="640" offheight="640"/><map znear="0.01" zfar="20"/></visual>
  <asset><material name="default" rgba="1 1 1 1"/></asset>
  <default>
    <joint damping="2" armature="0.1"/>
    <geom contype="0" conaffinity="0" friction="1 0.005 0.0001" solref="0.01 1" solimp="0.95 0.99 0.001"/>
    <position kp="400" kv="40" forcerange="-150 150"/>
    <default class="link"><geom rgba="0.82 0.82 0.85 1" mass="0.8"/></default>
    <default class="visual"><geom contype="0" conaffinity="0" mass="0"/></default>
    <default class="block"><geom type="box" size="{BLOCK_HALF} {BLOCK_HALF} {BLOCK_HALF}" mass="0.05"
                                 {_contact(_BLOCK, _TABLE | _BLOCK | _FINGER | _FIXTURE)}/></default>
    <default class="finger"><geom type="box" rgba="0.2 0.2 0.22 1" mass="0.05" friction="1.5 0.005 0.0001"
                                  {_contact(_FINGER, _TABLE | _BLOCK)}/></default>
    <default class="fixture"><geom type="box" group="3" rgba="0.5 0.5 0.5 0.3" mass="0"
                                   {_contact(_FIXTURE, _BLOCK)}/></default>
  </default>
  <worldbody>
    <light name="sun" directional="true" pos="0.4 0.3 2" dir="-0.2 -0.15 -1" diffuse="0.8 0.8 0.8"/>
    <geom name="table" type="plane" size="0.7 0.9 0.01" pos="0.55 0 0" rgba="0.72 0.6 0.45 1"
          {_contact(_TABLE, _BLOCK | _FINGER)}/>
    <camera name="agentview" pos="{_f(*agent_pos)}" xyaxes="{_f(*lookat_xyaxes(agent_pos, agent_target))}"
            fovy="{cfg.agent_fovy}"/>{_arm_xml()}{_objects_xml()}
  </worldbody>
  <actuator>{"".join(f'''
    <position name="{j}" joint="{j}"/>''' for j in ARM_JOINTS)}
    <position name="finger_left" joint="finger_left" kp="300" kv="5" forcerange="-8 8" ctrlrange="0 {FINGER_OPEN}"/>
    <position name="finger_right" joint="finger_right" kp="300" kv="5" forcerange="-8 8" ctrlrange="0 {FINGER_OPEN}"/>
  </actuator>
</mujoco>
"""
    return xml.replace("__WRIST_FOVY__", f"{cfg.wrist_fovy}")


@dataclasses.dataclass(frozen=True)
class SceneIndex:
    """Integer addresses into the compiled model, resolved once by name (static under jit)."""
    arm_qpos: tuple[int, ...]
    finger_qpos: tuple[int, ...]
    block_qpos: tuple[int, ...]      # start of each block's 7-D free joint (pos 3, quat 4)
    block_body: tuple[int, ...]
    block_geom: tuple[int, ...]
    fixture_mocap: tuple[int, ...]   # bowl, plate
    tcp_site: int
    hand_body: int
    arm_dof: tuple[int, ...]
    camera: tuple[int, ...]          # agentview, wrist


@functools.lru_cache(maxsize=None)
def build(cfg: SceneConfig = SceneConfig()):
    """Compile the scene: returns (mujoco.MjModel, SceneIndex). Cached per config."""
    import mujoco

    model = mujoco.MjModel.from_xml_string(build_mjcf(cfg))
    jid = lambda n: mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, n)  # noqa: E731
    bid = lambda n: mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, n)  # noqa: E731
    gid = lambda n: mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, n)  # noqa: E731
    index = SceneIndex(
        arm_qpos=tuple(int(model.jnt_qposadr[jid(j)]) for j in ARM_JOINTS),
        finger_qpos=tuple(int(model.jnt_qposadr[jid(j)]) for j in FINGER_JOINTS),
        block_qpos=tuple(int(model.jnt_qposadr[jid(b)]) for b in BLOCKS),
        block_body=tuple(bid(b) for b in BLOCKS),
        block_geom=tuple(gid(b) for b in BLOCKS),
        fixture_mocap=tuple(int(model.body_mocapid[bid(f)]) for f in FIXTURES),
        tcp_site=mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, "tcp"),
        hand_body=bid("hand"),
        arm_dof=tuple(int(model.jnt_dofadr[jid(j)]) for j in ARM_JOINTS),
        camera=tuple(mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, c) for c in CAMERAS),
    )
    assert index.arm_qpos == tuple(range(7)) and index.arm_dof == tuple(range(7)), "arm joints must come first"
    return model, index
