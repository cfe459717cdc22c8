"""Does a program run slower right after another program than after itself?

`profile_engine.py --time` times each stage program after a different one, and there every program took 0.5-2.5 ms
longer than in a loop of its own (docs/BENCHMARKS.md, "The call as two programs"). This probe times one program,
blocked on its output, after a predecessor that ran (and was waited for) untimed just before it:

  vision after vision         the vision program after itself (a loop)
  vision after prefix         after the prefix fill program (an unrelated one, as in the profile's rounds)
  vision after call           after a whole call (vision, then prefix + denoise: what a robot's loop runs)
  call after call             the engine's call after itself
  call after prefix           after the prefix fill program

Then it traces 5 timed calls of the first two patterns and sums the host's events by name (`dispatch_probe`), so
what the host does differently shows.

    python scripts/order_probe.py --preset pi0_base --iters 30 --out order.json
"""

from __future__ import annotations

import json
import time

import jax
import numpy as np

from dispatch_probe import host_events, print_host   # scripts/ is on the path when this runs as a script
from pi0_jax import benchmark
from profile_engine import probe_arguments, probe_engine, write_json


def main() -> None:
    args = probe_arguments(__doc__, iters=30, out="the times and host events").parse_args()

    _, engine, noise, cameras, bucket, packed = probe_engine(args)
    w, b, n = engine.weights, args.batch, args.steps
    enc = engine.executable("encode_images", b, n, cameras, bucket)
    pre = engine.executable("fill_prefix_cache", b, n, cameras, bucket)
    tokens = enc(w, packed[0])
    programs = {"vision": lambda: enc(w, packed[0]),
                "prefix": lambda: pre(w, tokens, *packed[1:4]),
                "call": lambda: engine.sample_packed(packed, noise, n, cameras, bucket)}
    patterns = [("vision", "vision"), ("vision", "prefix"), ("vision", "call"), ("call", "call"), ("call", "prefix")]

    def after(timed: str, before: str):
        def run():
            jax.block_until_ready(programs[before]())
            start = time.perf_counter()
            jax.block_until_ready(programs[timed]())
            return (time.perf_counter() - start) * 1e3
        return run

    runs = {f"{t} after {a}": after(t, a) for t, a in patterns}
    for fn in runs.values():
        fn()
    times = {k: [] for k in runs}
    for i in range(args.iters):
        for name, fn in (runs.items() if i % 2 else reversed(runs.items())):
            times[name].append(fn())
    report = {"preset": args.preset, "batch": b, "steps": n, "env": benchmark.environment(),
              "median_ms": {k: float(np.median(v)) for k, v in times.items()},
              "p10_p90_ms": {k: [float(np.percentile(v, q)) for q in (10, 90)] for k, v in times.items()},
              "host": {}}
    print(json.dumps({k: round(v, 3) for k, v in report["median_ms"].items()}, indent=1), flush=True)
    for name in ("vision after vision", "vision after prefix"):
        t = report["host"][name] = host_events(runs[name], 5)   # the predecessor's events are in it too
        print_host(f"{name}: host events per pair of calls", t, 14)
    write_json(args.out, report)


if __name__ == "__main__":
    main()
