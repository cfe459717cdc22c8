"""The one policy pipeline, `PolicyCore`: a model plus its transforms (the prompt's tokenisation on the host, the
rest as pure device functions), which `Policy`, the policy server and the simulator's rollout all run.

`PolicyCore.program`: uint8 -> [-1, 1] and resize-with-pad to the model's size, state normalised and zero-padded,
the engine's vision -> prefix cache -> denoise (masked cameras not encoded, the prompt cut to its bucket), actions
sliced to the dataset's dims and un-normalised; also in parts (`encode`, `act`, `act_first`, `act_rest`) that
`Policy` compiles as programs of their own.

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
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from pi0_jax import normalize as _norm
from pi0_jax import pi0
from pi0_jax.config import IMAGE_KEYS, Pi0Config
from pi0_jax.engine import engine_weights, paths, programs, runtime
from pi0_jax.engine import weights as weights_lib
from pi0_jax.engine.runtime import STAGE_WEIGHTS
from pi0_jax.ops import matmul
from pi0_jax.preprocess import resize_with_pad
from pi0_jax.tokenizer import PaligemmaTokenizer

SAMPLERS = ("engine", "reference")


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
        # and each stage's attention (`paths.Attention.parse`)
        self.kernels, self.attention = paths.check_kernels(kernels), paths.Attention.parse(
            attention, dtype=config.dtype)
        self.gemm = matmul.check_gemm(gemm)   # XLA's GEMM library on a GPU (`pi0_jax.ops.matmul.compiler_options`)
        self.overlap = paths.check_overlap(overlap)   # the first denoise step beside the prefix fill, in `act`
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
        the first denoise step outside the loop (`paths.first_step_overlap`)."""
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
