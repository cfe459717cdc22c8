"""Can a program read per-layer GEMM weights as static slices of one stacked buffer without copying them?

Each weight buffer a call takes costs its host about 1.7 us before the first kernel (docs/BENCHMARKS.md, "The
host's share of a call"). The engine's GEMM weights are one buffer per layer and GEMM: stacked, a call would take
a few. This probe runs 18 layers of x <- x + (x @ w_i)[:, :D] with w_i (a) separate buffers, (b) static slices
of one stacked (18, D, F) buffer, (c) the same with XLA's dynamic-slice fusion on (cuBLAS reading a slice in
place), each with XLA's choice of GEMM and with cuBLAS only, and reports each program's copies / slice fusions from
the optimized HLO and its median time.

    python scripts/slice_probe.py --rows 816 --width 2048 --hidden 8192
"""

from __future__ import annotations

import argparse
import json
import re
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--rows", type=int, default=816)
    p.add_argument("--width", type=int, default=2048)
    p.add_argument("--hidden", type=int, default=8192)
    p.add_argument("--layers", type=int, default=18)
    p.add_argument("--iters", type=int, default=50)
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args()

    key = jax.random.key(0)
    d, f, n = args.width, args.hidden, args.layers
    stacked = (jax.random.normal(key, (n, d, f), jnp.float32) * d**-0.5).astype(jnp.bfloat16)
    separate = [stacked[i] + 0 for i in range(n)]
    x = jax.random.normal(key, (args.rows, d), jnp.bfloat16)

    def layers(ws, x):
        for w in ws:
            x = x + (x @ w)[:, :d]
        return x

    def from_stack(w, x):
        return layers([w[i] for i in range(n)], x)

    variants = {}
    for lib, lib_opts in (("xla", {}), ("cublas", {"xla_gpu_enable_triton_gemm": False})):
        variants[f"separate_{lib}"] = (layers, separate, lib_opts or None)
        variants[f"stacked_{lib}"] = (from_stack, stacked, lib_opts or None)
        variants[f"stacked_{lib}_dsf"] = (from_stack, stacked, {**lib_opts, "xla_gpu_enable_dynamic_slice_fusion": True})
    report = {"shape": [args.rows, d, f, n], "variants": {}}
    calls = {}
    for name, (fn, w, options) in variants.items():
        try:
            exe = jax.jit(fn).lower(w, x).compile(options)
        except Exception as e:   # an option this jaxlib does not define
            report["variants"][name] = {"error": str(e)[:300]}
            print(name, "failed:", str(e)[:300], flush=True)
            continue
        hlo = exe.as_text()
        entry = hlo[hlo.index("ENTRY"):]
        kinds = {k: len(re.findall(k, entry)) for k in (r" fusion\(", r" custom-call\(", r" copy\(", r"slice",
                                                          r"dynamic_slice_fusion|address_computation")}
        report["variants"][name] = {"hlo": kinds, "buffers": len(jax.tree.leaves(w))}
        calls[name] = (exe, w)
        print(name, json.dumps(kinds), flush=True)
    ref = None
    times = {k: [] for k in calls}
    for i in range(3 + args.iters):
        for name, (exe, w) in calls.items():
            start = time.perf_counter()
            out = jax.block_until_ready(exe(w, x))
            if i >= 3:
                times[name].append((time.perf_counter() - start) * 1e6)
            if i == 0:
                ref = out if ref is None else ref
                report["variants"][name]["max_abs_vs_first"] = float(jnp.max(jnp.abs(out.astype(jnp.float32)
                                                                                       - ref.astype(jnp.float32))))
    for name, t in times.items():
        report["variants"][name]["median_us"] = float(np.median(t))
    print(json.dumps(report, indent=1), flush=True)
    if args.out:
        args.out.write_text(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
