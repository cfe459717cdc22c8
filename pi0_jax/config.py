"""Frozen model configs and the named presets.

Sizes are decoded from variant names in one place (like big_vision's "So400m/14"), never sniffed from paths.
"""

from __future__ import annotations

import dataclasses
import json
from typing import Any

# The PaliGemma SentencePiece vocabulary; only the VLM expert has an embedder.
PALIGEMMA_VOCAB_SIZE = 257152
# Camera slots in the order the prefix is built (spec §5.3).
IMAGE_KEYS = ("base_0_rgb", "left_wrist_0_rgb", "right_wrist_0_rgb")


@dataclasses.dataclass(frozen=True)
class GemmaConfig:
    width: int
    depth: int
    mlp_dim: int
    num_heads: int
    num_kv_heads: int
    head_dim: int


@dataclasses.dataclass(frozen=True)
class SiglipConfig:
    width: int
    depth: int
    mlp_dim: int
    num_heads: int
    patch_size: int = 14
    image_size: int = 224

    @property
    def num_patches(self) -> int:
        return (self.image_size // self.patch_size) ** 2


class _GemmaVariants(dict):
    """The Gemma size table. Besides its entries it knows `<variant>_<n>l` for every entry: the same tower with its
    first n <= depth layers' shapes (layer-dropped checkpoints, `pi0-jax prune`, and shallower distillation students;
    which layers were kept is the checkpoint's business, the shapes only need n)."""

    def _derived(self, key):
        base, _, n = key.rpartition("_")
        if not (dict.__contains__(self, base) and n.endswith("l") and n[:-1].isdigit()):
            return None
        parent = dict.__getitem__(self, base)
        return dataclasses.replace(parent, depth=int(n[:-1])) if 1 <= int(n[:-1]) <= parent.depth else None

    def __missing__(self, key):
        derived = self._derived(key) if isinstance(key, str) else None
        if derived is None:
            raise KeyError(key)
        return derived

    def __contains__(self, key) -> bool:
        return dict.__contains__(self, key) or (isinstance(key, str) and self._derived(key) is not None)

    def get(self, key, default=None):
        return self[key] if key in self else default


GEMMA_VARIANTS: dict[str, GemmaConfig] = _GemmaVariants({
    "gemma_2b": GemmaConfig(width=2048, depth=18, mlp_dim=16_384, num_heads=8, num_kv_heads=1, head_dim=256),
    "gemma_300m": GemmaConfig(width=1024, depth=18, mlp_dim=4096, num_heads=8, num_kv_heads=1, head_dim=256),
    # Test sizes: every dimension distinct, and the expert's attention width (4*16) differs from its width (48),
    # as in the real model (2048 vs 1024).
    "dummy": GemmaConfig(width=64, depth=3, mlp_dim=160, num_heads=4, num_kv_heads=1, head_dim=16),
    "dummy_expert": GemmaConfig(width=48, depth=3, mlp_dim=96, num_heads=4, num_kv_heads=1, head_dim=16),
    # The small model trained in the MJX suite (pi0_small): the expert at half the VLM's width, as 1024 vs 2048.
    "gemma_small": GemmaConfig(width=256, depth=4, mlp_dim=1024, num_heads=4, num_kv_heads=1, head_dim=64),
    "gemma_small_expert": GemmaConfig(width=128, depth=4, mlp_dim=512, num_heads=4, num_kv_heads=1, head_dim=64),
    # Two-layer towers (distillation students, pruned checkpoints), as `_derived` would give them; listed so that
    # converters/detect.py, which matches tensor shapes against the entries, recognises them.
    "gemma_small_2l": GemmaConfig(width=256, depth=2, mlp_dim=1024, num_heads=4, num_kv_heads=1, head_dim=64),
    "gemma_small_expert_2l": GemmaConfig(width=128, depth=2, mlp_dim=512, num_heads=4, num_kv_heads=1, head_dim=64),
    "dummy_2l": GemmaConfig(width=64, depth=2, mlp_dim=160, num_heads=4, num_kv_heads=1, head_dim=16),
    "dummy_expert_2l": GemmaConfig(width=48, depth=2, mlp_dim=96, num_heads=4, num_kv_heads=1, head_dim=16),
})

SIGLIP_VARIANTS: dict[str, SiglipConfig] = {
    "So400m/14": SiglipConfig(width=1152, depth=27, mlp_dim=4304, num_heads=16),
    "dummy": SiglipConfig(width=40, depth=2, mlp_dim=88, num_heads=2),
    "small/14-112": SiglipConfig(width=256, depth=4, mlp_dim=768, num_heads=4, image_size=112),
    # Training tests on CPU (pi0_jax/train "dummy_smoke"): the dummy tower at 56 px, 16 patches per camera.
    "dummy/14-56": SiglipConfig(width=40, depth=2, mlp_dim=88, num_heads=2, image_size=56),
}


@dataclasses.dataclass(frozen=True)
class Pi0Config:
    """One π0 / π0.5 model. `pi05` selects the π0.5 suffix (time MLP -> adaRMS, no state token)."""

    name: str
    pi05: bool
    paligemma_variant: str = "gemma_2b"
    action_expert_variant: str = "gemma_300m"
    siglip_variant: str = "So400m/14"
    vocab_size: int = PALIGEMMA_VOCAB_SIZE
    action_dim: int = 32
    action_horizon: int = 50
    max_token_len: int = 48
    # π0.5 only: write the discretised normalised state into the prompt (spec §9).
    discrete_state_input: bool = False
    # Activation / matmul dtype; params may be stored in any float dtype and are cast at use.
    dtype: str = "bfloat16"
    num_cameras: int = len(IMAGE_KEYS)

    def __post_init__(self):
        for field, table in (
            ("paligemma_variant", GEMMA_VARIANTS),
            ("action_expert_variant", GEMMA_VARIANTS),
            ("siglip_variant", SIGLIP_VARIANTS),
        ):
            if getattr(self, field) not in table:
                raise ValueError(f"unknown {field} {getattr(self, field)!r}; known: {sorted(table)}")
        a, b = self.paligemma, self.action_expert
        if (a.depth, a.num_heads, a.num_kv_heads, a.head_dim) != (b.depth, b.num_heads, b.num_kv_heads, b.head_dim):
            raise ValueError("the two experts must share depth, num_heads, num_kv_heads and head_dim")
        if self.dtype not in ("bfloat16", "float32"):
            raise ValueError(f"dtype must be bfloat16 or float32, got {self.dtype!r}")
        if self.discrete_state_input and not self.pi05:
            raise ValueError("discrete_state_input is a π0.5 feature")

    @property
    def paligemma(self) -> GemmaConfig:
        return GEMMA_VARIANTS[self.paligemma_variant]

    @property
    def action_expert(self) -> GemmaConfig:
        return GEMMA_VARIANTS[self.action_expert_variant]

    @property
    def siglip(self) -> SiglipConfig:
        return SIGLIP_VARIANTS[self.siglip_variant]

    @property
    def image_size(self) -> int:
        return self.siglip.image_size

    @property
    def prefix_len(self) -> int:
        return self.num_cameras * self.siglip.num_patches + self.max_token_len

    @property
    def suffix_len(self) -> int:
        return self.action_horizon + (0 if self.pi05 else 1)

    def replace(self, **kw: Any) -> Pi0Config:
        return dataclasses.replace(self, **kw)

    def to_json(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> Pi0Config:
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"unknown Pi0Config fields {sorted(unknown)}")
        return cls(**d)

    def dumps(self) -> str:
        return json.dumps(self.to_json(), indent=2, sort_keys=True)


PRESETS: dict[str, Pi0Config] = {
    "pi0_base": Pi0Config(name="pi0_base", pi05=False),
    "pi05_base": Pi0Config(name="pi05_base", pi05=True, max_token_len=200, discrete_state_input=True),
    "pi0_libero": Pi0Config(name="pi0_libero", pi05=False),
    # openpi's pi05_libero: horizon 10, the state is not written into the prompt (the model never sees it).
    "pi05_libero": Pi0Config(name="pi05_libero", pi05=True, action_horizon=10, max_token_len=200,
                             discrete_state_input=False),
    # ~7.6 M params: trained on the MJX suite's expert demos (pi0_jax/train), embedded as the demo model.
    # Two cameras (agent view, wrist) at 112 px -> 2 x 64 image tokens; action_dim 8 holds the 8-D state and 7-D
    # actions; the vocabulary is a small SentencePiece model trained on the suite's instructions.
    "pi0_small": Pi0Config(name="pi0_small", pi05=False, paligemma_variant="gemma_small",
                           action_expert_variant="gemma_small_expert", siglip_variant="small/14-112", vocab_size=128,
                           action_dim=8, action_horizon=10, max_token_len=32, num_cameras=2),
    "dummy": Pi0Config(name="dummy", pi05=False, paligemma_variant="dummy", action_expert_variant="dummy_expert",
                       siglip_variant="dummy", vocab_size=1024, action_horizon=10, dtype="float32"),
    "dummy_pi05": Pi0Config(name="dummy_pi05", pi05=True, paligemma_variant="dummy",
                            action_expert_variant="dummy_expert", siglip_variant="dummy", vocab_size=1024,
                            action_horizon=10, max_token_len=200, dtype="float32"),
}


def get_config(name: str, **overrides: Any) -> Pi0Config:
    """A named preset, optionally with fields replaced (`get_config("pi05_base", dtype="float32")`)."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; known: {sorted(PRESETS)}")
    return PRESETS[name].replace(**overrides)
