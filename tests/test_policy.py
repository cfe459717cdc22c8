"""End-to-end Policy tests on the dummy presets, against a hand-built Observation and hand-written formulas."""

import numpy as np
import pytest
import jax

from pi0_jax import checkpoint, normalize as N, pi0
from pi0_jax.config import get_config
from pi0_jax.policy import ObservationError, Policy
from pi0_jax.tokenizer import PaligemmaTokenizer

RNG = np.random.default_rng(0)
STATE_STATS = N.NormStats(mean=RNG.normal(size=8), std=RNG.uniform(0.5, 2, 8), q01=-RNG.uniform(1, 2, 8),
                          q99=RNG.uniform(1, 2, 8))
ACTION_STATS = N.NormStats(mean=RNG.normal(size=7), std=RNG.uniform(0.5, 2, 7), q01=-RNG.uniform(1, 2, 7),
                           q99=RNG.uniform(1, 2, 7))
IMAGE = RNG.integers(0, 256, (224, 224, 3), dtype=np.uint8)
WRIST = RNG.integers(0, 256, (224, 224, 3), dtype=np.uint8)
STATE = RNG.uniform(-1, 1, 8)
PROMPT = "put the bowl on the plate"


def libero_obs():
    return {"observation/image": IMAGE, "observation/wrist_image": WRIST, "observation/state": STATE,
            "prompt": PROMPT}


def make_ckpt(tmp_path_factory, sp_model_path, preset, **overrides):
    config = get_config(preset, **overrides)
    # every leaf random: init_params zeroes SigLIP's head (as openpi does), so no pixel would reach the actions
    params = pi0.random_params(config, 0)
    stats_json = tmp_path_factory.mktemp("stats") / "norm_stats.json"
    N.save_openpi_norm_stats(stats_json, {"state": STATE_STATS, "actions": ACTION_STATS})
    dst = tmp_path_factory.mktemp("ckpt") / preset
    checkpoint.save_checkpoint(dst, params, config, assets={
        "physical-intelligence/libero/norm_stats.json": stats_json, "tokenizer.model": sp_model_path})
    return dst, config, params


@pytest.fixture(scope="module")
def pi0_ckpt(tmp_path_factory, sp_model_path):
    return make_ckpt(tmp_path_factory, sp_model_path, "dummy")


@pytest.fixture(scope="module")
def pi0_policy(pi0_ckpt):
    return Policy.from_checkpoint(pi0_ckpt[0], cache_dir=False)


def test_pi0_matches_hand_built_reference(pi0_ckpt, pi0_policy, sp_model_path):
    _, config, params = pi0_ckpt
    H, D = config.action_horizon, config.action_dim
    noise = RNG.normal(size=(H, D)).astype(np.float32)
    out = pi0_policy.infer(libero_obs(), noise=noise)
    assert set(out) == {"actions", "policy_timing"}
    assert out["actions"].shape == (H, 7) and out["actions"].dtype == np.float32
    assert out["policy_timing"]["infer_ms"] > 0

    # Reference: openpi's LIBERO transforms written out by hand (pi0 -> z-score with eps 1e-6).
    tokens, mask = PaligemmaTokenizer(sp_model_path, config.max_token_len).tokenize(PROMPT)
    state = np.zeros(D, np.float32)
    state[:8] = (STATE - STATE_STATS.mean) / (STATE_STATS.std + 1e-6)
    f = lambda im: (im.astype(np.float32) / 255 * 2 - 1)[None]
    obs = pi0.Observation(
        images={"base_0_rgb": f(IMAGE), "left_wrist_0_rgb": f(WRIST),
                "right_wrist_0_rgb": f(np.zeros_like(IMAGE))},
        image_masks={"base_0_rgb": np.ones(1, bool), "left_wrist_0_rgb": np.ones(1, bool),
                     "right_wrist_0_rgb": np.zeros(1, bool)},
        state=state[None], tokenized_prompt=tokens[None], tokenized_prompt_mask=mask[None])
    raw = np.asarray(pi0.sample_actions(config, params, obs, noise[None], num_steps=10))[0]
    want = raw[:, :7] * (ACTION_STATS.std + 1e-6) + ACTION_STATS.mean
    np.testing.assert_allclose(out["actions"], want, rtol=1e-4, atol=1e-4)
    assert raw.std() > 1e-2                                    # not a degenerate model ...
    swapped = pi0_policy.infer({**libero_obs(), "observation/image": WRIST}, noise=noise)["actions"]
    assert np.abs(swapped - out["actions"]).max() > 1e-3       # ... and the pixels reach the actions


def test_noise_shapes_and_seeded_rng(pi0_ckpt, pi0_policy):
    _, config, _ = pi0_ckpt
    noise = RNG.normal(size=(config.action_horizon, config.action_dim)).astype(np.float32)
    a = pi0_policy.infer(libero_obs(), noise=noise)["actions"]
    np.testing.assert_array_equal(pi0_policy.infer(libero_obs(), noise=noise[None])["actions"], a)
    with pytest.raises(ValueError, match="noise"):
        pi0_policy.infer(libero_obs(), noise=noise[:, :7])
    p1, p2 = (Policy.from_checkpoint(pi0_ckpt[0], seed=3, cache_dir=False) for _ in range(2))
    first = p1.infer(libero_obs())["actions"]
    np.testing.assert_array_equal(p2.infer(libero_obs())["actions"], first)
    assert not np.array_equal(p1.infer(libero_obs())["actions"], first)  # the PRNG advances per call


def test_lerobot_keys_give_the_same_actions(pi0_ckpt, pi0_policy):
    _, config, _ = pi0_ckpt
    noise = RNG.normal(size=(config.action_horizon, config.action_dim)).astype(np.float32)
    ref = pi0_policy.infer(libero_obs(), noise=noise)["actions"]
    chw = lambda im: np.ascontiguousarray(im.transpose(2, 0, 1)).astype(np.float32) / 255  # LeRobot: [0,1] CHW
    obs = {"observation.images.image": chw(IMAGE), "observation.images.wrist_image": chw(WRIST),
           "observation.state": STATE.astype(np.float32), "task": PROMPT}
    np.testing.assert_allclose(pi0_policy.infer(obs, noise=noise)["actions"], ref, atol=1e-4)


def test_engine_equals_reference_sampler_f32(pi0_ckpt, pi0_policy):
    _, config, _ = pi0_ckpt
    ref = Policy.from_checkpoint(pi0_ckpt[0], sampler="reference", cache_dir=False)
    noise = RNG.normal(size=(config.action_horizon, config.action_dim)).astype(np.float32)
    got = pi0_policy.infer(libero_obs(), noise=noise)["actions"]
    want = ref.infer(libero_obs(), noise=noise)["actions"]
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)
    assert pi0_policy.metadata["sampler"] == "engine" and ref.metadata["sampler"] == "reference"


def test_two_programs_equal_the_pipeline_as_one(pi0_ckpt, pi0_policy):
    """Policy runs `PolicyCore.encode` and `PolicyCore.act` as two programs, each on its own part of the weights;
    the simulator embeds `PolicyCore.program` whole. Both give the same actions."""
    from pi0_jax.engine import prompt_bucket

    _, config, _ = pi0_ckpt
    noise = RNG.normal(size=(config.action_horizon, config.action_dim)).astype(np.float32)
    got = pi0_policy.infer(libero_obs(), noise=noise)["actions"]
    core, p = pi0_policy.core, pi0_policy.prepare(libero_obs(), noise)
    vision, rest = core.split_model(core.model)
    assert set(vision["weights"]) == {"img"} and "img" not in rest["weights"] and "sched" in rest
    n = prompt_bucket(p.valid_tokens, config.max_token_len)
    one = jax.jit(lambda m, nm, im, *a: core.program(m, nm, im, p.cameras, *a))(
        core.model, core.norm, tuple(p.images[c][None] for c in p.cameras), np.ones((len(p.cameras), 1), bool),
        p.tokens[None, :n], p.token_mask[None, :n], p.state[None], p.noise[None])
    np.testing.assert_allclose(got, np.asarray(one)[0], rtol=1e-6, atol=1e-6)


def test_the_first_step_beside_the_prefix_in_the_policy(pi0_ckpt, pi0_policy, monkeypatch):
    """overlap="on": `Policy`'s second program runs its first denoise step after the prefix fill and compiles in
    XLA's CONCURRENT mode, and the loop over the other steps is a third program in XLA's default order, as the
    engine's call (`Engine.call_stages`); the actions are the same bit for bit. Either way the call's last program
    leaves the actions in host memory (`policy._to_host`)."""
    import re

    from pi0_jax.engine.store import ProgramStore

    compiled = {}

    def compile(self, name, parts, fn, args, options=None):
        compiled[name] = (options, jax.jit(fn).lower(*args).compile(options))
        return compiled[name][1]

    monkeypatch.setattr(ProgramStore, "compile", compile)
    noise = RNG.normal(size=(pi0_ckpt[1].action_horizon, pi0_ckpt[1].action_dim)).astype(np.float32)
    got = {}
    for overlap in ("on", "off"):
        got[overlap] = Policy.from_checkpoint(pi0_ckpt[0], cache_dir=False, overlap=overlap).infer(
            libero_obs(), noise=noise)["actions"]
        options, act = compiled.pop("policy_act_rest" if overlap == "on" else "policy_act")
        trips = re.findall(r'known_trip_count":\{"n":"(\d+)"', act.as_text())
        assert trips == (["9"] if overlap == "on" else ["10"])
        assert act.out_info.sharding.memory_kind == "pinned_host"   # the last program copies the actions back
        assert (options or {}).get("xla_gpu_command_buffer_scheduling_mode") is None
        if overlap == "on":
            options, first = compiled.pop("policy_act_first")
            assert options["xla_gpu_command_buffer_scheduling_mode"] == "CONCURRENT"
            assert not re.findall(r'known_trip_count', first.as_text())
    np.testing.assert_array_equal(got["on"], got["off"])
    assert pi0_policy.core.overlap == "auto"
    with pytest.raises(ValueError, match="overlap must be"):
        Policy.from_checkpoint(pi0_ckpt[0], cache_dir=False, overlap="always")


def test_each_policy_program_takes_the_engines_gemm_library_for_its_stage(pi0_ckpt, monkeypatch):
    """`Policy`'s programs get the GEMM library (`matmul.library`) of the engine's program for the same stage, from
    the weights that program takes: with an FP8 prefix and a bf16 expert (simulated here: the VLM's weights count
    as FP8, the library decides as on a GPU) the vision tower and the prefix fill run on cuBLAS, and the loop over
    the other denoise steps on XLA's choice, as the engine's `denoise_rest` (until session 50 it took cuBLAS from
    the whole VLM-and-expert tree)."""
    from pi0_jax.engine import runtime
    from pi0_jax.engine.store import ProgramStore
    from pi0_jax.ops import matmul

    own_library = matmul.library
    monkeypatch.setattr(matmul, "has_fp8", _has_vlm)
    monkeypatch.setattr(matmul, "library", lambda tree, gemm="auto", platform=None, **kw: own_library(
        tree, gemm, "gpu", **kw))
    compiled = {}

    class Traced:   # shapes only: nothing is compiled or run
        def __init__(self, fn, args):
            self.out_info = jax.eval_shape(fn, *args)

        def __call__(self, *args):
            raise AssertionError("not run")

    def compile(self, name, parts, fn, args, options=None):
        compiled[name] = options
        return Traced(fn, args)

    monkeypatch.setattr(ProgramStore, "compile", compile)
    policy = Policy.from_checkpoint(pi0_ckpt[0], cache_dir=False, overlap="on")
    p = policy.prepare(libero_obs())
    host = (tuple(p.images[c][None] for c in p.cameras), np.ones((len(p.cameras), 1), bool), p.tokens[None],
            p.token_mask[None], p.state[None], p.noise[None])
    policy.executable(host, p.cameras)
    cublas = {"xla_gpu_enable_triton_gemm": False}
    loop = {k: 0 for k in runtime.STAGE_WEIGHTS["denoise_rest"]}
    assert compiled["policy_act_rest"] == matmul.compiler_options(loop, "auto", **runtime.library_keywords(
        "denoise_rest", 1)) is None
    assert compiled["policy_act_first"]["xla_gpu_enable_triton_gemm"] is False
    encodes = [k for k in compiled if "encode" in k]
    assert encodes and all(compiled[k] == cublas for k in encodes)


def _has_vlm(tree) -> bool:
    return isinstance(tree, dict) and any(k == "vlm" or _has_vlm(v) for k, v in tree.items())


def test_the_vision_tower_as_two_programs_in_the_policy(pi0_ckpt, monkeypatch):
    """Where the engine's call cuts the vision tower in two (`runtime.VISION_SPLIT` blocks first), `Policy` compiles
    the same two programs, each on its own blocks' weights; the actions are the same bit for bit."""
    from pi0_jax.engine import runtime
    from pi0_jax.engine.store import ProgramStore

    compiled = {}

    def compile(self, name, parts, fn, args, options=None):
        compiled[name] = len(jax.tree.leaves(args[0]))
        return jax.jit(fn).lower(*args).compile(options)

    monkeypatch.setattr(ProgramStore, "compile", compile)
    noise = RNG.normal(size=(pi0_ckpt[1].action_horizon, pi0_ckpt[1].action_dim)).astype(np.float32)
    got = {}
    for split in (0, 1):
        monkeypatch.setattr(runtime, "VISION_SPLIT", split)
        got[split] = Policy.from_checkpoint(pi0_ckpt[0], cache_dir=False).infer(libero_obs(), noise=noise)["actions"]
    np.testing.assert_array_equal(got[0], got[1])
    depth = pi0_ckpt[1].siglip.depth
    # the patch embedding's 2, pos, the blocks' table of vectors (both programs take it), the final norm, head's 2
    per_block = (compiled["policy_encode"] - 7) // depth
    assert per_block == 4   # q/k/v, out, fc1, fc2: their biases and norms are in the table
    assert (compiled["policy_encode_head"], compiled["policy_encode_tail"]) == (4 + per_block,
                                                                                 4 + per_block * (depth - 1))


def test_engine_equals_reference_sampler_bf16(pi0_ckpt):
    _, config, _ = pi0_ckpt
    eng = Policy.from_checkpoint(pi0_ckpt[0], dtype="bfloat16", cache_dir=False)
    ref = Policy.from_checkpoint(pi0_ckpt[0], dtype="bfloat16", sampler="reference", cache_dir=False)
    noise = RNG.normal(size=(config.action_horizon, config.action_dim)).astype(np.float32)
    got, want = (p.infer(libero_obs(), noise=noise)["actions"] for p in (eng, ref))
    assert np.linalg.norm(got - want) / np.linalg.norm(want) < 1e-2


def test_infer_batch_equals_lone_calls_and_compiles_once_per_bucket(pi0_ckpt, pi0_policy):
    _, config, _ = pi0_ckpt
    shape = (config.action_horizon, config.action_dim)
    obs = [libero_obs(), {**libero_obs(), "prompt": "open the top drawer and put the bowl inside"},
           {**libero_obs(), "observation/state": -STATE}, {**libero_obs(), "observation/image": WRIST}]
    noise = [RNG.normal(size=shape).astype(np.float32) for _ in obs]
    lone = [pi0_policy.infer(o, noise=n)["actions"] for o, n in zip(obs, noise)]
    n_compiled = pi0_policy.num_compiled
    outs = pi0_policy.infer_batch(obs, noise=noise)
    assert [o["policy_timing"]["batch_size"] for o in outs] == [4] * 4
    for got, want in zip(outs, lone):
        np.testing.assert_allclose(got["actions"], want, rtol=1e-5, atol=1e-5)
    assert pi0_policy.num_compiled == n_compiled + 1          # one program for the batch of 4
    pi0_policy.infer_batch(obs[::-1], noise=noise[::-1])       # new values, same shapes: no new program
    pi0_policy.infer({**libero_obs(), "observation/state": STATE * 0.5})
    assert pi0_policy.num_compiled == n_compiled + 1
    # a 5th element with another camera shape runs as its own group, still in input order
    odd = {**libero_obs(), "observation/image": IMAGE[:100]}
    outs = pi0_policy.infer_batch(obs[:2] + [odd], noise=noise[:2] + [noise[0]])
    np.testing.assert_allclose(outs[1]["actions"], lone[1], rtol=1e-5, atol=1e-5)
    assert [o["policy_timing"]["batch_size"] for o in outs] == [2, 2, 1]


def _without(obs, key):
    return {k: v for k, v in obs.items() if k != key}


BAD_INPUTS = [
    ("NaN state", {"observation/state": np.where(np.arange(8) == 3, np.nan, STATE)}, "observation/state.*NaN"),
    ("short state", {"observation/state": STATE[:3]}, r"observation/state.*3 dims.*expect 8"),
    ("2-D state", {"observation/state": np.stack([STATE, STATE])}, "observation/state.*1-D"),
    ("string state", {"observation/state": np.array(["a"] * 8)}, "observation/state.*real numbers"),
    ("mistyped camera", {"observation/wrist_imag": WRIST}, r"observation/wrist_imag.*accepted keys"),
    ("unknown key", {"gripper": 1.0}, r"'gripper'.*accepted keys"),
    ("int32 image", {"observation/image": IMAGE.astype(np.int32)}, r"observation/image.*uint8.*float"),
    ("float image 0-255", {"observation/image": IMAGE.astype(np.float32)}, r"observation/image.*outside.*range"),
    ("NaN image", {"observation/image": np.full((224, 224, 3), np.nan, np.float32)}, "observation/image.*NaN"),
    ("2-D image", {"observation/image": IMAGE[..., 0]}, r"observation/image.*\(H, W, 3\)"),
    ("4-channel image", {"observation/image": np.zeros((224, 224, 4), np.uint8)}, "observation/image.*3-channel"),
    ("prompt not a string", {"prompt": 3}, "prompt.*string"),
]


@pytest.mark.parametrize("name,change,match", BAD_INPUTS, ids=[b[0] for b in BAD_INPUTS])
def test_bad_inputs_raise_naming_the_culprit(pi0_policy, name, change, match):
    with pytest.raises(ObservationError, match=match):
        pi0_policy.infer({**libero_obs(), **change})


def test_missing_inputs_and_opt_outs(pi0_ckpt, pi0_policy):
    _, config, _ = pi0_ckpt
    with pytest.raises(ObservationError, match=r"left_wrist_0_rgb.*missing.*observation/wrist_image"):
        pi0_policy.infer(_without(libero_obs(), "observation/wrist_image"))
    with pytest.raises(ObservationError, match="prompt"):
        pi0_policy.infer(_without(libero_obs(), "prompt"))
    with pytest.raises(ObservationError, match="state"):
        pi0_policy.infer(_without(libero_obs(), "observation/state"))
    shape = (config.action_horizon, config.action_dim)
    with pytest.raises(ObservationError, match="noise.*NaN"):
        pi0_policy.infer(libero_obs(), noise=np.full(shape, np.nan, np.float32))
    # opt-outs: extra keys ignored, a camera allowed to be masked, a key mapped to None, a default prompt
    lax = Policy.from_checkpoint(pi0_ckpt[0], strict=False, optional_cameras=("left_wrist_0_rgb", "right_wrist_0_rgb"),
                                 camera_map={"observation/top_image": None}, default_prompt="do it", cache_dir=False)
    obs = {**_without(_without(libero_obs(), "observation/wrist_image"), "prompt"), "gripper": 1.0,
           "observation/top_image": IMAGE}
    assert lax.make_observation(obs).image_masks["left_wrist_0_rgb"].tolist() == [False]
    out = lax.infer(obs)["actions"]
    assert out.shape == (config.action_horizon, 7) and np.isfinite(out).all()
    # dataset bookkeeping keys are ignored even when strict
    pi0_policy.infer({**libero_obs(), "timestamp": np.float32(0.1), "robot_type": "panda"})


def test_pi0_small_refuses_a_third_camera():
    from importlib import resources

    with resources.as_file(resources.files("pi0_jax") / "assets" / "pi0_small") as ckpt:
        policy = Policy.from_checkpoint(ckpt, dtype="float32", cache_dir=False)
    obs = {**policy.example_observation(), "observation.images.right_wrist_0_rgb": IMAGE}
    with pytest.raises(ObservationError, match=r"right_wrist_0_rgb.*only.*base_0_rgb"):
        policy.infer(obs)
    assert policy.infer(policy.example_observation())["actions"].shape == (10, 7)


def test_missing_assets(tmp_path, pi0_ckpt):
    with pytest.raises(FileNotFoundError, match="nope.model"):
        Policy.from_checkpoint(pi0_ckpt[0], tokenizer_path=tmp_path / "nope.model")
    with pytest.raises(FileNotFoundError, match="missing.json"):
        Policy.from_checkpoint(pi0_ckpt[0], norm_stats=tmp_path / "missing.json")


@pytest.fixture(scope="module")
def pi05_ckpt(tmp_path_factory, sp_model_path):
    return make_ckpt(tmp_path_factory, sp_model_path, "dummy_pi05", discrete_state_input=True)


def test_pi05_discrete_state_prompt(pi05_ckpt, sp_model_path):
    dst, config, _ = pi05_ckpt
    policy = Policy.from_checkpoint(dst, cache_dir=False)
    assert policy.normalizer.modes["state"] is N.Mode.QUANTILES  # openpi: quantiles for π0.5
    obs = policy.make_observation(libero_obs())
    tok = PaligemmaTokenizer(sp_model_path, config.max_token_len)
    n = int(obs.tokenized_prompt_mask.sum())
    text = tok.decode(obs.tokenized_prompt[0, 1:n])
    norm = (STATE - STATE_STATS.q01) / (STATE_STATS.q99 - STATE_STATS.q01 + 1e-6) * 2 - 1
    bins = np.floor((norm + 1) * 128).astype(int).clip(-1, 255)  # the 256 bins over [-1, 1], by hand
    assert text == f"Task: {PROMPT}, State: {' '.join(map(str, bins))};\nAction: "
    out = policy.infer(libero_obs())
    assert out["actions"].shape == (config.action_horizon, 7) and np.isfinite(out["actions"]).all()

    # LeRobot convention: the state is zero-padded to action_dim before it is written into the prompt.
    lr = N.Normalizer(stats={"state": STATE_STATS, "actions": ACTION_STATS},
                      modes={"state": "QUANTILES", "actions": "QUANTILES"}, convention="lerobot")
    policy = Policy.from_checkpoint(dst, norm_stats=lr, cache_dir=False)
    obs = policy.make_observation(libero_obs())
    n = int(obs.tokenized_prompt_mask.sum())
    listed = tok.decode(obs.tokenized_prompt[0, 1:n]).split("State: ")[1].split(";")[0].split()
    assert len(listed) == config.action_dim and listed[8:] == ["128"] * (config.action_dim - 8)


def test_a_policy_with_a_cache_dir_loads_its_programs_the_second_time(pi0_ckpt, pi0_policy, tmp_path, monkeypatch):
    """Policy's two programs through the program store (`engine.store`, turned on for this CPU): the second policy
    loads both, and its actions are the first one's and the uncached policy's. (Should a loaded program fail to run,
    as XLA:CPU's may in a process that compiled much before, `store._Loaded` compiles it again: the actions hold.)"""
    from pi0_jax.engine import store

    monkeypatch.setattr(store, "PLATFORMS", ("cpu", "gpu"))
    _, config, _ = pi0_ckpt
    noise = RNG.normal(size=(config.action_horizon, config.action_dim)).astype(np.float32)
    want = pi0_policy.infer(libero_obs(), noise=noise)["actions"]
    for stored in (0, 2):
        policy = Policy.from_checkpoint(pi0_ckpt[0], cache_dir=tmp_path)
        np.testing.assert_array_equal(policy.infer(libero_obs(), noise=noise)["actions"], want)
        assert policy.store.loaded == stored
    assert sorted(p.name.split("-")[0] for p in (tmp_path / "programs").glob("*.pkl")) == ["policy_act",
                                                                                           "policy_encode"]
