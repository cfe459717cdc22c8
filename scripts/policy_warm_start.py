"""A Policy's first call in this process: its programs compiled, or loaded from the program store (`engine.store`).

Run it twice with the same cache directory: the first process compiles and stores the call's programs, the
second loads them (`loaded` 2 on a GPU, one more where the first denoise step overlaps the prefix fill and one more
where the vision tower is cut, at full size) and must return the same actions.

    python scripts/policy_warm_start.py pi0_jax/assets/pi0_small /tmp/pi0-cache   # twice
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from pi0_jax.policy import Policy


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("checkpoint", help="a pi0-jax checkpoint directory (with its tokenizer and norm stats)")
    p.add_argument("cache_dir", help="the cache directory both processes share")
    p.add_argument("--seed", type=int, default=0, help="seed of the example observation and the noise")
    args = p.parse_args()
    policy = Policy.from_checkpoint(args.checkpoint, cache_dir=args.cache_dir)
    obs = policy.example_observation(args.seed)
    shape = (policy.config.action_horizon, policy.config.action_dim)
    noise = np.random.default_rng(args.seed).standard_normal(shape).astype(np.float32)
    start = time.perf_counter()
    actions = policy.infer(obs, noise=noise)["actions"]
    print(json.dumps({"first_infer_s": time.perf_counter() - start, "loaded": policy.store.loaded,
                      "abs_sum": float(np.abs(actions).sum()), "head": actions.ravel()[:4].tolist()}))


if __name__ == "__main__":
    main()
