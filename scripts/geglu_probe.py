"""Probe: the prefix MLP's gate/up GEMM with GeGLU in its epilogue, as a Pallas kernel, against XLA's GEMM + GeGLU.

XLA runs the gate/up GEMM in cuBLAS, which writes gate and up (2 x M x F bf16), and a separate fusion reads both
back to write GELU-tanh(gate) * up: at π0.5 B = 64 that fusion is 24 of the prefix's 297 ms (H200). A kernel that
keeps gate and up in registers and writes only the product removes that pass, if its GEMM is as fast as cuBLAS's.
Two kernels, both exact to bf16 rounding against XLA:
  triton  Pallas on Triton: a program per (128 x 128) output tile, grouped order, an f32 accumulator for gate and
          one for up over a K loop;
  mgpu    Pallas on Mosaic GPU (wgmma, TMA, warp-specialised, persistent): a CTA of two compute warpgroups, each
          with a gate and an up accumulator (64 rows x 128 hidden units, f32) and a TMA store of the product.
Also timed: cuBLAS's GEMM alone, and jax's stock Mosaic GPU Hopper matmul (the GEMM alone) at its fastest config.
The Mosaic GPU kernel won here and lost in the engine, where cuBLAS ran faster (docs/BENCHMARKS.md, "GeGLU in the
gate/up GEMM's epilogue"), so the engine keeps XLA's path.

The "xla:" forms are XLA programs of the same step laid out other ways (`XLA_FORMS`), bf16 and FP8 (e4m3 out, as the
down-projection takes it): the engine's gate/up in 32-unit block pairs, in [gate | up] halves, and gate and up as two
GEMMs, whose gate GEMM can take GELU-tanh as a cuBLASLt epilogue (XLA's gemm rewriter matches jax's form of it on a
cuBLASLt GEMM, in FP8 only with per-tensor scales), leaving the pass after it no GELU to compute. Each row says
whether the compiled program has a GELU epilogue and how many kernels it runs. Timed back to back (--chain calls).
On an H200 (docs/BENCHMARKS.md, session 53) halves were within 1 % of block pairs at B = 8 and 64 and slower at
B = 1; XLA took the GELU epilogue only in bf16 with Triton GEMMs off, and left the dequantised FP8 gate as a bf16
GEMM: the engine keeps its layout.

  python3 scripts/geglu_probe.py --rows 8192,51200,143616 --iters 15 --out OUT.json
  python3 scripts/geglu_probe.py --rows 816,6528,51200 --only xla: --out OUT.json
"""

from __future__ import annotations

import argparse
import functools
import json
import re
import time

import einops
import jax
import jax.experimental.pallas as pl
import jax.experimental.pallas.mosaic_gpu as plgpu
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.experimental.pallas import triton as pltriton

from pi0_jax.engine import layers
from pi0_jax.ops import formats, layout

BF16, F32 = jnp.bfloat16, jnp.float32


def _geglu(g, u, dtype):
    """GELU-tanh(gate) * up from the f32 accumulators, each first rounded to the dtype as XLA's GEMM output is."""
    g, u = (a.astype(dtype).astype(jnp.float32) for a in (g, u))
    c = 0.5 * (1.0 + jnp.tanh(np.float32(np.sqrt(2 / np.pi)) * (g + np.float32(0.044715) * g * g * g)))
    return (g * c * u).astype(dtype)


def _kernel(x_ref, w_ref, o_ref, *, bm, bn, bk, k, n_half, group, grid_n, dtype):
    pid = pl.program_id(0)
    per_group = group * grid_n                  # grouped order: `group` row blocks share each column block in L2
    first = (pid // per_group) * group
    i = first + (pid % per_group) % group
    j = (pid % per_group) // group
    rows, cg, cu = pl.ds(i * bm, bm), pl.ds(j * bn, bn), pl.ds(n_half + j * bn, bn)

    def body(kk, acc):
        ks = pl.ds(kk * bk, bk)
        a = x_ref[rows, ks]
        g = jax.lax.dot_general(a, w_ref[ks, cg], (((1,), (0,)), ((), ())), preferred_element_type=jnp.float32)
        u = jax.lax.dot_general(a, w_ref[ks, cu], (((1,), (0,)), ((), ())), preferred_element_type=jnp.float32)
        return acc[0] + g, acc[1] + u

    zero = jnp.zeros((bm, bn), jnp.float32)
    g, u = jax.lax.fori_loop(0, k // bk, body, (zero, zero))
    o_ref[rows, cg] = _geglu(g, u, dtype)


def geglu_triton(x, w, *, bm=128, bn=64, bk=64, group=8, num_warps=4, num_stages=3):
    """x (M, K) @ w (K, 2F) -> GELU-tanh(gate) * up (M, F); M a multiple of bm."""
    m, k = x.shape
    f = w.shape[1] // 2
    if m * f >= 2**31:
        raise ValueError(f"M x F = {m * f} overflows the kernel's int32 offsets")
    grid_m, grid_n = m // bm, f // bn
    kern = functools.partial(_kernel, bm=bm, bn=bn, bk=bk, k=k, n_half=f, group=group, grid_n=grid_n,
                             dtype=x.dtype)
    return pl.pallas_call(kern, grid=(grid_m * grid_n,), out_shape=jax.ShapeDtypeStruct((m, f), x.dtype),
                          compiler_params=pltriton.CompilerParams(num_warps=num_warps, num_stages=num_stages),
                          name="geglu_matmul")(x, w)


def geglu_mgpu(x, w, *, tile_m=128, tile_n=64, tile_k=64, stages=4, snake=8, interpret=False):
    """x (M, K) @ w (K, 2F) -> GELU-tanh(gate) * up (M, F) in x's dtype; M a multiple of 2 * tile_m. interpret: an
    `InterpretGPUParams` runs it on a CPU (Mosaic GPU's interpreter: a check of the indexing, not of speed)."""
    m, k = x.shape
    f = w.shape[1] // 2
    dtype = x.dtype
    cta_m = 2 * tile_m
    if m % cta_m or f % tile_n or k % tile_k:
        raise ValueError(f"shapes {x.shape} @ {w.shape} do not tile by ({cta_m}, {tile_n}, {tile_k})")
    m_iters, n_iters, k_iters = m // cta_m, f // tile_n, k // tile_k
    item = jnp.dtype(dtype).itemsize

    def transforms(minor):   # TMA tiles of 8 rows, swizzled by the row's width in bytes (at most 128)
        swizzle = plgpu.find_swizzle(minor * item * 8)
        return plgpu.TilingTransform((8, swizzle // item)), plgpu.SwizzleTransform(swizzle)

    in_tr, b_tr = transforms(tile_k), transforms(tile_n)

    def pipeline(body, context):
        spec = functools.partial(plgpu.BlockSpec, memory_space=plgpu.SMEM)
        return plgpu.emit_pipeline_warp_specialized(
            body, grid=(k_iters,), memory_registers=40,
            in_specs=[spec((cta_m, tile_k), lambda kk: (0, kk), transforms=in_tr),
                      spec((tile_k, tile_n), lambda kk: (kk, 0), transforms=b_tr),
                      spec((tile_k, tile_n), lambda kk: (kk, 0), transforms=b_tr)],
            wg_axis="wg", num_compute_wgs=2, max_concurrent_steps=stages, compute_context=context)

    def kernel(x_gmem, w_gmem, out_gmem):
        nothing = lambda *_, **__: None   # noqa: E731

        @functools.partial(pl.run_scoped,
                           allocs=pipeline(nothing, nothing).get_allocations(x_gmem, w_gmem, w_gmem),
                           out_smem=plgpu.SMEM((2, tile_m, tile_n), dtype, transforms=b_tr),
                           collective_axes="wg")
        def scope(allocs, out_smem):
            wg = lax.axis_index("wg")

            @plgpu.nd_loop((m_iters * n_iters,), collective_axes="cluster_grid")
            def tiles(info):
                (lin,) = info.index
                mi, ni = plgpu.planar_snake(lin, (m_iters, n_iters), 0, snake)
                rows = pl.ds(mi * cta_m, cta_m)
                wg_rows = pl.ds(wg * tile_m, tile_m)

                def context(run):
                    @functools.partial(pl.run_scoped, acc_g=plgpu.ACC((tile_m, tile_n), jnp.float32),
                                       acc_u=plgpu.ACC((tile_m, tile_n), jnp.float32))
                    def accs(acc_g, acc_u):
                        run((acc_g, acc_u))
                        y = _geglu(acc_g[...], acc_u[...], dtype)
                        plgpu.wait_smem_to_gmem(0, wait_read_only=True)
                        out_smem[wg] = y
                        plgpu.commit_smem()
                        plgpu.copy_smem_to_gmem(out_smem.at[wg],
                                                out_gmem.at[rows, pl.ds(ni * tile_n, tile_n)].at[wg_rows])

                def body(idx, a_smem, g_smem, u_smem, accs):
                    acc_g, acc_u = accs
                    plgpu.wgmma(acc_g, a_smem.at[wg_rows], g_smem)
                    plgpu.wgmma(acc_u, a_smem.at[wg_rows], u_smem)
                    plgpu.wgmma_wait(0)
                    return accs

                pipeline(body, context)(x_gmem.at[rows, :], w_gmem.at[:, pl.ds(ni * tile_n, tile_n)],
                                        w_gmem.at[:, pl.ds(f + ni * tile_n, tile_n)], allocations=allocs)
        plgpu.wait_smem_to_gmem(0, wait_read_only=True)

    sms = 1 if interpret else jax.devices()[0].core_count
    params = plgpu.CompilerParams(lowering_semantics=plgpu.LoweringSemantics.Warpgroup)
    call = plgpu.kernel(kernel, out_type=jax.ShapeDtypeStruct((m, f), dtype), grid=(sms,),
                        grid_names=("cluster_grid",), num_threads=3, thread_name="wg", compiler_params=params,
                        **({"interpret": interpret} if interpret else {}))
    return call(x, w)


def xla_geglu(x, w):
    gate, up = jnp.split(x @ w, 2, axis=-1)
    return jax.nn.gelu(gate, approximate=True) * up


def stock_mgpu_matmul(x, w):
    from jax.experimental.pallas.ops.gpu import hopper_matmul_mgpu as hm
    dim = hm.MatmulDimension
    cfg = hm.TuningConfig(tile_m=128, tile_n=128, tile_k=64, max_concurrent_steps=4, grid_tile_width=8,
                          grid_minor_dim=dim.M, cluster_dimension=dim.M)
    return hm.matmul(x, w, None, config=cfg)


def _time(fn, args, iters):
    for _ in range(2):
        jax.block_until_ready(fn(*args))
    ts = []
    for _ in range(iters):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        ts.append((time.perf_counter() - t0) * 1e3)
    return float(np.median(ts))


VARIANTS = {
    "xla gemm alone": lambda x, w: x @ w,
    "mgpu stock matmul, gemm alone": stock_mgpu_matmul,
    "xla gemm + GeGLU fusion": xla_geglu,
    "triton 128x128x32, 8 warps, 4 stages": functools.partial(geglu_triton, bm=128, bn=128, bk=32, num_warps=8,
                                                               num_stages=4),
    "triton 128x128x64, 8 warps, 3 stages": functools.partial(geglu_triton, bm=128, bn=128, bk=64, num_warps=8,
                                                              num_stages=3),
    "mgpu 2x64 rows x 128, 4 stages, snake 8": functools.partial(geglu_mgpu, tile_m=64, tile_n=128, stages=4,
                                                                 snake=8),
    "mgpu 2x128 rows x 64, 4 stages, snake 4": functools.partial(geglu_mgpu, tile_m=128, tile_n=64, stages=4,
                                                                 snake=4),
}


def _halves(y):
    return jnp.split(y, 2, axis=-1)


def _bf16(key, split):
    """One gate/up GEMM on the weight ws[key], its product split by `split`, GELU(gate) * up."""
    def fn(x, ws):
        gate, up = split(x @ ws[key])
        return layers.gelu_tanh(gate) * up
    return fn


def _bf16_two(gelu):
    """Gate and up as two GEMMs."""
    return lambda x, ws: gelu(x @ ws["gate"]) * (x @ ws["up"])


def _jax_gelu(x):
    return jax.nn.gelu(x, approximate=True)


def _fp8(key, split):
    """The engine's FP8 path until session 56 on the weight ws[key]: x quantised, one e4m3 gate/up GEMM with
    per-column weight scales applied and rounded to bf16, split, GELU(gate) * up in bf16, quantised for the down
    GEMM."""
    def fn(x, ws):
        gate, up = split(formats.qmatmul("...D,FD->...F", x, ws[key]))
        return formats.quantise(layers.gelu_tanh(gate) * up, ws["s_down"])
    return fn


def _fp8_f32(key, split):
    """The engine's FP8 path since session 56 (`layers._mlp` up to the down GEMM's input): the GEMM's unscaled
    product, gate and up scaled in f32 (ws[key]'s output scale folded, as `formats.fold_scales` makes the engine's
    weights), GeGLU in f32, quantised for the down GEMM."""
    def fn(x, ws):
        w = ws[key]
        y = formats.fp8_product("...D,FD->...F", formats.quantise(x, w.act_scale), w, BF16)
        gate, up = split(y.astype(F32) * formats.output_scale("...D,FD->...F", w))
        return formats.quantise(layers.gelu_tanh(gate) * up, ws["s_down"])
    return fn


def _dequantised_gate(xq, g, dtype):
    """x @ gate written as a product of two dequantised e4m3 operands with scalar scales, in `dtype`: the form XLA's
    gemm rewriter is written to turn into a scaled cuBLASLt FP8 GEMM, which could then take GELU as its epilogue
    (jaxlib 0.11.2's did not: it ran a bf16 or f32 GEMM of the dequantised operands, docs/BENCHMARKS.md, session 53)."""
    return jnp.einsum("...D,FD->...F", xq.astype(dtype) * g.act_scale.astype(dtype),
                      g.q.astype(dtype) * g.scale.reshape(()).astype(dtype), preferred_element_type=BF16)


def _fp8_two(gelu, dtype=BF16):
    """Gate and up as two e4m3 GEMMs: gate's weight with one scale, as `_dequantised_gate`; up's per column."""
    def fn(x, ws):
        g, u = ws["q_gate"], ws["q_up"]
        xq = formats.quantise(x, g.act_scale)
        gate = _dequantised_gate(xq, g, dtype)
        up = formats.fp8_product("...D,FD->...F", xq, u, BF16)
        up = (up.astype(F32) * formats.output_scale("...D,FD->...F", u)).astype(BF16)
        return formats.quantise(gelu(gate) * up, ws["s_down"])
    return fn


LT = {"xla_gpu_enable_cublaslt": True}
# name: (fn(x, ws), compiler options)
XLA_FORMS = {
    "xla: gate/up gemm alone (bf16)": (lambda x, ws: x @ ws["halves"], {}),
    "xla: gate gemm alone (bf16)": (lambda x, ws: x @ ws["gate"], {}),
    "xla: block pairs (the engine, bf16)": (_bf16("blocks", layout.split_gate_up), {}),
    "xla: halves (bf16)": (_bf16("halves", _halves), {}),
    "xla: two gemms, x sigmoid(2z) (bf16)": (_bf16_two(layers.gelu_tanh), {}),
    "xla: two gemms, jax gelu (bf16)": (_bf16_two(_jax_gelu), {}),
    "xla: two gemms, jax gelu, cublaslt (bf16)": (_bf16_two(_jax_gelu), LT),
    "xla: two gemms, jax gelu, cublaslt, no triton (bf16)": (_bf16_two(_jax_gelu),
                                                           {**LT, "xla_gpu_enable_triton_gemm": False}),
    "xla: gate/up gemm alone (fp8)": (lambda x, ws: formats.fp8_product(
        "...D,FD->...F", formats.quantise(x, ws["q_halves"].act_scale), ws["q_halves"], BF16), {}),
    "xla: block pairs (the engine, fp8)": (_fp8_f32("qf_blocks", layout.split_gate_up), {}),
    "xla: block pairs, scaled in bf16 (the engine until session 56, fp8)": (_fp8("q_blocks", layout.split_gate_up),
                                                                          {}),
    "xla: halves (fp8)": (_fp8("q_halves", _halves), {}),
    "xla: two gemms, x sigmoid(2z) (fp8)": (_fp8_two(layers.gelu_tanh), {}),
    "xla: two gemms, jax gelu (fp8)": (_fp8_two(_jax_gelu), {}),
    "xla: two gemms, jax gelu, f32 dequantised (fp8)": (_fp8_two(_jax_gelu, F32), {}),
    "xla: gate gemm alone, dequantised (fp8)": (lambda x, ws: _dequantised_gate(
        formats.quantise(x, ws["q_gate"].act_scale), ws["q_gate"], BF16), {}),
    "xla: gate gemm alone, f32 dequantised (fp8)": (lambda x, ws: _dequantised_gate(
        formats.quantise(x, ws["q_gate"].act_scale), ws["q_gate"], F32), {}),
    "xla: gate gemm + jax gelu, f32 dequantised (fp8)": (lambda x, ws: _jax_gelu(_dequantised_gate(
        formats.quantise(x, ws["q_gate"].act_scale), ws["q_gate"], F32)), {}),
}


def _exact_mm(x, w):
    """x @ w in f32 with exact products: bf16 operands on the tensor cores with f32 accumulation (their products are
    exact in f32), else f32 at the highest precision: at B = 64's 52,224 rows that is 7 TFLOP on the f32 units, about
    two minutes."""
    if x.dtype == w.dtype == BF16:
        return jnp.matmul(x, w, preferred_element_type=F32)
    return jnp.matmul(x.astype(F32), w.astype(F32), precision=jax.lax.Precision.HIGHEST)


def xla_weights(x, w):
    """Every layout the XLA forms read, from w (K, 2F) = [gate | up], and their FP8 scales from x."""
    f = w.shape[1] // 2
    gate, up = w[:, :f], w[:, f:]
    # the engine's layout (`engine.weights`'s gate_up pattern)
    blocks = einops.rearrange(jnp.stack([gate, up]), "two D (Fb u) -> D (Fb two u)", u=layout.gate_up_block(f))
    sx = jnp.asarray(formats.act_scale_from_amax(jnp.max(jnp.abs(x.astype(F32)))))
    ref = jax.nn.gelu(_exact_mm(x, gate), approximate=True) * _exact_mm(x, up)
    s_down = jnp.asarray(formats.act_scale_from_amax(jnp.max(jnp.abs(ref))))

    def q(a, per_channel=True):   # (K, N) -> e4m3 laid out (N, K), as the engine's FP8 weights
        return formats.quantize_fp8(a.T.astype(F32), contract=(-1,), per_channel=per_channel, act_scale=sx)

    return {"halves": w, "blocks": blocks, "gate": gate, "up": up, "q_halves": q(w), "q_blocks": q(blocks),
            "qf_blocks": formats.fold_scales(q(blocks)), "q_gate": q(gate, per_channel=False), "q_up": q(up),
            "s_down": s_down}, ref


def _chain(fn, args, iters, chain):
    """ms a call: `chain` calls dispatched back to back, then one wait; the median of `iters` such runs."""
    for _ in range(2):
        jax.block_until_ready(fn(*args))
    ts = []
    for _ in range(iters):
        t0 = time.perf_counter()
        for _ in range(chain):
            out = fn(*args)
        jax.block_until_ready(out)
        ts.append((time.perf_counter() - t0) * 1e3 / chain)
    return float(np.median(ts))


def _compiled_facts(compiled) -> dict:
    """Whether cuBLASLt took GELU as an epilogue, and the entry computation's kernels (fusions and library calls)."""
    text = compiled.as_text()
    entry = text[text.index("ENTRY"):]
    kernels = len(re.findall(r"= \S+ (?:fusion|custom-call)\(", entry))
    return {"gelu_epilogue": bool(re.search(r'"epilogue":"GELU', text)), "kernels": kernels,
            "library_calls": re.findall(r'custom_call_target="([^"]+)"', entry),
            "epilogues": re.findall(r'"epilogue":"(\w+)"', text)}


def run_xla_forms(x, w, iters, chain, only, hlo=None):
    ws, ref = xla_weights(x, w)
    row = {}
    for name, (fn, options) in XLA_FORMS.items():
        if only and not any(o in name for o in only):
            continue
        try:
            compiled = jax.jit(fn).lower(x, ws).compile(compiler_options=options or None)
            got = compiled(x, ws)
            r = {"ms": _chain(compiled, (x, ws), iters, chain), **_compiled_facts(compiled), "options": options}
            if hlo:
                with open(hlo, "a") as f:
                    text = compiled.as_text()
                    f.write(f"### {name}, M = {x.shape[0]}\n{text[text.index('ENTRY'):]}\n")
            if not name.startswith("xla: gate"):   # the others compute GeGLU
                g = got.astype(F32) * (ws["s_down"] if got.dtype == formats.E4M3 else 1.0)
                r["rel_l2_vs_f32"] = float(jnp.linalg.norm(g - ref) / jnp.linalg.norm(ref))
        except Exception as e:  # noqa: BLE001  (a probe: report the form that fails and go on)
            r = {"error": f"{type(e).__name__}: {str(e)[:300]}"}
        row[name] = r
        print(f"   {name:52s} " + (f"{r['ms']:8.4f} ms  kernels {r['kernels']:3d}  GELU epilogue "
                                    f"{'yes' if r['gelu_epilogue'] else 'no '}"
                                    + (f"  rel L2 {r['rel_l2_vs_f32']:.1e}" if "rel_l2_vs_f32" in r else "")
                                    if "ms" in r else r["error"]), flush=True)
    return row


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--rows", default="8192,51200",
                   help="comma-separated M values: B x prefix tokens (the Pallas kernels need multiples of 256)")
    p.add_argument("--width", type=int, default=2048, help="K: Gemma 2B's width")
    p.add_argument("--hidden", type=int, default=16384, help="F: Gemma 2B's MLP width")
    p.add_argument("--iters", type=int, default=15, help="timed calls per variant (median reported)")
    p.add_argument("--chain", type=int, default=20,
                   help="the XLA forms: calls dispatched back to back per timed run (default: %(default)s)")
    p.add_argument("--only", action="append", default=None,
                   help="repeatable: only the variants and forms whose name contains this (e.g. 'xla:')")
    p.add_argument("--hlo", default=None, help="append each XLA form's optimized entry computation to this file")
    p.add_argument("--out", default=None, help="write the results as JSON here")
    args = p.parse_args()
    key = jax.random.key(0)
    w = (jax.random.normal(key, (args.width, 2 * args.hidden), jnp.float32) * 0.02).astype(jnp.bfloat16)
    res = {"device": str(jax.devices()[0]), "jax": jax.__version__, "rows": {}}
    for m in map(int, args.rows.split(",")):
        x = jax.random.normal(jax.random.fold_in(key, m), (m, args.width), jnp.float32).astype(jnp.bfloat16)
        flops = 2 * m * args.width * 2 * args.hidden
        want = jax.jit(xla_geglu)(x, w).astype(jnp.float32)
        row = res["rows"][m] = {}
        print(f"M={m}", flush=True)
        for name, fn in VARIANTS.items():
            if args.only and not any(o in name for o in args.only):
                continue
            try:
                fn = jax.jit(fn)
                got = fn(x, w)
                r = {"ms": _time(fn, (x, w), args.iters)}
                r["tflops"] = flops / r["ms"] / 1e9
                if got.shape == want.shape:
                    r["rel_l2"] = float(jnp.linalg.norm(got.astype(jnp.float32) - want) / jnp.linalg.norm(want))
            except Exception as e:  # noqa: BLE001  (a probe: report the variant that fails and go on)
                r = {"error": f"{type(e).__name__}: {str(e)[:300]}"}
            row[name] = r
            print(f"   {name:42s} " + (f"{r['ms']:8.3f} ms {r['tflops']:5.0f} TFLOP/s"
                                         + (f"  rel L2 {r['rel_l2']:.1e}" if "rel_l2" in r else "")
                                         if "ms" in r else r["error"]), flush=True)
        row.update(run_xla_forms(x, w, args.iters, args.chain, args.only, args.hlo))
    if args.out:
        with open(args.out, "w") as f:
            json.dump(res, f, indent=1)


if __name__ == "__main__":
    main()
