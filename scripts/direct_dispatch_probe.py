"""What jax's call of a compiled program costs the host per argument, and what the engine's programs gain without
it. Three ways to call the same executable, round-robin in one process:

  jax     jax's own call (`jax.stages.Compiled`, its C++ path: every argument flattened and checked)
  bare    the executable's `execute_sharded` on the buffers alone, nothing checked
  engine  `engine.dispatch.Dispatch`: the same, with the arguments it was not given before checked (the engine's)

first on programs of N small arguments (1, 115, 300: the sum of them, so none is dropped), then on π0's vision
program and its call (the inputs rotating over four sets; `bare` and `engine` only where the engine makes every
program of the call direct). The outputs of the three are compared bit for bit. A GPU probe, not a test; the
`bare` rows are the first form of this probe, which ran on an H200 as `dev76b.py` (docs/BENCHMARKS.md, session 76).

    python scripts/direct_dispatch_probe.py --preset pi0_base --iters 40 --out direct_dispatch.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from profile_engine import round_robin, write_json  # noqa: E402

from pi0_jax import benchmark  # noqa: E402
from pi0_jax.config import get_config  # noqa: E402
from pi0_jax.engine import Engine, dispatch  # noqa: E402
from pi0_jax.engine.runtime import run_call, stage_tree  # noqa: E402


def bare(compiled):
    """The executable called with its buffers and nothing checked (jax's call without its front)."""
    plans = []   # `dispatch.plan`'s reading of jax's internals, made at the first call

    def call(*args):
        if not plans:
            plans.append(dispatch.plan(compiled, args))
        p, leaves = plans[0], jax.tree.leaves(args)
        out = p.execute([leaves[i] for i in p.kept]).consume_with_handlers(p.handlers)
        return jax.tree.unflatten(p.out_tree, out)
    return call


def small(n: int, iters: int) -> dict:
    """µs a call of a program summing n (8, 8) arrays, each way (the median of 5 runs of `iters` calls)."""
    w = {f"w{i:03d}": jnp.full((8, 8), i, jnp.float32) for i in range(n)}
    x = jnp.ones((8, 8))
    compiled = jax.jit(lambda w, x: x + sum(w.values())).lower(w, x).compile()
    ways = {"jax": compiled, "bare": bare(compiled), "engine": dispatch.Dispatch(compiled)}
    want = np.asarray(compiled(w, x))
    times = {k: [] for k in ways}
    for _ in range(5):
        for name, fn in ways.items():
            for _ in range(50):
                assert np.array_equal(np.asarray(fn(w, x)), want)
            start = time.perf_counter()
            for _ in range(iters):
                out = fn(w, x)
            jax.block_until_ready(out)
            times[name].append((time.perf_counter() - start) / iters * 1e6)
    return {k: round(float(np.median(v)), 2) for k, v in times.items()}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", default="pi0_base", help="the engine's preset (default: pi0_base)")
    p.add_argument("--iters", type=int, default=40, help="rounds of the round-robin (default: 40)")
    p.add_argument("--out", type=Path, help="JSON of every figure")
    args = p.parse_args()
    report = {"device": jax.devices()[0].device_kind, "small_us_per_call": {}}
    for n in (1, 115, 300):
        report["small_us_per_call"][n] = small(n, 2000)
        print(n, report["small_us_per_call"][n], flush=True)

    config = get_config(args.preset)
    engine = Engine(config, benchmark.random_params(config, 0), cache_dir=False)
    sets = [benchmark.make_inputs(config, 1, 3, 48, i) for i in range(4)]
    cameras, bucket = engine.plan(sets[0][0])
    packed = [engine.pack(obs, cameras, bucket) for obs, _ in sets]
    w, steps, sched = engine.weights, 10, engine.schedule(10)
    progs = engine.call_programs(1, steps, cameras, bucket)
    vision = engine.executable("encode_images", 1, steps, cameras, bucket)
    report["buffers"] = {p.stage: len(jax.tree.leaves(engine.stage_weights(p.stage))) for p in (*progs, vision)}
    way = {"jax": lambda p: lambda w, *a: p.compiled(stage_tree(w, p.stage, p.split), *a),
           "bare": lambda p: lambda w, *a, f=bare(p.compiled): f(stage_tree(w, p.stage, p.split), *a),
           "engine": lambda p: p}

    def call(ps, i):   # `Engine.sample_packed` on these programs
        return run_call(ps, progs[0].stage == "vision_head", w, sched, packed[i % 4], sets[i % 4][1])

    calls, count, want = {}, iter(range(10**9)), None
    for name, make in way.items():
        ps, v = tuple(make(p) for p in progs), make(vision)
        for _ in range(2):   # the engine's second call is its first direct one
            outs = [np.asarray(call(ps, 0)), np.asarray(v(w, packed[0][0]))]
        want = outs if want is None else want   # jax's, the first way
        report.setdefault("equal_to_jax", {})[name] = bool(all(np.array_equal(a, b) for a, b in zip(want, outs)))
        calls[f"vision_{name}"] = lambda v=v: v(w, packed[next(count) % 4][0])
        calls[f"call_{name}"] = lambda ps=ps: call(ps, next(count))
    report["direct_calls"] = {p.stage: p.dispatch.direct_calls for p in (*progs, vision)}
    print("buffers", report["buffers"], "equal", report["equal_to_jax"], "direct", report["direct_calls"], flush=True)
    for r in range(2):
        times = round_robin(calls, args.iters)
        report[f"round{r}"] = {k: {"median_ms": round(float(np.median(t)), 4),
                                   "p10_ms": round(float(np.percentile(t, 10)), 4)} for k, t in times.items()}
        print(r, json.dumps({k: v["median_ms"] for k, v in report[f"round{r}"].items()}), flush=True)
    write_json(args.out, report)


if __name__ == "__main__":
    main()
