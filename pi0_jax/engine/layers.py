"""The engine's transformer passes: plain jnp over `weights.prepare` output, the same function as `pi0_jax.gemma`.

Numerics follow the reference exactly where it matters (fp32 islands: RMSNorm statistics, RoPE angles and rotation,
attention logits and softmax, the time embedding; the big negative fill for masked logits); what differs is the
grouping of matmuls (fused q/k/v and gate/up) and the schedule (layers unrolled or scanned, attention over the cached
prefix and the suffix as one softmax over two logit blocks, so the cache is never concatenated or copied).

Axis legend: B batch, T query tokens, P cached prefix tokens, S suffix tokens, K kv heads, G query heads per kv
head, H head dim, D width.
"""

from __future__ import annotations

import einops
import jax
import jax.numpy as jnp

from pi0_jax.config import GemmaConfig
from pi0_jax.gemma import _BIG_NEG, rotate
from pi0_jax.ops import attention, expert_attention, expert_kernels, formats, fp8_geglu, layout, mosaic_gemm
from pi0_jax.ops.formats import QArray
from pi0_jax.ops.matmul import input_scale, matmul, raw_matmul


def rms_norm(x, scale=None, mod=None):
    """Plain RMSNorm (scale) or adaRMS (mod = concat[scale, shift, gate]: (B or 1, 3D), or per token (B or 1, S or 1,
    3D)); returns (y, gate)."""
    dtype = x.dtype
    var = jnp.mean(jnp.square(x.astype(jnp.float32)), axis=-1, keepdims=True)
    normed = x * jax.lax.rsqrt(var + 1e-6)
    if mod is None:
        return (normed * (1 + scale)).astype(dtype), None
    s, shift, gate = jnp.split(mod if mod.ndim == 3 else mod[:, None, :], 3, axis=-1)
    return (normed * (1 + s) + shift).astype(dtype), gate


def _eqn(w) -> str:
    """The einsum of x @ w: plain weights are (in, out); FP8 ones (out, in), contracted on their last axis
    (`weights._rearrange`)."""
    return "...D,FD->...F" if isinstance(w, QArray) and w.contract == (-1,) else "...D,DF->...F"


def _mm(x, w):
    """x @ w through the one matmul entry point (a quantised weight takes its own op: FP8 GEMM on Hopper)."""
    return matmul(_eqn(w), x, w)


def raw_mm(x, w, dtype):
    """x @ w with an FP8 weight's output scale left to the reader (`ops.matmul.raw_matmul`): (y, its f32 scale
    over the output columns, or None)."""
    y, scale = raw_matmul(_eqn(w), x, w, dtype)
    return y, (None if scale is None else jnp.broadcast_to(scale, y.shape[-1:]))


def _scaled_mm(xq, w, dtype):
    """x @ w for an e4m3 x that a kernel quantised with `input_scale(w)`: the FP8 product scaled in f32 and rounded
    to dtype, `formats.qmatmul`'s end."""
    y, scale = raw_mm(xq, w, dtype)
    return (y.astype(jnp.float32) * scale).astype(dtype)


def _qkv(h, w, cfg: GemmaConfig, angles):
    """q (scaled), k, v of the fused q/k/v GEMM, q and k rotated by `gemma.rope_angles`' (sin, cos) `angles`."""
    qkv = _mm(h, w)
    nq = cfg.num_heads * cfg.head_dim
    q = einops.rearrange(qkv[..., :nq], "B T (N H) -> B T N H", H=cfg.head_dim)
    k, v = einops.rearrange(qkv[..., nq:], "B T (two K H) -> two B T K H", two=2, H=cfg.head_dim)
    q = rotate(q, angles)
    q = q * jnp.asarray(cfg.head_dim**-0.5, q.dtype)
    k = rotate(k, angles)
    return einops.rearrange(q, "B T (K G) H -> B T K G H", K=cfg.num_kv_heads), k, v


def gelu_tanh(x):
    """GELU-tanh (`jax.nn.gelu(x, approximate=True)`) written as x sigmoid(2 z), z = sqrt(2 / pi) (x + 0.044715 x^3):
    the same function (1 + tanh z = 2 sigmoid(2 z)), in x's dtype as jax's. XLA's GeGLU pass is bound by GELU's
    arithmetic, and this form is shorter: the pass alone 9-10 % faster at 6,528 rows (π0's prefix at B = 8), the
    prefix's kernels 0.5-2.5 % shorter at B = 1 (H200s, docs/BENCHMARKS.md, session 52)."""
    z = jnp.asarray(2 * 0.7978845608028654, x.dtype) * (x + jnp.asarray(0.044715, x.dtype) * x * x * x)
    return x * jax.nn.sigmoid(z)


# The prefix's FP8 x FP8 MLPs: gate/up GEMM, GeGLU and the down GEMM's e4m3 input as one Mosaic GPU kernel
# (`ops.fp8_geglu`). "auto": on a Hopper GPU, where it ran π0's FP8 prefix 8.6 % faster at B = 8 and 2.1 % at B = 1
# (H200, docs/BENCHMARKS.md, session 56); True: wherever it applies (the CPU tests: Mosaic GPU's interpreter); False:
# XLA's GEMM and pass, here, in the expert and in SigLIP's fc1 (`vision.FP8_GELU_ROWS`). The action expert's FP8 MLPs
# (`every-gemm`) take the kernel too from FP8_GEGLU_EXPERT_ROWS rows a step (B x 50-51): π0's call 0.6 % faster at
# B = 8 and 2.2 % at B = 64 (H200, session 57); fewer rows are untimed (at B = 1, 51 rows cost a pad and a cut).
# None: never.
FP8_GEGLU = "auto"
FP8_GEGLU_EXPERT_ROWS = 256

# The XLA expert's attention kernel with folded query heads (B >= 8) takes its queries and the suffix's keys and values
# in one buffer (`expert_attention.attention`'s packed), which one XLA fusion makes from q/k/v's GEMM output: else two
# (an A/B switch, read when traced).
PACK_ATTENTION_INPUT = True
# The same kernel's split merge writes only each element's real rows and, before an FP8 x FP8 out-projection, its e4m3
# input (`expert_attention.merge`'s kept and scale): else one XLA fusion cuts and quantises after it (A/B, when traced).
ATTENTION_ENDS_IN_MERGE = True


def fp8_mlp_kernel() -> bool:
    """Whether FP8 MLPs run `ops.fp8_geglu`'s kernels on this backend (`FP8_GEGLU`)."""
    if FP8_GEGLU == "auto":
        return mosaic_gemm.hopper()
    return bool(FP8_GEGLU)


def _mlp_on_kernel(w) -> bool:
    """Whether a layer's FP8 x FP8 MLP (w's gate_up and down) runs `ops.fp8_geglu` on this backend, rows allowing."""
    gate_up, down = w["gate_up"], w["down"]
    return (input_scale(gate_up) is not None and input_scale(down) is not None and fp8_mlp_kernel()
            and fp8_geglu.applies(gate_up, down))


def _mlp(h, w, kernel: bool = False, scales=None):
    """Gemma's GeGLU MLP. FP8 x FP8: gate and up leave the GEMM unscaled and go through GeGLU in f32 straight into
    the down GEMM's e4m3 input (the kernel's numerics): in `ops.fp8_geglu` where `kernel` and `fp8_mlp_kernel()`
    allow it, else XLA's GEMM and one pass. Scaled and rounded to h's dtype first (`formats.qmatmul`'s end), gate
    and up cost the H200's compile (jax 0.11.2) no more kernels and the prefix fill 1.6 % more time; jaxlib 0.10.2's
    compile for an H200 wrote the scaled gate half out in a pass of its own (docs/BENCHMARKS.md, session 56).
    scales: the kernel's column scales made before (`expert_mlp_scales`), or None: made here."""
    gate_up, down = w["gate_up"], w["down"]
    if input_scale(gate_up) is None or input_scale(down) is None:
        gate, up = layout.split_gate_up(_mm(h, gate_up))
        # GELU in f32, rounded to the dtype at its end as the reference's is; then the dtype's product, written as the
        # product of the two rounded values in f32 rounded once (exact in f32 for bf16 and fp16 operands, so the same
        # numbers). With GELU in the dtype XLA wrote the gate half out in a pass of its own before the GeGLU pass (17
        # a prefix fill at B = 1, session 79); with the product in the dtype its cost model still did so for an H100's
        # bandwidth, not an H200's (20 us a layer on an H100: docs/BENCHMARKS.md, session 82)
        g = gelu_tanh(gate.astype(jnp.float32)).astype(gate.dtype)
        return _mm((g.astype(jnp.float32) * up.astype(jnp.float32)).astype(gate.dtype), down)
    xq = formats.quantise(h, gate_up.act_scale)
    if kernel and _mlp_on_kernel(w):
        y = fp8_geglu.geglu(xq.reshape(-1, xq.shape[-1]), gate_up, down.act_scale, scales=scales)
        y = y.reshape(*h.shape[:-1], -1)
    else:
        product, scale = raw_mm(xq, gate_up, h.dtype)
        gate, up = layout.split_gate_up(product.astype(jnp.float32) * scale)
        y = formats.quantise(gelu_tanh(gate) * up, down.act_scale)
    return _scaled_mm(y, down, h.dtype)


def _attend(q, ks, vs, masks, dtype):
    """One softmax over several key blocks: q (B,T,K,G,H); ks/vs [(B,S_i,K,H)]; masks [(B,T,S_i) bool]."""
    logits = [jnp.einsum("BTKGH,BSKH->BKGTS", q, k, preferred_element_type=jnp.float32) for k in ks]
    logits = [jnp.where(m[:, None, None], lg, _BIG_NEG) for lg, m in zip(logits, masks)]
    probs = jax.nn.softmax(jnp.concatenate(logits, axis=-1), axis=-1).astype(dtype)
    out, start = 0, 0
    for v in vs:
        out = out + jnp.einsum("BKGTS,BSKH->BTKGH", probs[..., start : start + v.shape[1]], v)
        start += v.shape[1]
    return einops.rearrange(out, "B T K G H -> B T (K G H)")


def _attend_fused(q, keys, values, kv_len):
    """One fused attention (`ops.attention.fused`: cuDNN on a GPU) over keys masked by length: each element attends
    its first kv_len keys. q (B,T,K,G,H), pre-scaled.

    Every query row of an element sees the same keys, so a kv head's G query heads are folded into T·G rows of one
    head (a reshape when K = 1): the kernel then reads each K/V block once for all G heads, and its row tiles cover
    T·G rows rather than G separate runs of T (T = 50 in the denoise step). Same sums per row."""
    g = q.shape[3]
    out = attention.fused(einops.rearrange(q, "B T K G H -> B (T G) K H"), keys, values, scale=1.0, kv_len=kv_len)
    return einops.rearrange(out, "B (T G) K H -> B T (K G H)", G=g)


def prefix_layer(cfg: GemmaConfig, w, x, angles, mask, kv_len=None, keys: int | None = None):
    """One VLM layer over the prefix. x (B,P,D); angles: RoPE's (sin, cos) at the rows' positions
    (`gemma.rope_angles`); mask (B,P,P). Returns (x, k, v) with k, v (B,P,K,H) post-RoPE.
    kv_len: None for XLA attention under `mask`, else (B,) lengths for the fused kernel (the valid tokens are then
    each element's first kv_len, see `programs.fill_prefix_cache`). keys: with kv_len, k and v are zero-padded to
    this many keys first (the Pallas expert's cache length) and returned so; the fused kernel reads them padded,
    cut off by kv_len, so the cache needs no copy of its own."""
    h, _ = rms_norm(x, w["pre_attn"])
    q, k, v = _qkv(h, w["qkv"], cfg, angles)
    if keys is not None and kv_len is not None:
        k, v = (jnp.pad(a, ((0, 0), (0, keys - a.shape[1]), (0, 0), (0, 0))) for a in (k, v))
    y = _attend(q, [k], [v], [mask], x.dtype) if kv_len is None else _attend_fused(q, k, v, kv_len)
    x = x + _mm(y, w["attn_out"])
    h, _ = rms_norm(x, w["pre_ffw"])
    return x + _mlp(h, w, kernel=True), k, v


def _attend_suffix_fused(q, k, v, buf_k, buf_v, kv_len, slot: int = 0):
    """Fused attention over keys [suffix | prefix]: putting the suffix first makes every element's invalid prefix
    tokens a tail, cut off by `kv_len` = S + valid prefix tokens (the valid prefix must be a run from the front).
    buf_k / buf_v (B, S + P, K, H): the prefix cache behind S slots (`programs.suffix_kv`); this step's k / v are
    written into the slots from `slot` on (in place when the buffers are a loop carry: a concatenation would copy the
    cache; slot 1 where π0's state keys, made once a call, hold slot 0). Every query row sees every key up to
    kv_len: no suffix mask (π0's state row, which sees no action, is not a row of the step here). Returns the output
    and the filled buffers."""
    keys = jax.lax.dynamic_update_slice_in_dim(buf_k, k.astype(buf_k.dtype), slot, axis=1)
    values = jax.lax.dynamic_update_slice_in_dim(buf_v, v.astype(buf_v.dtype), slot, axis=1)
    return _attend_fused(q, keys, values, kv_len), keys, values


def query_rows(cfg: GemmaConfig, s: int, blocks: expert_kernels.Blocks) -> int:
    """An element's query rows in the attention kernel's call from the XLA expert: its S suffix rows padded to Sp,
    or with blocks.fold its S G rows (a kv head's G query heads folded in) padded to whole query blocks."""
    if not blocks.fold:
        return layout.suffix_rows(s)
    rows = s * (cfg.num_heads // cfg.num_kv_heads)
    return -(-rows // blocks.q) * blocks.q


def _attend_kernel(cfg: GemmaConfig, q, k, v, cache_k, cache_v, prefix_mask, suffix_mask, out_scale=None):
    """The Pallas expert's split-key attention (`ops.expert_attention.attention`) for the XLA expert's q (B,T,K,G,H)
    (post-RoPE, scaled), k, v (B,T,K,H), over the cache in the kernels' layout (B,Pp,K,2hp); masks as
    `pallas_tables` makes them at `expert_kernels.blocks_at`'s launch. Unfolded, one row block of [q | k | v] per
    element, suffix rows padded to Sp. Folded (MQA), the G query heads of a kv head are rows (T G) of one head, as
    in `_attend_fused`: an element's cache is then read by its blocks of T G rows (7 of 64 for 51 x 8) rather than
    by its G heads' blocks of Sp rows (8 of 64), with less padding. Same sums per row. Returns (B, T, N H), in e4m3
    quantised with out_scale where given and `ATTENTION_ENDS_IN_MERGE` (else out_scale is ignored)."""
    b, t = q.shape[:2]
    hd, kv_heads, blocks = cfg.head_dim, cfg.num_kv_heads, expert_kernels.blocks_at(b)
    g = cfg.num_heads // kv_heads
    ends = dict(out_rows=t * (g if blocks.fold else 1), out_scale=out_scale) if ATTENTION_ENDS_IN_MERGE else {}
    cache = (c.reshape(b * c.shape[1], -1) for c in (cache_k, cache_v))
    sp = layout.suffix_rows(t)
    if not blocks.fold:
        qkv = jnp.concatenate([q.reshape(b, t, -1, hd), k, v], axis=2).reshape(b, t, -1)
        qkv = layout.rows(layout.heads(qkv, -1, hd), sp)
        y = expert_attention.attention(qkv, *cache, prefix_mask, suffix_mask, batch=b, num_heads=cfg.num_heads,
                                     num_kv_heads=kv_heads, blocks=blocks, **ends)
        return layout.unheads(y.reshape(b, -1, y.shape[-1])[:, :t], hd)
    rows = query_rows(cfg, t, blocks)
    kv = layout.rows(layout.heads(jnp.concatenate([k, v], axis=2).reshape(b, t, -1), -1, hd), sp)
    qf = layout.rows(layout.heads(einops.rearrange(q, "B T K G H -> B (T G) (K H)"), -1, hd), rows)
    heads = dict(batch=b, num_heads=kv_heads, num_kv_heads=kv_heads, blocks=blocks, **ends)
    if PACK_ATTENTION_INPUT and not blocks.mosaic_attention and rows % 2 == 0:
        packed = jnp.concatenate([qf.reshape(b, rows, -1), kv.reshape(b, 2 * sp, -1)], axis=1)
        y = expert_attention.attention(packed.reshape(-1, qf.shape[1]), *cache, prefix_mask, suffix_mask, packed=True,
                                     **heads)
    else:
        y = expert_attention.attention(qf, *cache, prefix_mask, suffix_mask, kv=kv, **heads)
    y = layout.unheads(y.reshape(b, -1, y.shape[-1])[:, : t * g], hd)
    return einops.rearrange(y, "B (T G) (K H) -> B T (K G H)", G=g, H=hd)


def suffix_layer(cfg: GemmaConfig, w, x, angles, cache_k, cache_v, prefix_mask, suffix_mask, mods=None,
                 kv_len=None, kernel: bool = False, slot: int = 0, mlp_scales=None):
    """One action-expert layer over the suffix, attending to [cached prefix | suffix]. Returns (x, k, v).

    angles: RoPE's (sin, cos) at the rows' positions (`gemma.rope_angles`); cache_k/v (B,P,K,H); prefix_mask
    (B,S,P); suffix_mask (B,S,S); mods: None (π0) or (attn, ffw) adaRMS outputs.
    With XLA's attention k, v are the suffix's own keys and values (B,S,K,H). kv_len: None for XLA attention, else
    (B,) key lengths for the fused kernel; cache_k/v are then the suffix-first buffers (B,S'+P,K,H) of
    `_attend_suffix_fused`, k, v come back as those buffers with this step's suffix keys in them from `slot` on, and
    suffix_mask is unused (every row sees every suffix key). kernel: the attention is the Pallas kernel's
    (`_attend_kernel`; cache_k/v and the masks in its layout, returned as given). mlp_scales: this layer's
    `expert_mlp_scales`, or None.
    """
    mod_attn, mod_ffw = mods if mods is not None else (None, None)
    h, gate = rms_norm(x, w.get("pre_attn"), mod_attn)
    q, k, v = _qkv(h, w["qkv"], cfg, angles)
    if kernel:
        y = _attend_kernel(cfg, q, k, v, cache_k, cache_v, prefix_mask, suffix_mask, input_scale(w["attn_out"]))
        k, v = cache_k, cache_v
    elif kv_len is None:
        y = _attend(q, [cache_k, k], [cache_v, v], [prefix_mask, suffix_mask], x.dtype)
    else:
        y, k, v = _attend_suffix_fused(q, k, v, cache_k, cache_v, kv_len, slot)
    # the attention kernel quantised y for an FP8 out-projection
    y = _scaled_mm(y, w["attn_out"], x.dtype) if y.dtype == formats.E4M3 else _mm(y, w["attn_out"])
    x = x + (y if gate is None else y * gate)
    h, gate = rms_norm(x, w.get("pre_ffw"), mod_ffw)
    y = _mlp(h, w, kernel=_expert_mlp_kernel(h.size // h.shape[-1]), scales=mlp_scales)
    return x + (y if gate is None else y * gate), k, v


def _expert_mlp_kernel(rows: int) -> bool:
    """Whether an expert layer of `rows` rows a step may run its FP8 MLP on the kernel (`FP8_GEGLU_EXPERT_ROWS`)."""
    return FP8_GEGLU_EXPERT_ROWS is not None and rows >= FP8_GEGLU_EXPERT_ROWS


def expert_mlp_scales(weights, rows: int) -> tuple | None:
    """The FP8 MLP kernel's column scales (`fp8_geglu.column_scales`) of each unrolled expert layer whose MLP at
    `rows` rows runs on it (else None for that layer), for `suffix_layer`'s mlp_scales: they depend on the weights
    alone, so a denoise loop makes them before its first step. None for stacked (scanned) layers, which the kernel
    does not take."""
    if not isinstance(weights, (list, tuple)):
        return None
    return tuple(fp8_geglu.column_scales(w["gate_up"], w["down"].act_scale)
                 if _expert_mlp_kernel(rows) and _mlp_on_kernel(w) else None for w in weights)


def run_layers(layer_fn, weights, x, per_layer=(), *, unroll: bool):
    """Apply layer_fn(w_i, x, *per_layer_i) -> (x, *outs) over layers; returns (x, outs).

    weights: a list of per-layer dicts (unroll=True) or one stacked dict (unroll=False, lax.scan). Each per_layer
    input and each returned output is indexed by layer: a tuple of per-layer arrays when unrolled (separate buffers,
    no slicing), an array stacked on axis 0 when scanned."""
    if unroll:
        outs = []
        for i, w in enumerate(weights):
            x, *o = layer_fn(w, x, *(a[i] for a in per_layer))
            outs.append(o)
        return x, [tuple(o) for o in zip(*outs)]

    def body(x, xs):
        w, extra = xs
        x, *o = layer_fn(w, x, *extra)
        return x, tuple(o)

    x, outs = jax.lax.scan(body, x, (weights, tuple(per_layer)))
    return x, list(outs)


def pallas_tables(cfg: GemmaConfig, positions, prefix_mask, suffix_mask, blocks=None) -> tuple:
    """`suffix_layers_pallas`' per-call tables, alike for every denoise step: RoPE's cos and sin for the suffix rows
    (B Sp, hp) and the prefix and suffix masks as int32, the suffix's padded to (B Sp, Sp). blocks: the XLA expert's
    launch (`_attend_kernel`); with blocks.fold the suffix mask's rows are the folded query rows (B R, Sp), row
    t G + g of an element being its token t's (`query_rows`)."""
    b, s = positions.shape
    sp = layout.suffix_rows(s)
    cos, sin = layout.rope_tables(jnp.pad(positions, ((0, 0), (0, sp - s))), cfg.head_dim)
    smask = jnp.pad(suffix_mask, ((0, 0), (0, 0), (0, sp - s)))
    rows = sp
    if blocks is not None and blocks.fold:
        smask, rows = jnp.repeat(smask, cfg.num_heads // cfg.num_kv_heads, axis=1), query_rows(cfg, s, blocks)
    smask = jnp.pad(smask, ((0, 0), (0, rows - smask.shape[1]), (0, 0))).reshape(b * rows, sp).astype(jnp.int32)
    return cos, sin, prefix_mask.astype(jnp.int32), smask


def suffix_layers_pallas(cfg: GemmaConfig, weights, x, positions, cache_k, cache_v, prefix_mask, suffix_mask,
                         mods=None, blocks: expert_kernels.Blocks | None = None, tables=None, step=None):
    """All action-expert layers as Pallas kernels (`pi0_jax.ops`): per layer four split-K GEMMs and the attention,
    each followed by one XLA fusion (norm, RoPE, GeGLU, residuals, the split merges); the same function as
    `suffix_layer` applied layer by layer.

    weights: the engine's per-layer dicts, laid out for the kernels here (`ops.layout.expert_weights`: reshapes that
    XLA makes free at full size, where nothing is padded); cache_k/v: per layer (B, Pp, K, 2hp)
    and prefix_mask (B, Pp) in kernel layout (`ops.layout.cache_kv`); x (B, S, D); positions (B, S); suffix_mask
    (B, S, S); mods: None (π0) or a step's π0.5 adaRMS outputs (attn, ffw), (L, 3D) each, or with step (an int32
    scalar) every step's, (T, L, 3D) each, which the kernels read at the step's rows in place; tables: `pallas_tables`
    of these, made once per call by the caller (None: made here); blocks: the kernels' launch (None: this jax's,
    `expert_kernels.default_blocks`). Returns x (B, S, D).
    """
    blocks = expert_kernels.default_blocks() if blocks is None else blocks
    b, s, d = x.shape
    sp = layout.suffix_rows(s)
    # The residual after each GEMM fuses into the next norm's XLA (Triton) fusion only where its inputs are buffers of
    # their own: the first layer's rows not a pad XLA could fuse into it, and π0.5's gates not slices of its tables.
    # Else the residual is a kernel of its own: 18 a step more for π0.5 (docs/BENCHMARKS.md, session 79). q/k/v with
    # RoPE on Mosaic GPU takes no norm fusion: the pad then fuses with its scaled input (session 84). π0.5's takes its
    # adaRMS shift in the last row of each of the kernel's row blocks, where that row is padding
    pad_row = all(r % sp >= s for r in range(mosaic_gemm.ROWS - 1, b * sp, mosaic_gemm.ROWS))
    rows = layout.rows(x, sp)
    if expert_kernels.rope_launch(blocks, mods is not None, pad_row) is None:
        rows = jax.lax.optimization_barrier(rows)
    cos, sin, pmask, smask = pallas_tables(cfg, positions, prefix_mask, suffix_mask) if tables is None else tables
    heads = {"num_heads": cfg.num_heads, "num_kv_heads": cfg.num_kv_heads}
    adaptive = mods is not None
    at = None if step is None or not adaptive else expert_kernels.Step(jnp.asarray(step, jnp.int32), 3 * len(weights))
    if adaptive:
        mods_attn, mods_ffw = (layout.mods(m.reshape(-1, m.shape[-1]), d) for m in mods)
        gates = jax.lax.optimization_barrier([tuple(expert_kernels.table_row(m, 3 * i + 2, at)
                                                    for m in (mods_attn, mods_ffw)) for i in range(len(weights))])
    for i, w in enumerate(weights):
        w = layout.expert_weights(w, cfg)
        if adaptive:  # layer i's rows of the step's table: scale 3i, shift 3i + 1, gate 3i + 2
            (ma, ra, ga), (mf, rf, gf) = (mods_attn, 3 * i, gates[i][0]), (mods_ffw, 3 * i, gates[i][1])
        else:
            (ma, ra, ga), (mf, rf, gf) = (w["pre_attn"], 0, None), (w["pre_ffw"], 0, None)
        qkv = expert_kernels.norm_qkv_rope(rows, ma, ra, adaptive, w["qkv"], cos, sin, width=d,
                                           head_dim=cfg.head_dim, blocks=blocks, step=at, pad_row=pad_row, **heads)
        k, v = (c[i].reshape(b * c[i].shape[1], -1) for c in (cache_k, cache_v))
        y = expert_attention.attention(qkv, k, v, pmask, smask, batch=b, blocks=blocks, **heads)
        rows = expert_kernels.matmul_residual(y, w["attn_out"], rows, ga, gemm=blocks.out, blocks=blocks,
                                              name="expert_attn_out", mosaic=blocks.mosaic_out)
        h = expert_kernels.norm_geglu(rows, mf, rf, adaptive, w["gate_up"], width=d, blocks=blocks, step=at)
        rows = expert_kernels.matmul_residual(h, w["down"], rows, gf, gemm=blocks.down, blocks=blocks,
                                              name="expert_down", mosaic=blocks.mosaic_down)
    return rows.reshape(b, sp, -1)[:, :s, :d]
