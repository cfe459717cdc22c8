"""Where a call's time goes outside the GPU's kernels: the host's dispatch of one compiled engine program.

At B = 1 the fused program's kernels span about 15.3 ms on an H200 and the call took 16.7 ms (median, host-timed
with `block_until_ready`). This probe times, round-robin in one process on the engine's own weights:

  infer        the fused program (`Engine.executable("infer")`: every engine weight, 423 buffers for π0)
  null         a program of one tiny op that takes only the noise
  null_tree    the same op, with the whole weights tree passed and pruned at compile time (jit's default)
  null_kept    the same op, with the whole weights tree passed and kept as the program's arguments

It counts the fused program's kernels and writes a profiler trace of a few calls, summing the host's trace events by
name (what the host does per call, nested events counted in each) beside the GPU's span (`profile_engine.idle`).
null_kept against null is what the tree's buffers cost per call.

    python scripts/dispatch_probe.py --preset pi0_base --iters 50 --out dispatch.json
"""

from __future__ import annotations

import collections
import functools
import json
import re
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from pi0_jax import benchmark
from pi0_jax.engine import runtime
# scripts/ is on the path when this runs as a script
from profile_engine import (count_ops, gpu_kernels, idle, probe_arguments, probe_engine, round_robin, traced,
                            write_json)


def host_events(fn, calls: int) -> dict:
    """Trace `calls` calls of fn; the host's events summed by name per call, and the GPU kernels' span per call."""
    events, threads, gpu, _ = traced(fn, calls)
    rows = collections.defaultdict(lambda: [0, 0.0])
    kernels = gpu_kernels(events, threads, gpu)
    for e in events:
        if e.get("ph") != "X" or e["pid"] in gpu:
            continue
        name = re.sub(r"([._]\d+)+$", "", e["name"])[:100]
        rows[name][0] += 1
        rows[name][1] += float(e.get("dur", 0.0))
    top = sorted(rows.items(), key=lambda kv: -kv[1][1])[:40]
    span = idle(kernels, calls)
    return {"calls": calls, "span_ms": span["span_ms"], "idle_ms": span["idle_ms"],
            "host": [{"name": n, "per_call": c / calls, "us_per_call": t / calls} for n, (c, t) in top]}


def timeline(fn, calls: int, n: int = 15) -> dict:
    """Each of `calls` traced calls of fn (blocked on its output) against the GPU's kernels: `pre_us` from the call's
    start to its first kernel, `span_us` the kernels' span, `post_us` from the last kernel's end to the call's return
    (medians), and the host's events inside the pre window summed by name (the n largest, per call)."""
    def annotated():
        with jax.profiler.TraceAnnotation("probe_call"):
            return jax.block_until_ready(fn())
    events, threads, gpu, _ = traced(annotated, calls)
    spans = sorted((float(e["ts"]), float(e["ts"]) + float(e.get("dur", 0.0))) for e in events
                   if e.get("ph") == "X" and e.get("name") == "probe_call")
    kernels = [(ts, ts + dur) for ts, dur, _ in gpu_kernels(events, threads, gpu)]
    pre, span, post, rows = [], [], [], collections.defaultdict(float)
    for start, end in spans:
        inside = [k for k in kernels if start <= k[0] and k[1] <= end]
        if not inside:
            continue
        first, last = inside[0][0], max(k[1] for k in inside)
        pre.append(first - start)
        span.append(last - first)
        post.append(end - last)
        for e in events:
            if (e.get("ph") == "X" and e["pid"] not in gpu and e.get("name") != "probe_call"
                    and start <= float(e["ts"]) < first):
                rows[re.sub(r"([._]\d+)+$", "", e["name"])[:100]] += min(float(e.get("dur", 0.0)), first - float(e["ts"]))
    top = sorted(rows.items(), key=lambda kv: -kv[1])[:n]
    med = lambda v: float(np.median(v)) if v else float("nan")   # noqa: E731  (no kernels: not a GPU)
    return {"calls": len(pre), "pre_us": med(pre), "span_us": med(span), "post_us": med(post),
            "host_before_first_kernel": [{"name": k, "us_per_call": v / max(len(pre), 1)} for k, v in top]}


def first_dispatch(calls: dict, iters: int) -> dict:
    """Untraced µs until each call's dispatch returns (medians), the GPU idle before it in three ways: after
    `block_until_ready` on the previous call's output (a robot's loop: the host thread slept), after polling
    `is_ready` on it instead (the thread stayed awake), and right behind the previous call's dispatch with the GPU
    still busy (back to back)."""
    def ready(out):
        return all(x.is_ready() for x in jax.tree.leaves(out))

    rows = {}
    for name, fn in calls.items():
        times = {"after_block": [], "after_spin": [], "back_to_back": []}
        for i in range(iters + 3):
            jax.block_until_ready(fn())
            start = time.perf_counter()
            out = fn()
            mid = time.perf_counter()
            jax.block_until_ready(out)
            prev = fn()
            while not ready(prev):
                pass
            spin = time.perf_counter()
            out = fn()
            spun = time.perf_counter()
            again = fn()
            end = time.perf_counter()
            jax.block_until_ready((out, again))
            if i >= 3:
                times["after_block"].append(mid - start)
                times["after_spin"].append(spun - spin)
                times["back_to_back"].append(end - spun)
        rows[name] = {k: round(float(np.median(v)) * 1e6, 1) for k, v in times.items()}
    return rows


def print_host(title: str, t: dict, n: int) -> None:
    """`host_events`' n largest rows under a title."""
    print(title, flush=True)
    for row in t["host"][:n]:
        print(f"   {row['us_per_call']:9.1f} us  x{row['per_call']:7.1f}  {row['name']}", flush=True)


def dispatch_calls(engine, args, w, sched, noise, cameras, bucket, inputs) -> dict:
    """`first_dispatch`'s calls: each program of the engine's call on its inputs, a one-op program that keeps the
    vision head's weights as arguments (its buffers without its kernels), a one-op program, and the call."""
    progs = engine.call_programs(args.batch, args.steps, cameras, bucket)
    calls, x = {}, inputs[0]
    for prog in progs:   # each on the one before's outputs, as `Engine.sample_packed` chains them
        if prog.stage in ("vision_head", "encode_images"):
            head_w = runtime.stage_tree(w, prog.stage, prog.split)
            kept = jax.jit(lambda w, x: x * 2.0, keep_unused=True).lower(head_w, noise).compile()
            calls["one_op_with_its_weights"] = functools.partial(kept, head_w, noise)
        given = {"vision_head": (w, x), "encode_images": (w, x), "vision_tail": (w, *x),
                 "denoise_rest": (w, sched, *x)}.get(prog.stage, (w, sched, x, *inputs[1:], noise))
        calls[prog.stage] = functools.partial(prog, *given)
        x = prog(*given)
    null = jax.jit(lambda x: x * 2.0).lower(noise).compile()
    calls["one_op"] = functools.partial(null, noise)
    calls["call"] = functools.partial(engine.sample_packed, inputs, noise, args.steps, cameras, bucket)
    return calls


def main() -> None:
    p = probe_arguments(__doc__, iters=50, out="the times, kernel counts and the host's events")
    p.add_argument("--dump-hlo", type=Path, default=None, help="write the fused program's optimized HLO here")
    p.add_argument("--timeline", action="store_true",
                   help="also each call's time to its first kernel and after its last one, from a trace (`timeline`), "
                        "for the programs above and the engine's call (two programs)")
    p.add_argument("--first-dispatch", action="store_true",
                   help="only the untraced time to each program's dispatch return (`first_dispatch`): the call's "
                        "vision programs, one-op programs taking their weights, and the engine's call")
    args = p.parse_args()

    _, engine, noise, cameras, bucket, inputs = probe_engine(args)
    w, sched = engine.weights, engine.schedule(args.steps)
    if args.first_dispatch:
        report = {"preset": args.preset, "batch": args.batch, "env": benchmark.environment(),
                  "first_dispatch_us": first_dispatch(dispatch_calls(engine, args, w, sched, noise, cameras, bucket,
                                                                     inputs), args.iters)}
        print(json.dumps(report["first_dispatch_us"], indent=1), flush=True)
        write_json(args.out, report)
        return
    infer = engine.executable("infer", args.batch, args.steps, cameras, bucket)

    def tiny(w, x):
        return x * 2.0

    null = jax.jit(lambda x: x * 2.0).lower(noise).compile()
    pruned = jax.jit(tiny).lower(w, noise).compile()
    kept = jax.jit(tiny, keep_unused=True).lower(w, noise).compile()
    calls = {"infer": lambda: infer(w, sched, *inputs, noise),
             "null": lambda: null(noise), "null_tree": lambda: pruned(w, noise), "null_kept": lambda: kept(w, noise),
             "copy_only": lambda: jnp.copy(noise)}
    counts = {comp: c for comp, c in count_ops(infer.as_text()).items()
              if comp.startswith("ENTRY") or c["fusion"] + c["custom-call"] > 20}
    print("infer", json.dumps(counts), flush=True)
    if args.dump_hlo:
        args.dump_hlo.mkdir(parents=True, exist_ok=True)
        (args.dump_hlo / "infer.hlo.txt").write_text(infer.as_text())
    times = {k: [t * 1e3 for t in v] for k, v in round_robin(calls, args.iters).items()}   # µs
    report = {"preset": args.preset, "batch": args.batch, "steps": args.steps, "env": benchmark.environment(),
              "buffers": len(jax.tree.leaves(w)), "hlo_counts": counts,
              "median_us": {k: float(np.median(v)) for k, v in times.items()},
              "p10_p90_us": {k: [float(np.percentile(v, q)) for q in (10, 90)] for k, v in times.items()}}
    print(json.dumps({k: report[k] for k in ("buffers", "median_us")}, indent=1), flush=True)
    for name in ("infer", "null_kept"):
        report[f"trace_{name}"] = t = host_events(calls[name], 5)
        print_host(f"{name}: the GPU's span {t['span_ms']:.3f} ms per call ({t['idle_ms']:.3f} idle); host events:",
                   t, 16)
    if args.timeline:
        report["timeline"] = {}
        for name, fn in {**calls, "call": lambda: engine.sample_packed(inputs, noise, args.steps, cameras,
                                                                       bucket)}.items():
            t = report["timeline"][name] = timeline(fn, 8)
            print(f"{name}: {t['pre_us']:.1f} us to the first kernel, span {t['span_us']:.1f}, {t['post_us']:.1f} "
                  "after the last; the host before the first kernel:", flush=True)
            for row in t["host_before_first_kernel"][:10]:
                print(f"   {row['us_per_call']:9.1f} us  {row['name']}", flush=True)
    write_json(args.out, report)


if __name__ == "__main__":
    main()
