"""Where a program's dispatch goes around its CUDA graph's launch: run under `launch_shim.py` (which logs each
cuGraphLaunch's start and host time on the clock of `time.perf_counter`), it calls a program after the GPU went
idle and splits each call's host time into before the first cuGraphLaunch, the launches, and after the last one.
Programs: a chain of 128 XLA fusions in one command buffer (`graph_launch_probe.chain`) and the vision head of π0's
call (the call's first program, random full-size weights), each with the previous call's outputs kept alive during
the call and dropped before it. GPU only:

    python3 scripts/launch_shim.py --out DIR -- python3 scripts/launch_lead_probe.py --out DIR/lead.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import graph_launch_probe  # noqa: E402
from launch_shim import read_log  # noqa: E402
from profile_engine import write_json  # noqa: E402

from pi0_jax import benchmark  # noqa: E402
from pi0_jax.config import get_config  # noqa: E402
from pi0_jax.engine import Engine  # noqa: E402


def split(fn, args, log: Path, iters: int, keep: bool) -> dict:
    """keep: the previous call's outputs stay alive during the call (its outputs and temporaries then land
    elsewhere, and XLA updates the graph's nodes that use them), else they are dropped first, as `Policy.infer`
    drops them."""
    out = fn(*args)
    jax.block_until_ready(out)
    windows = []
    for _ in range(iters):
        jax.block_until_ready(out)
        if not keep:
            out = None
        time.sleep(0.002)   # the GPU idle, as a robot's call finds it
        start = time.perf_counter() * 1e6
        out = fn(*args)
        windows.append((start, time.perf_counter() * 1e6))
    jax.block_until_ready(out)
    log_rows = read_log(log)[0]   # (exec, host µs, start µs, nodes), read once after the calls
    rows = []
    for start, end in windows:
        launched = [r for r in log_rows if start <= r[2] <= end]
        if launched:
            first, last = launched[0], launched[-1]
            rows.append((first[2] - start, sum(r[1] for r in launched), end - (last[2] + last[1]), end - start,
                         len(launched), sum(r[3] for r in launched)))
    if not rows:
        return {"launches": 0}
    med = np.median(np.array(rows), axis=0)
    return {"before_first_launch_us": round(med[0], 1), "in_launches_us": round(med[1], 1),
            "after_last_launch_us": round(med[2], 1), "dispatch_us": round(med[3], 1), "launches": int(med[4]),
            "node_updates": int(med[5])}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--iters", type=int, default=30)
    p.add_argument("--no-engine", action="store_true", help="the toy programs only")
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args()
    log = Path(os.environ["SHIM_DIR"]) / "shim.log"
    rows = []
    x = jax.random.normal(jax.random.PRNGKey(0), (graph_launch_probe.ROWS, graph_launch_probe.WIDTH), jnp.bfloat16)
    chain = jax.jit(graph_launch_probe.chain("fusion", 128)).lower(x, x).compile()
    for keep in (True, False):
        rows.append({"program": "128 XLA fusions", "keep": keep, **split(chain, (x, x), log, args.iters, keep)})
        print(json.dumps(rows[-1]), flush=True)
    if args.no_engine:
        write_json(args.out, {"rows": rows, "env": benchmark.environment()})
        return
    config = get_config("pi0_base", dtype="bfloat16")
    engine = Engine(config, benchmark.random_params(config, 0), cache_dir=False)
    obs, noise = benchmark.make_inputs(config, 1, 3, 48, 0)
    cameras, bucket = engine.plan(obs)
    head = engine.executable("vision_head", 1, 10, cameras, bucket)
    images = jnp.asarray(engine.pack(obs, cameras, bucket)[0])
    for keep in (True, False):
        rows.append({"program": "π0's vision head (80 kernels)", "keep": keep,
                     **split(head, (engine.weights, images), log, args.iters, keep)})
        print(json.dumps(rows[-1]), flush=True)
    write_json(args.out, {"rows": rows, "env": benchmark.environment()})


if __name__ == "__main__":
    main()
