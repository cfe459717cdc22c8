"""Policy-server latency and throughput: N concurrent clients over real websockets, batched vs one at a time.

    python scripts/serve_bench.py                                   # embedded pi0_small (CPU is fine), 8 clients
    python scripts/serve_bench.py --preset pi0_base --all-cameras --requests 100 --out serve.json    # GPU, full size
    python scripts/serve_bench.py --url ws://127.0.0.1:8000 --clients 8     # a running `pi0-jax serve`

The script starts the server itself (`pi0_jax.serve.serve`, a background thread of this process) on one Policy,
compiles every batch bucket first (timed apart), and measures three configurations in the same run:

  1 client            one client, one request at a time: the round trip a robot sees (`overhead` = round trip
                      minus the server's model call, i.e. encoding + socket + decoding + validation + queueing)
  N clients, serial   N clients at once, the server answering one request per model call (max_batch 1)
  N clients, batched  N clients at once through dynamic batching (--max-batch, --batch-window-ms)

Clients are separate processes (`--client-threads` for threads), each with its own observation (random uint8
frames at the model's size, a random state, the example prompt); each sends --warmup requests, waits at a barrier,
then sends --requests requests back to back and times each round trip. requests/s = all timed requests / (last
reply - first send). `gain` = batched requests/s / serial requests/s. With --url only the server's own
configuration is measured (1 client and N clients). Prints a markdown table; --out writes the JSON.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import multiprocessing as mp
import threading
import time
import traceback
from pathlib import Path

import numpy as np


@dataclasses.dataclass(frozen=True)
class Args:
    checkpoint: Path | None
    preset: str | None
    url: str | None
    api_key: str | None
    clients: int
    requests: int
    warmup: int
    max_batch: int | None
    batch_window_ms: float
    num_steps: int | None
    dtype: str | None
    all_cameras: bool
    client_threads: bool
    seed: int
    out: Path | None


def parse(argv=None) -> Args:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    src = p.add_mutually_exclusive_group()
    src.add_argument("--checkpoint", type=Path, default=None, help="pi0-jax checkpoint (default: the embedded one)")
    src.add_argument("--preset", default=None,
                     help="pi0_jax.config preset with random weights (e.g. pi0_base), identity normalisation and "
                          "the embedded tokenizer: full-size timing without a checkpoint")
    src.add_argument("--url", default=None, help="measure a running server (ws://host:port) instead of starting one")
    p.add_argument("--api-key", default=None, help="with --url: the server's API key")
    p.add_argument("--clients", type=int, default=8, help="concurrent clients N (default: %(default)s)")
    p.add_argument("--requests", type=int, default=30, help="timed requests per client (default: %(default)s)")
    p.add_argument("--warmup", type=int, default=3, help="untimed requests per client first (default: %(default)s)")
    p.add_argument("--max-batch", type=int, default=None, help="batched row's max batch (default: N)")
    p.add_argument("--batch-window-ms", type=float, default=2.0, help="batched row's window (default: %(default)g)")
    p.add_argument("--num-steps", type=int, default=None, help="flow steps (default: the checkpoint's, else 10)")
    p.add_argument("--dtype", choices=("float32", "bfloat16"), default=None,
                   help="param / compute dtype (default: float32 on CPU, else the checkpoint's or preset's)")
    p.add_argument("--all-cameras", action="store_true",
                   help="also send the cameras the model may go without (π0's right wrist): 3 cameras for full-size")
    p.add_argument("--client-threads", action="store_true", help="clients as threads of this process, not processes")
    p.add_argument("--seed", type=int, default=0, help="observations' and random weights' seed")
    p.add_argument("--out", type=Path, default=None, help="write the JSON here")
    a = p.parse_args(argv)
    if a.clients < 1 or a.requests < 1:
        p.error("--clients and --requests must be >= 1")
    return Args(**vars(a))


# -- the policy -------------------------------------------------------------------------------------------------------
def build_policy(args: Args):
    """-> (Policy, description). Every batch bucket is compiled by the caller."""
    import jax
    from importlib import resources

    from pi0_jax.policy import Policy

    max_batch = args.max_batch or args.clients
    cpu = jax.default_backend() == "cpu"
    dtype = args.dtype or ("float32" if cpu else None)
    if args.preset is None:
        with resources.as_file(resources.files("pi0_jax") / "assets" / "pi0_small") as embedded:
            ckpt = args.checkpoint or embedded
            policy = Policy.from_checkpoint(ckpt, num_steps=args.num_steps, seed=args.seed, max_batch=max_batch,
                                            dtype=dtype)
        return policy, str(args.checkpoint or "embedded pi0_small")

    from pi0_jax import benchmark
    from pi0_jax import normalize as nz
    from pi0_jax.config import get_config
    from pi0_jax.tokenizer import PaligemmaTokenizer

    config = get_config(args.preset, **({"dtype": dtype} if dtype else {}))
    params = jax.block_until_ready(benchmark.random_params(config, args.seed))
    # any SentencePiece model gives the timing (a prompt's content does not change the cost): the embedded model's
    tok = PaligemmaTokenizer(resources.files("pi0_jax") / "assets" / "pi0_small" / "tokenizer.model",
                             config.max_token_len)
    policy = Policy(config, params, tok, nz.Normalizer.identity(), num_steps=args.num_steps or 10, seed=args.seed,
                    max_batch=max_batch)
    return policy, f"{args.preset} (random weights)"


def observation(metadata: dict, example: dict, seed: int, all_cameras: bool) -> dict:
    """The example observation with this client's own random frames and state (same shapes and keys)."""
    rng = np.random.default_rng(1000 + seed)
    obs = {k: rng.integers(0, 256, v.shape, dtype=np.uint8) if isinstance(v, np.ndarray) and v.dtype == np.uint8
           else v for k, v in example.items()}
    if all_cameras:
        size = metadata["image_size"]
        for slot in metadata["camera_slots"]:
            if slot not in metadata["required_cameras"]:
                obs[slot] = rng.integers(0, 256, (size, size, 3), dtype=np.uint8)
    for k in ("observation/state", "observation.state", "state"):
        if k in obs:
            obs[k] = rng.uniform(-1, 1, np.shape(obs[k])).astype(np.float32)
    return obs


# -- clients ----------------------------------------------------------------------------------------------------------
def client_main(url: str, api_key: str | None, obs: dict, warmup: int, requests: int, barrier, results, idx: int):
    """One client (process or thread): warm up, wait at the barrier, time `requests` round trips."""
    try:
        from websockets.sync.client import connect

        from pi0_jax.serve import protocol

        headers = {"Authorization": f"Api-Key {api_key}"} if api_key else None
        with connect(url, compression=None, max_size=None, additional_headers=headers, open_timeout=60) as ws:
            protocol.unpackb(ws.recv(timeout=600))      # metadata
            frame = protocol.packb(obs)

            def once():
                ws.send(frame)
                reply = ws.recv(timeout=600)
                if isinstance(reply, str):
                    raise RuntimeError(f"server error:\n{reply}")
                return protocol.unpackb(reply)

            for _ in range(warmup):
                once()
            barrier.wait(timeout=600)
            rtt, timing = [], []
            t_first = time.monotonic()        # CLOCK_MONOTONIC: comparable across processes on Linux
            for _ in range(requests):
                t0 = time.perf_counter()
                reply = once()
                rtt.append((time.perf_counter() - t0) * 1e3)
                timing.append(reply["server_timing"])
            results.put((idx, {"rtt_ms": rtt, "server_timing": timing, "t_first": t_first, "t_last": time.monotonic()}))
    except BaseException:  # noqa: BLE001  (reported to the parent)
        results.put((idx, {"error": traceback.format_exc()}))
        with contextlib.suppress(Exception):
            barrier.abort()


def run_clients(url: str, args: Args, observations: list[dict]) -> dict:
    """N clients at once against `url` -> latency / throughput summary."""
    n = len(observations)
    if args.client_threads:
        import queue

        barrier, results = threading.Barrier(n), queue.Queue()
        workers = [threading.Thread(target=client_main, args=(url, args.api_key, observations[i], args.warmup,
                                                               args.requests, barrier, results, i), daemon=True)
                   for i in range(n)]
    else:
        ctx = mp.get_context("spawn")   # no fork of a process that runs JAX and the server's threads
        barrier, results = ctx.Barrier(n), ctx.Queue()
        workers = [ctx.Process(target=client_main, args=(url, args.api_key, observations[i], args.warmup,
                                                         args.requests, barrier, results, i), daemon=True)
                   for i in range(n)]
    for w in workers:
        w.start()
    got = dict(results.get(timeout=1800) for _ in range(n))
    for w in workers:
        w.join(60)
    errors = [r["error"] for r in got.values() if "error" in r]
    if errors:
        raise RuntimeError("a client failed:\n" + errors[0])
    rtt = np.concatenate([r["rtt_ms"] for r in got.values()])
    timing = [t for r in got.values() for t in r["server_timing"]]
    wall = max(r["t_last"] for r in got.values()) - min(r["t_first"] for r in got.values())
    infer = np.array([t["infer_ms"] for t in timing])
    overhead = rtt - infer
    p50, p90, p99 = np.percentile(rtt, [50, 90, 99])
    return {"clients": n, "requests": int(rtt.size), "p50_ms": p50, "p90_ms": p90, "p99_ms": p99,
            "mean_ms": float(rtt.mean()), "requests_per_s": rtt.size / wall, "wall_s": wall,
            "mean_batch": float(np.mean([t["batch_size"] for t in timing])),
            "server_infer_p50_ms": float(np.median(infer)), "overhead_p50_ms": float(np.median(overhead)),
            "queue_p50_ms": float(np.median([t["queue_ms"] for t in timing])),
            "prepare_p50_ms": float(np.median([t["prepare_ms"] for t in timing]))}


# -- main -------------------------------------------------------------------------------------------------------------
def table(rows: list[dict]) -> str:
    head = ("| configuration | clients | p50 ms | p90 ms | p99 ms | requests/s | mean batch | model call p50 ms | "
            "overhead p50 ms |\n|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    lines = [f"| {r['name']} | {r['clients']} | {r['p50_ms']:.2f} | {r['p90_ms']:.2f} | {r['p99_ms']:.2f} | "
             f"{r['requests_per_s']:.1f} | {r['mean_batch']:.2f} | {r['server_infer_p50_ms']:.2f} | "
             f"{r['overhead_p50_ms']:.2f} |" for r in rows]
    return "\n".join([head, *lines])


def main(argv=None) -> int:
    args = parse(argv)
    import jax

    from pi0_jax.serve import serve

    dev = jax.devices()[0]
    info = {"device": getattr(dev, "device_kind", str(dev)), "backend": jax.default_backend(),
            "jax": jax.__version__, "clients": args.clients, "requests_per_client": args.requests,
            "warmup_per_client": args.warmup, "client_processes": not args.client_threads}
    rows = []
    if args.url is not None:
        from websockets.sync.client import connect

        from pi0_jax.serve import protocol

        headers = {"Authorization": f"Api-Key {args.api_key}"} if args.api_key else None
        with connect(args.url, compression=None, max_size=None, additional_headers=headers, open_timeout=60) as ws:
            metadata = protocol.unpackb(ws.recv(timeout=60))
        if "camera_keys" not in metadata:
            raise SystemExit("--url: the server's metadata does not describe its observation (not pi0-jax serve?)")
        example = _example_from_metadata(metadata)
        obs = [observation(metadata, example, i, args.all_cameras) for i in range(args.clients)]
        info.update(model=metadata.get("name"), url=args.url, metadata=metadata)
        rows.append({"name": "1 client", **run_clients(args.url, args, obs[:1])})
        rows.append({"name": f"{args.clients} clients (server's settings)", **run_clients(args.url, args, obs)})
    else:
        t0 = time.perf_counter()
        policy, model = build_policy(args)
        load_s = time.perf_counter() - t0
        metadata = policy.metadata
        example = policy.example_observation(args.seed)
        obs = [observation(metadata, example, i, args.all_cameras) for i in range(args.clients)]
        t0 = time.perf_counter()
        for o in {tuple(sorted(o)): o for o in obs}.values():     # each key set (camera count) once
            policy.warmup(policy.batch_buckets, o)
        compile_s = time.perf_counter() - t0
        max_batch = policy.batch_buckets[-1]
        info.update(model=model, num_steps=metadata["num_steps"], dtype=metadata["dtype"],
                    cameras=sum(k in metadata["camera_keys"] or k in metadata["camera_slots"] for k in obs[0]),
                    batch_buckets=list(policy.batch_buckets), batch_window_ms=args.batch_window_ms,
                    load_s=load_s, compile_s=compile_s)
        print(f"{model}: loaded in {load_s:.1f} s, compiled batch sizes {policy.batch_buckets} in {compile_s:.1f} s "
              f"on {info['device']}", flush=True)
        configs = [("1 client", obs[:1], 1, 0.0),
                   (f"{args.clients} clients, serial", obs, 1, 0.0),
                   (f"{args.clients} clients, batched", obs, max_batch, args.batch_window_ms)]
        for name, client_obs, mb, window in configs:
            with serve(policy, "127.0.0.1", 0, max_batch=mb, batch_window_ms=window) as handle:
                row = run_clients(handle.url, args, client_obs)
            rows.append({"name": name, "max_batch": mb, "batch_window_ms": window, **row})
            print(f"  {name}: p50 {row['p50_ms']:.2f} ms, {row['requests_per_s']:.1f} requests/s", flush=True)
    result = {"config": info, "rows": rows}
    if args.url is None:
        result["batching_gain"] = rows[2]["requests_per_s"] / rows[1]["requests_per_s"]
    print()
    print(table(rows))
    if "batching_gain" in result:
        print(f"\nbatching gain ({args.clients} clients): {result['batching_gain']:.2f}x requests/s; "
              f"1-client overhead over the model call: {rows[0]['overhead_p50_ms']:.2f} ms (p50)")
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=2, default=float))
        print(f"wrote {args.out}")
    return 0


def _example_from_metadata(metadata: dict) -> dict:
    """An observation for a remote server from its metadata: one key per required camera, state, prompt."""
    size, keys = metadata["image_size"], {}
    for key, slot in metadata["camera_keys"].items():
        if slot in metadata["required_cameras"]:
            keys.setdefault(slot, key)
    obs = {k: np.zeros((size, size, 3), np.uint8) for k in keys.values()}
    if metadata.get("state_dim") or not metadata.get("pi05"):
        obs["observation/state"] = np.zeros(metadata.get("state_dim") or 32, np.float32)
    obs["prompt"] = "pick up the red block"
    return obs


if __name__ == "__main__":
    raise SystemExit(main())
