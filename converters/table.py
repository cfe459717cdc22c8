"""The conversion table: PyTorch state-dict keys (openpi PyTorch / LeRobot) -> the openpi JAX param tree.

One row per target leaf (spec §10.1 / §11.2): the source key(s), with `{i}` for the layer index, and an einops
pattern that maps one layer's source tensor(s) to one layer's target. Rows with `layers` are stacked on a new
leading axis over that tower's depth (the scan layout). Several source keys are stacked on a new axis `s` first
(k/v -> kv_einsum, gate/up -> gating_einsum).

Shapes are never guessed: the target shape comes from `pi0_jax.pi0.param_shapes(config)`, each axis of the
pattern's right side is bound to it, and the expected source shape is read off the left side. So `(n h) d` means
"rows are head-major, n outer", and a square matrix cannot hide a transposition.

Axis legend: d model width, f MLP width, n heads, k kv heads, h head dim, v vocab, i/o in/out features,
c channels, p/q patch height/width, t patches, s stacked sources.
"""

from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Callable, Mapping

import einops
import numpy as np

from converters.errors import ConversionError, listing

# Source key prefixes (spec §11.2), after stripping LeRobot's leading `model.`.
V = "paligemma_with_expert.paligemma.model.vision_tower.vision_model"
PROJ = "paligemma_with_expert.paligemma.model.multi_modal_projector"
LM = "paligemma_with_expert.paligemma.model.language_model"
EX = "paligemma_with_expert.gemma_expert.model"
LM_HEAD = "paligemma_with_expert.paligemma.lm_head.weight"
EX_HEAD = "paligemma_with_expert.gemma_expert.lm_head.weight"
IMG, LLM = "PaliGemma/img", "PaliGemma/llm"
BLOCK = f"{IMG}/Transformer/encoderblock"


@dataclasses.dataclass(frozen=True)
class Rule:
    """target <- einops(pattern)(sources). `spellings`: alternative source spellings, each a tuple of key
    patterns; `layers`: "img" or "llm" to stack over that depth; `when`: "pi0" / "pi05" to restrict the row;
    `prefer_first`: if several spellings are present, take the first and ignore the rest (else it is an error)."""

    target: str
    spellings: tuple[tuple[str, ...], ...]
    pattern: str
    layers: str | None = None
    when: str | None = None
    prefer_first: bool = False


def _r(target, source, pattern, layers=None, when=None, alt=(), prefer_first=False) -> Rule:
    spell = lambda s: (s,) if isinstance(s, str) else tuple(s)  # noqa: E731
    return Rule(target, (spell(source), *map(spell, alt)), pattern, layers, when, prefer_first)


LINEAR = "o i -> i o"  # torch nn.Linear weight (out, in) -> flax kernel (in, out)
COPY = "d -> d"


def _vision_rows() -> list[Rule]:
    L = f"{V}.encoder.layers.{{i}}"
    mha = f"{BLOCK}/MultiHeadDotProductAttention_0"
    rows = [
        _r(f"{IMG}/embedding/kernel", f"{V}.embeddings.patch_embedding.weight", "o c p q -> p q c o"),  # OIHW->HWIO
        _r(f"{IMG}/embedding/bias", f"{V}.embeddings.patch_embedding.bias", COPY),
        _r(f"{IMG}/pos_embedding", f"{V}.embeddings.position_embedding.weight", "t d -> 1 t d"),
        _r(f"{IMG}/Transformer/encoder_norm/scale", f"{V}.post_layernorm.weight", COPY),
        _r(f"{IMG}/Transformer/encoder_norm/bias", f"{V}.post_layernorm.bias", COPY),
        _r(f"{IMG}/head/kernel", f"{PROJ}.linear.weight", LINEAR),
        _r(f"{IMG}/head/bias", f"{PROJ}.linear.bias", COPY),
        _r(f"{mha}/out/kernel", f"{L}.self_attn.out_proj.weight", "d (n h) -> n h d", "img"),
        _r(f"{mha}/out/bias", f"{L}.self_attn.out_proj.bias", COPY, "img"),
        _r(f"{BLOCK}/MlpBlock_0/Dense_0/kernel", f"{L}.mlp.fc1.weight", LINEAR, "img"),
        _r(f"{BLOCK}/MlpBlock_0/Dense_0/bias", f"{L}.mlp.fc1.bias", COPY, "img"),
        _r(f"{BLOCK}/MlpBlock_0/Dense_1/kernel", f"{L}.mlp.fc2.weight", LINEAR, "img"),
        _r(f"{BLOCK}/MlpBlock_0/Dense_1/bias", f"{L}.mlp.fc2.bias", COPY, "img"),
    ]
    for jax_name, torch_name in (("query", "q_proj"), ("key", "k_proj"), ("value", "v_proj")):
        rows += [_r(f"{mha}/{jax_name}/kernel", f"{L}.self_attn.{torch_name}.weight", "(n h) d -> d n h", "img"),
                 _r(f"{mha}/{jax_name}/bias", f"{L}.self_attn.{torch_name}.bias", "(n h) -> n h", "img")]
    for jax_name, torch_name in (("LayerNorm_0", "layer_norm1"), ("LayerNorm_1", "layer_norm2")):
        rows += [_r(f"{BLOCK}/{jax_name}/scale", f"{L}.{torch_name}.weight", COPY, "img"),
                 _r(f"{BLOCK}/{jax_name}/bias", f"{L}.{torch_name}.bias", COPY, "img")]
    return rows


def _gemma_rows(src: str, suffix: str, adarms: str | None) -> list[Rule]:
    """One Gemma expert. `suffix` is "" for the VLM and "_1" for the action expert (openpi's naming).
    `adarms`: None for plain RMSNorms everywhere; "pi0" / "pi05" when the plain norm (π0) and the adaRMS Dense
    (π0.5) alternate by model."""
    L, A = f"{src}.layers.{{i}}", f"{LLM}/layers/attn"
    rows = [
        _r(f"{A}/q_einsum{suffix}/w", f"{L}.self_attn.q_proj.weight", "(n h) d -> n d h", "llm"),
        _r(f"{A}/kv_einsum{suffix}/w", (f"{L}.self_attn.k_proj.weight", f"{L}.self_attn.v_proj.weight"),
           "s (k h) d -> s k d h", "llm"),
        _r(f"{A}/attn_vec_einsum{suffix}/w", f"{L}.self_attn.o_proj.weight", "d (n h) -> n h d", "llm"),
        _r(f"{LLM}/layers/mlp{suffix}/gating_einsum", (f"{L}.mlp.gate_proj.weight", f"{L}.mlp.up_proj.weight"),
           "s f d -> s d f", "llm"),
        _r(f"{LLM}/layers/mlp{suffix}/linear", f"{L}.mlp.down_proj.weight", "d f -> f d", "llm"),
    ]
    norms = ((f"layers/pre_attention_norm{suffix}", f"{L}.input_layernorm", "llm"),
             (f"layers/pre_ffw_norm{suffix}", f"{L}.post_attention_layernorm", "llm"),
             (f"final_norm{suffix}", f"{src}.norm", None))
    for target, source, layers in norms:
        # RMSNorm weights are used as (1 + w) on both sides (HF GemmaRMSNorm), so they copy without an offset.
        rows.append(_r(f"{LLM}/{target}/scale", f"{source}.weight", COPY, layers, "pi0" if adarms else None))
        if adarms:
            rows += [_r(f"{LLM}/{target}/Dense_0/kernel", f"{source}.dense.weight", LINEAR, layers, "pi05"),
                     _r(f"{LLM}/{target}/Dense_0/bias", f"{source}.dense.bias", COPY, layers, "pi05")]
    return rows


def _top_rows() -> list[Rule]:
    rows = []
    for name in ("action_in_proj", "action_out_proj"):
        rows += [_r(f"{name}/kernel", f"{name}.weight", LINEAR), _r(f"{name}/bias", f"{name}.bias", COPY)]
    rows += [_r("state_proj/kernel", "state_proj.weight", LINEAR, when="pi0"),
             _r("state_proj/bias", "state_proj.bias", COPY, when="pi0")]
    # LeRobot renames time_mlp_* <-> action_time_mlp_* between π0 and π0.5, so both spellings occur for both.
    for io in ("in", "out"):
        for target, other, when in ((f"action_time_mlp_{io}", f"time_mlp_{io}", "pi0"),
                                    (f"time_mlp_{io}", f"action_time_mlp_{io}", "pi05")):
            rows += [_r(f"{target}/kernel", f"{target}.weight", LINEAR, when=when, alt=[f"{other}.weight"]),
                     _r(f"{target}/bias", f"{target}.bias", COPY, when=when, alt=[f"{other}.bias"])]
    return rows


TABLE: tuple[Rule, ...] = (
    *_vision_rows(),
    # PaliGemma ties lm_head to embed_tokens and safetensors keeps only the first name, `lm_head`, so openpi files
    # lack embed_tokens (spec §11.3). When both are present embed_tokens wins, as in LeRobot's loader.
    _r(f"{LLM}/embedder/input_embedding", f"{LM}.embed_tokens.weight", "v d -> v d", alt=[LM_HEAD],
       prefer_first=True),
    *_gemma_rows(LM, "", None),
    *_gemma_rows(EX, "_1", "pi05"),
    *_top_rows(),
)

# Source tensors dropped on purpose: (regex on the normalised key, model it applies to or None, reason).
IGNORED: tuple[tuple[str, str | None, str], ...] = (
    (re.escape(EX_HEAD), None, "the action expert's lm_head is randomly initialised and unused (no JAX leaf)"),
    (rf"{re.escape(EX)}\.(layers\.\d+\.(input_layernorm|post_attention_layernorm)|norm)\.weight", "pi05",
     "adaRMS norms have no scale; LeRobot drops these keys for π0.5 too"),
    (r"state_proj\.(weight|bias)", "pi05", "π0.5 has no state token; LeRobot drops state_proj for π0.5 too"),
    (r"proprio_history_proj\.(weight|bias)", None, "LeRobot MEM proprioceptive-history projection (not supported)"),
    (r".*\.rotary_emb\.inv_freq|.*\.embeddings\.position_ids", None, "non-persistent buffer, recomputed at run time"),
)


@dataclasses.dataclass(frozen=True)
class Step:
    """One resolved row: the concrete source keys per layer, the target shape and the einops axis sizes."""

    rule: Rule
    keys: tuple[tuple[str, ...], ...]  # per layer (one entry when not stacked)
    shape: tuple[int, ...]  # full target shape
    sizes: Mapping[str, int]


@dataclasses.dataclass(frozen=True)
class Plan:
    steps: tuple[Step, ...]
    ignored: Mapping[str, str]  # source key -> reason


def _tokens(side: str) -> list[str]:
    return re.findall(r"\([^)]*\)|\S+", side)


def source_shape(pattern: str, target_shape: tuple[int, ...], n_sources: int) -> tuple[tuple[int, ...], dict]:
    """Bind the right side of `pattern` to `target_shape` and read one source's shape off the left side."""
    lhs, rhs = (_tokens(s) for s in pattern.split("->"))
    if len(rhs) != len(target_shape):
        raise RuntimeError(f"table pattern {pattern!r} does not fit target shape {target_shape}")
    sizes = {}
    for tok, dim in zip(rhs, target_shape):
        if tok == "1":
            if dim != 1:
                raise RuntimeError(f"table pattern {pattern!r}: target shape {target_shape} has no unit axis")
        else:
            sizes[tok] = dim
    dims = [1 if t == "1" else math.prod(sizes[n] for n in t.strip("()").split()) for t in lhs]
    if n_sources > 1:
        if lhs[0] != "s" or sizes.get("s") != n_sources:
            raise RuntimeError(f"table pattern {pattern!r} does not stack {n_sources} sources")
        dims = dims[1:]
    return tuple(dims), sizes


def _flatten(tree, prefix=()) -> dict[str, tuple[int, ...]]:
    out = {}
    for k, v in tree.items():
        if isinstance(v, Mapping):
            out.update(_flatten(v, (*prefix, k)))
        else:
            out["/".join((*prefix, k))] = tuple(v.shape)
    return out


def make_plan(config, header: Mapping[str, tuple[int, ...]], origin: Mapping[str, str] | None = None) -> Plan:
    """Check a source's key set and shapes against the table for `config` (no tensor is read).

    header: normalised source key -> shape; origin: key -> where it was read ("'model.x' in 'file'"), for messages.
    Raises ConversionError listing every missing key, unexpected key and wrong shape. Every target leaf of
    `param_shapes(config)` is produced by exactly one row (asserted).
    """
    where = lambda k: (origin or {}).get(k, repr(k))  # noqa: E731
    from pi0_jax.pi0 import param_shapes  # jax import deferred: `--help` stays fast

    targets = _flatten(param_shapes(config))
    variant = "pi05" if config.pi05 else "pi0"
    rows = [r for r in TABLE if r.when in (None, variant)]
    covered = [r.target for r in rows]
    if sorted(covered) != sorted(targets):
        raise RuntimeError(f"conversion table and param tree disagree: table-only "
                           f"{sorted(set(covered) - set(targets))}, tree-only {sorted(set(targets) - set(covered))}")
    depths = {"img": config.siglip.depth, "llm": config.paligemma.depth}

    steps, ignored, consumed = [], {}, set()
    missing, bad_shapes, conflicts = [], [], []
    for rule in rows:
        n_layers = depths[rule.layers] if rule.layers else None
        expand = lambda spelling: tuple(  # noqa: E731
            tuple(p.format(i=i) for p in spelling) for i in (range(n_layers) if n_layers else [0]))
        present = [s for s in rule.spellings if any(k in header for ks in expand(s) for k in ks)]
        chosen = present[0] if present else rule.spellings[0]
        if len(present) > 1:
            if not rule.prefer_first:
                conflicts.append(f"{listing(present[0])} and {listing(present[1])} are two spellings of "
                                 f"{rule.target!r}; keep one")
            for other in present[1:]:
                for k in (k for ks in expand(other) for k in ks if k in header):
                    ignored[k] = f"superseded by {chosen[0].format(i=0)!r}"
        keys = expand(chosen)
        shape = targets[rule.target]
        want, sizes = source_shape(rule.pattern, shape[1:] if n_layers else shape, len(chosen))
        for k in (k for ks in keys for k in ks):
            consumed.add(k)
            if k not in header:
                alts = [s[0] for s in rule.spellings if s is not chosen]
                missing.append(k + (f" (or {listing(a.format(i=0) for a in alts)})" if alts else ""))
            elif tuple(header[k]) != want:
                bad_shapes.append(f"{where(k)}: shape {tuple(header[k])}, expected {want} for {rule.target!r} "
                                  f"({rule.pattern})")
        steps.append(Step(rule, keys, shape, sizes))

    for k in header:
        if k in consumed or k in ignored:
            continue
        for regex, when, reason in IGNORED:
            if when in (None, variant) and re.fullmatch(regex, k):
                ignored[k] = reason
                break
    unexpected = [k for k in header if k not in consumed and k not in ignored]

    problems = []
    if missing:
        problems.append(f"missing {len(missing)} key(s): {listing(missing)}")
    if unexpected:
        problems.append(f"unexpected {len(unexpected)} key(s): " + ", ".join(sorted(map(where, unexpected))[:8])
                        + (f" ... and {len(unexpected) - 8} more" if len(unexpected) > 8 else ""))
    if bad_shapes:
        problems.append(f"wrong shape for {len(bad_shapes)} key(s): " + "; ".join(sorted(bad_shapes)[:8]))
    problems += conflicts
    if problems:
        raise ConversionError(f"keys do not fit {config.name!r} ({variant}): " + " | ".join(problems))
    return Plan(tuple(steps), ignored)


def run_step(step: Step, get: Callable[[str], np.ndarray], dtype) -> np.ndarray:
    """Materialise one target leaf, reading one layer's source tensor(s) at a time into a preallocated array."""
    out = np.empty(step.shape, dtype)
    stacked = step.rule.layers is not None
    for li, keys in enumerate(step.keys):
        xs = [get(k) for k in keys]
        y = einops.rearrange(xs[0] if len(xs) == 1 else xs, step.rule.pattern, **step.sizes)
        if stacked:
            out[li] = y  # casts to `dtype` (fp32 -> bf16 rounds to nearest even, as torch does)
        else:
            out[...] = y
    return out


def unflatten(flat: Mapping[str, np.ndarray]) -> dict:
    tree: dict = {}
    for path, leaf in flat.items():
        *parents, name = path.split("/")
        node = tree
        for p in parents:
            node = node.setdefault(p, {})
        node[name] = leaf
    return tree
