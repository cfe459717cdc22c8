"""Observation dicts as robots and datasets send them, checked strictly on the host: `Validator.validate(obs) ->
Prepared` or an `ObservationError` that names the key and says what was expected. Nothing is dropped, padded or
masked without the caller having asked for it.

Keys (one observation, no batch axis; a leading batch of 1 on images / state is tolerated):

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

Bare slot names (`base_0_rgb`, ...) are accepted too; `camera_map` entries extend / override the table, and a key
mapped to None is ignored. Dataset bookkeeping keys (`IGNORED_KEYS`, plus `ignore_keys`) are ignored. Any other key
is an error listing the accepted ones, unless `strict=False`.

Rules:
* cameras: every slot the model has must be present, except `optional_cameras` (default: the right wrist, which
  openpi's LIBERO and DROID setups never send; it is masked, so attention never sees it). A camera mapped to a slot
  the model does not have is an error. Images are uint8 (0-255) or float in [0, 1] (`preprocess.to_signed_float`),
  HWC or CHW (`preprocess.to_hwc`), 1 to 4096 px a side, finite; any size is resized with padding on device.
* state: 1-D, real, finite, with exactly the dims the checkpoint's norm stats have (no stats: at most action_dim).
  π0.5 without the state in the prompt never reads it, so it may be absent (when sent, it is checked all the same).
* prompt: a string (or bytes / 0-d string array, as datasets hold it); `default_prompt` when absent.
* noise: (H, action_dim) or (1, H, action_dim), finite.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from pi0_jax import normalize as _norm
from pi0_jax.config import IMAGE_KEYS
from pi0_jax.preprocess import to_hwc, to_signed_float

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
# LeRobot dataset frames carry these next to the observation; they never reach the model.
IGNORED_KEYS = ("robot_type", "timestamp", "frame_index", "episode_index", "index", "task_index")
DEFAULT_OPTIONAL_CAMERAS = ("right_wrist_0_rgb",)
MAX_IMAGE_SIDE = 4096


class ObservationError(ValueError):
    """An observation the policy refuses; the message names the key and what was expected."""


@dataclasses.dataclass(frozen=True, eq=False)
class Prepared:
    """One validated request, ready to batch. images: {slot: (h, w, 3) uint8 or float32 in [-1, 1]} for the present
    cameras; state: (action_dim,) float32 raw, zero-padded; tokens / token_mask: (max_len,); noise (H, action_dim)."""

    images: dict[str, np.ndarray]
    state: np.ndarray
    tokens: np.ndarray
    token_mask: np.ndarray
    noise: np.ndarray

    @property
    def cameras(self) -> tuple[str, ...]:
        return tuple(k for k in IMAGE_KEYS if k in self.images)

    @property
    def valid_tokens(self) -> int:
        return int(self.token_mask.sum())

    @property
    def signature(self) -> tuple:
        """Requests with equal signatures run in one batched call."""
        return tuple((k, self.images[k].shape, self.images[k].dtype.str) for k in self.cameras)


def _first(obs: Mapping[str, Any], keys: tuple[str, ...]) -> tuple[str | None, Any]:
    present = [k for k in keys if k in obs]
    if len(present) > 1:
        raise ObservationError(f"observation has several of {present}; send one")
    return (present[0], obs[present[0]]) if present else (None, None)


def _real_array(key: str, value, what: str) -> np.ndarray:
    try:
        x = np.asarray(value)
    except Exception as e:  # ragged lists and the like
        raise ObservationError(f"{key!r}: cannot read {what} as an array ({e})") from None
    if x.dtype == bool or not (np.issubdtype(x.dtype, np.integer) or np.issubdtype(x.dtype, np.floating)):
        raise ObservationError(f"{key!r}: {what} must be real numbers, got dtype {x.dtype}")
    return x


class Validator:
    """Host-side checks and tokenisation for one `PolicyCore` (see the module docstring for the rules)."""

    def __init__(self, core, *, camera_map: Mapping[str, str | None] | None = None, default_prompt: str | None = None,
                 strict: bool = True, optional_cameras: Sequence[str] = DEFAULT_OPTIONAL_CAMERAS,
                 ignore_keys: Sequence[str] = ()):
        self.core = core
        self.camera_map = {**DEFAULT_CAMERA_MAP, **(camera_map or {})}
        for key, slot in self.camera_map.items():
            if slot is not None and slot not in IMAGE_KEYS:
                raise ValueError(f"camera_map[{key!r}] = {slot!r} is not a camera slot {IMAGE_KEYS}")
        for slot in optional_cameras:
            if slot not in IMAGE_KEYS:
                raise ValueError(f"optional_cameras: {slot!r} is not a camera slot {IMAGE_KEYS}")
        self.optional_cameras = tuple(optional_cameras)
        self.default_prompt = default_prompt
        self.strict = strict
        self.ignore_keys = frozenset(IGNORED_KEYS) | frozenset(ignore_keys)

    def accepted_keys(self) -> list[str]:
        return sorted({*self.camera_map, *STATE_KEYS, *PROMPT_KEYS, *self.ignore_keys})

    def describe(self) -> dict[str, Any]:
        """What the policy expects, for its metadata."""
        slots = self.core.slots
        return {"camera_slots": list(slots),
                "required_cameras": [s for s in slots if s not in self.optional_cameras],
                "camera_keys": {k: v for k, v in sorted(self.camera_map.items()) if v in slots},
                "state_keys": list(STATE_KEYS), "prompt_keys": list(PROMPT_KEYS), "strict": self.strict}

    # -----------------------------------------------------------------------------------------------------------------
    def validate(self, obs: Mapping[str, Any], noise) -> Prepared:
        if not isinstance(obs, Mapping):
            raise ObservationError(f"an observation is a dict of arrays and a prompt, got {type(obs).__name__}")
        cfg, core = self.core.config, self.core
        images = {}
        for key, value in obs.items():
            if not isinstance(key, str):
                raise ObservationError(f"observation keys must be strings, got {key!r}")
            if key in STATE_KEYS or key in PROMPT_KEYS or key in self.ignore_keys:
                continue
            if key not in self.camera_map:
                if self.strict:
                    raise ObservationError(f"unknown observation key {key!r}; accepted keys: {self.accepted_keys()} "
                                           "(map a camera with camera_map, or pass strict=False to ignore extras)")
                continue
            slot = self.camera_map[key]
            if slot is None:
                continue
            if slot not in core.slots:
                raise ObservationError(f"{key!r} maps to camera slot {slot!r}, but this model has only "
                                       f"{list(core.slots)}; map it to None to ignore it")
            if slot in images:
                raise ObservationError(f"two observation keys map to camera slot {slot!r} ({key!r} is the second)")
            images[slot] = self._image(key, value)
        missing = [s for s in core.slots if s not in images and s not in self.optional_cameras]
        if missing:
            keys = {s: sorted(k for k, v in self.camera_map.items() if v == s) for s in missing}
            raise ObservationError(f"camera(s) {missing} missing: this model was trained with them (send one of "
                                   f"{keys}, or allow masking with optional_cameras)")
        if not images:
            raise ObservationError(f"no camera in observation keys {sorted(obs)}")

        state_key, raw = self._state(obs)
        normalized = None
        if cfg.pi05 and cfg.discrete_state_input:
            try:
                normalized = core.normalizer.normalize(_norm.STATE, raw)
            except (KeyError, ValueError) as e:
                raise ObservationError(f"{state_key!r}: {e}") from None
        state = np.zeros(cfg.action_dim, np.float32)
        if raw is not None:
            state[: raw.shape[0]] = raw
        prompt_key, prompt = _first(obs, PROMPT_KEYS)
        if prompt is None:
            if self.default_prompt is None:
                raise ObservationError(f"observation has no prompt (one of {list(PROMPT_KEYS)}) and no "
                                       "default_prompt is set")
            prompt = self.default_prompt
        prompt = self._prompt(prompt_key, prompt)
        tokens, token_mask = core.tokenize(prompt, normalized)
        if tokens.max(initial=0) >= cfg.vocab_size:
            raise ObservationError(f"{prompt_key!r}: token id {int(tokens.max())} >= the model's vocab_size "
                                   f"{cfg.vocab_size} (wrong tokenizer for this checkpoint?)")
        return Prepared(images=images, state=state, tokens=tokens, token_mask=token_mask, noise=self._noise(noise))

    def _image(self, key: str, value) -> np.ndarray:
        x = _real_array(key, value, "an image")
        if x.ndim == 4 and x.shape[0] == 1:
            x = x[0]
        if x.ndim != 3:
            raise ObservationError(f"{key!r}: expected one image, (H, W, 3) or (3, H, W), got shape {x.shape}")
        try:
            x = to_hwc(x)
        except ValueError as e:
            raise ObservationError(f"{key!r}: {e}") from None
        if not (0 < x.shape[0] <= MAX_IMAGE_SIDE and 0 < x.shape[1] <= MAX_IMAGE_SIDE):
            raise ObservationError(f"{key!r}: image sides must be 1..{MAX_IMAGE_SIDE} px, got {x.shape[:2]}")
        if x.dtype == np.uint8:
            return np.ascontiguousarray(x)
        if not np.issubdtype(x.dtype, np.floating):
            raise ObservationError(f"{key!r}: image dtype must be uint8 (0-255) or float in [0, 1], got {x.dtype}")
        if not np.isfinite(x).all():
            raise ObservationError(f"{key!r}: image has NaN or Inf values")
        try:
            return np.ascontiguousarray(to_signed_float(x))
        except ValueError as e:
            raise ObservationError(f"{key!r}: {e}") from None

    def _state(self, obs) -> tuple[str | None, np.ndarray | None]:
        """-> (key, the raw 1-D state as sent) or (None, None) when absent and never read."""
        core, dim = self.core, self.core.config.action_dim
        key, value = _first(obs, STATE_KEYS)
        if value is None:
            if core.reads_state:
                raise ObservationError(f"observation has no state (one of {list(STATE_KEYS)})")
            return None, None
        x = _real_array(key, value, "the state")
        if x.ndim == 2 and x.shape[0] == 1:
            x = x[0]
        if x.ndim != 1:
            raise ObservationError(f"{key!r}: expected a 1-D state, got shape {x.shape}")
        if not np.isfinite(x).all():
            raise ObservationError(f"{key!r}: state has NaN or Inf values at {np.flatnonzero(~np.isfinite(x))}")
        want = core.state_dim
        if want is not None and x.shape[0] != want:
            raise ObservationError(f"{key!r} has {x.shape[0]} dims, but this checkpoint's norm stats expect {want}")
        if x.shape[0] > dim:
            raise ObservationError(f"{key!r} has {x.shape[0]} dims, more than the model's action_dim {dim}")
        return key, x

    @staticmethod
    def _prompt(key, prompt) -> str:
        if isinstance(prompt, np.ndarray) and prompt.ndim == 0:
            prompt = prompt.item()
        if isinstance(prompt, bytes):
            try:
                prompt = prompt.decode("utf-8")
            except UnicodeDecodeError:
                raise ObservationError(f"{key!r}: prompt bytes are not UTF-8") from None
        if not isinstance(prompt, str):
            raise ObservationError(f"{key!r}: the prompt must be a string, got {type(prompt).__name__}")
        return prompt

    def _noise(self, noise) -> np.ndarray:
        cfg = self.core.config
        shape = (cfg.action_horizon, cfg.action_dim)
        x = _real_array("noise", noise, "the noise")
        if x.ndim == 3 and x.shape[0] == 1:
            x = x[0]
        if x.shape != shape:
            raise ObservationError(f"'noise' must be {shape} or {(1, *shape)}, got {np.shape(noise)}")
        if not np.isfinite(x).all():
            raise ObservationError("'noise' has NaN or Inf values")
        return x.astype(np.float32)

    def example(self, seed: int = 0) -> dict[str, Any]:
        """A valid observation (random frames at the model's size, a random state, a short prompt)."""
        core, rng = self.core, np.random.default_rng(seed)
        size = core.config.image_size
        by_slot = {}
        for key, slot in self.camera_map.items():   # the first key of each slot in table order: openpi's names
            if slot in core.slots and slot not in self.optional_cameras:
                by_slot.setdefault(slot, key)
        obs: dict[str, Any] = {k: rng.integers(0, 256, (size, size, 3), dtype=np.uint8) for k in by_slot.values()}
        n = core.state_dim if core.state_dim is not None else core.config.action_dim
        if core.reads_state:
            obs["observation/state"] = rng.uniform(-1, 1, n).astype(np.float32)
        obs["prompt"] = "pick up the red block"
        return obs
