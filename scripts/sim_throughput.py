"""Throughput of the MJX task suite: env-steps/s with both cameras rendered, and episodes/min with a π0.5 in the loop.

    python scripts/sim_throughput.py                        # GPU: N = 64, 256, 1024 at 224 x 224; π0.5 full size
    python scripts/sim_throughput.py --sizes 4 8 --resolution 32 --steps 8 --policy-model dummy_pi05 \
        --policy-batch 4 --policy-episode-steps 20          # CPU smoke check

1. Environment: N environments (all tasks mixed), the scripted expert acting (so grasps and contacts happen),
   one control step = controller + 10 MJX substeps + both cameras rendered by the JAX ray caster. Measured
   with and without rendering; compile timed separately, one warm-up call, then `--steps` steps in one jitted scan,
   block_until_ready before the clock is read. A checksum of every image is carried so rendering is not elided.
2. Policy in the loop: `--policy-model` (default pi05_libero, full size, random weights in the preset's dtype,
   bf16, drawn once for every batch) driving `--policy-batch` environments through the evaluation's own segment
   program (pi0_jax.sim.evaluate): plan (SigLIP on 3 slots, prefix, `--num-steps` Euler steps) every
   `--replan-steps` steps. Random weights never
   succeed, so every episode runs `--policy-episode-steps` steps: the worst case. Reports episodes/min and the
   estimated time of LIBERO's 2000-episode protocol at the same per-step cost (its step limits average 330;
   every episode runs to its limit).

Prints a markdown table and a JSON line (also written to --json). State is sharded over every local device.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import math
import subprocess
import sys
import time
from pathlib import Path

import pi0_jax.sim  # noqa: F401  (XLA:CPU flags before jax starts)

LIBERO_EPISODES, LIBERO_MEAN_STEPS = 2000, (220 + 280 + 300 + 520) / 4   # 4 suites x 10 tasks x 50


@dataclasses.dataclass(frozen=True)
class Args:
    sizes: tuple[int, ...]
    resolution: int
    steps: int
    policy_model: str
    policy_batch: tuple[int, ...]
    policy_quant: str | None
    policy_episode_steps: int
    replan_steps: int
    num_steps: int
    skip_policy: bool
    skip_env: bool
    no_physics_only: bool
    json: Path | None


def parse(argv=None) -> Args:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sizes", type=int, nargs="+", default=[64, 256, 1024], help="environment counts N")
    p.add_argument("--resolution", type=int, default=224, help="camera resolution (square)")
    p.add_argument("--steps", type=int, default=50, help="timed control steps per measurement")
    p.add_argument("--policy-model", default="pi05_libero", help="pi0_jax.config preset for the policy run")
    p.add_argument("--policy-batch", type=int, nargs="+", default=[64],
                   help="environments in the policy run; several values: one run each (default: 64)")
    p.add_argument("--policy-quant", default=None, metavar="FORMAT",
                   help="number format of the policy's weights, as `pi0-jax eval --quant` (an FP8 scheme such as "
                        "prefix-mlp, calibrated on rendered suite frames; default: bf16 as initialised)")
    p.add_argument("--policy-episode-steps", type=int, default=220, help="steps per episode in the policy run")
    p.add_argument("--replan-steps", type=int, default=5, help="steps per action chunk")
    p.add_argument("--num-steps", type=int, default=10, help="flow-matching steps per policy call")
    p.add_argument("--skip-policy", action="store_true", help="environment throughput only")
    p.add_argument("--skip-env", action="store_true", help="policy-in-the-loop throughput only")
    p.add_argument("--no-physics-only", action="store_true", help="skip the physics-only (no cameras) runs")
    p.add_argument("--json", type=Path, default=None, help="also write the JSON here")
    a = p.parse_args(argv)
    return Args(**{**vars(a), "sizes": tuple(a.sizes), "policy_batch": tuple(a.policy_batch)})


def _sharded(x, sharding):
    import jax
    return jax.tree.map(lambda v: jax.device_put(v, sharding), x)


def env_throughput(env, n: int, steps: int, render: bool, sharding) -> dict:
    """Control steps per second of n environments, expert acting, with or without both cameras rendered."""
    import jax
    import jax.numpy as jnp

    from pi0_jax.sim import expert

    t = len(env.tasks)
    state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.key(0), n), jnp.arange(n) % t,
                                         (jnp.arange(n) // t) % env.num_init_states)
    es = jax.tree.map(lambda x: jnp.broadcast_to(x, (n,) + x.shape), expert.init())
    carry = _sharded((state, es, jnp.zeros((n,), jnp.int32)), sharding)

    def run(carry):
        def body(c, _):
            s, e, check = c
            a, e = jax.vmap(lambda s_, e_: expert.act(env, s_, e_))(s, e)
            s = jax.vmap(env.step)(s, a)
            if render:
                obs = jax.vmap(env.observe)(s)
                check = check + obs["agentview"].sum((1, 2, 3), jnp.int32) + obs["wrist"].sum((1, 2, 3), jnp.int32)
            return (s, e, check), None
        return jax.lax.scan(body, carry, None, length=steps)[0]

    fn = jax.jit(run, donate_argnums=0)
    t0 = time.perf_counter()
    compiled = fn.lower(carry).compile()
    compile_s = time.perf_counter() - t0
    carry = jax.block_until_ready(compiled(carry))          # warm-up
    t0 = time.perf_counter()
    carry = jax.block_until_ready(compiled(carry))
    dt = time.perf_counter() - t0
    return {"n": n, "render": render, "steps": steps, "seconds": dt, "env_steps_per_s": n * steps / dt,
            "compile_s": compile_s}


def policy_weights(args: Args) -> dict:
    """The policy's config, random weights (quantised to --policy-quant) and tokenizer: drawn once for every batch."""
    import jax

    from pi0_jax import normalize as nz
    from pi0_jax import pi0
    from pi0_jax.config import get_config
    from pi0_jax.policy import find_tokenizer
    from pi0_jax.sim import policies
    from pi0_jax.tokenizer import PaligemmaTokenizer

    config = get_config(args.policy_model)
    t0 = time.perf_counter()
    params = jax.block_until_ready(pi0.random_params(config, 0))
    init_s = time.perf_counter() - t0
    n_params = sum(x.size for x in jax.tree.leaves(params))
    # any SentencePiece model works for timing (the prompt's content does not change the cost): the embedded model's
    tok = PaligemmaTokenizer(find_tokenizer(Path(pi0_jax.__file__).parent / "assets" / "pi0_small"),
                             config.max_token_len)
    t0 = time.perf_counter()
    params = policies.quantize_for_suite(config, params, tok, nz.Normalizer.identity(), args.policy_quant)
    return {"config": config, "params": params, "tok": tok, "n_params": n_params, "init_s": init_s,
            "quant_s": time.perf_counter() - t0}


def policy_throughput(args: Args, weights: dict, n: int, sharding) -> dict:
    """Episodes per minute with a π0 / π0.5 (random weights) at batch n in the loop, through evaluate.make_segment."""
    import jax
    import jax.numpy as jnp

    from pi0_jax import normalize as nz
    from pi0_jax.sim import batching, evaluate, policies, tasks
    from pi0_jax.sim.env import Env
    from pi0_jax.sim.render import RenderConfig

    config, tok = weights["config"], weights["tok"]
    names = tasks.SUITES["all"]
    res = args.resolution
    env = Env(names, RenderConfig(res, res, batching.auto_ray_chunk(res, res, n // len(jax.local_devices()))),
              max_steps=args.policy_episode_steps)
    policy = policies.model_policy(config, weights["params"], tok, nz.Normalizer.identity(), env,
                                   num_steps=args.num_steps,
                                   name=f"{args.policy_model} (random weights)", quant=args.policy_quant)
    cfg = evaluate.EvalConfig(batch=n, replan_steps=args.replan_steps, max_steps=args.policy_episode_steps,
                              resolution=res, videos=0, segment_replans=8, num_steps=args.num_steps)
    segment = evaluate.make_segment(env, policy, cfg, 0)
    replicated = jax.sharding.NamedSharding(sharding.mesh, jax.sharding.PartitionSpec())
    params = _sharded(policy.params, replicated)     # the policy's own (engine weights, norm), not the raw tree

    def fresh_carry():
        t = len(names)
        keys = jax.random.split(jax.random.key(1), n)
        state = jax.jit(jax.vmap(env.reset))(keys, jnp.arange(n) % t, (jnp.arange(n) // t) % env.num_init_states)
        return _sharded(evaluate.Carry(state=state, pstate=policy.init(n), keys=keys), sharding)

    t0 = time.perf_counter()
    compiled = segment.lower(params, fresh_carry()).compile()
    compile_s = time.perf_counter() - t0
    n_seg = math.ceil(args.policy_episode_steps / (evaluate.segment_replans(cfg, env) * args.replan_steps))
    jax.block_until_ready(compiled(params, fresh_carry()))     # warm-up
    carry = fresh_carry()
    jax.block_until_ready(carry)
    t0 = time.perf_counter()
    for _ in range(n_seg):
        carry, _, _ = compiled(params, carry)
    jax.block_until_ready(carry)
    dt = time.perf_counter() - t0
    steps = n_seg * evaluate.segment_replans(cfg, env) * args.replan_steps
    plan_calls = steps // args.replan_steps

    # the policy call alone, same batch, for the breakdown
    obs = jax.jit(jax.vmap(env.observe))(carry.state)
    plan = jax.jit(policy.plan)
    keys = jax.random.split(jax.random.key(2), n)
    jax.block_until_ready(plan(params, carry.pstate, obs, carry.state, keys))
    t1 = time.perf_counter()
    for _ in range(3):
        out = plan(params, carry.pstate, obs, carry.state, keys)
    jax.block_until_ready(out)
    plan_ms = (time.perf_counter() - t1) / 3 * 1e3
    ep_per_min = n / dt * 60
    step_s = dt / steps                                       # wall time of one batched step incl. its share of plans
    protocol_min = LIBERO_EPISODES / n * LIBERO_MEAN_STEPS * step_s / 60
    return {"model": args.policy_model, "params": int(weights["n_params"]), "dtype": config.dtype, "batch": n,
            "quant": args.policy_quant or "none", "quantise_s": weights["quant_s"],
            "episode_steps": steps, "replan_steps": args.replan_steps, "num_steps": args.num_steps,
            "plan_calls_per_episode": plan_calls, "seconds": dt, "episodes_per_min": ep_per_min,
            "plan_ms": plan_ms, "compile_s": compile_s, "init_params_s": weights["init_s"],
            "libero_2000_protocol_min_estimate": protocol_min}


def main(argv=None) -> int:
    args = parse(argv)
    import jax
    import mujoco
    import numpy as np
    from jax.sharding import Mesh, NamedSharding, PartitionSpec

    from pi0_jax.sim import batching, tasks
    from pi0_jax.sim.env import Env
    from pi0_jax.sim.render import RenderConfig

    devices = jax.local_devices()
    sharding = NamedSharding(Mesh(np.array(devices), ("batch",)), PartitionSpec("batch"))
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                                cwd=Path(__file__).parent).stdout.strip()
    except OSError:
        commit = ""
    result = {"date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
              "device": f"{len(devices)} x {devices[0].device_kind}", "backend": jax.default_backend(),
              "jax": jax.__version__, "mujoco": mujoco.__version__, "commit": commit,
              "command": " ".join([Path(sys.argv[0]).name, *(sys.argv[1:] if argv is None else argv)]),
              "resolution": args.resolution, "env": [], "policy": None}
    res = args.resolution
    for n in () if args.skip_env else args.sizes:
        n = math.ceil(n / len(devices)) * len(devices)
        env = Env(tasks.SUITES["all"], RenderConfig(res, res, batching.auto_ray_chunk(res, res, n // len(devices))))
        for render in (True,) if args.no_physics_only else (True, False):
            r = env_throughput(env, n, args.steps, render, sharding)
            result["env"].append(r)
            print(f"N={n:5d} render={render!s:5}: {r['env_steps_per_s']:10.0f} env-steps/s "
                  f"(compile {r['compile_s']:.0f} s)", flush=True)
            _save(args, result)
    if not args.skip_policy:
        result["policy"], weights = [], policy_weights(args)
        for n in args.policy_batch:
            n = math.ceil(n / len(devices)) * len(devices)
            result["policy"].append(policy_throughput(args, weights, n, sharding))
            print(json.dumps(result["policy"][-1]), flush=True)
            _save(args, result)

    print(f"\n{result['device']} ({result['backend']}), jax {result['jax']}, mujoco {result['mujoco']}, "
          f"commit {commit}, {result['date']}\n`{result['command']}`\n")
    if result["env"]:
        print(f"| N | env-steps/s, 2 cameras {res}x{res} | env-steps/s, physics only | compile (s) |")
        print("|---:|---:|---:|---:|")
    for n in sorted({r["n"] for r in result["env"]}):
        ren = next(r for r in result["env"] if r["n"] == n and r["render"])
        phy = next((r["env_steps_per_s"] for r in result["env"] if r["n"] == n and not r["render"]), float("nan"))
        print(f"| {n} | {ren['env_steps_per_s']:.0f} | {phy:.0f} | {ren['compile_s']:.0f} |")
    if result["policy"]:
        print("\n| policy in the loop | batch | steps/episode | plan calls/episode | policy call (ms) | "
              "policy share | episodes/min | LIBERO 2000-episode protocol (min, est.) |")
        print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for p in result["policy"] or ():
        share = p["plan_ms"] * p["plan_calls_per_episode"] / 1e3 / p["seconds"]
        print(f"| {p['model']} ({p['params'] / 1e9:.2f} B params, {p['dtype']}, {p['quant']}, {p['num_steps']} "
              f"steps) | {p['batch']} | {p['episode_steps']} | {p['plan_calls_per_episode']} | {p['plan_ms']:.1f} | "
              f"{100 * share:.0f} % | {p['episodes_per_min']:.1f} | {p['libero_2000_protocol_min_estimate']:.1f} |")
    print("\n" + json.dumps(result))
    _save(args, result)
    return 0


def _save(args: Args, result: dict) -> None:
    """Write the JSON so far (a run cut short still leaves its finished measurements)."""
    if args.json is not None:
        args.json.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    sys.exit(main())
