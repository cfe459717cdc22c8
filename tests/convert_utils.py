"""Test helpers for the converter: build PyTorch-layout (openpi / LeRobot) checkpoints from our own param trees.

`to_torch` is the "From JAX" column of spec §11.2, written with plain transposes and reshapes, independently of
converters/table.py (which goes the other way with einops), so a round trip checks one against the other. It uses
only array methods (transpose/reshape/index), so it also runs under `jax.eval_shape` on full-size presets for free.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping
from pathlib import Path

import jax
import ml_dtypes
import numpy as np
from safetensors.numpy import save_file

from pi0_jax.config import Pi0Config, get_config
from pi0_jax import pi0

V = "paligemma_with_expert.paligemma.model.vision_tower.vision_model"
PROJ = "paligemma_with_expert.paligemma.model.multi_modal_projector"
LM = "paligemma_with_expert.paligemma.model.language_model"
EX = "paligemma_with_expert.gemma_expert.model"
LM_HEAD = "paligemma_with_expert.paligemma.lm_head.weight"
EMBED = f"{LM}.embed_tokens.weight"
EX_HEAD = "paligemma_with_expert.gemma_expert.lm_head.weight"


def random_params(config: Pi0Config, seed: int = 0, bf16_exact: bool = False) -> dict:
    """Random normal values in the shapes of `param_shapes(config)` (f32). Norms are random too (init has zeros).
    bf16_exact: round to bf16-representable values, so a mixed fp32/bf16 source is lossless."""
    rng = np.random.default_rng(seed)

    def leaf(s):
        x = rng.standard_normal(s.shape, dtype=np.float32)
        return x.astype(ml_dtypes.bfloat16).astype(np.float32) if bf16_exact else x

    return jax.tree.map(leaf, pi0.param_shapes(config))


def _linear(sd, name, node):
    sd[f"{name}.weight"] = node["kernel"].T
    sd[f"{name}.bias"] = node["bias"]


def to_torch(params: Mapping, pi05: bool) -> dict:
    """JAX param tree -> openpi PyTorch state dict (bare keys, `lm_head` for the embedding, no expert lm_head)."""
    sd: dict = {}
    img, llm = params["PaliGemma"]["img"], params["PaliGemma"]["llm"]
    sd[f"{V}.embeddings.patch_embedding.weight"] = img["embedding"]["kernel"].transpose(3, 2, 0, 1)
    sd[f"{V}.embeddings.patch_embedding.bias"] = img["embedding"]["bias"]
    pos = img["pos_embedding"]
    sd[f"{V}.embeddings.position_embedding.weight"] = pos.reshape(pos.shape[1], pos.shape[2])
    blk = img["Transformer"]["encoderblock"]
    mha = blk["MultiHeadDotProductAttention_0"]
    for i in range(blk["LayerNorm_0"]["scale"].shape[0]):
        L = f"{V}.encoder.layers.{i}"
        for jax_name, torch_name in (("LayerNorm_0", "layer_norm1"), ("LayerNorm_1", "layer_norm2")):
            sd[f"{L}.{torch_name}.weight"] = blk[jax_name]["scale"][i]
            sd[f"{L}.{torch_name}.bias"] = blk[jax_name]["bias"][i]
        for jax_name, torch_name in (("query", "q_proj"), ("key", "k_proj"), ("value", "v_proj")):
            k = mha[jax_name]["kernel"][i]  # (D, N, H): row of the torch weight = n*H + h
            sd[f"{L}.self_attn.{torch_name}.weight"] = k.reshape(k.shape[0], k.shape[1] * k.shape[2]).T
            sd[f"{L}.self_attn.{torch_name}.bias"] = mha[jax_name]["bias"][i].reshape(-1)
        o = mha["out"]["kernel"][i]  # (N, H, D): column = n*H + h
        sd[f"{L}.self_attn.out_proj.weight"] = o.reshape(o.shape[0] * o.shape[1], o.shape[2]).T
        sd[f"{L}.self_attn.out_proj.bias"] = mha["out"]["bias"][i]
        for jax_name, torch_name in (("Dense_0", "fc1"), ("Dense_1", "fc2")):
            sd[f"{L}.mlp.{torch_name}.weight"] = blk["MlpBlock_0"][jax_name]["kernel"][i].T
            sd[f"{L}.mlp.{torch_name}.bias"] = blk["MlpBlock_0"][jax_name]["bias"][i]
    sd[f"{V}.post_layernorm.weight"] = img["Transformer"]["encoder_norm"]["scale"]
    sd[f"{V}.post_layernorm.bias"] = img["Transformer"]["encoder_norm"]["bias"]
    _linear(sd, f"{PROJ}.linear", img["head"])

    sd[LM_HEAD] = llm["embedder"]["input_embedding"]
    layers, attn = llm["layers"], llm["layers"]["attn"]
    for s, prefix in (("", LM), ("_1", EX)):
        adarms = pi05 and s == "_1"
        for i in range(attn[f"q_einsum{s}"]["w"].shape[0]):
            L = f"{prefix}.layers.{i}"
            q = attn[f"q_einsum{s}"]["w"][i]  # (N, D, H)
            sd[f"{L}.self_attn.q_proj.weight"] = q.transpose(0, 2, 1).reshape(q.shape[0] * q.shape[2], q.shape[1])
            sd[f"{L}.self_attn.k_proj.weight"] = attn[f"kv_einsum{s}"]["w"][i, 0, 0].T
            sd[f"{L}.self_attn.v_proj.weight"] = attn[f"kv_einsum{s}"]["w"][i, 1, 0].T
            o = attn[f"attn_vec_einsum{s}"]["w"][i]  # (N, H, D)
            sd[f"{L}.self_attn.o_proj.weight"] = o.reshape(o.shape[0] * o.shape[1], o.shape[2]).T
            sd[f"{L}.mlp.gate_proj.weight"] = layers[f"mlp{s}"]["gating_einsum"][i, 0].T
            sd[f"{L}.mlp.up_proj.weight"] = layers[f"mlp{s}"]["gating_einsum"][i, 1].T
            sd[f"{L}.mlp.down_proj.weight"] = layers[f"mlp{s}"]["linear"][i].T
            for jax_name, torch_name in (("pre_attention_norm", "input_layernorm"),
                                         ("pre_ffw_norm", "post_attention_layernorm")):
                node = layers[f"{jax_name}{s}"]
                if adarms:
                    sd[f"{L}.{torch_name}.dense.weight"] = node["Dense_0"]["kernel"][i].T
                    sd[f"{L}.{torch_name}.dense.bias"] = node["Dense_0"]["bias"][i]
                else:
                    sd[f"{L}.{torch_name}.weight"] = node["scale"][i]
        final = llm[f"final_norm{s}"]
        if adarms:
            sd[f"{prefix}.norm.dense.weight"] = final["Dense_0"]["kernel"].T
            sd[f"{prefix}.norm.dense.bias"] = final["Dense_0"]["bias"]
        else:
            sd[f"{prefix}.norm.weight"] = final["scale"]

    names = ["action_in_proj", "action_out_proj"]
    names += ["time_mlp_in", "time_mlp_out"] if pi05 else ["state_proj", "action_time_mlp_in", "action_time_mlp_out"]
    for name in names:
        _linear(sd, name, params[name])
    return sd


def torch_state_dict(params: Mapping, config: Pi0Config, *, embed: str = "lm_head", expert_head: bool = True,
                     swap_time_spelling: bool = False, seed: int = 1) -> dict[str, np.ndarray]:
    """A concrete state dict in numpy. embed: "lm_head" (openpi), "embed_tokens" or "both" (LeRobot fine-tunes,
    with a *different* lm_head so the test sees which one was used); expert_head: add the unused expert lm_head;
    swap_time_spelling: write π0's action_time_mlp_* as time_mlp_* (and π0.5's the other way)."""
    sd = {k: np.asarray(v) for k, v in to_torch(params, config.pi05).items()}
    rng = np.random.default_rng(seed)
    if embed in ("embed_tokens", "both"):
        sd[EMBED] = sd.pop(LM_HEAD)
    if embed == "both":
        sd[LM_HEAD] = rng.standard_normal(sd[EMBED].shape, dtype=np.float32)
    if expert_head:
        sd[EX_HEAD] = rng.standard_normal((config.vocab_size, config.action_expert.width), dtype=np.float32)
    if swap_time_spelling:
        a, b = ("action_time_mlp", "time_mlp") if not config.pi05 else ("time_mlp", "action_time_mlp")
        sd = {(b + k[len(a):] if k.startswith(a + "_") else k): v for k, v in sd.items()}
    return sd


def write_safetensors(directory: Path, sd: Mapping[str, np.ndarray], *, prefix: str = "", shards: int = 1,
                      bf16: Iterable[str] = ()) -> list[Path]:
    """Write `sd` as model.safetensors (or `shards` files + model.safetensors.index.json); keys in `bf16` as bf16."""
    directory.mkdir(parents=True, exist_ok=True)
    bf16 = set(bf16)
    tensors = {prefix + k: np.ascontiguousarray(v.astype(ml_dtypes.bfloat16) if k in bf16 else v)
               for k, v in sd.items()}
    if shards == 1:
        path = directory / "model.safetensors"
        save_file(tensors, str(path), metadata={"format": "pt"})
        return [path]
    keys = sorted(tensors)
    names = [f"model-{j + 1:05d}-of-{shards:05d}.safetensors" for j in range(shards)]
    weight_map = {k: names[j % shards] for j, k in enumerate(keys)}
    for name in names:
        save_file({k: tensors[k] for k in keys if weight_map[k] == name}, str(directory / name),
                  metadata={"format": "pt"})
    total = sum(t.nbytes for t in tensors.values())
    (directory / "model.safetensors.index.json").write_text(
        json.dumps({"metadata": {"total_size": total}, "weight_map": weight_map}, indent=1))
    return [directory / n for n in names]


def full_size_header(preset: str) -> dict[str, tuple[int, ...]]:
    """The key -> shape header of an openpi-converted full-size checkpoint, computed without allocating."""
    config = get_config(preset)
    shapes = jax.eval_shape(lambda p: to_torch(p, config.pi05), pi0.param_shapes(config))
    header = {k: tuple(v.shape) for k, v in shapes.items()}
    header[EX_HEAD] = (config.vocab_size, config.action_expert.width)
    return header


def flatten(tree: Mapping, prefix: str = "") -> dict[str, np.ndarray]:
    out = {}
    for k, v in tree.items():
        if isinstance(v, Mapping):
            out.update(flatten(v, f"{prefix}{k}/"))
        else:
            out[f"{prefix}{k}"] = v
    return out

