"""Open-loop check of training-time action conditioning (issue 15): does a model trained with `pi0-jax train
--max-delay` use the committed actions it is given?

On demonstration frames (held out from training), the chunk is sampled from the same noise four ways, and its
actions D .. H-1 are compared with the demonstration's (mean absolute error of the six motion dims, in action units):

  free     nothing committed (d = 0)
  given    the demonstration's own actions 0 .. D-1 committed: what the robot executed, as in training
  hold     zero motion, gripper open committed (what an episode's first plan is given)
  earlier  the demonstration's actions from 5 steps earlier committed: a prefix that was not executed

If the conditioning works, `given` is below `free`. `hold` and `earlier` show how far the model follows a prefix
that disagrees with the frame. The reference sampler (pi0.sample_actions), f32, on the CPU in about a minute.

    python scripts/sim_demos.py DEMOS --episodes-per-task 1 --first-init 0 --resolution 112 --action-noise 0.2
    python scripts/conditioning_check.py CKPT DEMOS
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from pi0_jax import pi0
from pi0_jax.policy import Policy, load_parts
from pi0_jax.sim.realtime import hold_chunk


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("checkpoint", type=Path, help="a checkpoint trained with --max-delay")
    p.add_argument("demos", type=Path, help="demonstrations (scripts/sim_demos.py), held out from its training")
    p.add_argument("--delay", type=int, default=4, help="committed actions D (default: %(default)s)")
    p.add_argument("--every", type=int, default=6, help="frames between checked frames (default: %(default)s)")
    p.add_argument("--num-steps", type=int, default=10, help="flow steps (default: %(default)s)")
    args = p.parse_args()

    config, params, tokenizer, normalizer = load_parts(args.checkpoint, dtype="float32")
    policy = Policy(config, params, tokenizer, normalizer)
    h, a, d = config.action_horizon, config.action_dim, args.delay
    scale, offset = (np.asarray(policy.core.norm[k]) for k in ("action_scale", "action_offset"))
    sample = jax.jit(pi0.sample_actions, static_argnums=(0, 4))

    def model_space(actions):
        out = np.zeros((1, h, a), np.float32)
        out[0, :, :actions.shape[1]] = (actions - offset) / scale
        return jnp.asarray(out)

    hold = np.asarray(hold_chunk(1, h, len(scale))[0])
    errors: dict[str, list[float]] = {"free": [], "given": [], "hold": [], "earlier": []}
    for path in sorted(args.demos.glob("episode_*.npz")):
        ep = np.load(path)
        for t in range(5, len(ep["actions"]) - h, args.every):
            obs = policy.make_observation({"observation/image": ep["agentview"][t],
                                           "observation/wrist_image": ep["wrist"][t],
                                           "observation/state": ep["state"][t], "prompt": str(ep["prompt"])})
            truth = ep["actions"][t:t + h]
            noise = jax.random.normal(jax.random.key(t), (1, h, a))
            cases = {"free": (truth, 0), "given": (truth, d), "hold": (hold, d),
                     "earlier": (ep["actions"][t - 5:t - 5 + h], d)}
            for name, (prefix, n) in cases.items():
                x = sample(config, params, obs, noise, args.num_steps, model_space(prefix), jnp.array([n]))
                x = np.asarray(x)[0, :, :len(scale)] * scale + offset
                errors[name].append(float(np.abs(x[d:, :6] - truth[d:, :6]).mean()))
    result = {k: float(np.mean(v)) for k, v in errors.items()}
    result.update(frames=len(errors["free"]), delay=d, checkpoint=str(args.checkpoint), demos=str(args.demos))
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
