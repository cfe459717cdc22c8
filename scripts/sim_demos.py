"""Write scripted-expert demonstrations of the MJX task suite: one npz per episode + meta.json.

    python scripts/sim_demos.py OUT --suite all --episodes-per-task 50 --batch 64 --resolution 224
    # training data for pi0_small (pi0_jax/train): states 50..99, disjoint from the evaluation's 0..49
    python scripts/sim_demos.py OUT --episodes-per-task 50 --first-init 50 --resolution 112 --no-compress
    # with DART noise injection (recovery data): noisy execution, clean expert labels
    python scripts/sim_demos.py OUT --episodes-per-task 50 --first-init 50 --resolution 112 --action-noise 0.2

Layout and fields: pi0_jax/sim/demos.py. On a GPU the whole suite (550 episodes at 224 x 224) takes minutes; on a
CPU use a small resolution.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import pi0_jax.sim  # noqa: F401  (XLA:CPU flags before jax starts)


@dataclasses.dataclass(frozen=True)
class Args:
    out: Path
    suite: str
    episodes_per_task: int
    batch: int
    resolution: int
    keep_failures: bool
    first_init: int
    no_compress: bool
    action_noise: float
    gain: float


def parse(argv=None) -> Args:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out", type=Path, help="output directory")
    p.add_argument("--suite", default="all", help="spatial, object, goal, all, or one task name (default: all)")
    p.add_argument("--episodes-per-task", type=int, default=50,
                   help="initial states FIRST..FIRST+K-1 of each task (FIRST: --first-init)")
    p.add_argument("--first-init", type=int, default=0, metavar="FIRST",
                   help="first initial state (default 0; 50 keeps training demos off the evaluation's 0..49)")
    p.add_argument("--batch", type=int, default=32, help="environments rolled out at once")
    p.add_argument("--resolution", type=int, default=224, help="camera images are PX x PX")
    p.add_argument("--keep-failures", action="store_true", help="also write episodes the expert failed")
    p.add_argument("--no-compress", action="store_true",
                   help="write plain npz (np.savez): much faster for large datasets, ~3x the disk")
    p.add_argument("--action-noise", type=float, default=0.0, metavar="SIGMA",
                   help="DART noise injection: execute the expert's action plus N(0, s^2) on the motion dims, s drawn "
                        "per episode uniform in [0, SIGMA], and record the clean action (default 0: no noise)")
    p.add_argument("--gain", type=float, default=None, metavar="G",
                   help="the expert's proportional position gain per control step (the rotation gain scales with "
                        "it); the default 1.5 does not tolerate 2 steps of latency, 0.5 tolerates 4 "
                        "(scripts/expert_latency.py); default: pi0_jax.sim.expert.POS_GAIN")
    return Args(**vars(p.parse_args(argv)))


def main(argv=None) -> int:
    from pi0_jax.sim.demos import write_demos

    a = parse(argv)
    meta = write_demos(a.out, a.suite, a.episodes_per_task, a.batch, a.resolution, a.keep_failures,
                       first_init=a.first_init, compress=not a.no_compress, action_noise=a.action_noise,
                       **({} if a.gain is None else {"pos_gain": a.gain}))
    ok = sum(e["success"] for e in meta["episodes"])
    print(f"{len(meta['episodes'])} episodes written to {a.out} ({ok} successful)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
