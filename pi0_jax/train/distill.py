"""Flow-step distillation: a trained π0 (the teacher, sampled with `teacher_steps` Euler steps) into a student that
samples with `student_steps` (1 or 2), optionally with fewer transformer layers.

Objective, per batch: observations drawn exactly as the trainer draws them (`step.make_batch`, with the config's
augmentation: teacher and student see the same augmented view, so it only widens the inputs on which the student
matches its teacher), noise eps (B, H, action_dim) ~ N(0, I), and

  loss = mean over (B, H, the demos' real action dims) of (S(obs, eps) - stop_gradient(T(obs, eps)))^2

where T and S are `pi0.sample_actions` of the teacher (teacher_steps) and the student (student_steps) from the same
eps, in normalised action space. The model's action_dim - 7 padding dims of the final sample are left out: the
policy reads only the first 7 (the demos' action dims). Within a multi-step sampler they do feed back (x_t enters the
next velocity whole), so the student's own intermediate padding values are left free rather than matched.

Differentiating the student's sampler: `pi0.sample_actions` loops with `lax.fori_loop` over a Python-int trip
count, which JAX lowers to a `scan`, and scans are reverse-differentiable; so the student is trained through the
very function the policy samples with. The teacher's sampler runs forward only inside the same jitted step.

Student init: the teacher's f32 params, with `layers` of its transformer layers kept (`layer_indices`: evenly
spaced, the first and the last included). The PaliGemma and the action-expert towers are one scanned subtree,
`PaliGemma/llm/layers/*` (`*_1` the expert), with a leading L axis, so slicing it slices both; SigLIP's
`PaliGemma/img/Transformer/encoderblock` is kept whole. The student's config names the `<variant>_<n>l` GemmaConfig
variants of pi0_jax/config.py.

OUT/ is the trainer's layout (pi0_jax/train/trainer.py), through the same loop (logging, train-state checkpoints,
exact resume), except that tokenizer.model and norm_stats.json are the teacher's (the student reads and writes the
same normalised values) and checkpoint/ is the student, whose config.json also records the teacher, teacher_steps,
student_steps, the kept layers and `num_steps` = student_steps (`pi0-jax eval` samples with it by default).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from flax import traverse_util
from jax.sharding import Mesh

from pi0_jax import normalize as nz
from pi0_jax import pi0
from pi0_jax.config import GEMMA_VARIANTS, Pi0Config
from pi0_jax.train import data as data_lib
from pi0_jax.train import step as step_lib
from pi0_jax.train import trainer
from pi0_jax.train.config import DistillConfig

LAYERS = ("PaliGemma", "llm", "layers")      # the scanned Gemma blocks of both experts: leaves (L, ...)


# ---------------------------------------------------------------------------------------------------------------------
# The student.


def layer_indices(depth: int, layers: int) -> tuple[int, ...]:
    """`layers` of `depth` layers, evenly spaced, the first and the last included: (4, 2) -> (0, 3),
    (18, 4) -> (0, 6, 11, 17), (3, 3) -> (0, 1, 2)."""
    if not 2 <= layers <= depth:
        raise ValueError(f"layers must be in [2, {depth}] (the teacher's depth), got {layers}")
    # the spacing (depth - 1) / (layers - 1) >= 1, so the rounded indices are distinct
    return tuple(int(i) for i in np.round(np.linspace(0, depth - 1, layers)))


def student_config(teacher: Pi0Config, layers: int) -> Pi0Config:
    """The teacher's config with both experts `layers` deep: the GemmaConfig variants `<variant>_<layers>l`."""
    if layers == teacher.paligemma.depth:
        return teacher
    names = {f: f"{getattr(teacher, f)}_{layers}l" for f in ("paligemma_variant", "action_expert_variant")}
    for field, name in names.items():
        want = dataclasses.replace(GEMMA_VARIANTS[getattr(teacher, field)], depth=layers)
        if GEMMA_VARIANTS.get(name) != want:
            raise ValueError(f"GEMMA_VARIANTS derives no {name!r} = {want} (it derives `<entry>_<n>l` from its "
                             f"own entries only, for 1 <= n <= depth)")
    return teacher.replace(name=f"{teacher.name}_{layers}l", **names)


def slice_layers(params: dict, keep: tuple[int, ...]) -> dict:
    """The param tree with only the layers `keep` of both Gemma experts (SigLIP and the projections unchanged)."""
    idx = np.asarray(keep)
    flat = traverse_util.flatten_dict(params)
    return traverse_util.unflatten_dict({k: v[idx] if k[: len(LAYERS)] == LAYERS else v for k, v in flat.items()})


# ---------------------------------------------------------------------------------------------------------------------
# The loss and the jitted step.


def draw(cfg: DistillConfig, model: Pi0Config, data: dict, rng: jax.Array, shard) -> tuple[pi0.Observation, jax.Array]:
    """One batch of observations (as a train step draws them) and of noise (B, H, action_dim) from `rng`."""
    k_batch, k_noise = jax.random.split(rng)
    obs, actions = step_lib.make_batch(cfg.train, model, data, k_batch, shard)
    return obs, shard(jax.random.normal(k_noise, actions.shape, jnp.float32))


def student_loss(cfg: DistillConfig, model: Pi0Config, params, obs: pi0.Observation, noise: jax.Array,
                 target: jax.Array, real_dims: int) -> jax.Array:
    """Mean squared error of the student's `student_steps` sample against `target` over the real action dims."""
    actions = pi0.sample_actions(model, params, obs, noise, num_steps=cfg.student_steps)
    return jnp.mean(jnp.square(actions - target)[..., :real_dims])


def teacher_actions(cfg: DistillConfig, model: Pi0Config, params, obs: pi0.Observation, noise: jax.Array):
    return jax.lax.stop_gradient(pi0.sample_actions(model, params, obs, noise, num_steps=cfg.teacher_steps))


def distill_step(cfg: DistillConfig, teacher: Pi0Config, student: Pi0Config, mesh: Mesh, state: step_lib.TrainState,
                 teacher_params, data: dict):
    """One AdamW step of the student on one batch. -> (new state, {"loss", "grad_norm", "lr"})."""
    shard = step_lib.batch_sharder(mesh)
    obs, noise = draw(cfg, student, data, step_lib.step_key(cfg.train, state.step), shard)
    target = teacher_actions(cfg, teacher, teacher_params, obs, noise)
    real_dims = data["actions"].shape[-1]
    return step_lib.optimizer_step(
        cfg.train, state, lambda params: student_loss(cfg, student, params, obs, noise, target, real_dims))


def batch_loss(cfg: DistillConfig, teacher: Pi0Config, student: Pi0Config, teacher_params, params, data: dict,
               rng: jax.Array) -> jax.Array:
    """The distillation loss of student `params` on one batch drawn from `rng` as a step draws it (no sharding
    constraint): for comparing weights on the same inputs."""
    obs, noise = draw(cfg, student, data, rng, lambda x: x)
    target = teacher_actions(cfg, teacher, teacher_params, obs, noise)
    return student_loss(cfg, student, params, obs, noise, target, data["actions"].shape[-1])


@functools.lru_cache(maxsize=8)
def jitted_step(cfg: DistillConfig, teacher: Pi0Config, student: Pi0Config, mesh: Mesh):
    """`step(state, teacher_params, data) -> (state, metrics)`, compiled once per (configs, mesh); the state is
    donated."""
    rep = step_lib.replicated(mesh)
    return jax.jit(functools.partial(distill_step, cfg, teacher, student, mesh), out_shardings=(rep, rep),
                   donate_argnums=0)


# ---------------------------------------------------------------------------------------------------------------------


def distill(cfg: DistillConfig, teacher_dir: str | Path, demos_dir: str | Path, out_dir: str | Path, *,
            resume: bool = False, stop_at: int | None = None, max_episodes: int | None = None, log=print) -> dict:
    """Distil the teacher checkpoint on the demos' observations, writing OUT/ as the module docstring says.
    -> summary dict (trainer.finish's). stop_at / resume as in `trainer.train`."""
    teacher_dir = Path(teacher_dir).absolute()
    teacher, teacher_params = trainer.load_trained(teacher_dir, "teacher")
    keep = layer_indices(teacher.paligemma.depth, cfg.layers or teacher.paligemma.depth)
    student = student_config(teacher, len(keep))
    out, mesh = trainer.open_run(cfg.train, out_dir, resume)

    tok_path, stats_path = trainer.copy_inputs(teacher_dir, out, resume)
    t0 = time.perf_counter()
    ds = data_lib.load_demos(demos_dir, data_lib.suite_prompts(), tok_path, student.max_token_len,
                             max_episodes=max_episodes, log=log)
    stats = nz.load_openpi_norm_stats(stats_path)
    trainer.check_stats(stats, ds, teacher_dir)
    (out / "train_config.json").write_text(json.dumps(
        {**cfg.to_json(), "model": student.to_json(), "teacher": str(teacher_dir), "teacher_model": teacher.to_json(),
         "teacher_layers": keep, "demos": str(demos_dir)}, indent=2) + "\n")
    data = step_lib.device_data(ds, stats, mesh)
    trainer.log_data(ds, mesh, cfg.train, time.perf_counter() - t0, log)
    del ds
    log(f"teacher {teacher.name} ({cfg.teacher_steps} steps) -> student {student.name} ({cfg.student_steps} "
        f"step(s), teacher layers {list(keep)})")

    jitted = jitted_step(cfg, teacher, student, mesh)
    teacher_dev = jax.device_put(teacher_params, step_lib.replicated(mesh))
    state, history, start, end, compile_s = trainer.run_steps(
        cfg.train, out, mesh, lambda: step_lib.state_from_params(cfg.train, slice_layers(teacher_params, keep)),
        lambda s: jitted(s, teacher_dev, data), resume=resume, stop_at=stop_at, log=log)
    meta = {"trained_by": "pi0_jax.train.distill", "train_config": cfg.to_json(), "num_steps": cfg.student_steps,
            "distill": {"teacher": str(teacher_dir), "teacher_steps": cfg.teacher_steps,
                        "student_steps": cfg.student_steps, "layers": student.paligemma.depth,
                        "teacher_layers": list(keep)}}
    return trainer.finish(cfg.train, out, mesh, state, history, start, end, compile_s,
                          lambda: trainer.export_model(student, state, out, meta),
                          f"{cfg.name}: {teacher.name} x{cfg.teacher_steps} -> {student.name} x{cfg.student_steps}",
                          "distillation MSE (window mean)", log)
