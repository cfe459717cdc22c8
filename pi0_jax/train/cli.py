"""`pi0-jax train`: train a π0 on expert demonstrations; `pi0-jax distill`: distil a trained one into a 1-2 flow-step
student. `add_train_parser` / `add_distill_parser(subparsers)` are what pi0_jax/cli.py wires in; importing this module
does not import jax."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

DESCRIPTION = """\
Train a π0 from scratch with the flow-matching loss on a demos directory written by scripts/sim_demos.py
(meta.json + episode_*.npz). AdamW with warm-up + cosine decay, gradient clipping, an EMA of the weights, bf16
compute over f32 master weights, data parallel over every local device (the global batch is split among them).
The whole dataset is put on every device once (uint8 images: ~18 GB for the embedded model's 4,400 demos at
112 px) and each batch is gathered, normalised and augmented inside the jitted step.

Writes OUT/: tokenizer.model and norm_stats.json (computed from the demos), train_state/ (orbax, every
--save-every steps, the newest --keep kept), train_log.json, loss.png and, at the end, checkpoint/ (the EMA weights
as a pi0-jax checkpoint with its tokenizer and norm stats; `pi0-jax eval --policy OUT/checkpoint` and
Policy.from_checkpoint load it).
Every batch and noise draw comes from (seed, step), so --resume continues bit-identically.

Pipeline of the demo model (see pi0_jax/train/__init__.py and scripts/gpu_suite.sh):
  python scripts/sim_demos.py DEMOS --episodes-per-task 400 --first-init 50 --resolution 112 --no-compress \
      --action-noise 0.2
  pi0-jax train --config pi0_small_suite --demos DEMOS --out RUN
  pi0-jax eval --policy RUN/checkpoint --resolution 112 --episodes-per-task 50

A fine-tune to a longer action horizon (real-time chunking needs an overlap of the previous chunk to guide):
  pi0-jax train --config pi0_small_suite --init pi0_jax/assets/pi0_small --horizon 20 --steps 4000 --lr 1e-4 \
      --warmup 100 --demos DEMOS --out RUN20
A fine-tune that conditions on up to 4 committed actions (for `pi0-jax eval --execution conditioned`):
  pi0-jax train --config pi0_small_suite --init pi0_jax/assets/pi0_small --max-delay 4 --steps 4000 --lr 1e-4 \
      --warmup 100 --demos DEMOS --out RUN_D4
"""


def add_train_parser(subparsers) -> argparse.ArgumentParser:
    from pi0_jax.train.config import PRESETS

    p = subparsers.add_parser("train", help="train a π0 on expert demonstrations (flow matching, data parallel)",
                              description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", required=True, choices=sorted(PRESETS), metavar="NAME",
                   help=f"training preset: {', '.join(sorted(PRESETS))} (pi0_jax/train/config.py)")
    p.add_argument("--demos", required=True, type=Path, metavar="DIR",
                   help="demonstrations directory (meta.json + episode_*.npz, scripts/sim_demos.py)")
    p.add_argument("--out", required=True, type=Path, metavar="DIR",
                   help="run directory; must hold no train state unless --resume")
    p.add_argument("--init", type=Path, default=None, metavar="CKPT",
                   help="fine-tune: start from the weights of a checkpoint `pi0-jax train` exported, with its model "
                        "config, tokenizer.model and norm stats (the preset still gives the optimiser, schedule and "
                        "batch); default: a fresh init of the preset's model")
    p.add_argument("--horizon", type=int, default=None, metavar="H",
                   help="action horizon (actions per chunk) of the trained model; π0's weights do not depend on it, "
                        "so --init can fine-tune a checkpoint to another horizon; default: the preset's or the "
                        "--init checkpoint's")
    p.add_argument("--max-delay", type=int, default=None, metavar="D",
                   help="training-time action conditioning for real-time execution (Black, Ren, Equi, Levine "
                        "2025): each sample's first d ~ U{0..D} actions are given clean and left out of the loss, "
                        "so the model continues actions already committed (`pi0-jax eval --execution conditioned "
                        "--latency-steps d`); needs D < the horizon; default: the preset's (0, off)")
    _add_run_flags(p, PRESETS.values())
    p.set_defaults(func=run)
    return p


def _preset_default(presets, field: str) -> str:
    """"default: the preset's (V)", V the value (or values) that `presets` give `field`."""
    return f"default: the preset's ({' or '.join(f'{v!r}' for v in sorted({getattr(c, field) for c in presets}))})"


def _add_run_flags(p: argparse.ArgumentParser, presets) -> None:
    """The optimiser, logging and run flags that `train` and `distill` share (None: the preset's); `presets`: the
    subcommand's TrainConfigs (the help quotes their decay_lr, clip_norm, weight_decay, b2 and keep)."""
    p.add_argument("--steps", type=int, default=None, metavar="N",
                   help="total optimizer steps (the cosine schedule ends here); default: the preset's")
    p.add_argument("--batch", type=int, default=None, metavar="B",
                   help="global batch size, a multiple of the local device count; default: the preset's")
    p.add_argument("--lr", type=float, default=None, help="peak learning rate; default: the preset's")
    p.add_argument("--warmup", type=int, default=None, metavar="N", help="linear warm-up steps; default: the preset's")
    p.add_argument("--decay-lr", type=float, default=None, metavar="LR",
                   help="the learning rate the cosine schedule ends at, at --steps (openpi's decay_lr; --lr for a "
                        f"constant rate after the warm-up); {_preset_default(presets, 'decay_lr')}")
    p.add_argument("--ema", type=float, default=None, metavar="DECAY",
                   help="EMA decay of the exported weights; 0 disables the EMA (the raw weights are exported); "
                        "default: the preset's")
    p.add_argument("--clip-norm", type=float, default=None, metavar="NORM",
                   help="gradients are scaled down to this global L2 norm (over all parameters, before AdamW) "
                        f"when above it; inf: no clipping; {_preset_default(presets, 'clip_norm')}")
    p.add_argument("--weight-decay", type=float, default=None, metavar="WD",
                   help="AdamW's decoupled weight decay, per unit of learning rate (each step subtracts "
                        f"lr x WD x the weights); {_preset_default(presets, 'weight_decay')}")
    p.add_argument("--b2", type=float, default=None,
                   help="AdamW's per-step decay of its second-moment (squared gradient) average, in [0, 1); "
                        f"{_preset_default(presets, 'b2')}")
    p.add_argument("--no-augment", action="store_true",
                   help="turn off the image augmentation (crop/resize/rotate on the agent view, colour jitter)")
    p.add_argument("--seed", type=int, default=None,
                   help="seed of the batches and noise (and of train's init); default: the preset's")
    p.add_argument("--log-every", type=int, default=None, metavar="N",
                   help="steps between loss fetches / log lines (the only host syncs); default: the preset's")
    p.add_argument("--save-every", type=int, default=None, metavar="N",
                   help="steps between train-state checkpoints; default: the preset's")
    p.add_argument("--keep", type=int, default=None, metavar="N",
                   help="train-state checkpoints kept in OUT/train_state (the newest N; older ones are deleted); "
                        f"{_preset_default(presets, 'keep')}")
    p.add_argument("--resume", action="store_true",
                   help="continue from the newest OUT/train_state checkpoint (bit-identical to an uninterrupted run)")
    p.add_argument("--stop-at", type=int, default=None, metavar="N",
                   help="save the train state after N steps and exit without exporting (the schedule still runs to "
                        "--steps; continue with --resume)")
    p.add_argument("--max-episodes", type=int, default=None, metavar="N",
                   help="use only the first N episodes of the demos (smoke runs)")


def _overrides(args: argparse.Namespace) -> dict:
    over = {k: v for k, v in {"steps": args.steps, "batch_size": args.batch, "lr": args.lr,
                              "warmup_steps": args.warmup, "decay_lr": args.decay_lr, "clip_norm": args.clip_norm,
                              "weight_decay": args.weight_decay, "b2": args.b2, "seed": args.seed,
                              "log_every": args.log_every, "save_every": args.save_every,
                              "keep": args.keep}.items() if v is not None}
    if args.ema is not None:
        over["ema_decay"] = args.ema or None
    if args.no_augment:
        over["augment"] = False
    return over


def config_from_args(args: argparse.Namespace):
    from pi0_jax.train.config import get_train_config

    return get_train_config(args.config, **_overrides(args))


# the updates, the schedule and the batch stream depend on these: changing them on --resume breaks the exact resume
_RESUME_KEYS = ("model", "batch_size", "lr", "warmup_steps", "decay_lr", "clip_norm", "weight_decay", "b2", "seed",
                "augment", "ema_decay", "max_delay")


def _warn_if_changed(out: Path, mine: dict, keys: tuple[str, ...]) -> None:
    """Warn if OUT/train_config.json differs from `mine` at `keys` or at the TrainConfig's _RESUME_KEYS."""
    saved = out / "train_config.json"
    if saved.is_file():
        prev = json.loads(saved.read_text())
        changed = [k for k in keys if prev.get(k) != mine.get(k)]
        changed += [k for k in _RESUME_KEYS if prev["train"].get(k) != mine["train"].get(k)]
        if changed:
            print(f"warning: resuming with changed {changed}; the run will not match an uninterrupted one")


def run(args: argparse.Namespace) -> int:
    from pi0_jax.train.trainer import train

    try:
        cfg = config_from_args(args)
        if args.max_delay is not None:
            cfg = cfg.replace(max_delay=args.max_delay)
    except ValueError as e:   # a flag out of range: TrainConfig names the field
        raise SystemExit(f"pi0-jax train: {e}") from None
    if args.horizon is not None and args.horizon < 1:
        raise SystemExit(f"--horizon must be positive, got {args.horizon}")
    init = args.init and str(args.init.absolute())
    if args.resume:
        _warn_if_changed(args.out, {"train": cfg.to_json(), "init": init}, ("init",))
    summary = train(cfg, args.demos, args.out, resume=args.resume, stop_at=args.stop_at,
                    max_episodes=args.max_episodes, init=args.init, horizon=args.horizon)
    print(json.dumps(summary, indent=2))
    return 0


DISTILL_DESCRIPTION = """\
Distil a trained π0 (the teacher, a checkpoint that `pi0-jax train` exported) into a student that samples with 1 or
2 Euler flow steps, optionally with fewer transformer layers (--layers: kept in both the PaliGemma and the
action-expert towers, evenly spaced, the first and the last always kept; SigLIP whole). The student starts as the
teacher's weights. Each step draws a batch of observations from the demos as training does (augmented unless
--no-augment: teacher and student see the same augmented view), one noise draw, and fits the student's
--student-steps sample to the teacher's --teacher-steps sample from the same noise (mean squared error in normalised
action space over the demos' real action dims), with the trainer's AdamW, schedule, clipping, EMA, bf16-over-f32
compute and data parallelism (pi0_jax/train/distill.py).

Writes OUT/ as `pi0-jax train` does (train_log.json, loss.png, train_state/, checkpoint/) with the teacher's
tokenizer.model and norm stats; checkpoint/config.json records the teacher, its steps, the student's and the kept
layers, and num_steps, with which `pi0-jax eval --policy OUT/checkpoint` samples unless --num-steps is given.

  pi0-jax distill --teacher RUN/checkpoint --demos DEMOS --out DISTILL --student-steps 1
  pi0-jax eval --policy DISTILL/checkpoint --resolution 112 --episodes-per-task 50
"""


def add_distill_parser(subparsers) -> argparse.ArgumentParser:
    from pi0_jax.train.config import DISTILL_PRESETS

    p = subparsers.add_parser("distill", help="distil a trained π0 into a 1-2 flow-step (and optionally shallower) "
                                              "student", description=DISTILL_DESCRIPTION,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--teacher", required=True, type=Path, metavar="CKPT",
                   help="the teacher: a pi0-jax checkpoint with tokenizer.model and assets/mjx_suite/norm_stats.json "
                        "(`pi0-jax train`'s OUT/checkpoint)")
    p.add_argument("--demos", required=True, type=Path, metavar="DIR",
                   help="demonstrations directory whose observations are distilled on (scripts/sim_demos.py)")
    p.add_argument("--out", required=True, type=Path, metavar="DIR",
                   help="run directory; must hold no train state unless --resume")
    p.add_argument("--config", default="pi0_small_distill", choices=sorted(DISTILL_PRESETS), metavar="NAME",
                   help=f"distillation preset: {', '.join(sorted(DISTILL_PRESETS))} (pi0_jax/train/config.py; "
                        "default: %(default)s)")
    p.add_argument("--student-steps", type=int, default=None, metavar="N",
                   help="Euler steps the student samples with, and is exported to sample with (1 or 2); "
                        "default: the preset's (1)")
    p.add_argument("--teacher-steps", type=int, default=None, metavar="N",
                   help="Euler steps of the teacher's target samples; default: the preset's (10)")
    p.add_argument("--layers", type=int, default=None, metavar="N",
                   help="transformer layers of the student (both experts), at least 2 and at most the teacher's; "
                        "its towers are the `<variant>_<N>l` variants pi0_jax/config.py derives from the teacher's; "
                        "default: the teacher's depth")
    _add_run_flags(p, [c.train for c in DISTILL_PRESETS.values()])
    p.set_defaults(func=run_distill)
    return p


def run_distill(args: argparse.Namespace) -> int:
    from pi0_jax.train.config import get_distill_config
    from pi0_jax.train.distill import distill

    over = {k: v for k, v in {"student_steps": args.student_steps, "teacher_steps": args.teacher_steps,
                              "layers": args.layers}.items() if v is not None}
    try:
        cfg = get_distill_config(args.config, **over, **_overrides(args))
    except ValueError as e:   # a flag out of range: the config names the field
        raise SystemExit(f"pi0-jax distill: {e}") from None
    if args.resume:
        _warn_if_changed(args.out, {**cfg.to_json(), "teacher": str(args.teacher.absolute())},
                         ("student_steps", "teacher_steps", "layers", "teacher"))
    summary = distill(cfg, args.teacher, args.demos, args.out, resume=args.resume, stop_at=args.stop_at,
                      max_episodes=args.max_episodes)
    print(json.dumps(summary, indent=2))
    return 0
