"""The three inference stages, the last two as one (`prefix_denoise`) or split after the first denoise step
(`prefix_first_step`, `denoise_rest`), and the fused program, as pure functions of (engine weights, inputs).

Static per compiled program: the config, batch size, the active cameras (a camera masked for every element is not
encoded at all), the prompt bucket length, num_steps, whether layers are unrolled, each stage's attention
(`Attention`) and the expert's kernels ("xla": `layers.suffix_layer`; "pallas": the fused kernels of
`pi0_jax.ops`, with the prefix cache in their layout; "auto": `expert_path`). Masked-out tokens never advance
positions, so skipping them leaves every number as it was.
"""

from __future__ import annotations

import dataclasses
import functools

import flax.struct
import jax
import jax.numpy as jnp

from pi0_jax import pi0
from pi0_jax.config import Pi0Config
from pi0_jax.engine import layers, vision
from pi0_jax.ops import expert_kernels, layout, mosaic_gemm, pallas_base
from pi0_jax.ops import matmul as quant

# The batch sizes at which kernels="auto" runs the expert's Pallas kernels on a GPU: measured faster than XLA at
# B = 1 and 2 and slower at B = 3 (π0.5), 4 and 8 (H200, docs/BENCHMARKS.md); their 64-row blocks stream the weights
# once per row block.
PALLAS_MAX_BATCH = 2

# The batch from which the denoise step's attention="auto" is cuDNN's fused kernel on a GPU (H200, docs/BENCHMARKS.md),
# below it XLA's ops (at B <= PALLAS_MAX_BATCH the Pallas expert, which has its own attention). π0.5: its denoise loop
# 7 % faster at B = 3 with a kv head's 8 query heads folded into its rows, 8-14 % at B = 4-64 before that fold (which
# took a further 3 % off at B = 8, 13 % at B = 64). π0, its state token once a call (`cached_state`): 16 % faster at
# B = 3, 28 % at B = 8 (it was 9 % slower at B = 3 while the state row ran as XLA's attention beside the kernel).
CUDNN_DENOISE_MIN_BATCH = 3
# The batches at which the denoise attention="auto" is the Pallas split-key kernel in the XLA expert's layers, at
# `expert_kernels.blocks_at`'s launch (docs/BENCHMARKS.md, "The Pallas attention in the XLA expert"). π0 (the kernel
# runs its state row in every step): the 10-step denoise 25 % faster than XLA's attention at B = 3, 28 / 19 / 9 %
# faster than cuDNN's at B = 4 / 8 / 16 with 8 warps (H200s), 4 warps 6-9 % faster again (H100), 18 % slower at
# B = 64; against cuDNN's with the state once a call, 22 / 18 / 8 % faster at B = 3 / 8 / 16 (H200s, session 40).
# π0.5: with 4 warps 19 / 6.5 % faster than cuDNN's at B = 4 / 8, 5 % slower at B = 16 (H100).
PALLAS_DENOISE_BATCHES_MASKED = range(3, 17)
PALLAS_DENOISE_BATCHES = range(4, 9)


# π0's action in-projection folded into the time MLP's first product (`weights.fold_action_in`); False: the two
# products as the reference runs them (an A/B switch for probes, read when a program is traced)
FOLD_ACTION_IN = True

KERNELS = ("auto", "xla", "pallas")
# SigLIP's LayerNorm kernel measured 3 % faster on the tower at 24 and 192 images, and no faster at 3 (H100, XLA's
# GEMMs; docs/BENCHMARKS.md, "SigLIP's LayerNorm as a kernel"): "auto" takes it where it was measured faster
VISION_NORM_MIN_IMAGES = 24
OVERLAPS = ("auto", "on", "off")
# The first denoise step beside the prefix fill (`first_step_overlap`): "auto" up to this batch. On H200s π0's call
# was 1.0-2.4 % faster at B = 1 (six machines) and π0.5's 2.3-3.5 % (two), and level at B = 2 (-0.4 %), 8 and 64,
# where it costs compile time and scratch memory for nothing. With the other steps' loop a program of its own
# (`Engine.call_stages`, session 45) π0's call is 1.3 % faster at B = 1 again and 1.7 % faster at B = 2 than without
# the overlap (H200; docs/BENCHMARKS.md)
OVERLAP_MAX_BATCH = 2
# The call's second program with its first denoise step beside the prefix fill (`first_step_overlap`) compiles with
# this: XLA's command buffers then run each kernel once the kernels whose buffers it reads are done, not in the
# scheduler's one order (XLA's default, "LHS")
CONCURRENT = {"xla_gpu_command_buffer_scheduling_mode": "CONCURRENT"}


def check_kernels(kernels: str) -> str:
    if kernels not in KERNELS:
        raise ValueError(f"kernels must be one of {KERNELS}, got {kernels!r}")
    return kernels


def check_overlap(overlap: str) -> str:
    if overlap not in OVERLAPS:
        raise ValueError(f"overlap must be one of {OVERLAPS}, got {overlap!r}")
    return overlap


def is_quantised(tree) -> bool:
    """Whether any weight in tree is quantised (an FP8 `QArray` or a calibration `Tap`)."""
    return any(quant.is_quant(x) for x in jax.tree.leaves(tree, is_leaf=quant.is_quant))


def expert_path(kernels: str, batch: int, expert_weights, platform: str | None = None) -> str:
    """The action expert's path for one program: "xla" or "pallas" as asked; "auto" picks the faster at this batch
    on this platform: the Pallas kernels on a GPU up to PALLAS_MAX_BATCH (with unrolled, unquantised layers; on a
    jax without Pallas's Triton backend, `pallas_base.TRITON`, only where all of them run on Mosaic GPU,
    `expert_kernels.TRITON_FREE`: bf16 on Hopper), else XLA (on a CPU the kernels run interpreted)."""
    if check_kernels(kernels) != "auto":
        return kernels
    if expert_weights is None:
        raise ValueError("kernels='auto' chooses the expert's path by its weights; without them pass 'xla' or "
                         "'pallas' (e.g. `Engine.kernels_for(batch)`)")
    platform = platform or jax.default_backend()
    unrolled = isinstance(expert_weights, (list, tuple))
    pallas = platform == "gpu" and batch <= PALLAS_MAX_BATCH and unrolled and not is_quantised(expert_weights)
    if pallas and not pallas_base.TRITON:
        bf16 = all(expert_weights[0][k].dtype == jnp.bfloat16 for k in ("qkv", "attn_out", "gate_up", "down"))
        pallas = bf16 and mosaic_gemm.hopper()
    return "pallas" if pallas else "xla"


def first_step_overlap(overlap: str, kernels: str, batch: int, expert_weights, platform: str | None = None) -> bool:
    """Whether the call's second program runs its first denoise step beside the prefix fill: the step after the
    fill (`prefix_first_step`, or `peel_first` in `prefix_denoise`; its layer i then waits for the cache's layer i
    alone), the program compiled with `CONCURRENT`, so the latency-bound step's kernels run in the compute-bound
    prefix's gaps. "on" / "off" as asked; "auto" up to OVERLAP_MAX_BATCH where the expert runs its Pallas kernels on
    a GPU (`expert_path`). On an H200 at B = 1 the call is 2.4 % (π0) and 3.5 % (π0.5) faster; at B = 8 and 64 level,
    and at B = 64 the program takes 4.5 GB more scratch (docs/BENCHMARKS.md, "The first denoise step beside the prefix
    fill"); at B = 2 1.7 % faster since the other steps' loop is a program of its own ("The denoise loop as a program
    of its own")."""
    if check_overlap(overlap) != "auto":
        return overlap == "on"
    platform = platform or jax.default_backend()
    return (platform == "gpu" and batch <= OVERLAP_MAX_BATCH
            and expert_path(kernels, batch, expert_weights, platform) == "pallas")


def overlap_options(options: dict | None, overlap: bool) -> dict | None:
    """A call's second program's compiler options: `options`, with `CONCURRENT` where it overlaps its first step."""
    return {**(options or {}), **CONCURRENT} if overlap else options


def vision_norm(kernels: str, images: int, platform: str | None = None) -> str:
    """SigLIP's residual adds and LayerNorms: "xla" or "pallas" (`ops.layer_norm`: one kernel where XLA runs two or
    three) as asked; "auto" the kernel on a GPU from VISION_NORM_MIN_IMAGES images per call, XLA's ops below (and
    on a CPU, where the kernel runs interpreted, and on a jax without Pallas's Triton backend)."""
    if check_kernels(kernels) != "auto":
        return kernels
    gpu = (platform or jax.default_backend()) == "gpu" and pallas_base.TRITON
    return "pallas" if gpu and images >= VISION_NORM_MIN_IMAGES else "xla"


@dataclasses.dataclass(frozen=True)
class Attention:
    """Each stage's attention: "xla" (the reference's ops: logits, softmax, weighted sum) or "cudnn" (one fused
    flash kernel, `ops.attention.fused`: cuDNN on a GPU, its XLA form elsewhere; masks by lengths, so the prefix
    fill puts each element's valid tokens first). Vision's may also be "pallas" (`ops.vision_attention`: q, k and v
    read in place from the fused GEMM's output). The denoise step's may also be "pallas" (the XLA expert's layers
    with the Pallas expert's split-key attention, `ops.expert_kernels.attention`, over a cache in its layout; not
    differentiable) or "auto": "cudnn" from CUDNN_DENOISE_MIN_BATCH on, else "xla", but "pallas" at
    PALLAS_DENOISE_BATCHES (π0: PALLAS_DENOISE_BATCHES_MASKED) (`at_batch` resolves it; the programs do). It is
    unused by the Pallas expert, which has its own."""

    vision: str = "xla"
    prefix: str = "xla"
    denoise: str = "xla"

    def __post_init__(self):
        for stage, value in dataclasses.asdict(self).items():
            extra = {"vision": ("pallas",), "denoise": ("pallas", "auto")}.get(stage, ())
            if value not in ("xla", "cudnn", *extra):
                raise ValueError(f"attention for {stage} must be one of {('xla', 'cudnn', *extra)}, got {value!r}")

    def at_batch(self, batch: int, suffix_mask: bool = False, differentiable: bool = False) -> Attention:
        """The concrete choice of every stage for a program of this batch size; suffix_mask: the model's suffix
        masks some of its own keys (π0; π0.5's attends everywhere); differentiable: XLA's denoise attention (a
        program that differentiates the velocity, `guidance.guided_denoise`: the Pallas kernel has no VJP, and
        cuDNN's flash attention refused a backward pass at the suffix's sequence lengths on a GPU). On a jax without
        Pallas's Triton backend "pallas" is the kernel on Mosaic GPU (`expert_kernels.TRITON_FREE`: Hopper; "auto" is
        bf16 only), and elsewhere cuDNN's or XLA's."""
        if self.denoise != "auto":
            return self
        if differentiable:
            return dataclasses.replace(self, denoise="xla")
        kernel = PALLAS_DENOISE_BATCHES_MASKED if suffix_mask else PALLAS_DENOISE_BATCHES
        if batch in kernel and (pallas_base.TRITON or mosaic_gemm.hopper()):   # without Triton on Mosaic GPU
            return dataclasses.replace(self, denoise="pallas")
        return dataclasses.replace(self, denoise="cudnn" if batch >= CUDNN_DENOISE_MIN_BATCH else "xla")

    @classmethod
    def parse(cls, spec, platform: str | None = None, dtype: str = "bfloat16") -> Attention:
        """"xla" | "cudnn" (every stage) | "auto" (`AUTO_GPU` on a GPU for bfloat16 models, with cuDNN's vision
        attention on a jax without Pallas's Triton backend; else "xla": cuDNN's flash kernel takes no float32) |
        "vision=cudnn,prefix=xla" (unnamed stages "xla") | an Attention."""
        if isinstance(spec, cls):
            return spec
        if spec == "auto":
            if (platform or jax.default_backend()) != "gpu" or dtype != "bfloat16":
                return cls()
            return AUTO_GPU if pallas_base.TRITON else dataclasses.replace(AUTO_GPU, vision="cudnn")
        if spec in ("xla", "cudnn"):
            return cls(spec, spec, spec)
        fields = {f.name for f in dataclasses.fields(cls)}
        kw = {}
        for part in str(spec).split(","):
            stage, _, value = part.partition("=")
            if stage not in fields or not value:
                raise ValueError(f"attention: expected 'xla', 'cudnn', 'auto' or stage=impl pairs over {sorted(fields)}, "
                                 f"got {spec!r}")
            kw[stage] = value
        return cls(**kw)

    def __str__(self) -> str:
        return ",".join(f"{k}={v}" for k, v in dataclasses.asdict(self).items())


def attention_spec(spec: str) -> str:
    """`Attention.parse`'s check for command lines (argparse `type=`): returns spec unchanged, or raises."""
    Attention.parse(spec, platform="cpu")
    return spec


# attention="auto" on a GPU: per stage (and, in the denoise step, per batch), the faster (docs/BENCHMARKS.md): the
# Pallas vision attention beat cuDNN's at 3, 24 and 192 images (H100, 6 / 4 / 2 % of the tower): it needs no q/k/v
# copies
AUTO_GPU = Attention(vision="pallas", prefix="cudnn", denoise="auto")


@flax.struct.dataclass
class PrefixCache:
    """k, v: per layer (B, P, K, H), post-RoPE (a tuple when unrolled, (L, ...) stacked when scanned); mask (B, P).
    With kernels="pallas", in the kernels' layout (`ops.layout.cache_kv`, `cache_mask`: keys and head dims padded)."""

    k: tuple | jax.Array
    v: tuple | jax.Array
    mask: jax.Array


def encode_images(config: Pi0Config, weights: dict, images: jax.Array, *, unroll: bool = False,
                  attention: Attention = Attention(), kernels: str = "xla") -> jax.Array:
    """images (C, B, H, W, 3) f32 in [-1, 1] for the C active cameras -> (B, C * 256, VLM width), camera-major.
    unroll: the weights' SigLIP blocks are per layer (a list), and so are the layers. kernels: `vision_norm`'s."""
    c, b = images.shape[:2]
    # batch-major (B * C images): a batch sharded over devices stays sharded; merging C-major would all-gather it
    flat = jnp.swapaxes(images, 0, 1).reshape(b * c, *images.shape[2:])
    tokens = vision.encode(config.siglip, weights["img"], flat, dtype=jnp.dtype(config.dtype), unroll=unroll,
                           attention=attention.vision, norm=vision_norm(kernels, b * c))
    return tokens.reshape(b, -1, tokens.shape[-1])


def encode_images_head(config: Pi0Config, weights: dict, images: jax.Array, *, attention: Attention = Attention(),
                       kernels: str = "xla") -> tuple:
    """`encode_images` up to the blocks of weights["img"]["blocks"] (`vision.encode_head`; unrolled) -> (x, f):
    the first of the call's two vision programs where the tower is cut (`runtime.VISION_SPLIT`)."""
    c, b = images.shape[:2]
    flat = jnp.swapaxes(images, 0, 1).reshape(b * c, *images.shape[2:])
    return vision.encode_head(config.siglip, weights["img"], flat, dtype=jnp.dtype(config.dtype),
                              attention=attention.vision, norm=vision_norm(kernels, b * c))


def encode_images_tail(config: Pi0Config, weights: dict, x, f, *, cameras: int, attention: Attention = Attention(),
                       kernels: str = "xla") -> jax.Array:
    """`encode_images` from `encode_images_head`'s (x, f), over the other blocks, the final norm and the projection
    (`vision.encode_tail`) -> (B, C * 256, VLM width). cameras: C, the active cameras."""
    tokens = vision.encode_tail(config.siglip, weights["img"], x, f, dtype=jnp.dtype(config.dtype),
                                attention=attention.vision, norm=vision_norm(kernels, x.shape[0]))
    return tokens.reshape(x.shape[0] // cameras, -1, tokens.shape[-1])


def fill_prefix_cache(config: Pi0Config, weights: dict, image_tokens, image_masks, tokens, token_mask, *,
                      unroll: bool, kernels: str = "xla", attention: Attention = Attention()) -> PrefixCache:
    """image_tokens (B, C*256, D); image_masks (C, B) bool; tokens / token_mask (B, L). The prefix is bidirectional.

    With a fused attention in the prefix or the denoise step (masks by lengths), each element's valid tokens are
    moved to the front first, in order: positions are computed before and travel with them, and attention does
    not depend on the order of its keys, so the cache holds the same keys, in that order, with a run of a mask."""
    dtype = jnp.dtype(config.dtype)
    attention = attention.at_batch(image_tokens.shape[0], suffix_mask=not config.pi05)
    n_img = image_tokens.shape[1] // image_masks.shape[0]
    text = weights["embedding"][tokens]
    text = text * jnp.sqrt(config.paligemma.width).astype(text.dtype)  # sqrt(width) cast to the table dtype first
    x = jnp.concatenate([image_tokens.astype(dtype), text.astype(dtype)], axis=1)
    mask = jnp.concatenate([jnp.repeat(image_masks.T, n_img, axis=1), token_mask], axis=1)
    positions = jnp.cumsum(mask, axis=1) - 1
    kv_len = None
    if "cudnn" in (attention.prefix, attention.denoise):
        order = jnp.argsort(~mask, axis=1, stable=True)
        x = jnp.take_along_axis(x, order[..., None], axis=1)
        positions, mask = (jnp.take_along_axis(a, order, axis=1) for a in (positions, mask))
        if attention.prefix == "cudnn":
            kv_len = jnp.sum(mask, axis=1, dtype=jnp.int32)
    attn_mask = mask[:, None, :] & mask[:, :, None]
    kernel = kernel_cache(kernels, attention, x.shape[0], weights.get("expert"))
    keys = layout.cache_len(x.shape[1]) if kernel else None   # each layer writes its cache padded
    layer = functools.partial(layers.prefix_layer, config.paligemma, positions=positions, mask=attn_mask,
                              kv_len=kv_len, keys=keys)
    _, (k, v) = layers.run_layers(layer, weights["vlm"], x, unroll=unroll)
    if kernel:  # once per call: no step pads
        head_dim = config.paligemma.head_dim
        k, v = (jax.tree.map(lambda a: layout.cache_kv(a, head_dim), c) for c in (k, v))
        mask = layout.cache_mask(mask)
    return PrefixCache(k=k, v=v, mask=mask)


def _dense(p, x):
    return x @ p["kernel"] + p["bias"]


def kernel_cache(kernels: str, attention: Attention, batch: int, expert_weights) -> bool:
    """Whether a program at this batch keeps its prefix cache in the expert kernels' layout (`ops.layout.cache_kv`):
    the Pallas expert's path, or the XLA expert's with the Pallas attention. `attention` resolved (`at_batch`)."""
    return expert_path(kernels, batch, expert_weights) == "pallas" or attention.denoise == "pallas"


def fused_suffix_attention(config: Pi0Config, attention: Attention, kernels: str, batch: int,
                           expert_weights) -> bool:
    """Whether the denoise step at this batch runs the XLA expert with the fused (cuDNN) attention, which reads the
    suffix-first key / value buffers of `suffix_kv`."""
    fused = attention.at_batch(batch, suffix_mask=not config.pi05).denoise == "cudnn"
    return fused and expert_path(kernels, batch, expert_weights) != "pallas"


def suffix_kv(config: Pi0Config, cache: PrefixCache, state_kv: tuple | None = None) -> tuple:
    """The fused attention's keys and values, per layer [S suffix slots | prefix cache] (B, S + P, K, H): made once
    per call, and each step writes its suffix keys into the slots. As a loop carry that is in place; concatenating
    [suffix | cache] copied the whole cache every layer and step (13.4 of 72 ms of π0.5's denoise at B = 64, H200).
    Per layer tuples when unrolled, (L, ...) stacked when scanned, as the cache. state_kv: π0's state keys and
    values (`cached_state`), written into slot 0 here, so that the steps fill slots 1 to S - 1."""
    def slots(c):
        pad = [(0, 0)] * c.ndim
        pad[-3] = (config.suffix_len, 0)
        return jnp.pad(c, pad)

    bufs = tuple(jax.tree.map(slots, c) for c in (cache.k, cache.v))
    if state_kv is None:
        return bufs
    return tuple(jax.tree.map(lambda b, s: b.at[..., :1, :, :].set(s.astype(b.dtype)), buf, kv)
                 for buf, kv in zip(bufs, state_kv))


def cached_state(config: Pi0Config, attention: Attention, kernels: str, batch: int, expert_weights) -> bool:
    """Whether π0's state token runs through the expert once a call, before the denoise loop, instead of as a row of
    every step. Its row attends to the prefix and to itself alone (a causal block of its own, spec §5.4), so its keys
    and values at every layer depend on neither the noisy actions nor the flow time; the steps then run the action
    rows alone, unmasked, as π0.5's. On the XLA expert with XLA's or the fused attention: the Pallas expert and the
    Pallas attention lay their tables out for the row. `attention` resolved or not."""
    if config.pi05 or expert_path(kernels, batch, expert_weights) != "xla":
        return False
    return attention.at_batch(batch, suffix_mask=True).denoise in ("xla", "cudnn")


def _state_kv(config: Pi0Config, weights: dict, cache: PrefixCache, state_token, position, *, unroll: bool):
    """π0's state token (B, D) at `position` (B, 1) through the expert's layers over the cache: its keys and values
    at each layer, (B, 1, K, H) per layer as the cache's own."""
    x = state_token[:, None, :].astype(jnp.dtype(config.dtype))
    own = jnp.ones((x.shape[0], 1, 1), bool)

    def layer(w, x, k, v):
        return layers.suffix_layer(config.action_expert, w, x, position, k, v, cache.mask[:, None, :], own)

    _, (k, v) = layers.run_layers(layer, weights["expert"], x, [cache.k, cache.v], unroll=unroll)
    return k, v


def step_inputs(config: Pi0Config, weights: dict, cache: PrefixCache, state, batch: int, kernels: str,
                attention: Attention, *, unroll: bool) -> tuple[dict, PrefixCache, tuple | None]:
    """(fixed, cache, kv), made once before a denoise loop: `step_invariants`, then what the steps attend to besides
    their own rows: with the fused attention (`fused_suffix_attention`) the prefix cache and `suffix_kv`'s buffers,
    with π0's state in slot 0 when it ran once a call; else the prefix cache, with the state's keys after it, and
    None."""
    fixed = step_invariants(config, weights, cache, state, batch, kernels, attention, unroll=unroll)
    state_kv = fixed["state_kv"]
    if fused_suffix_attention(config, attention, kernels, batch, weights["expert"]):
        return fixed, cache, suffix_kv(config, cache, state_kv)
    if state_kv is None:
        return fixed, cache, None
    k, v = (jax.tree.map(lambda c, s: jnp.concatenate([c, s.astype(c.dtype)], axis=-3), c, s)
            for c, s in zip((cache.k, cache.v), state_kv))
    return fixed, PrefixCache(k=k, v=v, mask=jnp.pad(cache.mask, ((0, 0), (0, 1)), constant_values=True)), None


def step_invariants(config: Pi0Config, weights: dict, cache: PrefixCache, state, batch: int, kernels: str,
                    attention: Attention, *, unroll: bool) -> dict:
    """What every denoise step of one call computes alike, made once before the loop rather than in each step:
    "state" π0's state token (B, D) in f32 (π0.5: None), "state_kv" its keys and values per layer where it runs once
    a call (`cached_state`; else None), "positions" (B, S) and "suffix_mask" (B, S, S) of the rows a step runs (S
    without the state's row where it ran once), "tables" `layers.pallas_tables` for a cache in the kernels' layout
    (`kernel_cache`), else None."""
    ar_state = [] if config.pi05 else [True]   # π0's state token: a causal block of its own before the actions
    s = len(ar_state) + config.action_horizon
    ar = jnp.asarray(ar_state + [True] + [False] * (config.action_horizon - 1))
    suffix_mask = jnp.broadcast_to(pi0.make_attn_mask(jnp.ones((1, s), bool), ar), (batch, s, s))
    positions = jnp.sum(cache.mask, axis=-1, keepdims=True) + jnp.arange(s)[None, :]
    tables = None
    if kernel_cache(kernels, attention.at_batch(batch, suffix_mask=not config.pi05), batch, weights["expert"]):
        xla_expert = expert_path(kernels, batch, weights["expert"]) == "xla"   # the kernel's launch in its layers
        tables = layers.pallas_tables(config.action_expert, positions, cache.mask, suffix_mask,
                                      expert_kernels.blocks_at(batch) if xla_expert else None)
    state_token = None if config.pi05 else _dense(weights["top"]["state_proj"], state)
    state_kv = None
    if cached_state(config, attention, kernels, batch, weights["expert"]):
        state_kv = _state_kv(config, weights, cache, state_token, positions[:, :1], unroll=unroll)
        positions, suffix_mask = positions[:, 1:], suffix_mask[:, 1:, 1:]
    return {"state": state_token, "state_kv": state_kv, "positions": positions, "suffix_mask": suffix_mask,
            "tables": tables}


def step_velocity(config: Pi0Config, weights: dict, sched: dict, step: jax.Array, cache: PrefixCache, fixed: dict,
                  x_t, kv, *, unroll: bool, attention: Attention, kernels: str, frozen: jax.Array | None) -> tuple:
    """One denoise step's velocity v(x_t, t_step) -> (v, kv). cache, kv: `step_inputs`'; kv, the suffix-first
    buffers of `suffix_kv` (exactly when `fused_suffix_attention`, else None), comes back with this step's suffix keys
    written in. fixed: `step_invariants`. frozen (B, H) or None: committed actions, at flow time 0."""
    dtype = jnp.dtype(config.dtype)
    top, b = weights["top"], x_t.shape[0]
    attention = attention.at_batch(b, suffix_mask=not config.pi05)

    def at_step(key):   # the schedule row of `key` for every action: (1, 1, ...) or, with `frozen`, (B, H, ...)
        now = sched[key][step][None, None]
        if frozen is None:
            return now
        where = frozen.reshape(frozen.shape + (1,) * (now.ndim - 2))
        return jnp.where(where, sched["committed"][key][0][None, None], now)

    if config.pi05:
        x = _dense(top["action_in_proj"], x_t)  # f32: the projections run in the promoted dtype
        mods = (at_step("mods_attn"), at_step("mods_ffw"))  # (B or 1, H or 1, L, 3D) each
    else:
        if FOLD_ACTION_IN:   # the in-projection inside the time MLP's first product (`weights.fold_action_in`)
            h = _dense(top["action_time_in"], x_t) + at_step("time_in")
        else:
            w_in = top["action_time_mlp_in"]["kernel"]
            h = _dense(top["action_in_proj"], x_t) @ w_in[: config.action_expert.width].astype(jnp.float32)
            h = h + at_step("time_in")
        x = _dense(top["action_time_mlp_out"], jax.nn.swish(h))
        if fixed["state_kv"] is None:
            x = jnp.concatenate([fixed["state"][:, None, :], x], axis=1)
        mods = None
    x = x.astype(dtype)
    s = x.shape[1]
    positions, suffix_mask = fixed["positions"], fixed["suffix_mask"]
    final_mod = at_step("mods_final") if config.pi05 else None

    if expert_path(kernels, b, weights["expert"]) == "pallas":
        if frozen is not None:
            raise ValueError("committed actions (training-time action conditioning) run on the XLA expert path")
        x = layers.suffix_layers_pallas(config.action_expert, weights["expert"], x, positions, cache.k, cache.v,
                                        cache.mask, suffix_mask, None if mods is None else tuple(m[0, 0] for m in mods),
                                        tables=fixed["tables"])
        return _top(config, weights, final_mod, x), kv

    kv_len = None
    if attention.denoise == "pallas":   # the kernel's masks: prefix (B, Pp), suffix (B Sp, Sp), int32
        prefix_mask, suffix_mask = fixed["tables"][2:]
    else:
        prefix_mask = jnp.broadcast_to(cache.mask[:, None, :], (b, s, cache.mask.shape[1]))
    slot = config.suffix_len - s   # 1 where π0's state ran once a call and holds the suffix's first slot
    if attention.denoise == "cudnn":   # no suffix mask: the action rows, and π0.5's, see every suffix key
        if not (config.pi05 or slot):
            raise ValueError("the fused denoise attention takes π0's state token once a call (`cached_state`)")
        kv_len = (config.suffix_len + jnp.sum(cache.mask, axis=-1)).astype(jnp.int32)

    def layer(w, x, k, v, *mod):
        m = None if mods is None else mod
        x, k, v = layers.suffix_layer(config.action_expert, w, x, positions, k, v, prefix_mask, suffix_mask, m,
                                      kv_len, kernel=attention.denoise == "pallas", slot=slot)
        return (x, k, v) if kv_len is not None else (x,)

    per_layer = [cache.k, cache.v] if kv is None else list(kv)
    if mods is not None:   # layer axis first: (L, B or 1, H or 1, 3D)
        per_layer += [_by_layer(jnp.moveaxis(m, 2, 0), unroll) for m in mods]
    x, outs = layers.run_layers(layer, weights["expert"], x, per_layer, unroll=unroll)
    return _top(config, weights, final_mod, x), (None if kv is None else tuple(outs))


def _top(config, weights, final_mod, x):
    """The expert's final norm (π0.5: adaRMS with `final_mod`) and the action output projection."""
    if config.pi05:
        x, _ = layers.rms_norm(x, mod=final_mod)
    else:
        x, _ = layers.rms_norm(x, weights["final_norm_1"])
    return _dense(weights["top"]["action_out_proj"], x[:, -config.action_horizon:])


def _by_layer(x, unroll):
    return tuple(x[i] for i in range(x.shape[0])) if unroll else x


def denoise(config: Pi0Config, weights: dict, sched: dict, cache: PrefixCache, state, noise, *, num_steps: int,
            unroll: bool, unroll_steps: bool, attention: Attention = Attention(), kernels: str = "xla",
            committed: jax.Array | None = None, num_committed: jax.Array | None = None,
            peel_first: bool = False) -> jax.Array:
    """num_steps Euler steps from noise (t = 1) to actions (t = 0): a fixed trip count for a Python int, a while
    loop for a traced int32 (then `sched` must hold at least num_steps entries). With `committed` (B, H, action_dim)
    and `num_committed` d (B,): actions i < d are given, clean at every step and returned as given (training-time
    action conditioning, as `pi0.sample_actions`). peel_first: the first step outside the loop, in the program's
    own sequence, where its layer i depends on the cache's layer i alone (not on the whole prefix fill)."""
    if not isinstance(num_steps, int):
        unroll_steps = None
    x = noise.astype(jnp.float32)
    frozen = None
    if num_committed is not None:
        frozen = pi0.committed_mask(config.action_horizon, num_committed)
        x = jnp.where(frozen[..., None], committed.astype(jnp.float32), x)

    fixed, cache, kv = step_inputs(config, weights, cache, state, x.shape[0], kernels, attention, unroll=unroll)
    step = _euler_step(config, weights, sched, cache, fixed, num_steps, unroll=unroll, attention=attention,
                       kernels=kernels, frozen=frozen)
    carry, first = (x, kv), 0
    if peel_first and isinstance(num_steps, int) and num_steps > 0:
        carry, first = step(0, carry), 1
    return jax.lax.fori_loop(first, num_steps, step, carry, unroll=unroll_steps)[0]


def _euler_step(config, weights, sched, cache, fixed, num_steps, *, unroll, attention, kernels, frozen=None):
    """The loop body of `denoise`: (i, (x_t, kv)) -> (x_t + dt v, kv), dt = -1 / num_steps."""
    dt = -1.0 / num_steps
    if not isinstance(num_steps, int):
        dt = jnp.asarray(dt, jnp.float32)   # f32 as the reference's traced dt

    def step(i, carry):   # the suffix-first buffers ride in the carry, so each step fills their slots in place
        x_t, kv = carry
        v, kv = step_velocity(config, weights, sched, i, cache, fixed, x_t, kv, unroll=unroll, attention=attention,
                              kernels=kernels, frozen=frozen)
        x_next = x_t + dt * v  # dt * v in v's dtype, then promoted to f32: as the reference
        return (x_next if frozen is None else jnp.where(frozen[..., None], x_t, x_next)), kv

    return step


def prefix_first_step(config: Pi0Config, weights: dict, sched: dict, image_tokens, image_masks, tokens, token_mask,
                      state, noise, *, num_steps: int, unroll: bool, attention: Attention = Attention(),
                      kernels: str = "xla") -> tuple:
    """The call's second program where its denoise loop is a program of its own (`denoise_rest`): the prefix cache
    and the first denoise step, whose layer i waits for the cache's layer i alone. -> (x after the first step, the
    suffix-first buffers or None, the cache and the step invariants the other steps read: `denoise_rest`'s inputs)."""
    cache = fill_prefix_cache(config, weights, image_tokens, image_masks, tokens, token_mask, unroll=unroll,
                              kernels=kernels, attention=attention)
    fixed, cache, kv = step_inputs(config, weights, cache, state, noise.shape[0], kernels, attention, unroll=unroll)
    step = _euler_step(config, weights, sched, cache, fixed, num_steps, unroll=unroll, attention=attention,
                       kernels=kernels)
    x, kv = step(0, (noise.astype(jnp.float32), kv))
    return x, kv, cache, fixed


def denoise_rest(config: Pi0Config, weights: dict, sched: dict, x, kv, cache: PrefixCache, fixed: dict, *,
                 num_steps: int, unroll: bool, unroll_steps: bool, attention: Attention = Attention(),
                 kernels: str = "xla") -> jax.Array:
    """Denoise steps 1 .. num_steps - 1 from `prefix_first_step`'s outputs: the call's third program."""
    step = _euler_step(config, weights, sched, cache, fixed, num_steps, unroll=unroll, attention=attention,
                       kernels=kernels)
    return jax.lax.fori_loop(1, num_steps, step, (x, kv), unroll=unroll_steps)[0]


def prefix_denoise(config: Pi0Config, weights: dict, sched: dict, image_tokens, image_masks, tokens, token_mask,
                   state, noise, *, num_steps: int, unroll: bool, unroll_steps: bool,
                   attention: Attention = Attention(), kernels: str = "xla", peel_first: bool = False) -> jax.Array:
    """The prefix cache from `encode_images`' tokens, then the denoise loop: a call's second program."""
    cache = fill_prefix_cache(config, weights, image_tokens, image_masks, tokens, token_mask, unroll=unroll,
                              kernels=kernels, attention=attention)
    return denoise(config, weights, sched, cache, state, noise, num_steps=num_steps, unroll=unroll,
                   unroll_steps=unroll_steps, attention=attention, kernels=kernels, peel_first=peel_first)


def infer(config: Pi0Config, weights: dict, sched: dict, images, image_masks, tokens, token_mask, state, noise, *,
          num_steps: int, unroll: bool, unroll_steps: bool, attention: Attention = Attention(),
          kernels: str = "xla") -> jax.Array:
    """The fused program: vision -> prefix cache -> denoise, one XLA executable (the pipeline inside a larger
    program, as the simulator's rollout; the engine's own call runs `encode_images` and `prefix_denoise`)."""
    image_tokens = encode_images(config, weights, images, unroll=unroll, attention=attention, kernels=kernels)
    return prefix_denoise(config, weights, sched, image_tokens, image_masks, tokens, token_mask, state, noise,
                          num_steps=num_steps, unroll=unroll, unroll_steps=unroll_steps, attention=attention,
                          kernels=kernels)
