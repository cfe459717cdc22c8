"""The task registry: language-conditioned tasks in three LIBERO-like families over one scene.

  spatial  the same two identical black blocks, placed on the plate; which one is named by where it is
           (left / right / nearest the robot / next to the bowl), as LIBERO-spatial names a bowl by its place
  object   a different object each task (red, green, blue block) into the bowl, everything else a distractor
  goal     one nominal layout (small perturbations), a different goal each task (place, stack, lift)

Each task has a prompt, a success predicate (data: kind + object + target, so one jitted predicate serves all tasks),
a step limit (LIBERO's per-suite limits: 220 spatial, 280 object, 300 goal) and a fixed set of initial states drawn
from seeds. The initial states are versioned: SUITE_VERSION names the generator; `tests/test_sim_tasks.py` pins a
digest of every task's states, so a change to the generator must bump the version. Referenced black block: the
task's object is always `black_block_a`; the layout sampler puts it where the prompt says.

Frames: the robot's left is +y; "nearest the robot" is smallest x (the base is at the origin, facing +x).
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import math
import zlib
from collections.abc import Callable

import numpy as np

from pi0_jax.sim import scene

SUITE_VERSION = 1
NUM_INIT_STATES = 50
# LIBERO's observation state (the tool centre point's position and axis-angle, two finger joints) and action dims
STATE_DIM, ACTION_DIM = 8, 7

PLACE, STACK, LIFT = 0, 1, 2
LIFT_HEIGHT = 0.10           # block centre above this = lifted (rests at 0.02)

# layout sampling region and clearances (metres)
_X, _Y = (0.33, 0.62), (-0.25, 0.25)
_FIX_X, _FIX_Y = (0.38, 0.58), (-0.2, 0.2)
_FIX_R = {"bowl": scene.BOWL_RADIUS + 0.016, "plate": scene.PLATE_RADIUS}
_BLOCK_GAP = 0.10            # block centre to block centre: an open jaw (8 cm) fits between neighbours
_FIX_GAP = 0.06              # block centre to fixture edge
_ARM_NOISE = 0.02            # rad, uniform, per arm joint


@dataclasses.dataclass(frozen=True)
class Layout:
    """One initial state. block: (5, 4) x, y, z, yaw in scene.BLOCKS order; fixture: (2, 3) in scene.FIXTURES
    order; arm_q: (7,) joint angles."""
    block: np.ndarray
    fixture: np.ndarray
    arm_q: np.ndarray


@dataclasses.dataclass(frozen=True)
class Task:
    name: str
    family: str
    prompt: str
    kind: int                 # PLACE (object on/in a fixture), STACK (object on a block), LIFT
    obj: str                  # a block name
    target: str | None        # fixture name for PLACE, block name for STACK
    max_steps: int
    accept: Callable[[Layout], bool] = dataclasses.field(repr=False, compare=False, default=lambda lay: True)
    nominal: bool = False     # goal family: perturb one fixed layout instead of sampling freely

    @property
    def obj_index(self) -> int:
        return scene.BLOCKS.index(self.obj)

    @property
    def target_index(self) -> int:
        if self.kind == PLACE:
            return scene.FIXTURES.index(self.target)
        return scene.BLOCKS.index(self.target) if self.kind == STACK else 0


def _b(lay: Layout, name: str) -> np.ndarray:
    return lay.block[scene.BLOCKS.index(name), :2]


def _f(lay: Layout, name: str) -> np.ndarray:
    return lay.fixture[scene.FIXTURES.index(name), :2]


def _dist(a, b) -> float:
    """Distance in the table plane (x, y): math.hypot, since the sampler calls this half a million times."""
    return math.hypot(float(a[0]) - float(b[0]), float(a[1]) - float(b[1]))


_A, _B_ = "black_block_a", "black_block_b"
_SPATIAL, _OBJECT, _GOAL = 220, 280, 300

TASKS: tuple[Task, ...] = (
    Task("spatial/left_black_block_on_plate", "spatial",
         "pick up the black block on the left and place it on the plate", PLACE, _A, "plate", _SPATIAL,
         accept=lambda lay: _b(lay, _A)[1] > _b(lay, _B_)[1] + 0.12),
    Task("spatial/right_black_block_on_plate", "spatial",
         "pick up the black block on the right and place it on the plate", PLACE, _A, "plate", _SPATIAL,
         accept=lambda lay: _b(lay, _A)[1] < _b(lay, _B_)[1] - 0.12),
    Task("spatial/nearest_black_block_on_plate", "spatial",
         "pick up the black block nearest the robot and place it on the plate", PLACE, _A, "plate", _SPATIAL,
         accept=lambda lay: _b(lay, _A)[0] < _b(lay, _B_)[0] - 0.10),
    Task("spatial/black_block_by_bowl_on_plate", "spatial",
         "pick up the black block next to the bowl and place it on the plate", PLACE, _A, "plate", _SPATIAL,
         accept=lambda lay: _dist(_b(lay, _A), _f(lay, "bowl")) < _FIX_R["bowl"] + _FIX_GAP + 0.04
         and _dist(_b(lay, _B_), _f(lay, "bowl")) > 0.28),
    Task("object/red_block_in_bowl", "object",
         "pick up the red block and place it in the bowl", PLACE, "red_block", "bowl", _OBJECT),
    Task("object/green_block_in_bowl", "object",
         "pick up the green block and place it in the bowl", PLACE, "green_block", "bowl", _OBJECT),
    Task("object/blue_block_in_bowl", "object",
         "pick up the blue block and place it in the bowl", PLACE, "blue_block", "bowl", _OBJECT),
    Task("goal/red_block_on_plate", "goal", "put the red block on the plate", PLACE, "red_block", "plate", _GOAL,
         nominal=True),
    Task("goal/blue_block_in_bowl", "goal", "put the blue block in the bowl", PLACE, "blue_block", "bowl", _GOAL,
         nominal=True),
    Task("goal/stack_green_on_blue", "goal", "stack the green block on the blue block", STACK, "green_block",
         "blue_block", _GOAL, nominal=True),
    Task("goal/lift_red_block", "goal", "pick up the red block and hold it up", LIFT, "red_block", None, _GOAL,
         nominal=True),
)

SUITES: dict[str, tuple[str, ...]] = {
    "spatial": tuple(t.name for t in TASKS if t.family == "spatial"),
    "object": tuple(t.name for t in TASKS if t.family == "object"),
    "goal": tuple(t.name for t in TASKS if t.family == "goal"),
    "all": tuple(t.name for t in TASKS),
}
_BY_NAME = {t.name: t for t in TASKS}

# goal family: one nominal layout (x, y) for blocks and fixtures, perturbed per initial state
_NOMINAL_BLOCKS = {"black_block_a": (0.34, 0.22), "black_block_b": (0.60, -0.02), "red_block": (0.40, 0.04),
                   "green_block": (0.47, -0.20), "blue_block": (0.58, 0.12)}
_NOMINAL_FIXTURES = {"bowl": (0.40, -0.10), "plate": (0.50, 0.24)}


def get_task(name: str) -> Task:
    return _BY_NAME[name]


def suite_tasks(suite: str) -> tuple[Task, ...]:
    if suite in SUITES:
        return tuple(_BY_NAME[n] for n in SUITES[suite])
    if suite in _BY_NAME:
        return (_BY_NAME[suite],)
    raise KeyError(f"unknown suite or task {suite!r}; suites: {', '.join(SUITES)}")


def _clear(lay_blocks: list, lay_fix: dict, xy: np.ndarray) -> bool:
    if any(_dist(xy, b) < _BLOCK_GAP for b in lay_blocks):
        return False
    return all(_dist(xy, p) >= _FIX_R[n] + _FIX_GAP for n, p in lay_fix.items())


def _sample_layout(rng: np.random.Generator, task: Task) -> Layout:
    for _ in range(10_000):
        if task.nominal:
            fix = {n: np.array(p) + rng.uniform(-0.015, 0.015, 2) for n, p in _NOMINAL_FIXTURES.items()}
            blocks = [np.array(_NOMINAL_BLOCKS[n]) + rng.uniform(-0.02, 0.02, 2) for n in scene.BLOCKS]
            ok = _dist(fix["bowl"], fix["plate"]) > _FIX_R["bowl"] + _FIX_R["plate"] + 0.05 and all(
                _clear(blocks[:i], fix, b) for i, b in enumerate(blocks))
        else:
            fix, blocks, ok = {}, [], True
            for n in scene.FIXTURES:
                p = rng.uniform([_FIX_X[0], _FIX_Y[0]], [_FIX_X[1], _FIX_Y[1]])
                if any(_dist(p, q) < _FIX_R[n] + _FIX_R[m] + 0.08 for m, q in fix.items()):
                    ok = False
                    break
                fix[n] = p
            for _n in scene.BLOCKS if ok else ():
                for _ in range(200):
                    p = rng.uniform([_X[0], _Y[0]], [_X[1], _Y[1]])
                    if _clear(blocks, fix, p):
                        blocks.append(p)
                        break
                else:
                    ok = False
                    break
        if not ok:
            continue
        yaw = rng.uniform(-np.pi / 4, np.pi / 4, len(scene.BLOCKS))
        lay = Layout(
            block=np.concatenate([np.stack(blocks), np.full((len(blocks), 1), scene.BLOCK_HALF), yaw[:, None]], 1),
            fixture=np.concatenate([np.stack([fix[n] for n in scene.FIXTURES]), np.zeros((2, 1))], 1),
            arm_q=scene.home_qpos() + rng.uniform(-_ARM_NOISE, _ARM_NOISE, 7))
        if task.accept(lay):
            return lay
    raise RuntimeError(f"could not sample a layout for {task.name}")


@functools.lru_cache(maxsize=None)
def init_states(name: str, n: int = NUM_INIT_STATES, version: int = SUITE_VERSION) -> Layout:
    """The task's fixed initial states, stacked: block (n, 5, 4), fixture (n, 2, 3), arm_q (n, 7), float32.

    State i comes from np.random.default_rng([version, crc32(task name), i]), so states are independent of n and
    of the other tasks."""
    if version != SUITE_VERSION:
        raise ValueError(f"this build generates suite version {SUITE_VERSION}, not {version}")
    task = _BY_NAME[name]
    lays = [_sample_layout(np.random.default_rng([version, zlib.crc32(name.encode()), i]), task) for i in range(n)]
    return Layout(*(np.stack([getattr(lay, f.name) for lay in lays]).astype(np.float32)
                    for f in dataclasses.fields(Layout)))


def init_states_digest(name: str) -> str:
    """sha256 of the task's initial states (rounded to 0.1 mm / 1 mrad, so BLAS or libm differences do not count)."""
    lay = init_states(name)
    h = hashlib.sha256()
    for arr in (lay.block, lay.fixture, lay.arm_q):
        h.update(np.round(arr.astype(np.float64) * 1e4).astype(np.int64).tobytes())
    return h.hexdigest()


@dataclasses.dataclass(frozen=True)
class TaskTable:
    """Per-task arrays for jitted code, indexed by a task index into `tasks` (leading axis T)."""
    tasks: tuple[Task, ...]
    kind: np.ndarray          # (T,) int32
    obj: np.ndarray           # (T,) int32
    target: np.ndarray        # (T,) int32
    max_steps: np.ndarray     # (T,) int32
    block: np.ndarray         # (T, N, 5, 4)
    fixture: np.ndarray       # (T, N, 2, 3)
    arm_q: np.ndarray         # (T, N, 7)


@functools.lru_cache(maxsize=None)
def task_table(names: tuple[str, ...], n: int = NUM_INIT_STATES) -> TaskTable:
    tasks = tuple(_BY_NAME[x] for x in names)
    states = [init_states(x, n) for x in names]
    return TaskTable(
        tasks=tasks,
        kind=np.array([t.kind for t in tasks], np.int32), obj=np.array([t.obj_index for t in tasks], np.int32),
        target=np.array([t.target_index for t in tasks], np.int32),
        max_steps=np.array([t.max_steps for t in tasks], np.int32),
        block=np.stack([s.block for s in states]), fixture=np.stack([s.fixture for s in states]),
        arm_q=np.stack([s.arm_q for s in states]))


def success(kind, obj, target, block_pos, fixture_pos):
    """The success predicate, in jnp. kind/obj/target: int scalars; block_pos (5, 3), fixture_pos (2, 3) -> bool.

    PLACE: the object's centre is over the fixture (inside the bowl's rim, on the plate's top) and resting on it
    (height within 1.5 cm of its resting height there). STACK: centred on the other block within half a block,
    one block higher (+-1 cm). LIFT: centre above LIFT_HEIGHT."""
    import jax.numpy as jnp

    p = block_pos[obj]
    fix = fixture_pos[jnp.clip(target, 0, fixture_pos.shape[0] - 1)]
    radius = jnp.where(target == scene.FIXTURES.index("bowl"), scene.BOWL_RADIUS - 0.015, scene.PLATE_RADIUS - 0.01)
    top = fix[2] + 2 * jnp.where(target == scene.FIXTURES.index("bowl"), scene.BOWL_BASE_HALF_H, scene.PLATE_HALF_H)
    placed = (jnp.linalg.norm(p[:2] - fix[:2]) < radius) & (jnp.abs(p[2] - (top + scene.BLOCK_HALF)) < 0.015)
    other = block_pos[jnp.clip(target, 0, block_pos.shape[0] - 1)]
    stacked = (jnp.linalg.norm(p[:2] - other[:2]) < scene.BLOCK_HALF) & (
        jnp.abs(p[2] - other[2] - 2 * scene.BLOCK_HALF) < 0.01)
    lifted = p[2] > LIFT_HEIGHT
    return jnp.select([kind == PLACE, kind == STACK], [placed, stacked], lifted)
