"""Where the time goes: kernel counts of the compiled engine programs and a jax.profiler trace.

Counts, from the optimized HLO of each stage program: fusions (one GPU kernel each), library calls (cuBLAS GEMMs,
cuDNN, ...) and copies, in the whole program and inside the denoise loop body (i.e. per step when the loop is
rolled). Optionally writes a jax.profiler trace of a few fused calls (open it in TensorBoard / Perfetto) and sums its
GPU kernels by name (`kernel_times`): what each kernel costs inside the program, and how much of the wall time the
GPU sat idle between kernels.

    python scripts/profile_engine.py --preset pi05_base --batch 1 --steps 10 [--trace DIR]
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

from pi0_jax import benchmark
from pi0_jax.config import get_config
from pi0_jax.engine import Engine


def count_ops(hlo: str) -> dict:
    """Kernel-level op counts per HLO computation ('ENTRY' and each while body)."""
    counts, current = {}, None
    for line in hlo.splitlines():
        head = re.match(r"^(ENTRY )?%?([\w.\-]+) .*\{$", line)
        if head:
            current = ("ENTRY " if head.group(1) else "") + head.group(2)
            counts[current] = {"fusion": 0, "custom-call": 0, "copy": 0, "while": 0, "other": 0}
            continue
        m = re.search(r"=.*?\b(fusion|custom-call|copy|while|convolution|dot)\(", line)
        if current and m:
            kind = m.group(1)
            counts[current][kind if kind in counts[current] else "other"] += 1
    return {k: v for k, v in counts.items() if sum(v.values())}


def kernel_times(fn, calls: int = 5, log_dir: str | None = None) -> dict:
    """Run fn() `calls` times under jax.profiler and sum the GPU kernels of the trace by name (numeric suffixes
    dropped: fusion.12 and fusion.40 are one row). Per call: kernels launched, their summed time, the host-timed wall
    time, and busy = summed / wall (1 - busy is the GPU idle between kernels: launch gaps)."""
    jax.block_until_ready(fn())
    log_dir = log_dir or tempfile.mkdtemp()
    with jax.profiler.trace(log_dir, create_perfetto_trace=True):
        start = time.perf_counter()
        for _ in range(calls):
            jax.block_until_ready(fn())
        wall = (time.perf_counter() - start) / calls
    events = json.load(gzip.open(glob.glob(f"{log_dir}/**/perfetto_trace.json.gz", recursive=True)[0]))
    events = events["traceEvents"] if isinstance(events, dict) else events
    procs = {e["pid"]: e["args"]["name"] for e in events if e.get("name") == "process_name"}
    threads = {(e["pid"], e["tid"]): e["args"]["name"] for e in events if e.get("name") == "thread_name"}
    gpu = {pid for pid, name in procs.items() if "GPU" in name.upper()}
    # kernels sit on the device's "Stream #N" lines; other device lines (XLA Ops / Modules) repeat them as spans
    gpu_lines = {key: name for key, name in threads.items() if key[0] in gpu}
    rows = collections.defaultdict(lambda: [0, 0.0])
    for e in events:
        if e.get("ph") == "X" and gpu_lines.get((e["pid"], e.get("tid")), "").startswith("Stream"):
            name = re.sub(r"([._]\d+)+$", "", e["name"])
            rows[name][0] += 1
            rows[name][1] += float(e.get("dur", 0.0))
    launched = sum(c for c, _ in rows.values()) / calls
    busy_us = sum(t for _, t in rows.values()) / calls
    top = sorted(rows.items(), key=lambda kv: -kv[1][1])
    return {"calls": calls, "wall_ms": wall * 1e3, "kernels_per_call": launched, "kernel_ms": busy_us / 1e3,
            "busy": busy_us / 1e3 / (wall * 1e3) if wall else None, "device_lines": sorted(gpu_lines.values()),
            "by_name": [{"name": n, "per_call": c / calls, "us_per_call": t / calls} for n, (c, t) in top[:60]]}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", default="pi05_base")
    p.add_argument("--dtype", default="bfloat16")
    p.add_argument("--batch", type=int, default=1)
    p.add_argument("--steps", type=int, default=10)
    p.add_argument("--cameras", type=int, default=3)
    p.add_argument("--prompt-tokens", type=int, default=20)
    p.add_argument("--no-unroll", action="store_true")
    p.add_argument("--unroll-steps", action="store_true")
    p.add_argument("--kernels", choices=["xla", "pallas"], default="xla", help="the expert's layers: XLA or Pallas")
    p.add_argument("--trace", type=Path, default=None, help="write a jax.profiler trace of 3 fused calls here")
    p.add_argument("--out", type=Path, default=None, help="JSON of the counts")
    args = p.parse_args()

    config = get_config(args.preset, dtype=args.dtype)
    engine = Engine(config, benchmark.random_params(config, 0), unroll=not args.no_unroll,
                    unroll_steps=args.unroll_steps, kernels=args.kernels, cache_dir=False)
    obs, noise = benchmark.make_inputs(config, args.batch, args.cameras, args.prompt_tokens, 0)
    cameras, bucket = engine.plan(obs)
    report = {"kernels": args.kernels}
    for stage in ("encode_images", "fill_prefix_cache", "denoise", "infer"):
        exe = engine.executable(stage, args.batch, args.steps, cameras, bucket)
        counts = count_ops(exe.as_text())
        report[stage] = counts
        print(f"== {stage}")
        for comp, c in counts.items():
            if comp.startswith("ENTRY") or c["fusion"] + c["custom-call"] > 20:
                print(f"   {comp[:60]:60s} {json.dumps(c)}")
    if args.trace:
        packed = engine.pack(obs, cameras, bucket)
        fused = engine.executable("infer", args.batch, args.steps, cameras, bucket)
        sched = engine.schedule(args.steps)
        jax.block_until_ready(fused(engine.weights, sched, *packed, jnp.copy(noise)))
        with jax.profiler.trace(str(args.trace)):
            for _ in range(3):
                jax.block_until_ready(fused(engine.weights, sched, *packed, jnp.copy(noise)))
        print(f"trace in {args.trace}")
    if args.out:
        args.out.write_text(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
