"""What an FP8 activation quantisation costs as an XLA fusion, by form, at the prefix's and SigLIP's shapes.

Every e4m3 GEMM of the engine gets its input from an XLA fusion that ends in "x / act_scale, clipped to ±448,
converted to e4m3" (`ops.formats.qmatmul`); the one before the down-projection also applies gate/up's per-column
weight scale and GeGLU. This times such fusions alone on a GPU, as bytes moved per second against a plain bf16
pass of the same size, so a slow form shows as a fraction of the bandwidth:

  copy     y + 1 in bf16 (reads and writes bf16: the bandwidth reference)
  div      the quantisation as qmatmul writes it: x / s
  mul      x * (1 / s), the reciprocal computed outside the fusion
  geglu-*  gate/up's epilogue: per-column scale, GELU-tanh(gate) * up in bf16, then div or mul; geglu-f32-mul:
           GELU and the product in f32, rounded to bf16 once
  gelu-*   SigLIP's fc1 epilogue (--hidden wide): per-column scale, bias, GELU-tanh in bf16 (gelu-bf16: no
           quantisation after it), in f32 (gelu-f32-div), or as x sigmoid(2 z) (gelu-sigmoid-div); then div
  halfsum  gate + up in bf16 (reads gate/up's output, writes half of it: GeGLU's bandwidth reference in bf16);
           halfsum-e4m3 the same quantised: e4m3's conversion alone
  geglu-bf16  geglu-div without the quantisation
  geglu-sigmoid-div  geglu-div with the engine's GELU-tanh, x sigmoid(2 z) (`engine.layers.gelu_tanh`);
           geglu-sigmoid-bf16 the same unquantised
  geglu-blocks  geglu-div on the engine's fused gate/up product (gate and up in `layout.gate_up_block` pairs);
           geglu-blocks-bf16 geglu-bf16 on it
  geglu-pallas:R:C:W[:V]  geglu-div as a Pallas Triton kernel, R rows and C columns a program, W warps: scale,
           GELU, product and quantisation in f32 registers, rounded to bf16 where XLA's path rounds; V a variant
           (`_geglu_pallas`)

    python scripts/quantise_probe.py --rows 51200 --out quantise.json
    python scripts/quantise_probe.py --rows 49152 --width 1152 --hidden 4304 --forms copy gelu-bf16 gelu-div
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import jax.numpy as jnp
import numpy as np

from pi0_jax.engine import layers
from pi0_jax.ops import layout
from pi0_jax.ops.formats import quantise

E4M3, F32, BF16 = jnp.float8_e4m3fn, jnp.float32, jnp.bfloat16


def _clip(x):   # the "mul" forms' end; the "div" forms call the project's own `formats.quantise`
    return jnp.clip(x, -448.0, 448.0).astype(E4M3)


def _tanh_gelu(x):
    return jax.nn.gelu(x, approximate=True)


def _geglu(y, col, f32: bool, split=lambda h: jnp.split(h, 2, axis=-1), gelu=_tanh_gelu):
    """gelu: jax's GELU-tanh, or the engine's x sigmoid(2 z) form (`engine.layers.gelu_tanh`)."""
    h = (y.astype(F32) * col).astype(BF16)
    gate, up = split(h)
    if f32:
        gate, up = gate.astype(F32), up.astype(F32)
        return (gelu(gate) * up).astype(BF16)
    return gelu(gate) * up


def _geglu_pallas(rows: int, cols: int, warps: int, variant: str = "full"):
    """y (R, 2F) as [gate | up] -> e4m3 (R, F), one (rows, cols) block of gate and of up a program. variant: "full"
    (XLA's roundings, GELU as x sigmoid(2 z), x / s); "bf16out" (no quantisation: a bf16 output); "nogelu" (gate *
    up quantised); "lean" (no bf16 roundings between the ops, x * (1 / s)); "tanh" (full with GELU's tanh)."""
    from jax.experimental import pallas as pl
    from jax.experimental.pallas import triton as plgpu

    def rnd(x):
        return x if variant == "lean" else x.astype(BF16).astype(F32)

    def kernel(y_ref, col_ref, s_ref, o_ref):
        f = o_ref.shape[1]
        r = pl.ds(pl.program_id(0) * rows, rows)
        g_cols, u_cols = pl.ds(pl.program_id(1) * cols, cols), pl.ds(f + pl.program_id(1) * cols, cols)
        g = rnd(y_ref[r, g_cols].astype(F32) * col_ref[pl.ds(0, 1), g_cols])
        u = rnd(y_ref[r, u_cols].astype(F32) * col_ref[pl.ds(0, 1), u_cols])
        z = 0.7978845608028654 * (g + 0.044715 * g * g * g)
        if variant == "nogelu":
            act = g
        elif variant == "tanh":
            act = 0.5 * g * (1.0 + jnp.tanh(z))
        else:
            act = g / (1.0 + jnp.exp(-2.0 * z))
        h = rnd(rnd(act) * u)
        if variant == "bf16out":
            o_ref[r, g_cols] = h.astype(BF16)
            return
        h = h * (1.0 / s_ref[0, 0]) if variant == "lean" else h / s_ref[0, 0]
        o_ref[r, g_cols] = jnp.clip(h, -448.0, 448.0).astype(E4M3)

    def fn(y, col, s, inv):
        n, f = y.shape[0], y.shape[1] // 2
        cpu = jax.default_backend() == "cpu"
        out = jax.ShapeDtypeStruct((n, f), BF16 if variant == "bf16out" else E4M3)
        return pl.pallas_call(kernel, grid=(n // rows, f // cols), out_shape=out, interpret=cpu,
                              name="geglu_quantise",
                              compiler_params=None if cpu else plgpu.CompilerParams(num_warps=warps, num_stages=1),
                              )(y, col[None], jnp.reshape(s, (1, 1)))
    return fn


def _gelu(y, col, form: str):
    """SigLIP's fc1 epilogue before fc2's quantisation: per-column scale, the bias (here 0.5), GELU-tanh."""
    h = (y.astype(F32) * col).astype(BF16) + jnp.asarray(0.5, BF16)
    if form == "f32":
        return jax.nn.gelu(h.astype(F32), approximate=True)
    if form == "sigmoid":   # 0.5 (1 + tanh(z)) = sigmoid(2 z)
        return h * jax.nn.sigmoid(jnp.asarray(1.5957691, BF16) * (h + jnp.asarray(0.044715, BF16) * h * h * h))
    return jax.nn.gelu(h, approximate=True)


FORMS = {
    "copy": lambda y, col, s, inv: y + jnp.asarray(1, BF16),
    "div": lambda y, col, s, inv: quantise(y, s),
    "mul": lambda y, col, s, inv: _clip(y.astype(F32) * inv),
    "geglu-div": lambda y, col, s, inv: quantise(_geglu(y, col, False), s),
    "geglu-mul": lambda y, col, s, inv: _clip(_geglu(y, col, False).astype(F32) * inv),
    "geglu-f32-mul": lambda y, col, s, inv: _clip(_geglu(y, col, True).astype(F32) * inv),
    "geglu-sigmoid-div": lambda y, col, s, inv: quantise(_geglu(y, col, False, gelu=layers.gelu_tanh), s),
    "geglu-blocks": lambda y, col, s, inv: quantise(_geglu(y, col, False, layout.split_gate_up), s),
    "geglu-blocks-bf16": lambda y, col, s, inv: _geglu(y, col, False, layout.split_gate_up),
    "halfsum": lambda y, col, s, inv: y[:, : y.shape[1] // 2] + y[:, y.shape[1] // 2 :],
    "halfsum-e4m3": lambda y, col, s, inv: quantise(y[:, : y.shape[1] // 2] + y[:, y.shape[1] // 2 :], s),
    "geglu-bf16": lambda y, col, s, inv: _geglu(y, col, False),
    "geglu-sigmoid-bf16": lambda y, col, s, inv: _geglu(y, col, False, gelu=layers.gelu_tanh),
    "gelu-bf16": lambda y, col, s, inv: _gelu(y, col, "bf16"),
    "gelu-div": lambda y, col, s, inv: quantise(_gelu(y, col, "bf16"), s),
    "gelu-f32-div": lambda y, col, s, inv: quantise(_gelu(y, col, "f32"), s),
    "gelu-sigmoid-div": lambda y, col, s, inv: quantise(_gelu(y, col, "sigmoid"), s),
}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--rows", type=int, default=51200, help="activation rows (default: %(default)s, π0.5's prefix "
                                                           "at B = 64)")
    p.add_argument("--width", type=int, default=2048, help="a GEMM input's width (default: %(default)s)")
    p.add_argument("--hidden", type=int, default=16384, help="the MLP hidden width (default: %(default)s)")
    p.add_argument("--forms", nargs="+", default=list(FORMS), help="forms to time (default: all but the Pallas "
                                                                   "ones): " + ", ".join(FORMS) + ", geglu-pallas:R:C:W")
    p.add_argument("--iters", type=int, default=20, help="calls per timing, median of 5 (default: %(default)s)")
    p.add_argument("--out", default=None, help="write the rows as JSON here")
    args = p.parse_args()
    s = jnp.float32(0.05)
    inv = 1 / s
    rows, outs = [], {}
    for name in args.forms:
        fields = name.split(":")
        if name.startswith("geglu-pallas"):
            fn = _geglu_pallas(*map(int, fields[1:4]), *fields[4:])
        else:
            fn = FORMS[name]
        width = {"geglu": 2 * args.hidden, "gelu": args.hidden, "halfsum": 2 * args.hidden}.get(
            name.split("-")[0], args.width)
        rng = np.random.default_rng(0)   # the same inputs for every form of a width
        y = jax.random.normal(jax.random.key(0), (args.rows, width), BF16)
        col = jnp.asarray(rng.uniform(0.5, 1.5, width), F32)
        exe = jax.jit(fn).lower(y, col, s, inv).compile()
        out = exe(y, col, s, inv)
        moved = y.nbytes + out.nbytes
        times = []
        for _ in range(5):
            jax.block_until_ready(exe(y, col, s, inv))
            t0 = time.perf_counter()
            for _ in range(args.iters):
                out = exe(y, col, s, inv)
            jax.block_until_ready(out)
            times.append((time.perf_counter() - t0) / args.iters)
        t = float(np.median(times))
        rows.append({"form": name, "shape": list(y.shape), "out": str(out.dtype), "ms": t * 1e3,
                     "bytes": moved, "gb_s": moved / t / 1e9})
        if name.startswith("geglu") and out.dtype == E4M3:   # against the first e4m3 GeGLU form timed
            got = np.asarray(out.astype(F32))
            cols = "blocks" if name == "geglu-blocks" else "halves"
            ref = outs.setdefault(cols, got)
            rows[-1]["vs_first_geglu_" + cols] = {"differing": float(np.mean(got != ref)),
                                                  "max_abs": float(np.max(np.abs(got - ref))),
                                                  "nan": int(np.isnan(got).sum())}
        print(json.dumps(rows[-1]), flush=True)
        del y, out
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"rows": rows, "device": str(jax.devices()[0])}, f, indent=1)


if __name__ == "__main__":
    main()
