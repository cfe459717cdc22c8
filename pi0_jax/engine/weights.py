"""Engine weights: the openpi param tree rearranged for inference, computing the same function.

- q/k/v of each expert fused into one (D, (N + 2K) H) GEMM, gate/up into one (D, 2F) GEMM whose gate and up
  columns alternate in blocks of 32 units (`ops.layout.gate_up_block`), attention out as (N H, D): fewer, larger
  kernels. The same for SigLIP's q/k/v and attention out (`vision_weights`).
- Per-layer weights split into separate buffers (unrolled layers) or kept stacked (scanned layers).
- The prefix pass returns only K/V, so XLA drops the VLM's last MLP and final norm as dead code; the VLM's final
  norm weights are not carried at all.
- An FP8 x FP8 weight carries its product's output scale (act_scale x the weight's scale: `ops.formats.fold_scales`).
- π0's action in-projection is folded into its time MLP's first product (`fold_action_in`): two f32 products in a
  row with nothing between them are one.
- The step schedule of a fixed-step sampler is known: its times, the time embeddings and what depends only on them
  (π0.5's adaRMS scale/shift/gate for every layer and step; π0's time half of `action_time_mlp_in`) are precomputed
  once per (params, num_steps) with exactly the reference's ops, so the denoise loop never reads those weights.

Axis legend: L layers, D width, N query heads, K kv heads, H head dim, F MLP hidden, T steps.
"""

from __future__ import annotations

import re

import einops
import jax
import jax.numpy as jnp
import numpy as np

from pi0_jax import pi0
from pi0_jax.ops import formats as quant
from pi0_jax.ops import layout
from pi0_jax.config import Pi0Config


def step_times(num_steps, length: int | None = None):
    """t_k at which the velocity is evaluated, accumulated in f32 exactly as the reference sampler does.

    num_steps: a Python int (numpy result), or a traced int32 with a static `length` >= it (the first num_steps
    entries are the times; the rest continue the same arithmetic and are never read)."""
    if length is None:
        dt = np.float32(-1.0 / num_steps)
        t, out = np.float32(1.0), []
        for _ in range(num_steps):
            out.append(t)
            t = np.float32(t + dt)
        return np.asarray(out, np.float32)
    dt = (-1.0 / jnp.asarray(num_steps, jnp.float32)).astype(jnp.float32)
    _, times = jax.lax.scan(lambda t, _: (t + dt, t), jnp.float32(1.0), None, length=length)
    return times


def _rearrange(w, pattern: str, dtype, **sizes):
    """A plain weight rearranged to (in, out) and cast; a quantised one (`pi0_jax.ops.formats.QArray`, fused after
    quantising, so its scales are per output channel of the fused matrix) keeps its storage dtype and is laid out
    (out, in): the operand layout cuBLASLt's FP8 GEMM reads as is (an (in, out) FP8 weight is transposed by XLA
    before every GEMM, a full copy of it). `pattern` names the (in, out) target; its output is swapped here."""
    if isinstance(w, quant.QArray):
        src, dst = pattern.split("->")
        *lead, d_in, d_out = _groups(dst)
        return quant.rearrange(w, f"{src}-> {' '.join(lead)} {d_out} {d_in}", contract=(-1,), **sizes)
    return einops.rearrange(w, pattern, **sizes).astype(dtype)


def _groups(spec: str) -> list[str]:
    """einops axis groups of one side: "L D (N H)" -> ["L", "D", "(N H)"]."""
    return re.findall(r"\([^)]*\)|[^\s()]+", spec)


def _fused(parts, dtype):
    """Weights that share their GEMM input, each rearranged to (in, out) by its pattern, as one GEMM: concatenated on
    the output axis (the last of a plain weight; the second to last of an FP8 one, laid out (out, in))."""
    if isinstance(parts[0][0], quant.QArray):
        return quant.concat([_rearrange(w, pattern, dtype) for w, pattern in parts], axis=-2)
    return jnp.concatenate([einops.rearrange(w, pattern) for w, pattern in parts], axis=-1).astype(dtype)


def _expert_weights(attn: dict, mlp: dict, suffix: str, dtype) -> dict:
    qkv = _fused([(attn[f"q_einsum{suffix}"]["w"], "L N D H -> L D (N H)"),
                  (attn[f"kv_einsum{suffix}"]["w"], "L two K D H -> L D (two K H)")], dtype)
    gating = mlp["gating_einsum"]
    return {
        "qkv": qkv,
        "attn_out": _rearrange(attn[f"attn_vec_einsum{suffix}"]["w"], "L N H D -> L (N H) D", dtype),
        "gate_up": _rearrange(gating, "L two D (Fb u) -> L D (Fb two u)", dtype,
                              u=layout.gate_up_block(gating.shape[-1])),
        "down": _rearrange(mlp["linear"], "L F D -> L F D", dtype),
    }


# A SigLIP block's rows in the tower's `vectors` table (`vision_weights`): its LayerNorms' scales and biases, the
# biases of the two Dense outputs that are added to the residual stream (each inside the next LayerNorm), then
# q/k/v's bias (3 D values: SigLIP's heads span its width) over three rows and fc1's (F values) over the rows from
# FC1_BIAS, ceil(F / D) of them, zero-padded (`_vectors`); the encoder's final norm has a table of its own, its first
# two rows.
LN1_SCALE, LN1_BIAS, LN2_SCALE, LN2_BIAS, OUT_BIAS, FC2_BIAS, QKV_BIAS = range(7)
FC1_BIAS = QKV_BIAS + 3


def _vectors(rows) -> jax.Array:
    """(..., n) vectors -> one (..., R, D) f32 table, D the first's length, each vector over ceil(n / D) rows,
    zero-padded: the norms' parameters as they are, the biases after their cast to the activation dtype (exact in
    f32, cast back where they are added)."""
    d = rows[0].shape[-1]

    def cut(r):
        n = -(-r.shape[-1] // d) * d
        r = jnp.pad(r.astype(jnp.float32), [(0, 0)] * (r.ndim - 1) + [(0, n - r.shape[-1])])
        return r.reshape(*r.shape[:-1], n // d, d)

    return jnp.concatenate([cut(r) for r in rows], axis=-2)


def vision_weights(img: dict, dtype) -> dict:
    """openpi's SigLIP tree (blocks stacked) -> `engine.vision`'s: q/k/v fused into one (D, 3 N H) GEMM, the
    attention output as (N H, D); every block's LayerNorm parameters and biases in one table, `vectors` (L, R, D)
    of f32 (rows LN1_SCALE ... FC1_BIAS), outside the blocks: XLA takes the biases out of it in one kernel for all
    blocks, the LayerNorm kernel reads its rows in place, and a call takes it as one buffer where it took 4 L (the
    host pays about 1.2-1.7 us per buffer per call: docs/BENCHMARKS.md, "The host's share of a call" and session
    72); the patch embedding and position table as they are (an f32 island)."""
    blk = img["Transformer"]["encoderblock"]
    mha, mlp = blk["MultiHeadDotProductAttention_0"], blk["MlpBlock_0"]
    ln1, ln2 = blk["LayerNorm_0"], blk["LayerNorm_1"]
    qkv_bias = jnp.concatenate([einops.rearrange(mha[n]["bias"], "L N H -> L (N H)")
                                for n in ("query", "key", "value")], axis=-1)
    if qkv_bias.shape[-1] != 3 * ln1["scale"].shape[-1]:
        raise ValueError(f"SigLIP's q/k/v bias has {qkv_bias.shape[-1]} values a block, not 3 x its width "
                         f"{ln1['scale'].shape[-1]}")
    vectors = _vectors([ln1["scale"], ln1["bias"], ln2["scale"], ln2["bias"]]
                       + [b.astype(dtype) for b in (mha["out"]["bias"], mlp["Dense_1"]["bias"], qkv_bias,
                                                    mlp["Dense_0"]["bias"])])
    blocks = {
        "qkv": _fused([(mha[n]["kernel"], "L D N H -> L D (N H)") for n in ("query", "key", "value")], dtype),
        "out": _rearrange(mha["out"]["kernel"], "L N H D -> L (N H) D", dtype),
        "fc1": _rearrange(mlp["Dense_0"]["kernel"], "L D F -> L D F", dtype),
        "fc2": _rearrange(mlp["Dense_1"]["kernel"], "L F D -> L F D", dtype),
    }
    head = {"kernel": _rearrange(img["head"]["kernel"], "D E -> D E", dtype), "bias": img["head"]["bias"].astype(dtype)}
    norm = img["Transformer"]["encoder_norm"]
    return {"embedding": img["embedding"], "pos": img["pos_embedding"], "blocks": blocks, "vectors": vectors,
            "norm": _vectors([norm["scale"], norm["bias"]]), "head": head}


def prepare(config: Pi0Config, params: dict) -> dict:
    """Engine weights (stacked over layers) from openpi-layout params. Pure; jit it to run on device."""
    dtype = jnp.dtype(config.dtype)
    llm = params["PaliGemma"]["llm"]
    layers = llm["layers"]
    vlm = _expert_weights(layers["attn"], layers["mlp"], "", dtype)
    vlm["pre_attn"] = layers["pre_attention_norm"]["scale"]
    vlm["pre_ffw"] = layers["pre_ffw_norm"]["scale"]
    expert = _expert_weights(layers["attn"], layers["mlp_1"], "_1", dtype)
    if not config.pi05:
        expert["pre_attn"] = layers["pre_attention_norm_1"]["scale"]
        expert["pre_ffw"] = layers["pre_ffw_norm_1"]["scale"]
    top = {k: v for k, v in params.items() if k != "PaliGemma"}
    if not config.pi05:
        top["action_time_in"] = fold_action_in(config, params)
    out = {
        "img": vision_weights(params["PaliGemma"]["img"], dtype),
        "embedding": llm["embedder"]["input_embedding"],
        "vlm": vlm,
        "expert": expert,
        "top": top,
    }
    if not config.pi05:
        out["final_norm_1"] = llm["final_norm_1"]["scale"]
    return quant.fold_scales(out)


def fold_action_in(config: Pi0Config, params: dict) -> dict:
    """π0's action in-projection folded into the time MLP's action half, as one Dense (A -> D) in f32. The reference
    computes (x W_a + b_a) W_1 + (the time half), two f32 products in a row with nothing between them; the fold is
    x (W_a W_1) + b_a W_1 + (the time half), the same function to f32 rounding, W_a W_1 and b_a W_1 made here in full
    f32. The step's first product then has K = A (32) where it had two GEMMs, one over a 1024 x 1024 weight."""
    w_a, w_1 = params["action_in_proj"], params["action_time_mlp_in"]["kernel"][: config.action_expert.width]

    def f32(a, b):
        return jnp.matmul(a.astype(jnp.float32), b.astype(jnp.float32), precision=jax.lax.Precision.HIGHEST)

    return {"kernel": f32(w_a["kernel"], w_1), "bias": f32(w_a["bias"], w_1)}


def precompute_schedule(config: Pi0Config, params: dict, num_steps, length: int | None = None) -> dict:
    """Everything that depends only on the step times. Pure; jit it to run on device. A traced num_steps needs a
    static `length` (the schedule's leading axis; see `step_times`).

    π0.5: `mods_attn`, `mods_ffw` (T, L, 3 D) and `mods_final` (T, 3 D): the adaRMS Dense outputs, computed in the
    activation dtype as the reference does (cond cast to it, then Dense). π0: `time_in` (T, D) = the time half of
    `action_time_mlp_in` plus its bias, in f32 (the projection runs in f32 in the reference too). `committed`: the
    same at t = 0 (leading axis 1), the time of committed actions under training-time action conditioning.
    """
    out = _schedule_at(config, params, jnp.asarray(step_times(num_steps, length)))
    out["committed"] = _schedule_at(config, params, jnp.zeros((1,), jnp.float32))
    return out


def _schedule_at(config: Pi0Config, params: dict, t: jax.Array) -> dict:
    dtype = jnp.dtype(config.dtype)
    width = config.action_expert.width
    emb = pi0.posemb_sincos(t, width)  # (T, D) f32
    if config.pi05:
        def dense(p, x):
            return x @ p["kernel"] + p["bias"]

        cond = jax.nn.swish(dense(params["time_mlp_out"], jax.nn.swish(dense(params["time_mlp_in"], emb))))
        cond = cond.astype(dtype)
        layers = params["PaliGemma"]["llm"]["layers"]

        def mods(norm):  # kernel (L, D, 3D), bias (L, 3D) -> (T, L, 3D)
            k, b = norm["Dense_0"]["kernel"].astype(dtype), norm["Dense_0"]["bias"].astype(dtype)
            return jnp.einsum("TD,LDE->TLE", cond, k) + b

        final = params["PaliGemma"]["llm"]["final_norm_1"]["Dense_0"]
        return {
            "mods_attn": mods(layers["pre_attention_norm_1"]),
            "mods_ffw": mods(layers["pre_ffw_norm_1"]),
            "mods_final": cond @ final["kernel"].astype(dtype) + final["bias"].astype(dtype),
        }
    w = params["action_time_mlp_in"]
    kernel = w["kernel"].astype(jnp.float32)
    return {"time_in": emb @ kernel[width:] + w["bias"].astype(jnp.float32)}


def schedule_params(config: Pi0Config, params: dict) -> dict:
    """The part of the param tree `precompute_schedule` reads (time MLPs, adaRMS Dense layers)."""
    if not config.pi05:
        return {"action_time_mlp_in": params["action_time_mlp_in"]}
    llm = params["PaliGemma"]["llm"]
    layers = {k: llm["layers"][k] for k in ("pre_attention_norm_1", "pre_ffw_norm_1")}
    return {"time_mlp_in": params["time_mlp_in"], "time_mlp_out": params["time_mlp_out"],
            "PaliGemma": {"llm": {"layers": layers, "final_norm_1": llm["final_norm_1"]}}}


def unstack(tree: dict, depth: int) -> list[dict]:
    """Stacked (L, ...) leaves -> one dict per layer with separate buffers (for unrolled layers)."""
    return [jax.tree.map(lambda x, i=i: x[i], tree) for i in range(depth)]
