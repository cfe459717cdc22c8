"""Probe: the denoise step's residual GEMMs (out-projection, down) as one cluster split-K kernel, against the Triton
split-K partials with XLA's epilogue (sum, gate, residual), at the step's shape (64 rows, B = 1).

Each variant runs a chain of 18 GEMMs (one per layer, each with its own weights, so nothing stays in L2) as one
jitted program, x <- x + y @ w_l, passed over `--repeats` times in that program; the time per GEMM is the
program's median over calls / (18 x repeats). Variants that fail to
compile are recorded and skipped.

    python3 scripts/cluster_gemm_probe.py --out probe.json
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
import traceback

import jax
import jax.numpy as jnp
import numpy as np

from pi0_jax.ops import cluster_gemm, expert_kernels
from profile_engine import kernel_times
from pi0_jax.ops.expert_kernels import Blocks
from pi0_jax.ops.mosaic_gemm import Launch


def _time(fn, args, iters):
    out = fn(*args)
    jax.block_until_ready(out)
    times = []
    for _ in range(iters):
        t = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t)
    return statistics.median(times), out


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--layers", type=int, default=18, help="GEMMs in the chain (each its own weights)")
    p.add_argument("--repeats", type=int, default=10, help="passes over the chain inside one program (amortises the "
                   "host's dispatch)")
    p.add_argument("--iters", type=int, default=30, help="timed calls of the chain per variant")
    p.add_argument("--gated", action="store_true", help="also time the gated epilogue (π0.5's adaRMS gate)")
    p.add_argument("--out", default=None, help="JSON file for the results")
    args = p.parse_args()

    rows, d = 64, 1024
    rng = np.random.default_rng(0)
    results = []
    for gemm_name, k, triton_gemm in (("down", 4096, Blocks().down), ("out", 2048, Blocks().out)):
        ws = [jnp.asarray(rng.normal(0, k**-0.5, (k, d)), jnp.bfloat16) for _ in range(args.layers)]
        ys = [jnp.asarray(rng.normal(0, 1, (rows, k)), jnp.bfloat16) for _ in range(args.repeats)]
        x0 = jnp.asarray(rng.normal(0, 1, (rows, d)), jnp.bfloat16)
        gate = jnp.asarray(rng.normal(1, 0.1, (d,)), jnp.bfloat16)
        # the reference: XLA in f32
        ref = x0.astype(jnp.float32) + sum(y.astype(jnp.float32) @ w.astype(jnp.float32) for y in ys for w in ws)

        def chain(step):
            def run(ys, x, *ws):
                for y in ys:   # a y of its own per pass: XLA would merge equal GEMMs that take no x
                    for w in ws:
                        x = step(y, w, x)
                return x
            return jax.jit(run)

        variants = {"triton+xla": lambda y, w, x: expert_kernels.matmul_residual(y, w, x, gemm=triton_gemm)}
        for splits in (4, 8):
            variants[f"mosaic partials s{splits}+xla"] = (
                lambda y, w, x, launch=Launch(64, splits, 4): expert_kernels.matmul_residual(
                    y, w, x, gemm=triton_gemm, mosaic=launch))
        for cols, splits, stages, tk, ablate in ((64, 4, 4, 64, ""), (64, 4, 4, 64, "launch"), (64, 4, 4, 64, "sync"),
                                                 (64, 4, 4, 128, ""), (64, 4, 2, 256, ""), (64, 8, 2, 64, ""),
                                                 (64, 8, 2, 64, "launch"), (64, 8, 2, 128, "")):
            launch = cluster_gemm.ClusterLaunch(cols, splits, stages, tk, ablate)
            if (k // splits) % tk or (k // splits) // tk < 1:
                continue
            variants[f"cluster c{cols} s{splits} st{stages} tk{tk} {ablate}".strip()] = (
                lambda y, w, x, launch=launch: cluster_gemm.matmul_residual(y, w, x, launch=launch))
        if args.gated:
            variants["triton+xla gated"] = lambda y, w, x: expert_kernels.matmul_residual(
                y, w, x, gate[None], 0, gemm=triton_gemm)
            variants["cluster gated c64 s4"] = lambda y, w, x: cluster_gemm.matmul_residual(y, w, x, gate)
        for name, step in variants.items():
            row = {"gemm": gemm_name, "k": k, "n": d, "rows": rows, "variant": name}
            try:
                fn = chain(step)
                t, out = _time(fn, (ys, x0, *ws), args.iters)
                gemms = args.layers * args.repeats
                row["us_per_gemm"] = 1e6 * t / gemms
                trace = kernel_times(lambda: fn(ys, x0, *ws), 3)
                row["trace_span_us_per_gemm"] = 1e3 * trace["span_ms"] / gemms
                row["kernels"] = {k["name"]: round(k["us_per_call"] / gemms, 3) for k in trace["by_name"]}
                if "gated" not in name and not any(a in name for a in ("launch", "sync")):
                    err = jnp.linalg.norm(out.astype(jnp.float32) - ref) / jnp.linalg.norm(ref)
                    row["rel_l2_vs_f32"] = float(err)
            except Exception as e:  # a launch that does not compile is recorded, the others still run
                row["error"] = f"{type(e).__name__}: {str(e)[:2000]}"
                traceback.print_exc()
            print(json.dumps(row), flush=True)
            results.append(row)
    info = {"device": str(jax.devices()[0].device_kind), "jax": jax.__version__, "results": results}
    if args.out:
        with open(args.out, "w") as f:
            json.dump(info, f, indent=1)


if __name__ == "__main__":
    main()
