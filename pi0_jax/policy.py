"""`Policy.infer(obs) -> {"actions", "policy_timing"}`, like openpi's `Policy.infer` with its LIBERO transforms, on
the compiled engine.

One pipeline serves every caller (`Policy.infer` / `infer_batch`, the policy server, the simulator's rollout):

  host    `pi0_jax.observation.validate`: keys, cameras, dtypes, shapes and finiteness checked, the prompt tokenised
          (cached per prompt string; π0.5 with the state in the prompt tokenises per call);
  device  `PolicyCore.program`, compiled per shape bucket (batch, camera shapes, prompt bucket): uint8 -> [-1, 1]
          and resize-with-pad to the model's size, state normalised and zero-padded, the engine's vision -> prefix
          cache -> denoise (masked cameras not encoded, the prompt cut to its bucket), actions sliced to the
          dataset's dims and un-normalised. `Policy` runs it as two programs, `PolicyCore.encode` (the vision
          tower) then `PolicyCore.act` (where its first denoise step overlaps the prefix fill, `act_first` then
          `act_rest`), as `Engine.sample_actions` does; the simulator embeds `program` whole.

Normalisation runs on device as x * scale + offset (`Normalizer.affine`): every mode is affine per dimension, and
the scale/offset come from the exact float64 formulas (openpi un-normalises all 32 dims and then slices; per-dim
stats make that the same, and it is what LeRobot does). `sampler="reference"` runs `pi0.sample_actions` (openpi's
structure) inside the same pipeline instead of the engine: the parity path.

Conventions follow where the stats came from: openpi `norm_stats.json` -> openpi eps, quantiles for π0.5 and
z-score for π0, and the state prompt lists the un-padded state; LeRobot processor files -> LeRobot eps and the modes
they name, and the state prompt lists the state zero-padded to action_dim (LeRobot pads before discretising).
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
from pi0_jax.config import IMAGE_KEYS, Pi0Config
from pi0_jax.engine import engine_weights, enable_compilation_cache, prompt_bucket
from pi0_jax.engine import programs, runtime
from pi0_jax.engine import weights as weights_lib
from pi0_jax.engine.runtime import STAGE_WEIGHTS
from pi0_jax.engine.store import ProgramStore, shapes
from pi0_jax.observation import DEFAULT_OPTIONAL_CAMERAS, ObservationError, Prepared, Validator
from pi0_jax.ops import matmul
from pi0_jax.preprocess import resize_with_pad
from pi0_jax.tokenizer import PaligemmaTokenizer

__all__ = ["ObservationError", "Policy", "PolicyCore", "Prepared", "find_tokenizer"]

TOKENIZER_FILE = "tokenizer.model"
SAMPLERS = ("engine", "reference")


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


class PolicyCore:
    """A model plus its transforms as pure device functions, independent of where the inputs come from.

    `model` (engine weights and step schedule, or the reference params) and `norm` (affine (un)normalisation) are
    pytrees passed to every program as arguments, never baked in as constants.
    """

    unroll = True   # the engine's layers unrolled (per-layer weight buffers; the Pallas kernels need them)

    def __init__(self, config: Pi0Config, params: dict | None, tokenizer: PaligemmaTokenizer,
                 normalizer: _norm.Normalizer, *, num_steps: int = 10, action_dims: int | None = None,
                 sampler: str = "engine", kernels: str = "auto", attention: str = "auto", gemm: str = "auto",
                 overlap: str = "auto"):
        if tokenizer.max_len != config.max_token_len:
            raise ValueError(f"tokenizer max_len {tokenizer.max_len} != config.max_token_len {config.max_token_len}")
        if sampler not in SAMPLERS:
            raise ValueError(f"sampler must be one of {SAMPLERS}, got {sampler!r}")
        if action_dims is None:
            action_dims = normalizer.dim(_norm.ACTIONS) or config.action_dim
        if not 0 < action_dims <= config.action_dim:
            raise ValueError(f"action_dims must be in [1, {config.action_dim}], got {action_dims}")
        self.config, self.tokenizer, self.normalizer = config, tokenizer, normalizer
        self.num_steps, self.action_dims, self.sampler = int(num_steps), int(action_dims), sampler
        # the engine's expert layers ("xla" ops, the fused Pallas kernels of pi0_jax.ops, or "auto": by batch size)
        # and each stage's attention (`programs.Attention.parse`)
        self.kernels, self.attention = programs.check_kernels(kernels), programs.Attention.parse(
            attention, dtype=config.dtype)
        self.gemm = matmul.check_gemm(gemm)   # XLA's GEMM library on a GPU (`pi0_jax.ops.matmul.compiler_options`)
        self.overlap = programs.check_overlap(overlap)   # the first denoise step beside the prefix fill, in `act`
        self.slots = IMAGE_KEYS[: config.num_cameras]
        # The state's dims as the stats know them (None: no stats, so only <= action_dim can be checked).
        self.state_dim = normalizer.dim(_norm.STATE)
        self.reads_state = not config.pi05 or config.discrete_state_input
        self.norm = self._norm_arrays()
        if params is None:   # the transforms alone (`preprocess`, tokenisation)
            self.model = None
        elif sampler == "engine":
            runtime.check_allocator()
            self._sched_params = weights_lib.schedule_params(config, params)
            self.model = {"weights": engine_weights(config, params, unroll=self.unroll, kernels=kernels),
                          "sched": jax.jit(weights_lib.precompute_schedule, static_argnums=(0, 2))(
                              config, self._sched_params, self.num_steps)}
        else:
            self.model = {"params": jax.device_put(params)}

    def dynamic_model(self) -> dict:
        """`model` for programs whose step count is traced (one compile for every count up to max_dynamic_steps):
        the engine's schedule is then computed inside the program from the time-MLP / adaRMS params."""
        if self.sampler != "engine":
            return self.model
        return {"weights": self.model["weights"], "sched_params": self._sched_params}

    def _norm_arrays(self) -> dict:
        cfg, n = self.config, self.state_dim
        if self.reads_state and n is not None:
            scale, offset = self.normalizer.affine(_norm.STATE, n)
        elif self.reads_state:
            scale, offset = self.normalizer.affine(_norm.STATE, cfg.action_dim)   # identity: nothing to slice
            n = cfg.action_dim
        else:
            scale, offset, n = np.zeros(0, np.float32), np.zeros(0, np.float32), 0   # π0.5 never reads it
        pad = cfg.action_dim - n   # padded dims stay exactly 0, as zero-padding after normalising
        a_scale, a_offset = self.normalizer.affine(_norm.ACTIONS, self.action_dims, inverse=True)
        return {"state_scale": np.pad(scale, (0, pad)), "state_offset": np.pad(offset, (0, pad)),
                "action_scale": a_scale, "action_offset": a_offset}

    # -- host side ------------------------------------------------------------------------------------------------
    @functools.lru_cache(maxsize=1024)
    def tokenize_prompt(self, prompt: str) -> tuple[np.ndarray, np.ndarray]:
        """(tokens (L,) int32, mask (L,) bool) of a prompt without state, cached per string (read-only arrays)."""
        tokens, mask = self.tokenizer.tokenize(prompt)
        tokens.flags.writeable = mask.flags.writeable = False
        return tokens, mask

    def tokenize(self, prompt: str, normalized_state: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """The prompt's tokens; π0.5 with `discrete_state_input` writes the normalised state into it."""
        cfg = self.config
        if not (cfg.pi05 and cfg.discrete_state_input):
            return self.tokenize_prompt(prompt)
        # openpi tokenizes before padding; LeRobot pads to max_state_dim first, so its prompt lists 32 numbers.
        state = normalized_state
        if self.normalizer.convention is _norm.Convention.LEROBOT:
            state = np.pad(state, (0, cfg.action_dim - state.shape[0]))
        return self.tokenizer.tokenize(prompt, state)

    max_dynamic_steps = 16

    def _schedule(self, model: dict, num_steps) -> dict:
        if "sched" in model:
            if num_steps != self.num_steps:
                raise ValueError(f"this model's schedule is for {self.num_steps} steps, not {num_steps}; "
                                 "use dynamic_model()")
            return model["sched"]
        length = None if isinstance(num_steps, int) else self.max_dynamic_steps
        return weights_lib.precompute_schedule(self.config, model["sched_params"], num_steps, length)

    # -- device side ----------------------------------------------------------------------------------------------
    def preprocess(self, norm, images: Sequence[jax.Array], state: jax.Array) -> tuple[list[jax.Array], jax.Array]:
        """The input transforms on device: images -> (B, size, size, 3) f32 in [-1, 1]; raw state -> normalised."""
        return [self.pixels(x) for x in images], self.normalize_state(norm, state)

    def pixels(self, x: jax.Array) -> jax.Array:
        """One camera's frames (B, h, w, 3), uint8 or f32 in [-1, 1] -> (B, size, size, 3) f32 in [-1, 1]."""
        size = self.config.image_size
        x = x.astype(jnp.float32) / 255.0 * 2.0 - 1.0 if x.dtype == jnp.uint8 else x.astype(jnp.float32)
        return resize_with_pad(x, size, size)

    @staticmethod
    def normalize_state(norm, state: jax.Array) -> jax.Array:
        return state.astype(jnp.float32) * norm["state_scale"] + norm["state_offset"]

    def program(self, model, norm, images: Sequence[jax.Array], cameras: Sequence[str], image_masks, tokens,
                token_mask, state, noise, *, num_steps=None) -> jax.Array:
        """The whole policy on device. Pure and traceable (jit it, or call it inside a larger jitted program).

        images: one (B, h, w, 3) array per camera in `cameras` (static), uint8 or float32 already in [-1, 1], any
        size (resized with padding to the model's); image_masks (C, B) bool; tokens / token_mask (B, L), L a prompt
        bucket; state (B, action_dim) raw, zero-padded; noise (B, H, action_dim) f32 at t = 1.
        num_steps: None (the core's); another int or a traced int32 <= `max_dynamic_steps` needs `dynamic_model()`.
        Returns (B, H, action_dims) f32 actions, un-normalised.
        """
        if self.sampler == "engine":
            return self.act(model, norm, self.encode(model, images), image_masks, tokens, token_mask, state, noise,
                            num_steps=num_steps)
        cfg, size = self.config, self.config.image_size
        num_steps = self.num_steps if num_steps is None else num_steps
        pixels, state = self.preprocess(norm, images, state)
        b = noise.shape[0]
        black = jnp.full((b, size, size, 3), -1.0, jnp.float32)
        by_slot = dict(zip(cameras, pixels))
        masks = dict(zip(cameras, image_masks))
        obs = pi0.Observation(images={k: by_slot.get(k, black) for k in self.slots},
                              image_masks={k: masks.get(k, jnp.zeros((b,), bool)) for k in self.slots},
                              state=state, tokenized_prompt=tokens, tokenized_prompt_mask=token_mask)
        return self._actions(norm, pi0.sample_actions(cfg, model["params"], obs, noise.astype(jnp.float32),
                                                      num_steps=num_steps))

    # The engine's pipeline in two parts, which `Policy` compiles as two programs (engine.runtime's module doc)
    @staticmethod
    def split_model(model: dict) -> tuple[dict, dict]:
        """The engine sampler's model as (what `encode` reads: the vision tower's weights, what `act` reads)."""
        keys = STAGE_WEIGHTS["encode_images"]
        w = model["weights"]
        return ({"weights": {k: w[k] for k in keys}},
                {**model, "weights": {k: v for k, v in w.items() if k not in keys}})

    def encode(self, model, images: Sequence[jax.Array]) -> jax.Array:
        """The engine sampler's vision half of `program`: images (one (B, h, w, 3) array per active camera) ->
        image tokens (B, C * 256, VLM width)."""
        pixels = [self.pixels(x) for x in images]
        return programs.encode_images(self.config, model["weights"], jnp.stack(pixels), unroll=self.unroll,
                                      kernels=self.kernels, attention=self.attention)

    # `encode` as two programs where the engine's call cuts the tower (`runtime.splits_vision`)
    def encode_head(self, model, images: Sequence[jax.Array]) -> tuple:
        """`encode` up to the blocks of its weights (`programs.encode_images_head`)."""
        pixels = [self.pixels(x) for x in images]
        return programs.encode_images_head(self.config, model["weights"], jnp.stack(pixels), kernels=self.kernels,
                                           attention=self.attention)

    def encode_tail(self, model, x, f, *, cameras: int) -> jax.Array:
        """`encode` after `encode_head` (`programs.encode_images_tail`) -> image tokens."""
        return programs.encode_images_tail(self.config, model["weights"], x, f, cameras=cameras,
                                           kernels=self.kernels, attention=self.attention)

    def act(self, model, norm, image_tokens, image_masks, tokens, token_mask, state, noise, *,
            num_steps=None, peel_first: bool = False) -> jax.Array:
        """The engine sampler's other half of `program`: `encode`'s tokens -> un-normalised actions. peel_first:
        the first denoise step outside the loop (`programs.first_step_overlap`)."""
        num_steps = self.num_steps if num_steps is None else num_steps
        actions = programs.prefix_denoise(self.config, model["weights"], self._schedule(model, num_steps),
                                          image_tokens, image_masks, tokens, token_mask,
                                          self.normalize_state(norm, state), noise.astype(jnp.float32),
                                          num_steps=num_steps, unroll=self.unroll, unroll_steps=False,
                                          kernels=self.kernels, attention=self.attention, peel_first=peel_first)
        return self._actions(norm, actions)

    # `act` as two programs where its first denoise step overlaps the prefix fill (`Engine.call_stages`)
    def act_first(self, model, norm, image_tokens, image_masks, tokens, token_mask, state, noise) -> tuple:
        """`act` up to its first denoise step: `programs.prefix_first_step`'s outputs."""
        return programs.prefix_first_step(self.config, model["weights"], self._schedule(model, self.num_steps),
                                          image_tokens, image_masks, tokens, token_mask,
                                          self.normalize_state(norm, state), noise.astype(jnp.float32),
                                          num_steps=self.num_steps, unroll=self.unroll, kernels=self.kernels,
                                          attention=self.attention)

    def act_rest(self, model, norm, x, kv, cache, fixed) -> jax.Array:
        """`act` after its first denoise step (`programs.denoise_rest`) -> un-normalised actions."""
        actions = programs.denoise_rest(self.config, model["weights"], self._schedule(model, self.num_steps), x, kv,
                                        cache, fixed, num_steps=self.num_steps, unroll=self.unroll,
                                        unroll_steps=False, kernels=self.kernels, attention=self.attention)
        return self._actions(norm, actions)

    def _actions(self, norm, actions: jax.Array) -> jax.Array:
        actions = actions[..., : self.action_dims].astype(jnp.float32)
        return actions * norm["action_scale"] + norm["action_offset"]


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
        peel = programs.first_step_overlap(core.overlap, core.kernels, spec[-1].shape[0], rest["weights"]["expert"])
        options = options_for("prefix_denoise", rest)
        if peel and core.num_steps > 1:   # the loop as a program of its own, as `Engine.call_stages`
            first_args = (rest, self._norm, tokens, *spec[1:])
            first = compile_("act_first", core.act_first, first_args,
                             programs.overlap_options(options_for("prefix_first_step", rest), True))
            loop = {**rest, "weights": {k: rest["weights"][k] for k in STAGE_WEIGHTS["denoise_rest"]
                                        if k in rest["weights"]}}
            last = compile_("act_rest", _to_host(core.act_rest), (loop, self._norm, *shapes(first.out_info)),
                            options_for("denoise_rest", loop))

            def call(norm, images, *args):
                return last(loop, norm, *first(rest, norm, encode(images), *args))

            return call
        act = compile_("act", _to_host(functools.partial(core.act, peel_first=peel)),
                       (rest, self._norm, tokens, *spec[1:]), programs.overlap_options(options, peel))

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
