"""`Policy.infer(obs) -> {"actions", "policy_timing"}`, like openpi's `Policy.infer` with its LIBERO transforms, on
the compiled engine.

One pipeline serves every caller (`Policy.infer` / `infer_batch`, the policy server, the simulator's rollout):

  host    `pi0_jax.observation.validate`: keys, cameras, dtypes, shapes and finiteness checked, the prompt tokenised
          (cached per prompt string; π0.5 with the state in the prompt tokenises per call);
  device  `pipeline.PolicyCore.program`, compiled per shape bucket (batch, camera shapes, prompt bucket): the input
          transforms, the engine's vision -> prefix cache -> denoise, the actions un-normalised. `Policy` runs it as
          two programs, `PolicyCore.encode` (the vision tower) then `PolicyCore.act` (where its first denoise step
          overlaps the prefix fill, `act_first` then `act_rest`), as `Engine.sample_actions` does; the simulator
          embeds `program` whole.

This module holds the host side: checks, batching into compiled batch buckets, the compiled calls on disk
(`engine.store`), and loading a checkpoint with its tokenizer and norm stats.
"""

from __future__ import annotations

import functools
import os
import threading
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from pi0_jax import normalize as _norm
from pi0_jax import pi0
from pi0_jax.config import Pi0Config
from pi0_jax.engine import enable_compilation_cache, paths, prompt_bucket, runtime
from pi0_jax.engine.runtime import STAGE_WEIGHTS
from pi0_jax.engine.store import ProgramStore, shapes
from pi0_jax.observation import DEFAULT_OPTIONAL_CAMERAS, ObservationError, Prepared, Validator
from pi0_jax.ops import matmul
from pi0_jax.pipeline import PolicyCore
from pi0_jax.tokenizer import PaligemmaTokenizer

__all__ = ["ObservationError", "Policy", "Prepared", "find_tokenizer"]

TOKENIZER_FILE = "tokenizer.model"


def _to_host(fn):
    """fn with its result in pinned host memory: the call's last program copies the actions back itself. A copy
    asked for after the call (`np.asarray` of a device array) took 0.44 ms of a 14.2 ms call on an H200; this way
    `Policy.infer` was 0.17-0.23 ms faster (docs/BENCHMARKS.md, "π0 under 14 ms, the call's host times, and
    `Policy`'s copy back")."""
    @functools.wraps(fn)
    def wrapped(*args):
        return jax.device_put(fn(*args), jax.memory.Space.Host)
    return wrapped


def _stack(rows: list) -> np.ndarray:
    """The rows as one batch: a view of a single row (no copy of its frames before the call's own transfer)."""
    return rows[0][None] if len(rows) == 1 else np.stack(rows)


def batch_buckets(max_batch: int) -> tuple[int, ...]:
    """Batch sizes compiled for up to max_batch requests: powers of two, then max_batch itself."""
    out, b = [], 1
    while b < max_batch:
        out.append(b)
        b *= 2
    return (*out, max_batch)


class Policy:
    """A loaded model plus its transforms. `infer` takes one observation dict and returns an action chunk.

    strict: unknown observation keys are an error (False: ignored). optional_cameras: camera slots that may be
    missing (masked, as LIBERO's absent right wrist); default `observation.DEFAULT_OPTIONAL_CAMERAS`. max_batch: the
    largest batch one device call takes (`infer_batch` and the server split larger ones). kernels, attention: the
    engine's paths (`pi0_jax.engine.Engine`), and overlap its first denoise step beside the prefix fill; the
    defaults pick the faster on this device for each batch size.
    cache_dir: where compiled programs are kept (`engine.store`, beside XLA's persistent cache; None: the default
    directory, False: nothing kept).
    """

    def __init__(self, config: Pi0Config, params, tokenizer: PaligemmaTokenizer, normalizer: _norm.Normalizer, *,
                 num_steps: int = 10, camera_map: Mapping[str, str | None] | None = None,
                 action_dims: int | None = None, seed: int = 0, default_prompt: str | None = None,
                 sampler: str = "engine", strict: bool = True, optional_cameras: Sequence[str] | None = None,
                 ignore_keys: Sequence[str] = (), max_batch: int = 8, kernels: str = "auto",
                 attention: str = "auto", cache_dir: str | os.PathLike | None | bool = None, overlap: str = "auto"):
        root = None   # the compiled programs on disk (`engine.store`), beside XLA's cache
        if cache_dir is not False:
            root = enable_compilation_cache(None if cache_dir in (None, True) else cache_dir) / "programs"
        self.store = ProgramStore(root)
        self.core = PolicyCore(config, params, tokenizer, normalizer, num_steps=num_steps, action_dims=action_dims,
                               sampler=sampler, kernels=kernels, attention=attention, overlap=overlap)
        self.validator = Validator(self.core, camera_map=camera_map, default_prompt=default_prompt, strict=strict,
                                   optional_cameras=DEFAULT_OPTIONAL_CAMERAS if optional_cameras is None
                                   else optional_cameras, ignore_keys=ignore_keys)
        self.batch_buckets = batch_buckets(int(max_batch))
        self._norm = jax.device_put(self.core.norm)
        self._noise_rng = np.random.default_rng(seed)
        self._executables: dict[tuple, Any] = {}
        self.compile_seconds: dict[tuple, float] = {}
        self._lock = threading.Lock()         # compiles
        self._noise_lock = threading.Lock()   # the noise stream, so validation never waits for a compile

    config = property(lambda self: self.core.config)
    normalizer = property(lambda self: self.core.normalizer)
    tokenizer = property(lambda self: self.core.tokenizer)
    num_steps = property(lambda self: self.core.num_steps)
    action_dims = property(lambda self: self.core.action_dims)

    # -----------------------------------------------------------------------------------------------------------------
    @classmethod
    def from_checkpoint(cls, path: str | os.PathLike, *, tokenizer_path: str | os.PathLike | None = None,
                        norm_stats: _norm.Normalizer | Mapping[str, _norm.NormStats] | str | os.PathLike | None = None,
                        dtype: str | None = None, num_steps: int | None = None, **kw) -> Policy:
        """Load a converted checkpoint dir (`checkpoint.load_checkpoint`) with its assets.

        tokenizer_path: default `<path>/tokenizer.model`, then `<path>/assets/tokenizer.model`.
        norm_stats: None -> found under `<path>/assets` (`normalize.find_norm_stats`); a Normalizer; a {key:
          NormStats} dict (openpi convention); a norm_stats.json file or LeRobot processor dir; or "identity".
        dtype: param and compute dtype (default: the checkpoint's). num_steps: default the checkpoint's recorded
          `num_steps` (a distilled student's), else 10. Other keywords: `Policy(...)`.
        """
        from pi0_jax import checkpoint

        config, params, tokenizer, normalizer = load_parts(path, tokenizer_path=tokenizer_path,
                                                           norm_stats=norm_stats, dtype=dtype)
        if num_steps is None:
            num_steps = int(checkpoint.read_meta(path).get("num_steps", 10))
        return cls(config, params, tokenizer, normalizer, num_steps=num_steps, **kw)

    # -----------------------------------------------------------------------------------------------------------------
    def prepare(self, obs: Mapping[str, Any], noise=None) -> Prepared:
        """Validate one observation and tokenise its prompt (host only). Raises `ObservationError` naming the key.

        noise: (H, action_dim) or (1, H, action_dim) at t = 1; None draws it from the policy's seeded generator, so
        the order of `prepare` calls fixes which request gets which noise."""
        cfg = self.config
        shape = (cfg.action_horizon, cfg.action_dim)
        if noise is None:
            with self._noise_lock:
                noise = self._noise_rng.standard_normal(shape, np.float32)
        return self.validator.validate(obs, noise)

    def make_observation(self, obs: Mapping[str, Any]) -> pi0.Observation:
        """The host transforms alone, as the reference model's batch-1 `pi0.Observation` (images at the model's
        size in [-1, 1], state normalised and padded); for inspection and tests."""
        p = self.prepare(obs, np.zeros((self.config.action_horizon, self.config.action_dim), np.float32))
        core, size = self.core, self.config.image_size
        pixels, state = core.preprocess(core.norm, [jnp.asarray(p.images[c][None]) for c in p.cameras],
                                        jnp.asarray(p.state[None]))
        images = {k: np.full((1, size, size, 3), -1.0, np.float32) for k in core.slots}
        images.update({c: np.asarray(x) for c, x in zip(p.cameras, pixels)})
        return pi0.Observation(images=images, image_masks={k: np.array([k in p.images]) for k in core.slots},
                               state=np.asarray(state), tokenized_prompt=p.tokens[None],
                               tokenized_prompt_mask=p.token_mask[None])

    def run(self, prepared: Sequence[Prepared]) -> list[dict[str, Any]]:
        """Prepared requests -> their outputs, in order: one device call per group of requests with the same camera
        shapes (at most max_batch each, padded up to a compiled batch bucket). Each element's actions depend only on
        its own inputs and noise (to float rounding across batch sizes)."""
        outs: list[dict | None] = [None] * len(prepared)
        groups: dict[tuple, list[int]] = {}
        for i, p in enumerate(prepared):
            groups.setdefault(p.signature, []).append(i)
        top = self.batch_buckets[-1]
        for members in groups.values():
            for start in range(0, len(members), top):
                chunk = members[start: start + top]
                actions, ms = self._run_group([prepared[i] for i in chunk])
                for j, i in enumerate(chunk):
                    outs[i] = {"actions": actions[j],
                               "policy_timing": {"infer_ms": ms, "batch_size": len(chunk)}}
        return outs

    def infer(self, obs: Mapping[str, Any], noise=None) -> dict[str, Any]:
        """One observation -> {"actions": (H, action_dims) float32, "policy_timing": {"infer_ms", "batch_size"}}.

        noise: see `prepare`. infer_ms times the device call including the host-to-device and device-to-host
        copies, as openpi does."""
        return self.run([self.prepare(obs, noise)])[0]

    def infer_batch(self, observations: Sequence[Mapping[str, Any]], noise=None) -> list[dict[str, Any]]:
        """Several observations in as few device calls as their shapes allow; noise: None or one entry per
        observation (each None or an array). Element i equals `infer(observations[i], noise[i])`."""
        noise = [None] * len(observations) if noise is None else list(noise)
        if len(noise) != len(observations):
            raise ValueError(f"{len(observations)} observations but {len(noise)} noise entries")
        return self.run([self.prepare(o, n) for o, n in zip(observations, noise)])

    # -----------------------------------------------------------------------------------------------------------------
    def _run_group(self, group: Sequence[Prepared]) -> tuple[np.ndarray, float]:
        cfg, n = self.config, len(group)
        batch = next(b for b in self.batch_buckets if b >= n)
        rows = list(group) + [group[0]] * (batch - n)    # padding rows repeat the first request, then are dropped
        cameras = group[0].cameras
        prompt_len = prompt_bucket(max(p.valid_tokens for p in group), cfg.max_token_len)
        host = (tuple(_stack([p.images[c] for p in rows]) for c in cameras),
                np.ones((len(cameras), batch), bool),
                _stack([p.tokens[:prompt_len] for p in rows]), _stack([p.token_mask[:prompt_len] for p in rows]),
                _stack([p.state for p in rows]), _stack([p.noise for p in rows]))
        call = self.executable(host, cameras)
        start = time.perf_counter()
        # numpy in, so the call's own dispatch copies it to the device (jax.device_put first took 0.5 ms more); the
        # actions come back in host memory (`_to_host`)
        actions = np.asarray(call(self._norm, *host))
        return actions[:n], (time.perf_counter() - start) * 1000.0

    def executable(self, host_args: tuple, cameras: tuple[str, ...]):
        """The compiled call for these input shapes (compiled ahead of time on first use, then kept):
        (norm, *host_args) -> actions, in pinned host memory (`_to_host`). With the engine sampler it is two
        programs, `PolicyCore.encode` on the vision tower's weights and `PolicyCore.act` on the rest (three where the
        first denoise step overlaps the prefix fill: `act_first`, then `act_rest` on the expert's weights; and the
        tower itself two, `encode_head` and `encode_tail`, where the engine cuts it: `runtime.splits_vision`), each
        dispatched while the GPU runs the one before, as `Engine.sample_actions`; the reference sampler is one
        program."""
        key = (cameras, tuple((x.shape, x.dtype.str) for x in jax.tree.leaves(host_args)))
        with self._lock:
            if key not in self._executables:   # the shapes' tree only here: 17 µs a call (a CPU core)
                start = time.perf_counter()
                self._executables[key] = self._compile(shapes(host_args), cameras)
                self.compile_seconds[key] = time.perf_counter() - start
            return self._executables[key]

    def _compile(self, spec: tuple, cameras: tuple[str, ...]):
        core = self.core
        # everything the traced programs depend on besides their arguments and compiler options
        parts = (repr(core.config), core.sampler, core.num_steps, core.action_dims, core.unroll, core.kernels,
                 repr(core.attention), core.gemm, core.overlap, cameras)

        def compile_(name, fn, args, options):
            return self.store.compile(f"policy_{name}", parts, fn, args, options)

        if core.sampler != "engine":
            @_to_host
            def fn(model, norm, images, image_masks, tokens, token_mask, state, noise):
                return core.program(model, norm, images, cameras, image_masks, tokens, token_mask, state, noise)

            exe = compile_("reference", fn, (core.model, self._norm, *spec),
                           matmul.compiler_options(core.model, core.gemm))
            return functools.partial(exe, core.model)
        vision, rest = core.split_model(core.model)
        images = spec[0]

        def options_for(stage, tree):   # the engine's library for the stage this program runs
            return matmul.compiler_options(tree, core.gemm, **runtime.library_keywords(stage, spec[-1].shape[0]))

        vision_options = options_for("vision_head", vision)
        if runtime.splits_vision(core.config, core.unroll):   # the tower as two programs, as `Engine.call_stages`
            head_w, tail_w = ({"weights": runtime.stage_tree(vision["weights"], s)} for s in ("vision_head",
                                                                                               "vision_tail"))
            head = compile_("encode_head", core.encode_head, (head_w, images), vision_options)
            tail_fn = functools.partial(core.encode_tail, cameras=len(cameras))
            tail = compile_("encode_tail", tail_fn, (tail_w, *shapes(head.out_info)), vision_options)

            def encode(images):
                return tail(tail_w, *head(head_w, images))
        else:
            tail = compile_("encode", core.encode, (vision, images), vision_options)
            encode = functools.partial(tail, vision)
        tokens = shapes(tail.out_info)   # the image tokens, read off the tower's last program
        peel = paths.first_step_overlap(core.overlap, core.kernels, spec[-1].shape[0], rest["weights"]["expert"])
        options = options_for("prefix_denoise", rest)
        if peel and core.num_steps > 1:   # the loop as a program of its own, as `Engine.call_stages`
            first_args = (rest, self._norm, tokens, *spec[1:])
            first = compile_("act_first", core.act_first, first_args,
                             paths.overlap_options(options_for("prefix_first_step", rest), True))
            loop = {**rest, "weights": {k: rest["weights"][k] for k in STAGE_WEIGHTS["denoise_rest"]
                                        if k in rest["weights"]}}
            last = compile_("act_rest", _to_host(core.act_rest), (loop, self._norm, *shapes(first.out_info)),
                            options_for("denoise_rest", loop))

            def call(norm, images, *args):
                return last(loop, norm, *first(rest, norm, encode(images), *args))

            return call
        act = compile_("act", _to_host(functools.partial(core.act, peel_first=peel)),
                       (rest, self._norm, tokens, *spec[1:]), paths.overlap_options(options, peel))

        def call(norm, images, *args):
            return act(rest, norm, encode(images), *args)

        return call

    @property
    def num_compiled(self) -> int:
        return len(self._executables)

    def warmup(self, batch_sizes: Sequence[int] | None = None, example: Mapping[str, Any] | None = None) -> float:
        """Compile the programs for `example`'s shapes at these batch sizes (default: every bucket). -> seconds."""
        start = time.perf_counter()
        p = self.prepare(example if example is not None else self.example_observation(),
                         np.zeros((self.config.action_horizon, self.config.action_dim), np.float32))
        for b in batch_sizes or self.batch_buckets:
            self._run_group([p] * min(b, self.batch_buckets[-1]))
        return time.perf_counter() - start

    def example_observation(self, seed: int = 0) -> dict[str, Any]:
        """A valid observation for this policy (random uint8 frames at the model's size, a random state)."""
        return self.validator.example(seed)

    @property
    def metadata(self) -> dict[str, Any]:
        cfg = self.config
        return {"name": cfg.name, "pi05": cfg.pi05, "action_horizon": cfg.action_horizon,
                "action_dims": self.action_dims, "num_steps": self.num_steps, "dtype": cfg.dtype,
                "normalization": self.normalizer.convention.value, "sampler": self.core.sampler,
                "kernels": self.core.kernels, "attention": str(self.core.attention), "overlap": self.core.overlap,
                "image_size": cfg.image_size, "state_dim": self.core.state_dim, "max_batch": self.batch_buckets[-1],
                **self.validator.describe()}


def load_parts(path: str | os.PathLike, *, tokenizer_path: str | os.PathLike | None = None,
               norm_stats: _norm.Normalizer | Mapping[str, _norm.NormStats] | str | os.PathLike | None = None,
               dtype: str | None = None) -> tuple[Pi0Config, dict, PaligemmaTokenizer, _norm.Normalizer]:
    """A checkpoint dir -> (config, params, tokenizer, normaliser), as every policy (Policy, the simulator's) loads
    it; see `Policy.from_checkpoint` for the arguments."""
    from pi0_jax import checkpoint

    path = Path(path)
    config, params = checkpoint.load_checkpoint(path, dtype=dtype)
    if dtype is not None:   # params and compute: bf16 on CPU is emulated and slower than f32
        config = config.replace(dtype=dtype)
    tokenizer = PaligemmaTokenizer(find_tokenizer(path, tokenizer_path), config.max_token_len)
    use_quantiles = config.pi05  # openpi: quantiles for every model type but PI0
    if isinstance(norm_stats, _norm.Normalizer):
        normalizer = norm_stats
    elif isinstance(norm_stats, str) and norm_stats == "identity":
        normalizer = _norm.Normalizer.identity()
    elif isinstance(norm_stats, Mapping):
        normalizer = _norm.Normalizer.openpi(norm_stats, use_quantiles=use_quantiles)
    else:
        normalizer = _norm.load_normalizer(path if norm_stats is None else norm_stats, use_quantiles=use_quantiles)
    return config, params, tokenizer, normalizer


def find_tokenizer(ckpt: str | os.PathLike, explicit: str | os.PathLike | None = None) -> Path:
    """The checkpoint's SentencePiece model: `explicit`, else <ckpt>/tokenizer.model, else
    <ckpt>/assets/tokenizer.model."""
    ckpt = Path(ckpt)
    candidates = [Path(explicit)] if explicit is not None else [ckpt / TOKENIZER_FILE, ckpt / "assets" / TOKENIZER_FILE]
    for c in candidates:
        if c.is_file():
            return c
    raise FileNotFoundError(f"tokenizer model not found (tried {[str(c) for c in candidates]}); pass tokenizer_path= "
                            "(openpi: gs://big_vision/paligemma_tokenizer.model)")
