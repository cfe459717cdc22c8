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

from pi0_jax.serve.protocol import ProtocolError, packb, unpackb
from pi0_jax.serve.server import Batcher, PolicyServer, ServerHandle, serve

__all__ = ["Batcher", "PolicyServer", "ProtocolError", "ServerHandle", "packb", "serve", "unpackb"]
