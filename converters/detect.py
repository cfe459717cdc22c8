"""Which model a source checkpoint holds: π0 or π0.5, and which sizes. Never from a folder name.

Evidence, in order: the source `config.json` (LeRobot `type`, `chunk_size`, `tokenizer_max_length`; openpi's
`paligemma_variant` / `action_expert_variant` / `action_horizon`), then the key set (adaRMS `dense` norms in the
action expert => π0.5, plain expert norm weights => π0), then the tensor shapes, matched against the known Gemma
and SigLIP variants. When two sources of evidence disagree it is an error, never a silent pick.
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from converters.errors import ConversionError
from converters.table import EX, LM, LM_HEAD, V
from pi0_jax.config import GEMMA_VARIANTS, PRESETS, SIGLIP_VARIANTS, Pi0Config

LEROBOT_TYPES = {"pi0": False, "pi05": True}
Header = Mapping[str, tuple[int, ...]]


def read_source_config(src_dir: Path) -> tuple[dict[str, Any] | None, Path | None]:
    path = src_dir / "config.json"
    if not path.is_file():
        return None, None
    try:
        cfg = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise ConversionError(f"cannot parse {str(path)!r}: {e}") from e
    if not isinstance(cfg, dict):
        raise ConversionError(f"{str(path)!r} holds a {type(cfg).__name__}, expected a JSON object")
    return cfg, path


def _shape(header: Header, key: str, why: str) -> tuple[int, ...]:
    if key not in header:
        raise ConversionError(f"missing key {key!r} (needed to determine {why})")
    return tuple(header[key])


def _depth(header: Header, prefix: str, why: str) -> int:
    """1 + the highest layer index with a q_proj: a stray key of another layer is then reported as unexpected."""
    pat = re.compile(re.escape(prefix) + r"\.layers\.(\d+)\.self_attn\.q_proj\.weight")
    idx = {int(m.group(1)) for k in header if (m := pat.fullmatch(k))}
    if not idx:
        raise ConversionError(f"no keys {prefix}.layers.<i>.self_attn.q_proj.weight in the source "
                              f"(needed to determine {why})")
    return max(idx) + 1


def _gemma_variant(header: Header, prefix: str, what: str, field: str, named: str | None) -> str:
    L = f"{prefix}.layers.0"
    q = _shape(header, f"{L}.self_attn.q_proj.weight", f"the {what} size")
    k = _shape(header, f"{L}.self_attn.k_proj.weight", f"the {what} size")
    f = _shape(header, f"{L}.mlp.gate_proj.weight", f"the {what} size")
    got = dict(width=q[1], depth=_depth(header, prefix, f"the {what} depth"), mlp_dim=f[0], q_out=q[0], kv_out=k[0])
    matches = [n for n, g in GEMMA_VARIANTS.items()
               if got == dict(width=g.width, depth=g.depth, mlp_dim=g.mlp_dim, q_out=g.num_heads * g.head_dim,
                              kv_out=g.num_kv_heads * g.head_dim)]
    if named is not None:
        base = named.removesuffix("_lora")  # LoRA variants have the base variant's shapes
        if base not in GEMMA_VARIANTS:
            raise ConversionError(f"unknown variant: config.json {field}={named!r}; known: {sorted(GEMMA_VARIANTS)}")
        if base not in matches:
            raise ConversionError(f"config.json {field}={named!r} but the {what} tensors ({L}.self_attn.q_proj.weight "
                                  f"{q}, mlp.gate_proj {f}, {got['depth']} layers) are {matches or 'no known variant'}")
        return base
    if not matches:
        raise ConversionError(f"unknown variant: the {what} tensors ({L}.self_attn.q_proj.weight {q}, "
                              f"k_proj {k}, mlp.gate_proj {f}, {got['depth']} layers) match no known Gemma variant "
                              f"({', '.join(sorted(GEMMA_VARIANTS))})")
    return matches[0]


def _siglip_variant(header: Header) -> str:
    patch = _shape(header, f"{V}.embeddings.patch_embedding.weight", "the vision tower size")
    pos = _shape(header, f"{V}.embeddings.position_embedding.weight", "the vision tower size")
    fc1 = _shape(header, f"{V}.encoder.layers.0.mlp.fc1.weight", "the vision tower size")
    depth = _depth(header, f"{V}.encoder", "the vision tower depth")
    got = (patch[0], depth, fc1[0], patch[2], pos[0])
    for name, s in SIGLIP_VARIANTS.items():
        if got == (s.width, s.depth, s.mlp_dim, s.patch_size, s.num_patches):
            return name
    raise ConversionError(f"unknown variant: the vision tensors (patch_embedding {patch}, position_embedding {pos}, "
                          f"fc1 {fc1}, {depth} layers) match no known SigLIP variant ({', '.join(SIGLIP_VARIANTS)})")


def _is_pi05_from_keys(header: Header) -> tuple[bool | None, str]:
    """adaRMS `dense` in the action expert's norms is π0.5's structural mark; plain norm weights are π0's."""
    dense = sorted(k for k in header if k.startswith(f"{EX}.") and re.search(r"(layernorm|norm)\.dense\.", k))
    plain = sorted(k for k in header if re.fullmatch(
        re.escape(EX) + r"\.(layers\.\d+\.(input_layernorm|post_attention_layernorm)|norm)\.weight", k))
    if dense:
        return True, f"adaRMS key {dense[0]!r}"
    if plain:
        return False, f"plain expert norm key {plain[0]!r}"
    if "state_proj.weight" in header:
        return False, "key 'state_proj.weight'"
    return None, "no expert norm keys"


def _pick(cfg: Mapping[str, Any] | None, *names: str):
    for n in names:
        if cfg is not None and cfg.get(n) is not None:
            return n, cfg[n]
    return None, None


def detect(header: Header, src_cfg: Mapping[str, Any] | None, *, lerobot: bool, dtype: str,
           preset: str | None = None) -> tuple[Pi0Config, dict[str, Any]]:
    """-> (the Pi0Config to convert into, a record of the evidence used)."""
    # π0 vs π0.5.
    from_keys, key_evidence = _is_pi05_from_keys(header)
    _, type_name = _pick(src_cfg, "type")
    from_cfg, cfg_field = None, None
    if type_name is not None:
        cfg_field = f"type={type_name!r}"
        if type_name not in LEROBOT_TYPES:
            raise ConversionError(f"unknown variant: config.json type={type_name!r}; this converter reads "
                                  f"{' and '.join(LEROBOT_TYPES)}")
        from_cfg = LEROBOT_TYPES[type_name]
    elif src_cfg is not None and isinstance(src_cfg.get("pi05"), bool):
        from_cfg, cfg_field = src_cfg["pi05"], f"pi05={src_cfg['pi05']}"
    if from_cfg is not None and from_keys is not None and from_cfg != from_keys:
        raise ConversionError(f"config.json {cfg_field} says {'π0.5' if from_cfg else 'π0'} but the key set is "
                              f"{'π0.5' if from_keys else 'π0'} ({key_evidence})")
    pi05 = from_cfg if from_cfg is not None else from_keys
    if pi05 is None:
        raise ConversionError(f"cannot tell π0 from π0.5: {key_evidence} under {EX!r} and no config.json 'type'")

    # Sizes, from shapes (config.json names are cross-checked, never trusted alone).
    variants = (
        _gemma_variant(header, LM, "VLM (Gemma)", "paligemma_variant", _pick(src_cfg, "paligemma_variant")[1]),
        _gemma_variant(header, EX, "action expert", "action_expert_variant",
                       _pick(src_cfg, "action_expert_variant")[1]),
        _siglip_variant(header),
    )
    emb_keys = [k for k in (f"{LM}.embed_tokens.weight", LM_HEAD) if k in header]
    if not emb_keys:
        raise ConversionError(f"missing key {LM}.embed_tokens.weight (or its tied copy {LM_HEAD}): "
                              f"the text embedding")
    vocab = header[emb_keys[0]][0]
    action_dim = _shape(header, "action_in_proj.weight", "the action dimension")[1]
    out_dim = _shape(header, "action_out_proj.weight", "the action dimension")[0]
    if out_dim != action_dim:
        raise ConversionError(f"'action_in_proj.weight' {tuple(header['action_in_proj.weight'])} and "
                              f"'action_out_proj.weight' {tuple(header['action_out_proj.weight'])} disagree on the "
                              f"action dimension ({action_dim} vs {out_dim})")
    field, cfg_action_dim = _pick(src_cfg, "max_action_dim", "action_dim")
    if cfg_action_dim is not None and int(cfg_action_dim) != action_dim:
        raise ConversionError(f"config.json {field}={cfg_action_dim} but 'action_in_proj.weight' has shape "
                              f"{tuple(header['action_in_proj.weight'])} (action dim {action_dim})")
    _, horizon = _pick(src_cfg, "chunk_size", "action_horizon")
    _, max_len = _pick(src_cfg, "tokenizer_max_length", "max_token_len")

    def fits(p: Pi0Config) -> bool:
        return p.pi05 == pi05 and (p.paligemma_variant, p.action_expert_variant, p.siglip_variant) == variants

    overrides: dict[str, Any] = {"dtype": dtype}
    if preset is not None:
        if preset not in PRESETS:
            raise ConversionError(f"unknown preset {preset!r}; known: {sorted(PRESETS)}")
        base = PRESETS[preset]
        want = dict(pi05=pi05, paligemma_variant=variants[0], action_expert_variant=variants[1],
                    siglip_variant=variants[2], vocab_size=vocab, action_dim=action_dim)
        wrong = {k: (getattr(base, k), v) for k, v in want.items() if getattr(base, k) != v}
        if wrong:
            raise ConversionError(f"--preset {preset!r} does not fit the source: " + ", ".join(
                f"{k}: preset {a!r}, tensors {b!r}" for k, (a, b) in wrong.items()))
    else:
        candidates = [p for p in PRESETS.values() if fits(p)]
        if not candidates:
            raise ConversionError(f"unknown variant: no preset has {'π0.5' if pi05 else 'π0'} with "
                                  f"{variants}; known presets: {sorted(PRESETS)}")
        # Prefer a preset that already has the horizon and prompt length; otherwise the first (base) one.
        candidates.sort(key=lambda p: (horizon is not None and p.action_horizon != int(horizon))
                        + (max_len is not None and p.max_token_len != int(max_len)))
        base = candidates[0]
        overrides.update(vocab_size=vocab, action_dim=action_dim)
        if horizon is not None:
            overrides["action_horizon"] = int(horizon)
        if max_len is not None:
            overrides["max_token_len"] = int(max_len)
        if lerobot and pi05:
            overrides["discrete_state_input"] = True  # LeRobot's π0.5 always writes the state into the prompt
    config = base.replace(**overrides)
    evidence = {"preset": base.name, "pi05": pi05,
                "pi05_evidence": f"config.json {cfg_field}" if from_cfg is not None else key_evidence,
                "variants": list(variants),
                "overrides": {k: v for k, v in overrides.items() if getattr(base, k) != v}}
    return config, evidence
