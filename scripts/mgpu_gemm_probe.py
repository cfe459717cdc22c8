"""The denoise step's four GEMM shapes (π0 full size, B = 1: 64 rows) on the Pallas Mosaic GPU kernel
(`pi0_jax.ops.mosaic_gemm`: TMA, wgmma, a producer warpgroup streaming the weight tiles STAGES deep) against the
engine's Triton split-K kernel and XLA's dot.

The Triton kernels run at 24-44 % of the weight-read bandwidth (docs/BENCHMARKS.md, "Launch parameters inside the
step"): a program issues its loads and waits, so the bytes in flight are set by the programs resident. A TMA
pipeline keeps STAGES tiles in flight per SM whatever the registers; this probe measures whether that closes the gap.

Each variant runs on `--copies` independent weights in one program (the caches see a layer's weights once, as in the
step) and is timed as the program's median over `--iters` calls divided by the copies, interleaved across variants,
and by its kernels' durations in a profiler trace. Each is checked against XLA's f32-accumulated product first.
(Run 32 also timed the norm inside the kernel: `git show 092647b:scripts/mgpu_gemm_probe.py`.)

    python scripts/mgpu_gemm_probe.py --out mgpu_gemm.json
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import sys
import time
import traceback
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from pi0_jax.ops import expert_kernels as ek
from pi0_jax.ops import layout, mosaic_gemm

sys.path.insert(0, str(Path(__file__).parent))
from bench_kernels import interleaved_ms  # noqa: E402
from profile_engine import kernel_times  # noqa: E402

# π0 full size, B = 1 (64 rows): (name, K, N, the engine's Triton launch)
SHAPES = [("qkv", 1024, 2560, ek.Gemm(128, 4)), ("attn_out", 2048, 1024, ek.Gemm(64, 4)),
          ("gate_up", 1024, 8192, ek.Gemm(128, 4, 1)), ("down", 4096, 1024, ek.Gemm(64, 8))]

# Mosaic launches per shape: (cols per warpgroup, warpgroups, splits, stages); each gives 64-256 CTAs
MGPU = {"qkv": [(64, 1, 4, 4), (64, 1, 2, 6), (64, 2, 4, 4), (128, 1, 4, 4), (64, 1, 8, 2)],
        "attn_out": [(64, 1, 8, 4), (64, 1, 4, 6), (64, 2, 8, 4), (128, 1, 8, 4), (64, 1, 16, 2)],
        "gate_up": [(64, 1, 1, 8), (64, 1, 2, 4), (64, 2, 2, 4), (128, 1, 2, 4), (64, 2, 1, 8), (128, 1, 1, 6)],
        "down": [(64, 1, 8, 4), (64, 1, 4, 8), (64, 2, 8, 4), (128, 1, 8, 4), (64, 1, 16, 4)]}


def _stages(stages: int, tk: int) -> int:
    """The pipeline depth that keeps a launch's shared memory when each step brings tk rows instead of 64."""
    return max(2, stages * mosaic_gemm.TK // tk)


def probe_shape(name, k, n, triton, args, rows: int = 64):
    key = jax.random.key([s[0] for s in SHAPES].index(name))
    kx, kw = jax.random.split(key)
    x = (jax.random.normal(kx, (rows, k), jnp.float32)).astype(jnp.bfloat16)
    ws = [(jax.random.normal(w, (k, n), jnp.float32) * k**-0.5).astype(jnp.bfloat16)
          for w in jax.random.split(kw, args.copies)]
    want = np.asarray(jnp.dot(x, ws[0], preferred_element_type=jnp.float32))
    res, calls = {}, {}

    def total(parts):   # the split sum in f32 (the engine's epilogue fusion does it)
        return parts.astype(jnp.float32).sum(0)

    variants = {"xla": lambda x, w: jnp.dot(x, w, preferred_element_type=jnp.float32)[None],
                f"triton {triton.cols}x{triton.splits}s{triton.stages}":
                    lambda x, w: ek.matmul_partials(x, w, gemm=triton, name=f"expert_{name}")[0]}
    launches = [(mosaic_gemm.Launch(cols, splits, stages, wgs), f"mgpu {cols}x{wgs}wg {splits}s {stages}st")
                for cols, wgs, splits, stages in MGPU[name]]
    if args.tk:   # the first launch of the sweep at each pipeline step's contraction rows
        first = launches[0][0]
        launches = [(dataclasses.replace(first, tk=tk, stages=_stages(first.stages, tk)), f"mgpu {first.cols}x"
                     f"{first.wgs}wg {first.splits}s {_stages(first.stages, tk)}st tk{tk}") for tk in args.tk]
    for launch, label in launches:
        variants[label] = functools.partial(lambda x, w, launch: mosaic_gemm.partials(x, w, launch), launch=launch)
    if name == "gate_up" and args.tk:   # the engine's gate/up: GeGLU in the epilogue (checked against XLA's)
        hidden = n // 2
        g, u = layout.split_gate_up(jnp.asarray(want))   # the engine's layout: gate and up in blocks of 32
        geglu_want = np.asarray(jax.nn.gelu(g, approximate=True) * u)
        for tk in args.tk:
            base = ek.Blocks().mosaic_mlp
            launch = dataclasses.replace(base, tk=tk, stages=_stages(base.stages, tk))
            try:
                got = np.asarray(jax.jit(mosaic_gemm.geglu, static_argnums=2)(x, ws[0], launch), np.float32)
                err = float(np.abs(got - geglu_want).max() / np.abs(geglu_want).max())
                prog = jax.jit(lambda x, ws, launch=launch: [mosaic_gemm.geglu(x, w, launch) for w in ws])
                prog(x, ws)
                label = f"mgpu geglu {launch.cols} {launch.stages}st tk{tk}"
                calls[label] = functools.partial(prog, x, ws)
                res[label] = {"max_rel_err": err, "hidden": hidden}
            except Exception:
                res[f"geglu tk{tk}"] = {"error": traceback.format_exc()[-1500:]}
                print(f"geglu tk{tk}", res[f"geglu tk{tk}"]["error"], flush=True)
    for label, fn in variants.items():
        try:
            got = np.asarray(jax.jit(lambda x, w: total(fn(x, w)))(x, ws[0]))
            err = float(np.abs(got - want).max() / np.abs(want).max())
            prog = jax.jit(lambda x, ws, fn=fn: [fn(x, w) for w in ws])
            prog(x, ws)
            calls[label] = functools.partial(prog, x, ws)
            res[label] = {"max_rel_err": err}
        except Exception:
            res[label] = {"error": traceback.format_exc()[-1500:]}
            print(label, res[label]["error"], flush=True)
    floor_us = k * n * 2 / args.bandwidth * 1e6
    for label, ms in interleaved_ms(calls, args.iters).items():
        us = ms * 1e3 / args.copies
        t = kernel_times(calls[label], 5)
        kus = t["kernel_ms"] * 1e3 / args.copies or float("nan")   # no GPU kernels traced on a CPU
        res[label].update(us=us, floor_us=floor_us, bandwidth_frac=floor_us / us, trace_kernel_us=kus,
                          kernels_per_copy=t["kernels_per_call"] / args.copies, trace_wall_ms=t["wall_ms"],
                          by_name=t["by_name"][:4])
        print(f"{name:9s} {label:28s} {us:7.2f} us wall, {kus:6.2f} us in kernels "
              f"({t['kernels_per_call'] / args.copies:.1f} per copy; {floor_us / kus:5.1%} of "
              f"{args.bandwidth / 1e12:.2f} TB/s)  err {res[label]['max_rel_err']:.1e}", flush=True)
    return res


def k_sweep(ks, args, rows: int = 64, hidden: int = 4096) -> dict:
    """The engine's two GEMM kernels of the step at growing K, the columns fixed: gate/up + GeGLU (Mosaic GPU, its
    default launch) and the Triton split-K kernel at 8 splits (64 columns, as down). A fit t = a + b K splits a
    kernel's time into what it costs whatever its work (a) and per K row (b)."""
    out = {"k": ks, "rows": []}
    for label in ("geglu", "triton"):
        times = []
        for k in ks:
            key = jax.random.key(k)
            x = jax.random.normal(key, (rows, k), jnp.float32).astype(jnp.bfloat16)
            n = 2 * hidden if label == "geglu" else 1024
            ws = [(jax.random.normal(w, (k, n), jnp.float32) * k**-0.5).astype(jnp.bfloat16)
                  for w in jax.random.split(key, args.copies)]
            if label == "geglu":
                launch = ek.Blocks().mosaic_mlp
                prog = jax.jit(lambda x, ws: [mosaic_gemm.geglu(x, w, launch) for w in ws])
            else:
                gemm = ek.Gemm(64, 8)
                prog = jax.jit(lambda x, ws: [ek.matmul_partials(x, w, gemm=gemm)[0] for w in ws])
            prog(x, ws)
            t = kernel_times(functools.partial(prog, x, ws), 5)
            times.append(t["kernel_ms"] * 1e3 / args.copies)
            print(f"k-sweep {label:6s} K={k:5d} N={n}: {times[-1]:6.2f} us a kernel "
                  f"({k * n * 2 / 1e6:.1f} MB)", flush=True)
        b, a = np.polyfit(np.asarray(ks, float), np.asarray(times), 1)
        print(f"k-sweep {label}: {a:.2f} us + {b * 1e3:.3f} us per 1000 rows of K", flush=True)
        out["rows"].append({"kernel": label, "us": times, "fixed_us": float(a), "us_per_k_row": float(b)})
    return out


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--iters", type=int, default=30, help="timed calls per median (default: %(default)s)")
    p.add_argument("--copies", type=int, default=18, help="independent weights per program (default: %(default)s)")
    p.add_argument("--bandwidth", type=float, default=4.8e12, help="the floor's bytes/s (default: H200's 4.8e12)")
    p.add_argument("--shapes", default=",".join(s[0] for s in SHAPES), help="which of the four (default: all)")
    p.add_argument("--tk", type=lambda v: [int(t) for t in v.split(",")], default=None,
                   help="comma list of contraction rows per pipeline step (multiples of 64): each shape's first "
                        "launch at each, instead of the sweep; gate/up also as the engine's GeGLU kernel")
    p.add_argument("--out", type=Path, default=Path("mgpu_gemm.json"), help="JSON results (default: %(default)s)")
    p.add_argument("--k-sweep", type=lambda v: [int(t) for t in v.split(",")], default=None,
                   help="comma list of K: time the gate/up + GeGLU and a Triton split-K kernel at each (columns "
                        "fixed) and fit a fixed cost plus a cost per K row, instead of the shapes")
    args = p.parse_args()
    out = {"device": jax.devices()[0].device_kind, "jax": jax.__version__,
           "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "copies": args.copies}
    if args.k_sweep:
        out["k_sweep"] = k_sweep(args.k_sweep, args)
        args.out.write_text(json.dumps(out, indent=1))
        return
    for name, k, n, triton in SHAPES:
        if name in args.shapes.split(","):
            out[name] = probe_shape(name, k, n, triton, args)
            args.out.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
