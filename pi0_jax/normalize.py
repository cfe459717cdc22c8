"""State / action normalisation: openpi and LeRobot conventions, and their stats files.

Keys are canonical: "state" and "actions" (openpi's names). LeRobot's "observation.state" / "action" are renamed on
load. The formulas differ only in where the epsilon goes (spec §12.2, §13):

| mode      | openpi (eps 1e-6)                                  | LeRobot (eps 1e-8)                                |
|-----------|----------------------------------------------------|---------------------------------------------------|
| MEAN_STD  | (x - mean) / (std + eps); inv x (std + eps) + mean | (x - mean) / (std + eps); inv x std + mean        |
| QUANTILES | (x - q01) / (q99 - q01 + eps) * 2 - 1              | 2 (x - q01) / d - 1, d = q99 - q01 (eps if d = 0) |
|           | inv (x + 1) / 2 * (q99 - q01 + eps) + q01          | inv (x + 1) d / 2 + q01                           |
| MIN_MAX   | (not used by openpi)                               | as QUANTILES with min / max                       |

(LeRobot's MEAN_STD inverse really has no eps: `tensor * std + mean` in `normalize_processor.py`.)

Dimensions, as openpi: normalising slices the stats to the input's last dim (the state is normalised before it is
padded); un-normalising a longer (padded) vector transforms the first len(stats) dims and passes the rest through,
except openpi's z-score, which pads mean with 0 and std with 1 (so the extra dims are scaled by 1 + 1e-6, exactly
as openpi does). The policy slices actions to the dataset dim afterwards, so padded dims never reach a robot.
No clipping anywhere.

Files:
* openpi: `assets/<asset_id>/norm_stats.json` =
  {"norm_stats": {"state": {"mean", "std", "q01", "q99"}, "actions": {...}}}.
* LeRobot: `policy_preprocessor.json` / `policy_postprocessor.json`, each {"name", "steps": [...]}; the step with
  `registry_name` "normalizer_processor" / "unnormalizer_processor" has `config` {"eps", "features": {name:
  {"type": "STATE"|"ACTION"|"VISUAL"|..., "shape"}}, "norm_map": {feature type: mode}} and `state_file`, a
  safetensors file next to the json with flat keys "<feature>.<stat>" (e.g. "observation.state.q01", "action.mean").
  Base models carry a normaliser step with no state_file (no stats).
"""

from __future__ import annotations

import dataclasses
import enum
import json
import os
from collections.abc import Mapping
from pathlib import Path

import numpy as np

STATE, ACTIONS = "state", "actions"


class Mode(str, enum.Enum):
    IDENTITY = "IDENTITY"
    MEAN_STD = "MEAN_STD"
    QUANTILES = "QUANTILES"
    MIN_MAX = "MIN_MAX"


class Convention(str, enum.Enum):
    OPENPI = "openpi"
    LEROBOT = "lerobot"


_DEFAULT_EPS = {Convention.OPENPI: 1e-6, Convention.LEROBOT: 1e-8}
_REQUIRED = {Mode.MEAN_STD: ("mean", "std"), Mode.QUANTILES: ("q01", "q99"), Mode.MIN_MAX: ("min", "max")}


@dataclasses.dataclass(frozen=True)
class NormStats:
    """Per-key statistics, each a 1-D float64 array or None."""

    mean: np.ndarray | None = None
    std: np.ndarray | None = None
    q01: np.ndarray | None = None
    q99: np.ndarray | None = None
    min: np.ndarray | None = None
    max: np.ndarray | None = None

    def __post_init__(self):
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if v is not None:
                object.__setattr__(self, f.name, np.asarray(v, np.float64).reshape(-1))

    @property
    def dim(self) -> int:
        for f in dataclasses.fields(self):
            if (v := getattr(self, f.name)) is not None:
                return v.shape[0]
        return 0

    def to_json(self) -> dict:
        return {f.name: getattr(self, f.name).tolist() for f in dataclasses.fields(self)
                if getattr(self, f.name) is not None}


# ---------------------------------------------------------------------------------------------------------------------
# Formulas.


def _get(stats: NormStats, name: str, key: str, mode: Mode) -> np.ndarray:
    v = getattr(stats, name)
    if v is None:
        raise ValueError(f"norm stats for {key!r} have no {name!r}, which {mode.value} needs")
    return v


def normalize(x, stats: NormStats, mode: Mode, convention: Convention, *, eps: float | None = None,
              key: str = "?") -> np.ndarray:
    """(..., n) raw -> normalised, in float64. Stats are sliced to n; n larger than the stats is an error."""
    mode, convention = Mode(mode), Convention(convention)
    x = np.asarray(x, np.float64)
    if mode is Mode.IDENTITY:
        return x
    eps = _DEFAULT_EPS[convention] if eps is None else eps
    n = x.shape[-1]
    a, b = (_get(stats, name, key, mode) for name in _REQUIRED[mode])
    if n > a.shape[0]:
        raise ValueError(f"{key!r} has {n} dims but its norm stats only {a.shape[0]}")
    a, b = a[:n], b[:n]
    if convention is Convention.OPENPI:
        if mode is Mode.MEAN_STD:
            return (x - a) / (b + eps)
        if mode is Mode.QUANTILES:
            return (x - a) / (b - a + eps) * 2.0 - 1.0
        raise ValueError(f"the openpi convention has no {mode.value} normalisation")
    if mode is Mode.MEAN_STD:
        return (x - a) / (b + eps)
    d = b - a
    return 2.0 * (x - a) / np.where(d == 0, eps, d) - 1.0


def unnormalize(x, stats: NormStats, mode: Mode, convention: Convention, *, eps: float | None = None,
                key: str = "?") -> np.ndarray:
    """(..., n) normalised -> raw, in float64. Dims past len(stats) pass through (openpi z-score: scaled by 1+eps)."""
    mode, convention = Mode(mode), Convention(convention)
    x = np.asarray(x, np.float64)
    if mode is Mode.IDENTITY:
        return x
    eps = _DEFAULT_EPS[convention] if eps is None else eps
    a, b = (_get(stats, name, key, mode) for name in _REQUIRED[mode])
    n, k = x.shape[-1], min(x.shape[-1], a.shape[0])
    if convention is Convention.OPENPI:
        if mode is Mode.MEAN_STD:
            # openpi pads mean with 0 and std with 1 up to the input dim.
            mean = np.concatenate([a[:k], np.zeros(n - k)])
            std = np.concatenate([b[:k], np.ones(n - k)])
            return x * (std + eps) + mean
        if mode is not Mode.QUANTILES:
            raise ValueError(f"the openpi convention has no {mode.value} normalisation")
        head = (x[..., :k] + 1.0) / 2.0 * (b[:k] - a[:k] + eps) + a[:k]
    elif mode is Mode.MEAN_STD:
        head = x[..., :k] * b[:k] + a[:k]
    else:
        d = b[:k] - a[:k]
        head = (x[..., :k] + 1.0) * np.where(d == 0, eps, d) / 2.0 + a[:k]
    return np.concatenate([head, x[..., k:]], axis=-1)


# ---------------------------------------------------------------------------------------------------------------------
# The normaliser a policy holds.


@dataclasses.dataclass(frozen=True)
class Normalizer:
    """Stats per canonical key + a mode per key + a convention. Keys with no mode are passed through."""

    stats: Mapping[str, NormStats]
    modes: Mapping[str, Mode]
    convention: Convention = Convention.OPENPI
    eps: float | None = None  # None: the convention's default
    source: str = ""  # where the stats came from, for messages

    def __post_init__(self):
        object.__setattr__(self, "convention", Convention(self.convention))
        object.__setattr__(self, "modes", {k: Mode(m) for k, m in self.modes.items()})
        for key, mode in self.modes.items():
            if mode is Mode.IDENTITY:
                continue
            if mode is Mode.MIN_MAX and self.convention is Convention.OPENPI:
                raise ValueError("the openpi convention has no MIN_MAX normalisation")
            if key not in self.stats:
                continue  # reported when used, so a stats-less base model can still be inspected
            for name in _REQUIRED[mode]:
                if getattr(self.stats[key], name) is None:
                    raise ValueError(f"norm stats for {key!r}{self._where} have no {name!r}, "
                                     f"which {mode.value} needs")

    @property
    def _where(self) -> str:
        return f" (from {self.source})" if self.source else ""

    def _lookup(self, key: str) -> tuple[Mode, NormStats | None]:
        mode = self.modes.get(key, Mode.IDENTITY)
        if mode is Mode.IDENTITY:
            return mode, None
        if key not in self.stats:
            raise KeyError(f"no norm stats for {key!r}{self._where} (mode {mode.value}); have {sorted(self.stats)}. "
                           "Pass norm_stats='identity' to run without normalisation.")
        return mode, self.stats[key]

    def normalize(self, key: str, x) -> np.ndarray:
        mode, stats = self._lookup(key)
        if stats is None:
            return np.asarray(x, np.float64)
        return normalize(x, stats, mode, self.convention, eps=self.eps, key=key)

    def unnormalize(self, key: str, x) -> np.ndarray:
        mode, stats = self._lookup(key)
        if stats is None:
            return np.asarray(x, np.float64)
        return unnormalize(x, stats, mode, self.convention, eps=self.eps, key=key)

    def affine(self, key: str, dim: int, *, inverse: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """The (un)normalisation of `dim` dims as float32 (scale, offset), y = x * scale + offset, for use on device.
        Every mode is affine per dimension, so the exact float64 formulas are evaluated once, at x = 0 and x = 1."""
        fn = self.unnormalize if inverse else self.normalize
        zero, one = fn(key, np.zeros(dim)), fn(key, np.ones(dim))
        return (one - zero).astype(np.float32), zero.astype(np.float32)

    def dim(self, key: str) -> int | None:
        """The stats' dim for a key (the dataset's action dim for "actions"), or None without stats."""
        return self.stats[key].dim if key in self.stats else None

    @classmethod
    def identity(cls) -> Normalizer:
        return cls(stats={}, modes={}, source="identity")

    @classmethod
    def openpi(cls, stats: Mapping[str, NormStats], *, use_quantiles: bool, source: str = "") -> Normalizer:
        """openpi's Normalize/Unnormalize: quantiles for every model but π0 (`model_type != PI0`)."""
        mode = Mode.QUANTILES if use_quantiles else Mode.MEAN_STD
        return cls(stats=dict(stats), modes={STATE: mode, ACTIONS: mode}, convention=Convention.OPENPI,
                   source=source)


# ---------------------------------------------------------------------------------------------------------------------
# openpi norm_stats.json.


def load_openpi_norm_stats(path: str | os.PathLike) -> dict[str, NormStats]:
    """`norm_stats.json` -> {key: NormStats}. Missing q01/q99 (old files) load as None."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"norm stats file not found: {path}")
    data = json.loads(path.read_text())
    if "norm_stats" not in data:
        raise ValueError(f"{path}: expected a top-level 'norm_stats' key, got {sorted(data)}")
    out = {}
    fields = {f.name for f in dataclasses.fields(NormStats)}
    for key, entry in data["norm_stats"].items():
        out[key] = NormStats(**{k: v for k, v in entry.items() if k in fields and v is not None})
    return out


def save_openpi_norm_stats(path: str | os.PathLike, stats: Mapping[str, NormStats]) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"norm_stats": {k: v.to_json() for k, v in stats.items()}}, indent=2))


# ---------------------------------------------------------------------------------------------------------------------
# LeRobot processor files.

PREPROCESSOR_FILE = "policy_preprocessor.json"
POSTPROCESSOR_FILE = "policy_postprocessor.json"


def _find_step(pipeline_path: Path, registry_name: str) -> dict | None:
    cfg = json.loads(pipeline_path.read_text())
    if "steps" not in cfg:
        raise ValueError(f"{pipeline_path}: not a LeRobot processor config (no 'steps')")
    # Steps are named by registry name, or (unregistered) by full class path, e.g. "...NormalizerProcessorStep".
    class_name = "".join(p.capitalize() for p in registry_name.split("_")[:-1]) + "ProcessorStep"
    for step in cfg["steps"]:
        if step.get("registry_name") == registry_name or str(step.get("class", "")).split(".")[-1] == class_name:
            return step
    return None


def _read_step_stats(step: dict, base: Path) -> dict[str, dict[str, np.ndarray]]:
    """A step's state file -> {feature: {stat: array}} (the flat "<feature>.<stat>" keys split at the last dot)."""
    if "state_file" not in step:
        return {}
    import safetensors.numpy

    state_path = base / step["state_file"]
    if not state_path.is_file():
        raise FileNotFoundError(f"normaliser state file named in the processor config not found: {state_path}")
    out: dict[str, dict[str, np.ndarray]] = {}
    for flat, arr in safetensors.numpy.load_file(str(state_path)).items():
        feature, stat = flat.rsplit(".", 1)
        out.setdefault(feature, {})[stat] = arr
    return out


def _feature_for(step: dict, feature_type: str, default: str) -> str:
    features = step.get("config", {}).get("features", {})
    names = [k for k, v in features.items() if v.get("type") == feature_type]
    if default in names or not names:
        return default
    if len(names) > 1:
        raise ValueError(f"several {feature_type} features in the normaliser config: {names}")
    return names[0]


def _lerobot_entry(step: dict, stats: dict, feature_type: str, default_name: str):
    name = _feature_for(step, feature_type, default_name)
    norm_map = step.get("config", {}).get("norm_map", {})
    mode = Mode(norm_map.get(feature_type, "IDENTITY"))  # raises on e.g. QUANTILE10, naming it
    fields = {f.name for f in dataclasses.fields(NormStats)}
    ns = NormStats(**{k: v for k, v in stats[name].items() if k in fields}) if name in stats else None
    return mode, ns


def load_lerobot_normalizer(directory: str | os.PathLike) -> Normalizer:
    """LeRobot processor files in `directory` -> Normalizer (LeRobot convention).

    The state's mode and stats come from the preprocessor's normalizer step; the actions' from the postprocessor's
    unnormalizer step (falling back to the preprocessor's, which also normalises actions for training).
    """
    directory = Path(directory)
    pre_path = directory / PREPROCESSOR_FILE
    if not pre_path.is_file():
        raise FileNotFoundError(f"LeRobot processor config not found: {pre_path}")
    pre = _find_step(pre_path, "normalizer_processor")
    if pre is None:
        raise ValueError(f"{pre_path}: no normalizer_processor step")
    post_path = directory / POSTPROCESSOR_FILE
    post = _find_step(post_path, "unnormalizer_processor") if post_path.is_file() else None
    act_step = post if post is not None else pre

    stats, modes = {}, {}
    for key, step, ftype, default in ((STATE, pre, "STATE", "observation.state"),
                                      (ACTIONS, act_step, "ACTION", "action")):
        mode, ns = _lerobot_entry(step, _read_step_stats(step, directory), ftype, default)
        modes[key] = mode
        if ns is not None:
            stats[key] = ns
    eps = pre.get("config", {}).get("eps")
    return Normalizer(stats=stats, modes=modes, convention=Convention.LEROBOT, eps=eps, source=str(directory))


# ---------------------------------------------------------------------------------------------------------------------
# Discovery in a converted checkpoint.


def find_norm_stats(root: str | os.PathLike) -> tuple[Convention, Path]:
    """Locate stats under a checkpoint dir: an openpi norm_stats.json anywhere under `root/assets`, else LeRobot
    processor files in `root/assets/**` or `root`. -> (convention, norm_stats.json path or processor dir)."""
    root = Path(root)
    assets = root / "assets"
    found = sorted(assets.rglob("norm_stats.json")) if assets.is_dir() else []
    if len(found) > 1:
        raise ValueError(f"several norm_stats.json under {assets}: {[str(p) for p in found]}; pass one explicitly")
    if found:
        return Convention.OPENPI, found[0]
    candidates = (sorted(assets.rglob(PREPROCESSOR_FILE)) if assets.is_dir() else []) + (
        [root / PREPROCESSOR_FILE] if (root / PREPROCESSOR_FILE).is_file() else [])
    if len(candidates) > 1:
        raise ValueError(f"several {PREPROCESSOR_FILE} under {root}: {[str(p) for p in candidates]}")
    if candidates:
        return Convention.LEROBOT, candidates[0].parent
    raise FileNotFoundError(f"no norm stats under {root}: looked for assets/**/norm_stats.json (openpi) and "
                            f"{PREPROCESSOR_FILE} (LeRobot) in assets/** and the checkpoint root")


def load_normalizer(path: str | os.PathLike, *, use_quantiles: bool) -> Normalizer:
    """A norm_stats.json file, a LeRobot processor dir, or a checkpoint dir to search. `use_quantiles` picks the
    openpi mode (LeRobot files name their own modes)."""
    path = Path(path)
    if path.is_file():
        if path.name == PREPROCESSOR_FILE:
            return load_lerobot_normalizer(path.parent)
        return Normalizer.openpi(load_openpi_norm_stats(path), use_quantiles=use_quantiles, source=str(path))
    if (path / PREPROCESSOR_FILE).is_file():
        return load_lerobot_normalizer(path)
    if (path / "norm_stats.json").is_file():
        return load_normalizer(path / "norm_stats.json", use_quantiles=use_quantiles)
    convention, found = find_norm_stats(path)
    if convention is Convention.LEROBOT:
        return load_lerobot_normalizer(found)
    return Normalizer.openpi(load_openpi_norm_stats(found), use_quantiles=use_quantiles, source=str(found))
