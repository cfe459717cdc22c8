"""What a caller pays on top of the engine: `Policy.infer` from host numpy against the engine's call alone
(device-resident inputs), in the same process, on the same weights' shapes and inputs.

Engine alone: `Engine.sample_packed` on already packed, device-resident inputs (the benchmark's `total`).
Policy.infer: one observation dict of uint8 HWC frames, a float state and a prompt string -> un-normalised actions
as numpy (validation, cached tokenisation, one host-to-device transfer, the compiled pipeline, the device-to-host
copy). infer_batch: B observations through one batched call.

    python scripts/policy_bench.py --preset pi0_base --out policy_bench.json          # random full-size weights
    python scripts/policy_bench.py --embedded --dtype float32 --out cpu.json          # the embedded pi0_small
"""

from __future__ import annotations

import argparse
import json
import time
from importlib import resources
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from pi0_jax import benchmark, checkpoint
from pi0_jax import normalize as nz
from pi0_jax import policy as policy_module
from pi0_jax.config import IMAGE_KEYS, get_config
from pi0_jax.engine import Engine, prompt_bucket
from pi0_jax.policy import Policy, find_tokenizer
from pi0_jax.tokenizer import PaligemmaTokenizer

EMBEDDED = resources.files("pi0_jax") / "assets" / "pi0_small"


def timed(fn, iters: int, warmup: int) -> dict:
    for _ in range(warmup):
        jax.block_until_ready(fn())
    times = []
    for _ in range(iters):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        times.append((time.perf_counter() - start) * 1e3)
    return {"median_ms": float(np.median(times)), "p90_ms": float(np.percentile(times, 90)),
            "min_ms": float(np.min(times))}


def observations(policy: Policy, n: int, cameras: int) -> list[dict]:
    """n distinct observations with `cameras` cameras at the model's size (openpi's LIBERO keys + bare slots)."""
    out = []
    size = policy.config.image_size
    for i in range(n):
        rng = np.random.default_rng(i)
        obs = policy.example_observation(seed=i)
        for slot in IMAGE_KEYS[len([k for k in obs if "image" in k]): cameras]:
            obs[slot] = rng.integers(0, 256, (size, size, 3), dtype=np.uint8)
        out.append(obs)
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", default="pi0_base", help="random weights of this preset (default: %(default)s)")
    p.add_argument("--embedded", action="store_true", help="the embedded trained pi0_small instead of --preset")
    p.add_argument("--dtype", default="bfloat16", help="bfloat16 or float32 (default: %(default)s)")
    p.add_argument("--steps", type=int, default=10, help="flow steps (default: %(default)s)")
    p.add_argument("--cameras", type=int, default=3, help="cameras sent (default: 3, as many as the model has)")
    p.add_argument("--batch", type=int, default=8, help="also time infer_batch of this many (default: 8; 0: skip)")
    p.add_argument("--iters", type=int, default=50, help="timed calls per measurement (default: %(default)s)")
    p.add_argument("--warmup", type=int, default=3, help="untimed calls first (default: %(default)s)")
    p.add_argument("--overlap", choices=("auto", "on", "off"), default="auto",
                   help="the first denoise step beside the prefix fill, in the policy and the engine alike "
                        "(`paths.first_step_overlap`; default: %(default)s)")
    p.add_argument("--copy-back-ab", action="store_true",
                   help="also time, in turns, a Policy whose actions are copied back after the call instead of by its "
                        "last program (`policy._to_host`)")
    p.add_argument("--out", type=Path, default=Path("policy_bench.json"), help="JSON results (default: %(default)s)")
    args = p.parse_args()

    if args.embedded:
        config, params = checkpoint.load_checkpoint(EMBEDDED, dtype=args.dtype)
        config = config.replace(dtype=args.dtype)
        normalizer = nz.load_normalizer(EMBEDDED, use_quantiles=config.pi05)
        name = "pi0_small (embedded)"
    else:
        config = get_config(args.preset, dtype=args.dtype)
        params = benchmark.random_params(config, 0)
        normalizer = nz.Normalizer.identity()
        name = f"{args.preset} (random weights)"
    # any SentencePiece model works for timing: the embedded model's, at the config's prompt length
    tokenizer = PaligemmaTokenizer(find_tokenizer(EMBEDDED), config.max_token_len)
    cameras = min(args.cameras, config.num_cameras)
    policy = Policy(config, params, tokenizer, normalizer, num_steps=args.steps, cache_dir=False,
                    max_batch=max(args.batch, 1), overlap=args.overlap)
    obs = observations(policy, 4, cameras)
    prepared = policy.prepare(obs[0])
    t0 = time.perf_counter()
    policy.warmup([1] + ([args.batch] if args.batch else []), obs[0])
    warmup_s = time.perf_counter() - t0

    # the engine alone on the same inputs, device-resident (Policy's transforms done once, outside the clock)
    engine = Engine(config, params, cache_dir=False, overlap=args.overlap)
    ref_obs = policy.make_observation(obs[0])
    cams, bucket = engine.plan(ref_obs)
    packed = engine.pack(ref_obs, cams, bucket)
    noise = jnp.asarray(prepared.noise[None])

    def call():
        return engine.sample_packed(packed, noise, args.steps, cams, bucket)

    engine_t = timed(call, args.iters, args.warmup)
    engine_actions = np.asarray(call())[0]

    i = iter(range(10**9))
    policy_t = timed(lambda: policy.infer(obs[next(i) % len(obs)])["actions"], args.iters, args.warmup)
    got = policy.infer(obs[0], noise=prepared.noise)["actions"]
    want = normalizer.unnormalize(nz.ACTIONS, engine_actions[:, : policy.action_dims]) if normalizer.stats else \
        engine_actions[:, : policy.action_dims]
    rel = float(np.linalg.norm(got - want) / np.linalg.norm(want))
    rows = {"engine_alone": engine_t, "policy_infer": policy_t}
    # Policy's compiled call alone, on the host arrays `Policy._run_group` makes for obs[0]: with them already on the
    # device (its programs against the engine's), then as numpy with the actions copied back (the transfers)
    n = prompt_bucket(prepared.valid_tokens, config.max_token_len)
    host = (tuple(prepared.images[c][None] for c in prepared.cameras), np.ones((len(prepared.cameras), 1), bool),
            prepared.tokens[None, :n], prepared.token_mask[None, :n], prepared.state[None], prepared.noise[None])
    policy_call = policy.executable(host, prepared.cameras)
    on_device = jax.device_put(host)
    rows["policy_call_device_inputs"] = timed(lambda: policy_call(policy._norm, *on_device), args.iters, args.warmup)
    rows["policy_call_numpy"] = timed(lambda: np.asarray(policy_call(policy._norm, *host)), args.iters, args.warmup)
    # which inputs' transfers cost: the images (the vision program's, at the call's start) or the small arrays (the
    # prefix program's, dispatched while the GPU runs the tower)
    rows["policy_call_images_on_device"] = timed(lambda: np.asarray(policy_call(policy._norm, on_device[0], *host[1:])),
                                                 args.iters, args.warmup)
    rows["policy_call_rest_on_device"] = timed(lambda: np.asarray(policy_call(policy._norm, host[0], *on_device[1:])),
                                               args.iters, args.warmup)
    # Policy.infer's steps one by one on top of the compiled call: the host arrays rebuilt from a fresh `prepare`
    # (its state and noise are new arrays each time), then `Policy.run` without its result dicts
    def rebuilt(p):
        return (tuple(p.images[c][None] for c in p.cameras), np.ones((len(p.cameras), 1), bool), p.tokens[None, :n],
                p.token_mask[None, :n], p.state[None], p.noise[None])

    rows["policy_call_prepared_each_call"] = timed(
        lambda: np.asarray(policy_call(policy._norm, *rebuilt(policy.prepare(obs[0])))), args.iters, args.warmup)
    # which fresh inputs cost (a robot's frames are new buffers each call): new view objects of the same frames, new
    # copies of the small arrays, new copies of the frames (the copies' own host time is in `host_copies`)
    def fresh(images, small):
        return (tuple(x[0][None] if images == "views" else x.copy() if images == "copies" else x for x in host[0]),
                *(x.copy() if small else x for x in host[1:]))

    rows["host_copies"] = timed(lambda: fresh("copies", True), args.iters, args.warmup)
    for images, small in (("views", False), ("same", True), ("copies", False), ("copies", True)):
        rows[f"policy_call_fresh_images_{images}_small_{'copies' if small else 'same'}"] = timed(
            lambda: np.asarray(policy_call(policy._norm, *fresh(images, small))), args.iters, args.warmup)
    rows["policy_run_group"] = timed(lambda: policy._run_group([policy.prepare(obs[0])])[0], args.iters, args.warmup)
    # the images as one array a camera (today's call) against one array of all cameras, into a program that only
    # reads them: what a transfer costs at the call's start
    frames = host[0]
    stacked = np.stack(frames)
    touch = jax.jit(lambda *xs: sum(x[..., :1, :1, :].astype(jnp.float32).sum() for x in xs))
    rows["images_one_array_a_camera"] = timed(lambda: touch(*frames), args.iters, args.warmup)
    rows["images_one_array"] = timed(lambda: touch(stacked), args.iters, args.warmup)
    rows["images_on_device"] = timed(lambda: touch(*on_device[0]), args.iters, args.warmup)
    # the frames staged through pinned host memory first (a host copy, then a DMA), where the device has it: into the
    # program that only reads them, and into the policy's call with the small arrays as numpy
    dev = jax.devices()[0]
    if "pinned_host" in {m.kind for m in dev.addressable_memories()}:
        pinned = jax.sharding.make_single_device_sharding(dev, memory_kind="pinned_host")
        device = jax.sharding.make_single_device_sharding(dev, memory_kind="device")

        def via_pinned(xs):
            return jax.device_put(jax.device_put(xs, pinned), device)

        rows["images_to_pinned_host"] = timed(lambda: jax.device_put(frames, pinned), args.iters, args.warmup)
        rows["images_via_pinned_host"] = timed(lambda: touch(*via_pinned(frames)), args.iters, args.warmup)
        rows["images_device_put"] = timed(lambda: touch(*jax.device_put(frames, device)), args.iters, args.warmup)
        rows["policy_call_images_via_pinned_host"] = timed(
            lambda: np.asarray(policy_call(policy._norm, via_pinned(host[0]), *host[1:])), args.iters, args.warmup)
        rows["policy_call_numpy_again"] = timed(lambda: np.asarray(policy_call(policy._norm, *host)), args.iters,
                                                args.warmup)
        assert np.array_equal(np.asarray(policy_call(policy._norm, via_pinned(host[0]), *host[1:])),
                              np.asarray(policy_call(policy._norm, *host)))
    # where the transfers' time goes: the actions' copy back alone; that copy queued behind the call at its dispatch;
    # the inputs as one host buffer (one transfer, unpacked on the device by a program of its own)
    rows["policy_call_device_inputs_copy_back"] = timed(lambda: np.asarray(policy_call(policy._norm, *on_device)),
                                                        args.iters, args.warmup)

    def queued(*inputs):
        out = policy_call(policy._norm, *inputs)
        out.copy_to_host_async()
        return np.asarray(out)

    rows["policy_call_numpy_copy_queued"] = timed(lambda: queued(*host), args.iters, args.warmup)
    leaves, tree = jax.tree.flatten(host)
    flat = [np.ascontiguousarray(x).reshape(-1).view(np.uint8) for x in leaves]
    ends = np.cumsum([0] + [f.size for f in flat])
    unpack = jax.jit(lambda buf: jax.tree.unflatten(tree, [
        jax.lax.bitcast_convert_type(buf[a:b].reshape(-1, x.dtype.itemsize), x.dtype).reshape(x.shape)
        if x.dtype.itemsize > 1 else buf[a:b].view(x.dtype).reshape(x.shape)
        for x, a, b in zip(leaves, ends[:-1], ends[1:])]))

    def one_transfer():
        buf = np.concatenate(flat)
        return queued(*unpack(buf))

    rows["policy_call_one_transfer"] = timed(one_transfer, args.iters, args.warmup)
    assert np.array_equal(one_transfer(), np.asarray(policy_call(policy._norm, *host)))
    if args.batch:
        batch_obs = [obs[k % len(obs)] for k in range(args.batch)]
        rows[f"infer_batch_{args.batch}"] = timed(lambda: policy.infer_batch(batch_obs)[-1]["actions"], args.iters,
                                                  args.warmup)
    if args.copy_back_ab:
        # the same Policy with the actions' copy back after the call (as before session 48), timed in turns with it
        own = policy_module._to_host
        policy_module._to_host = lambda fn: fn
        try:
            after = Policy(config, params, tokenizer, normalizer, num_steps=args.steps, cache_dir=False, max_batch=1,
                           overlap=args.overlap)
            after.warmup([1], obs[0])
        finally:
            policy_module._to_host = own
        for turn in range(2):
            rows[f"policy_infer_turn{turn}"] = timed(lambda: policy.infer(obs[0])["actions"], args.iters, args.warmup)
            rows[f"policy_infer_copy_after_call_turn{turn}"] = timed(lambda: after.infer(obs[0])["actions"],
                                                                     args.iters, args.warmup)
        assert np.array_equal(after.infer(obs[0], noise=prepared.noise)["actions"], got)
    env = benchmark.environment()
    result = {"model": name, "dtype": args.dtype, "steps": args.steps, "cameras": cameras,
              "overlap": {"policy": policy.metadata["overlap"], "at_batch_1": engine.overlaps(1)},
              "prompt_bucket": bucket, "env": env, "warmup_s": warmup_s, "rows": rows,
              "overhead_ms": policy_t["median_ms"] - engine_t["median_ms"],
              "policy_vs_engine_rel_l2": rel, "args": {k: str(v) for k, v in vars(args).items()}}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"{env['device']} · {name} · {args.dtype} · {args.steps} steps · {cameras} cameras · commit {env['commit']}")
    print("| path | median ms | p90 ms | min ms |\n|---|---:|---:|---:|")
    for k, r in rows.items():
        print(f"| {k} | {r['median_ms']:.2f} | {r['p90_ms']:.2f} | {r['min_ms']:.2f} |")
    print(f"Policy.infer - engine alone: {result['overhead_ms']:+.2f} ms; actions rel L2 vs engine: {rel:.1e}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
