"""Which FP8 GEMM forms does this JAX/XLA turn into fast cuBLASLt FP8 GEMMs, at the prefix's shapes?

For each form of "bf16 activations -> quantise to e4m3 with a static scale -> GEMM with an e4m3 weight -> bf16
out" (and the plain bf16 GEMM), prints: the FP8 custom calls in the optimized HLO with their output types, the other
kernels around them (transposes of the weight, f32 epilogues), the time per call and the rate. Shapes are Gemma 2B's
MLP in the prefix at B prefix rows of 816 tokens: gate/up (2048 -> 32768) and down (16384 -> 2048).

  python scripts/fp8_probe.py --rows 816 6528 52224 --out probe.json
"""

from __future__ import annotations

import argparse
import json
import re
import time

import jax
import jax.numpy as jnp

E4M3 = jnp.float8_e4m3fn
F32, BF16 = jnp.float32, jnp.bfloat16


def quantise(x, s):
    return jnp.clip(x.astype(F32) / s, -448.0, 448.0).astype(E4M3)


def _contract(w_t: bool):
    """x (M, K) against w (K, N) or, transposed, (N, K)."""
    return (((1,), (1,)), ((), ())) if w_t else (((1,), (0,)), ((), ()))


def form_bf16(x, w, ws, sx, w_t):
    return jax.lax.dot_general(x, w, _contract(w_t), preferred_element_type=BF16)


def form_channel_f32(x, w, ws, sx, w_t):
    """The engine's form until now: f32 dequantised operands, f32 out, per-channel scale, then bf16."""
    y = jax.lax.dot_general(quantise(x, sx).astype(F32) * sx, w.astype(F32), _contract(w_t),
                            preferred_element_type=F32)
    return (y * ws).astype(BF16)


def form_channel_bf16(x, w, ws, sx, w_t):
    """f32 dequantised operands, the GEMM's output converted to bf16 at once, the per-channel scale after."""
    y = jax.lax.dot_general(quantise(x, sx).astype(F32) * sx, w.astype(F32), _contract(w_t),
                            preferred_element_type=F32)
    return y.astype(BF16) * ws.astype(BF16)


def form_tensor_bf16(x, w, ws, sx, w_t):
    """Per-tensor weight scale: both scales are scalars, the output converted to bf16."""
    y = jax.lax.dot_general(quantise(x, sx).astype(F32) * sx, w.astype(F32) * ws[0, 0], _contract(w_t),
                            preferred_element_type=F32)
    return y.astype(BF16)


def form_direct_bf16(x, w, ws, sx, w_t):
    """e4m3 operands straight into the dot, bf16 out, both scales applied after."""
    y = jax.lax.dot_general(quantise(x, sx), w, _contract(w_t), preferred_element_type=BF16)
    return y * (sx * ws).astype(BF16)


FORMS = {"bf16": form_bf16, "channel_f32": form_channel_f32, "channel_bf16": form_channel_bf16,
         "tensor_bf16": form_tensor_bf16, "direct_bf16": form_direct_bf16}
SHAPES = {"gate_up": (2048, 32768), "down": (16384, 2048)}


def hlo_summary(text: str) -> dict:
    calls = re.findall(r"= \(?([a-z0-9]+\[[0-9,]*\])[^\n]*custom_call_target=\"([^\"]+)\"", text)
    entry = text[text.index("ENTRY"):]
    ops = re.findall(r"^\s*\S+ = \S+ (fusion|custom-call|transpose|copy|convert|multiply)\(", entry, re.M)
    return {"custom_calls": [f"{t} -> {s}" for s, t in calls], "entry_ops": len(ops),
            "fusions": sum(o == "fusion" for o in ops), "transposes": len(re.findall(r"transpose", entry))}


def bench(fn, args, iters: int) -> float:
    out = fn(*args)
    out.block_until_ready()
    times = []
    for _ in range(3):
        start = time.perf_counter()
        for _ in range(iters):
            out = fn(*args)
        out.block_until_ready()
        times.append((time.perf_counter() - start) / iters)
    return sorted(times)[1] * 1e3


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--rows", type=int, nargs="+", default=[816, 6528, 52224],
                   help="GEMM rows M (816 tokens per batch element: 816 = B1, 6528 = B8, 52224 = B64)")
    p.add_argument("--forms", nargs="+", default=list(FORMS), choices=list(FORMS), help="GEMM forms to try")
    p.add_argument("--iters", type=int, default=20, help="calls per timing (median of 3 timings)")
    p.add_argument("--layouts", default="both", choices=["both", "stored", "transposed"],
                   help="weight layouts: as stored (K, N), pre-transposed (N, K), or both")
    p.add_argument("--out", default=None, help="write the rows as JSON here")
    args = p.parse_args()
    key = jax.random.key(0)
    rows = []
    print(f"{jax.devices()[0].device_kind} · jax {jax.__version__}", flush=True)
    print(f"{'shape':8s} {'M':>6s} {'form':13s} {'w^T':>3s} {'ms':>8s} {'TFLOP/s':>8s} ops  custom calls")
    for name, (k, n) in SHAPES.items():
        w = jax.random.normal(jax.random.fold_in(key, 1), (k, n), F32) * 0.02
        scales = {"channel": jnp.max(jnp.abs(w), axis=0, keepdims=True) / 448.0,
                  "tensor": jnp.full((1, n), jnp.max(jnp.abs(w)) / 448.0)}
        for m in args.rows:
            x = (jax.random.normal(jax.random.fold_in(key, m), (m, k), F32)).astype(BF16)
            ref = form_bf16(x, w.astype(BF16), None, None, False).astype(F32)   # the bf16 GEMM every form is held to
            sx = jnp.float32(4.5 / 448.0)
            for form in args.forms:
                for w_t in {"both": (False, True), "stored": (False,), "transposed": (True,)}[args.layouts]:
                    ws = scales["tensor" if form.startswith("tensor") else "channel"]
                    weight = w.astype(BF16) if form == "bf16" else (w / ws).astype(E4M3)
                    weight = weight.T if w_t else weight
                    weight = jnp.asarray(weight)  # materialised in that layout, as a stored weight would be
                    fn = jax.jit(FORMS[form], static_argnums=4)
                    row = {"shape": name, "M": m, "K": k, "N": n, "form": form, "w_transposed": w_t}
                    try:
                        start = time.perf_counter()
                        compiled = fn.lower(x, weight, ws, sx, w_t).compile()
                        row["compile_s"] = time.perf_counter() - start
                        row.update(hlo_summary(compiled.as_text()))
                        ms = bench(lambda *a: compiled(*a), (x, weight, ws, sx), args.iters)
                        row["ms"], row["tflops"] = ms, 2 * m * k * n / ms / 1e9
                        got = compiled(x, weight, ws, sx).astype(F32)
                        row["rel_l2_vs_bf16"] = float(jnp.linalg.norm(got - ref) / jnp.linalg.norm(ref))
                    except Exception as e:  # noqa: BLE001 - a form XLA rejects is a result too
                        row["error"] = f"{type(e).__name__}: {str(e)[:200]}"
                    rows.append(row)
                    if "error" in row:
                        print(f"{name:8s} {m:6d} {form:13s} {int(w_t):3d} ERROR {row['error']}", flush=True)
                    else:
                        print(f"{name:8s} {m:6d} {form:13s} {int(w_t):3d} {row['ms']:8.3f} {row['tflops']:8.1f} "
                              f"{row['entry_ops']:3d}  {row['custom_calls']} err {row['rel_l2_vs_bf16']:.2e} "
                              f"compile {row['compile_s']:.1f} s",
                              flush=True)
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"device": jax.devices()[0].device_kind, "jax": jax.__version__, "rows": rows}, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
