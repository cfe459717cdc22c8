"""Where the evaluation's cold compile goes: the segment program and its parts, each compiled apart, cold.

`pi0-jax eval` compiles one program per batch size, the segment (`pi0_jax.sim.evaluate.make_segment`): the
policy's plan (vision, prefix, denoise) and `replan_steps` physics steps per plan, with rendering before each plan.
On a GPU that compile is half of the embedded model's cold 550-episode run. This probe compiles, in one process,
with no persistent cache, and times lower + compile of each:

  reset    the environments' reset (vmapped `Env.reset`)
  physics  `replan_steps` steps: the policy's `act` and the vmapped `Env.step`, under `lax.scan`
  render   both cameras (vmapped `Env.observe`)
  plan     the policy's plan (one chunk for every environment)
  segment  the whole segment, as `pi0-jax eval` compiles it
  threads  physics, render and plan again, compiled at once in three threads (wall clock of the three)

and each program's HLO size (instructions of the optimized module) and its GPU kernels.

    python scripts/compile_probe.py --json compile.json                        # GPU: the embedded model, N = 550
    python scripts/compile_probe.py --policy preset:dummy --batch 4 --resolution 32   # CPU check
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import threading
import time
from pathlib import Path


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--policy", default="pi0_jax/assets/pi0_small",
                   help="as `pi0-jax eval --policy` (default: the embedded model)")
    p.add_argument("--batch", type=int, default=550, help="environments (default: 550, what --batch auto picks)")
    p.add_argument("--resolution", type=int, default=224, help="camera pixels (default: 224)")
    p.add_argument("--replan-steps", type=int, default=5, help="physics steps per plan (default: 5)")
    p.add_argument("--gemm", choices=("xla", "cublas"), default="cublas", help="as `pi0-jax eval` (default: cublas)")
    p.add_argument("--only", default="reset,physics,render,plan,segment,threads",
                   help="comma-separated parts to compile (default: all, in this order)")
    p.add_argument("--json", type=Path, default=None, help="also write the result here")
    args = p.parse_args(argv)
    known = ("reset", "physics", "render", "plan", "segment", "threads")
    if unknown := set(args.only.split(",")) - set(known):
        p.error(f"--only: unknown parts {sorted(unknown)}; parts: {', '.join(known)}")

    import jax
    import jax.numpy as jnp
    import numpy as np

    from pi0_jax.ops import matmul
    from pi0_jax.sim import batching
    from pi0_jax.sim import evaluate as ev
    from pi0_jax.sim import tasks as tasks_lib
    from pi0_jax.sim.env import Env
    from pi0_jax.sim.policies import make_policy
    from pi0_jax.sim.realtime import Realtime
    from pi0_jax.sim.render import RenderConfig

    t0 = time.perf_counter()
    names = tuple(t.name for t in tasks_lib.suite_tasks("all"))
    n, r = args.batch, args.replan_steps
    env = Env(names, RenderConfig(args.resolution, args.resolution,
                                  batching.auto_ray_chunk(args.resolution, args.resolution, n)))
    policy = make_policy(args.policy, env, r, num_steps=10, gemm=args.gemm, realtime=Realtime())
    setup_s = time.perf_counter() - t0
    options = matmul.compiler_options(policy.params, policy.info.get("gemm", "xla"))
    spec = jax.ShapeDtypeStruct

    def shapes(tree):
        return jax.tree.map(lambda x: spec(np.shape(x), jnp.result_type(x)), tree)

    keys = spec((n,), jax.random.key(0).dtype)
    ints = spec((n,), jnp.int32)
    state = jax.eval_shape(jax.vmap(env.reset), keys, ints, ints)
    params = shapes(policy.params)
    pstate = jax.eval_shape(lambda: policy.init(n))
    obs = jax.eval_shape(jax.vmap(env.observe), state)

    def physics(state, ps):
        def inner(c, k):
            s, ps = c
            action, ps = policy.act(ps, s, k)
            return (jax.vmap(env.step)(s, action), ps), None
        return jax.lax.scan(inner, (state, ps), jnp.arange(r))[0]

    cfg = ev.EvalConfig(replan_steps=r, resolution=args.resolution)
    carry = ev.Carry(state=state, pstate=pstate, keys=keys)
    parts = {
        "reset": lambda: (jax.vmap(env.reset), (keys, ints, ints)),
        # fresh function objects each time: jax would return a function's earlier compile from its own caches
        "physics": lambda: (lambda *a: physics(*a), (state, pstate)),
        "render": lambda: (jax.vmap(env.observe), (state,)),
        "plan": lambda: (lambda *a: policy.plan(*a), (params, pstate, obs, state, keys)),
        "segment": lambda: (ev.make_segment(env, policy, cfg, 0), (params, carry)),
    }

    def compile_part(name: str) -> dict:
        fn, a = parts[name]()
        start = time.perf_counter()
        lowered = (fn if hasattr(fn, "lower") else jax.jit(fn)).lower(*a)
        lower_s = time.perf_counter() - start
        exe = lowered.compile(options)
        total = time.perf_counter() - start
        text = exe.as_text()
        return {"lower_s": round(lower_s, 2), "compile_s": round(total - lower_s, 2), "total_s": round(total, 2),
                "hlo_instructions": len(re.findall(r"^\s+\S+ = ", text, re.M)),
                "kernels": len(re.findall(r"^\s+\S+ = \S+ (?:fusion|custom-call)\(", text, re.M))}

    out = {"device": str(jax.devices()[0].device_kind), "jax": jax.__version__, "args": vars(args) | {
        "json": str(args.json)}, "setup_s": round(setup_s, 2), "parts": {}}
    print(f"{out['device']} · jax {jax.__version__} · setup {setup_s:.1f} s", flush=True)
    for name in args.only.split(","):
        if name == "threads":
            results, threads = {}, []
            start = time.perf_counter()
            for part in ("physics", "render", "plan"):
                t = threading.Thread(target=lambda part=part: results.__setitem__(part, compile_part(part)))
                t.start()
                threads.append(t)
            for t in threads:
                t.join()
            out["parts"]["threads"] = {"wall_s": round(time.perf_counter() - start, 2),
                                       "each_total_s": {k: v["total_s"] for k, v in results.items()}}
        else:
            out["parts"][name] = compile_part(name)
        print(f"{name:8s} {out['parts'][name]}", flush=True)
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
