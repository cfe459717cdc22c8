"""`Policy.infer(obs) -> {"actions", "policy_timing"}`, like openpi's `Policy.infer` with its LIBERO transforms.

Pipeline (openpi `create_trained_policy` order, spec §13):
  cameras -> slots (`camera_map`) -> images to (1, 224, 224, 3) in [-1, 1], missing slots black with mask False
  state -> normalise (un-padded) -> [π0.5 `discrete_state_input`: write it into the prompt] -> zero-pad to action_dim
  prompt -> tokenize -> jitted `pi0.sample_actions` -> slice to the dataset's action dim -> un-normalise.
(openpi un-normalises all 32 dims and then slices; per-dim stats make that the same, and it is what LeRobot does.)

Observation keys (one observation, no batch axis; a leading batch of 1 on images/state is tolerated):

| what   | openpi LIBERO            | LeRobot                               | model slot / meaning        |
|--------|--------------------------|---------------------------------------|-----------------------------|
| camera | `observation/image`      | `observation.images.image`,           | `base_0_rgb`                |
|        |                          | `observation.images.base_0_rgb`       |                             |
| camera | `observation/wrist_image`| `observation.images.wrist_image`,     | `left_wrist_0_rgb`          |
|        |                          | `observation.images.image2`,          |                             |
|        |                          | `observation.images.left_wrist_0_rgb` |                             |
| camera |                          | `observation.images.right_wrist_0_rgb`| `right_wrist_0_rgb`         |
| state  | `observation/state`      | `observation.state`                   | (also plain `state`)        |
| prompt | `prompt`                 | `task`                                |                             |

Bare slot names (`base_0_rgb`, ...) are accepted too. `camera_map` entries extend / override this table; map a key
to None to ignore it. Any other key that looks like a camera (`observation.images.*`, `observation/*image*`) raises,
so a mis-named camera is never silently dropped. Image value/layout rules: `pi0_jax.preprocess`.

Conventions follow where the stats came from: openpi `norm_stats.json` -> openpi eps, quantiles for π0.5 and
z-score for π0, and the state prompt lists the un-padded state; LeRobot processor files -> LeRobot eps and the modes
they name, and the state prompt lists the state zero-padded to action_dim (LeRobot pads before discretising).
"""

from __future__ import annotations

import os
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from pi0_jax import normalize as _norm
from pi0_jax import pi0
from pi0_jax.config import IMAGE_KEYS, Pi0Config
from pi0_jax.preprocess import pad_to_dim, preprocess_image
from pi0_jax.tokenizer import PaligemmaTokenizer

DEFAULT_CAMERA_MAP: dict[str, str] = {
    # openpi LIBERO client (examples/libero/main.py).
    "observation/image": "base_0_rgb",
    "observation/wrist_image": "left_wrist_0_rgb",
    # LeRobot LIBERO datasets / env.
    "observation.images.image": "base_0_rgb",
    "observation.images.wrist_image": "left_wrist_0_rgb",
    "observation.images.image2": "left_wrist_0_rgb",
    # LeRobot features already named after the slots, and the bare slot names.
    **{f"observation.images.{k}": k for k in IMAGE_KEYS},
    **{k: k for k in IMAGE_KEYS},
}
STATE_KEYS = ("observation/state", "observation.state", "state")
PROMPT_KEYS = ("prompt", "task")
TOKENIZER_FILE = "tokenizer.model"


def _looks_like_camera(key: str) -> bool:
    return key.startswith("observation.images.") or (key.startswith("observation/") and "image" in key)


def _first(obs: Mapping[str, Any], keys: tuple[str, ...]) -> tuple[str | None, Any]:
    present = [k for k in keys if k in obs]
    if len(present) > 1:
        raise ValueError(f"observation has several of {present}; send one")
    return (present[0], obs[present[0]]) if present else (None, None)


class Policy:
    """A loaded model plus its transforms. `infer` takes one observation dict and returns an action chunk."""

    def __init__(self, config: Pi0Config, params, tokenizer: PaligemmaTokenizer, normalizer: _norm.Normalizer, *,
                 num_steps: int = 10, camera_map: Mapping[str, str | None] | None = None,
                 action_dims: int | None = None, seed: int = 0, default_prompt: str | None = None):
        if tokenizer.max_len != config.max_token_len:
            raise ValueError(f"tokenizer max_len {tokenizer.max_len} != config.max_token_len {config.max_token_len}")
        self.config = config
        self.tokenizer = tokenizer
        self.normalizer = normalizer
        self.num_steps = int(num_steps)
        self.camera_map = {**DEFAULT_CAMERA_MAP, **(camera_map or {})}
        self.slots = IMAGE_KEYS[: config.num_cameras]
        for key, slot in self.camera_map.items():
            if slot is not None and slot not in IMAGE_KEYS:
                raise ValueError(f"camera_map[{key!r}] = {slot!r} is not a camera slot {IMAGE_KEYS}")
        if action_dims is None:
            action_dims = normalizer.dim(_norm.ACTIONS) or config.action_dim
        if not 0 < action_dims <= config.action_dim:
            raise ValueError(f"action_dims must be in [1, {config.action_dim}], got {action_dims}")
        self.action_dims = int(action_dims)
        self.default_prompt = default_prompt
        self._params = jax.device_put(params)
        self._rng = jax.random.key(seed)
        # One compiled program per Policy: config and num_steps are closed over (static), the rest are arguments.
        self._sample = jax.jit(
            lambda params, obs, noise: pi0.sample_actions(config, params, obs, noise, num_steps=self.num_steps))

    # -----------------------------------------------------------------------------------------------------------------
    @classmethod
    def from_checkpoint(cls, path: str | os.PathLike, *, tokenizer_path: str | os.PathLike | None = None,
                        norm_stats: _norm.Normalizer | Mapping[str, _norm.NormStats] | str | os.PathLike | None = None,
                        num_steps: int = 10, camera_map: Mapping[str, str | None] | None = None,
                        action_dims: int | None = None, seed: int = 0,
                        default_prompt: str | None = None) -> Policy:
        """Load a converted checkpoint dir (`checkpoint.load_checkpoint`) with its assets.

        tokenizer_path: default `<path>/tokenizer.model`, then `<path>/assets/tokenizer.model`.
        norm_stats: None -> found under `<path>/assets` (`normalize.find_norm_stats`); a Normalizer; a {key:
          NormStats} dict (openpi convention); a norm_stats.json file or LeRobot processor dir; or "identity".
        """
        from pi0_jax import checkpoint

        path = Path(path)
        config, params = checkpoint.load_checkpoint(path)
        tokenizer = PaligemmaTokenizer(_find_tokenizer(path, tokenizer_path), config.max_token_len)
        use_quantiles = config.pi05  # openpi: quantiles for every model type but PI0
        if isinstance(norm_stats, _norm.Normalizer):
            normalizer = norm_stats
        elif isinstance(norm_stats, str) and norm_stats == "identity":
            normalizer = _norm.Normalizer.identity()
        elif isinstance(norm_stats, Mapping):
            normalizer = _norm.Normalizer.openpi(norm_stats, use_quantiles=use_quantiles)
        else:
            normalizer = _norm.load_normalizer(path if norm_stats is None else norm_stats, use_quantiles=use_quantiles)
        return cls(config, params, tokenizer, normalizer, num_steps=num_steps, camera_map=camera_map,
                   action_dims=action_dims, seed=seed, default_prompt=default_prompt)

    # -----------------------------------------------------------------------------------------------------------------
    def make_observation(self, obs: Mapping[str, Any]) -> pi0.Observation:
        """The transforms alone: one observation dict -> a batch-1 `pi0.Observation` (numpy leaves)."""
        cfg = self.config
        size = cfg.image_size
        images, masks = {}, {}
        for key, value in obs.items():
            slot = self.camera_map.get(key, "unmapped")
            if slot == "unmapped":
                if _looks_like_camera(key):
                    raise ValueError(f"camera {key!r} has no slot; add it to camera_map (slot or None to ignore); "
                                     f"known: {sorted(k for k, v in self.camera_map.items() if v)}")
                continue
            if slot is None or slot not in self.slots:
                continue
            if slot in images:
                raise ValueError(f"two observation keys map to camera slot {slot!r}")
            img = preprocess_image(value, size=size)
            if img.shape[0] != 1:
                raise ValueError(f"{key!r}: one observation expected, got a batch of {img.shape[0]}")
            images[slot], masks[slot] = img, np.ones((1,), bool)
        if not images:
            raise ValueError(f"no camera found in observation keys {sorted(obs)}; see camera_map")
        for slot in self.slots:
            if slot not in images:  # LIBERO's right wrist: a black frame (uint8 zeros) that attention never sees
                images[slot] = np.full((1, size, size, 3), -1.0, np.float32)
                masks[slot] = np.zeros((1,), bool)

        state_key, state = _first(obs, STATE_KEYS)
        model_reads_state = not cfg.pi05 or cfg.discrete_state_input
        if state is None:
            if model_reads_state:
                raise KeyError(f"observation has no state (one of {STATE_KEYS})")
            state = np.zeros((0,), np.float64)  # π0.5 without state input never reads it
        state = np.asarray(state, np.float64)
        if state.ndim == 2 and state.shape[0] == 1:
            state = state[0]
        if state.ndim != 1:
            raise ValueError(f"{state_key!r}: expected a 1-D state, got shape {state.shape}")
        if state.shape[0] > cfg.action_dim:
            raise ValueError(f"{state_key!r} has {state.shape[0]} dims, more than the model's {cfg.action_dim}")
        if state.shape[0]:
            state = self.normalizer.normalize(_norm.STATE, state)

        _, prompt = _first(obs, PROMPT_KEYS)
        if prompt is None:
            if self.default_prompt is None:
                raise KeyError(f"observation has no prompt (one of {PROMPT_KEYS}) and no default_prompt is set")
            prompt = self.default_prompt
        prompt_state = None
        if cfg.pi05 and cfg.discrete_state_input:
            # openpi tokenizes before padding; LeRobot pads to max_state_dim first, so its prompt lists 32 numbers.
            prompt_state = (pad_to_dim(state, cfg.action_dim)
                            if self.normalizer.convention is _norm.Convention.LEROBOT else state)
        tokens, token_mask = self.tokenizer.tokenize(prompt, prompt_state)
        if tokens.max(initial=0) >= cfg.vocab_size:
            raise ValueError(f"token id {int(tokens.max())} >= the model's vocab_size {cfg.vocab_size}")

        return pi0.Observation(
            images={k: images[k] for k in self.slots},
            image_masks={k: masks[k] for k in self.slots},
            state=pad_to_dim(state, cfg.action_dim).astype(np.float32)[None],
            tokenized_prompt=tokens[None],
            tokenized_prompt_mask=token_mask[None],
        )

    def infer(self, obs: Mapping[str, Any], noise=None) -> dict[str, Any]:
        """One observation -> {"actions": (H, action_dims) float32, "policy_timing": {"infer_ms": float}}.

        noise: (H, action_dim) or (1, H, action_dim) at t = 1; None draws it from the policy's seeded PRNG (the
        same sequence of chunks for the same seed and inputs). infer_ms times the model call including the
        device-to-host copy, as openpi does.
        """
        cfg = self.config
        observation = self.make_observation(obs)
        shape = (1, cfg.action_horizon, cfg.action_dim)
        if noise is None:
            self._rng, key = jax.random.split(self._rng)
            noise = jax.random.normal(key, shape, jnp.float32)
        else:
            noise = jnp.asarray(noise, jnp.float32)
            if noise.ndim == 2:
                noise = noise[None]
            if noise.shape != shape:
                raise ValueError(f"noise must be {shape[1:]} or {shape}, got {noise.shape}")
        start = time.perf_counter()
        actions = np.asarray(self._sample(self._params, observation, noise))[0]
        infer_ms = (time.perf_counter() - start) * 1000.0
        actions = self.normalizer.unnormalize(_norm.ACTIONS, actions[:, : self.action_dims])
        return {"actions": actions.astype(np.float32), "policy_timing": {"infer_ms": infer_ms}}

    @property
    def metadata(self) -> dict[str, Any]:
        cfg = self.config
        return {"name": cfg.name, "action_horizon": cfg.action_horizon, "action_dims": self.action_dims,
                "num_steps": self.num_steps, "normalization": self.normalizer.convention.value}


def _find_tokenizer(ckpt: Path, explicit: str | os.PathLike | None) -> Path:
    candidates = [Path(explicit)] if explicit is not None else [ckpt / TOKENIZER_FILE, ckpt / "assets" / TOKENIZER_FILE]
    for c in candidates:
        if c.is_file():
            return c
    raise FileNotFoundError(f"tokenizer model not found (tried {[str(c) for c in candidates]}); pass tokenizer_path= "
                            "(openpi: gs://big_vision/paligemma_tokenizer.model)")
