"""Training configs: frozen dataclasses and their named presets. Data and output directories come from the command
line; a distillation's teacher checkpoint too."""

from __future__ import annotations

import dataclasses
from typing import Any

from pi0_jax.config import Pi0Config, get_config


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    name: str
    model: str | None                   # a pi0_jax.config preset; None where a checkpoint brings it (distillation)
    steps: int
    batch_size: int                     # global: split over the local devices, so a multiple of their number
    lr: float                           # peak learning rate
    warmup_steps: int
    decay_lr: float                     # the cosine ends here, at `steps`
    clip_norm: float = 1.0              # global gradient norm
    weight_decay: float = 1e-10         # openpi's AdamW: b1 0.9, b2 0.95, eps 1e-8, weight decay 1e-10
    b2: float = 0.95
    ema_decay: float | None = 0.999     # None: no EMA; the exported weights are the EMA's when it is on
    augment: bool = True                # spec §5.1 training augmentation
    seed: int = 0
    log_every: int = 50
    save_every: int = 1000
    keep: int = 2                       # train-state checkpoints kept
    model_overrides: tuple[tuple[str, Any], ...] = ()   # Pi0Config fields replaced in the preset
    # Training-time action conditioning (Black, Ren, Equi, Levine 2025): each sample's first d ~ U{0..max_delay}
    # actions are given clean (flow time 0) and left out of the loss, so the model learns to continue committed
    # actions (`pi0-jax eval --execution conditioned`). 0: plain flow matching.
    max_delay: int = 0

    def __post_init__(self):
        for f in ("steps", "batch_size", "log_every", "save_every", "keep"):
            if getattr(self, f) <= 0:
                raise ValueError(f"{f} must be positive, got {getattr(self, f)}")
        if self.max_delay < 0:
            raise ValueError(f"max_delay must be >= 0, got {self.max_delay}")
        for f in ("lr", "decay_lr"):
            if not getattr(self, f) >= 0:
                raise ValueError(f"{f} must be >= 0, got {getattr(self, f)}")
        if not self.clip_norm > 0:
            raise ValueError(f"clip_norm must be positive (inf: no clipping), got {self.clip_norm}")
        if not self.weight_decay >= 0:
            raise ValueError(f"weight_decay must be >= 0, got {self.weight_decay}")
        if not 0.0 <= self.b2 < 1.0:
            raise ValueError(f"b2 must be in [0, 1), got {self.b2}")
        if self.ema_decay is not None and not 0.0 <= self.ema_decay < 1.0:
            raise ValueError(f"ema_decay must be in [0, 1), got {self.ema_decay}")

    @property
    def model_config(self) -> Pi0Config:
        if self.model is None:
            raise ValueError(f"train config {self.name!r} names no model (a distillation config: its teacher does)")
        return get_config(self.model, **dict(self.model_overrides))

    def replace(self, **kw: Any) -> TrainConfig:
        return dataclasses.replace(self, **kw)

    def to_json(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["model_overrides"] = dict(self.model_overrides)
        return d


PRESETS: dict[str, TrainConfig] = {
    # The embedded demo model: pi0_small from scratch on 400 DART expert demos per task at 112 px (~254 k frames).
    # On one H100: 8,780 samples/s at batch 256, so 22k steps (5.6 M samples, ~22 passes) take ~11 minutes plus
    # ~40 s of compilation.
    "pi0_small_suite": TrainConfig(name="pi0_small_suite", model="pi0_small", steps=22_000, batch_size=256, lr=5e-4,
                                   warmup_steps=500, decay_lr=2.5e-5, log_every=100, save_every=2500),
    # CPU smoke / tests: the dummy model shaped like pi0_small (2 cameras, 8-D actions, 32 tokens) at 56 px.
    "dummy_smoke": TrainConfig(name="dummy_smoke", model="dummy", steps=20, batch_size=8, lr=3e-3, warmup_steps=2,
                               decay_lr=3e-4, ema_decay=0.9, log_every=2, save_every=10,
                               model_overrides=(("siglip_variant", "dummy/14-56"), ("num_cameras", 2),
                                                ("action_dim", 8), ("max_token_len", 32))),
}


def get_train_config(name: str, **overrides: Any) -> TrainConfig:
    if name not in PRESETS:
        raise ValueError(f"unknown train config {name!r}; known: {sorted(PRESETS)}")
    return PRESETS[name].replace(**overrides)


@dataclasses.dataclass(frozen=True)
class DistillConfig:
    """Flow-step distillation (pi0_jax/train/distill.py): the optimiser, batch and EMA settings of `train` (model
    None: the student's architecture is the teacher checkpoint's, `layers` deep), the teacher's Euler step count
    (its targets) and the student's (what it is trained, and exported, to sample with)."""

    train: TrainConfig
    student_steps: int = 1
    teacher_steps: int = 10
    layers: int | None = None           # transformer layers kept in both experts; None: the teacher's depth

    def __post_init__(self):
        if self.train.model is not None:
            raise ValueError(f"a distillation's train config names no model (the teacher's), got {self.train.model!r}")
        for f in ("student_steps", "teacher_steps"):
            if getattr(self, f) <= 0:
                raise ValueError(f"{f} must be positive, got {getattr(self, f)}")
        if self.layers is not None and self.layers < 2:
            raise ValueError(f"layers must be >= 2 (the first and the last are always kept), got {self.layers}")

    @property
    def name(self) -> str:
        return self.train.name

    def replace(self, **kw: Any) -> DistillConfig:
        """Fields of DistillConfig or, by name, of its TrainConfig (`steps=..., layers=...`)."""
        own = {f.name for f in dataclasses.fields(self)} - {"train"}
        train = self.train.replace(**{k: v for k, v in kw.items() if k not in own})
        return dataclasses.replace(self, train=train, **{k: v for k, v in kw.items() if k in own})

    def to_json(self) -> dict[str, Any]:
        return {"train": self.train.to_json(), "student_steps": self.student_steps,
                "teacher_steps": self.teacher_steps, "layers": self.layers}


DISTILL_PRESETS: dict[str, DistillConfig] = {
    # pi0_small_suite's model -> 1 Euler step: the student starts at the teacher, so a lower peak lr and a short
    # warm-up; each step also runs the teacher's 10-step sampler (forward only) on the batch. docs/RESULTS.md ran
    # 3,000 steps (~2 minutes on one H100).
    "pi0_small_distill": DistillConfig(TrainConfig(name="pi0_small_distill", model=None, steps=3000, batch_size=256,
                                                   lr=1e-4, warmup_steps=100, decay_lr=1e-5, log_every=50,
                                                   save_every=500)),
    # CPU tests: a dummy_smoke teacher.
    "dummy_distill": DistillConfig(TrainConfig(name="dummy_distill", model=None, steps=10, batch_size=8, lr=1e-3,
                                               warmup_steps=1, decay_lr=1e-4, ema_decay=0.9, log_every=2,
                                               save_every=5)),
}


def get_distill_config(name: str, **overrides: Any) -> DistillConfig:
    if name not in DISTILL_PRESETS:
        raise ValueError(f"unknown distillation config {name!r}; known: {sorted(DISTILL_PRESETS)}")
    return DISTILL_PRESETS[name].replace(**overrides)
