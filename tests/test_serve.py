"""The policy server (pi0_jax.serve) over real sockets on 127.0.0.1.

A small openpi-protocol client is written here from the protocol's description (msgpack maps with byte-string keys
for numpy values; metadata first; text frame + close 1011 on error), independent of pi0_jax.serve.protocol. Every
failure case is followed by a NEW client that must still get the right answer. Timeouts bound every wait.
"""

from __future__ import annotations

import contextlib
import http.client
import os
import signal
import subprocess
import sys
import threading
import time

import msgpack
import numpy as np
import pytest
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.sync.client import connect

from pi0_jax import checkpoint, normalize as N, pi0
from pi0_jax.config import get_config
from pi0_jax.policy import Policy
from pi0_jax.serve import protocol, serve

TIMEOUT = 60.0      # seconds; a dummy-preset batch of 8 on two busy CPU cores takes well under one
NUM_STEPS = 2
API_KEY = "test-key"
WINDOW_MS = 50      # the module server's batch window
RNG = np.random.default_rng(0)
PROMPTS = ["pick up the black bowl and place it on the plate", "open the top drawer and put the bowl inside",
           "turn on the stove", "put the moka pot on the stove", "put both the alphabet soup and the tomato sauce "
           "in the basket", "put the bowl on the plate", "open the drawer", "place it on the plate"]


def make_obs(rng: np.random.Generator, prompt: str = PROMPTS[0], size: int = 224) -> dict:
    return {"observation/image": rng.integers(0, 256, (size, size, 3), dtype=np.uint8),
            "observation/wrist_image": rng.integers(0, 256, (size, size, 3), dtype=np.uint8),
            "observation/state": rng.uniform(-1, 1, 8).astype(np.float32), "prompt": prompt}


OBS = make_obs(np.random.default_rng(1))


# -- a minimal openpi-protocol client ---------------------------------------------------------------------------------
def _enc(x):
    if isinstance(x, np.ndarray):
        return {b"__ndarray__": True, b"data": x.tobytes(), b"dtype": x.dtype.str, b"shape": list(x.shape)}
    if isinstance(x, np.generic):
        return {b"__npgeneric__": True, b"data": x.item(), b"dtype": x.dtype.str}
    raise TypeError(type(x))


def _dec(m):
    if b"__ndarray__" in m:
        return np.frombuffer(m[b"data"], np.dtype(m[b"dtype"])).reshape(m[b"shape"])
    if b"__npgeneric__" in m:
        return np.dtype(m[b"dtype"]).type(m[b"data"])
    return m


def pack(obj) -> bytes:
    return msgpack.packb(obj, default=_enc, use_bin_type=True)


def unpack(frame: bytes):
    return msgpack.unpackb(frame, object_hook=_dec)


class Client:
    def __init__(self, url: str, api_key: str | None = API_KEY):
        headers = {"Authorization": f"Api-Key {api_key}"} if api_key else None
        self._stack = contextlib.ExitStack()   # websockets >= 17 wants connect() as a context manager
        self.ws = self._stack.enter_context(connect(url, compression=None, max_size=None, additional_headers=headers,
                                                    open_timeout=TIMEOUT, close_timeout=5))
        self.metadata = unpack(self.ws.recv(timeout=TIMEOUT))

    def infer(self, obs: dict) -> dict:
        self.ws.send(pack(obs))
        reply = self.ws.recv(timeout=TIMEOUT)
        assert isinstance(reply, bytes), f"server error:\n{reply}"
        return unpack(reply)

    def expect_error(self, frame) -> tuple[str, int]:
        """Send a raw frame; the server must answer with a text frame and close with 1011."""
        self.ws.send(frame)
        text = self.ws.recv(timeout=TIMEOUT)
        assert isinstance(text, str), "expected a text error frame"
        with pytest.raises(ConnectionClosed) as e:
            self.ws.recv(timeout=TIMEOUT)
        return text, e.value.rcvd.code

    def close(self):
        self._stack.close()


# -- fixtures ---------------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def ckpt(tmp_path_factory, sp_model_path):
    config = get_config("dummy")
    params = pi0.random_params(config, 0)     # every leaf random (init_params zeroes SigLIP's head: pixels unseen)
    stats = {"state": N.NormStats(mean=RNG.normal(size=8), std=RNG.uniform(0.5, 2, 8)),
             "actions": N.NormStats(mean=RNG.normal(size=7), std=RNG.uniform(0.5, 2, 7))}
    stats_json = tmp_path_factory.mktemp("stats") / "norm_stats.json"
    N.save_openpi_norm_stats(stats_json, stats)
    dst = tmp_path_factory.mktemp("ckpt") / "dummy"
    checkpoint.save_checkpoint(dst, params, config, assets={
        "physical-intelligence/libero/norm_stats.json": stats_json, "tokenizer.model": sp_model_path})
    return dst


@pytest.fixture(scope="module")
def reference(ckpt):
    """A fresh Policy (seed 0) answering one request at a time; its first call draws the seed's first noise."""
    policy = Policy.from_checkpoint(ckpt, num_steps=NUM_STEPS, seed=0, max_batch=8)   # only batch 1 is compiled
    return policy, policy.infer(OBS)["actions"]


@pytest.fixture(scope="module")
def server(ckpt):
    """A fresh Policy (seed 0) behind the server; its first request (no noise) is made here, before any test."""
    policy = Policy.from_checkpoint(ckpt, num_steps=NUM_STEPS, seed=0, max_batch=8)
    policy.warmup(policy.batch_buckets, policy.example_observation())
    handle = serve(policy, "127.0.0.1", 0, max_batch=8, batch_window_ms=WINDOW_MS, api_key=API_KEY,
                   max_frame_bytes=2**20)
    client = Client(handle.url)
    handle.first_reply = client.infer(OBS)
    client.close()
    yield handle
    handle.stop(timeout=TIMEOUT)


def noise_for(policy, seed: int) -> np.ndarray:
    cfg = policy.config
    return np.random.default_rng(seed).normal(size=(cfg.action_horizon, cfg.action_dim)).astype(np.float32)


def assert_served(server, reference, seed: int = 99):
    """A new client gets the lone-request answer for its own noise."""
    policy, _ = reference
    noise = noise_for(policy, seed)
    client = Client(server.url)
    try:
        out = client.infer({**OBS, "noise": noise})
    finally:
        client.close()
    np.testing.assert_allclose(out["actions"], policy.infer(OBS, noise=noise)["actions"], rtol=1e-5, atol=1e-5)


# -- the protocol and the happy path ----------------------------------------------------------------------------------
def test_metadata_and_first_actions_equal_policy_infer(server, reference):
    policy, first = reference
    client = Client(server.url)
    assert client.metadata == policy.metadata and client.metadata
    client.close()
    reply = server.first_reply
    assert set(reply) >= {"actions", "policy_timing", "server_timing"}
    assert reply["actions"].dtype == np.float32 and reply["actions"].shape == first.shape
    np.testing.assert_allclose(reply["actions"], first, rtol=1e-5, atol=1e-5)   # same seed, same first observation
    timing = reply["server_timing"]
    assert timing["batch_size"] == 1 and timing["infer_ms"] > 0
    assert 0 <= timing["queue_ms"] < WINDOW_MS      # a lone client does not wait for company
    assert_served(server, reference)


def test_prev_total_ms_and_noise_extension(server, reference):
    policy, _ = reference
    client = Client(server.url)
    noise = noise_for(policy, 5)
    first, second = client.infer({**OBS, "noise": noise}), client.infer({**OBS, "noise": noise})
    client.close()
    assert "prev_total_ms" not in first["server_timing"] and second["server_timing"]["prev_total_ms"] > 0
    np.testing.assert_array_equal(first["actions"], second["actions"])
    np.testing.assert_allclose(first["actions"], policy.infer(OBS, noise=noise)["actions"], rtol=1e-5, atol=1e-5)


def test_concurrent_clients_are_batched_and_each_gets_its_own_actions(server, reference):
    policy, _ = reference
    n, rounds = 8, 3
    obs = [make_obs(np.random.default_rng(100 + i), PROMPTS[i]) for i in range(n)]
    noise = [[noise_for(policy, 1000 + 10 * i + r) for r in range(rounds)] for i in range(n)]
    want = [[policy.infer(obs[i], noise=noise[i][r])["actions"] for r in range(rounds)] for i in range(n)]
    got, errors, barrier = {}, [], threading.Barrier(n, timeout=TIMEOUT)

    def worker(i):
        try:
            client = Client(server.url)
            barrier.wait()
            for r in range(rounds):
                got[i, r] = client.infer({**obs[i], "noise": noise[i][r]})
            client.close()
        except Exception as e:  # reported below
            errors.append(e)

    threads = [threading.Thread(target=worker, args=(i,)) for i in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(TIMEOUT * rounds)
    assert not errors, errors
    assert len(got) == n * rounds
    for (i, r), reply in got.items():
        np.testing.assert_allclose(reply["actions"], want[i][r], rtol=1e-5, atol=1e-5, err_msg=f"client {i} #{r}")
    sizes = [reply["server_timing"]["batch_size"] for reply in got.values()]
    assert max(sizes) > 1, f"nothing was batched: {sizes}"
    assert_served(server, reference)


# -- every failure closes only its own connection ---------------------------------------------------------------------
def _array(data: bytes, dtype: str, shape) -> dict:
    return {b"__ndarray__": True, b"data": data, b"dtype": dtype, b"shape": shape}


def _with_state(array: dict) -> bytes:
    return pack({**OBS, "observation/state": array})


BAD_FRAMES = {   # case: (frame, a word the error's text must contain)
    "object dtype": (_with_state(_array(b"\0" * 64, "|O", [8])), "dtype"),
    "void dtype": (_with_state(_array(b"\0" * 64, "|V8", [8])), "dtype"),
    "complex dtype": (_with_state(_array(b"\0" * 64, "<c8", [8])), "dtype"),
    "short data": (_with_state(_array(b"\0" * 31, "<f4", [8])), "bytes"),
    "long data": (_with_state(_array(b"\0" * 33, "<f4", [8])), "bytes"),
    "negative shape": (_with_state(_array(b"", "<f4", [-8])), "shape"),
    "absurd shape": (_with_state(_array(b"\0" * 4, "<f4", [2**40, 2**40])), "shape"),
    "huge product": (_with_state(_array(b"\0" * 4, "<f4", [2**30, 2**30, 2**30])), "bytes"),
    "not msgpack": (b"\xc1\xc1 certainly not msgpack", "msgpack"),
    "trailing bytes": (pack(OBS) + b"\x00", "msgpack"),
    "not a map": (pack([1, 2, 3]), "map"),
    "text frame": ("{'observation/state': [0, 0]}", "text frame"),
    "unknown key": (pack({**OBS, "observation/wrist_imag": OBS["observation/wrist_image"]}), "observation/wrist_imag"),
}


@pytest.mark.parametrize("case", list(BAD_FRAMES))
def test_bad_frame_fails_alone(server, reference, case):
    frame, needle = BAD_FRAMES[case]
    client = Client(server.url)
    text, code = client.expect_error(frame)
    assert code == 1011
    assert needle in text, text
    assert_served(server, reference)


def test_nan_state_names_the_key(server, reference):
    state = OBS["observation/state"].copy()
    state[3] = np.nan
    client = Client(server.url)
    text, code = client.expect_error(pack({**OBS, "observation/state": state}))
    assert code == 1011 and "observation/state" in text.splitlines()[0], text
    assert_served(server, reference)


def test_oversized_frame_is_refused(server, reference):
    client = Client(server.url)
    client.ws.send(pack({**OBS, "observation/image": np.zeros((1024, 1024, 3), np.uint8)}))   # 3 MiB > 1 MiB
    with pytest.raises(ConnectionClosed) as e:
        client.ws.recv(timeout=TIMEOUT)
    assert e.value.rcvd.code == 1009     # message too big
    assert_served(server, reference)


def test_client_leaving_mid_request(server, reference):
    for _ in range(3):
        client = Client(server.url)
        client.ws.send(pack(OBS))
        client.ws.socket.close() if _ == 0 else client.close()   # abrupt, then polite
    assert_served(server, reference)


def test_api_key_and_healthz(server, reference):
    for key, status in ((None, 401), ("wrong-key", 403)):
        with pytest.raises(InvalidStatus) as e:
            Client(server.url, api_key=key)
        assert e.value.response.status_code == status
    conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=TIMEOUT)
    conn.request("GET", "/healthz")
    assert conn.getresponse().status == 200
    conn.close()
    assert_served(server, reference)


# -- the batcher and shutdown, on a stand-in policy (no model) --------------------------------------------------------
class FakePolicy:
    """prepare/run contract without a model: actions = the request's `x`; `x == 13` breaks any batch it is in."""
    metadata = {"name": "fake"}
    batch_buckets = (1, 2, 4)

    def __init__(self, delay_s: float = 0.0):
        self.delay_s, self.calls, self.running = delay_s, [], threading.Event()

    def prepare(self, obs, noise=None):
        if set(obs) != {"x"}:
            raise ValueError(f"unknown keys {sorted(set(obs) - {'x'})}")
        return float(obs["x"])

    def run(self, prepared):
        self.calls.append(len(prepared))
        self.running.set()
        time.sleep(self.delay_s)
        if 13.0 in prepared:
            raise RuntimeError("unlucky batch")
        return [{"actions": np.full((2, 3), x, np.float32), "policy_timing": {}} for x in prepared]


def test_failing_batch_is_retried_one_by_one():
    policy = FakePolicy(delay_s=0.05)
    # a long window costs nothing here: the batch closes as soon as the 4th request arrives
    with serve(policy, "127.0.0.1", 0, max_batch=4, batch_window_ms=5000) as handle:
        results, barrier = {}, threading.Barrier(4, timeout=TIMEOUT)

        def worker(x):
            client = Client(handle.url, api_key=None)
            barrier.wait()
            client.ws.send(pack({"x": x}))
            results[x] = client.ws.recv(timeout=TIMEOUT)
            client.close()

        threads = [threading.Thread(target=worker, args=(x,)) for x in (1.0, 2.0, 13.0, 4.0)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(TIMEOUT)
        assert isinstance(results[13.0], str) and "unlucky batch" in results[13.0]
        for x in (1.0, 2.0, 4.0):
            reply = unpack(results[x])
            assert reply["actions"][0, 0] == x and reply["server_timing"]["batch_size"] == 1
        assert policy.calls[0] == 4 and sorted(policy.calls[1:]) == [1, 1, 1, 1]
        assert Client(handle.url, api_key=None).infer({"x": 7.0})["actions"][0, 0] == 7.0


def test_shutdown_finishes_in_flight_requests():
    policy = FakePolicy(delay_s=1.0)
    handle = serve(policy, "127.0.0.1", 0, max_batch=1, batch_window_ms=0)
    client = Client(handle.url, api_key=None)
    client.ws.send(pack({"x": 3.0}))
    assert policy.running.wait(TIMEOUT)      # the request is in the model call
    stopper = threading.Thread(target=handle.stop, kwargs={"timeout": TIMEOUT})
    stopper.start()
    assert unpack(client.ws.recv(timeout=TIMEOUT))["actions"][0, 0] == 3.0
    with pytest.raises(ConnectionClosed) as e:
        client.ws.recv(timeout=TIMEOUT)
    assert e.value.rcvd.code == 1001        # going away
    stopper.join(TIMEOUT)
    assert not handle.thread.is_alive()
    with pytest.raises(OSError):
        Client(handle.url, api_key=None)


# -- protocol unit checks and the CLI ---------------------------------------------------------------------------------
@pytest.mark.parametrize("value", [
    np.arange(6, dtype=np.int16).reshape(2, 3), np.array([np.nan, np.inf]), np.array(["ab", "c"]),
    np.array([True, False]), np.zeros((0, 3), np.float32), np.array(1.5, ">f8"), np.float32(2.5), np.int64(-3),
    np.bool_(True), {"a": [np.ones(2, np.uint8)]}])
def test_protocol_round_trip(value):
    for decoded in (protocol.unpackb(pack(value)), unpack(protocol.packb(value))):   # both directions vs. this client
        if isinstance(value, dict):
            np.testing.assert_array_equal(decoded["a"][0], value["a"][0])
        else:
            assert np.asarray(decoded).dtype.newbyteorder("=") == np.asarray(value).dtype.newbyteorder("=")
            np.testing.assert_array_equal(decoded, value)


def test_protocol_refuses_object_arrays_on_encode():
    with pytest.raises(protocol.ProtocolError, match="dtype"):
        protocol.packb({"a": np.array([object()], dtype=object)})


def test_serve_help_explains_every_flag(capsys, cli_options):
    from pi0_jax import cli

    with pytest.raises(SystemExit) as e:
        cli.main(["serve", "--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    flags = ("--host", "--port", "--num-steps", "--seed", "--max-batch", "--batch-window-ms", "--api-key",
             "--max-frame-mb", "--no-warmup", "--strict", "--tokenizer", "--norm-stats", "--dtype")
    for flag in flags:
        assert flag in out
    cli_options("serve", flags)     # each flag defined by the parser, every option with help


def test_cli_serves_and_exits_cleanly_on_sigterm(ckpt):
    """`pi0-jax serve CKPT --port 0` in a subprocess: it listens, /healthz answers, SIGTERM exits 0."""
    proc = subprocess.Popen([sys.executable, "-m", "pi0_jax.cli", "serve", str(ckpt), "--port", "0", "--no-warmup",
                             "--num-steps", str(NUM_STEPS)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, env={**os.environ, "JAX_PLATFORMS": "cpu"})
    killer = threading.Timer(180, proc.kill)   # bounds every blocking read below
    killer.start()
    try:
        lines, port = [], None
        while port is None:
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line)
            if line.startswith("listening on ws://"):
                port = int(line.split()[2].rsplit(":", 1)[1])
        assert port is not None, "".join(lines)
        conn = http.client.HTTPConnection("127.0.0.1", port, timeout=TIMEOUT)
        conn.request("GET", "/healthz")
        assert conn.getresponse().status == 200
        conn.close()
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=60)
        assert proc.returncode == 0, "".join(lines) + out
        assert "server stopped" in out
    finally:
        killer.cancel()
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)


def test_serve_cli_passes_the_kernel_path_to_the_policy():
    import argparse

    from pi0_jax.serve import cli as serve_cli

    parser = argparse.ArgumentParser()
    serve_cli.add_serve_parser(parser.add_subparsers())
    defaults = serve_cli._policy_kwargs(parser.parse_args(["serve"]))
    assert defaults["kernels"] == "auto" and defaults["attention"] == "auto" and defaults["overlap"] == "auto"
    given = serve_cli._policy_kwargs(parser.parse_args(["serve", "--kernels", "pallas", "--attention", "prefix=cudnn",
                                                        "--overlap", "off"]))
    assert given["kernels"] == "pallas" and given["attention"] == "prefix=cudnn" and given["overlap"] == "off"
    for bad in (["--kernels", "triton"], ["--attention", "flash"], ["--attention", "decoder=cudnn"],
                ["--overlap", "yes"]):
        with pytest.raises(SystemExit):
            parser.parse_args(["serve", *bad])
