"""Where the time goes: kernel counts of the compiled engine programs and a jax.profiler trace.

Counts, from the optimized HLO of each stage program: fusions (one GPU kernel each), library calls (cuBLAS GEMMs,
cuDNN, ...) and copies, in the whole program and inside the denoise loop body (i.e. per step when the loop is
rolled). Optionally writes a jax.profiler trace of a few fused calls (open it in TensorBoard / Perfetto).

    python scripts/profile_engine.py --preset pi05_base --batch 1 --steps 10 [--trace DIR]
"""

from __future__ import annotations

import argparse
import json
import re
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
