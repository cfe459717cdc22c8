"""Can one GPU run the physics and rendering of one group of environments while the policy plans for another?

XLA runs a program's kernels one after another on one compute stream, so inside the evaluation's segment the
policy and the simulator take turns however the work is split. XLA's experimental stream annotation
(`jax.experimental.compute_on("gpu_stream:1")` under `--xla_gpu_experimental_stream_annotation=true`) puts an
annotated call on a second stream. This probe measures whether that overlaps anything at the evaluation's shapes.

Two halves A and B of N environments (all tasks mixed, both cameras rendered at --resolution). One program plans
for A (the policy: vision, prefix, --num-steps denoise steps on random weights) and steps B --replan-steps times
with the last chunk, then renders B, with no data dependence between the two. The program is timed three ways:
the physics alone, both in one program (sequential, one stream), and both with the policy annotated to
stream 1. Overlap works if the last is below the sum of the first two. To save compilations the
policy alone is not compiled: one stream runs the two back to back, so the policy's share is (both, one stream)
minus (physics alone), and `overlap_fraction` is the time saved by stream 1 over the smaller of the two.

    python scripts/overlap_probe.py --json overlap.json                  # GPU: pi05_libero, N = 128
    python scripts/overlap_probe.py --model dummy_pi05 --batch 4 --resolution 32 --replan-steps 2   # CPU check

On the CPU (no streams) the annotation is reported as not applicable, and the four programs still run.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path


def on_stream(f, compute_type: str):
    """f as a call XLA runs on another stream. jax 0.11 made `compute_on` a function transform with explicit output
    memory spaces (earlier: `compute_on2`; `compute_on` was a context manager)."""
    import inspect

    import jax
    from jax.experimental import compute_on as co

    if "out_memory_spaces" in inspect.signature(co.compute_on).parameters:
        transform = co.compute_on
    else:
        transform = co.compute_on2
    space = getattr(getattr(jax, "memory", None), "Space", None)
    if space is None:
        from jax._src.core import MemorySpace as space
    return transform(f, compute_type=compute_type, out_memory_spaces=space.Device)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", default="pi05_libero", help="pi0_jax.config preset of the policy (random weights)")
    p.add_argument("--batch", type=int, default=128, help="environments N, split into two halves (default: 128)")
    p.add_argument("--resolution", type=int, default=224, help="camera pixels (default: 224)")
    p.add_argument("--replan-steps", type=int, default=5, help="physics steps per plan (default: 5)")
    p.add_argument("--num-steps", type=int, default=10, help="flow steps per plan (default: 10)")
    p.add_argument("--iters", type=int, default=3, help="timed calls per program (default: 3; the median counts)")
    p.add_argument("--json", type=Path, default=None, help="also write the result here")
    args = p.parse_args(argv)
    if "--xla_gpu_experimental_stream_annotation" not in os.environ.get("XLA_FLAGS", ""):
        os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "")
                                   + " --xla_gpu_experimental_stream_annotation=true").strip()
    import jax
    import jax.numpy as jnp
    import numpy as np

    import pi0_jax.sim  # noqa: F401  (XLA:CPU flags before the backend starts)
    from pi0_jax.sim import batching, policies, tasks
    from pi0_jax.sim.env import Env
    from pi0_jax.sim.render import RenderConfig

    half = args.batch // 2
    res = args.resolution
    env = Env(tasks.SUITES["all"], RenderConfig(res, res, batching.auto_ray_chunk(res, res, half)))
    policy = policies.preset_policy(args.model, env, num_steps=args.num_steps)
    params = jax.device_put(policy.params)
    t = len(env.tasks)

    def reset(seed):
        keys = jax.random.split(jax.random.key(seed), half)
        return jax.jit(jax.vmap(env.reset))(keys, jnp.arange(half) % t, (jnp.arange(half) // t) % env.num_init_states)

    state_a, state_b = reset(0), reset(1)
    obs_a = jax.jit(jax.vmap(env.observe))(state_a)
    chunk_b = jnp.zeros((half, policy.horizon, 7), jnp.float32)
    keys = jax.random.split(jax.random.key(2), half)

    def plan(params, obs, state):
        return policy.plan(params, policy.init(half), obs, state, keys)

    def physics(state, chunk):
        def body(s, k):
            return jax.vmap(env.step)(s, chunk[:, k, :7]), None
        state = jax.lax.scan(body, state, jnp.arange(args.replan_steps))[0]
        obs = jax.vmap(env.observe)(state)
        return state, obs["agentview"].sum(dtype=jnp.int32) + obs["wrist"].sum(dtype=jnp.int32)

    def both(params, obs_a, state_a, state_b, chunk_b):
        return plan(params, obs_a, state_a), physics(state_b, chunk_b)

    plan_on_stream = on_stream(plan, "gpu_stream:1")

    def both_streams(params, obs_a, state_a, state_b, chunk_b):
        return plan_on_stream(params, obs_a, state_a), physics(state_b, chunk_b)

    programs = {"physics alone": (physics, (state_b, chunk_b)),
                "both, one stream": (both, (params, obs_a, state_a, state_b, chunk_b)),
                "both, policy on stream 1": (both_streams, (params, obs_a, state_a, state_b, chunk_b))}
    result = {"device": jax.devices()[0].device_kind, "backend": jax.default_backend(), "jax": jax.__version__,
              "model": args.model, "batch": args.batch, "half": half, "resolution": res,
              "replan_steps": args.replan_steps, "num_steps": args.num_steps, "xla_flags": os.environ["XLA_FLAGS"],
              "command": " ".join(["overlap_probe.py", *(sys.argv[1:] if argv is None else argv)]), "ms": {},
              "errors": {}}
    for name, (fn, fargs) in programs.items():
        try:
            t0 = time.perf_counter()
            compiled = jax.jit(fn).lower(*fargs).compile()
            compile_s = time.perf_counter() - t0
            if name.endswith("stream 1"):
                hlo = compiled.as_text()
                result["annotated_async_ops"] = sum(hlo.count(k) for k in ("call-start", "async-start"))
                result["stream_attribute_in_hlo"] = "_xla_stream_annotation" in hlo or "operation_queue_id" in hlo
            jax.block_until_ready(compiled(*fargs))
            times = []
            for _ in range(args.iters):
                t0 = time.perf_counter()
                jax.block_until_ready(compiled(*fargs))
                times.append(1e3 * (time.perf_counter() - t0))
            result["ms"][name] = float(np.median(times))
            print(f"{name:>26}: {result['ms'][name]:9.2f} ms (compile {compile_s:.0f} s)", flush=True)
            if args.json is not None:
                args.json.write_text(json.dumps(result, indent=2) + "\n")
        except Exception as e:   # noqa: BLE001  (an experimental XLA feature: report, do not stop)
            result["errors"][name] = f"{type(e).__name__}: {str(e)[:400]}"
            print(f"{name:>26}: failed: {result['errors'][name]}", flush=True)
    ms = result["ms"]
    if {"physics alone", "both, one stream", "both, policy on stream 1"} <= set(ms):
        # one stream runs the two back to back: its time is the sum; a perfect overlap would leave the larger
        policy_ms = ms["both, one stream"] - ms["physics alone"]
        gap = min(policy_ms, ms["physics alone"])
        result["policy_ms_derived"] = policy_ms
        result["overlap_fraction"] = (ms["both, one stream"] - ms["both, policy on stream 1"]) / gap if gap > 0 else None
    print(json.dumps(result))
    if args.json is not None:
        args.json.write_text(json.dumps(result, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
