"""SigLIP's four GEMM shapes at B = 1 (3 cameras: 768 rows), and the VLM prefix's MLP GEMMs (`--shape gate_up
--shape down`), on jax's own Hopper matmul kernel
(`jax.experimental.pallas.ops.gpu.hopper_matmul_mgpu`: persistent, TMA, two consumer warpgroups) over a sweep of
its tilings, against XLA's dot on cuBLAS (the vision program's library).

The tower's GEMMs run at 300-520 TFLOP/s in the engine (docs/BENCHMARKS.md, session 45): at M = 768 cuBLAS's tiles
leave SMs idle (fc1's 224 x 128 tiles make 136 on 132 SMs, two waves). This probe measures whether another tiling
beats it before any epilogue (bias, GELU, residual) is written. So400m's 4304 is not a multiple of 64, so fc1's N and
fc2's K are zero-padded to 4352 for the Mosaic kernel (exact: GELU(0) = 0); cuBLAS runs both the real and the
padded shape.

Each variant runs on `--copies` independent weights in one program (a layer's weights come from HBM, as in the
tower) and is timed by its kernels' durations in a profiler trace, divided by the copies; each is checked against
XLA's f32-accumulated product.

    python scripts/vision_gemm_probe.py --out vision_gemm.json
"""

from __future__ import annotations

import argparse
import functools
import itertools
import json
import sys
import traceback
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from profile_engine import kernel_times  # noqa: E402

# (name, M, K, N, M padded, K padded, N padded): So400m at 768 rows; the VLM prefix's MLP at π0's 864 rows (3
# cameras, a 48-token prompt), padded to whole 128-row tiles
SHAPES = [("qkv", 768, 1152, 3456, 768, 1152, 3456), ("out", 768, 1152, 1152, 768, 1152, 1152),
          ("fc1", 768, 1152, 4304, 768, 1152, 4352), ("fc2", 768, 4304, 1152, 768, 4352, 1152),
          ("gate_up", 864, 2048, 32768, 896, 2048, 32768), ("down", 864, 16384, 2048, 896, 16384, 2048)]
VISION = ("qkv", "out", "fc1", "fc2")
PEAK = 989e12   # bf16 dense, H100 / H200 SXM


def configs(m: int, n: int, sms: int = 132):
    """(label, TuningConfig) of the sweep whose CTA tiles divide (m, n), fewest waves first. Over several waves both
    grid orders run: `grid_minor_dim` N walks a weight tile's row blocks one after another (the tile then serves
    them from L2: the prefix's MLP weights are 67-134 MB, its rows 864), M walks the column blocks first."""
    from jax.experimental.pallas.ops.gpu import hopper_matmul_mgpu as hm
    dims = hm.MatmulDimension
    out = []
    for tm, tn, wg, steps, minor in itertools.product((64, 128), (64, 128, 192, 256), dims, (4, 6), dims):
        width = 1
        cm, cn = tm * (1 + (wg == dims.M)), tn * (1 + (wg == dims.N))
        if m % cm or n % cn or tm * tn > 128 * 192:   # the f32 accumulator in a warpgroup's registers
            continue
        tiles = (m // cm) * (n // cn)
        if minor == dims.M and tiles <= sms:   # one wave: the order does not matter
            continue
        label = f"{cm}x{cn} (wg {wg.name}, {tm}x{tn}) {steps}st {minor.name}-minor [{tiles} tiles]"
        out.append((-(-tiles // sms), -tiles, label, hm.TuningConfig(
            tile_m=tm, tile_n=tn, tile_k=64, max_concurrent_steps=steps, epi_tile_m=64, epi_tile_n=64,
            grid_minor_dim=minor, grid_tile_width=width, wg_dimension=wg)))
    out.sort(key=lambda c: c[:2])
    return [(label, cfg) for *_, label, cfg in out]


def probe_shape(name, rows, k, n, rp, kp, np_, args):
    from jax.experimental.pallas.ops.gpu import hopper_matmul_mgpu as hm
    key = jax.random.key(hash(name) % 1000)
    kx, kw = jax.random.split(key)
    # an input per copy too: XLA merges dots that share an operand into one GEMM over concatenated weights
    xs = [jax.random.normal(x, (rows, k), jnp.float32).astype(jnp.bfloat16) for x in jax.random.split(kx, args.copies)]
    ws = [(jax.random.normal(w, (k, n), jnp.float32) * k**-0.5).astype(jnp.bfloat16)
          for w in jax.random.split(kw, args.copies)]
    xps = [jnp.pad(x, ((0, rp - rows), (0, kp - k))) for x in xs]
    wps = [jnp.pad(w, ((0, kp - k), (0, np_ - n))) for w in ws]
    want = np.asarray(jnp.dot(xs[0], ws[0], preferred_element_type=jnp.float32))
    flops = 2 * rows * k * n
    res = {}

    def run(label, fn, xs, ws):
        try:
            got = np.asarray(jax.jit(fn)(xs[0], ws[0]), np.float32)[:rows, :n]
            err = float(np.abs(got - want).max() / np.abs(want).max())
            prog = jax.jit(lambda xs, ws: [fn(x, w) for x, w in zip(xs, ws)])
            jax.block_until_ready(prog(xs, ws))
            t = kernel_times(functools.partial(prog, xs, ws), 5)
            us = t["kernel_ms"] * 1e3 / args.copies or float("nan")
            res[label] = {"us": us, "tflops": flops / us / 1e6, "max_rel_err": err,
                          "kernels_per_copy": t["kernels_per_call"] / args.copies, "by_name": t["by_name"][:2]}
            tflops = flops / us / 1e6
            print(f"{name:4s} {label:70s} {us:7.2f} us {tflops:6.0f} TFLOP/s ({tflops * 1e12 / PEAK:4.0%})  "
                  f"err {err:.1e}", flush=True)
        except Exception:
            res[label] = {"error": traceback.format_exc()[-800:]}
            print(name, label, "FAILED", traceback.format_exc()[-300:], flush=True)

    run("cublas", lambda x, w: jnp.dot(x, w), xs, ws)
    if (rp, kp, np_) != (rows, k, n):
        run("cublas padded", lambda x, w: jnp.dot(x, w), xps, wps)
    for label, cfg in configs(rp, np_)[:args.max_configs]:
        run("mgpu " + label, functools.partial(lambda x, w, cfg: hm.matmul(x, w, None, cfg), cfg=cfg), xps, wps)
    return res


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--shape", action="append", choices=[s[0] for s in SHAPES], default=None,
                   help="repeatable (default: SigLIP's four)")
    p.add_argument("--copies", type=int, default=6, help="independent weights per program (beyond the L2's 50 MB)")
    p.add_argument("--max-configs", type=int, default=24, help="tilings tried per shape, fewest waves first")
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args()
    report = {"device": str(jax.devices()[0].device_kind), "shapes": {}}
    for name, *dims in SHAPES:
        if (args.shape is None and name in VISION) or name in (args.shape or ()):
            report["shapes"][name] = probe_shape(name, *dims, args)
    if args.out:
        args.out.write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
