"""The training loop: data -> device, jitted steps, logging, train-state checkpoints, resume, export.

Layout of OUT/ (`train(cfg, demos, out)`; distill.py writes the same through the same loop):
  tokenizer.model        SentencePiece model trained on the suite's prompts (kept on resume)
  norm_stats.json        openpi norm stats of the demos' state and actions (kept on resume)
  train_config.json      the TrainConfig and the model config
  train_state/<step>/    orbax checkpoints of the full TrainState (step, f32 params, AdamW state, EMA), every
                         `save_every` steps and at the end, the newest `keep` kept; each written atomically
  train_log.json         per log step: loss and grad norm (means over the window), lr, samples/s
  loss.png               the loss curve
  checkpoint/            the exported pi0-jax checkpoint (EMA weights in the model's dtype, tokenizer.model,
                         assets/mjx_suite/norm_stats.json): `pi0-jax eval --policy OUT/checkpoint` loads it as is

Resume (`resume=True`) restores the newest train_state/ and continues; as every step's batch and noise are drawn
from fold_in(key(seed), step), the continued run is bit-identical to one that was never interrupted.
"""

from __future__ import annotations

import json
import shutil
import sys
import time
from collections.abc import Callable
from pathlib import Path

import jax
import numpy as np
import orbax.checkpoint as ocp
from jax.sharding import Mesh

from pi0_jax import checkpoint as ckpt_lib
from pi0_jax import normalize as nz
from pi0_jax.config import Pi0Config
from pi0_jax.train import data as data_lib
from pi0_jax.train import step as step_lib
from pi0_jax.train.config import TrainConfig

ASSET_ID = "mjx_suite"


# ---------------------------------------------------------------------------------------------------------------------
# Train-state checkpoints: the state's leaves in tree order, keyed by index (the tree structure comes from the config).


def _state_dirs(root: Path) -> list[Path]:
    return sorted((p for p in root.glob("[0-9]" * 8) if p.is_dir()), key=lambda p: int(p.name)) if root.is_dir() else []


def save_state(root: Path, state: step_lib.TrainState, keep: int) -> Path:
    step = int(jax.device_get(state.step))
    leaves = jax.device_get(jax.tree.leaves(state))
    dst = root / f"{step:08d}"
    with ckpt_lib.atomic_directory(dst, overwrite=True) as tmp, ocp.PyTreeCheckpointer() as ckptr:
        ckptr.save(tmp / "state", {f"{i:05d}": np.asarray(x) for i, x in enumerate(leaves)})
    for old in _state_dirs(root)[:-keep]:
        shutil.rmtree(old)
    return dst


def restore_state(path: Path, template: step_lib.TrainState, sharding) -> step_lib.TrainState:
    """Read a saved state into the structure (and check the shapes / dtypes) of `template`."""
    want, treedef = jax.tree.flatten(template)
    with ocp.PyTreeCheckpointer() as ckptr:
        # the item comes from the template (keys "00000".. in leaf order): metadata reading differs across orbax
        # versions, and a count mismatch still fails in restore
        item = {f"{i:05d}": np.zeros(w.shape, w.dtype) for i, w in enumerate(want)}
        args = jax.tree.map(lambda _: ocp.RestoreArgs(restore_type=np.ndarray), item)
        flat = ckptr.restore(path / "state", args=ocp.args.PyTreeRestore(item=item, restore_args=args))
    have = [flat[k] for k in sorted(flat)]
    if len(have) != len(want):
        raise ValueError(f"{path}: {len(have)} arrays, the config's train state has {len(want)}")
    for i, (h, w) in enumerate(zip(have, want)):
        if h.shape != w.shape or h.dtype != w.dtype:
            raise ValueError(f"{path}: leaf {i} is {h.dtype}{h.shape}, expected {w.dtype}{w.shape}")
    return jax.device_put(jax.tree.unflatten(treedef, have), sharding)


# ---------------------------------------------------------------------------------------------------------------------
# Logs.


def plot_loss(log: list[dict], path: Path, title: str, ylabel: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = [r["step"] for r in log]
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.plot(steps, [r["loss"] for r in log], label="loss")
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel(ylabel)
    ax.grid(True, which="both", alpha=0.3)
    lr_ax = ax.twinx()
    lr_ax.plot(steps, [r["lr"] for r in log], color="tab:orange", alpha=0.6, label="lr")
    lr_ax.set_ylabel("learning rate")
    ax.set_title(title)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def export_model(model: Pi0Config, state: step_lib.TrainState, out: Path, meta: dict) -> Path:
    """OUT/checkpoint: the EMA (else the raw) weights in the model's dtype, with OUT/tokenizer.model and
    OUT/norm_stats.json, and `meta` (plus the step and which weights) in its config.json."""
    params = state.ema if state.ema is not None else state.params
    params = jax.device_get(jax.tree.map(lambda x: x.astype(model.dtype), params))
    return ckpt_lib.save_checkpoint(
        out / "checkpoint", params, model, overwrite=True,
        assets={"tokenizer.model": out / "tokenizer.model", f"{ASSET_ID}/norm_stats.json": out / "norm_stats.json"},
        extra_meta={**meta, "step": int(state.step), "weights": "ema" if state.ema is not None else "params"})


def load_trained(path: Path, role: str) -> tuple[Pi0Config, dict]:
    """(config, f32 params) of a pi0-jax checkpoint that holds the trainer's tokenizer and norm stats (a teacher to
    distil from, or the start of a fine-tune)."""
    for rel in ("tokenizer.model", f"assets/{ASSET_ID}/norm_stats.json"):
        if not (path / rel).is_file():
            raise FileNotFoundError(f"{role} {path} has no {rel}: pass a checkpoint that `pi0-jax train` exported")
    if "quant" in ckpt_lib.read_meta(path):
        raise ValueError(f"{role} {path} is quantised; start from the full-precision checkpoint")
    return ckpt_lib.load_checkpoint(path, dtype="float32")


def copy_inputs(src: Path, out: Path, resume: bool) -> tuple[Path, Path]:
    """OUT/tokenizer.model and OUT/norm_stats.json from a trained checkpoint (kept on resume), so that the run reads
    and writes the same tokens and normalised values as the model it starts from."""
    tok_path, stats_path = out / "tokenizer.model", out / "norm_stats.json"
    for a, b in ((src / "tokenizer.model", tok_path), (src / "assets" / ASSET_ID / "norm_stats.json", stats_path)):
        if not (resume and b.is_file()):
            shutil.copyfile(a, b)
    return tok_path, stats_path


def check_stats(stats: dict, ds: data_lib.Dataset, src: Path) -> None:
    for key, have in ((nz.STATE, ds.state), (nz.ACTIONS, ds.actions)):
        if stats[key].mean.shape != have.shape[1:]:
            raise ValueError(f"{src}'s {key} norm stats are {stats[key].mean.shape[0]}-D, the demos' {key} "
                             f"{have.shape[1]}-D")


def export(cfg: TrainConfig, state: step_lib.TrainState, out: Path) -> Path:
    return export_model(cfg.model_config, state, out, {"trained_by": "pi0_jax.train", "train_config": cfg.to_json()})


# ---------------------------------------------------------------------------------------------------------------------
# The run: shared by `train` and pi0_jax.train.distill.


def open_run(cfg: TrainConfig, out_dir: str | Path, resume: bool) -> tuple[Path, Mesh]:
    """Check the batch against the devices and OUT/train_state against `resume`; make OUT. -> (absolute OUT, mesh)"""
    out = Path(out_dir).absolute()    # orbax wants absolute paths
    mesh = step_lib.make_mesh()
    if cfg.batch_size % mesh.devices.size:
        raise ValueError(f"batch size {cfg.batch_size} is not a multiple of the {mesh.devices.size} local devices")
    saved = _state_dirs(out / "train_state")
    if saved and not resume:
        raise FileExistsError(f"{out / 'train_state'} holds checkpoints; pass --resume to continue, or use a new --out")
    if resume and not saved:
        raise FileNotFoundError(f"--resume: no train state under {out / 'train_state'}")
    out.mkdir(parents=True, exist_ok=True)
    return out, mesh


def log_data(ds: data_lib.Dataset, mesh: Mesh, cfg: TrainConfig, seconds: float, log) -> None:
    log(f"data: {ds.num_episodes} episodes, {ds.num_frames} frames at {ds.resolution} px "
        f"({ds.images.nbytes / 2**30:.2f} GiB of images) in {seconds:.1f} s; "
        f"{mesh.devices.size} device(s) {mesh.devices.flat[0].platform}, global batch {cfg.batch_size}")


def run_steps(cfg: TrainConfig, out: Path, mesh: Mesh, init: Callable[[], step_lib.TrainState], step_fn, *,
              resume: bool, stop_at: int | None, log) -> tuple[step_lib.TrainState, list[dict], int, int, float | None]:
    """Start from `init()` (or, with resume, from the newest OUT/train_state in its structure) and apply
    `step_fn(state) -> (state, {"loss", "grad_norm", "lr"})` up to cfg.steps (or stop_at): log every log_every
    steps to OUT/train_log.json, save the train state every save_every steps and at the end.
    -> (state, log rows, first step, last step, seconds of the first (compiling) step)"""
    rep = step_lib.replicated(mesh)
    if resume:
        saved = _state_dirs(out / "train_state")[-1]
        state = restore_state(saved, jax.eval_shape(init), rep)
        log(f"resumed from {saved} (step {int(state.step)})")
    else:
        state = jax.device_put(init(), rep)
    start = int(state.step)
    log_path = out / "train_log.json"
    history = json.loads(log_path.read_text())["log"] if resume and log_path.is_file() else []
    history = [r for r in history if r["step"] <= start]

    tty = sys.stderr.isatty()
    from tqdm import tqdm

    bar = tqdm(total=cfg.steps, initial=start, disable=not tty, unit="step", dynamic_ncols=True)
    pending, t_window, compile_s, paused, n_window_start = [], time.perf_counter(), None, 0.0, start
    end = cfg.steps if stop_at is None else min(stop_at, cfg.steps)
    for step in range(start, end):
        state, metrics = step_fn(state)
        pending.append(metrics)
        if compile_s is None:          # the first call compiles: time it apart from the throughput windows
            jax.block_until_ready(metrics)
            compile_s = time.perf_counter() - t_window
            t_window, n_window_start = time.perf_counter(), step + 1
            first = jax.device_get(metrics)
            log(f"step {step + 1}: first step (compile + run) {compile_s:.1f} s, loss {float(first['loss']):.4f}")
        done = step + 1
        bar.update(1)
        if done % cfg.log_every == 0 or done == end:
            fetched = jax.device_get(pending)
            now = time.perf_counter()
            n = max(done - n_window_start, 0)
            row = {"step": done, "loss": float(np.mean([m["loss"] for m in fetched])),
                   "grad_norm": float(np.mean([m["grad_norm"] for m in fetched])),
                   "lr": float(fetched[-1]["lr"]),
                   "samples_per_s": n * cfg.batch_size / (now - t_window - paused) if n else None}
            history.append(row)
            sps = f"{row['samples_per_s']:.0f}" if row["samples_per_s"] else "-"
            bar.set_postfix(loss=f"{row['loss']:.4f}", lr=f"{row['lr']:.2e}", samples_s=sps)
            if not tty:
                log(f"step {done}/{cfg.steps} loss {row['loss']:.4f} grad_norm {row['grad_norm']:.3f} "
                    f"lr {row['lr']:.2e} samples/s {sps}")
            pending, t_window, n_window_start, paused = [], time.perf_counter(), done, 0.0
        if done % cfg.save_every == 0 or done == end:
            jax.block_until_ready(state)
            t_save = time.perf_counter()
            save_state(out / "train_state", state, cfg.keep)
            log_path.write_text(json.dumps({"config": cfg.name, "log": history}, indent=1) + "\n")
            paused += time.perf_counter() - t_save      # checkpoint time is not training throughput
    bar.close()
    log_path.write_text(json.dumps({"config": cfg.name, "log": history}, indent=1) + "\n")
    return state, history, start, end, compile_s


def finish(cfg: TrainConfig, out: Path, mesh: Mesh, state: step_lib.TrainState, history: list[dict], start: int,
           end: int, compile_s: float | None, export_fn: Callable[[], Path], title: str, ylabel: str, log) -> dict:
    """After run_steps: at cfg.steps plot OUT/loss.png and `export_fn()`. -> summary dict."""
    if end < cfg.steps:
        log(f"stopped at step {end} of {cfg.steps}; continue with --resume")
        return {"steps": cfg.steps, "start_step": start, "stopped_at": end, "compile_s": compile_s}
    if history:
        plot_loss(history, out / "loss.png", title, ylabel)
    ckpt = export_fn()
    rates = [r["samples_per_s"] for r in history[len(history) // 2:] if r["samples_per_s"]]
    summary = {"steps": cfg.steps, "start_step": start, "final_loss": history[-1]["loss"] if history else None,
               "compile_s": compile_s, "samples_per_s": float(np.median(rates)) if rates else None,
               "checkpoint": str(ckpt), "devices": mesh.devices.size}
    log(f"exported {ckpt} (step {int(state.step)}); final loss {summary['final_loss']}")
    return summary


def train(cfg: TrainConfig, demos_dir: str | Path, out_dir: str | Path, *, resume: bool = False,
          stop_at: int | None = None, max_episodes: int | None = None, init: str | Path | None = None,
          horizon: int | None = None, log=print) -> dict:
    """Train `cfg` on the demos, writing OUT/ as the module docstring says. -> summary dict.

    stop_at: save the train state after this many steps and return without exporting (the schedule still runs to
    cfg.steps; continue with resume=True).
    init: a checkpoint `train` exported: start from its weights (a fine-tune); its model config, tokenizer and norm
    stats replace the preset's model and the ones computed from the demos.
    horizon: the action horizon of the trained model. π0's weights do not depend on it (the suffix is one token per
    action, positions by RoPE), so a checkpoint trained at one horizon can be fine-tuned to another."""
    out, mesh = open_run(cfg, out_dir, resume)
    init_params = None
    if init is not None:
        init = Path(init).absolute()
        model, init_params = load_trained(init, "--init")
        tok_path, stats_path = copy_inputs(init, out, resume)
    else:
        model = cfg.model_config
        tok_path, stats_path = out / "tokenizer.model", out / "norm_stats.json"
        if not (resume and tok_path.is_file()):   # computed once and kept: a resumed run sees the same inputs
            tok_path.write_bytes(data_lib.train_tokenizer(data_lib.suite_prompts(), min(model.vocab_size, 128)))
    if horizon is not None:
        model = model.replace(action_horizon=horizon)
    t0 = time.perf_counter()
    ds = data_lib.load_demos(demos_dir, data_lib.suite_prompts(), tok_path, model.max_token_len,
                             max_episodes=max_episodes, log=log)
    if init is not None or (resume and stats_path.is_file()):
        stats = nz.load_openpi_norm_stats(stats_path)
        check_stats(stats, ds, init or stats_path)
    else:
        stats = data_lib.norm_stats(ds)
        nz.save_openpi_norm_stats(stats_path, stats)
    (out / "train_config.json").write_text(json.dumps({"train": cfg.to_json(), "model": model.to_json(),
                                                       "demos": str(demos_dir), "init": init and str(init)},
                                                      indent=2) + "\n")
    data = step_lib.device_data(ds, stats, mesh)
    log_data(ds, mesh, cfg, time.perf_counter() - t0, log)
    del ds

    jitted = step_lib.jitted_step(cfg, model, mesh)
    start_state = ((lambda: step_lib.state_from_params(cfg, init_params)) if init_params is not None
                   else (lambda: step_lib.init_state(cfg, model)))
    state, history, start, end, compile_s = run_steps(cfg, out, mesh, start_state, lambda s: jitted(s, data),
                                                      resume=resume, stop_at=stop_at, log=log)
    meta = {"trained_by": "pi0_jax.train", "train_config": cfg.to_json(), **({"init": str(init)} if init else {})}
    return finish(cfg, out, mesh, state, history, start, end, compile_s, lambda: export_model(model, state, out, meta),
                  f"{cfg.name} ({model.name}, batch {cfg.batch_size})", "flow-matching loss (window mean)", log)
