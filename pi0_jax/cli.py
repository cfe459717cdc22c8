"""`pi0-jax`: the command-line front door. Subcommands are thin entry points over the package.

  pi0-jax convert SRC DST   PyTorch (openpi / LeRobot) checkpoint -> pi0-jax checkpoint
  pi0-jax demo              evaluate the embedded trained pi0_small in the MJX suite (success table, video)
  pi0-jax benchmark         per-stage latency of the compiled engine over steps x batch x dtype
  pi0-jax quantize SRC DST  FP8 quantised checkpoint (calibrated static activation scales), accuracy report
  pi0-jax train             train a π0 on expert demonstrations (pi0_jax/train)
  pi0-jax distill           distil a trained π0 into a 1-2 flow-step (optionally shallower) student
  pi0-jax prune SRC DST     drop transformer layers (both Gemma towers) from a checkpoint
  pi0-jax serve [CKPT]      serve a policy over openpi's websocket protocol (dynamic batching, /healthz)
"""

from __future__ import annotations

import argparse
import sys
from importlib import resources
from pathlib import Path

EMBEDDED_MODEL = "pi0_small"   # pi0_jax/assets/pi0_small: trained in the MJX suite (scripts/gpu_suite.sh)


def _demo_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "demo", help="evaluate the embedded trained π0 (pi0_small) in the MJX task suite (CPU is enough)",
        description="Evaluate the embedded model -- a small π0 (7.9 M params, pi0_small) trained with the "
                    "flow-matching loss on the suite's expert demonstrations -- in the MJX table-top suite: "
                    "K episodes per task from the fixed initial states, both cameras rendered at the model's "
                    "112 px, action chunks of 10, 5 executed per call. Prints the success table and writes "
                    "DIR/eval_info.json and DIR/videos/*.mp4. About 3-5 minutes on two CPU cores with the "
                    "defaults (the first segment includes ~1 minute of compilation).",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--output-dir", type=Path, default=Path("pi0-jax-demo"), metavar="DIR",
                   help="where eval_info.json and videos/ go (default: %(default)s)")
    p.add_argument("--episodes-per-task", type=int, default=2, metavar="K",
                   help="episodes per task (11 tasks; default: %(default)s); the GPU protocol is 50")
    p.add_argument("--suite", default="all", metavar="NAME",
                   help="suite (all, spatial, object, goal) or one task name (default: %(default)s)")
    p.add_argument("--batch", type=int, default=22, metavar="N",
                   help="environments simulated at once (default: %(default)s)")
    p.add_argument("--num-steps", type=int, default=None,
                   help="flow-matching Euler steps (default: the checkpoint's num_steps, e.g. a distilled student's, "
                        "else 10)")
    p.add_argument("--replan-steps", type=int, default=5, metavar="R",
                   help="actions executed from each chunk of 10 before the next call (default: %(default)s)")
    p.add_argument("--videos", type=int, default=2, metavar="V", help="MP4s of the first V episodes (default: 2)")
    p.add_argument("--dtype", choices=("float32", "bfloat16"), default="float32",
                   help="param and compute dtype (default: %(default)s; the model was trained and is evaluated "
                        "on the GPU in bfloat16, which XLA:CPU only emulates)")
    p.add_argument("--checkpoint", type=Path, default=None, metavar="DIR",
                   help="evaluate this pi0-jax checkpoint instead of the embedded one")
    p.add_argument("--seed", type=int, default=0, help="base PRNG seed of the policy's noise (default: 0)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_run_demo)


def _run_demo(args: argparse.Namespace) -> int:
    from pi0_jax.checkpoint import read_meta
    from pi0_jax.config import Pi0Config
    from pi0_jax.sim.cli import default_num_steps
    from pi0_jax.sim.evaluate import EvalConfig, evaluate, format_table

    with resources.as_file(resources.files("pi0_jax") / "assets" / EMBEDDED_MODEL) as embedded:
        ckpt = args.checkpoint or embedded
        config = Pi0Config.from_json(read_meta(ckpt)["model"])
        cfg = EvalConfig(suite=args.suite, episodes_per_task=args.episodes_per_task, batch=args.batch,
                         replan_steps=args.replan_steps, resolution=config.image_size, seed=args.seed,
                         videos=args.videos,
                         num_steps=default_num_steps(str(ckpt)) if args.num_steps is None else args.num_steps)
        info = evaluate(str(ckpt), cfg, args.output_dir, progress=not args.no_progress,
                        policy_kwargs={"dtype": args.dtype})
    a = info["aggregated"]
    print(f"\n{config.name} ({'embedded' if args.checkpoint is None else ckpt}), {args.dtype}, "
          f"{cfg.num_steps} flow steps, {cfg.replan_steps} of {config.action_horizon} actions per call")
    print(format_table(info))
    print(f"\n{a['n_episodes']} episodes in {a['eval_s']:.1f} s (first segment incl. compile "
          f"{a['first_segment_s']:.1f} s) on {info['config']['devices']} {info['config']['backend']} device(s)")
    print(f"wrote {args.output_dir / 'eval_info.json'}" + "".join(f"\n      {v}" for v in info["video_paths"]))
    return 0


def _benchmark_parser(subparsers) -> None:
    from pi0_jax import benchmark  # noqa: F401  (imports jax; only the parser is built here)

    p = subparsers.add_parser("benchmark", help="per-stage latency of the compiled engine (JSON, table, chart)",
                              description=benchmark.__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    benchmark.add_arguments(p)
    p.set_defaults(func=benchmark.main)


def _quantize_parser(subparsers) -> None:
    from pi0_jax.quant import report

    p = subparsers.add_parser("quantize", help="FP8 quantised checkpoint (calibrated) and accuracy report",
                              description=report.__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    report.add_arguments(p)
    p.set_defaults(func=report.main)


def build_parser() -> argparse.ArgumentParser:
    from converters.cli import add_convert_parser
    from pi0_jax.prune import add_prune_parser
    from pi0_jax.serve.cli import add_serve_parser
    from pi0_jax.sim.cli import add_eval_parser
    from pi0_jax.train.cli import add_distill_parser, add_train_parser

    parser = argparse.ArgumentParser(prog="pi0-jax", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    add_convert_parser(sub)
    _demo_parser(sub)
    _benchmark_parser(sub)
    _quantize_parser(sub)
    add_eval_parser(sub)
    add_train_parser(sub)
    add_distill_parser(sub)
    add_prune_parser(sub)
    add_serve_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
