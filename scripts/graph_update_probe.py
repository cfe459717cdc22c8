"""What `Policy.infer` pays when its programs' buffers move: XLA re-records a CUDA graph's commands whose buffer
addresses changed since its last launch (`command_buffer::update` in a trace). Back to back, the allocator hands
each program the same addresses every call; other device work between calls can move them.

Each phase times `Policy.infer` alone (60 calls; what runs between calls is outside the clock), then traces 5
rounds and counts the graph updates and their host time per round:
- back_to_back: `Policy.infer` only;
- small_work_between: a small jax computation between calls (an 8 MB array made and dropped);
- batch_2_between: `Policy.infer_batch` of two observations between calls (a server's other batch bucket);
- engine_between: the engine's own call on the same weights between calls.
Each variant is a Policy whose programs compile with extra XLA options (`--variant`).

    python scripts/graph_update_probe.py --preset pi0_base --out graph_update_probe.json
"""

from __future__ import annotations

import argparse
import collections
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
import profile_engine  # noqa: E402
from policy_bench import EMBEDDED, observations  # noqa: E402

from pi0_jax import benchmark  # noqa: E402
from pi0_jax import normalize as nz  # noqa: E402
from pi0_jax.config import get_config  # noqa: E402
from pi0_jax.engine import Engine  # noqa: E402
from pi0_jax.ops import matmul  # noqa: E402
from pi0_jax.policy import Policy, find_tokenizer  # noqa: E402
from pi0_jax.tokenizer import PaligemmaTokenizer  # noqa: E402

VARIANTS = {"default": {}, "skip-profiled": {"xla_gpu_command_buffer_update_mode": "SKIP_PROFILED"}}
EVENTS = ("command_buffer::update", "command_buffer::execute", "cuGraphLaunch")


INFER = "graph_update_probe.infer"


def graph_events(fn, rounds: int) -> dict:
    """Per round of fn: the host events of each `EVENTS` name inside its `INFER` spans (`Policy.infer`, not the work
    between), how many and their summed µs."""
    events, _, gpu, _ = profile_engine.traced(fn, rounds)
    spans = [(float(e["ts"]), float(e["ts"]) + float(e.get("dur", 0.0))) for e in events
             if e.get("ph") == "X" and e.get("name") == INFER]
    sums = collections.defaultdict(lambda: [0, 0.0])
    for e in events:
        name = e.get("name", "")
        key = next((k for k in EVENTS if name.startswith(k)), None)
        if key and e.get("ph") == "X" and e["pid"] not in gpu and any(a <= float(e["ts"]) < b for a, b in spans):
            sums[key][0] += 1
            sums[key][1] += float(e.get("dur", 0.0))
    return {k: {"per_round": c / rounds, "us_per_round": t / rounds} for k, (c, t) in sums.items()}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", default="pi0_base", help="random weights of this preset (default: %(default)s)")
    p.add_argument("--iters", type=int, default=60, help="timed calls a phase (default: %(default)s)")
    p.add_argument("--variant", action="append", choices=list(VARIANTS), default=None,
                   help="repeatable (default: all)")
    p.add_argument("--out", type=Path, default=None, help="JSON of every phase")
    args = p.parse_args()
    config = get_config(args.preset, dtype="bfloat16")
    params = benchmark.random_params(config, 0)
    tokenizer = PaligemmaTokenizer(find_tokenizer(EMBEDDED), config.max_token_len)
    engine = Engine(config, params, cache_dir=False)
    own_options = matmul.compiler_options
    report = {"preset": args.preset, "env": benchmark.environment(), "rows": []}
    for name in args.variant or list(VARIANTS):
        extra = VARIANTS[name]
        matmul.compiler_options = lambda *a, o=extra, **kw: {**(own_options(*a, **kw) or {}), **o} or None
        try:
            policy = Policy(config, params, tokenizer, nz.Normalizer.identity(), cache_dir=False, max_batch=2)
            obs = observations(policy, 2, config.num_cameras)
            policy.warmup([1, 2], obs[0])
        except Exception as e:   # an option this jaxlib does not define
            print(json.dumps({"variant": name, "error": str(e)[:400]}), flush=True)
            report.setdefault("errors", []).append({"variant": name, "error": str(e)[:2000]})
            continue
        finally:
            matmul.compiler_options = own_options
        ref = policy.make_observation(obs[0])
        cams, bucket = engine.plan(ref)
        packed, noise = engine.pack(ref, cams, bucket), jnp.zeros((1, config.action_horizon, config.action_dim))
        host = np.ones((1024, 1024, 2), np.float32)
        between = {"back_to_back": None,
                   "small_work_between": lambda: jax.block_until_ready(jnp.asarray(host) * 2),
                   "batch_2_between": lambda: policy.infer_batch(obs),
                   "engine_between": lambda: jax.block_until_ready(
                       engine.sample_packed(packed, noise, 10, cams, bucket))}
        for phase, work in between.items():
            times = []
            for i in range(5 + args.iters):
                if work is not None:
                    work()
                start = time.perf_counter()
                policy.infer(obs[0])
                if i >= 5:
                    times.append((time.perf_counter() - start) * 1e3)

            def one_round(work=work):
                if work is not None:
                    work()
                with jax.profiler.TraceAnnotation(INFER):
                    return policy.infer(obs[0])["actions"]

            row = {"variant": name, "options": extra, "phase": phase, "median_ms": float(np.median(times)),
                   "p90_ms": float(np.percentile(times, 90)), "min_ms": float(np.min(times)),
                   "graph_events": graph_events(one_round, 5)}
            report["rows"].append(row)
            print(json.dumps({k: row[k] for k in ("variant", "phase", "median_ms", "p90_ms")}
                             | {"updates_per_round": row["graph_events"].get("command_buffer::update", {})}),
                  flush=True)
    profile_engine.write_json(args.out, report)


if __name__ == "__main__":
    main()
