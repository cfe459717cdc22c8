"""Where a call's time goes outside the GPU's kernels: the host's dispatch of one compiled engine program.

At B = 1 the fused program's kernels span about 15.3 ms on an H200 and the call takes 16.7 ms (median, host-timed
with `block_until_ready`). This probe times, round-robin in one process on the engine's own weights:

  infer        the fused program as `Engine.sample_actions` calls it (the weights tree, 559 buffers for π0)
  null         a program of one tiny op that takes only the noise
  null_tree    the same op, with the whole weights tree passed and pruned at compile time (jit's default)
  null_kept    the same op, with the whole weights tree passed and kept as the program's arguments

and writes a profiler trace of a few `infer` calls, summing the host's trace events by name (what the host does
per call, nested events counted in each) beside the GPU's span (`profile_engine.idle`). The difference between null_kept and null is what
the tree's buffers cost per call.

    python scripts/dispatch_probe.py --preset pi0_base --iters 50 --out dispatch.json
"""

from __future__ import annotations

import argparse
import collections
import glob
import gzip
import json
import re
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from pi0_jax import benchmark
from pi0_jax.config import get_config
from pi0_jax.engine import Engine, programs
from pi0_jax.ops import matmul
from profile_engine import count_ops, idle   # scripts/ is on the path when this runs as a script


def host_events(fn, calls: int) -> dict:
    """Trace `calls` calls of fn; the host's events summed by name per call, and the GPU kernels' span per call."""
    jax.block_until_ready(fn())
    log_dir = tempfile.mkdtemp()
    with jax.profiler.trace(log_dir, create_perfetto_trace=True):
        for _ in range(calls):
            jax.block_until_ready(fn())
    events = json.load(gzip.open(glob.glob(f"{log_dir}/**/perfetto_trace.json.gz", recursive=True)[0]))
    events = events["traceEvents"] if isinstance(events, dict) else events
    procs = {e["pid"]: e["args"]["name"] for e in events if e.get("name") == "process_name"}
    threads = {(e["pid"], e["tid"]): e["args"]["name"] for e in events if e.get("name") == "thread_name"}
    gpu = {pid for pid, name in procs.items() if "GPU" in name.upper()}
    rows = collections.defaultdict(lambda: [0, 0.0])
    kernels = []
    for e in events:
        if e.get("ph") != "X":
            continue
        line = threads.get((e["pid"], e.get("tid")), "")
        if e["pid"] in gpu:
            if line.startswith("Stream"):
                kernels.append((float(e["ts"]), float(e.get("dur", 0.0)), e["name"]))
            continue
        name = re.sub(r"([._]\d+)+$", "", e["name"])[:100]
        rows[name][0] += 1
        rows[name][1] += float(e.get("dur", 0.0))
    top = sorted(rows.items(), key=lambda kv: -kv[1][1])[:40]
    span = idle(kernels, calls)
    return {"calls": calls, "span_ms": span["span_ms"], "idle_ms": span["idle_ms"],
            "host": [{"name": n, "per_call": c / calls, "us_per_call": t / calls} for n, (c, t) in top]}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", default="pi0_base", help="model preset, random weights (default: %(default)s)")
    p.add_argument("--batch", type=int, default=1)
    p.add_argument("--steps", type=int, default=10)
    p.add_argument("--prompt-tokens", type=int, default=48)
    p.add_argument("--iters", type=int, default=50, help="timed calls of each program (default: %(default)s)")
    p.add_argument("--pack-skip", action="append", default=None,
                   help="a variant of the fused program that takes its 1-D weights packed into one buffer per dtype, "
                        "except those whose key path matches this regex ('' packs all); repeat it to compare")
    p.add_argument("--dump-hlo", type=Path, default=None, help="write each variant's optimized HLO here")
    p.add_argument("--out", type=Path, default=None, help="JSON of the times and the host's events")
    args = p.parse_args()

    config = get_config(args.preset)
    engine = Engine(config, benchmark.random_params(config, 0), cache_dir=False)
    obs, noise = benchmark.make_inputs(config, args.batch, 3, args.prompt_tokens, 0)
    cameras, bucket = engine.plan(obs)
    packed = engine.pack(obs, cameras, bucket)
    w, sched = engine.weights, engine.schedule(args.steps)
    infer = engine.executable("infer", args.batch, args.steps, cameras, bucket)

    def tiny(w, x):
        return x * 2.0

    def packed_infer(skip: str):
        """The fused program with every 1-D weight (biases, norm scales) whose key path does not match the regex
        `skip` packed into one buffer per dtype, unpacked inside by static slices."""
        flat, tdef = jax.tree_util.tree_flatten_with_path(w)
        spec, big, tables = [], [], collections.defaultdict(list)
        for path, x in flat:
            if x.ndim == 1 and not (skip and re.search(skip, jax.tree_util.keystr(path))):
                key = str(x.dtype)
                spec.append(("table", key, sum(a.size for a in tables[key]), x.size))
                tables[key].append(x)
            else:
                spec.append(("big", len(big)))
                big.append(x)
        tables = {k: jnp.concatenate(v) for k, v in tables.items()}

        def fn(big, tables, *rest):
            leaves = [big[s[1]] if s[0] == "big" else tables[s[1]][s[2]:s[2] + s[3]] for s in spec]
            return programs.infer(config, jax.tree.unflatten(tdef, leaves), *rest, num_steps=args.steps,
                                  unroll=True, unroll_steps=False, attention=engine.attention, kernels=engine.kernels)

        exe = jax.jit(fn, donate_argnums=(8,)).lower(big, tables, sched, *packed, noise).compile(
            matmul.compiler_options(w, engine.gemm))
        return exe, big, tables

    null = jax.jit(lambda x: x * 2.0).lower(noise).compile()
    pruned = jax.jit(tiny).lower(w, noise).compile()
    kept = jax.jit(tiny, keep_unused=True).lower(w, noise).compile()
    variants = {"infer": (infer, None, None)}
    for skip in args.pack_skip or []:
        variants[f"packed skip={skip}"] = packed_infer(skip)
    counts = {name: {comp: c for comp, c in count_ops(exe.as_text()).items()
                     if comp.startswith("ENTRY") or c["fusion"] + c["custom-call"] > 20}
              for name, (exe, _, _) in variants.items()}
    for i, (name, c) in enumerate(counts.items()):
        print(name, json.dumps(c), flush=True)
        if args.dump_hlo:
            args.dump_hlo.mkdir(parents=True, exist_ok=True)
            (args.dump_hlo / f"infer_{i}.hlo.txt").write_text(f"// {name}\n" + variants[name][0].as_text())
    calls = {"infer": lambda: infer(w, sched, *packed, jnp.copy(noise))}
    for name, (exe, big, tables) in list(variants.items())[1:]:
        calls[name] = lambda exe=exe, big=big, tables=tables: exe(big, tables, sched, *packed, jnp.copy(noise))
    calls |= {"null": lambda: null(noise), "null_tree": lambda: pruned(w, noise), "null_kept": lambda: kept(w, noise),
              "copy_only": lambda: jnp.copy(noise)}
    times = {k: [] for k in calls}
    for i in range(3 + args.iters):
        for name, fn in (calls.items() if i % 2 else reversed(calls.items())):
            start = time.perf_counter()
            jax.block_until_ready(fn())
            if i >= 3:
                times[name].append((time.perf_counter() - start) * 1e6)
    ref = np.asarray(calls["infer"](), np.float64)
    diffs = {k: float(np.max(np.abs(np.asarray(calls[k](), np.float64) - ref))) for k in list(variants)[1:]}
    report = {"preset": args.preset, "batch": args.batch, "steps": args.steps, "env": benchmark.environment(),
              "weight_buffers": len(jax.tree.leaves(w)), "hlo_counts": counts, "max_abs_vs_infer": diffs,
              "buffers": {k: len(v[1]) + len(v[2]) for k, v in list(variants.items())[1:]},
              "median_us": {k: float(np.median(v)) for k, v in times.items()},
              "p10_p90_us": {k: [float(np.percentile(v, q)) for q in (10, 90)] for k, v in times.items()}}
    print(json.dumps({k: report[k] for k in ("weight_buffers", "buffers", "max_abs_vs_infer", "median_us")}, indent=1),
          flush=True)
    for name in ("infer", "null_kept"):
        report[f"trace_{name}"] = t = host_events(calls[name], 5)
        print(f"{name}: the GPU's span {t['span_ms']:.3f} ms per call ({t['idle_ms']:.3f} idle); host events:", flush=True)
        for row in t["host"][:25]:
            print(f"   {row['us_per_call']:9.1f} us  x{row['per_call']:7.1f}  {row['name']}", flush=True)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
