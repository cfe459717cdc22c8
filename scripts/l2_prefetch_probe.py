"""Would the denoise step's GEMMs run faster from L2? A weight prefetch riding on a latency-bound kernel, measured.

At B = 1 the step's attention kernel reads 0.85 MB in about 6.5 us while DRAM idles, and the out-projection (4.2 MB)
and gate/up (16.8 MB) kernels after it stream their weights at 20-50 % of the bandwidth (docs/BENCHMARKS.md,
"A persistent kernel for a layer's four GEMMs"). If those weights were already in L2 (50 MB), extra programs of the
attention kernel could have loaded them meanwhile. This probe measures the two halves of that bet, per layer, for
18 layers of distinct weights (378 MB, so nothing stays in L2 from one call to the next):

  gemms        the engine's out-projection and gate/up kernels (`ops.expert_kernels`, Pallas expert at B = 1)
  prefetch     a Pallas kernel whose programs read the same weights once (summed, so the loads stay)
  both         prefetch, then the GEMMs, layer by layer: (both - prefetch) is what the GEMMs cost from L2

`--trace` also times each kernel under the profiler. Use it: the host-timed chains hold the host's share of each
call, and on 2026-11-26 they showed the GEMMs 10 us a layer faster after the prefetch where the trace showed the
same kernel times (docs/BENCHMARKS.md, session 30).

GPU only.

    python scripts/l2_prefetch_probe.py --out l2.json
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as plgpu

from pi0_jax.ops import expert_kernels as ek

sys.path.insert(0, str(Path(__file__).parent))
from bench_kernels import median_ms  # noqa: E402
from profile_engine import kernel_times  # noqa: E402

M, D, A, F = 64, 1024, 2048, 4096  # rows, width, attention width, MLP hidden (π0's expert)
COLS = 1024  # a prefetch row: the weights viewed as (rows, 1024)


def _prefetch_kernel(*refs, rows: int, block: int, programs: list[int]):
    """Program p reads `rows` rows of one weight (the first programs[0] programs the first weight, ...)."""
    *w_refs, o_ref = refs
    pid = pl.program_id(0)
    start = 0
    for w_ref, n in zip(w_refs, programs):
        @pl.when((pid >= start) & (pid < start + n))
        def _(w_ref=w_ref, base=start):
            acc = jnp.zeros((block, COLS), jnp.float32)
            for b in range(rows // block):
                acc += w_ref[pl.ds((pid - base) * rows + b * block, block), :].astype(jnp.float32)
            o_ref[pl.ds(pid, 1)] = jnp.sum(acc, keepdims=True)[0]
        start += n


def prefetch(ws, rows: int, block: int, warps: int):
    """A kernel reading every weight once: each viewed as (n, 1024), `rows` rows a program."""
    views = [w.reshape(-1, COLS) for w in ws]
    programs = [v.shape[0] // rows for v in views]
    kernel = functools.partial(_prefetch_kernel, rows=rows, block=block, programs=programs)
    return pl.pallas_call(kernel, grid=(sum(programs),),
                          out_shape=jax.ShapeDtypeStruct((sum(programs),), jnp.float32),
                          compiler_params=plgpu.CompilerParams(num_warps=warps, num_stages=1),
                          name="weight_prefetch")(*views)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", help="JSON file to write")
    p.add_argument("--layers", type=int, default=18, help="layers of distinct weights (default: %(default)s)")
    p.add_argument("--rows", default="64,128", help="comma list: weight rows a prefetch program reads")
    p.add_argument("--block", type=int, default=16, help="rows a prefetch load takes (default: %(default)s)")
    p.add_argument("--warps", type=int, default=4, help="warps a prefetch program (default: %(default)s)")
    p.add_argument("--trace", action="store_true",
                   help="also each variant's kernels under the profiler: time per kernel name and layer")
    p.add_argument("--iters", type=int, default=30, help="timed calls per variant (default: %(default)s)")
    args = p.parse_args()
    if jax.default_backend() != "gpu":
        raise SystemExit("l2_prefetch_probe needs a GPU")
    ks = jax.random.split(jax.random.PRNGKey(0), 4)
    dt = jnp.bfloat16
    y = jax.random.normal(ks[0], (M, A), jnp.float32).astype(dt)
    x = jax.random.normal(ks[1], (M, D), jnp.float32).astype(dt)
    w_out = [(jax.random.normal(k, (A, D), jnp.float32) * 0.02).astype(dt)
             for k in jax.random.split(ks[2], args.layers)]
    w_gu = [(jax.random.normal(k, (D, 2 * F), jnp.float32) * 0.02).astype(dt)
            for k in jax.random.split(ks[3], args.layers)]
    blocks = ek.Blocks()
    mods = jnp.zeros((2, D), dt)

    def gemms(y, x, wo, wg):
        x2 = ek.matmul_residual(y, wo, x, gemm=blocks.out, blocks=blocks, name="expert_out")
        return ek.norm_geglu(x2, mods, 0, False, wg, width=D, blocks=blocks)

    def chain(with_gemms: bool, rows: int | None):
        def run(y, x, wos, wgs):
            outs = []
            for wo, wg in zip(wos, wgs):
                if rows:
                    s = prefetch([wo, wg], rows, args.block, args.warps)
                    y = y + (s[0] * 0).astype(dt)  # the GEMMs after the prefetch (its sum is 0 * finite)
                if with_gemms:
                    outs.append(gemms(y, x, wo, wg)[0, 0])
            return jnp.stack(outs) if outs else y
        return jax.jit(run)

    variants = {"gemms": chain(True, None)}
    for rows in (int(r) for r in args.rows.split(",")):
        variants[f"prefetch rows={rows}"] = chain(False, rows)
        variants[f"both rows={rows}"] = chain(True, rows)
    times = {k: [] for k in variants}
    for _ in range(3):
        for k, fn in variants.items():
            times[k].append(median_ms(fn, (y, x, w_out, w_gu), args.iters // 3 or 1, warmup=1))
    res = {"device": jax.devices()[0].device_kind, "jax": jax.__version__, "layers": args.layers,
           "date": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()), "args": vars(args), "rows": []}
    per = {k: float(np.median(v)) * 1e3 / args.layers for k, v in times.items()}
    for k in variants:
        res["rows"].append({"variant": k, "us_per_layer": per[k], "rounds_ms": times[k]})
        print(f"{k:24s} {per[k]:7.2f} us/layer", flush=True)
    for rows in (int(r) for r in args.rows.split(",")):
        warm = per[f"both rows={rows}"] - per[f"prefetch rows={rows}"]
        print(f"rows={rows}: the GEMMs after the prefetch {warm:.2f} us/layer, cold {per['gemms']:.2f} "
              "(host-timed: see --trace)", flush=True)
    if args.trace:
        res["kernels"] = {}
        for k, fn in variants.items():
            t = kernel_times(lambda fn=fn: jax.block_until_ready(fn(y, x, w_out, w_gu)), 5)
            res["kernels"][k] = t
            names = ", ".join(f"{r['name']} {r['us_per_call'] / args.layers:.2f}" for r in t["by_name"][:6])
            print(f"{k:24s} kernels per layer (us): {names}; span {t['span_ms'] * 1e3 / args.layers:.2f}, "
                  f"idle {t['idle_ms'] * 1e3 / args.layers:.2f}", flush=True)
    if args.out:
        with open(args.out, "w") as fh:
            json.dump(res, fh, indent=1)


if __name__ == "__main__":
    main()
