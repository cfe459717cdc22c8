"""End-to-end Policy tests on the dummy presets, against a hand-built Observation and hand-written formulas."""

import numpy as np
import pytest
import jax

from pi0_jax import checkpoint, normalize as N, pi0
from pi0_jax.config import get_config
from pi0_jax.policy import Policy
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
    params = pi0.init_params(config, jax.random.key(0))
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
    return Policy.from_checkpoint(pi0_ckpt[0])


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
    assert np.abs(want).max() > 0  # not a degenerate all-zero model


def test_noise_shapes_and_seeded_rng(pi0_ckpt, pi0_policy):
    _, config, _ = pi0_ckpt
    noise = RNG.normal(size=(config.action_horizon, config.action_dim)).astype(np.float32)
    a = pi0_policy.infer(libero_obs(), noise=noise)["actions"]
    np.testing.assert_array_equal(pi0_policy.infer(libero_obs(), noise=noise[None])["actions"], a)
    with pytest.raises(ValueError, match="noise"):
        pi0_policy.infer(libero_obs(), noise=noise[:, :7])
    p1, p2 = Policy.from_checkpoint(pi0_ckpt[0], seed=3), Policy.from_checkpoint(pi0_ckpt[0], seed=3)
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


def test_observation_errors(pi0_ckpt, pi0_policy):
    bad = {**libero_obs(), "observation/top_image": IMAGE}
    with pytest.raises(ValueError, match="observation/top_image"):
        pi0_policy.make_observation(bad)
    p = Policy.from_checkpoint(pi0_ckpt[0], camera_map={"observation/top_image": None}, default_prompt="do it")
    obs = {k: v for k, v in bad.items() if k != "prompt"}
    assert p.make_observation(obs).image_masks["right_wrist_0_rgb"].tolist() == [False]
    with pytest.raises(KeyError, match="prompt"):
        pi0_policy.make_observation({k: v for k, v in libero_obs().items() if k != "prompt"})
    with pytest.raises(KeyError, match="state"):
        pi0_policy.make_observation({k: v for k, v in libero_obs().items() if k != "observation/state"})


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
    policy = Policy.from_checkpoint(dst)
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
    policy = Policy.from_checkpoint(dst, norm_stats=lr)
    obs = policy.make_observation(libero_obs())
    n = int(obs.tokenized_prompt_mask.sum())
    listed = tok.decode(obs.tokenized_prompt[0, 1:n]).split("State: ")[1].split(";")[0].split()
    assert len(listed) == config.action_dim and listed[8:] == ["128"] * (config.action_dim - 8)
