"""Quantisation schemes over the openpi param tree, calibration of static activation scales, checkpoint storage.

A scheme is a set of GEMM groups; each group is a list of weight leaves (path in the openpi tree, contracting axes,
the engine GEMM whose input calibrates it). Activations are quantised (FP8 x FP8 GEMMs) in every group but "expert",
the action expert's weight-only group: at small batch its denoise step runs M = horizon rows and is not
compute-bound. "expert-act" is the same weights with their activations quantised, for large batches (a simulator's
hundreds of environments: M = batch x horizon rows), calibrated over every step of the denoise loop.
"""

from __future__ import annotations

import functools
import time

import jax
import jax.numpy as jnp
import numpy as np

from pi0_jax.config import IMAGE_KEYS, Pi0Config
from pi0_jax.ops import matmul as hooks
from pi0_jax.ops.formats import QArray, act_scale_from_amax, fake_quant_fp4, quantize_fp8
from pi0_jax.ops.formats import from_storage, quantized_paths, to_storage  # noqa: F401  (re-exported)
from pi0_jax.ops.formats import get_leaf as _get
from pi0_jax.ops.formats import set_leaf as _set

_LLM = ("PaliGemma", "llm", "layers")
_IMG = ("PaliGemma", "img", "Transformer", "encoderblock")
_MHA = "MultiHeadDotProductAttention_0"

# the action expert's GEMMs; keys: "expert/<name>" per layer (`weights.prepare`'s names), recorded in the denoise loop
_EXPERT = [(_LLM + ("attn", "q_einsum_1", "w"), (-2,), "expert/qkv"),
           (_LLM + ("attn", "kv_einsum_1", "w"), (-2,), "expert/qkv"),
           (_LLM + ("attn", "attn_vec_einsum_1", "w"), (-3, -2), "expert/attn_out"),
           (_LLM + ("mlp_1", "gating_einsum"), (-2,), "expert/gate_up"),
           (_LLM + ("mlp_1", "linear"), (-2,), "expert/down")]
# group -> [(path, contracting axes, engine calibration key)]; keys: "vlm/<name>" per layer, "img/<name>" per block
# (both the engine's GEMM names: `weights.prepare`, `weights.vision_weights`), and "img/head".
GROUPS: dict[str, list[tuple[tuple[str, ...], tuple[int, ...], str | None]]] = {
    "prefix-mlp": [(_LLM + ("mlp", "gating_einsum"), (-2,), "vlm/gate_up"),
                   (_LLM + ("mlp", "linear"), (-2,), "vlm/down")],
    "prefix-attn": [(_LLM + ("attn", "q_einsum", "w"), (-2,), "vlm/qkv"),
                    (_LLM + ("attn", "kv_einsum", "w"), (-2,), "vlm/qkv"),
                    (_LLM + ("attn", "attn_vec_einsum", "w"), (-3, -2), "vlm/attn_out")],
    "vision": [(_IMG + (_MHA, n, "kernel"), (-3,), "img/qkv") for n in ("query", "key", "value")]
    + [(_IMG + (_MHA, "out", "kernel"), (-3, -2), "img/out")]
    + [(_IMG + ("MlpBlock_0", n, "kernel"), (-2,), f"img/{k}") for n, k in (("Dense_0", "fc1"), ("Dense_1", "fc2"))]
    + [(("PaliGemma", "img", "head", "kernel"), (-2,), "img/head")],
    "expert": [(path, contract, None) for path, contract, _ in _EXPERT],   # weight-only: nothing to calibrate
    "expert-act": _EXPERT,
}
WEIGHT_ONLY = {"expert"}
SCHEMES: dict[str, tuple[str, ...]] = {
    "prefix-mlp": ("prefix-mlp",),
    "prefix-all": ("prefix-mlp", "prefix-attn"),
    "vision": ("vision",),
    "prefix-vision": ("prefix-mlp", "prefix-attn", "vision"),   # FP8 x FP8 in the prefix and SigLIP: large batches
    "expert-weights": ("expert",),
    "all": ("prefix-mlp", "prefix-attn", "vision", "expert"),
    "every-gemm": ("prefix-mlp", "prefix-attn", "vision", "expert-act"),   # and the expert's: hundreds of samples
}


def _leaves(scheme: str | None):
    """(group, path, contract, key) of the scheme's weights; None: of every group."""
    if scheme is not None and scheme not in SCHEMES:
        raise ValueError(f"unknown scheme {scheme!r}; schemes: {sorted(SCHEMES)}")
    return [(group, *leaf) for group in (GROUPS if scheme is None else SCHEMES[scheme]) for leaf in GROUPS[group]]


def sample_observations(config: Pi0Config, n: int, seed: int = 0, batch: int = 1, tokenizer=None):
    """Realistic calibration / evaluation inputs: smooth natural-image-like images in [-1, 1] (a coarse random
    field upsampled and squashed), LIBERO-style prompts tokenised with `tokenizer` (else random ids), normal state.
    Returns a list of n `pi0.Observation` of `batch` elements each."""
    from pi0_jax import pi0

    rng = np.random.default_rng(seed)
    prompts = ["pick up the black bowl and place it on the plate", "open the top drawer of the cabinet",
               "put the cream cheese in the bowl", "turn on the stove", "push the plate to the front of the stove",
               "put the wine bottle on top of the cabinet", "stack the left bowl on the right bowl"]
    s, L = config.image_size, config.max_token_len
    out = []
    for _ in range(n):
        images = {}
        for k in IMAGE_KEYS[: config.num_cameras]:
            coarse = rng.normal(size=(batch, 8, 8, 3)) + rng.normal(size=(batch, 1, 1, 3))
            fine = jax.image.resize(jnp.asarray(coarse, jnp.float32), (batch, s, s, 3), "cubic")
            fine = fine + 0.05 * jnp.asarray(rng.normal(size=(batch, s, s, 3)), jnp.float32)
            images[k] = jnp.tanh(fine)
        tokens, mask = np.zeros((batch, L), np.int32), np.zeros((batch, L), bool)
        for b in range(batch):
            if tokenizer is not None:
                ids, m = tokenizer.tokenize(prompts[rng.integers(len(prompts))])
                ids, m = np.asarray(ids), np.asarray(m, bool)
                ids = np.where(ids < config.vocab_size, ids, 1)
            else:
                m = np.arange(L) < rng.integers(8, min(24, L) + 1)
                ids = np.where(m, rng.integers(2, config.vocab_size, L), 0)
            tokens[b], mask[b] = ids[:L], m[:L]
        out.append(pi0.Observation(
            images=images, image_masks={k: jnp.ones((batch,), bool) for k in images},
            state=jnp.asarray(rng.normal(size=(batch, config.action_dim)), jnp.float32),
            tokenized_prompt=jnp.asarray(tokens), tokenized_prompt_mask=jnp.asarray(mask)))
    return out


def calibrate(config: Pi0Config, params: dict, observations, scheme: str | None = None, *,
              percentile: float | None = 99.99, num_steps: int = 10, seed: int = 0,
              timing: dict | None = None) -> dict[str, dict[str, np.ndarray]]:
    """Static activation magnitudes {"amax": {key: m}, "percentile": {key: m}} (percentile only if given), m of
    shape (L,) per layer (or () for the SigLIP head), for the activation-quantised GEMMs of `scheme` (None: of every
    scheme, so that any scheme can read its keys).

    Runs the engine's vision and prefix stages (one jit) over `observations` with every such GEMM's weight tapped;
    with the action expert's GEMMs ("expert-act") also the `num_steps` denoise loop from fixed noise (`seed`), whose
    every step is recorded. Deterministic: fixed inputs; amax is a max, percentile a max of per-call values.
    timing: a dict to receive the seconds spent compiling (`compile_s`) and running (`run_s`) the program."""
    from pi0_jax.engine import programs, weights as weights_lib

    keys = {key for group, _, _, key in _leaves(scheme) if group not in WEIGHT_ONLY}
    w = weights_lib.prepare(config, params)
    depths = {"vlm": config.paligemma.depth, "expert": config.paligemma.depth, "img": config.siglip.depth}
    w["vlm"], w["expert"] = (weights_lib.unstack(w[p], depths[p]) for p in ("vlm", "expert"))
    w["img"]["blocks"] = weights_lib.unstack(w["img"]["blocks"], depths["img"])
    for prefix, blocks in (("vlm", w["vlm"]), ("expert", w["expert"]), ("img", w["img"]["blocks"])):
        for i, block in enumerate(blocks):
            for name in block:
                if f"{prefix}/{name}" in keys:
                    block[name] = hooks.Tap(block[name], f"{prefix}/{name}/{i}")
    if "img/head" in keys:
        w["img"]["head"]["kernel"] = hooks.Tap(w["img"]["head"]["kernel"], "img/head")
    expert = any(k.startswith("expert/") for k in keys)
    sched = weights_lib.precompute_schedule(config, params, num_steps) if expert else None

    def stages(w, images, image_masks, tokens, token_mask, state, noise):
        image_tokens = programs.encode_images(config, w, images, unroll=True)
        cache = programs.fill_prefix_cache(config, w, image_tokens, image_masks, tokens, token_mask, unroll=True)
        if not expert:
            return cache.k
        return programs.denoise(config, w, sched, cache, state, noise, num_steps=num_steps, unroll=True,
                                unroll_steps=False)

    rng = np.random.default_rng(seed)
    compiled, seconds = {}, {"compile_s": 0.0, "run_s": 0.0}
    with hooks.recording(percentile) as rec:
        # traced inside the recording: the taps' callbacks are in the program. It runs once, so on a GPU its GEMMs
        # are cuBLAS's: XLA's autotuner would compile Triton GEMMs for each new shape first
        run = jax.jit(stages)
        for obs in observations:
            cams = IMAGE_KEYS[: config.num_cameras]
            images = jnp.stack([jnp.asarray(obs.images[k], jnp.float32) for k in cams])
            image_masks = jnp.stack([jnp.asarray(obs.image_masks[k], bool) for k in cams])
            state = jnp.asarray(obs.state, jnp.float32)
            noise = rng.standard_normal((state.shape[0], config.action_horizon, config.action_dim), np.float32)
            args = (w, images, image_masks, jnp.asarray(obs.tokenized_prompt), jnp.asarray(obs.tokenized_prompt_mask),
                    state, jnp.asarray(noise))
            shapes = tuple(a.shape for a in jax.tree.leaves(args[1:]))
            t0 = time.perf_counter()
            if shapes not in compiled:
                compiled[shapes] = run.lower(*args).compile(hooks.compiler_options(w, "cublas"))
            t1 = time.perf_counter()
            jax.block_until_ready(compiled[shapes](*args))
            seconds["compile_s"] += t1 - t0
            seconds["run_s"] += time.perf_counter() - t1
        t1 = time.perf_counter()
        jax.effects_barrier()
        seconds["run_s"] += time.perf_counter() - t1
    if timing is not None:
        timing.update(seconds)
    result = {}
    for method in ("amax", "percentile") if percentile is not None else ("amax",):
        per_call = hooks.summarize(rec, method)
        out = result[method] = {}
        for key in keys:
            if key == "img/head":
                out[key] = np.asarray(per_call[key], np.float32)
            else:
                n = depths[key.split("/")[0]]
                out[key] = np.asarray([per_call[f"{key}/{i}"] for i in range(n)], np.float32)
    return result


# -- params transforms ----------------------------------------------------------------------------------------------
def quantize_params(params: dict, scheme: str, amax: dict | None, *, per_channel: bool = True) -> dict:
    """params with the scheme's weights replaced by FP8 `QArray`s; `amax` (from `calibrate`) gives the static
    activation scales of the activation-quantised groups."""
    for group, path, contract, key in _leaves(scheme):
        w = _get(params, path)
        if isinstance(w, QArray):
            raise ValueError(f"{'/'.join(path)} is quantised already: quantise to {scheme!r} from unquantised weights")
        act = None
        if group not in WEIGHT_ONLY:
            if amax is None or key not in amax:
                raise ValueError(f"scheme {scheme!r} quantises activations: calibrate it first (missing {key})")
            act = act_scale_from_amax(amax[key])
        stacked = path[:len(_IMG)] == _IMG or path[:len(_LLM)] == _LLM
        params = _set(params, path, _quantize_fp8_jit(w, act, contract=contract, per_channel=per_channel,
                                                      stacked=stacked))
    return params


@functools.partial(jax.jit, static_argnames=("contract", "per_channel", "stacked"))
def _quantize_fp8_jit(w, act, *, contract, per_channel, stacked):
    return quantize_fp8(w, contract=contract, per_channel=per_channel, stacked=stacked, act_scale=act)


def fake_quant_fp4_params(params: dict, fmt: str, scheme: str = "all") -> dict:
    """FP4 emulation: the scheme's weights quantised to `fmt` (nvfp4 / mxfp4) and dequantised back to their dtype,
    blocks along the (merged) contracting axes. Computed on the CPU backend: on GPU (jax 0.11) the nvfp4 round
    trip came back unchanged, so the emulation is pinned to the backend whose rounding the tests check."""
    with jax.default_device(jax.devices("cpu")[0]):
        return _fake_quant_fp4_params(jax.device_get(params), fmt, scheme)


def _fake_quant_fp4_params(params: dict, fmt: str, scheme: str) -> dict:
    for _, path, contract, _ in _leaves(scheme):
        w = jnp.asarray(_get(params, path))
        lo, hi = w.ndim + contract[0], w.ndim + contract[-1]
        merged = w.reshape(*w.shape[:lo], -1, *w.shape[hi + 1:])
        fq = jax.jit(fake_quant_fp4, static_argnums=(1, 2))(merged, fmt, lo - merged.ndim)
        params = _set(params, path, fq.reshape(w.shape))
    return params
