"""`Engine`: ahead-of-time compiled, static-shape programs for π0 / π0.5 inference.

One executable per (stage, batch, num_steps, active cameras, prompt bucket); the config (preset, dtype) is fixed per
Engine. Executables are kept, compiled ahead of time (`jit(...).lower(...).compile()`), so an input of the wrong
shape is an error, never a silent recompile. With a cache directory, a second process starts warm: the programs come
back from `store.ProgramStore` without tracing, and anything else compiled from XLA's persistent cache.

A call (`sample_actions`) is two programs, dispatched one after the other with no host round trip between them:
the vision tower, then the prefix fill and the denoise loop (three where the first denoise step overlaps the prefix
fill, and the tower itself two at full size: `Engine.call_stages`). Each takes only its own weights (`stage_tree`):
the host pays about 1.2-1.7 µs per buffer a call takes before its first kernel runs (about 0.9 µs of it jax's
checks, which `dispatch.Dispatch` skips for weights it was given before), and each program's dispatch runs while
the GPU runs the one before. And the vision program gets its own GEMM library (`matmul.compiler_options`).
At batch 1 and 2 on a GPU the second program runs its first denoise step beside the prefix fill (`Engine.overlaps`).
On an H200, π0 at B = 1 in a loop of calls: 16.1 ms against 17.2 ms for the one fused program (`infer`, kept for
comparison and for callers that embed the pipeline in a larger program); docs/BENCHMARKS.md, "The call as two
programs", which also gives a round-robin where it was slower.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import time
import warnings
from collections.abc import Sequence
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from pi0_jax import pi0
from pi0_jax.config import IMAGE_KEYS, Pi0Config
from pi0_jax.engine import dispatch as dispatch_lib, paths, programs, weights as weights_lib
from pi0_jax.engine.store import ProgramStore, shapes
from pi0_jax.ops import matmul

PROMPT_BUCKETS = (16, 32, 48, 64, 96, 128, 160, 200)
# The engine weights (top-level keys of `weights.prepare`'s tree) each program reads; "infer" is the fused program
STAGE_WEIGHTS = {"encode_images": ("img",), "vision_head": ("img",), "vision_tail": ("img",),
                 "fill_prefix_cache": ("embedding", "vlm"),
                 "denoise": ("expert", "top", "final_norm_1"),
                 "prefix_denoise": ("embedding", "vlm", "expert", "top", "final_norm_1"),
                 "prefix_first_step": ("embedding", "vlm", "expert", "top", "final_norm_1"),
                 "denoise_rest": ("expert", "top", "final_norm_1"),
                 "infer": ("img", "embedding", "vlm", "expert", "top", "final_norm_1")}
STAGES = tuple(STAGE_WEIGHTS)
VISION_STAGES = ("encode_images", "vision_head", "vision_tail")
PREFIX_STAGES = ("fill_prefix_cache", "prefix_first_step")   # the prefix fill, with at most the first step


def library_keywords(stage: str, batch: int) -> dict:
    """`matmul.library`'s keywords for a stage's program (the engine's and `Policy`'s alike): the vision tower's
    programs, and the prefix fill's without the denoise loop (`PREFIX_STAGES`)."""
    return {"vision_tower": stage in VISION_STAGES, "prefix_batch": batch if stage in PREFIX_STAGES else None}

# The call's vision tower as two programs, the first with this many blocks (`Engine.splits_vision`): the host
# dispatches the second while the GPU runs the first, and the first, with a third of the tower's weight buffers,
# starts sooner. π0's call at B = 1 took 14.03 against 15.18 ms (H200, one process; 6 blocks 14.19, 13 blocks
# 14.08, 3 blocks 15.20: the first program then ends before the second is dispatched; docs/BENCHMARKS.md, session 46)
VISION_SPLIT = 9


def splits_vision(config: Pi0Config, unroll: bool) -> bool:
    """Whether a call runs the vision tower as two programs (`VISION_SPLIT`): with unrolled layers, where the tower
    has more blocks than the first program takes."""
    return unroll and 0 < VISION_SPLIT < config.siglip.depth


def stage_tree(weights: dict, stage: str, split: int | None = None) -> dict:
    """The engine weights a stage's program takes: `STAGE_WEIGHTS`' keys; the vision tower's two programs take
    its blocks before `split` (None: `VISION_SPLIT`) with the patch embedding ("vision_head"), or the others with
    the final norm and the projection ("vision_tail"), and both the blocks' one table of vectors."""
    if stage in ("vision_head", "vision_tail"):
        img, split = weights["img"], VISION_SPLIT if split is None else split
        if stage == "vision_head":
            return {"img": {"embedding": img["embedding"], "pos": img["pos"], "blocks": img["blocks"][:split],
                            "vectors": img["vectors"]}}
        return {"img": {"blocks": img["blocks"][split:], "vectors": img["vectors"], "norm": img["norm"],
                        "head": img["head"]}}
    return {k: weights[k] for k in STAGE_WEIGHTS[stage] if k in weights}


def run_call(progs: Sequence, split_vision: bool, weights: dict, sched, packed: tuple, noise: jax.Array):
    """A call's programs (`Engine.call_programs`, or callables taking the same arguments) on `pack`'s arrays, each
    dispatched while the GPU runs the one before: the vision tower (two programs where `split_vision`), then the
    prefix fill and the denoise loop (one program, or the first step's and the loop's)."""
    images, image_masks, tokens, token_mask, state = packed
    if split_vision:
        head, tail, act, *rest = progs
        image_tokens = tail(weights, *head(weights, images))
    else:
        vision, act, *rest = progs
        image_tokens = vision(weights, images)
    out = act(weights, sched, image_tokens, image_masks, tokens, token_mask, state, noise)
    return rest[0](weights, sched, *out) if rest else out


@dataclasses.dataclass(frozen=True)
class Program:
    """A compiled stage program and the engine weights it reads: called with the engine's whole weights tree, it
    hands the program only those (`stage_tree` of its stage: under the top-level `keys`), so the host never
    dispatches a buffer the program does not read; and without jax's checks of weights it was given before
    (`dispatch.Dispatch`)."""

    compiled: jax.stages.Compiled
    keys: tuple[str, ...]
    stage: str
    split: int   # the vision tower's first program's blocks (`stage_tree`)
    dispatch: dispatch_lib.Dispatch = dataclasses.field(init=False, repr=False, compare=False)

    def __post_init__(self):
        object.__setattr__(self, "dispatch", dispatch_lib.Dispatch(self.compiled))

    def __call__(self, weights: dict, *args):
        return self.dispatch(stage_tree(weights, self.stage, self.split), *args)

    def as_text(self) -> str:
        return self.compiled.as_text()


def default_cache_dir() -> Path:
    return Path(os.environ.get("PI0_JAX_CACHE_DIR", Path.home() / ".cache" / "pi0_jax" / "xla"))


# jax's GPU allocators under which the engine's calls run much slower (π0's `Policy.infer` at B = 1, 10 steps on an
# H200: 14.6 ms with the default BFC allocator): "vmm" moves every program's buffers each call, so XLA re-records
# their CUDA graphs first (16-19 ms); "platform" allocates and frees each buffer through the driver (26 ms; CUDA's
# free synchronises with the device, the likely cause, not traced). docs/BENCHMARKS.md, session 50.
SLOW_ALLOCATORS = {"vmm": "16-19 ms", "platform": "26 ms"}


def check_allocator(platform: str | None = None) -> str | None:
    """Warn (once per process and value, `warnings`' default) where `XLA_PYTHON_CLIENT_ALLOCATOR` names an allocator
    the engine's calls are slow under, on a GPU; -> the allocator warned about, or None."""
    allocator = os.environ.get("XLA_PYTHON_CLIENT_ALLOCATOR", "").strip().lower()
    if allocator not in SLOW_ALLOCATORS or (platform or jax.default_backend()) != "gpu":
        return None
    warnings.warn(f"XLA_PYTHON_CLIENT_ALLOCATOR={allocator}: the engine's calls are much slower under this allocator "
                  f"(π0 Policy.infer on an H200: {SLOW_ALLOCATORS[allocator]} against 14.6 ms with jax's default; "
                  "pi0-jax docs/BENCHMARKS.md, session 50). Unset it unless you need it.", RuntimeWarning,
                  stacklevel=3)
    return allocator


def enable_compilation_cache(path: str | os.PathLike | None = None) -> Path:
    """Turn on XLA's persistent compilation cache at `path` (default: $PI0_JAX_CACHE_DIR or ~/.cache/pi0_jax/xla)."""
    path = Path(path) if path is not None else default_cache_dir()
    path.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path


def prompt_bucket(valid_len: int, max_len: int) -> int:
    """The smallest bucket that holds `valid_len` tokens (prompts are right-padded, so a prefix slice keeps them)."""
    for b in PROMPT_BUCKETS:
        if valid_len <= b <= max_len:
            return b
    return max_len


def engine_weights(config: Pi0Config, params: dict, *, unroll: bool = True, kernels: str = "auto") -> dict:
    """The programs' weights (`weights.prepare`, on device); unroll: per-layer buffers for unrolled layers.
    kernels: only checked here ("pallas" needs unrolled, unquantised expert layers; their layout is made inside
    the programs)."""
    def build(params):   # one program: per-layer slices taken eagerly would each compile and dispatch apart
        w = weights_lib.prepare(config, params)
        if unroll:
            depth = config.paligemma.depth
            w["vlm"] = weights_lib.unstack(w["vlm"], depth)
            w["expert"] = weights_lib.unstack(w["expert"], depth)
            w["img"]["blocks"] = weights_lib.unstack(w["img"]["blocks"], config.siglip.depth)
        return w

    w = jax.jit(build)(params)
    if kernels == "pallas":
        if not unroll:
            raise ValueError("kernels='pallas' needs unroll=True")
        if paths.is_quantised(w["expert"]):
            raise ValueError("kernels='pallas' needs unquantised expert weights")
    return w


class Engine:
    """Compiled inference for one model.

    >>> engine = Engine(config, params)
    >>> actions = engine.sample_actions(observation, noise, num_steps=10)   # picks cameras / bucket, compiles once

    unroll: layers unrolled (separate per-layer weight buffers) instead of `lax.scan`; unroll_steps: the denoise
    loop unrolled; attention: each stage's attention (`paths.Attention.parse`: "xla", "cudnn", "auto" = the
    faster per stage on a GPU, XLA elsewhere, or "vision=cudnn,prefix=cudnn,denoise=xla"); kernels: the action
    expert's layers as XLA ops ("xla"), as the fused Pallas kernels of `pi0_jax.ops` ("pallas": Triton on GPU,
    interpret mode on CPU; needs unrolled layers and unquantised expert weights), or "auto" (per batch size,
    `paths.expert_path`: the kernels at B <= 2 on a GPU, XLA otherwise); the same choice for SigLIP's LayerNorm
    (`paths.vision_norm`: "auto" is the kernel on a GPU from 24 images a call); gemm: the library of XLA's GEMMs on a
    GPU (`pi0_jax.ops.matmul.compiler_options`: "auto", cuBLAS in the vision program and XLA's autotuned choice in
    the others; "xla" or "cublas" in every program); cache_dir: where compiled programs are kept (`store`, beside
    XLA's persistent cache; None: $PI0_JAX_CACHE_DIR or ~/.cache/pi0_jax/xla, False: nothing kept); overlap: the
    first denoise step beside the prefix fill in the call's second program (`overlaps`: "auto" at batch 1 and 2 on a
    GPU, where the expert runs its Pallas kernels, "on", "off").
    """

    def __init__(self, config: Pi0Config, params: dict, *, unroll: bool = True, unroll_steps: bool = False,
                 attention: str | paths.Attention = "auto", kernels: str = "auto",
                 gemm: str = "auto", cache_dir: str | os.PathLike | None | bool = None, overlap: str = "auto"):
        self.attention = paths.Attention.parse(attention, dtype=config.dtype)
        self.kernels = paths.check_kernels(kernels)
        self.gemm = matmul.check_gemm(gemm)
        self.overlap = paths.check_overlap(overlap)
        check_allocator()
        if cache_dir is not False:
            self.cache_dir = enable_compilation_cache(None if cache_dir in (None, True) else cache_dir)
        self.store = ProgramStore(self.cache_dir / "programs" if cache_dir is not False else None)
        self.config = config
        self.unroll = unroll
        self.unroll_steps = unroll_steps
        self._schedule_params = weights_lib.schedule_params(config, params)  # not the whole tree: it is 6 GB
        self.weights = engine_weights(config, params, unroll=unroll, kernels=kernels)
        self.vision_split = VISION_SPLIT if splits_vision(config, unroll) else 0
        self._schedules: dict[int, dict] = {}
        self._executables: dict[tuple, jax.stages.Compiled] = {}
        self._calls: dict[tuple, tuple] = {}   # `call_programs` by shape
        self.compile_seconds: dict[tuple, float] = {}

    # -- schedules and executables ------------------------------------------------------------------------------
    def schedule(self, num_steps: int) -> dict:
        if num_steps not in self._schedules:
            fn = jax.jit(functools.partial(weights_lib.precompute_schedule, self.config), static_argnums=1)
            self._schedules[num_steps] = fn(self._schedule_params, num_steps)
        return self._schedules[num_steps]

    @property
    def num_compiled(self) -> int:
        return len(self._executables)

    def kernels_for(self, batch: int) -> str:
        """The expert's path at this batch size: "xla" or "pallas" (`paths.expert_path`)."""
        return paths.expert_path(self.kernels, batch, self.weights["expert"])

    def overlaps(self, batch: int) -> bool:
        """Whether the call's second program at this batch runs its first denoise step beside the prefix fill
        (`paths.first_step_overlap`)."""
        return paths.first_step_overlap(self.overlap, self.kernels, batch, self.weights["expert"])

    def executable(self, stage: str, batch: int, num_steps: int, cameras: Sequence[str], prompt_len: int) -> Program:
        """The compiled program for a stage and static shape (compiled on first use, then kept). Call it with the
        engine's weights: `Program` passes on only the stage's own."""
        key = self.key(stage, batch, num_steps, cameras, prompt_len)
        if key not in self._executables:
            start = time.perf_counter()
            weights = self.stage_weights(stage)
            fn, args = self._stage(stage, shapes(weights), batch, num_steps, cameras, prompt_len)
            options = paths.overlap_options(
                matmul.compiler_options(weights, self.gemm, **library_keywords(stage, batch)),
                stage == "prefix_first_step" or (stage == "prefix_denoise" and self.overlaps(batch)))
            # everything the traced program depends on besides its arguments and options
            parts = (key, repr(self.config), self.unroll, self.unroll_steps, repr(self.attention), self.kernels,
                     self.gemm, self.overlap, self.vision_split)
            self._executables[key] = Program(self.store.compile(stage, parts, fn, args, options), tuple(weights),
                                             stage, self.vision_split)
            self.compile_seconds[key] = time.perf_counter() - start
        return self._executables[key]

    def stage_weights(self, stage: str) -> dict:
        """The engine weights a stage's program takes (`stage_tree`)."""
        return stage_tree(self.weights, stage, self.vision_split)

    def gemm_library(self, stage: str, batch: int) -> str:
        """The GEMM library of a stage's program at this batch on this device: "xla" (XLA's choice) or "cublas"."""
        return matmul.library(self.stage_weights(stage), self.gemm, **library_keywords(stage, batch))

    @staticmethod
    def key(stage: str, batch: int, num_steps: int, cameras: Sequence[str], prompt_len: int) -> tuple:
        """The key of a stage's program in `compile_seconds` (the shapes it depends on)."""
        if stage not in STAGE_WEIGHTS:
            raise ValueError(f"unknown stage {stage!r}; stages: {STAGES}")
        if stage in (*VISION_STAGES, "fill_prefix_cache"):
            num_steps = 0  # these programs do not depend on the step count
        if stage in VISION_STAGES:
            prompt_len = 0
        return (stage, batch, num_steps, tuple(cameras), prompt_len)

    def call_stages(self, batch: int, num_steps: int) -> tuple[str, ...]:
        """The stages of a call's programs, in order: the vision tower (as two programs where `splits_vision`), then
        the prefix fill with the denoise loop; where the first denoise step runs beside the prefix fill (`overlaps`)
        and other steps follow, the prefix fill with that step, then the loop as a program of its own. XLA's command
        buffers run the overlap's program in their CONCURRENT order, and there a while loop's iterations were 20-25 µs
        apart; in a program of its own the loop keeps XLA's default order (docs/BENCHMARKS.md, "The denoise loop as a
        program of its own")."""
        vision = ("vision_head", "vision_tail") if self.splits_vision() else ("encode_images",)
        if self.overlaps(batch) and num_steps > 1:
            return *vision, "prefix_first_step", "denoise_rest"
        return *vision, "prefix_denoise"

    def splits_vision(self) -> bool:
        """Whether the call runs the vision tower as two programs (`splits_vision`, fixed when the Engine is made)."""
        return self.vision_split > 0

    def call_programs(self, batch: int, num_steps: int, cameras: Sequence[str], prompt_len: int) -> tuple:
        """The programs of a call (`sample_actions`), in `call_stages`' order; chosen once per shape, then kept. The
        choice walks the expert's weights (`overlaps`), which took the host 0.12 ms (a CPU core; 0.4 ms under the
        profiler) before every call's first kernel until session 47 (docs/BENCHMARKS.md, "The call's edges")."""
        key = (batch, num_steps, tuple(cameras), prompt_len)
        if key not in self._calls:
            self._calls[key] = tuple(self.executable(stage, batch, num_steps, cameras, prompt_len)
                                     for stage in self.call_stages(batch, num_steps))
        return self._calls[key]

    def _stage(self, stage, w, batch, num_steps, cameras, prompt_len):
        cfg, s = self.config, self.config.image_size
        f32, dtype = jnp.float32, jnp.dtype(cfg.dtype)
        spec = jax.ShapeDtypeStruct
        c = len(cameras)
        images = spec((c, batch, s, s, 3), f32)
        image_masks = spec((c, batch), jnp.bool_)
        tokens, token_mask = spec((batch, prompt_len), jnp.int32), spec((batch, prompt_len), jnp.bool_)
        state = spec((batch, cfg.action_dim), f32)
        noise = spec((batch, cfg.action_horizon, cfg.action_dim), f32)
        sched = jax.tree.map(lambda x: spec(x.shape, x.dtype), self.schedule(num_steps)) if num_steps else None
        kw = {"unroll": self.unroll, "attention": self.attention}
        denoise_kw = {**kw, "num_steps": num_steps, "unroll_steps": self.unroll_steps, "kernels": self.kernels}
        if stage == "encode_images":
            return functools.partial(programs.encode_images, cfg, **kw, kernels=self.kernels), (w, images)
        vision_kw = {"attention": self.attention, "kernels": self.kernels}
        if stage == "vision_head":
            return functools.partial(programs.encode_images_head, cfg, **vision_kw), (w, images)
        if stage == "vision_tail":   # it takes the first vision program's outputs (read off it)
            outs = shapes(self.executable("vision_head", batch, num_steps, cameras, prompt_len).compiled.out_info)
            return functools.partial(programs.encode_images_tail, cfg, cameras=c, **vision_kw), (w, *outs)
        image_tokens = spec((batch, c * cfg.siglip.num_patches, cfg.paligemma.width), dtype)
        # the prefix program alone has no expert weights to choose the cache's layout by: it is given the choice
        fill = functools.partial(programs.fill_prefix_cache, cfg, **kw, kernels=self.kernels_for(batch))
        if stage == "fill_prefix_cache":
            return fill, (w, image_tokens, image_masks, tokens, token_mask)
        if stage == "denoise":
            cache = jax.eval_shape(fill, shapes(self.stage_weights("fill_prefix_cache")), image_tokens, image_masks,
                                   tokens, token_mask)
            fn = functools.partial(programs.denoise, cfg, **denoise_kw)
            return fn, (w, sched, cache, state, noise)
        if stage == "prefix_denoise":
            fn = functools.partial(programs.prefix_denoise, cfg, **denoise_kw, peel_first=self.overlaps(batch))
            return fn, (w, sched, image_tokens, image_masks, tokens, token_mask, state, noise)
        if stage == "prefix_first_step":
            fn = functools.partial(programs.prefix_first_step, cfg, **kw, num_steps=num_steps, kernels=self.kernels)
            return fn, (w, sched, image_tokens, image_masks, tokens, token_mask, state, noise)
        if stage == "denoise_rest":   # it takes the first step's program's outputs (read off it, not traced again)
            outs = shapes(self.executable("prefix_first_step", batch, num_steps, cameras, prompt_len).compiled.out_info)
            return functools.partial(programs.denoise_rest, cfg, **denoise_kw), (w, sched, *outs)
        fn = functools.partial(programs.infer, cfg, **denoise_kw)
        return fn, (w, sched, images, image_masks, tokens, token_mask, state, noise)


    # -- inputs -----------------------------------------------------------------------------------------------------
    def plan(self, obs: pi0.Observation) -> tuple[tuple[str, ...], int]:
        """Active cameras (valid for some element) and the prompt bucket, read from the host-side masks."""
        keys = IMAGE_KEYS[: self.config.num_cameras]
        cameras = tuple(k for k in keys if np.asarray(obs.image_masks[k]).any())
        valid = int(np.asarray(obs.tokenized_prompt_mask).sum(axis=1).max(initial=0))
        return cameras, prompt_bucket(valid, obs.tokenized_prompt.shape[1])

    def pack(self, obs: pi0.Observation, cameras: Sequence[str], prompt_len: int):
        """pi0.Observation -> the arrays the programs take (cameras stacked, prompt cut to its bucket)."""
        mask = np.asarray(obs.tokenized_prompt_mask)
        if mask[:, prompt_len:].any():
            raise ValueError(f"valid prompt tokens beyond the bucket of {prompt_len} (prompts must be right-padded)")
        images = jnp.stack([jnp.asarray(obs.images[k], jnp.float32) for k in cameras])
        image_masks = jnp.stack([jnp.asarray(obs.image_masks[k], bool) for k in cameras])
        return (images, image_masks, jnp.asarray(obs.tokenized_prompt[:, :prompt_len], jnp.int32),
                jnp.asarray(mask[:, :prompt_len]), jnp.asarray(obs.state, jnp.float32))

    # -- running ------------------------------------------------------------------------------------------------------
    def sample_actions(self, obs: pi0.Observation, noise: jax.Array, num_steps: int = 10) -> jax.Array:
        """Actions for a batch of observations (noise is not consumed: the programs donate no input). A caller that
        keeps the last actions on the device while it calls again moves the call's buffers, and XLA then updates
        the nodes of its CUDA graphs before launching them (π0: about 500 a call against 0-13, 0.05-1.3 ms on an
        H100, docs/BENCHMARKS.md, session 69): take them to the host, as `Policy.infer` does, or drop them first."""
        cameras, prompt_len = self.plan(obs)
        return self.sample_packed(self.pack(obs, cameras, prompt_len), jnp.asarray(noise, jnp.float32), num_steps,
                                  cameras, prompt_len)

    def sample_packed(self, packed: tuple, noise: jax.Array, num_steps: int, cameras: Sequence[str],
                      prompt_len: int) -> jax.Array:
        """`sample_actions` on `pack`'s arrays: the call's programs (`call_stages`), each dispatched while the GPU
        runs the one before (no host round trip between them). noise (B, H, action_dim) f32."""
        progs = self.call_programs(noise.shape[0], num_steps, cameras, prompt_len)
        return run_call(progs, progs[0].stage == "vision_head", self.weights, self.schedule(num_steps), packed, noise)

    def run_stages(self, obs: pi0.Observation, noise: jax.Array, num_steps: int = 10):
        """The three stage programs one after another (for per-stage timing); returns (image_tokens, cache, actions)."""
        cameras, prompt_len = self.plan(obs)
        images, image_masks, tokens, token_mask, state = self.pack(obs, cameras, prompt_len)
        b = noise.shape[0]
        image_tokens = self.executable("encode_images", b, num_steps, cameras, prompt_len)(self.weights, images)
        cache = self.executable("fill_prefix_cache", b, num_steps, cameras, prompt_len)(
            self.weights, image_tokens, image_masks, tokens, token_mask)
        actions = self.executable("denoise", b, num_steps, cameras, prompt_len)(
            self.weights, self.schedule(num_steps), cache, state, jnp.asarray(noise, jnp.float32))
        return image_tokens, cache, actions
