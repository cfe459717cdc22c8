"""Low-precision number formats: FP8 (e4m3) weights and activations, FP4 (e2m1) weights with block scales.

Conventions:
- A quantised weight is a `QArray` pytree node that sits in the param tree in place of the array. `q` has the
  weight's shape (so Flax's param shape check and `nn.scan` slicing see the original shape); `scale` has the same
  rank with size 1 on the contracting axes (per output channel) or on every axis but a leading layer axis (per
  tensor); `act_scale` is the static per-tensor scale of the GEMM's input (None: weight-only).
- Every stacked leaf carries the layer axis first, act_scale included, so scans and `x[i]` slice all fields alike.
- real value = q * scale. Scales are amax / format max, so the largest magnitude maps to the format's largest
  finite value (e4m3fn: 448, e2m1: 6); values are clipped first (e4m3fn has no inf: overflow would be NaN).
- `qmatmul` hands XLA the two e4m3 operands themselves, contracted with the activation dtype as the result type:
  on Hopper that is one cuBLASLt FP8 GEMM writing bf16 (`__cublas$lt$matmul$f8`). The scales (activation x
  per-channel weight) multiply its output in f32, an elementwise op that XLA fuses into the GEMM's consumer. The
  older form (operands dequantised to f32, an f32 dot) is rewritten too, but its f32 output and separate scaling
  pass cost more than FP8 saves (docs/BENCHMARKS.md, "FP8 that pays").
- XLA's GPU autotuner also tries Triton for FP8 GEMMs: ~150 s of compiling per GEMM shape, for cuBLASLt in the end.
  `pi0_jax.ops.matmul.compiler_options` turns Triton GEMMs off for programs that hold FP8 weights.
- A `folded` QArray (the engine's, `fold_scales`) holds act_scale x the weight's scale in `scale`: the FP8 x FP8
  product's output scale, made once with the weights. Computed in the program, each such product was a kernel of
  its own per weight (17 of the 423 in π0's FP8 prefix at B = 1).
"""

from __future__ import annotations

import flax.struct
from flax import traverse_util
import jax
import jax.numpy as jnp
import numpy as np

E4M3 = jnp.float8_e4m3fn
E2M1 = jnp.float4_e2m1fn
E8M0 = jnp.float8_e8m0fnu
E4M3_MAX = 448.0
E2M1_MAX = 6.0
FP4_BLOCK = {"nvfp4": 16, "mxfp4": 32}


@flax.struct.dataclass
class QArray:
    """An FP8 weight. q: e4m3 (weight shape); scale: f32 (see module doc); act_scale: f32 () or (L,) or None.

    contract: the contracting axes of the weight (negative, static), used for per-channel scales and re-layouts.
    folded: `scale` is act_scale x the weight's scale (`fold_scales`).
    """

    q: jax.Array
    scale: jax.Array
    act_scale: jax.Array | None = None
    contract: tuple[int, ...] = flax.struct.field(pytree_node=False, default=(-2,))
    folded: bool = flax.struct.field(pytree_node=False, default=False)

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(self.q.shape)

    @property
    def dtype(self):
        return self.q.dtype

    @property
    def ndim(self) -> int:
        return self.q.ndim

    def __getitem__(self, i):
        """Index the leading axis (FeedForward's gate/up split of one layer's `gating_einsum`)."""
        scale = self.scale[i] if self.scale.shape[0] == self.q.shape[0] else self.scale[0]
        contract = tuple(c for c in self.contract if c != -self.q.ndim)
        return QArray(self.q[i], scale, self.act_scale, contract, self.folded)

    def weight_scale(self) -> jax.Array:
        """The weight's own scale (real value = q x it), folded or not."""
        return self.scale / _act_against(self.act_scale, self.scale) if self.folded else self.scale

    def dequantize(self, dtype=jnp.float32) -> jax.Array:
        return (self.q.astype(jnp.float32) * self.weight_scale()).astype(dtype)


def _act_against(act: jax.Array, scale: jax.Array) -> jax.Array:
    """act_scale (() or (L,): per layer) shaped to broadcast against a scale of the same leading axes."""
    act = jnp.asarray(act, jnp.float32)
    return act.reshape(act.shape + (1,) * (scale.ndim - act.ndim))


def fold_scales(tree):
    """Every FP8 x FP8 QArray of a pytree with its output scale folded in (`folded`): for a program's weights,
    whose products then read their scale as it is. Weight-only and folded QArrays stay as they are."""
    def fold(w):
        if not isinstance(w, QArray) or w.act_scale is None or w.folded:
            return w
        return QArray(w.q, w.scale * _act_against(w.act_scale, w.scale), w.act_scale, w.contract, True)

    return jax.tree.map(fold, tree, is_leaf=lambda v: isinstance(v, QArray))


def _safe_scale(amax, fmt_max):
    return jnp.where(amax > 0, amax / fmt_max, 1.0).astype(jnp.float32)


def quantize_fp8(w: jax.Array, *, contract=(-2,), per_channel: bool = True, stacked: bool = False,
                 act_scale=None) -> QArray:
    """Weight -> e4m3 with amax scales: per output channel (reduce over `contract`) or per tensor (per layer when
    `stacked`, i.e. the leading axis is layers)."""
    w = jnp.asarray(w, jnp.float32)
    contract = tuple(a if a < 0 else a - w.ndim for a in contract)
    if per_channel:
        axes = tuple(a % w.ndim for a in contract)
    else:
        axes = tuple(range(1 if stacked else 0, w.ndim))
    scale = _safe_scale(jnp.max(jnp.abs(w), axis=axes, keepdims=True), E4M3_MAX)
    q = jnp.clip(w / scale, -E4M3_MAX, E4M3_MAX).astype(E4M3)
    act = None if act_scale is None else jnp.asarray(act_scale, jnp.float32)
    return QArray(q, scale, act, contract)


def act_scale_from_amax(amax) -> np.ndarray:
    """Static activation scale for e4m3 from a calibrated magnitude (amax or a percentile)."""
    amax = np.asarray(amax, np.float32)
    return np.where(amax > 0, amax / E4M3_MAX, 1.0).astype(np.float32)


def quantise(x: jax.Array, act_scale: jax.Array) -> jax.Array:
    """x -> e4m3 with a static activation scale (f32, any shape that broadcasts): x / scale in f32, clipped to ±448
    (saturating), rounded to nearest even."""
    return jnp.clip(x.astype(jnp.float32) / act_scale.astype(jnp.float32), -E4M3_MAX, E4M3_MAX).astype(E4M3)


def qdq_fp8(x: jax.Array, scale: jax.Array) -> jax.Array:
    """Quantise x to e4m3 with a static scalar scale and dequantise back to x.dtype (saturating)."""
    return quantise(x, scale).astype(x.dtype) * scale.astype(x.dtype)


def _labels(eqn: str):
    lhs, out = eqn.replace(" ", "").split("->")
    _, rhs = lhs.split(",")
    return rhs, out


def _output_scale(eqn: str, w: QArray, dtype) -> jax.Array:
    """The per-channel weight scale laid out to broadcast against the einsum output."""
    rhs, out = _labels(eqn)
    out_labels = out.replace("...", "")
    keep = [i for i, c in enumerate(rhs) if c in out_labels]
    s = w.scale.reshape([w.scale.shape[i] for i in keep])
    kept = [rhs[i] for i in keep]
    order = sorted(range(len(kept)), key=lambda i: out_labels.index(kept[i]))
    s = jnp.transpose(s, order)
    shape = [s.shape[order.index(kept.index(c))] if c in kept else 1 for c in out_labels]
    return s.reshape(shape).astype(dtype)


def qmatmul(eqn: str, x: jax.Array, w: QArray) -> jax.Array:
    """einsum(eqn, x, w) with an FP8 weight; output in x.dtype.

    With an act_scale: x quantised to e4m3 with it, e4m3 x e4m3 contracted straight into x.dtype (accumulation in
    f32 inside the GEMM), then (act_scale x weight scale) applied in f32. Weight-only: the weight dequantised to
    x.dtype (no FP8 tensor cores: bf16 x FP8 is not an FP8 GEMM)."""
    dtype = x.dtype
    if w.act_scale is None:
        wq = w.q.astype(dtype)
        if w.scale.size == 1:
            return jnp.einsum(eqn, x, wq * w.scale.reshape(()).astype(dtype))
        return jnp.einsum(eqn, x, wq) * _output_scale(eqn, w, dtype)
    y = fp8_product(eqn, quantise(x, w.act_scale), w, dtype)
    return (y.astype(jnp.float32) * output_scale(eqn, w)).astype(dtype)


def fp8_product(eqn: str, xq: jax.Array, w: QArray, dtype) -> jax.Array:
    """einsum(eqn, xq, w.q) of an e4m3 input, contracted straight into dtype and not yet scaled: `qmatmul` without
    its two ends, for a kernel that quantises the input before it or scales the output after it."""
    return jnp.einsum(eqn, xq, w.q, preferred_element_type=dtype)


def output_scale(eqn: str, w: QArray) -> jax.Array:
    """The f32 factor of an FP8 x FP8 product (`fp8_product`): act_scale x the weight's scale, laid out to broadcast
    against the einsum output."""
    scale = w.scale.reshape(()) if w.scale.size == 1 else _output_scale(eqn, w, jnp.float32)
    return scale if w.folded else w.act_scale.astype(jnp.float32) * scale


def _unfolded(w: QArray) -> None:
    if w.folded:   # the re-layouts come first (`engine.weights.prepare`); a folded scale holds its act_scale
        raise ValueError(f"QArray {w.q.shape}: its scale has its act_scale folded in; re-lay it out before folding")


def has_fp8(tree) -> bool:
    """Whether the pytree holds an FP8 weight (`QArray`)."""
    return any(isinstance(x, QArray) for x in jax.tree.leaves(tree, is_leaf=lambda v: isinstance(v, QArray)))


def rearrange(w: QArray, pattern: str, contract=(-2,), **sizes) -> QArray:
    """einops.rearrange of a QArray (q and scale alike); per-tensor scales are broadcast to per-channel first so
    that re-laid-out weights can be concatenated."""
    import einops

    _unfolded(w)
    shape = [1 if (i - w.q.ndim) in w.contract else n for i, n in enumerate(w.q.shape)]
    scale = jnp.broadcast_to(w.scale, shape)
    return QArray(einops.rearrange(w.q, pattern, **sizes), einops.rearrange(scale, pattern, **sizes), w.act_scale,
                  tuple(contract))


def concat(ws, axis: int = -1) -> QArray:
    """Concatenate QArrays along an output axis (fused q/k/v): the inputs share the GEMM input, so one act_scale."""
    for w in ws:
        _unfolded(w)
    acts = [w.act_scale for w in ws]
    act = None if acts[0] is None else jnp.max(jnp.stack(acts), axis=0)
    return QArray(jnp.concatenate([w.q for w in ws], axis), jnp.concatenate([w.scale for w in ws], axis), act,
                  ws[0].contract)


# -- FP4 (emulation only: dequantise, then matmul) -------------------------------------------------------------------
def quantize_fp4(w: jax.Array, fmt: str, axis: int = -2):
    """Weight -> (q e2m1, block scales, tensor scale) with blocks of FP4_BLOCK[fmt] along the contracting `axis`.

    nvfp4: block scales e4m3 of (block amax / 6) / tensor_scale, tensor_scale f32 = amax / (6 * 448).
    mxfp4: block scales e8m0 (powers of two), the OCP MX rule 2^(floor(log2(block amax)) - 2) (2 = e2m1's emax),
    so values up to 8x the scale can clip to 6: MX trades that saturation for a free (shift-only) scale.
    Block scales have `axis` of size ceil(n / block); a partial last block is zero-padded (zeros leave amax as is).
    """
    if fmt not in FP4_BLOCK:
        raise ValueError(f"unknown FP4 format {fmt!r}; formats: {sorted(FP4_BLOCK)}")
    bs = FP4_BLOCK[fmt]
    w = jnp.moveaxis(jnp.asarray(w, jnp.float32), axis, -1)
    n = w.shape[-1]
    w = jnp.pad(w, [(0, 0)] * (w.ndim - 1) + [(0, -n % bs)])
    blocks = w.reshape(*w.shape[:-1], -1, bs)
    bmax = jnp.max(jnp.abs(blocks), axis=-1, keepdims=True)
    if fmt == "nvfp4":
        tensor_scale = _safe_scale(jnp.max(bmax), E2M1_MAX * E4M3_MAX)
        bscale = jnp.clip(bmax / E2M1_MAX / tensor_scale, 0, E4M3_MAX).astype(E4M3)
        eff = bscale.astype(jnp.float32) * tensor_scale
    else:  # mxfp4
        tensor_scale = jnp.float32(1.0)
        exp = jnp.floor(jnp.log2(jnp.where(bmax > 0, bmax, 1.0))) - 2
        bscale = jnp.exp2(jnp.clip(exp, -127, 127)).astype(E8M0)
        eff = bscale.astype(jnp.float32)
    eff = jnp.where(eff > 0, eff, 1.0)
    q = jnp.clip(blocks / eff, -E2M1_MAX, E2M1_MAX).astype(E2M1)
    q = jnp.moveaxis(q.reshape(w.shape)[..., :n], -1, axis)
    return q, jnp.moveaxis(bscale[..., 0], -1, axis), tensor_scale


def dequantize_fp4(q, block_scale, tensor_scale, fmt: str, axis: int = -2, dtype=jnp.float32) -> jax.Array:
    bs = FP4_BLOCK[fmt]
    qm = jnp.moveaxis(q.astype(jnp.float32), axis, -1)
    n = qm.shape[-1]
    qm = jnp.pad(qm, [(0, 0)] * (qm.ndim - 1) + [(0, -n % bs)])
    sm = jnp.moveaxis(block_scale.astype(jnp.float32), axis, -1) * tensor_scale
    out = (qm.reshape(*qm.shape[:-1], -1, bs) * sm[..., None]).reshape(qm.shape)[..., :n]
    return jnp.moveaxis(out, -1, axis).astype(dtype)


def fake_quant_fp4(w: jax.Array, fmt: str, axis: int = -2) -> jax.Array:
    """Quantise-dequantise (the emulated FP4 weight), in w's dtype."""
    return dequantize_fp4(*quantize_fp4(w, fmt, axis), fmt, axis, dtype=w.dtype)


# -- checkpoint storage: QArray leaves as plain arrays (pi0_jax.checkpoint) ------------------------------------
def get_leaf(tree, path):
    for p in path:
        tree = tree[p]
    return tree


def set_leaf(tree, path, value):
    """Copy-on-write set of a nested-dict leaf (the input tree is not modified)."""
    if not path:
        return value
    out = dict(tree)
    out[path[0]] = set_leaf(tree[path[0]], path[1:], value)
    return out


# -- calibration ----------------------------------------------------------------------------------------------------
def quantized_paths(params: dict) -> list[str]:
    flat = traverse_util.flatten_dict(params, sep="/", is_leaf=lambda _, v: not isinstance(v, dict))
    return sorted(k for k, v in flat.items() if isinstance(v, QArray))


def to_storage(params: dict) -> tuple[dict, dict]:
    """QArray leaves -> plain dicts {q (uint8 bits), scale, act_scale?}; returns (tree, per-leaf metadata)."""
    meta = {}
    for path in quantized_paths(params):
        keys = tuple(path.split("/"))
        qa = get_leaf(params, keys)
        _unfolded(qa)
        leaf = {"q": np.asarray(qa.q).view(np.uint8), "scale": np.asarray(qa.scale, np.float32)}
        if qa.act_scale is not None:
            leaf["act_scale"] = np.asarray(qa.act_scale, np.float32)
        meta[path] = {"dtype": str(np.asarray(qa.q).dtype), "contract": list(qa.contract)}
        params = set_leaf(params, keys, leaf)
    return params, meta


def from_storage(tree: dict, meta: dict) -> dict:
    import ml_dtypes

    for path, m in meta.items():
        keys = tuple(path.split("/"))
        leaf = get_leaf(tree, keys)
        q = np.asarray(leaf["q"]).view(getattr(ml_dtypes, m["dtype"]))
        act = leaf.get("act_scale")
        tree = set_leaf(tree, keys, QArray(q, np.asarray(leaf["scale"], np.float32),
                                       None if act is None else np.asarray(act, np.float32), tuple(m["contract"])))
    return tree
