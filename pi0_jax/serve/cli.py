"""`pi0-jax serve [CHECKPOINT]`: serve a policy over openpi's websocket protocol (see pi0_jax/serve/server.py)."""

from __future__ import annotations

import argparse
import asyncio
import logging
import time
from importlib import resources
from pathlib import Path

DESCRIPTION = """\
Serve a pi0-jax checkpoint (default: the embedded pi0_small) to robots over openpi's websocket protocol, so an
unchanged openpi-client `WebsocketClientPolicy(host, port, api_key)` works against it.

On connect the server sends the policy metadata (one binary msgpack frame). Each request is one binary frame: a
msgpack map of the observation in openpi's msgpack-numpy encoding (for the embedded model: observation/image,
observation/wrist_image (H, W, 3) uint8, observation/state (8,), prompt). An optional "noise" entry, an
(action_horizon, action_dim) float array, fixes the flow-matching noise (reproducible actions); otherwise it
comes from the policy's seeded generator in arrival order. The reply is {"actions", "policy_timing",
"server_timing"}. A request that fails gets the error and its traceback as a text frame, and its connection is
closed with code 1011; every other client is unaffected. GET /healthz answers 200.

Requests from concurrent clients that arrive within --batch-window-ms of each other are answered by one batched
model call (at most --max-batch; every batch size is compiled before the server listens). Each client gets the
actions a lone request with the same noise would get. SIGINT / SIGTERM: stop accepting, answer the requests in
flight, close, exit 0.

examples:
  pi0-jax serve                                   # embedded model on 127.0.0.1:8000
  pi0-jax serve ./pi05_libero_jax --host 0.0.0.0 --api-key "$KEY" --num-steps 10
"""


def add_serve_parser(subparsers) -> None:
    p = subparsers.add_parser("serve", help="serve a policy over openpi's websocket protocol (dynamic batching)",
                              description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("checkpoint", nargs="?", type=Path, default=None, metavar="CHECKPOINT",
                   help="pi0-jax checkpoint directory (`pi0-jax convert` output); default: the embedded pi0_small")
    net = p.add_argument_group("network")
    net.add_argument("--host", default="127.0.0.1",
                     help="address to listen on (default: %(default)s, this machine only; 0.0.0.0 for every "
                          "interface -- then also set --api-key)")
    net.add_argument("--port", type=int, default=8000,
                     help="TCP port (default: %(default)s, openpi's; 0 picks a free one and prints it)")
    net.add_argument("--api-key", default=None, metavar="KEY",
                     help="require the header 'Authorization: Api-Key KEY' (what openpi-client sends for "
                          "api_key=KEY); a missing header is refused with HTTP 401, a wrong key with 403 "
                          "(default: no key; /healthz never needs one)")
    net.add_argument("--max-frame-mb", type=float, default=64.0, metavar="MB",
                     help="largest request frame accepted, in MiB; a larger one closes its connection with code "
                          "1009 (default: %(default)g)")
    bat = p.add_argument_group("batching")
    bat.add_argument("--max-batch", type=int, default=8, metavar="N",
                     help="most requests answered by one model call; a group is padded up to one of the policy's "
                          "batch buckets, each compiled ahead (default: %(default)s; 1 answers each request alone)")
    bat.add_argument("--batch-window-ms", type=float, default=2.0, metavar="MS",
                     help="how long the oldest waiting request waits for other clients' requests to share its "
                          "call, counted from its arrival or from the model becoming free, whichever is later, and "
                          "only while another connected client has nothing queued (default: %(default)g). 0 never "
                          "waits; requests that queued while the model was busy still share the next call "
                          "(--max-batch 1 answers each request alone)")
    pol = p.add_argument_group("policy")
    pol.add_argument("--num-steps", type=int, default=None,
                     help="flow-matching Euler steps per request (default: the checkpoint's num_steps, e.g. a "
                          "distilled student's, else 10)")
    pol.add_argument("--seed", type=int, default=0,
                     help="seed of the policy's noise generator, used for requests without 'noise' (default: 0)")
    pol.add_argument("--dtype", choices=("float32", "bfloat16"), default=None,
                     help="param and compute dtype (default: float32 on CPU, where XLA only emulates bfloat16; "
                          "the checkpoint's on an accelerator)")
    pol.add_argument("--kernels", choices=("auto", "xla", "pallas"), default="auto",
                     help="the action expert's layers in the denoise step: XLA ops, the Pallas kernels of "
                          "pi0_jax.ops, or auto: the kernels for batches of 1 and 2 on a GPU, XLA for larger ones and "
                          "on a CPU (where the kernels run interpreted, slowly). On an H200 the kernels are faster "
                          "at batch 1 (0.83 against 1.09 ms per flow step) and slower at batch 8 (3.9 against "
                          "2.5 ms): docs/BENCHMARKS.md, 'Fused kernels'. SigLIP's LayerNorm likewise (auto: the "
                          "kernel on a GPU from 24 images a call). Default: %(default)s")
    pol.add_argument("--attention", default="auto", type=_attention,
                     help="each stage's attention: xla, cudnn (one fused flash kernel), auto (the faster per stage "
                          "on a GPU, XLA on a CPU), or per stage, e.g. vision=pallas,prefix=cudnn,denoise=xla "
                          "(vision may be pallas: a kernel that reads q, k, v in place; denoise may be pallas: the "
                          "action expert's split-key kernel) (default: %(default)s)")
    pol.add_argument("--overlap", choices=("auto", "on", "off"), default="auto",
                     help="the first denoise step beside the prefix fill (that program's command buffers in XLA's "
                          "CONCURRENT mode, the other steps a program of their own): on, off, or auto (on a GPU where "
                          "the expert runs its Pallas kernels, at batch 1 and 2; on an H200 such a call 2-3.5 %% "
                          "faster at batch 1, docs/BENCHMARKS.md). Default: %(default)s")
    pol.add_argument("--tokenizer", type=Path, default=None, metavar="FILE",
                     help="PaliGemma SentencePiece model (default: CHECKPOINT/tokenizer.model, then "
                          "CHECKPOINT/assets/tokenizer.model)")
    pol.add_argument("--norm-stats", default=None, metavar="PATH",
                     help="openpi norm_stats.json or LeRobot processor directory, or 'identity' (default: found "
                          "under CHECKPOINT/assets)")
    pol.add_argument("--strict", action=argparse.BooleanOptionalAction, default=None,
                     help="--no-strict ignores observation keys the policy does not know instead of refusing the "
                          "request (default: strict)")
    p.add_argument("--no-warmup", action="store_true",
                   help="listen at once and compile each batch size on its first request (default: compile every "
                        "batch size before listening, and print how long it took)")
    p.add_argument("--log-level", default="INFO", choices=("DEBUG", "INFO", "WARNING", "ERROR"),
                   help="logging level: INFO logs one line per connection opened / closed and per failed request "
                        "(default: %(default)s)")
    p.set_defaults(func=run)


def _attention(spec: str) -> str:
    from pi0_jax.engine.paths import attention_spec   # jax on use: --help stays light

    return attention_spec(spec)


def _policy_kwargs(args: argparse.Namespace) -> dict:
    """The keyword arguments for `Policy.from_checkpoint`; the optional ones only when given."""
    import jax

    kwargs = {"num_steps": args.num_steps, "seed": args.seed, "max_batch": args.max_batch, "kernels": args.kernels,
              "attention": args.attention, "overlap": args.overlap,
              "dtype": args.dtype if args.dtype or jax.default_backend() != "cpu" else "float32"}
    optional = {"tokenizer_path": args.tokenizer, "norm_stats": args.norm_stats, "strict": args.strict}
    return {**kwargs, **{k: v for k, v in optional.items() if v is not None}}


def run(args: argparse.Namespace) -> int:
    from pi0_jax.policy import Policy
    from pi0_jax.serve.server import PolicyServer

    if logging.getLogger().handlers == []:
        logging.basicConfig(level=args.log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    logging.getLogger("pi0_jax").setLevel(args.log_level)
    if args.log_level == "DEBUG":   # websockets' own connection logs too
        logging.getLogger("pi0_jax.serve.websockets").setLevel(logging.DEBUG)
    if args.max_batch < 1:
        raise SystemExit("pi0-jax serve: --max-batch must be >= 1")
    with resources.as_file(resources.files("pi0_jax") / "assets" / "pi0_small") as embedded:
        ckpt = args.checkpoint or embedded
        t0 = time.perf_counter()
        policy = Policy.from_checkpoint(ckpt, **_policy_kwargs(args))
        import jax

        print(f"loaded {policy.metadata.get('name', ckpt)} ({'embedded' if args.checkpoint is None else ckpt}) "
              f"in {time.perf_counter() - t0:.1f} s on {jax.default_backend()}", flush=True)
        if not args.no_warmup:
            sizes = tuple(b for b in policy.batch_buckets if b <= args.max_batch)
            t0 = time.perf_counter()
            policy.warmup(sizes, policy.example_observation())
            print(f"compiled batch sizes {sizes} in {time.perf_counter() - t0:.1f} s", flush=True)
        server = PolicyServer(policy, args.host, args.port, max_batch=args.max_batch,
                              batch_window_ms=args.batch_window_ms, api_key=args.api_key,
                              max_frame_bytes=int(args.max_frame_mb * 2**20))

        def ready(s: PolicyServer) -> None:
            print(f"listening on ws://{s.host}:{s.port} (GET /healthz; Ctrl-C stops)", flush=True)

        asyncio.run(server.run(ready, handle_signals=True))
    return 0
