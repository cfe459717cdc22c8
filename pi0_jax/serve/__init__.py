"""Serve a policy to robots over openpi's websocket protocol (`pi0-jax serve`).

  protocol.py  openpi's msgpack-numpy frames: encode replies, decode requests without trusting them
  server.py    the websocket server: metadata on connect, one worker thread on the device, dynamic batching,
               errors as a text frame + close 1011, /healthz, API key, clean shutdown
  cli.py       `pi0-jax serve [CHECKPOINT]`

From Python (a background thread; port 0 picks a free port):

    from pi0_jax.policy import Policy
    from pi0_jax.serve import serve

    policy = Policy.from_checkpoint(ckpt, num_steps=10, max_batch=8)
    policy.warmup(policy.batch_buckets, policy.example_observation())
    with serve(policy, "127.0.0.1", 0, max_batch=8, batch_window_ms=2) as handle:
        ...                                   # clients connect to handle.url
"""

import importlib

_EXPORTS = {"ProtocolError": "protocol", "packb": "protocol", "unpackb": "protocol", "Batcher": "server",
            "PolicyServer": "server", "ServerHandle": "server", "serve": "server"}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    # Lazy: `pi0-jax eval` and the rest of the CLI import this package's parser without websockets or msgpack.
    if name in _EXPORTS:
        return getattr(importlib.import_module(f"pi0_jax.serve.{_EXPORTS[name]}"), name)
    raise AttributeError(f"module 'pi0_jax.serve' has no attribute {name!r}")
