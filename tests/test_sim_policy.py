"""A pi0-jax checkpoint in the simulated loop: LeRobot's tiny random π0.5 parity fixture (LeRobot normaliser, state
written into the prompt), converted with `pi0-jax convert`, with the suite's small tokenizer.

* The batched in-jit policy (policies.checkpoint_policy) gives the same action chunks as the host-side
  `pi0_jax.policy.Policy.infer` on the same rendered observations and noise. Both run one pipeline
  (`PolicyCore`: resize-with-pad, normalisation, un-normalisation), so this checks the simulator's side of it:
  camera slots, the batch, the discretised-state prompt built on the device against the host's tokenised one.
  The pipeline's transforms themselves are checked against hand-written formulas in tests/test_policy.py.
* `pi0-jax eval --policy CKPT` runs end to end and writes eval_info.json and a video (the model scores ~0 %).
"""

import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pi0_jax import cli
from pi0_jax.policy import Policy
from pi0_jax.sim import policies
from pi0_jax.sim.env import Env
from pi0_jax.sim.render import RenderConfig

RES = 32
NUM_STEPS = 3
TASKS = ("goal/red_block_on_plate", "object/blue_block_in_bowl")


@pytest.fixture(scope="module")
def demo_ckpt(tmp_path_factory):
    from converters import convert
    from pi0_jax.train.data import suite_prompts, train_tokenizer

    root = tmp_path_factory.mktemp("ckpt")
    tokenizer = root / "tokenizer.model"
    tokenizer.write_bytes(train_tokenizer(suite_prompts()))
    src = Path(__file__).parent / "fixtures" / "lerobot_pi05"
    return convert(src, root / "demo_pi05", dtype="float32"), tokenizer


def test_batched_policy_matches_policy_infer(demo_ckpt):
    ckpt, tokenizer = demo_ckpt
    env = Env(TASKS, RenderConfig(RES, RES))
    pol = policies.checkpoint_policy(ckpt, env, tokenizer_path=tokenizer, num_steps=NUM_STEPS)
    n = len(TASKS)
    task = jnp.arange(n)
    state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.key(0), n), task, jnp.array([3, 5]))
    obs = jax.jit(jax.vmap(env.observe))(state)
    keys = jax.random.split(jax.random.key(7), n)
    chunk = np.asarray(jax.jit(pol.plan)(pol.params, pol.init(n), obs, state, keys))
    assert chunk.shape == (n, pol.horizon, 7) and np.isfinite(chunk).all()

    ref = Policy.from_checkpoint(ckpt, tokenizer_path=tokenizer, num_steps=NUM_STEPS)
    assert pol.info["prompt_tokens"] < ref.config.max_token_len     # the state prompt runs in a shorter bucket
    for i in range(n):
        noise = jax.random.normal(keys[i], (ref.config.action_horizon, ref.config.action_dim))
        out = ref.infer({"observation/image": np.asarray(obs["agentview"][i]),
                         "observation/wrist_image": np.asarray(obs["wrist"][i]),
                         "observation/state": np.asarray(obs["state"][i]), "prompt": env.prompts[i]}, noise=noise)
        np.testing.assert_allclose(chunk[i], out["actions"], rtol=1e-4, atol=1e-4)


def test_state_prompt_bound_holds_every_state(demo_ckpt):
    """The bound the sim's π0.5 bucket is cut to holds the prompt of any state: random ones, the range's ends and
    beyond (bins -1 and 255), for every task of the suite."""
    from pi0_jax import checkpoint
    from pi0_jax import normalize as nz
    from pi0_jax.pipeline import PolicyCore
    from pi0_jax.sim.tasks import STATE_DIM, TASKS
    from pi0_jax.tokenizer import PaligemmaTokenizer

    ckpt, tokenizer = demo_ckpt
    config = checkpoint.load_checkpoint(ckpt)[0]
    core = PolicyCore(config, None, PaligemmaTokenizer(tokenizer, config.max_token_len),
                      nz.load_normalizer(ckpt, use_quantiles=True))
    prompts = [t.prompt for t in TASKS]
    bound = policies.state_prompt_tokens(core, prompts)
    states = np.random.default_rng(0).uniform(-1.5, 1.5, (64, STATE_DIM))
    longest = max(int(core.tokenize(p, s)[1].sum()) for p in prompts for s in states)
    assert longest <= bound < config.max_token_len


def test_engine_reference_and_dynamic_steps_plan_the_same(demo_ckpt):
    """The sim policy's three ways to sample (the engine, the reference sampler, the engine with the step count
    traced, as results_grid compiles it once for every count) give the same chunks for the same noise."""
    from pi0_jax import checkpoint
    from pi0_jax import normalize as nz
    from pi0_jax.tokenizer import PaligemmaTokenizer

    ckpt, tokenizer = demo_ckpt
    config, params = checkpoint.load_checkpoint(ckpt)
    tok = PaligemmaTokenizer(tokenizer, config.max_token_len)
    normalizer = nz.load_normalizer(ckpt, use_quantiles=config.pi05)
    env = Env(TASKS, RenderConfig(RES, RES))
    n = len(TASKS)
    state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.key(1), n), jnp.arange(n), jnp.array([0, 7]))
    obs = jax.jit(jax.vmap(env.observe))(state)
    keys = jax.random.split(jax.random.key(3), n)
    chunks = {}
    for name, kw in (("engine", {}), ("reference", {"sampler": "reference"}), ("dynamic", {"dynamic_steps": True})):
        pol = policies.model_policy(config, params, tok, normalizer, env, num_steps=NUM_STEPS, **kw)
        chunks[name] = np.asarray(jax.jit(pol.plan)(pol.params, pol.init(n), obs, state, keys))
    np.testing.assert_allclose(chunks["engine"], chunks["reference"], rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(chunks["dynamic"], chunks["engine"], rtol=1e-5, atol=1e-5)
    pol = policies.model_policy(config, params, tok, normalizer, env, num_steps=NUM_STEPS, dynamic_steps=True)
    other = np.asarray(jax.jit(pol.plan)({**pol.params, "num_steps": np.int32(NUM_STEPS + 2)}, pol.init(n), obs,
                                         state, keys))
    assert np.abs(other - chunks["dynamic"]).max() > 1e-3      # the traced count is really used


@pytest.mark.parametrize("n_dev,local,chunk", [(1, 5, 2), (2, 5, 2), (2, 4, 4), (1, 3, 1), (2, 3, None)])
def test_chunked_plan_layout(n_dev, local, chunk):
    """chunked_plan: each call sees at most `chunk` rows per device (the same rows of every device's block), and the
    result is the plan's on the whole batch, padding dropped."""
    seen = []

    def plan(params, x, keys):
        seen.append(x.shape[0])
        return {"y": x * params + jax.vmap(jax.random.uniform)(keys)[:, None], "b": x.sum(-1) > 0}

    b = n_dev * local
    x = jnp.arange(b * 3, dtype=jnp.float32).reshape(b, 3) - 7.0
    keys = jax.random.split(jax.random.key(0), b)
    want = plan(2.0, x, keys)
    seen.clear()
    got = jax.jit(policies.chunked_plan(plan, chunk, n_dev))(2.0, x, keys)
    jax.tree.map(np.testing.assert_array_equal, got, want)
    assert max(seen) <= n_dev * (chunk or local) and (chunk is None or chunk >= local or max(seen) < b)
    assert chunk is not None or seen == [b]                                   # no chunk: the whole batch at once


def test_chunked_plan_matches_whole_batch(demo_ckpt):
    """The sim's π0.5 planning 5 environments in chunks of 2 (3 chunks, one padded row) gives the whole batch's
    action chunks."""
    ckpt, tokenizer = demo_ckpt
    env = Env(TASKS, RenderConfig(RES, RES))
    pol = policies.checkpoint_policy(ckpt, env, tokenizer_path=tokenizer, num_steps=NUM_STEPS)
    n = 5
    state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.key(2), n), jnp.arange(n) % 2, jnp.arange(n))
    obs = jax.jit(jax.vmap(env.observe))(state)
    keys = jax.random.split(jax.random.key(5), n)
    whole = np.asarray(jax.jit(pol.plan)(pol.params, pol.init(n), obs, state, keys))
    chunked = np.asarray(jax.jit(policies.chunked_plan(pol.plan, 2))(pol.params, pol.init(n), obs, state, keys))
    assert np.abs(whole[1:] - whole[:-1]).max() > 1e-3                      # the rows differ
    np.testing.assert_allclose(chunked, whole, rtol=1e-5, atol=1e-5)


def test_eval_cli_with_checkpoint(demo_ckpt, tmp_path):
    ckpt, tokenizer = demo_ckpt
    out = tmp_path / "eval"
    assert cli.main(["eval", "--policy", str(ckpt), "--tokenizer", str(tokenizer), "--suite", "goal",
                     "--episodes-per-task", "1", "--batch", "4", "--steps", "10", "--replan-steps", "5",
                     "--num-steps", str(NUM_STEPS), "--resolution", str(RES), "--videos", "1",
                     "--gemm", "xla", "--attention", "vision=pallas", "--output-dir", str(out), "--no-progress"]) == 0
    info = json.loads((out / "eval_info.json").read_text())
    agg = info["aggregated"]
    assert agg["n_episodes"] == 4 and len(info["per_episode"]) == 4
    assert all(e["length"] == 10 or e["success"] for e in info["per_episode"])
    assert info["config"]["policy_info"]["model"] == "dummy_pi05"
    assert info["config"]["policy_info"]["gemm"] == "xla"      # recorded; it changes nothing off a GPU
    assert info["config"]["policy_info"]["attention"].startswith("vision=pallas,")   # the vision kernel, interpreted
    assert info["config"]["policy_info"]["kernels"] == "auto"   # the expert's and the LayerNorm's rule, recorded
    assert len(info["video_paths"]) == 1


def test_random_policy_chunks():
    pol = policies.random_policy(5)
    chunk = np.asarray(pol.plan(None, pol.init(3), None, None, jax.random.split(jax.random.key(0), 3)))
    assert chunk.shape == (3, 5, 7) and np.abs(chunk).max() <= 1.0 and chunk.std() > 0.3
    action, _ = pol.act(jnp.asarray(chunk), None, 2)
    np.testing.assert_array_equal(np.asarray(action), chunk[:, 2])


def test_eval_preset_policy_with_timing_and_profile(tmp_path):
    """`--policy preset:NAME` (random weights, the protocol's timing without a checkpoint) runs, and eval_info.json
    says where the time went."""
    out = tmp_path / "eval"
    assert cli.main(["eval", "--policy", "preset:dummy", "--suite", "goal", "--episodes-per-task", "1", "--batch", "4",
                     "--steps", "5", "--replan-steps", "5", "--num-steps", "2", "--resolution", str(RES),
                     "--videos", "0", "--output-dir", str(out), "--no-progress", "--profile"]) == 0
    info = json.loads((out / "eval_info.json").read_text())
    t = info["timing"]
    assert info["config"]["policy"] == "preset:dummy (random weights)"
    assert info["config"]["policy_info"]["sampler"] == "engine"
    assert t["episodes_per_min"] > 0 and t["rollout_s"] >= t["first_segment_s"] > 0
    assert set(t["policy_setup_s"]) == {"random_params_s", "policy_s"}    # no quantising asked
    assert t["setup_s"] >= sum(t["policy_setup_s"].values()) > 0
    assert {"physics_ms", "render_ms", "policy_ms"} <= set(t["phases"]) and all(
        t["phases"][k] > 0 for k in ("physics_ms", "render_ms", "policy_ms"))
    assert abs(sum(t["phases"]["share"].values()) - 1) < 1e-6


def test_balanced_batch():
    from pi0_jax.sim.batching import balanced_batch

    assert balanced_batch(2000, 1024, 1) == 1000          # 2 even batches, not 1024 + 976
    assert balanced_batch(2000, 2048, 2) == 2000 and balanced_batch(2001, 2048, 2) == 2002
    assert balanced_batch(550, 1024, 1) == 550
    assert balanced_batch(10, 4, 1) == 4 and balanced_batch(10, 4, 3) == 3 and balanced_batch(5, 1, 2) == 2


def test_eval_batch_auto(tmp_path, monkeypatch):
    """`--batch auto` starts from the whole suite and halves while the compiled segment does not fit the memory
    budget (here: the first program reports more bytes than any device has), recording what it tried."""
    from pi0_jax.sim import evaluate

    real, calls = evaluate.program_bytes, []

    def program_bytes(compiled):
        calls.append(real(compiled))
        return 1 << 60 if len(calls) == 1 else calls[-1]

    monkeypatch.setattr(evaluate, "program_bytes", program_bytes)
    out = tmp_path / "eval"
    assert cli.main(["eval", "--policy", "expert", "--suite", "goal/red_block_on_plate", "--episodes-per-task", "2",
                     "--batch", "auto", "--steps", "10", "--resolution", "16", "--videos", "0", "--output-dir",
                     str(out), "--no-progress"]) == 0
    info = json.loads((out / "eval_info.json").read_text())
    tried = info["config"]["batch_auto"]["tried"]
    assert [t["batch"] for t in tried] == [2, 1] and info["config"]["batch_rounded"] == 1
    assert tried[1]["program_bytes"] == calls[1] > 0 and tried[1]["free_bytes"] > calls[1]
    assert info["aggregated"]["n_episodes"] == 2 and all(e["length"] <= 10 for e in info["per_episode"])
    with pytest.raises(SystemExit):
        cli.main(["eval", "--policy", "expert", "--batch", "0"])
    with pytest.raises(SystemExit):
        cli.main(["eval", "--policy", "expert", "--plan-chunk", "0"])


def test_eval_batch_auto_chunks_the_plan_first(tmp_path, monkeypatch):
    """`--batch auto` halves the policy's chunk before the batch when the segment does not fit (its activations
    are what grows with the batch), and records the chunk it ran."""
    from pi0_jax.sim import evaluate

    real, calls = evaluate.program_bytes, []

    def program_bytes(compiled):
        calls.append(real(compiled))
        return 1 << 60 if len(calls) == 1 else calls[-1]

    monkeypatch.setattr(evaluate, "program_bytes", program_bytes)
    monkeypatch.setattr(evaluate, "AUTO_MIN_PLAN_CHUNK", 1)
    out = tmp_path / "eval"
    assert cli.main(["eval", "--policy", "preset:dummy", "--suite", "goal/red_block_on_plate", "--episodes-per-task",
                     "4", "--batch", "auto", "--steps", "5", "--num-steps", "2", "--resolution", str(RES),
                     "--videos", "0", "--output-dir", str(out), "--no-progress"]) == 0
    info = json.loads((out / "eval_info.json").read_text())
    tried = info["config"]["batch_auto"]["tried"]
    assert [(t["batch"], t["plan_chunk"]) for t in tried] == [(4, None), (4, 2)]
    assert info["config"]["plan_chunk"] == 2 and info["aggregated"]["n_episodes"] == 4


def test_eval_quant(tmp_path, monkeypatch):
    """`--quant` runs an FP8 scheme (static scales calibrated on rendered suite frames) in the loop and says so."""
    monkeypatch.setattr(policies, "CALIB_SAMPLES", 2)
    out = tmp_path / "eval"
    assert cli.main(["eval", "--policy", "preset:dummy", "--suite", "goal/red_block_on_plate", "--episodes-per-task",
                     "2", "--batch", "2", "--steps", "5", "--replan-steps", "5", "--num-steps", "2", "--resolution",
                     str(RES), "--videos", "0", "--output-dir", str(out), "--no-progress", "--quant",
                     "prefix-mlp"]) == 0
    info = json.loads((out / "eval_info.json").read_text())
    assert info["config"]["policy_info"]["quant"] == "prefix-mlp" and info["aggregated"]["n_episodes"] == 2
    setup = info["timing"]["policy_setup_s"]
    assert set(setup) == {"random_params_s", "observations_s", "calibrate_compile_s", "calibrate_run_s", "quantize_s",
                          "policy_s"} and setup["calibrate_compile_s"] > 0 and setup["calibrate_run_s"] > 0
    with pytest.raises(ValueError, match="unknown number format 'fp7'"):
        policies.quantize_for_suite(None, {}, None, None, "fp7")
