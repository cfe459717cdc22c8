"""Parity with LeRobot's PyTorch π0 / π0.5 (an implementation nobody here wrote), float32, CPU.

The fixtures under tests/fixtures/lerobot_pi0{,5}/ were written by `scripts/make_lerobot_fixtures.py` (LeRobot 0.6.1,
transformers 5.5, torch 2.11): LeRobot's own `save_pretrained` checkpoint at a tiny size with every weight random,
plus inputs, injected noise and LeRobot's outputs at every stage. Here the checkpoint goes through `pi0-jax convert`
and each stage is compared.

Tolerances (float32 on both sides; differences come from op order, HF's RoPE angle arithmetic and LeRobot computing
the time embedding in float64):
  per stage (vision tokens, prefix embeddings, K/V, one velocity, loss): rtol 1e-4, atol 1e-4 (atol is needed for
  near-zero elements; K at positions ~900 differs by ~2e-5 from angle rounding alone);
  10-step sampling: the same (measured max abs error ~2e-5; LeRobot's own openpi parity test uses rtol 1e-2, atol 5e-3).
Each comparison also reports the relative L2 error, asserted below 1e-5 (measured 1e-6 to 5e-6).
"""

import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import converters
from pi0_jax import checkpoint, pi0
from pi0_jax.config import IMAGE_KEYS

FIXTURES = Path(__file__).parent / "fixtures"


def rel_l2(a, b):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return np.linalg.norm(a - b) / np.linalg.norm(b)


def check(name, got, want, rtol, atol, max_rel_l2):
    got, want = np.asarray(got), np.asarray(want)
    assert got.shape == want.shape, f"{name}: shape {got.shape} != {want.shape}"
    assert np.isfinite(got).all(), f"{name}: non-finite output"
    err = rel_l2(got, want)
    assert err < max_rel_l2, f"{name}: relative L2 error {err:.2e} >= {max_rel_l2:.0e}"
    np.testing.assert_allclose(got, want, rtol=rtol, atol=atol, err_msg=name)


@pytest.fixture(scope="module", params=["lerobot_pi0", "lerobot_pi05"])
def converted(request, tmp_path_factory):
    src = FIXTURES / request.param
    dst = tmp_path_factory.mktemp(request.param) / "converted"
    converters.convert(src, dst, dtype="float32")
    config, params = checkpoint.load_checkpoint(dst)
    golden = dict(np.load(src / "golden.npz"))
    meta = json.loads((src / "meta.json").read_text())
    return config, params, golden, meta


def observation(g):
    images = g["images"].astype(np.float32) / 255 * 2 - 1  # exactly LeRobot's preprocessing (see meta.json)
    return pi0.Observation(
        images={k: jnp.asarray(images[i]) for i, k in enumerate(IMAGE_KEYS)},
        image_masks={k: jnp.asarray(g["image_masks"][i]) for i, k in enumerate(IMAGE_KEYS)},
        state=jnp.asarray(g["state"]),
        tokenized_prompt=jnp.asarray(g["tokens"], jnp.int32),
        tokenized_prompt_mask=jnp.asarray(g["token_masks"]),
    )


def test_converted_config(converted):
    config, params, golden, meta = converted
    assert config.pi05 == (meta["variant"] == "pi05")
    assert (config.paligemma_variant, config.action_expert_variant) == ("dummy", "dummy_expert")
    assert config.action_horizon == golden["noise"].shape[1]
    assert config.max_token_len == golden["tokens"].shape[1]
    assert config.dtype == "float32"


def test_vision_tokens(converted):
    config, params, g, _ = converted
    obs = observation(g)
    for i, key in enumerate(IMAGE_KEYS):
        got = jax.jit(pi0.embed_images, static_argnums=0)(config, params, obs.images[key])
        check(f"vision tokens {key}", got, g["vision_tokens"][i], 1e-4, 1e-4, 1e-5)


def test_prefix_embeddings_and_kv_cache(converted):
    config, params, g, _ = converted
    obs = observation(g)
    tokens, mask, _ = jax.jit(pi0.embed_prefix, static_argnums=0)(config, params, obs)
    check("prefix embeddings", tokens, g["prefix_embs"], 1e-4, 1e-4, 1e-5)
    np.testing.assert_array_equal(mask, g["prefix_pad_masks"])
    cache = jax.jit(pi0.fill_prefix_cache, static_argnums=0)(config, params, obs)
    # Rows of masked tokens are computed from masked-out context; compare the valid rows (what anyone can attend).
    valid = g["prefix_pad_masks"][None, :, :, None, None]
    for name, got in (("prefix_k", cache.k), ("prefix_v", cache.v)):
        check(name, np.where(valid, got, 0), np.where(valid, g[name], 0), 1e-4, 1e-4, 1e-5)


def test_one_velocity(converted):
    config, params, g, _ = converted
    cache = jax.jit(pi0.fill_prefix_cache, static_argnums=0)(config, params, observation(g))
    v = jax.jit(pi0.denoise_step, static_argnums=0)(config, params, cache, jnp.asarray(g["x_t"]),
                                                    jnp.asarray(g["time"]))
    check("velocity", v, g["velocity"], 1e-4, 1e-4, 1e-5)


def test_sample_actions_10_steps(converted):
    config, params, g, _ = converted
    actions = jax.jit(pi0.sample_actions, static_argnums=(0, 4))(config, params, observation(g),
                                                                 jnp.asarray(g["noise"]), 10)
    check("actions", actions, g["actions"], 1e-4, 1e-4, 1e-5)


def test_loss(converted):
    config, params, g, _ = converted
    obs = observation(g)
    t = jnp.asarray(g["loss_time"])
    x_t = t[:, None, None] * g["loss_noise"] + (1 - t[:, None, None]) * g["loss_actions"]
    v = jax.jit(lambda p, o, x, t: pi0._apply(config, p, o, x, t, method=pi0.Pi0.joint_velocity))(params, obs, x_t, t)
    per_element = (np.asarray(v) - (g["loss_noise"] - g["loss_actions"])) ** 2
    check("loss", per_element, g["loss"], 1e-4, 1e-4, 1e-5)
    loss = jax.jit(pi0.compute_loss, static_argnums=0)(config, params, obs, jnp.asarray(g["loss_actions"]),
                                                       jnp.asarray(g["loss_noise"]), t)
    np.testing.assert_allclose(loss, g["loss"].mean(-1), rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("variant", ["lerobot_pi0", "lerobot_pi05"])
def test_normalisation_from_lerobot_processor_files(variant):
    """LeRobot's saved processor files (MEAN_STD for π0, QUANTILES for π0.5) give LeRobot's numbers."""
    from pi0_jax.normalize import load_lerobot_normalizer

    g = np.load(FIXTURES / variant / "golden.npz")
    normalizer = load_lerobot_normalizer(FIXTURES / variant)
    np.testing.assert_allclose(normalizer.normalize("state", g["norm_state_in"]), g["norm_state_out"], rtol=1e-5,
                               atol=1e-6)
    np.testing.assert_allclose(normalizer.unnormalize("actions", g["unnorm_actions_in"]), g["unnorm_actions_out"],
                               rtol=1e-5, atol=1e-6)
    assert not np.allclose(g["norm_state_in"], g["norm_state_out"])  # the stats are not an identity
