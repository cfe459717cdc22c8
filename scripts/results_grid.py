"""Task success of a trained checkpoint over flow steps x numeric scheme, in the MJX suite (docs/RESULTS.md).

For every scheme (bf16, FP8 schemes, FP4 emulations from pi0_jax.quant) the checkpoint is quantised once (activation
scales calibrated on rendered suite observations) and evaluated at every step count on the same episodes: K per task
from the fixed initial states 0..K-1, the same policy noise (fold_in(seed, episode)). The step count travels in the
policy's params, so one compiled rollout per scheme serves every step count (and the persistent compilation cache
serves repeats). Success rates come with Wilson 95 % intervals.

    python scripts/results_grid.py --checkpoint out/train/checkpoint --out results --episodes-per-task 50 \
        --schemes bf16:10+1+2+3+5,prefix-mlp:10,all:10,nvfp4:10,mxfp4:10
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import jax

import pi0_jax.sim  # noqa: F401  (sets the XLA:CPU flags MJX needs before the backend starts)
from pi0_jax.sim import policies
from pi0_jax.policy import load_parts
from pi0_jax.sim.evaluate import EvalConfig, evaluate


def wilson(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion (percent)."""
    if n == 0:
        return float("nan"), float("nan")
    p = k / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return 100 * max(0.0, centre - half), 100 * min(1.0, centre + half)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", type=Path, required=True, help="a pi0-jax checkpoint (e.g. pi0_small trained)")
    p.add_argument("--out", type=Path, required=True, help="directory for results.json and results.md")
    p.add_argument("--episodes-per-task", type=int, default=50, help="episodes per task (default: %(default)s)")
    p.add_argument("--steps", default="1,2,3,5,10", help="comma list of flow steps (default: %(default)s)")
    p.add_argument("--schemes", default="bf16",
                   help="comma list of SCHEME[:N+N..]: bf16, a pi0_jax.quant FP8 scheme (prefix-mlp, prefix-all, "
                        "vision, expert-weights, all) or an FP4 emulation (nvfp4, mxfp4), optionally with its own "
                        "step counts (default: --steps); run in the order given")
    p.add_argument("--batch", type=int, default=550, help="environments at once (default: %(default)s)")
    p.add_argument("--replan-steps", type=int, default=5, help="actions executed per call (default: 5)")
    p.add_argument("--calib-samples", type=int, default=64, help="observations for activation scales (default: 64)")
    p.add_argument("--seed", type=int, default=0, help="policy noise seed (default: 0)")
    p.add_argument("--max-steps", type=int, default=None, help="episode step limit (default: each task's own)")
    p.add_argument("--cache-dir", type=Path, default=Path.home() / ".cache/pi0_jax/xla",
                   help="persistent compilation cache (default: %(default)s)")
    args = p.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(args.cache_dir))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)

    config, params, tok, normalizer = load_parts(args.checkpoint)
    steps = [int(s) for s in args.steps.split(",") if s]
    rows = []
    calib = None
    plan = []       # (scheme, step counts): "bf16:10+1+2" evaluates bf16 at 10, 1, 2 steps; no ":" = --steps
    for entry in (e for e in args.schemes.split(",") if e):
        name, _, counts = entry.partition(":")
        plan.append((name, [int(c) for c in counts.split("+")] if counts else steps))
    steps = sorted({n for _, counts in plan for n in counts})
    for scheme, counts in plan:
        quant = None if scheme == "bf16" else scheme
        if quant not in (None, *policies.QUANT_FORMATS) and calib is None:
            calib = policies.calibration_observation(config, tok, normalizer, args.calib_samples, args.seed)
        t0 = time.perf_counter()
        qparams = policies.quantize_for_suite(config, params, tok, normalizer, quant, seed=args.seed, calib=calib)
        quant_s = time.perf_counter() - t0
        for n in counts:
            def make(env, qparams=qparams, n=n, scheme=scheme, quant=quant):
                return policies.model_policy(config, qparams, tok, normalizer, env, num_steps=n, dynamic_steps=True,
                                             name=f"{config.name}/{scheme}", quant=quant)
            cfg = EvalConfig(suite="all", episodes_per_task=args.episodes_per_task, batch=args.batch,
                             replan_steps=args.replan_steps, resolution=config.image_size, seed=args.seed, videos=0,
                             num_steps=n, max_steps=args.max_steps)
            info = evaluate(make, cfg, None, progress=False)
            a = info["aggregated"]
            lo, hi = wilson(a["n_success"], a["n_episodes"])
            row = {"scheme": scheme, "num_steps": n, "n_episodes": a["n_episodes"], "n_success": a["n_success"],
                   "pc_success": a["pc_success"], "ci95": [lo, hi], "eval_s": a["eval_s"],
                   "first_segment_s": a["first_segment_s"], "quantise_s": quant_s,
                   "per_group": {g["group"]: g["pc_success"] for g in info["per_group"]},
                   "per_task": {t["task"]: t["pc_success"] for t in info["per_task"]}}
            rows.append(row)
            print(f"{scheme:>14} steps {n:>2}: {a['pc_success']:5.1f}% [{lo:.1f}, {hi:.1f}] of {a['n_episodes']} "
                  f"({a['eval_s']:.0f} s)", flush=True)
            (args.out / "results.json").write_text(json.dumps(
                {"checkpoint": str(args.checkpoint), "model": config.name, "device": jax.devices()[0].device_kind,
                 "jax": jax.__version__, "rows": rows}, indent=2) + "\n")
    (args.out / "results.md").write_text(markdown(rows, steps))
    print(markdown(rows, steps))
    return 0


def markdown(rows: list[dict], steps: list[int]) -> str:
    schemes = list(dict.fromkeys(r["scheme"] for r in rows))
    by = {(r["scheme"], r["num_steps"]): r for r in rows}
    out = ["| scheme | " + " | ".join(f"{n} step{'s' if n > 1 else ''}" for n in steps) + " |",
           "|---|" + "---:|" * len(steps)]
    for s in schemes:
        cells = []
        for n in steps:
            r = by.get((s, n))
            cells.append("" if r is None else f"{r['pc_success']:.1f}% [{r['ci95'][0]:.1f}, {r['ci95'][1]:.1f}]")
        out.append(f"| {s} | " + " | ".join(cells) + " |")
    return "\n".join(out) + "\n"


if __name__ == "__main__":
    raise SystemExit(main())
