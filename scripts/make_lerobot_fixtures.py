#!/usr/bin/env python
"""Build golden fixtures from LeRobot's PyTorch π0 / π0.5 at a tiny size.

This script is NOT run in CI.  It needs a separate environment with LeRobot and PyTorch:

    python -m venv /opt/lerobot-venv
    /opt/lerobot-venv/bin/pip install 'lerobot==0.6.1' 'transformers>=5.4,<5.6' 'torch<2.12'
    /opt/lerobot-venv/bin/python scripts/make_lerobot_fixtures.py            # writes tests/fixtures/lerobot_pi{0,05}/

It builds LeRobot's own ``PI0Policy`` / ``PI05Policy`` (nothing of LeRobot is copied here; all numerics
come from LeRobot/transformers code), shrunk to the "dummy" preset that pi0-jax also defines:

* VLM Gemma ``dummy``:          width 64, depth 3, mlp 160, 4 heads, 1 kv head, head_dim 16, vocab 1024
* action expert ``dummy_expert``: width 48, depth 3, mlp 96,  4 heads, 1 kv head, head_dim 16
* SigLIP ``dummy``:             hidden 40, depth 2, mlp 88, 2 heads (head_dim 20), patch 14, image 224,
                                projector 40 -> 64
* action/state dim 32, chunk 10, 3 cameras, tokenizer_max_length 48 (π0) / 200 (π0.5), 10 flow steps, float32

How it is shrunk (LeRobot hard-codes the 2B/300M Gemma table, the So400m vision tower, the 2048-wide projector
and the 257152 vocab): while the policy is constructed we substitute, inside LeRobot's modeling module only,
(a) ``get_gemma_config`` so that the variants ``dummy``/``dummy_expert`` exist, and (b) the two HF model
classes it instantiates by thin wrappers that edit the HF config objects LeRobot has just built
(vision sizes, projection_dim, vocab) before calling the original constructors.  site-packages is not edited.

Every parameter is then re-randomised with a fixed seed (per-parameter generator seeded from the seed and a
CRC32 of the parameter name), including the ones LeRobot/HF zero- or one-initialise (RMSNorm weights,
LayerNorms, biases, the adaRMS ``dense`` layers), so that a bug anywhere changes the outputs.

Outputs per variant (``<out-dir>/lerobot_pi0`` and ``<out-dir>/lerobot_pi05``):

* ``config.json`` + ``model.safetensors``: written by LeRobot's ``policy.save_pretrained``.
* ``policy_preprocessor.json`` / ``policy_postprocessor.json`` + ``*_normalizer_processor.safetensors``:
  written by LeRobot's processor pipelines (``make_pi0{5}_pre_post_processors``).  The tokenizer step is
  kept in the JSON exactly as LeRobot writes it, but the tokenizer itself is never loaded (a stub replaces
  ``AutoTokenizer.from_pretrained`` while the pipeline is built; nothing touches the HF hub).
* ``golden.npz``: inputs and LeRobot's outputs, see ``meta.json`` for every array's meaning and layout.
* ``meta.json``: shapes, layouts, versions, seed, command.

Everything runs on CPU in float32 with one thread and deterministic algorithms; rerunning with the same seed
and the same package versions reproduces the files byte for byte (the npz is written with fixed zip
timestamps for that reason).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import logging
import os
import platform
import shutil
import sys
import zipfile
import zlib
from pathlib import Path
from unittest import mock

import numpy as np

# Must be set before torch is imported to pin the thread pools.
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")
os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")

import torch  # noqa: E402

REPO_ROOT = Path(__file__).resolve().parents[1]
DEFAULT_OUT_DIR = REPO_ROOT / "tests" / "fixtures"

# ---------------------------------------------------------------------------------------------------------
# Tiny sizes (must match the "dummy" presets of pi0_jax).
# ---------------------------------------------------------------------------------------------------------
VLM_VARIANT = "dummy"
EXPERT_VARIANT = "dummy_expert"
GEMMA_SIZES = {
    # width, depth, mlp_dim, num_heads, num_kv_heads, head_dim
    VLM_VARIANT: dict(width=64, depth=3, mlp_dim=160, num_heads=4, num_kv_heads=1, head_dim=16),
    EXPERT_VARIANT: dict(width=48, depth=3, mlp_dim=96, num_heads=4, num_kv_heads=1, head_dim=16),
}
VOCAB_SIZE = 1024
SIGLIP = dict(hidden_size=40, num_hidden_layers=2, intermediate_size=88, num_attention_heads=2, patch_size=14,
              image_size=224)
NUM_IMG_TOKENS = (SIGLIP["image_size"] // SIGLIP["patch_size"]) ** 2  # 256
CAMERAS = ("base_0_rgb", "left_wrist_0_rgb", "right_wrist_0_rgb")
MAX_DIM = 32  # max_state_dim == max_action_dim
CHUNK = 10
NUM_STEPS = 10
BATCH = 2
RAW_STATE_DIM = 8  # dataset-level state/action dims used for the config features and the normaliser fixtures
RAW_ACTION_DIM = 7

VARIANTS = {
    "pi0": dict(tokenizer_max_length=48, token_lengths=(13, 31), norm="MEAN_STD"),
    "pi05": dict(tokenizer_max_length=200, token_lengths=(45, 131), norm="QUANTILES"),
}


# ---------------------------------------------------------------------------------------------------------
# LeRobot imports / shrinking patches
# ---------------------------------------------------------------------------------------------------------
def _lerobot_modules(variant: str):
    if variant == "pi0":
        from lerobot.policies.pi0 import modeling_pi0 as modeling
        from lerobot.policies.pi0 import processor_pi0 as processor
        from lerobot.policies.pi0.configuration_pi0 import PI0Config as Config

        return modeling, processor, Config, modeling.PI0Policy, processor.make_pi0_pre_post_processors
    from lerobot.policies.pi05 import modeling_pi05 as modeling
    from lerobot.policies.pi05 import processor_pi05 as processor
    from lerobot.policies.pi05.configuration_pi05 import PI05Config as Config

    return modeling, processor, Config, modeling.PI05Policy, processor.make_pi05_pre_post_processors


@contextlib.contextmanager
def tiny_lerobot(modeling):
    """Make LeRobot's modeling module build the tiny model (scoped to this context)."""
    orig_get = modeling.get_gemma_config
    orig_vlm_cls = modeling.PaliGemmaForConditionalGenerationWithPiGemma
    orig_expert_cls = modeling.PiGemmaForCausalLM

    def get_gemma_config(variant):
        if variant in GEMMA_SIZES:
            return modeling.GemmaConfig(**GEMMA_SIZES[variant])
        return orig_get(variant)

    def vlm_cls(config):
        # LeRobot has just set vision intermediate_size=4304, projection_dim=2048 and vocab 257152 on this
        # PaliGemmaConfig; override them (and the So400m defaults) before the model is built.
        vc = config.vision_config
        for k, v in SIGLIP.items():
            setattr(vc, k, v)
        vc.projection_dim = GEMMA_SIZES[VLM_VARIANT]["width"]
        config.projection_dim = GEMMA_SIZES[VLM_VARIANT]["width"]
        config.hidden_size = GEMMA_SIZES[VLM_VARIANT]["width"]
        config.text_config.vocab_size = VOCAB_SIZE
        config.text_config.num_image_tokens = NUM_IMG_TOKENS
        config._vocab_size = VOCAB_SIZE  # noqa: SLF001  (LeRobot sets this legacy attribute too)
        config.image_token_index = VOCAB_SIZE  # LeRobot uses image_token_index == vocab size (unused here)
        return orig_vlm_cls(config=config)

    def expert_cls(config):
        config.vocab_size = VOCAB_SIZE  # only sizes the (unused) expert lm_head
        return orig_expert_cls(config=config)

    with (
        mock.patch.object(modeling, "get_gemma_config", get_gemma_config),
        mock.patch.object(modeling, "PaliGemmaForConditionalGenerationWithPiGemma", vlm_cls),
        mock.patch.object(modeling, "PiGemmaForCausalLM", expert_cls),
    ):
        yield


class _MergeHeadsOnReshape(torch.Tensor):
    """Attention output whose next ``reshape(B, -1, X)`` merges heads as ``(B, T, num_heads * head_dim)``."""

    def reshape(self, *shape):  # noqa: D102
        base = self.as_subclass(torch.Tensor)  # (B, T, H, D)
        return base.reshape(base.shape[0], base.shape[1], base.shape[2] * base.shape[3])


@contextlib.contextmanager
def lerobot_joint_attention_any_heads(modeling):
    """Work around a LeRobot hard-code so the *joint* (training) forward supports num_heads != 8.

    ``compute_layer_complete`` (used only by the prefix+suffix training forward) merges the attention heads
    with ``att_output.reshape(batch_size, -1, 1 * 8 * head_dim)``, i.e. it assumes 8 heads (true for
    gemma_2b / gemma_300m).  With the tiny 4-head preset that reshape folds two tokens into one row and the
    o_proj matmul fails.  We route LeRobot's ``modeling_gemma.eager_attention_forward`` (looked up through the
    module attribute ``modeling_gemma`` of LeRobot's modeling file) through a wrapper that returns the very
    same tensor tagged so that this single reshape merges ``num_heads * head_dim``.  The math is unchanged
    for 8 heads; the script checks the result against the KV-cache path (which uses HF GemmaAttention).
    """
    real = modeling.modeling_gemma

    class _Proxy:
        def __getattr__(self, name):
            return getattr(real, name)

        @staticmethod
        def eager_attention_forward(*args, **kwargs):
            out, weights = real.eager_attention_forward(*args, **kwargs)
            return out.as_subclass(_MergeHeadsOnReshape), weights

    with mock.patch.object(modeling, "modeling_gemma", _Proxy()):
        yield


class _NoTokenizer:
    """Stands in for the PaliGemma tokenizer: LeRobot's pipeline is only built and saved, never tokenises."""

    def __getattr__(self, name):
        raise RuntimeError("the tokenizer is not available in the fixture builder (no HF hub access)")


# ---------------------------------------------------------------------------------------------------------
# Deterministic re-initialisation
# ---------------------------------------------------------------------------------------------------------
def _param_init(name: str, shape: tuple[int, ...]) -> tuple[float, float]:
    """(mean, std) of the normal distribution used for parameter ``name``."""
    fan_in = int(np.prod(shape[1:])) if len(shape) >= 2 else shape[0]
    if ".dense." in name:  # adaRMS modulation Linear(cond -> 3*width); zero-initialised by LeRobot
        return (0.0, 0.5 * fan_in**-0.5) if name.endswith(".weight") else (0.0, 0.1)
    if "layer_norm" in name or "post_layernorm" in name:  # SigLIP LayerNorm (weight used as-is)
        return (1.0, 0.1) if name.endswith(".weight") else (0.0, 0.1)
    if name.endswith("layernorm.weight") or name.endswith(".norm.weight"):  # Gemma RMSNorm, used as (1 + w)
        return (0.0, 0.1)
    if name.endswith("embed_tokens.weight"):  # multiplied by sqrt(width) = 8 inside HF's embedding
        return (0.0, 0.125)
    if name.endswith("lm_head.weight"):  # unused by π0/π0.5 but saved; different values from embed_tokens
        return (0.0, 0.05)
    if name.endswith("position_embedding.weight"):
        return (0.0, 0.1)
    if name.endswith(".weight") and len(shape) >= 2:  # Linear / Conv2d kernels
        return (0.0, fan_in**-0.5)
    if name.endswith(".bias"):
        return (0.0, 0.05)
    raise ValueError(f"no init rule for parameter {name} {shape}")


@torch.no_grad()
def reinit_parameters(module: torch.nn.Module, seed: int) -> dict[str, list[float]]:
    rules = {}
    # No parameter is shared under two names (LeRobot's lm_head / embed_tokens are separate tensors).
    assert len(list(module.named_parameters(remove_duplicate=False))) == len(list(module.named_parameters()))
    for name, p in module.named_parameters():
        mean, std = _param_init(name, tuple(p.shape))
        g = torch.Generator().manual_seed(seed * 1_000_003 + zlib.crc32(name.encode()))
        p.copy_(torch.randn(p.shape, generator=g, dtype=torch.float64).mul_(std).add_(mean).to(p.dtype))
        rules[name] = [mean, std]
    return rules


# ---------------------------------------------------------------------------------------------------------
# Inputs
# ---------------------------------------------------------------------------------------------------------
def make_images(rng: np.random.Generator) -> np.ndarray:
    """uint8 (num_cams, B, 224, 224, 3): smooth per-camera colour waves/gradients plus noise.

    The pattern is drawn on a 32x32 grid and upsampled by 7 (nearest), so every 14x14 SigLIP patch holds
    2x2 distinct colours and the array deflates to a few kB.
    """
    n = SIGLIP["image_size"]
    lo, up = 32, SIGLIP["image_size"] // 32
    yy, xx = np.meshgrid(np.linspace(0.0, 1.0, lo), np.linspace(0.0, 1.0, lo), indexing="ij")
    out = np.empty((len(CAMERAS), BATCH, n, n, 3), np.uint8)
    for c in range(len(CAMERAS)):
        for b in range(BATCH):
            chans = []
            for _ in range(3):
                fx, fy, ph = rng.uniform(0.5, 3.0), rng.uniform(0.5, 3.0), rng.uniform(0, 2 * np.pi)
                a, gx, gy = rng.uniform(40, 90), rng.uniform(-60, 60), rng.uniform(-60, 60)
                wave = a * np.sin(2 * np.pi * (fx * xx + fy * yy) + ph)
                chans.append(128 + wave + gx * (xx - 0.5) + gy * (yy - 0.5))
            img = np.stack(chans, -1) + rng.normal(0.0, 12.0, size=(lo, lo, 3))
            img = np.clip(np.rint(img), 0, 255).astype(np.uint8)
            out[c, b] = img.repeat(up, axis=0).repeat(up, axis=1)
    return out


def make_inputs(seed: int, variant: str) -> dict[str, np.ndarray]:
    rng = np.random.default_rng([seed, 0 if variant == "pi0" else 1])
    L = VARIANTS[variant]["tokenizer_max_length"]
    lengths = VARIANTS[variant]["token_lengths"]
    tokens = np.zeros((BATCH, L), np.int32)
    token_masks = np.zeros((BATCH, L), bool)
    for b, n in enumerate(lengths):
        tokens[b, :n] = rng.integers(2, VOCAB_SIZE, size=n)
        token_masks[b, :n] = True
    image_masks = np.ones((len(CAMERAS), BATCH), bool)
    image_masks[2, 1] = False
    f32 = np.float32
    inputs = dict(
        images=make_images(rng),
        image_masks=image_masks,
        tokens=tokens,
        token_masks=token_masks,
        state=rng.normal(size=(BATCH, MAX_DIM)).astype(f32),
        noise=rng.normal(size=(BATCH, CHUNK, MAX_DIM)).astype(f32),
        x_t=rng.normal(size=(BATCH, CHUNK, MAX_DIM)).astype(f32),
        time=np.array([0.7, 0.3], f32),
        loss_actions=rng.normal(size=(BATCH, CHUNK, MAX_DIM)).astype(f32),
        loss_noise=rng.normal(size=(BATCH, CHUNK, MAX_DIM)).astype(f32),
        # LeRobot samples Beta(1.5, 1.0) * 0.999 + 0.001; we inject fixed draws from the same law.
        loss_time=(rng.beta(1.5, 1.0, size=BATCH) * 0.999 + 0.001).astype(f32),
        # Normaliser fixtures (dataset-level dims, before padding to 32).
        norm_state_in=(rng.normal(size=(BATCH, RAW_STATE_DIM)) * 2.0 + 0.5).astype(f32),
        unnorm_actions_in=rng.uniform(-1.2, 1.2, size=(BATCH, CHUNK, RAW_ACTION_DIM)).astype(f32),
    )
    return inputs


def make_stats(seed: int, variant: str) -> dict[str, dict[str, np.ndarray]]:
    """Synthetic dataset statistics in LeRobot's layout (as computed by lerobot.datasets.compute_stats)."""
    rng = np.random.default_rng([seed, 2 if variant == "pi0" else 3])
    stats = {}
    for key, dim in (("observation.state", RAW_STATE_DIM), ("action", RAW_ACTION_DIM)):
        mean = rng.normal(size=dim) * 0.5
        std = rng.uniform(0.2, 2.0, size=dim)
        q01 = mean - std * rng.uniform(1.8, 2.6, size=dim)
        q99 = mean + std * rng.uniform(1.8, 2.6, size=dim)
        stats[key] = {
            "mean": mean, "std": std,
            "min": q01 - rng.uniform(0.1, 0.5, size=dim), "max": q99 + rng.uniform(0.1, 0.5, size=dim),
            "q01": q01, "q99": q99,
        }
    return {k: {s: v.astype(np.float32) for s, v in d.items()} for k, d in stats.items()}


# ---------------------------------------------------------------------------------------------------------
# Building, running, saving
# ---------------------------------------------------------------------------------------------------------
def build_config(Config, variant: str):
    from lerobot.configs.types import FeatureType, PolicyFeature

    cfg = Config(
        device="cpu",
        dtype="float32",
        chunk_size=CHUNK,
        n_action_steps=CHUNK,
        max_state_dim=MAX_DIM,
        max_action_dim=MAX_DIM,
        num_inference_steps=NUM_STEPS,
        tokenizer_max_length=VARIANTS[variant]["tokenizer_max_length"],
        push_to_hub=False,
    )
    # Set after __post_init__ (which only accepts gemma_2b / gemma_300m); config.json records the tiny preset
    # names that pi0-jax understands.  Stock LeRobot cannot re-load this config.json (it rejects the variant).
    cfg.paligemma_variant = VLM_VARIANT
    cfg.action_expert_variant = EXPERT_VARIANT
    s = SIGLIP["image_size"]
    cfg.input_features = {
        **{f"observation.images.{c}": PolicyFeature(type=FeatureType.VISUAL, shape=(3, s, s)) for c in CAMERAS},
        "observation.state": PolicyFeature(type=FeatureType.STATE, shape=(RAW_STATE_DIM,)),
    }
    cfg.output_features = {"action": PolicyFeature(type=FeatureType.ACTION, shape=(RAW_ACTION_DIM,))}
    return cfg


def _t(x, dtype=None):
    t = torch.from_numpy(np.ascontiguousarray(x))
    return t if dtype is None else t.to(dtype)


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().cpu().contiguous().numpy()


@torch.no_grad()
def run_lerobot(policy, modeling, variant: str, inp: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Record LeRobot's outputs.  All model math is LeRobot's; we only call its methods and spy on calls."""
    model = policy.model  # PI0Pytorch / PI05Pytorch
    pwe = model.paligemma_with_expert
    is_pi0 = variant == "pi0"

    # Images: the brief's formula x/255*2-1, via LeRobot's own [0,1] -> [-1,1] step; NCHW as SigLIP expects.
    batch = {
        f"observation.images.{c}": _t(inp["images"][i].astype(np.float32) / np.float32(255.0)).permute(0, 3, 1, 2)
        for i, c in enumerate(CAMERAS)
    }
    images, _ = policy._preprocess_images(batch)  # noqa: SLF001  (masks from here are all True; ours below)
    img_masks = [_t(inp["image_masks"][i]) for i in range(len(CAMERAS))]
    tokens = _t(inp["tokens"], torch.long)
    token_masks = _t(inp["token_masks"])
    state = _t(inp["state"])
    out: dict[str, np.ndarray] = {}
    # LeRobot's conversion is bit-identical to images.astype(f32) / 255 * 2 - 1 (not stored: derivable).
    expected = (inp["images"].astype(np.float32) / np.float32(255.0)) * 2 - 1
    assert np.array_equal(np.stack([_np(im) for im in images]), expected.transpose(0, 1, 4, 2, 3))

    # 1. Vision tokens (SigLIP + projector), per camera.
    out["vision_tokens"] = np.stack([_np(pwe.embed_image(im)) for im in images])

    # 2. Spy on LeRobot's sample_actions to capture the prefix embedding, the prefix KV cache and the
    #    Euler trajectory, all produced by LeRobot's own code path.
    captured: dict = {"steps": []}
    orig_embed_prefix, orig_pwe_forward, orig_denoise = model.embed_prefix, pwe.forward, model.denoise_step

    def spy_embed_prefix(*a, **kw):
        res = orig_embed_prefix(*a, **kw)
        captured["prefix"] = res
        return res

    def spy_forward(*a, **kw):
        res = orig_pwe_forward(*a, **kw)
        if kw["inputs_embeds"][1] is None:
            captured["cache"] = res[1]
        return res

    def spy_denoise(*a, **kw):
        v = orig_denoise(*a, **kw)
        captured["steps"].append((kw["x_t"].clone(), kw["timestep"].clone(), v.clone()))
        return v

    noise = _t(inp["noise"])
    with (
        mock.patch.object(model, "embed_prefix", spy_embed_prefix),
        mock.patch.object(pwe, "forward", spy_forward),
        mock.patch.object(model, "denoise_step", spy_denoise),
    ):
        if is_pi0:
            actions = model.sample_actions(images, img_masks, tokens, token_masks, state, noise=noise)
        else:
            actions = model.sample_actions(images, img_masks, tokens, token_masks, noise=noise)
    out["actions"] = _np(actions)

    prefix_embs, prefix_pad_masks, prefix_att_masks = captured["prefix"]
    assert not prefix_att_masks.any()
    out["prefix_embs"] = _np(prefix_embs)
    n_img = len(CAMERAS) * NUM_IMG_TOKENS
    vis = out["vision_tokens"].transpose(1, 0, 2, 3).reshape(BATCH, n_img, -1)
    assert np.array_equal(out["prefix_embs"][:, :n_img], vis)  # image rows of the prefix == vision_tokens
    out["prefix_pad_masks"] = _np(prefix_pad_masks)
    cache = captured["cache"]
    ks, vs = zip(*[(k, v) for k, v, _ in cache])  # each (B, K, P, H)
    out["prefix_k"] = np.stack([_np(k.transpose(1, 2)) for k in ks])  # (depth, B, P, K, H)
    out["prefix_v"] = np.stack([_np(v.transpose(1, 2)) for v in vs])
    out["sample_x_t"] = np.stack([_np(x) for x, _, _ in captured["steps"]])
    out["sample_time"] = np.stack([_np(t[0]) for _, t, _ in captured["steps"]])
    out["sample_v_t"] = np.stack([_np(v) for _, _, v in captured["steps"]])
    assert len(captured["steps"]) == NUM_STEPS

    # 3. One velocity evaluation at (x_t, time) over the prefix cache (LeRobot's denoise_step clones the cache).
    kw = dict(prefix_pad_masks=prefix_pad_masks, past_key_values=cache, x_t=_t(inp["x_t"]),
              timestep=_t(inp["time"]))
    if is_pi0:
        kw["state"] = state
    out["velocity"] = _np(model.denoise_step(**kw))

    # 4. Flow-matching loss of LeRobot's model forward with injected noise and time (per element, 32 dims).
    loss_args = (images, img_masks, tokens, token_masks) + ((state,) if is_pi0 else ())
    with lerobot_joint_attention_any_heads(modeling):
        loss = model.forward(*loss_args, _t(inp["loss_actions"]), _t(inp["loss_noise"]), _t(inp["loss_time"]))
    out["loss"] = _np(loss)

    # Self-check: the joint (training) pass must agree with prefix-cache + suffix pass at the same point.
    tl = _t(inp["loss_time"])[:, None, None]
    x_t_loss = tl * _t(inp["loss_noise"]) + (1 - tl) * _t(inp["loss_actions"])
    kw.update(x_t=x_t_loss, timestep=_t(inp["loss_time"]))
    v_cached = model.denoise_step(**kw)
    loss_cached = (_t(inp["loss_noise"]) - _t(inp["loss_actions"]) - v_cached) ** 2
    err = float((loss_cached - loss).abs().max())
    assert err < 1e-4 * max(1.0, float(loss.abs().max())), f"joint vs cached loss mismatch: {err}"
    print(f"  [{variant}] joint-pass loss vs KV-cache-path loss: max abs diff {err:.3g}")

    # Self-check: sample_actions is the Euler integration of denoise_step from the captured states.
    x = noise
    for x_rec, _, v in captured["steps"]:
        assert torch.equal(x_rec, x)
        x = x + (-1.0 / NUM_STEPS) * v
    assert torch.equal(x, actions)
    return out


def run_normalisers(processor_mod, make_processors, cfg, variant, stats, inp, out_dir: Path) -> dict:
    from lerobot.processor import NormalizerProcessorStep
    from lerobot.processor import tokenizer_processor
    from lerobot.lerobot_types import TransitionKey
    from lerobot.processor.converters import create_transition

    stats_t = {k: {s: torch.from_numpy(v) for s, v in d.items()} for k, d in stats.items()}
    with mock.patch.object(tokenizer_processor.AutoTokenizer, "from_pretrained", lambda *a, **k: _NoTokenizer()):
        pre, post = make_processors(cfg, dataset_stats=stats_t)
    pre.save_pretrained(out_dir)
    post.save_pretrained(out_dir)

    (norm_step,) = [s for s in pre.steps if isinstance(s, NormalizerProcessorStep)]
    tr = create_transition(observation={"observation.state": _t(inp["norm_state_in"])})
    norm_state_out = norm_step(tr)[TransitionKey.OBSERVATION]["observation.state"]
    unnorm_actions_out = post(_t(inp["unnorm_actions_in"]))
    res = {"norm_state_out": _np(norm_state_out), "unnorm_actions_out": _np(unnorm_actions_out)}
    extra = {}
    if variant == "pi05":
        # LeRobot π0.5 writes the discretised *normalised* state into the prompt; record the strings it builds.
        step = processor_mod.Pi05PrepareStateTokenizerProcessorStep(max_state_dim=cfg.max_state_dim)
        tr = create_transition(
            observation={"observation.state": norm_state_out},
            complementary_data={"task": ["pick up the red cube", "open_the drawer\n"]},
        )
        extra["pi05_state_prompts"] = step(tr)[TransitionKey.COMPLEMENTARY_DATA]["task"]
    return res, extra


def save_npz_deterministic(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """Same format as np.savez_compressed, but with fixed zip timestamps so reruns are byte-identical."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name in sorted(arrays):
            info = zipfile.ZipInfo(name + ".npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            with zf.open(info, "w", force_zip64=True) as f:
                np.lib.format.write_array(f, np.asanyarray(arrays[name]), allow_pickle=False)
    path.write_bytes(buf.getvalue())


ARRAY_DOCS = {
    # inputs
    "images": "INPUT uint8 (cams=3, B, 224, 224, 3) HWC RGB, cameras in order base_0_rgb, left_wrist_0_rgb, "
    "right_wrist_0_rgb. Model input = images.astype(float32) / 255 * 2 - 1 (float32 ops in that order); LeRobot "
    "gets it as NCHW [0,1] (x/255) and applies *2-1 itself (PI0Policy._preprocess_images).",
    "image_masks": "INPUT bool (cams, B): camera valid flags; camera 2 (right wrist) is False for batch element 1.",
    "tokens": "INPUT int32 (B, L) language token ids in [2, 1024), right-padded with id 0 (L = tokenizer_max_length).",
    "token_masks": "INPUT bool (B, L) True for valid tokens (right padding, different lengths per row).",
    "state": "INPUT float32 (B, 32) normalised + padded state fed to the π0 suffix (state_proj). "
    "π0.5: unused by the network (LeRobot π0.5 puts the state into the prompt text only).",
    "noise": "INPUT float32 (B, chunk=10, 32) initial x_1 for sample_actions.",
    "x_t": "INPUT float32 (B, 10, 32) noisy actions for the single velocity evaluation.",
    "time": "INPUT float32 (B,) flow time for the single velocity evaluation (t=1 noise, t=0 data).",
    "loss_actions": "INPUT float32 (B, 10, 32) target actions for the loss (all 32 dims random, no padding).",
    "loss_noise": "INPUT float32 (B, 10, 32) injected noise for the loss.",
    "loss_time": "INPUT float32 (B,) injected flow time for the loss (Beta(1.5,1)*0.999+0.001 draws).",
    "norm_state_in": "INPUT float32 (B, 8) raw (dataset-scale) observation.state.",
    "unnorm_actions_in": "INPUT float32 (B, 10, 7) normalised actions (model output space, already sliced to 7).",
    # outputs
    "vision_tokens": "OUTPUT float32 (cams, B, 256, 64): PaliGemmaWithExpertModel.embed_image(x_c) with x_c = "
    "(images[c].astype(f32)/255*2-1) as NCHW (B, 3, 224, 224); = "
    "SigLIP last_hidden_state (post_layernorm) -> multi_modal_projector; no sqrt(width) scaling. Computed for "
    "every camera, masked or not.",
    "prefix_embs": "OUTPUT float32 (B, P, 64), P = 3*256 + L: embed_prefix output = [cam0 | cam1 | cam2 | "
    "language]; language rows are embed_tokens[id] * sqrt(64) (=8, HF GemmaTextScaledWordEmbedding); image "
    "rows equal vision_tokens.",
    "prefix_pad_masks": "OUTPUT bool (B, P): prefix input mask (camera mask repeated x256, then token_masks). "
    "The prefix is fully bidirectional (ar all 0); positions = cumsum(prefix_pad_masks) - 1.",
    "prefix_k": "OUTPUT float32 (depth=3, B, P, num_kv_heads=1, head_dim=16): VLM keys from LeRobot's prefix "
    "pass DynamicCache, post-RoPE (HF rotate_half convention), transposed from HF (B, K, P, H). Rows of padded "
    "tokens / masked cameras are included as computed.",
    "prefix_v": "OUTPUT float32 (depth, B, P, 1, 16): VLM values of the prefix pass, same layout as prefix_k.",
    "velocity": "OUTPUT float32 (B, 10, 32): LeRobot denoise_step(x_t, time) over the prefix cache = "
    "action_out_proj(expert output[:, -10:]).",
    "actions": "OUTPUT float32 (B, 10, 32): model.sample_actions(..., noise=noise), 10 Euler steps from t=1 with "
    "dt=-0.1, all 32 dims (not sliced, not unnormalised).",
    "sample_x_t": "OUTPUT float32 (10, B, 10, 32): x_t at the start of each Euler step of sample_actions "
    "(sample_x_t[0] == noise).",
    "sample_time": "OUTPUT float32 (10,): time of each Euler step, float32(1.0 + step * (-0.1)) computed in "
    "Python double then cast (LeRobot euler_integrate), not accumulated in float32.",
    "sample_v_t": "OUTPUT float32 (10, B, 10, 32): velocity returned by denoise_step at each Euler step; "
    "x_{k+1} = x_k + (-0.1) * v_k.",
    "loss": "OUTPUT float32 (B, 10, 32): PI0Pytorch.forward(..., actions=loss_actions, noise=loss_noise, "
    "time=loss_time) = F.mse_loss(u_t, v_t, reduction='none') with x_t = t*noise + (1-t)*actions, u_t = noise - "
    "actions, from ONE joint prefix+suffix pass (positions = cumsum(all pad masks) - 1). LeRobot's policy then "
    "slices to the real action dim and takes the mean; openpi averages over all 32 dims.",
    "norm_state_out": "OUTPUT float32 (B, 8): LeRobot NormalizerProcessorStep(norm_state_in) with the saved stats "
    "(pi0 MEAN_STD: (x-mean)/(std+1e-8); pi05 QUANTILES: 2*(x-q01)/(q99-q01)-1).",
    "unnorm_actions_out": "OUTPUT float32 (B, 10, 7): LeRobot policy_postprocessor(unnorm_actions_in) "
    "(pi0 MEAN_STD: x*std+mean (no eps); pi05 QUANTILES: (x+1)*(q99-q01)/2+q01).",
}


def _versions() -> dict[str, str]:
    import importlib.metadata as md

    out = {"python": platform.python_version()}
    for pkg in ("lerobot", "transformers", "torch", "numpy", "safetensors"):
        out[pkg] = md.version(pkg)
    return out


def build_variant(variant: str, seed: int, out_root: Path) -> Path:
    modeling, processor_mod, Config, Policy, make_processors = _lerobot_modules(variant)
    out_dir = out_root / f"lerobot_{variant}"
    if out_dir.exists():
        shutil.rmtree(out_dir)
    out_dir.mkdir(parents=True)

    cfg = build_config(Config, variant)
    with tiny_lerobot(modeling):
        policy = Policy(cfg)
    policy.eval()
    init_rules = reinit_parameters(policy, seed)
    assert all(p.dtype == torch.float32 for p in policy.parameters())

    # 1. Checkpoint, exactly as LeRobot writes it.
    policy.save_pretrained(out_dir)

    # 2. Golden outputs.
    inp = make_inputs(seed, variant)
    out = run_lerobot(policy, modeling, variant, inp)

    # Round trip through LeRobot's own loader (from_pretrained with our in-memory config, since stock LeRobot
    # rejects the tiny variant names in config.json): the reloaded policy must reproduce the actions exactly.
    logging.disable(logging.WARNING)  # LeRobot warns about every patch_embedding key it loads
    with tiny_lerobot(modeling), contextlib.redirect_stdout(io.StringIO()) as log:
        reloaded = Policy.from_pretrained(out_dir, config=cfg, strict=True, local_files_only=True)
    logging.disable(logging.NOTSET)
    assert "All keys loaded successfully" in log.getvalue(), log.getvalue()
    reloaded.eval()
    re_out = run_lerobot(reloaded, modeling, variant, inp)
    for k in ("actions", "velocity", "loss", "prefix_k"):
        assert np.array_equal(re_out[k], out[k]), f"reloaded checkpoint differs in {k}"

    # 3. Normalisation parity.
    stats = make_stats(seed, variant)
    norm_out, norm_extra = run_normalisers(processor_mod, make_processors, cfg, variant, stats, inp, out_dir)
    out.update(norm_out)

    arrays = {**inp, **out}
    for k, v in arrays.items():
        assert v.dtype in (np.float32, np.uint8, np.int32, np.bool_), (k, v.dtype)
        assert np.isfinite(v).all() if v.dtype == np.float32 else True, k
    save_npz_deterministic(out_dir / "golden.npz", arrays)

    from safetensors import safe_open

    with safe_open(out_dir / "model.safetensors", "pt") as f:
        st_keys = sorted(f.keys())
        st_dtypes = sorted({str(f.get_slice(k).get_dtype()) for k in st_keys})
    L = VARIANTS[variant]["tokenizer_max_length"]
    meta = {
        "description": f"Golden fixtures of LeRobot's PyTorch {variant} (tiny 'dummy' preset, seeded random "
        "weights), generated by scripts/make_lerobot_fixtures.py. Compare pi0-jax against these.",
        "command": " ".join(["python scripts/make_lerobot_fixtures.py", *sys.argv[1:]]),
        "seed": seed,
        "versions": _versions(),
        "device": "cpu",
        "dtype": "float32",
        "torch_threads": torch.get_num_threads(),
        "variant": variant,
        "sizes": {
            "paligemma_variant": VLM_VARIANT, "action_expert_variant": EXPERT_VARIANT,
            "gemma": GEMMA_SIZES, "vocab_size": VOCAB_SIZE, "siglip": {**SIGLIP, "projection_dim": 64},
            "num_image_tokens_per_camera": NUM_IMG_TOKENS, "cameras": list(CAMERAS), "batch": BATCH,
            "max_state_dim": MAX_DIM, "max_action_dim": MAX_DIM, "chunk_size": CHUNK,
            "num_inference_steps": NUM_STEPS, "tokenizer_max_length": L,
            "prefix_len": len(CAMERAS) * NUM_IMG_TOKENS + L,
            "token_valid_lengths": list(VARIANTS[variant]["token_lengths"]),
            "raw_state_dim": RAW_STATE_DIM, "raw_action_dim": RAW_ACTION_DIM,
            "time_embedding_dim": GEMMA_SIZES[EXPERT_VARIANT]["width"],
        },
        "arrays": {
            k: {"shape": list(v.shape), "dtype": str(v.dtype), "meaning": ARRAY_DOCS[k]}
            for k, v in sorted(arrays.items())
        },
        "checkpoint": {
            "files": sorted(p.name for p in out_dir.iterdir() if p.name not in ("golden.npz", "meta.json")),
            "model_safetensors_num_keys": len(st_keys),
            "model_safetensors_dtypes": st_dtypes,
            "model_safetensors_keys": st_keys,
            "init": "every parameter ~ N(mean, std) with a per-parameter torch.Generator seeded by "
            "seed*1000003 + crc32(name); (mean, std) per key below",
            "init_rules": init_rules,
        },
        "normalisation": {
            "mode": VARIANTS[variant]["norm"],
            "stats": {k: {s: v.tolist() for s, v in d.items()} for k, d in stats.items()},
            **norm_extra,
        },
        "notes": NOTES[variant],
    }
    (out_dir / "meta.json").write_text(json.dumps(meta, indent=1) + "\n")
    return out_dir


NOTES_COMMON = [
    "config.json says paligemma_variant='dummy' and action_expert_variant='dummy_expert' (pi0-jax presets); "
    "stock LeRobot refuses to re-load it (PI0Config only accepts gemma_2b/gemma_300m).",
    "model.safetensors keys all start with 'model.' (LeRobot policy wrapper). Both "
    "model.paligemma_with_expert.paligemma.model.language_model.embed_tokens.weight and "
    "model.paligemma_with_expert.paligemma.lm_head.weight are present and UNTIED (different random values): "
    "LeRobot replaces the language model after HF ties the weights. The model uses embed_tokens only; "
    "lm_head and model.paligemma_with_expert.gemma_expert.lm_head.weight (1024x48) are unused.",
    "All tensors float32 (dtype='float32'). Non-persistent buffers (rotary inv_freq, embed_scale, SigLIP "
    "position_ids) are not saved.",
    "Attention masks: LeRobot passes an additive 4D mask (0 / -2.3819763e38) straight to HF (4D masks "
    "bypass HF mask creation); fully-masked query rows therefore softmax uniformly, like openpi.",
    "Positions: prefix cumsum(prefix_pad_masks)-1; suffix sum(prefix_pad_masks) + cumsum(suffix_mask) - 1; "
    "training pass cumsum(all masks)-1. RoPE: HF Gemma rotary (inv_freq = 1/10000^(2i/16), float32).",
    "KV cache: HF DynamicCache from the prefix pass (use_cache=True); each denoise_step clones it and HF "
    "appends the suffix K/V to the clone (the stored prefix cache itself is not modified).",
    "Time embedding is computed in float64 on CPU (LeRobot create_sinusoidal_pos_embedding) and cast to "
    "float32; openpi computes it in float32. Dimension = expert width (48).",
    "The loss was computed with a scoped workaround for LeRobot's hard-coded 8 attention heads in "
    "compute_layer_complete (joint training pass only); it is checked against the KV-cache path.",
]
NOTES = {
    "pi0": NOTES_COMMON
    + [
        "π0 suffix = [state_proj(state), action_time_mlp_out(silu(action_time_mlp_in(cat(action_in_proj(x_t), "
        "time_emb))))], ar = [1, 1, 0 x 9].",
    ],
    "pi05": NOTES_COMMON
    + [
        "π0.5 suffix = action_in_proj(x_t), ar = [1, 0 x 9]; adarms_cond = silu(time_mlp_out(silu(time_mlp_in("
        "time_emb)))) feeds the expert's adaRMS norms (dense: Linear(48 -> 144), chunks scale|shift|gate). "
        "The state is not an input of the network.",
    ],
}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=(
            "Writes <out-dir>/lerobot_pi0/ and <out-dir>/lerobot_pi05/, each with LeRobot's config.json,\n"
            "model.safetensors, policy_{pre,post}processor.json (+ normaliser .safetensors), golden.npz and\n"
            "meta.json. Existing lerobot_<variant>/ folders are replaced. Needs lerobot==0.6.1,\n"
            "transformers>=5.4,<5.6 and torch (CPU is enough); no network access is used. Example:\n"
            "  /opt/lerobot-venv/bin/python scripts/make_lerobot_fixtures.py"
        ),
    )
    parser.add_argument("--out-dir", type=Path, default=DEFAULT_OUT_DIR,
                        help="parent folder of the lerobot_pi0/ and lerobot_pi05/ fixture folders "
                        f"(default: {DEFAULT_OUT_DIR.relative_to(REPO_ROOT)} in this repository)")
    parser.add_argument("--seed", type=int, default=0,
                        help="seed for the weights, the inputs and the normalisation stats (default: 0); the "
                        "same seed and package versions reproduce the fixtures byte for byte")
    parser.add_argument("--variants", nargs="+", choices=sorted(VARIANTS), default=sorted(VARIANTS),
                        help="which policies to build (default: both)")
    args = parser.parse_args(argv)

    torch.set_num_threads(1)
    torch.use_deterministic_algorithms(True)
    torch.manual_seed(args.seed)  # nothing should draw from the global RNG, but pin it anyway

    for variant in args.variants:
        out_dir = build_variant(variant, args.seed, args.out_dir)
        sizes = {p.name: p.stat().st_size for p in sorted(out_dir.iterdir())}
        print(f"{variant}: {out_dir}  ({sum(sizes.values()) / 1e6:.2f} MB)")
        for name, size in sizes.items():
            print(f"  {name:60s} {size:>10,d}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
