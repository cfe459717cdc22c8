"""The one entry point of every weighted matmul (Gemma's einsums, the engine's fused GEMMs) and SigLIP's Dense hook.

`matmul(eqn, x, w)`: a plain weight is cast to the activation dtype and contracted with `jnp.einsum`; a `QArray`
(FP8, `pi0_jax.ops.formats`) brings its own op; a `Tap` (a plain weight that records the magnitude of its GEMM
input while `recording()` is active, for calibration) runs the plain op. SigLIP's Flax Dense layers keep their own
op for plain kernels and come here through `dense_interceptor` only for quantised or tapped ones.

`compiler_options(tree, gemm, vision_tower=..., prefix_batch=...)`: which library runs the GEMMs of a program
compiled on a GPU. "xla" is XLA's own choice: its autotuner picks a Triton GEMM or cuBLAS per dot, and a dot it
gives to Triton keeps its bias, GELU and residual as separate fusions. "cublas" turns XLA's Triton GEMMs off, so
every dot is a cuBLAS call that takes its bias, GELU-tanh and residual add as epilogues (SigLIP's Dense layers:
386 -> 305 kernels at B = 1).
That is faster in the vision tower at every batch (its kernels 2.32 -> 1.98 ms at B = 1, 5-10 % from B = 8) but
slower in the denoise step, and level or slower in the prefix from B = 8 (docs/BENCHMARKS.md, "cuBLAS for every
GEMM", "The call as two programs"); one option holds for a whole program. "auto" (the default) is therefore cuBLAS
for a program that runs only the vision tower (`vision_tower=True`: the engine's call runs it as a program of its
own) and for the prefix fill without the denoise loop at batch <= PREFIX_CUBLAS_MAX_BATCH (`prefix_batch`: the
call's prefix program with its first step, or the prefix alone), where XLA gives the prefix's q/k/v and
out-projection Triton GEMMs slower than cuBLAS's (the call 0.03-0.20 ms faster at B = 1 and 2 on H200s: "π0 under
14 ms, the call's host times, and `Policy`'s copy back"); XLA's choice for any other. The simulator's rollout
(`pi0-jax eval`), one program, defaults to "cublas", 5 % faster there ("cuBLAS in the simulator"). Programs with
FP8 weights always get cuBLAS: XLA's autotuner compiles Triton FP8 GEMMs for minutes, then picks cuBLASLt anyway.
"""

from __future__ import annotations

import contextlib
import functools
import string

import flax.linen as nn
import flax.struct
import jax
import jax.numpy as jnp

from pi0_jax.ops import formats
from pi0_jax.ops.formats import QArray, has_fp8, qmatmul

GEMMS = ("auto", "xla", "cublas")
PREFIX_CUBLAS_MAX_BATCH = 2   # measured at B = 1 and 2; at B = 8 and 64 it was level or slower (2026-11-25)
_RECORDER: dict | None = None


def check_gemm(gemm: str) -> str:
    if gemm not in GEMMS:
        raise ValueError(f"gemm must be one of {GEMMS}, got {gemm!r}")
    return gemm


def library(tree, gemm: str = "auto", platform: str | None = None, *, vision_tower: bool = False,
            prefix_batch: int | None = None) -> str:
    """Which GEMM library a program over the weights `tree` gets (module doc): "xla" (XLA's choice; always off a
    GPU) or "cublas". vision_tower: the program runs SigLIP alone; prefix_batch: the program fills the prefix cache
    (with at most the first denoise step) at this batch; gemm="auto" is cuBLAS for either at a small batch."""
    if (platform or jax.default_backend()) != "gpu":
        return "xla"
    gemm = check_gemm(gemm)
    if gemm == "auto":
        small_prefix = prefix_batch is not None and prefix_batch <= PREFIX_CUBLAS_MAX_BATCH
        gemm = "cublas" if vision_tower or small_prefix else "xla"
    return "cublas" if gemm == "cublas" or has_fp8(tree) else "xla"


def compiler_options(tree, gemm: str = "auto", platform: str | None = None, *, vision_tower: bool = False,
                     prefix_batch: int | None = None) -> dict | None:
    """XLA options for `library`'s choice: None (XLA's defaults) or no Triton GEMMs."""
    if library(tree, gemm, platform, vision_tower=vision_tower, prefix_batch=prefix_batch) == "xla":
        return None
    return {"xla_gpu_enable_triton_gemm": False}


@flax.struct.dataclass
class Tap:
    """A plain weight with a name: its GEMM input is recorded while `recording()` is active."""

    w: jax.Array
    key: str = flax.struct.field(pytree_node=False)

    @property
    def shape(self):
        return tuple(self.w.shape)


@contextlib.contextmanager
def recording(percentile: float | None = None):
    """Collect (key, amax, percentile-of-|x|) for every Tap matmul run inside the block. Under jit, trace and run
    inside the block (the percentile is baked into the trace)."""
    global _RECORDER
    prev, _RECORDER = _RECORDER, {"percentile": percentile, "rows": []}
    try:
        yield _RECORDER
    finally:
        _RECORDER = prev


def _append(key, amax, pct):
    if _RECORDER is not None:
        _RECORDER["rows"].append((key, float(amax), None if _RECORDER["percentile"] is None else float(pct)))


def _record(key: str, x: jax.Array) -> None:
    """Statistics on device, one host callback per call (works eagerly and under jit; the recorder must be active
    when the program runs, so block on its outputs inside `recording()`)."""
    if _RECORDER is None:
        return
    a = jnp.abs(x.astype(jnp.float32))
    p = _RECORDER["percentile"]
    pct = jnp.percentile(a, p) if p is not None else jnp.float32(0)
    jax.debug.callback(functools.partial(_append, key), jnp.max(a), pct)


def is_quant(w) -> bool:
    return isinstance(w, (QArray, Tap))


def matmul(eqn: str, x: jax.Array, w) -> jax.Array:
    if isinstance(w, QArray):
        return qmatmul(eqn, x, w)
    if isinstance(w, Tap):
        _record(w.key, x)
        return jnp.einsum(eqn, x, w.w.astype(x.dtype))
    return jnp.einsum(eqn, x, w.astype(x.dtype))


def input_scale(w) -> jax.Array | None:
    """w's activation scale where w is an FP8 x FP8 weight, whose GEMM takes an e4m3 input (`formats.quantise`);
    else None."""
    return w.act_scale if isinstance(w, QArray) and w.act_scale is not None else None


def raw_matmul(eqn: str, x: jax.Array, w, dtype) -> tuple[jax.Array, jax.Array | None]:
    """`matmul` with an FP8 x FP8 weight's two ends left to kernels around it: (product, its f32 output scale laid
    out against the output, `formats.output_scale`). x may come quantised (e4m3, by a kernel before this GEMM with
    `input_scale(w)`); otherwise it is quantised here. Any other weight: (matmul(eqn, x, w), None). dtype: the
    product's (the activation dtype)."""
    s = input_scale(w)
    if s is None:
        return matmul(eqn, x, w), None
    xq = x if x.dtype == formats.E4M3 else formats.quantise(x, s)
    return formats.fp8_product(eqn, xq, w, dtype), formats.output_scale(eqn, w)


def _dense(module, x):
    """Flax Dense / DenseGeneral (last-axes contraction) with a QArray or Tap kernel, as Flax computes it."""
    kernel = module.get_variable("params", "kernel")
    features = module.features if isinstance(module.features, tuple) else (module.features,)
    axis = getattr(module, "axis", -1)
    n_in = len(axis) if isinstance(axis, tuple) else 1
    letters = string.ascii_letters[: n_in + len(features)]
    ins, outs = letters[:n_in], letters[n_in:]
    dtype = module.dtype or x.dtype
    y = matmul(f"...{ins},{ins}{outs}->...{outs}", x.astype(dtype), kernel)
    if module.use_bias:
        y = y + module.get_variable("params", "bias").astype(dtype)
    return y


def dense_interceptor(next_fun, args, kwargs, context):
    """`nn.intercept_methods` hook: Dense / DenseGeneral calls whose kernel is quantised (or tapped) go through
    `matmul`; everything else runs unchanged."""
    module = context.module
    if context.method_name == "__call__" and isinstance(module, (nn.Dense, nn.DenseGeneral)):
        if module.has_variable("params", "kernel") and is_quant(module.get_variable("params", "kernel")):
            return _dense(module, args[0])
    return next_fun(*args, **kwargs)


def summarize(rec: dict, method: str) -> dict[str, float]:
    """Per tap key: the calibrated magnitude over every recorded call (calibration batch), by `amax` (max |x|) or
    `percentile` (the largest per-call percentile of |x|: one outlier token cannot stretch the scale)."""
    if method not in ("amax", "percentile"):
        raise ValueError(f"calibration method must be 'amax' or 'percentile', got {method!r}")
    if method == "percentile" and rec["percentile"] is None:
        raise ValueError("percentile calibration needs recording(percentile=...)")
    out: dict[str, float] = {}
    for key, amax, pct in rec["rows"]:
        out[key] = max(out.get(key, 0.0), amax if method == "amax" else pct)
    return out
