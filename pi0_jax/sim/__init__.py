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
# backend starts, so the flags are appended here unless a backend is already running, and only where JAX will run on
# the CPU: XLA_FLAGS is part of every compiled program's cache key (XLA's and `engine.store`'s), and the `pi0-jax`
# command imports this package for its parser, so on a GPU machine the flags would set `pi0-jax serve` apart from a
# script running the same programs.
_CPU_FLAGS = ("--xla_cpu_use_fusion_emitters=false", "--xla_cpu_enable_concurrency_optimized_scheduler=false")


def _backends_started() -> bool:
    if "jax" not in sys.modules:
        return False
    try:
        from jax._src import xla_bridge
        return bool(xla_bridge.backends_are_initialized())
    except (ImportError, AttributeError):   # private API moved: assume the worst
        return True


def _runs_on_cpu() -> bool:
    """Whether JAX's default backend will be the CPU: JAX_PLATFORMS names it first, or (unset) no GPU plugin of jax
    is installed (jax-cuda*/jax-rocm* distributions) or no GPU device node exists (a CUDA install on a machine
    without a GPU falls back to the CPU)."""
    import glob
    import importlib.metadata

    platforms = os.environ.get("JAX_PLATFORMS", "").strip()
    if platforms:
        return platforms.split(",")[0].strip() == "cpu"
    if not (glob.glob("/dev/nvidia[0-9]*") or os.path.exists("/dev/kfd")):
        return True
    gpu = ("jax-cuda", "jax_cuda", "jax-rocm", "jax_rocm")
    return not any((d.metadata["Name"] or "").lower().startswith(gpu) for d in importlib.metadata.distributions())


def _known_to_xla(flags) -> list[str]:
    """The flags this jaxlib's XLA defines: an unknown name in XLA_FLAGS is fatal, and XLA:CPU flags come and go
    between releases (jax 0.11 dropped --xla_cpu_use_fusion_emitters). XLA registers each flag under its name, so
    the name is a string in jaxlib's largest shared library; look it up there (memory-mapped, no jax import)."""
    import importlib.util
    import mmap

    spec = importlib.util.find_spec("jaxlib")
    if spec is None or not spec.submodule_search_locations:
        return []
    root = spec.submodule_search_locations[0]
    libs = [os.path.join(root, f) for f in os.listdir(root) if f.endswith(".so")]
    if not libs:
        return []
    with open(max(libs, key=os.path.getsize), "rb") as fh, mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as mm:
        return [f for f in flags if mm.find(f[2:].split("=")[0].encode() + b"\0") >= 0]


_missing = [f for f in _CPU_FLAGS if f.split("=")[0] not in os.environ.get("XLA_FLAGS", "")]
if _missing and _runs_on_cpu():
    if _backends_started():
        warnings.warn("pi0_jax.sim imported after a JAX backend started: on CPU, set "
                      f"XLA_FLAGS='{' '.join(_CPU_FLAGS)}' before JAX starts, or MJX steps are much slower",
                      stacklevel=2)
    elif _known := _known_to_xla(_missing):
        os.environ["XLA_FLAGS"] = " ".join([os.environ.get("XLA_FLAGS", ""), *_known]).strip()
