"""`pi0-jax`: the command-line front door. Subcommands are thin entry points over the package.

  pi0-jax convert SRC DST   PyTorch (openpi / LeRobot) checkpoint -> pi0-jax checkpoint
  pi0-jax demo              convert the embedded tiny model, run the policy on a synthetic observation, print timings
  pi0-jax benchmark         per-stage latency of the compiled engine over steps x batch x dtype
  pi0-jax train             train a π0 on expert demonstrations (pi0_jax/train)
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from importlib import resources
from pathlib import Path

DEMO_PROMPT = "pick up the black bowl between the plate and the ramekin and place it on the plate"


def _demo_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "demo", help="convert the embedded tiny π0.5 and sample actions from it (CPU is enough)",
        description="Convert the embedded demo checkpoint (a tiny random-weight π0.5 saved by LeRobot, with its "
                    "normaliser files and a small tokenizer) with `pi0-jax convert`, load it as a Policy, run "
                    "`infer` on a synthetic LIBERO-style observation and print compile and per-call timings. "
                    "The weights are random, so the actions mean nothing; the pipeline is the real one.")
    p.add_argument("--out-dir", type=Path, default=None,
                   help="where to write the converted checkpoint and demo_result.json (default: a temp dir)")
    p.add_argument("--steps", type=int, default=10, help="flow-matching Euler steps (default: %(default)s)")
    p.add_argument("--iters", type=int, default=20, help="timed calls after the warm-up call (default: %(default)s)")
    p.add_argument("--dtype", choices=("float32", "bfloat16"), default="float32",
                   help="param and compute dtype of the converted model (default: %(default)s; bf16 is slow on CPU)")
    p.add_argument("--seed", type=int, default=0, help="seed of the synthetic observation and noise")
    p.set_defaults(func=_run_demo)


def _run_demo(args: argparse.Namespace) -> int:
    import numpy as np

    from converters import convert
    from pi0_jax.policy import Policy

    out = args.out_dir or Path(tempfile.mkdtemp(prefix="pi0-jax-demo-"))
    out.mkdir(parents=True, exist_ok=True)
    with resources.as_file(resources.files("pi0_jax") / "assets" / "demo") as src:
        t0 = time.perf_counter()
        ckpt = convert(src, out / "demo_pi05", dtype=args.dtype, overwrite=True)
        convert_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        policy = Policy.from_checkpoint(ckpt, tokenizer_path=src / "tokenizer.model", num_steps=args.steps,
                                        seed=args.seed)
        load_s = time.perf_counter() - t0

    rng = np.random.default_rng(args.seed)
    obs = {  # what openpi's LIBERO client sends; 256x256 frames exercise resize-with-pad
        "observation/image": rng.integers(0, 256, (256, 256, 3), dtype=np.uint8),
        "observation/wrist_image": rng.integers(0, 256, (256, 256, 3), dtype=np.uint8),
        "observation/state": rng.normal(size=8),
        "prompt": DEMO_PROMPT,
    }
    t0 = time.perf_counter()
    first = policy.infer(obs)
    compile_s = time.perf_counter() - t0
    times = []
    for _ in range(args.iters):
        times.append(policy.infer(obs)["policy_timing"]["infer_ms"])
    noise = rng.normal(size=(policy.config.action_horizon, policy.config.action_dim)).astype(np.float32)
    same = np.array_equal(policy.infer(obs, noise=noise)["actions"], policy.infer(obs, noise=noise)["actions"])

    cfg = policy.config
    result = {
        "model": cfg.name, "pi05": cfg.pi05, "dtype": cfg.dtype, "num_steps": args.steps,
        "actions_shape": list(first["actions"].shape), "convert_s": convert_s, "load_s": load_s,
        "first_call_s": compile_s, "infer_ms_median": float(np.median(times)),
        "infer_ms_p90": float(np.percentile(times, 90)), "iters": args.iters, "noise_injection_reproducible": same,
        "checkpoint": str(ckpt),
    }
    (out / "demo_result.json").write_text(json.dumps(result, indent=2) + "\n")
    print(f"\nmodel {cfg.name} (π0.5 tiny, random weights), {cfg.dtype}, {args.steps} steps, "
          f"horizon {cfg.action_horizon}, prefix {cfg.prefix_len} tokens")
    print("| stage | time |\n|---|---|")
    print(f"| convert (LeRobot safetensors -> orbax) | {convert_s:.2f} s |")
    print(f"| load checkpoint + tokenizer + norm stats | {load_s:.2f} s |")
    print(f"| first infer (includes jit compile) | {compile_s:.2f} s |")
    print(f"| infer, median of {args.iters} | {result['infer_ms_median']:.1f} ms |")
    print(f"| infer, p90 | {result['infer_ms_p90']:.1f} ms |")
    print(f"\nactions {tuple(first['actions'].shape)}, first step: {np.array2string(first['actions'][0], precision=3)}")
    print(f"injected noise reproducible: {same}\nwrote {out / 'demo_result.json'}")
    return 0 if same else 1


def _benchmark_parser(subparsers) -> None:
    from pi0_jax import benchmark  # noqa: F401  (imports jax; only the parser is built here)

    p = subparsers.add_parser("benchmark", help="per-stage latency of the compiled engine (JSON, table, chart)",
                              description=benchmark.__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    benchmark.add_arguments(p)
    p.set_defaults(func=benchmark.main)


def build_parser() -> argparse.ArgumentParser:
    from converters.cli import add_convert_parser
    from pi0_jax.sim.cli import add_eval_parser
    from pi0_jax.train.cli import add_train_parser

    parser = argparse.ArgumentParser(prog="pi0-jax", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    add_convert_parser(sub)
    _demo_parser(sub)
    _benchmark_parser(sub)
    add_eval_parser(sub)
    add_train_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
