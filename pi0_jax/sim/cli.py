"""`pi0-jax eval`: batched MJX evaluation of a policy on a task suite. `add_eval_parser(subparsers)` is what
`pi0_jax/cli.py` wires in; importing this module does not import jax."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

DESCRIPTION = """\
Evaluate a policy on a LIBERO-like table-top suite simulated in MuJoCo MJX: N environments stepped, rendered
(agent view + wrist view) and controlled inside one jitted program, sharded over every local device (and every
host under jax.distributed). Episodes end at the first success or at the task's step limit, as in LIBERO.

Prints a per-task / per-family / overall success table and writes DIR/eval_info.json (LeRobot-like: per_episode,
per_task, per_group, aggregated pc_success, eval_s, eval_ep_s) and DIR/videos/*.mp4 (agent | wrist, 20 fps).
Deterministic: episode e uses initial state (e // tasks) % 50 of task e % tasks and PRNG key fold_in(seed, e),
whatever the batch size or device count.

On CPU set XLA_FLAGS=--xla_cpu_use_fusion_emitters=false before jax starts (this command does it for you):
without it MJX steps are ~100x slower.
"""


def add_eval_parser(subparsers) -> argparse.ArgumentParser:
    """Add the `eval` subcommand to an argparse subparsers object; returns its parser (func=run)."""
    from pi0_jax.sim.tasks import SUITES, TASKS  # light: no jax import

    p = subparsers.add_parser("eval", help="evaluate a policy (checkpoint, expert, random) in the MJX task suite",
                              description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--policy", required=True, metavar="PATH|expert|random|preset:NAME",
                   help="a pi0-jax checkpoint directory (`pi0-jax convert` output), 'expert' (the scripted expert, "
                        "privileged state), 'random' (uniform actions in [-1, 1]) or 'preset:NAME' (random weights "
                        "of a pi0_jax.config preset, e.g. preset:pi05_base: the protocol's timing without a "
                        "trained checkpoint)")
    p.add_argument("--suite", default="all", metavar="NAME",
                   help=f"task suite: {', '.join(SUITES)} ({len(TASKS)} tasks in all), or one task name such as "
                        f"{TASKS[0].name!r} (default: %(default)s)")
    p.add_argument("--episodes-per-task", type=int, default=10, metavar="K",
                   help="episodes per task; episode k of a task starts from its initial state k %% 50 "
                        "(default: %(default)s; LIBERO's protocol is 50)")
    p.add_argument("--batch", type=batch_arg, default=32, metavar="N|auto",
                   help="environments simulated at once, rounded up to a multiple of the device count; 'auto': "
                        "the fewest even batches of at most 1024 per device whose compiled segment fits in 85 %% "
                        "of the free device memory (the policy's --plan-chunk, then the batch, halved until it "
                        "does; what was tried goes into eval_info.json's config.batch_auto) (default: %(default)s)")
    p.add_argument("--plan-chunk", type=plan_chunk_arg, default=None, metavar="C",
                   help="the policy plans at most C environments per device at a time, one chunk after another: "
                        "a large batch's physics and rendering with the activation memory of C (a full-size π0.5 "
                        "needs ~60 MB per environment); default: the whole batch at once, or with --batch auto "
                        "halved from it (down to 128) before the batch is")
    p.add_argument("--replan-steps", type=int, default=5, metavar="R",
                   help="steps executed from each action chunk before the policy is called again; at most the "
                        "model's action horizon (default: %(default)s, openpi's LIBERO setting)")
    p.add_argument("--steps", type=int, default=None, metavar="S",
                   help="step limit of every episode (20 Hz control steps); default: each task's own limit "
                        "(LIBERO's 220 spatial, 280 object, 300 goal)")
    p.add_argument("--output-dir", type=Path, default=None, metavar="DIR",
                   help="where to write eval_info.json and videos/ (default: print only)")
    p.add_argument("--resolution", type=int, default=None, metavar="PX",
                   help="camera images are PX x PX (default: a checkpoint's own image size, e.g. 224 for π0 / π0.5 "
                        "and 112 for pi0_small; 224 for expert and random); a checkpoint policy resizes other sizes "
                        "to its own with openpi's resize-with-pad")
    p.add_argument("--videos", type=int, default=4, metavar="V",
                   help="record MP4s of the first V episodes (default: %(default)s; 0 for none)")
    p.add_argument("--seed", type=int, default=0, help="base PRNG seed of the policy's noise (default: 0)")
    p.add_argument("--num-steps", type=int, default=None,
                   help="flow-matching Euler steps of a checkpoint policy (default: the checkpoint's num_steps, "
                        "which a distilled student records, else 10)")
    p.add_argument("--dtype", choices=("float32", "bfloat16"), default=None,
                   help="param and compute dtype of a checkpoint policy (default: the checkpoint's own)")
    p.add_argument("--quant", default=None, metavar="FORMAT",
                   help="number format of a checkpoint or preset policy's weights: an FP8 scheme of pi0_jax.quant "
                        "(prefix-mlp, prefix-all, vision, prefix-vision, expert-weights, all, every-gemm: FP8 x FP8 "
                        "in the action expert too, for hundreds of environments; static activation scales calibrated "
                        "on 64 rendered observations from initial states 50-99, which are never evaluated) or an "
                        "FP4 weight emulation (nvfp4, mxfp4) (default: as stored)")
    p.add_argument("--sampler", choices=("engine", "reference"), default="engine",
                   help="how a checkpoint policy samples: the compiled engine's programs (default), or openpi's "
                        "reference structure (pi0.sample_actions; the parity path, slower)")
    p.add_argument("--gemm", choices=("xla", "cublas"), default="cublas",   # pi0_jax.ops.matmul.GEMMS (imports jax)
                   help="the library of a checkpoint or preset policy's GEMMs on a GPU: cublas (XLA's Triton GEMMs "
                        "off for the rollout program: bias, GELU and residual become cuBLAS epilogues; π0.5's "
                        "rollout 5 %% faster at 264 environments) or xla (XLA's autotuned choice of Triton or cuBLAS "
                        "per GEMM); FP8 weights always get cublas (default: %(default)s)")
    p.add_argument("--attention", default="auto",
                   help="a checkpoint or preset policy's attention per stage, as `pi0-jax benchmark --attention`: "
                        "auto (the faster per stage and batch on a GPU, XLA's ops on a CPU), xla, cudnn, or e.g. "
                        "vision=pallas,prefix=cudnn,denoise=auto (default: %(default)s)")
    p.add_argument("--tokenizer", type=Path, default=None, metavar="FILE",
                   help="SentencePiece model for a checkpoint policy (default: CKPT/tokenizer.model or "
                        "CKPT/assets/tokenizer.model)")
    p.add_argument("--norm-stats", default=None, metavar="PATH|identity",
                   help="norm stats for a checkpoint policy (default: found under CKPT/assets)")
    rt = p.add_argument_group("latency, asynchronous execution, prefix reuse (model policies; pi0_jax/sim/realtime.py)")
    rt.add_argument("--latency-steps", type=int, default=0, metavar="D",
                    help="inference latency in control steps: a chunk planned from the observation at step t is "
                         "first usable at t + D (one step is 50 ms at the suite's 20 Hz: D = 4 is 200 ms). Needs "
                         "D <= --replan-steps and --replan-steps + D <= the action horizon (default: %(default)s)")
    rt.add_argument("--execution", choices=("sync", "naive", "rtc", "conditioned"), default="sync",
                    help="what the robot does while a chunk is computed: sync = the world waits (D has no effect; "
                         "the usual protocol); naive = keep executing the previous chunk, switch to the new one at "
                         "its index D (an episode's first D steps hold still: zero motion, gripper open); rtc = as "
                         "naive, with the new chunk sampled by real-time chunking (first D actions frozen to the "
                         "committed ones, the overlap guided with decaying weights, ΠGDM guidance clipped at "
                         "--rtc-beta); conditioned = as naive, the committed actions given to the model as clean "
                         "inputs (training-time action conditioning: for a model trained with `pi0-jax train "
                         "--max-delay`; no extra compute). With D = 0 all four are the same policy "
                         "(default: %(default)s)")
    rt.add_argument("--rtc-beta", type=float, default=5.0, metavar="BETA",
                    help="rtc: the clip of the guidance weight min(BETA, (t^2 + (1 - t)^2) / (t (1 - t))) at flow "
                         "time t, the paper's β; larger binds the new chunk harder to the committed one, 0 turns the "
                         "guidance off (the sample is naive's) (default: %(default)s, the paper's)")
    rt.add_argument("--reuse-prefix", default=None, metavar="K|auto:THRESH",
                    help="recompute vision and the prefix KV cache only every K-th plan, otherwise denoise on the "
                         "cached prefix (K = 1: every plan, through the reuse path). auto:THRESH recomputes an "
                         "environment's prefix when its images changed more than THRESH since its cache's frame "
                         "(mean absolute difference of 16x16 downsampled frames in [0, 1], the larger camera), "
                         "selected per environment; the batch's vision + prefix run when any environment needs "
                         "them. π0 keeps the state in the suffix, so the fresh state still enters; π0.5 with the "
                         "state in the prompt uses the cached plan's (stale) state; π0.5 without state input has "
                         "none. eval_info.json's realtime.prefix_recompute_fraction is recomputes / plans "
                         "(default: recompute every plan, the fused program)")
    p.add_argument("--segment-replans", type=int, default=8, metavar="M",
                   help="policy calls per jitted segment; between segments the progress bar updates and the slots of "
                        "finished episodes start the next episodes (default: %(default)s)")
    p.add_argument("--profile", action="store_true",
                   help="also time physics, rendering and the policy of one replan cycle apart (extra compiles), "
                        "into eval_info.json's timing.phases")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--cache-dir", type=Path, default=None, metavar="DIR",
                   help="XLA's persistent compilation cache: a second run of the same evaluation skips compiling "
                        "(default: $PI0_JAX_CACHE_DIR or ~/.cache/pi0_jax/xla)")
    p.add_argument("--no-compile-cache", action="store_true", help="compile from scratch, write no cache")
    dist = p.add_argument_group("multi-host (jax.distributed)")
    dist.add_argument("--coordinator", default=None, metavar="HOST:PORT",
                      help="initialise jax.distributed with this coordinator (process 0 writes the outputs)")
    dist.add_argument("--num-processes", type=int, default=None, help="total processes (with --coordinator)")
    dist.add_argument("--process-id", type=int, default=None, help="this process's id (with --coordinator)")
    p.set_defaults(func=run)
    return p


def batch_arg(text: str) -> int | str:
    """--batch: a positive integer or 'auto'."""
    if text == "auto":
        return text
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: a positive number of environments or 'auto'")
    return n


def plan_chunk_arg(text: str) -> int:
    """--plan-chunk: a positive integer."""
    if not text.isdigit() or int(text) < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: a positive number of environments per device")
    return int(text)


def default_resolution(policy: str) -> int:
    """The image size a checkpoint or preset was built for (config.json's model), else 224."""
    from pi0_jax.config import Pi0Config, get_config

    if policy.startswith("preset:"):
        return get_config(policy.removeprefix("preset:")).image_size
    if policy in ("expert", "random") or not Path(policy).is_dir():
        return 224
    from pi0_jax.checkpoint import read_meta

    return Pi0Config.from_json(read_meta(policy)["model"]).image_size


def default_num_steps(policy: str) -> int:
    """The flow-step count a checkpoint records (config.json's num_steps: `pi0-jax distill` writes it), else 10."""
    if policy in ("expert", "random") or not Path(policy).is_dir():
        return 10
    from pi0_jax.checkpoint import read_meta

    return int(read_meta(policy).get("num_steps", 10))


def run(args: argparse.Namespace) -> int:
    import jax  # this module's package, pi0_jax.sim, has set the XLA:CPU flags already

    if args.coordinator:
        # gloo: cross-process collectives for the CPU backend (results are gathered); GPU backends ignore it
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
        jax.distributed.initialize(args.coordinator, num_processes=args.num_processes, process_id=args.process_id)

    from pi0_jax.sim.evaluate import EvalConfig, evaluate, format_table
    from pi0_jax.sim.realtime import Realtime

    try:   # the execution flags, checked before anything loads
        Realtime(args.execution, args.latency_steps, args.reuse_prefix, args.rtc_beta)
    except ValueError as e:
        raise SystemExit(f"pi0-jax eval: {e}") from None

    if not args.no_compile_cache:
        from pi0_jax.engine import enable_compilation_cache

        enable_compilation_cache(args.cache_dir)

    cfg = EvalConfig(suite=args.suite, episodes_per_task=args.episodes_per_task, batch=args.batch,
                     plan_chunk=args.plan_chunk, replan_steps=args.replan_steps, max_steps=args.steps,
                     resolution=args.resolution or default_resolution(args.policy),
                     seed=args.seed, videos=args.videos, segment_replans=args.segment_replans,
                     num_steps=default_num_steps(args.policy) if args.num_steps is None else args.num_steps,
                     execution=args.execution, latency_steps=args.latency_steps, reuse_prefix=args.reuse_prefix,
                     rtc_beta=args.rtc_beta)
    kw = {"tokenizer_path": args.tokenizer, "norm_stats": args.norm_stats, "dtype": args.dtype,
          "sampler": args.sampler, "quant": args.quant, "gemm": args.gemm,
          "attention": args.attention}
    info = evaluate(args.policy, cfg, args.output_dir, progress=not args.no_progress, policy_kwargs=kw,
                    profile=args.profile)
    if jax.process_index() == 0:
        a, t = info["aggregated"], info["timing"]
        print(format_table(info))
        print(f"\n{t['episodes_per_min']:.1f} episodes/min ({t['episodes_per_min_after_compile']:.1f} after the first "
              f"segment); host {t['host_s']:.1f} s, device {t['device_wait_s']:.1f} s"
              + "".join(f"; {k} {v:.1f} ms" for k, v in t.get("phases", {}).items() if k.endswith("_ms")))
        r = info.get("realtime", {})
        if r.get("execution", "sync") != "sync" or r.get("latency_steps") or r.get("reuse_prefix") is not None:
            print(f"execution {r['execution']}" + (f" (β {r['rtc_beta']:g})" if "rtc_beta" in r else "")
                  + f", latency {r['latency_steps']} steps ({r['latency_ms']:.0f} ms at 20 Hz)"
                  + (f", prefix recomputed at {100 * r['prefix_recompute_fraction']:.1f}% of plans"
                     if r.get("reuse_prefix") is not None and "prefix_recompute_fraction" in r else ""))
        print(f"{a['n_episodes']} episodes in {a['eval_s']:.1f} s ({a['eval_ep_s']:.2f} s/episode; setup "
              f"{t['setup_s']:.1f} s; first segment incl. compile {a['first_segment_s']:.1f} s) on "
              f"{info['config']['devices']} {info['config']['backend']} device(s)")
        if args.output_dir is not None:
            print(f"wrote {args.output_dir / 'eval_info.json'}" + "".join(f"\n      {v}" for v in info["video_paths"]))
        else:
            print(json.dumps(a))
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pi0_jax.sim.cli")
    sub = parser.add_subparsers(dest="command", required=True)
    add_eval_parser(sub)
    args = parser.parse_args(["eval", *(sys.argv[1:] if argv is None else argv)])
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
