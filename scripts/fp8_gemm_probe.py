"""Probe: the action expert's FP8 GEMMs at B = 4-16 (a few hundred rows) as a Pallas Triton kernel against the
engine's cuBLASLt GEMM, alone.

At B = 8 the FP8 step's three cuBLASLt GEMMs take 18.9 us a layer (q/k/v 6.6, out-projection 6.6, down 5.7: an H100
trace, docs/BENCHMARKS.md, session 60) for 2.2, 1.7 and 3.5 GFLOP and 2.6, 2.1 and 4.2 MB of weights: a few hundred
TFLOP/s, a third of the weight stream's rate. With 416 rows a GEMM has few output tiles of cuBLASLt's sizes, so
few SMs stream the weights. The kernel here tiles the output finely (and optionally splits K, its f32 partials
summed by XLA after it), e4m3 x e4m3 into f32 (Triton's FP8 dot), and writes the raw product in bf16 as the engine's
`formats.fp8_product` does (its column scales stay with the reader).

    python3 scripts/fp8_gemm_probe.py --batch 4,8,16 --out OUT.json
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl

sys.path.insert(0, str(Path(__file__).parent.parent))
sys.path.insert(0, str(Path(__file__).parent))
import geglu_probe  # noqa: E402
import profile_engine  # noqa: E402

from pi0_jax.ops import formats, pallas_base  # noqa: E402
from pi0_jax.ops.pallas_base import dot  # noqa: E402

F32, BF16, E4M3 = jnp.float32, jnp.bfloat16, formats.E4M3
ROWS = 52   # π0's suffix rows an element in the FP8 step (50 actions, padded to 16s: 416 at B = 8)
SHAPES = {"qkv": (2560, 1024), "out": (1024, 2048), "down": (1024, 4096)}   # (N, K), the weights K-major


def _kernel(x_ref, w_ref, o_ref, *, bm, bn, bk, chunk, m):
    i, j, s = pl.program_id(0), pl.program_id(1), pl.program_id(2)
    rows, cols = pl.ds(i * bm, bm), pl.ds(j * bn, bn)

    def body(kk, acc):
        ks = pl.ds(s * chunk + kk * bk, bk)
        return acc + dot(x_ref[rows, ks], w_ref[cols, ks], trans_b=True)

    acc = jax.lax.fori_loop(0, chunk // bk, body, jnp.zeros((bm, bn), F32))
    o_ref[pl.ds(s * m + i * bm, bm), cols] = acc.astype(o_ref.dtype)


def kernel_gemm(bm, bn, bk, warps, stages, splits):
    """xq (M, K) e4m3 @ w (N, K).T e4m3 -> (M, N) bf16 (splits > 1: f32 partials summed by XLA, then bf16; in the
    engine that sum would join the reader's fusion)."""
    def f(xq, wq):
        m, k = xq.shape
        n = wq.shape[0]
        chunk = k // splits
        kern = functools.partial(_kernel, bm=bm, bn=bn, bk=bk, chunk=chunk, m=m)
        out = jax.ShapeDtypeStruct((splits * m, n), BF16 if splits == 1 else F32)
        y = pallas_base.call(kern, grid=(m // bm, n // bn, splits), out_shape=out, name="fp8_gemm_probe",
                             num_warps=warps, num_stages=stages)(xq, wq)
        return y if splits == 1 else y.reshape(splits, m, n).sum(0).astype(BF16)
    return f


CONFIGS = [  # (bm, bn, bk, warps, stages, splits)
    (32, 64, 128, 4, 3, 1), (32, 128, 128, 4, 3, 1), (64, 64, 128, 4, 3, 1), (64, 128, 128, 4, 3, 1),
    (32, 64, 256, 4, 3, 1), (64, 64, 256, 4, 3, 1), (32, 32, 128, 4, 4, 1), (32, 64, 128, 4, 3, 2),
    (64, 64, 128, 4, 3, 2), (64, 128, 128, 8, 3, 1), (16, 64, 128, 4, 4, 1), (16, 128, 128, 4, 3, 1),
]


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--batch", default="4,8,16", help="comma-separated batches (rows = 52 an element)")
    p.add_argument("--iters", type=int, default=15, help="timed runs per form (median reported)")
    p.add_argument("--chain", type=int, default=10, help="programs dispatched back to back per timed run")
    p.add_argument("--layers", type=int, default=36,
                   help="GEMMs a program, each on a weight and an input of its own; times are per GEMM")
    p.add_argument("--out", default=None, help="write the results as JSON here")
    args = p.parse_args()
    res = {"jax": jax.__version__, "device": str(jax.devices()[0]), "rows": {}}
    for b in map(int, args.batch.split(",")):
        m = b * ROWS
        for name, (n, k) in SHAPES.items():
            key = jax.random.key(m + n + k)
            # an input a GEMM (XLA merges dots that share their input into one, after a copy of their weights)
            xq = [formats.quantise(jax.random.normal(jax.random.fold_in(key, 1000 + i), (m, k), F32), jnp.float32(0.01))
                  for i in range(args.layers)]
            wq = [formats.quantise(jax.random.normal(jax.random.fold_in(key, i + 1), (n, k), F32), jnp.float32(0.01))
                  for i in range(args.layers)]
            ref = jnp.einsum("mk,nk->mn", xq[0].astype(F32), wq[0].astype(F32))
            forms = {"xla (cuBLASLt, the engine)": lambda xq, wq: formats.fp8_product(
                "mk,nk->mn", xq, formats.QArray(wq, jnp.ones(())), BF16)}
            for c in CONFIGS:
                bm, bn, bk, _, _, s = c
                if m % bm or n % bn or k % (bk * s):
                    continue
                forms["kernel %dx%dx%d w%d s%d split%d" % c] = kernel_gemm(*c)
            # one program of `layers` GEMMs on distinct weights (as the step's layers: weights from HBM, one
            # dispatch for all), timed as a chain of such programs
            # compiled as the engine compiles an FP8 program (`ops.matmul.compiler_options`: no XLA Triton GEMMs)
            layered = {f: jax.jit(lambda xs, ws, fn=fn: tuple(fn(x, w) for x, w in zip(xs, ws))).lower(xq, wq).compile(
                {"xla_gpu_enable_triton_gemm": False}) for f, fn in forms.items()}
            row = res["rows"][f"B={b} {name}"] = {"m": m, "n": n, "k": k}
            flops, wbytes = 2 * m * n * k, n * k
            print(f"B={b} {name} ({m} x {n} x {k})", flush=True)
            for fname, fn in layered.items():
                try:
                    got = fn(xq, wq)[0].astype(F32)
                    rel = float(jnp.linalg.norm(got - ref) / jnp.linalg.norm(ref))
                    wall = geglu_probe._chain(fn, (xq, wq), args.iters, args.chain) / args.layers
                    # the device's time: the GPU kernels of a profiler trace (the wall holds the host's launches)
                    t = profile_engine.kernel_times(lambda fn=fn: fn(xq, wq), calls=3)
                    ms = t["kernel_ms"] / args.layers
                    r = {"us": ms * 1e3, "wall_us": wall * 1e3, "kernels": t["kernels_per_call"] / args.layers,
                         "kernel_names": [k["name"][:80] for k in t["by_name"][:3]],
                         "tflops": flops / ms / 1e9, "weight_gbs": wbytes / ms / 1e6, "rel_l2": rel}
                    print(f"   {fname:34s} {r['us']:7.2f} us {r['tflops']:6.0f} TFLOP/s {r['weight_gbs']:6.0f} GB/s "
                          f"(wall {r['wall_us']:6.2f} us, {r['kernels']:.0f} kernels) rel {rel:.1e} "
                          f"{r['kernel_names'][0][:40]}", flush=True)
                except Exception as e:  # noqa: BLE001  (a probe: report the form that fails and go on)
                    r = {"error": f"{type(e).__name__}: {str(e)[:400]}"}
                    print(f"   {fname:34s} {r['error'][:200]}", flush=True)
                row[fname] = r
            if args.out:
                with open(args.out, "w") as f:
                    json.dump(res, f, indent=1)


if __name__ == "__main__":
    main()
