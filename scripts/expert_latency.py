"""Is the suite's task itself tolerant of latency? The scripted expert (privileged state, a new action every step)
with its actions executed D control steps late, for several proportional gains (issue 15).

A policy cloned from the expert inherits its feedback law. The expert moves `gain` times the position error per
control step (POS_GAIN = 1.5 in the demos): with a delay of D steps, such a loop overshoots or oscillates once
gain x (D + 1) is large, whatever the policy does with its chunks. This measures where the expert itself stops
succeeding, with no learning in the way: every cell replans every step, the most reactive a delayed policy can be.

Writes OUT/expert_latency.json (every cell, the command, the device) and OUT/expert_latency.md (the table).

    python scripts/expert_latency.py --out OUT                                  # 550 episodes per cell
    python scripts/expert_latency.py --out /tmp/el --episodes-per-task 2 --delays 0,4 --gains 1.5   # smoke
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from pathlib import Path

import jax

import pi0_jax.sim  # noqa: F401  (sets the XLA:CPU flags MJX needs before the backend starts)
from pi0_jax.sim import expert
from pi0_jax.sim.evaluate import EvalConfig, evaluate
from pi0_jax.sim.policies import expert_policy
from pi0_jax.sim.realtime import CONTROL_HZ

sys.path.insert(0, str(Path(__file__).parent))
from results_grid import wilson  # noqa: E402


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, required=True, help="directory for expert_latency.json and .md")
    p.add_argument("--delays", default="0,1,2,4", help="latencies D in control steps of 50 ms (default: %(default)s)")
    p.add_argument("--gains", default=f"{expert.POS_GAIN},1.0,0.5",
                   help="proportional position gains; the rotation gain scales with them (the demos' expert: "
                        f"{expert.POS_GAIN} and {expert.ROT_GAIN}) (default: %(default)s)")
    p.add_argument("--episodes-per-task", type=int, default=50, help="episodes per task (default: %(default)s)")
    p.add_argument("--suite", default="all", help="task suite (default: %(default)s)")
    p.add_argument("--batch", type=int, default=550, help="environments at once (default: %(default)s)")
    args = p.parse_args()
    delays = [int(d) for d in args.delays.split(",")]
    gains = [float(g) for g in args.gains.split(",")]
    if min(delays) < 0 or min(gains) <= 0:
        raise SystemExit("--delays must be >= 0 and --gains > 0")
    args.out.mkdir(parents=True, exist_ok=True)

    rows = []
    for gain in gains:
        for d in delays:
            cfg = EvalConfig(suite=args.suite, episodes_per_task=args.episodes_per_task, batch=args.batch, videos=0)
            t0 = time.perf_counter()
            info = evaluate(lambda env, d=d, g=gain: expert_policy(env, d, g), cfg, None, progress=False)
            a = info["aggregated"]
            lo, hi = wilson(a["n_success"], a["n_episodes"])
            rows.append({"gain": gain, "rot_gain": expert.gains(gain)[1], "delay": d, "delay_ms": 1000 * d / CONTROL_HZ,
                         "n_episodes": a["n_episodes"], "n_success": a["n_success"], "pc_success": a["pc_success"],
                         "ci95": [lo, hi], "mean_length": sum(e["length"] for e in info["per_episode"])
                         / len(info["per_episode"]), "wall_s": time.perf_counter() - t0})
            r = rows[-1]
            print(f"gain {gain:g}, D = {d}: {r['pc_success']:.1f} % [{lo:.1f}, {hi:.1f}] of {r['n_episodes']}, "
                  f"mean length {r['mean_length']:.0f} steps ({r['wall_s']:.0f} s)", flush=True)

    head = "| position gain | " + " | ".join(f"D = {d} ({1000 * d // CONTROL_HZ} ms)" for d in delays) + " |"
    lines = [head, "|---:|" + "---:|" * len(delays)]
    for gain in gains:
        cells = [next(r for r in rows if r["gain"] == gain and r["delay"] == d) for d in delays]
        lines.append(f"| {gain:g} | " + " | ".join(f"{c['pc_success']:.1f} % [{c['ci95'][0]:.1f}, {c['ci95'][1]:.1f}]"
                                                 for c in cells) + " |")
    command = "python " + " ".join(shlex.quote(a) for a in sys.argv)
    (args.out / "expert_latency.md").write_text("\n".join(lines) + f"\n\nCommand:\n\n```\n{command}\n```\n")
    (args.out / "expert_latency.json").write_text(json.dumps(
        {"rows": rows, "command": command, "device": str(jax.devices()[0].device_kind),
         "episodes_per_task": args.episodes_per_task, "suite": args.suite}, indent=2) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
