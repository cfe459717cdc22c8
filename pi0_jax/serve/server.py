"""The websocket policy server: openpi's protocol, one worker thread on the device, dynamic batching.

Per connection (openpi's `WebsocketPolicyServer` protocol, so an unchanged `openpi_client.WebsocketClientPolicy`
works): the server sends `policy.metadata` as one binary msgpack frame, then answers each binary msgpack-numpy
frame (an observation dict, `protocol.py`) with one binary frame

    {"actions": (H, A) float32, "policy_timing": {...},
     "server_timing": {"infer_ms":   wall time of the `policy.run` call that answered this request,
                       "queue_ms":   from the request being validated to that call starting,
                       "prepare_ms": decoding + `policy.prepare` (validation, tokenisation),
                       "batch_size": requests handed to that call (policy_timing has the device call's),
                       "prev_total_ms": this connection's previous request, received to sent (as openpi)}}

Extension: a request may carry `"noise"`, an (H, action_dim) float array at t = 1, passed to `policy.prepare(obs,
noise=...)` (reproducible actions); without it the policy's seeded generator draws it, in request arrival order.

A request that fails for any reason (not msgpack, a text frame, a refused dtype, an `ObservationError`, a failing
model call) gets one text frame (the error on the first line, then the traceback) and its connection is closed with
1011, as openpi does; every other connection is unaffected. Frames above `max_frame_bytes` are refused by
websockets itself (close 1009). `GET /healthz` answers 200 (no API key needed; 503 while shutting down).

Batching: each request is decoded and `prepare`d as it arrives, on the event loop, in arrival order (a bad one
fails alone, before any batch). The batcher takes the oldest waiting request, waits for company (up to
`max_batch`) until `batch_window_ms` after that request arrived or after the device became free, whichever is
later, and only while another open connection has nothing queued (a lone client never waits), then hands the group
to `policy.run` on the one worker thread. A window of 0 never delays anyone but still lets requests that queued
while the device was busy share the next call; `max_batch=1` answers each request alone. If a batched call raises,
its members are retried one by one, so only the culprit fails. A request whose client has gone is dropped.

    handle = serve(policy, "127.0.0.1", 0)   # background thread; port 0 picks a free port: handle.port, handle.url
    handle.stop()                             # stop accepting, finish in-flight requests, close, join
"""

from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import contextlib
import dataclasses
import hmac
import http
import logging
import os
import signal
import threading
import time
import traceback
from collections.abc import Callable, Mapping
from typing import Any

import websockets
from websockets.asyncio.server import ServerConnection
from websockets.asyncio.server import serve as _ws_serve
from websockets.frames import CloseCode

from pi0_jax.serve import protocol

log = logging.getLogger("pi0_jax.serve")
# websockets' own per-connection INFO lines duplicate ours; its warnings and errors still show.
_ws_log = logging.getLogger("pi0_jax.serve.websockets")
if _ws_log.level == logging.NOTSET:
    _ws_log.setLevel(logging.WARNING)

DEFAULT_PORT = 8000                   # openpi's serve_policy.py default
DEFAULT_MAX_FRAME_BYTES = 64 * 2**20  # three 640x480 uint8 cameras are 2.8 MB; float32 ones 11 MB
NOISE_KEY = "noise"


def _ms(seconds: float) -> float:
    return seconds * 1e3


@dataclasses.dataclass
class _Request:
    prepared: Any
    future: asyncio.Future
    queued_at: float          # perf_counter when it joined the queue


class Batcher:
    """Groups prepared requests into `policy.run` calls, one at a time, on a single worker thread."""

    def __init__(self, policy, *, max_batch: int, batch_window_ms: float, senders: Callable[[], int] | None = None):
        self.policy, self._senders = policy, senders     # senders(): open connections (None: unknown)
        self.max_batch = int(max_batch)
        self.window_s = float(batch_window_ms) / 1000.0
        self._queue: collections.deque[_Request] = collections.deque()
        self._wakeup = asyncio.Event()
        self._executor = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="pi0-serve-run")
        self._free_at = 0.0        # perf_counter when the last `policy.run` returned

    def submit(self, prepared) -> asyncio.Future:
        """Queue one prepared request; the future resolves to (output dict, server_timing dict)."""
        fut = asyncio.get_running_loop().create_future()
        self._queue.append(_Request(prepared, fut, time.perf_counter()))
        self._wakeup.set()
        return fut

    async def _next_group(self) -> list[_Request]:
        while not self._queue:
            self._wakeup.clear()
            await self._wakeup.wait()
        # Wait for company until `window` after the oldest request arrived or the device became free, whichever is
        # later, and only while some open connection has no request queued: a lone robot never waits. Counting from
        # the device's return lets the clients just answered rejoin the requests that queued meanwhile; counting
        # from arrival alone splits N back-to-back clients into cohorts that alternate at half the batch for ever.
        deadline = max(self._queue[0].queued_at, self._free_at) + self.window_s
        while (len(self._queue) < self.max_batch and (self._senders is None or self._senders() > len(self._queue))
               and (left := deadline - time.perf_counter()) > 0):
            self._wakeup.clear()
            try:
                await asyncio.wait_for(self._wakeup.wait(), left)
            except TimeoutError:
                break
        group = []
        while self._queue and len(group) < self.max_batch:
            req = self._queue.popleft()
            if not req.future.done():      # cancelled: its client left while it waited
                group.append(req)
        return group

    def _run(self, prepared: list) -> list[tuple[Any, BaseException | None, float, float, int]]:
        """Worker thread: one `policy.run` for the group; if it raises, each member alone so only the culprit fails.
        Per member: (output, error, start perf_counter, wall seconds and batch size of the call that answered it)."""
        t0 = time.perf_counter()
        try:
            outs = self.policy.run(prepared)
            if len(outs) != len(prepared):
                raise RuntimeError(f"policy.run returned {len(outs)} outputs for {len(prepared)} requests")
            return [(out, None, t0, time.perf_counter() - t0, len(prepared)) for out in outs]
        except Exception as e:
            if len(prepared) == 1:
                return [(None, e, t0, time.perf_counter() - t0, 1)]
            log.warning("batched run of %d requests failed (%s: %s); retrying them one by one",
                        len(prepared), type(e).__name__, e)
        results = []
        for p in prepared:
            t1 = time.perf_counter()
            try:
                results.append((self.policy.run([p])[0], None, t1, time.perf_counter() - t1, 1))
            except Exception as e:
                results.append((None, e, t1, time.perf_counter() - t1, 1))
        return results

    async def run_forever(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            group = await self._next_group()
            if not group:
                continue
            results = await loop.run_in_executor(self._executor, self._run, [r.prepared for r in group])
            self._free_at = time.perf_counter()
            for req, (out, err, start, wall, size) in zip(group, results):
                if req.future.done():
                    continue
                if err is not None:
                    req.future.set_exception(err)
                else:
                    req.future.set_result((out, {"infer_ms": _ms(wall), "queue_ms": _ms(start - req.queued_at),
                                                 "batch_size": size}))

    async def close(self) -> None:
        """Cancel what still waits (on the loop: asyncio futures are not thread-safe); let a running call finish."""
        while self._queue:
            self._queue.popleft().future.cancel()
        await asyncio.get_running_loop().run_in_executor(None, self._executor.shutdown)


class PolicyServer:
    """openpi-protocol websocket server over a `pi0_jax.policy.Policy` (anything with prepare / run / metadata).

    Use `serve(...)` for a background thread, or `await PolicyServer(...).run()` inside an event loop; `shutdown()`
    (thread-safe) stops it: no new connections (HTTP 503), in-flight requests answered, then connections closed
    with 1001 (going away).
    """

    def __init__(self, policy, host: str = "127.0.0.1", port: int = DEFAULT_PORT, *, max_batch: int = 8,
                 batch_window_ms: float = 2.0, api_key: str | None = None,
                 max_frame_bytes: int | None = DEFAULT_MAX_FRAME_BYTES, metadata: Mapping[str, Any] | None = None,
                 shutdown_timeout_s: float = 60.0):
        buckets = getattr(policy, "batch_buckets", None)
        if max_batch < 1 or (buckets and max_batch > max(buckets)):
            raise ValueError(f"max_batch must be in [1, {max(buckets) if buckets else 'inf'}] (the policy's largest "
                             f"batch bucket), got {max_batch}")
        if batch_window_ms < 0:
            raise ValueError(f"batch_window_ms must be >= 0, got {batch_window_ms}")
        self.policy, self.host, self.port = policy, host, port
        self.max_batch, self.batch_window_ms = int(max_batch), float(batch_window_ms)
        self.api_key, self.max_frame_bytes, self.shutdown_timeout_s = api_key, max_frame_bytes, shutdown_timeout_s
        self.metadata = dict(policy.metadata if metadata is None else metadata)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._idle: asyncio.Event | None = None
        self._draining, self._busy, self._open = False, 0, 0   # _busy: requests between receipt and reply
        self._batcher: Batcher | None = None

    # -- HTTP side of the handshake -----------------------------------------------------------------------------------
    def _process_request(self, connection: ServerConnection, request):
        if self._draining:             # /healthz too: a load balancer should stop sending robots here
            return connection.respond(http.HTTPStatus.SERVICE_UNAVAILABLE, "server shutting down\n")
        if request.path.split("?", 1)[0] == "/healthz":
            return connection.respond(http.HTTPStatus.OK, "OK\n")
        got = request.headers.get("Authorization")
        if self.api_key is None or (got and hmac.compare_digest(got.encode(), f"Api-Key {self.api_key}".encode())):
            return None
        status, why = (http.HTTPStatus.FORBIDDEN, "wrong API key") if got else \
            (http.HTTPStatus.UNAUTHORIZED, "missing 'Authorization: Api-Key <key>' header")
        log.warning("refused %s: %s", connection.remote_address, why)
        return connection.respond(status, why + "\n")

    # -- one connection -----------------------------------------------------------------------------------------------
    def _decode_and_prepare(self, frame):
        """One frame -> `policy.prepare`'s result, on the event loop: in arrival order (so is the noise), and with no
        thread hop on the latency path (decoding and validation take well under a millisecond; compiles happen in
        `policy.run`, on the worker thread)."""
        if isinstance(frame, str):
            raise protocol.ProtocolError("got a text frame; send the observation as one binary msgpack frame")
        obs = protocol.unpackb(frame)
        if not isinstance(obs, dict):
            raise protocol.ProtocolError(f"a request must be a msgpack map of observation keys, got "
                                         f"{type(obs).__name__}")
        noise = obs.pop(NOISE_KEY, None)
        return self.policy.prepare(obs, noise=noise)

    async def _answer(self, ws: ServerConnection, frame) -> dict | None:
        """One request -> the reply dict, or None when the client left before its answer was ready."""
        t0 = time.perf_counter()
        prepared = self._decode_and_prepare(frame)
        prepare_ms = _ms(time.perf_counter() - t0)
        fut = self._batcher.submit(prepared)
        closed = asyncio.ensure_future(ws.wait_closed())
        try:
            await asyncio.wait({fut, closed}, return_when=asyncio.FIRST_COMPLETED)
        finally:
            closed.cancel()
        if not fut.done():             # the client went away: drop its request (or its result)
            fut.cancel()
            return None
        out, timing = fut.result()
        return {**out, "server_timing": {**timing, "prepare_ms": prepare_ms}}

    async def _handler(self, ws: ServerConnection) -> None:
        peer = ws.remote_address
        log.info("connection from %s opened", peer)
        n, prev_total_ms, why = 0, None, "client closed"
        self._open += 1
        try:
            await ws.send(protocol.packb(self.metadata))
            while True:
                frame = await ws.recv()
                if self._draining:
                    why = "server shutting down"
                    await ws.close(CloseCode.GOING_AWAY, "server shutting down")
                    break
                start = time.perf_counter()
                self._busy += 1
                self._idle.clear()
                try:
                    reply = await self._answer(ws, frame)
                    if reply is None:
                        why = "client left mid-request"
                        break
                    if prev_total_ms is not None:
                        reply["server_timing"]["prev_total_ms"] = prev_total_ms
                    await ws.send(protocol.packb(reply))
                except websockets.ConnectionClosed:
                    raise
                except Exception as e:
                    why = f"error: {type(e).__name__}"
                    await self._fail(ws, e)
                    break
                finally:
                    self._busy -= 1
                    if self._busy == 0:
                        self._idle.set()
                n += 1
                prev_total_ms = _ms(time.perf_counter() - start)
        except websockets.ConnectionClosed as e:
            why = f"closed ({e.rcvd.code if e.rcvd else 'no close frame'})"
        finally:
            self._open -= 1
            log.info("connection from %s closed after %d requests: %s", peer, n, why)

    async def _fail(self, ws: ServerConnection, err: BaseException) -> None:
        """openpi's error path: the traceback as a text frame, then close with 1011. The error's own line first."""
        head = f"{type(err).__name__}: {err}"
        if isinstance(err, ValueError):    # ObservationError / ProtocolError / bad noise: the client's mistake
            log.warning("request from %s refused: %s", ws.remote_address, head)
        else:
            log.error("request from %s failed", ws.remote_address, exc_info=err)
        text = head + "\n\n" + "".join(traceback.format_exception(err))
        with contextlib.suppress(websockets.ConnectionClosed):
            await ws.send(text)
            await ws.close(CloseCode.INTERNAL_ERROR, "Internal server error. Traceback included in previous frame.")

    # -- lifecycle ----------------------------------------------------------------------------------------------------
    def shutdown(self) -> None:
        """Thread-safe (and signal-safe through the loop): stop accepting, finish in-flight requests, close."""
        if self._loop is not None and self._stop is not None:
            self._loop.call_soon_threadsafe(self._stop.set)

    async def run(self, ready: Callable[[PolicyServer], None] | None = None, *, handle_signals: bool = False) -> None:
        """Serve until `shutdown()` (or SIGINT/SIGTERM with handle_signals). `ready(self)` runs once listening;
        `self.port` is then the bound port."""
        self._loop = asyncio.get_running_loop()
        self._stop, self._idle = asyncio.Event(), asyncio.Event()
        self._idle.set()
        self._batcher = Batcher(self.policy, max_batch=self.max_batch, batch_window_ms=self.batch_window_ms,
                                senders=lambda: self._open)
        if handle_signals:
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._loop.add_signal_handler(sig, self._on_signal, sig)
        batch_task = asyncio.create_task(self._batcher.run_forever(), name="pi0-serve-batcher")
        try:
            async with _ws_serve(self._handler, self.host, self.port, process_request=self._process_request,
                                 compression=None, max_size=self.max_frame_bytes, max_queue=4,
                                 logger=_ws_log) as ws_server:
                self.port = ws_server.sockets[0].getsockname()[1]
                log.info("serving %s on ws://%s:%d (max_batch %d, batch window %g ms, api key %s, max frame %s)",
                         self.metadata.get("name", "policy"), self.host, self.port, self.max_batch,
                         self.batch_window_ms, "required" if self.api_key else "off",
                         f"{self.max_frame_bytes / 2**20:g} MiB" if self.max_frame_bytes else "unlimited")
                if ready is not None:
                    ready(self)
                await self._stop.wait()
                self._draining = True
                log.info("shutting down: refusing new connections, finishing %d in-flight request(s)", self._busy)
                try:
                    await asyncio.wait_for(self._idle.wait(), self.shutdown_timeout_s)
                except TimeoutError:
                    log.warning("%d request(s) still running after %g s; closing anyway", self._busy,
                                self.shutdown_timeout_s)
                ws_server.close(close_connections=True, reason="server shutting down")
        finally:
            batch_task.cancel()
            await asyncio.gather(batch_task, return_exceptions=True)
            await self._batcher.close()
            if handle_signals:
                for sig in (signal.SIGINT, signal.SIGTERM):
                    self._loop.remove_signal_handler(sig)
            log.info("server stopped")

    def _on_signal(self, sig: int) -> None:
        if self._stop.is_set():       # a second Ctrl-C: the user does not want to wait for in-flight requests
            log.warning("received %s again: exiting now", signal.Signals(sig).name)
            os._exit(128 + sig)
        log.info("received %s", signal.Signals(sig).name)
        self._stop.set()


class ServerHandle:
    """A `PolicyServer` running in a background thread (from `serve`); also a context manager that stops it."""

    def __init__(self, server: PolicyServer, thread: threading.Thread):
        self.server, self.thread = server, thread

    host = property(lambda self: self.server.host)
    port = property(lambda self: self.server.port)          # the bound one when started with port 0
    url = property(lambda self: f"ws://{self.host}:{self.port}")

    def stop(self, timeout: float | None = 60.0) -> None:
        """Stop accepting, answer in-flight requests, close every connection, join the thread."""
        self.server.shutdown()
        self.thread.join(timeout)
        if self.thread.is_alive():
            raise TimeoutError(f"policy server did not stop within {timeout} s")

    def __enter__(self) -> ServerHandle:
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


def serve(policy, host: str = "127.0.0.1", port: int = DEFAULT_PORT, *, max_batch: int = 8,
          batch_window_ms: float = 2.0, api_key: str | None = None,
          max_frame_bytes: int | None = DEFAULT_MAX_FRAME_BYTES, metadata: Mapping[str, Any] | None = None,
          start_timeout_s: float = 30.0) -> ServerHandle:
    """Start a `PolicyServer` in a daemon thread with its own event loop; returns once it listens (port 0: a free
    one, `handle.port`). Warm the policy up first (`policy.warmup`) unless the first requests may compile."""
    server = PolicyServer(policy, host, port, max_batch=max_batch, batch_window_ms=batch_window_ms, api_key=api_key,
                          max_frame_bytes=max_frame_bytes, metadata=metadata)
    started, errors = threading.Event(), []

    def main():
        try:
            asyncio.run(server.run(ready=lambda _: started.set()))
        except BaseException as e:  # noqa: BLE001  (reported to the caller of serve)
            errors.append(e)
        finally:
            started.set()

    thread = threading.Thread(target=main, name="pi0-serve", daemon=True)
    thread.start()
    if not started.wait(start_timeout_s):
        server.shutdown()
        raise TimeoutError(f"policy server did not start within {start_timeout_s} s")
    if errors:
        raise errors[0]
    return ServerHandle(server, thread)
