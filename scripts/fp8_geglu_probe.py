"""Probe: the FP8 prefix's gate/up GEMM with GeGLU and the down GEMM's e4m3 quantisation in its epilogue
(`pi0_jax.ops.fp8_geglu`, one persistent Mosaic GPU kernel) against the engine's XLA path (cuBLASLt's FP8 GEMM,
then a pass of its own), alone, at π0's prefix rows.

In the FP8 prefix, XLA runs gate/up as an e4m3 x e4m3 cuBLASLt GEMM into bf16, then one fusion reads gate and up
back, applies the per-column scales, GELU-tanh(gate) * up, and writes the down GEMM's e4m3 input. That pass costs
26 us a layer against the GEMM's 102 us at B = 1 (816 rows) and 1.84 against 5.37 ms at B = 64 (H200,
docs/BENCHMARKS.md, session 53), and cuBLASLt cannot take it as an epilogue (per-column scales). Session 46's bf16
kernel of this kind ran level with cuBLAS + pass; in FP8 the pass is a larger share of the GEMM (a third at B >= 8),
so the same design has more to win.

Forms, each timed as `--chain` calls back to back: the engine's XLA form (`geglu_probe.XLA_FORMS`' FP8 block pairs)
and its GEMM alone; the kernel at several launches (`CONFIGS`), on the rows as they are (the last row tile ragged)
and, where they do not tile, on x padded to whole tiles; the kernel's GEMM with no epilogue but a bf16 store
("product": its mainloop's speed), and with GeGLU's product stored in bf16 (no e4m3 conversion). The XLA forms start
from bf16 x and quantise it (in the engine that fuses into the norm before); the kernel takes x in e4m3, so it is
spared that pass: one read of x, about 1 % of the GEMM. Outputs are compared as dequantised values: against the
kernel's XLA form (`fp8_geglu.reference`: the same numerics, another summation order), the engine's form and f32.

Written in session 54 (2026-12-04), which was lent no GPU: the kernel passes the CPU tests in Mosaic GPU's
interpreter (`tests/test_fp8_geglu.py`). Session 55 (no GPU either) lowered it for sm_90 on a CPU, which found a
layout-inference failure (fixed), and compiled it through ptxas with `scripts/deviceless.py` (168 registers, no
spills, as jax's own Hopper matmul example). It has not yet been timed.

    python3 scripts/fp8_geglu_probe.py --rows 816,6528,51200 --out OUT.json
    python3 scripts/fp8_geglu_probe.py --rows 416,832 --width 1024 --hidden 4096   # the action expert's MLP, B = 8, 16
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import jax
import jax.numpy as jnp

sys.path.insert(0, str(Path(__file__).parent))
import geglu_probe  # noqa: E402
import profile_engine  # noqa: E402

from pi0_jax.ops import formats, fp8_geglu  # noqa: E402
from pi0_jax.ops.fp8_geglu import Launch  # noqa: E402

BF16, F32, E4M3 = jnp.bfloat16, jnp.float32, formats.E4M3
CHECK_ROWS = 8192   # the rows each form's output is checked on

# name: (launch, what the kernel stores: "e4m3" (the engine's), "bf16" (GeGLU unquantised), "product" (no epilogue))
CONFIGS = {
    "GEMM alone (bf16 product), 128x256x128, 4 stages": (Launch(), "product"),
    "GEMM alone (bf16 product), 128x256x128, 4 stages, delay 1": (Launch(delay=1), "product"),
    "128x256x128, 4 stages, snake 8 (until session 62)": (Launch(), "e4m3"),
    "128x256x128, 4 stages, bf16 out": (Launch(), "bf16"),
    "128x256x128, 4 stages, approximate exp": (Launch(approx=True), "e4m3"),
    "128x256x128, 4 stages, delay 1": (Launch(delay=1), "e4m3"),
    "128x256x128, 4 stages, snake 8 on columns": (Launch(minor=1), "e4m3"),
    "128x256x128, 3 stages, snake 16": (Launch(stages=3, snake=16), "e4m3"),
    "128x256x64, 6 stages": (Launch(tile_k=64, stages=6), "e4m3"),
    "128x128x128, 6 stages": (Launch(tile_n=128, stages=6), "e4m3"),
    # GELU folded into one exp2 (`fp8_geglu.gelu_folded`): SigLIP's GELU kernel's epilogue form since session 61
    "128x256x128, 4 stages, folded, approximate exp, clusters of two (the default)": (fp8_geglu.LAUNCH, "e4m3"),
    "64x256x128, 4 stages, folded, approximate exp": (Launch(tile_m=64, folded=True, approx=True), "e4m3"),
    "128x256x128, 4 stages, one tanh, approximate": (Launch(tanh=True, approx=True), "e4m3"),
    "128x256x128, 3 stages, snake 16, folded, approximate exp": (
        dataclasses.replace(fp8_geglu.LAUNCH, stages=3, snake=16), "e4m3"),
    # without clusters of two (`Launch.cluster`), as until session 66
    "128x256x128, 4 stages, folded, approximate exp, no clusters": (
        dataclasses.replace(fp8_geglu.LAUNCH, cluster=False), "e4m3"),
    "GEMM alone (bf16 product), 128x256x128, 4 stages, clusters of two": (Launch(cluster=True), "product"),
}


def _operands(m, k, f, seed=0):
    key = jax.random.key(seed)
    x = jax.random.normal(jax.random.fold_in(key, m), (m, k), F32).astype(BF16)
    w = (jax.random.normal(key, (k, 2 * f), F32) * 0.02).astype(BF16)
    ws, ref = geglu_probe.xla_weights(x, w)
    q = ws["q_blocks"]
    return x, ws, ref, formats.quantise(x, q.act_scale), q, ws["s_down"]


def _kernel(launch, out, m, q):
    """The kernel as a jitted function of (x (e4m3, m rows: ragged or whole tiles), weight, column scales)."""
    launch = fp8_geglu.fit(launch, q.q.shape[1], q.q.shape[0])
    return jax.jit(lambda *a: fp8_geglu._call(m, q.q.shape[1], q.q.shape[0], launch, False, out,
                                                     sms=jax.devices()[0].core_count)(*a))


def _timed(fn, fargs, iters, chain, kernel_time=False) -> dict:
    """ms a call as `chain` calls back to back (the host's dispatch included: at the expert's shapes it bounds the
    measure, session 62), and with kernel_time the summed GPU kernels of one call in a profiler trace (3 calls)."""
    r = {"ms": geglu_probe._chain(fn, fargs, iters, chain)}
    if kernel_time:
        t = profile_engine.kernel_times(lambda: fn(*fargs), calls=3)
        r["kernel_us"], r["kernels"] = t["kernel_ms"] * 1e3, t["kernels_per_call"]
    return r


def _report(row, name, r, width, out, res):
    """Keep a form's result, print it, and write the JSON after every form (a run cut off by a time limit keeps
    what it measured)."""
    row[name] = r
    facts = " ".join(f"{k} {v:.1e}" for k, v in r.items() if k.startswith(("rel", "equal")))
    kernel = f"kernels {r['kernel_us']:8.2f} us ({r['kernels']:.0f}) " if "kernel_us" in r else ""
    print(f"   {name:{width}s} " + (f"{r['ms']:8.4f} ms {r['tflops']:6.0f} TFLOP/s {kernel}{facts}"
                                     if "ms" in r else r["error"]), flush=True)
    if out:
        with open(out, "w") as f:
            json.dump(res, f, indent=1)


def _rel(a, b):
    a, b = jnp.asarray(a, F32), jnp.asarray(b, F32)
    return float(jnp.linalg.norm(a - b) / jnp.linalg.norm(b))


# the GELU kernel's launches timed beside the engine's (128-column tiles, folded, approximate exp: 13 waves of 1,632
# tiles at B = 8 against 7 of 816 for 256 columns): the epilogue's arithmetic (Launch.approx: the exp without its
# range reduction; Launch.folded: `fp8_geglu.gelu_folded`; Launch.tanh: `fp8_geglu.gelu_half_tanh`)
GELU_LAUNCHES = {"3 stages, GELU as x sigmoid(2 z)": Launch(stages=3),
                 "3 stages, approximate exp": Launch(stages=3, approx=True),
                 "3 stages, folded": Launch(stages=3, folded=True),
                 "3 stages, folded, approximate exp": Launch(stages=3, folded=True, approx=True),
                 "3 stages, snake 16, folded, approximate exp": Launch(stages=3, snake=16, folded=True, approx=True),
                 "128x128, 4 stages, one tanh, approximate": Launch(tile_n=128, stages=4, tanh=True, approx=True),
                 "128x128, 4 stages, folded, approximate exp, no clusters (until session 66)": dataclasses.replace(
                     fp8_geglu.GELU_LAUNCH, cluster=False)}


def siglip(rows, k, n, iters, chain, out, padded=False, kernel_time=False, only=None) -> dict:
    """SigLIP's FP8 fc1 (K = 1,152, N = 4,304) into fc2's e4m3 input: the engine's XLA path (`engine.vision.block`:
    cuBLASLt's GEMM, then one pass of scale, bias, GELU-tanh and quantisation), its GEMM alone, and the kernel
    (`fp8_geglu.gelu`, 16-column stores; 4 stages of 256-column tiles do not fit its shared memory) at the engine's
    launch and at
    `GELU_LAUNCHES`, checked against `fp8_geglu.gelu_reference` and the XLA path; its mainloop with a bf16 store and
    no epilogue; padded: also N padded to 64-column stores. only: the forms whose name contains one of these, and
    the engine's XLA path."""
    from pi0_jax.engine import vision   # noqa: PLC0415
    res = {}
    for m in rows:
        key = jax.random.key(m)
        x = jax.random.normal(key, (m, k), F32)
        w = jax.random.normal(jax.random.fold_in(key, 1), (n, k), F32) * k**-0.5 * 2
        fc1 = formats.fold_scales(formats.quantize_fp8(w, contract=(-1,), act_scale=formats.act_scale_from_amax(
            float(jnp.abs(x).max()))))
        fc2 = formats.quantize_fp8(jnp.ones((16, n)), contract=(-1,), act_scale=formats.act_scale_from_amax(3.0))
        bias = (jax.random.normal(jax.random.fold_in(key, 2), (n,)) * 0.5).astype(BF16)
        xq = formats.quantise(x, fc1.act_scale)

        def xla(xq, fc1, bias):
            y, scale = vision.layers.raw_mm(xq, fc1, BF16)
            return formats.quantise(jax.nn.gelu(vision._finish(y, bias, scale), approximate=True), fc2.act_scale)

        forms = {"xla: the engine's path (GEMM, pass)": (jax.jit(xla), (xq, fc1, bias)),
                 "xla: the GEMM alone": (jax.jit(lambda xq, fc1: vision.layers.raw_mm(xq, fc1, BF16)[0]), (xq, fc1)),
                 "kernel (the engine's launch)": (jax.jit(lambda xq, fc1, bias: fp8_geglu.gelu(
                     xq, fc1, bias, fc2.act_scale)), (xq, fc1, bias))}
        for label, launch in GELU_LAUNCHES.items():
            forms[f"kernel {label}"] = (jax.jit(lambda xq, fc1, bias, launch=launch: fp8_geglu.gelu(
                xq, fc1, bias, fc2.act_scale, launch)), (xq, fc1, bias))
        sms = jax.devices()[0].core_count

        def product(w_q, launch):   # the kernel's mainloop and a bf16 store, no epilogue
            launch = fp8_geglu.fit_gelu(launch, k, w_q.shape[0])
            cols = -(-w_q.shape[0] // launch.tile_n) * launch.tile_n
            table = jnp.zeros((3, cols), F32)
            return jax.jit(lambda xq: fp8_geglu._call(m, k, w_q.shape[0], launch, False, "product", sms,
                                                      act="gelu")(xq, w_q, table)), (xq,)

        forms["mainloop + bf16 store, N as it is"] = product(fc1.q, Launch(stages=3))
        forms["mainloop + bf16 store, the engine's launch"] = product(fc1.q, fp8_geglu.GELU_LAUNCH)
        if padded:
            # N padded to whole 64-column blocks (zero weight rows, zero bias): 64-column swizzled stores instead of
            # 16-column unswizzled ones; the padded columns come out 0 and are cut for the checks
            npad = -(-n // fp8_geglu.GELU_BLOCK) * fp8_geglu.GELU_BLOCK
            fc1p = formats.fold_scales(formats.quantize_fp8(jnp.pad(w, ((0, npad - n), (0, 0))), contract=(-1,),
                                                            act_scale=fc1.act_scale))
            fc2p = formats.quantize_fp8(jnp.ones((16, npad)), contract=(-1,), act_scale=fc2.act_scale)
            biasp = jnp.pad(bias, (0, npad - n))
            for label, launch in (("", Launch(stages=3)), (", 128x128 4 stages", Launch(tile_n=128, stages=4)),
                                  (", approximate exp", Launch(stages=3, approx=True))):
                forms[f"kernel (3 stages), N padded to {npad}{label}"] = (jax.jit(
                    lambda xq, fc1, bias, launch=launch: fp8_geglu.gelu(xq, fc1, bias, fc2p.act_scale,
                                                                        launch)[:, :n]), (xq, fc1p, biasp))
            forms[f"mainloop + bf16 store, N padded to {npad}"] = product(fc1p.q, Launch(stages=3))
            forms[f"xla: the GEMM alone, N padded to {npad}"] = (
                jax.jit(lambda xq, fc1: vision.layers.raw_mm(xq, fc1, BF16)[0]), (xq, fc1p))
        mine = fp8_geglu.gelu_reference(xq, fc1, bias, fc2.act_scale).astype(F32)
        engine = forms["xla: the engine's path (GEMM, pass)"][0](xq, fc1, bias).astype(F32)
        row = res[m] = {"rel_l2_reference_vs_engine": _rel(mine, engine)}
        print(f"M={m} (SigLIP fc1)", flush=True)
        for name, (fn, fargs) in forms.items():
            if only and "engine's path" not in name and not any(o in name for o in only):
                continue
            try:
                r = _timed(fn, fargs, iters, chain, kernel_time)
                r["tflops"] = 2 * m * k * n / r["ms"] / 1e9
                if name.startswith("kernel"):   # (padded forms come out cut to N)
                    got = fn(*fargs).astype(F32)
                    r["equal_to_its_xla_form"] = float(jnp.mean(got == mine))
                    r["rel_l2_vs_its_xla_form"] = _rel(got, mine)
                    r["rel_l2_vs_engine"] = _rel(got, engine)
                    r["finite"] = bool(jnp.isfinite(got).all())
            except Exception as e:  # noqa: BLE001  (a probe: report the form that fails and go on)
                r = {"error": f"{type(e).__name__}: {str(e)[:600]}"}
            _report(row, name, r, 40, out, {"jax": jax.__version__, "device": str(jax.devices()[0]), "siglip": res})
    return res


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--rows", default="816,6528,51200", help="comma-separated M values (π0's prefix at B = 1, 8, 64)")
    p.add_argument("--width", type=int, default=2048, help="K: Gemma 2B's width")
    p.add_argument("--hidden", type=int, default=16384, help="F: Gemma 2B's MLP width")
    p.add_argument("--iters", type=int, default=15, help="timed runs per form (median reported)")
    p.add_argument("--chain", type=int, default=20, help="calls dispatched back to back per timed run")
    p.add_argument("--only", action="append", default=None,
                   help="repeatable: only the kernel configs (with --siglip: the forms) whose name contains this")
    p.add_argument("--kernel-time", action="store_true",
                   help="also each form's GPU kernel time from a profiler trace (the chained wall time is bound by "
                        "the host's dispatch at the expert's shapes)")
    p.add_argument("--out", default=None, help="write the results as JSON here")
    p.add_argument("--siglip", default=None,
                   help="comma-separated M values: SigLIP's FP8 fc1 with GELU (`fp8_geglu.gelu`) instead, e.g. "
                        "768,6144,49152 (3 cameras at B = 1, 8, 64)")
    p.add_argument("--siglip-padded", action="store_true",
                   help="with --siglip: also the kernel with N padded to whole 64-column stores (session 61: slower)")
    args = p.parse_args()
    if args.siglip:
        siglip([int(m) for m in args.siglip.split(",")], 1152, 4304, args.iters, args.chain, args.out,
               args.siglip_padded, args.kernel_time, args.only)
        return
    res = {"jax": jax.__version__, "device": str(jax.devices()[0]), "rows": {}}
    for m in map(int, args.rows.split(",")):
        x, ws, ref, xq, q, s_down = _operands(m, args.width, args.hidden)
        flops = 2 * m * args.width * 2 * args.hidden
        engine = jax.jit(geglu_probe.XLA_FORMS["xla: block pairs (the engine, fp8)"][0])
        # the checks on the first rows only (each row's output depends on its own row): at B = 64's 52,224 rows the
        # setup's references over all rows printed nothing within 210 s (session 65)
        c = min(m, CHECK_ROWS)
        want = engine(x[:c], ws).astype(F32) * s_down
        mine = fp8_geglu.reference(xq[:c], q, s_down).astype(F32)
        product = jnp.einsum("md,nd->mn", xq[:c], q.q, preferred_element_type=F32)
        ref = ref[:c]
        row = res["rows"][m] = {}
        print(f"M={m}", flush=True)
        forms = {"xla: the engine's form (x quantised, GEMM, pass)": (engine, (x, ws)),
                 "xla: the engine's form until session 56 (scaled in bf16)": (jax.jit(geglu_probe.XLA_FORMS[
                     "xla: block pairs, scaled in bf16 (the engine until session 56, fp8)"][0]), (x, ws)),
                 "xla: the GEMM alone (x quantised)": (
                     jax.jit(geglu_probe.XLA_FORMS["xla: gate/up gemm alone (fp8)"][0]), (x, ws))}
        scales = fp8_geglu.column_scales(q, s_down)
        tile = fp8_geglu.LAUNCH.tile_m
        mp = -(-m // tile) * tile
        for name, (launch, out) in CONFIGS.items():
            if args.only and not any(o in name for o in args.only):
                continue
            forms[f"kernel {name}"] = (_kernel(launch, out, m, q), (xq, q.q, scales))
            if mp != m and launch == fp8_geglu.LAUNCH and out == "e4m3":
                forms[f"kernel {name}, x padded to {mp} rows"] = (
                    _kernel(launch, out, mp, q), (jnp.pad(xq, ((0, mp - m), (0, 0))), q.q, scales))
        for name, (fn, fargs) in forms.items():
            try:
                got = fn(*fargs)[:c]
                r = _timed(fn, fargs, args.iters, args.chain, args.kernel_time)
                r["tflops"] = flops / r["ms"] / 1e9
                if name.startswith("kernel") and got.shape == product.shape:   # the kernel's GEMM alone
                    r["rel_l2_vs_xla_product"] = _rel(got, product)
                elif name.startswith("kernel"):
                    g = got.astype(F32) * s_down   # up's columns carry 1 / s_down in bf16 out too
                    if got.dtype == E4M3:
                        r["rel_l2_vs_its_xla_form"] = _rel(got, mine)
                        r["equal_to_its_xla_form"] = float(jnp.mean(got.astype(F32) == mine))
                    r["rel_l2_vs_engine"] = _rel(g, want)
                    r["rel_l2_vs_f32"] = _rel(g, ref)
                elif "engine" in name:
                    r["rel_l2_vs_f32"] = _rel(want, ref)
            except Exception as e:  # noqa: BLE001  (a probe: report the form that fails and go on)
                r = {"error": f"{type(e).__name__}: {str(e)[:600]}"}
            _report(row, name, r, 72, args.out, res)


if __name__ == "__main__":
    main()
