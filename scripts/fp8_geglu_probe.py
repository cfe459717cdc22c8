"""Probe: the FP8 prefix's gate/up GEMM with GeGLU and the down GEMM's e4m3 quantisation in its epilogue, as one
Pallas Mosaic GPU kernel, against the engine's XLA path (cuBLASLt's FP8 GEMM, then a pass of its own).

In the FP8 prefix, XLA runs gate/up as an e4m3 x e4m3 cuBLASLt GEMM into bf16, then one fusion reads gate and up
back, applies the per-column scales, GELU-tanh(gate) * up, and writes the down GEMM's e4m3 input. That pass costs
26 us a layer against the GEMM's 102 us at B = 1 (816 rows) and 1.84 against 5.37 ms at B = 64 (H200,
docs/BENCHMARKS.md, session 53), and cuBLASLt cannot take it as an epilogue (per-column scales). Session 46's bf16
kernel of this kind ran level with cuBLAS + pass; in FP8 the pass is a larger share of the GEMM (a third at B >= 8),
so the same design has more to win.

The kernel (persistent: a CTA per SM walking (tile_m x tile_n) output tiles in a snake order; TMA, a producer
warpgroup, two compute warpgroups each owning tile_n / 2 columns, wgmma on e4m3 with f32 accumulators): x (M, K)
e4m3 and the engine's gate/up weight (2F, K) e4m3, K-major, gate and up in alternating blocks of 32 units
(`ops.layout.gate_up_block`), per-column scales (act_scale x weight scale). Its epilogue follows the engine's
roundings: the product rounded to bf16, scaled in f32 and rounded to bf16, GELU-tanh(gate) * up in f32 rounded to
bf16, divided by the down GEMM's activation scale and converted to e4m3 (saturating, nearest even).

Timed against the engine's XLA form (`geglu_probe.XLA_FORMS`' FP8 block pairs) and its GEMM alone, each as `--chain`
calls back to back; actions compared as the dequantised e4m3 outputs, against each other and against f32. The XLA
forms start from bf16 x and quantise it (in the engine that fuses into the norm before); the kernel takes x in e4m3,
so it is spared that pass: one read of x, about 1 % of the GEMM.

    python3 scripts/fp8_geglu_probe.py --rows 816,6528,51200 --out OUT.json
    python3 scripts/fp8_geglu_probe.py --cpu-check     # Mosaic GPU's interpreter, a small shape

On a GPU every kernel's output is compared with `reference` (the same numerics in XLA). The CPU check runs the kernel
in Mosaic GPU's interpreter with the weight N-major (`geglu_fp8(interpret=True)`), as jax 0.10.2's interpreter has
no transposed wgmma operand, which e4m3 needs on the GPU (both operands K-major).
Written in session 54 (2026-12-04), which was lent no GPU: the interpreter check passes (bit-equal to `reference`),
and the kernel has not yet been compiled for or timed on a GPU.
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
from pathlib import Path

import jax
import jax.experimental.pallas as pl
import jax.experimental.pallas.mosaic_gpu as plgpu
import jax.numpy as jnp
import numpy as np
from jax import lax

sys.path.insert(0, str(Path(__file__).parent))
import geglu_probe  # noqa: E402

from pi0_jax.ops import formats, layout  # noqa: E402
from pi0_jax.ops.mosaic_gemm import _interpret  # noqa: E402

BF16, F32, E4M3 = jnp.bfloat16, jnp.float32, formats.E4M3


def _transforms(minor: int, itemsize: int = 1):
    """TMA tiles of 8 rows, swizzled by the row's width in bytes (at most 128)."""
    swizzle = plgpu.find_swizzle(minor * itemsize * 8)
    return plgpu.TilingTransform((8, swizzle // itemsize)), plgpu.SwizzleTransform(swizzle)


def _round(a):
    return a.astype(BF16).astype(F32)


def _gelu_tanh(g):
    inner = np.float32(np.sqrt(2 / np.pi)) * (g + np.float32(0.044715) * g * g * g)
    return np.float32(0.5) * g * (1 + jnp.tanh(inner))


def geglu_fp8(xq, wq, col_scale, s_down: float, *, tile_m=128, tile_n=256, tile_k=128, stages=4, snake=8,
              minor=0, block=32, delay=0, geglu=True, e4m3=True, ragged=False, approx=False, interpret=False):
    """xq (M, K) e4m3, wq (2F, K) e4m3 in gate/up block pairs of `block` units, col_scale (2F,) f32 -> e4m3 (M, F):
    quantise(GELU-tanh(gate) * up, s_down) with gate and up the scaled product's halves of each pair. M, 2F and K
    must tile by (tile_m, tile_n, tile_k); each compute warpgroup's tile_n / 2 columns hold whole pairs. delay:
    wgmma steps left in flight when the next is issued (their tiles released that many steps later). geglu=False:
    the GEMM alone, its product rounded to bf16 (M, 2F), unscaled: the mainloop's speed without the epilogue.
    e4m3=False: GeGLU's product in bf16 (M, F), not quantised (a check of the kernel without its e4m3 stores).
    approx: Mosaic GPU's approximate math (tanh.approx.f32 for GELU's tanh, within bf16 rounding of the exact one).
    ragged: M need not tile; the last row tile reads zeros past the end and its stores there are dropped (TMA on a
    GPU; the interpreter refuses such reads), so the engine's 816 rows at B = 1 need no padded copy.

    interpret: Mosaic GPU's CPU interpreter (jax 0.10.2), which has neither a transposed wgmma operand nor
    `plgpu.load`: the weight then streams as its (K, 2F) transpose and the scales are read as a plain ref, so the
    check covers the tiling, the pipeline and the epilogue's layout, not the K-major operand."""
    m, k = xq.shape
    n2 = wq.shape[0]
    wg_n = tile_n // 2
    pairs = wg_n // (2 * block)
    if (m % tile_m and not ragged) or n2 % tile_n or k % tile_k or wg_n % (2 * block) or wq.shape[1] != k:
        raise ValueError(f"{xq.shape} @ {wq.shape}.T does not tile by ({tile_m}, {tile_n}, {tile_k}, pairs of {block})")
    m_iters, n_iters, k_iters = -(-m // tile_m), n2 // tile_n, k // tile_k
    if interpret:
        wq = wq.T
    out_dtype = E4M3 if e4m3 else BF16
    in_tr, out_tr = _transforms(tile_k), _transforms(block, jnp.dtype(out_dtype).itemsize)
    down = np.float32(s_down)

    def pipeline(body, context):
        spec = functools.partial(plgpu.BlockSpec, memory_space=plgpu.SMEM, transforms=in_tr, delay_release=delay)
        return plgpu.emit_pipeline_warp_specialized(
            body, grid=(k_iters,), memory_registers=40,
            in_specs=[spec((tile_m, tile_k), lambda kk: (0, kk)),
                      spec((tile_k, tile_n), lambda kk: (kk, 0), transforms=_transforms(tile_n)) if interpret
                      else spec((tile_n, tile_k), lambda kk: (0, kk))],
            wg_axis="wg", num_compute_wgs=2, max_concurrent_steps=stages, compute_context=context)

    def kernel(x_gmem, w_gmem, s_gmem, out_gmem):
        nothing = lambda *_, **__: None   # noqa: E731

        @functools.partial(pl.run_scoped, allocs=pipeline(nothing, nothing).get_allocations(x_gmem, w_gmem),
                           out_smem=(plgpu.SMEM((2, pairs, tile_m, block), out_dtype, transforms=out_tr) if geglu
                                     else plgpu.SMEM((2, tile_m, block), BF16, transforms=_transforms(block, 2))),
                           s_smem=plgpu.SMEM((2, wg_n), F32), s_bar=plgpu.Barrier(num_barriers=2),
                           collective_axes="wg")
        def scope(allocs, out_smem, s_smem, s_bar):
            wg = lax.axis_index("wg")

            @plgpu.nd_loop((m_iters * n_iters,), collective_axes="cluster_grid")
            def tiles(info):
                (lin,) = info.index
                mi, ni = plgpu.planar_snake(lin, (m_iters, n_iters), minor, snake)
                rows = pl.ds(mi * tile_m, tile_m)
                col0 = ni * tile_n + wg * wg_n

                def context(run):
                    plgpu.copy_gmem_to_smem(s_gmem.at[pl.ds(col0, wg_n)], s_smem.at[wg], s_bar.at[wg])

                    @functools.partial(pl.run_scoped, acc=plgpu.ACC((tile_m, wg_n), F32))
                    def _(acc):
                        run(acc)
                        plgpu.barrier_wait(s_bar.at[wg])
                        if not geglu:   # bf16 out in column chunks of `block` (shared memory is full)
                            y = acc[...].astype(BF16)
                            for c in range(wg_n // block):
                                plgpu.wait_smem_to_gmem(0, wait_read_only=True)
                                out_smem[wg] = y[:, c * block:(c + 1) * block]
                                plgpu.commit_smem()
                                plgpu.copy_smem_to_gmem(out_smem.at[wg],
                                                        out_gmem.at[rows, pl.ds(col0 + c * block, block)])
                            return
                        s = (s_smem[wg] if interpret
                             else plgpu.load(s_smem.at[wg], (), layout=plgpu.Layout.WGMMA.reduce(0)))
                        y = _round(_round(acc[...]) * s[None, :])
                        plgpu.wait_smem_to_gmem(0, wait_read_only=True)
                        for p in range(pairs):
                            g = y[:, 2 * p * block:(2 * p + 1) * block]
                            u = y[:, (2 * p + 1) * block:(2 * p + 2) * block]
                            h = _round(_gelu_tanh(g) * u)
                            out_smem[wg, p] = (h / down).astype(E4M3) if e4m3 else h.astype(BF16)
                        plgpu.commit_smem()
                        for p in range(pairs):
                            plgpu.copy_smem_to_gmem(out_smem.at[wg, p],
                                                    out_gmem.at[rows, pl.ds(col0 // 2 + p * block, block)])

                def body(_, a_smem, b_smem, acc):
                    cols = pl.ds(wg * wg_n, wg_n)
                    plgpu.wgmma(acc, a_smem, b_smem.at[:, cols] if interpret
                                else plgpu.transpose_ref(b_smem.at[cols], (1, 0)))
                    plgpu.wgmma_wait(delay)
                    return acc

                w_cols = pl.ds(ni * tile_n, tile_n)
                pipeline(body, context)(x_gmem.at[rows, :], w_gmem.at[:, w_cols] if interpret else w_gmem.at[w_cols, :],
                                        allocations=allocs)
        plgpu.wait_smem_to_gmem(0, wait_read_only=True)

    sms = 1 if interpret else jax.devices()[0].core_count
    params = plgpu.CompilerParams(lowering_semantics=plgpu.LoweringSemantics.Warpgroup,
                                  **({"approx_math": True} if approx else {}))
    out = jax.ShapeDtypeStruct((m, n2 // 2), out_dtype) if geglu else jax.ShapeDtypeStruct((m, n2), BF16)
    call = plgpu.kernel(kernel, out_type=out, grid=(sms,),
                        grid_names=("cluster_grid",), num_threads=3, thread_name="wg", compiler_params=params,
                        kernel_name="fp8_geglu", **({"interpret": _interpret()} if interpret else {}))
    return call(xq, wq, col_scale)


def _product(xq, wq):
    """The kernel's GEMM alone (geglu=False): e4m3 x e4m3 into bf16, unscaled."""
    return jnp.einsum("md,nd->mn", xq, wq, preferred_element_type=BF16)


def reference(xq, wq, col_scale, s_down, e4m3=True):
    """The kernel's numerics in XLA: the engine's FP8 gate/up form (`formats.qmatmul`, `layout.split_gate_up`, GeGLU,
    `formats.quantise`; e4m3=False: GeGLU's bf16 product), with GELU-tanh as the kernel writes it."""
    y = (_product(xq, wq).astype(F32) * col_scale).astype(BF16)
    gate, up = layout.split_gate_up(y.astype(F32))
    h = (_gelu_tanh(gate) * up).astype(BF16)
    return formats.quantise(h, jnp.float32(s_down)) if e4m3 else h


def _operands(m, k, f, seed=0):
    key = jax.random.key(seed)
    x = jax.random.normal(jax.random.fold_in(key, m), (m, k), F32).astype(BF16)
    w = (jax.random.normal(key, (k, 2 * f), F32) * 0.02).astype(BF16)
    ws, ref = geglu_probe.xla_weights(x, w)
    q = ws["q_blocks"]
    xq = formats.quantise(x, q.act_scale)
    col_scale = formats.output_scale("...D,FD->...F", q).reshape(-1)
    return x, ws, ref, xq, q.q, col_scale, float(ws["s_down"])


def _rel(a, b):
    a, b = jnp.asarray(a, F32), jnp.asarray(b, F32)
    return float(jnp.linalg.norm(a - b) / jnp.linalg.norm(b))


def cpu_check() -> dict:
    """The kernel in Mosaic GPU's interpreter against `reference`: one CTA over 2 x 2 tiles of two pairs a
    warpgroup."""
    m, k, f = 256, 256, 256
    _, _, _, xq, wq, cs, s_down = _operands(m, k, f)
    out = {}
    for name, kw in {"geglu": {}, "geglu, bf16 out": {"e4m3": False}, "gemm alone": {"geglu": False}}.items():
        got = geglu_fp8(xq, wq, cs, s_down, tile_m=128, tile_n=256, tile_k=128, stages=2, interpret=True, **kw)
        want = _product(xq, wq) if name == "gemm alone" else reference(xq, wq, cs, s_down, kw.get("e4m3", True))
        g, w = (np.asarray(a.astype(F32)) for a in (got, want))
        out[name] = {"shape": [m, k, f], "rel_l2": _rel(g, w),
                                                   "elements_differing": int(np.sum(g != w)), "elements": g.size}
    print(json.dumps(out), flush=True)
    return out


CONFIGS = {   # name: geglu_fp8 keywords
    "GEMM alone, 128x256x128, 4 stages, snake 8": {"geglu": False},
    "GEMM alone, 128x256x128, 4 stages, delay 1, snake 8": {"geglu": False, "delay": 1},
    "128x256x128, 4 stages, snake 8": {},
    "128x256x128, 4 stages, snake 8, bf16 out": {"e4m3": False},
    "128x256x128, 4 stages, snake 8, approximate tanh": {"approx": True},
    "128x256x128, 4 stages, delay 1, snake 8": {"delay": 1},
    "128x256x128, 4 stages, snake 8 on N": {"minor": 1},
    "128x256x128, 3 stages, snake 16": {"stages": 3, "snake": 16},
    "128x256x64, 6 stages, snake 8": {"tile_k": 64, "stages": 6},
    "128x128x128, 6 stages, snake 8": {"tile_n": 128, "stages": 6},
}


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--rows", default="816,6528,51200", help="comma-separated M values (π0's prefix at B = 1, 8, 64)")
    p.add_argument("--width", type=int, default=2048, help="K: Gemma 2B's width")
    p.add_argument("--hidden", type=int, default=16384, help="F: Gemma 2B's MLP width")
    p.add_argument("--iters", type=int, default=15, help="timed runs per form (median reported)")
    p.add_argument("--chain", type=int, default=20, help="calls dispatched back to back per timed run")
    p.add_argument("--only", action="append", default=None,
                   help="repeatable: only the kernel configs whose name contains this")
    p.add_argument("--cpu-check", action="store_true", help="only the interpreter check (a CPU is enough)")
    p.add_argument("--out", default=None, help="write the results as JSON here")
    args = p.parse_args()
    res = {"jax": jax.__version__, "device": str(jax.devices()[0]), "rows": {}}
    if args.cpu_check:
        res["cpu_check"] = cpu_check()
        args.rows = ""
    for m in (int(r) for r in args.rows.split(",") if r):
        x, ws, ref, xq, wq, cs, s_down = _operands(m, args.width, args.hidden)
        flops = 2 * m * args.width * 2 * args.hidden
        engine_fn, _ = geglu_probe.XLA_FORMS["xla: block pairs (the engine, fp8)"]
        gemm_fn, _ = geglu_probe.XLA_FORMS["xla: gate/up gemm alone (fp8)"]
        engine = jax.jit(engine_fn)
        want = engine(x, ws).astype(F32) * s_down
        row = res["rows"][m] = {}
        print(f"M={m}", flush=True)
        forms = {"xla: the engine's form (x quantised, GEMM, pass)": (engine, (x, ws)),
                 "xla: the GEMM alone (x quantised)": (jax.jit(gemm_fn), (x, ws))}
        mp = -(-m // 128) * 128
        xp = jnp.pad(xq, ((0, mp - m), (0, 0))) if mp != m else xq
        for name, kw in CONFIGS.items():
            if args.only and not any(o in name for o in args.only):
                continue
            fn = jax.jit(functools.partial(geglu_fp8, s_down=s_down, **kw))
            forms["kernel " + name + (f" (x padded to {mp} rows)" if mp != m else "")] = (fn, (xp, wq, cs))
            if mp != m and not kw:   # the default launch on the rows as they are
                fn = jax.jit(functools.partial(geglu_fp8, s_down=s_down, ragged=True))
                forms["kernel " + name + f" ({m} rows, the last tile ragged)"] = (fn, (xq, wq, cs))
        for name, (fn, fargs) in forms.items():
            try:
                got = fn(*fargs)
                r = {"ms": geglu_probe._chain(fn, fargs, args.iters, args.chain)}
                r["tflops"] = flops / r["ms"] / 1e9
                if name.startswith("kernel GEMM alone"):
                    r["vs_reference_numerics"] = _rel(got[:m], _product(xq, wq))
                elif name.startswith("kernel"):
                    e4m3 = got.dtype == E4M3
                    g = got[:m].astype(F32) * (s_down if e4m3 else 1.0)
                    r["rel_l2_vs_engine"] = _rel(g, want)
                    r["rel_l2_vs_f32"] = _rel(g, ref)
                    r["vs_reference_numerics"] = _rel(got[:m], reference(xq, wq, cs, s_down, e4m3))
                elif "engine" in name:
                    r["rel_l2_vs_f32"] = _rel(want, ref)
            except Exception as e:  # noqa: BLE001  (a probe: report the form that fails and go on)
                r = {"error": f"{type(e).__name__}: {str(e)[:600]}"}
            row[name] = r
            print(f"   {name:64s} " + (f"{r['ms']:8.4f} ms {r['tflops']:6.0f} TFLOP/s "
                                        + " ".join(f"{k} {v:.1e}" for k, v in r.items() if k.startswith(("rel", "vs")))
                                        if "ms" in r else r["error"]), flush=True)
    if args.out:
        with open(args.out, "w") as f:
            json.dump(res, f, indent=1)


if __name__ == "__main__":
    main()
