"""A LIBERO-like table-top task suite in MuJoCo MJX, rendered by a JAX ray caster, evaluated batched under jit.

  scene.py       MJCF from primitives: 7-DoF arm + parallel-jaw gripper, table, blocks, bowl, plate, two cameras
  controller.py  7-D end-effector delta (+ gripper) -> joint targets by damped least squares on the MJX Jacobian
  render.py      batched JAX ray caster over the scene's primitive geoms (RGB, depth, geom id)
  env.py         pure reset(rng) / step(state, action) over a struct State; observations; vmap outside
  tasks.py       the task registry: prompts, families, versioned initial states, success predicates, step limits
  expert.py      a scripted pick-and-place expert for every task (privileged state, pure JAX)
  policies.py    expert / random / pi0-jax checkpoint policies behind one batched interface
  evaluate.py    the sharded, lax.scan'ed rollout, multi-host merge, eval_info.json, videos
  demos.py       demonstration writer (one compressed npz per episode)
  cli.py         `pi0-jax eval`
"""

import os
import sys
import warnings

# MJX on XLA:CPU: the CPU fusion emitter blows up on deep kinematic chains (one 7-joint arm step took ~0.6 s instead
# of ~4 ms on this project's machines), and XLA:CPU's concurrency-optimised scheduler deadlocked this scene's batched
# step at batch >= 48 on a 2-core machine (all threads idle in BlockUntilReady). XLA reads XLA_FLAGS when its first
# backend starts, so the flags are appended here unless a backend is already running; GPU backends ignore them.
_CPU_FLAGS = ("--xla_cpu_use_fusion_emitters=false", "--xla_cpu_enable_concurrency_optimized_scheduler=false")


def _backends_started() -> bool:
    if "jax" not in sys.modules:
        return False
    try:
        from jax._src import xla_bridge
        return bool(xla_bridge.backends_are_initialized())
    except (ImportError, AttributeError):   # private API moved: assume the worst
        return True


_missing = [f for f in _CPU_FLAGS if f not in os.environ.get("XLA_FLAGS", "")]
if _missing:
    if _backends_started():
        warnings.warn(f"pi0_jax.sim imported after a JAX backend started: on CPU, set XLA_FLAGS='{' '.join(_CPU_FLAGS)}' "
                      "before JAX starts, or MJX steps are much slower", stacklevel=2)
    else:
        os.environ["XLA_FLAGS"] = " ".join([os.environ.get("XLA_FLAGS", ""), *_missing]).strip()
