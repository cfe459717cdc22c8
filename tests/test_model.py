"""Model self-consistency on the tiny presets at realistic sequence lengths (3 x 256 image tokens + prompt),
plus free `jax.eval_shape` checks of the full-size presets."""

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pi0_jax import pi0
from pi0_jax.config import IMAGE_KEYS, get_config


def randomize(params, seed=0, scale=0.2):
    """Every leaf random (openpi zero-inits norms, the adaRMS Dense and the SigLIP head, which would hide bugs).
    params: a param tree or its shapes (`pi0.param_shapes`: the same result without running the model's init).
    Each leaf is drawn flat and reshaped: the same bits as a draw at its shape, but XLA:CPU compiles a rank-4/5 draw
    in 1-3 s, a rank-1 one in ~0.2 s."""
    leaves, treedef = jax.tree.flatten(params)
    keys = jax.random.split(jax.random.key(seed), len(leaves))
    new = []
    for k, x in zip(keys, leaves):
        fan_in = x.shape[-2] if x.ndim >= 2 else 1
        std = scale if x.ndim < 2 else 1.0 / np.sqrt(fan_in)
        new.append(jax.random.normal(k, (int(np.prod(x.shape)),), jnp.float32).reshape(x.shape) * std)
    return jax.tree.unflatten(treedef, new)


def make_obs(config, batch=2, seed=0, valid_lens=(13, 31)):
    rng = np.random.default_rng(seed)
    s = config.image_size
    keys = IMAGE_KEYS[: config.num_cameras]
    images = {k: jnp.asarray(rng.uniform(-1, 1, (batch, s, s, 3)), jnp.float32) for k in keys}
    masks = {k: jnp.ones((batch,), bool) for k in keys}
    masks[keys[-1]] = jnp.asarray([True] + [False] * (batch - 1))
    L = config.max_token_len
    tokens = rng.integers(2, config.vocab_size, (batch, L))
    tmask = np.arange(L)[None, :] < np.asarray(valid_lens[:batch])[:, None]
    return pi0.Observation(
        images=images, image_masks=masks,
        state=jnp.asarray(rng.normal(size=(batch, config.action_dim)), jnp.float32),
        tokenized_prompt=jnp.asarray(np.where(tmask, tokens, 0), jnp.int32),
        tokenized_prompt_mask=jnp.asarray(tmask),
    )


@pytest.fixture(scope="module", params=["dummy", "dummy_pi05"])
def setup(request):
    config = get_config(request.param)
    params = randomize(pi0.param_shapes(config))   # every leaf is redrawn: init_params' values are never read
    return config, params


def test_prefix_is_realistic_length(setup):
    config, params = setup
    obs = make_obs(config)
    tokens, mask, ar = pi0.embed_prefix(config, params, obs)
    assert tokens.shape == (2, 3 * 256 + config.max_token_len, config.paligemma.width)
    assert mask.shape == tokens.shape[:2] and ar.shape == tokens.shape[1:2]
    assert config.prefix_len == tokens.shape[1] >= 800


def test_cached_prefix_equals_joint_pass(setup):
    config, params = setup
    obs = make_obs(config)
    x_t = jax.random.normal(jax.random.key(1), (2, config.action_horizon, config.action_dim))
    t = jnp.asarray([0.7, 0.3])
    cache = jax.jit(pi0.fill_prefix_cache, static_argnums=0)(config, params, obs)
    v_cached = jax.jit(pi0.denoise_step, static_argnums=0)(config, params, cache, x_t, t)
    v_joint = jax.jit(functools.partial(pi0._apply, method=pi0.Pi0.joint_velocity), static_argnums=0)(
        config, params, obs, x_t, t)
    assert v_cached.shape == (2, config.action_horizon, config.action_dim)
    assert float(jnp.std(v_joint)) > 1e-2  # not a degenerate output
    np.testing.assert_allclose(v_cached, v_joint, rtol=1e-5, atol=1e-5)


def test_sample_actions_is_euler_over_denoise_step(setup):
    config, params = setup
    obs = make_obs(config)
    noise = jax.random.normal(jax.random.key(2), (2, config.action_horizon, config.action_dim))
    got = jax.jit(pi0.sample_actions, static_argnums=(0, 4))(config, params, obs, noise, 3)
    cache = jax.jit(pi0.fill_prefix_cache, static_argnums=0)(config, params, obs)
    step = jax.jit(pi0.denoise_step, static_argnums=0)
    x, t = noise, 1.0
    for _ in range(3):
        x = x + (-1 / 3) * step(config, params, cache, x, t)
        t -= 1 / 3
    np.testing.assert_allclose(got, x, rtol=1e-4, atol=1e-4)  # jit vs op-by-op f32 reassociation over 3 steps


def test_masked_camera_and_padding_change_nothing(setup):
    """Masked camera pixels and padded prompt ids are invisible, and dropping them entirely (fewer cameras, a shorter
    prompt) gives the same actions: masked tokens do not advance positions."""
    config, params = setup
    sample = jax.jit(pi0.sample_actions, static_argnums=(0, 4))
    obs = make_obs(config, batch=1, valid_lens=(19,))  # batch 1: the last camera is valid, so mask it explicitly
    last = IMAGE_KEYS[config.num_cameras - 1]
    obs = obs.replace(image_masks={**obs.image_masks, last: jnp.zeros((1,), bool)})
    noise = jax.random.normal(jax.random.key(3), (1, config.action_horizon, config.action_dim))
    ref = sample(config, params, obs, noise, 2)

    scrambled = obs.replace(
        images={**obs.images, last: -obs.images[last]},
        tokenized_prompt=jnp.where(obs.tokenized_prompt_mask, obs.tokenized_prompt, 7),
    )
    np.testing.assert_array_equal(sample(config, params, scrambled, noise, 2), ref)

    short = dataclasses.replace(config, num_cameras=config.num_cameras - 1, max_token_len=19)
    trimmed = obs.replace(
        images={k: v for k, v in obs.images.items() if k != last},
        image_masks={k: v for k, v in obs.image_masks.items() if k != last},
        tokenized_prompt=obs.tokenized_prompt[:, :19], tokenized_prompt_mask=obs.tokenized_prompt_mask[:, :19],
    )
    np.testing.assert_allclose(sample(short, params, trimmed, noise, 2), ref, rtol=1e-5, atol=1e-5)
    # and the mask matters: unmasking the camera does change the output
    unmasked = obs.replace(image_masks={**obs.image_masks, last: jnp.ones((1,), bool)})
    assert not np.allclose(sample(config, params, unmasked, noise, 2), ref, atol=1e-4)


def test_compute_loss_matches_definition(setup):
    config, params = setup
    obs = make_obs(config)
    k1, k2 = jax.random.split(jax.random.key(4))
    actions = jax.random.normal(k1, (2, config.action_horizon, config.action_dim))
    noise = jax.random.normal(k2, actions.shape)
    t = jnp.asarray([0.25, 0.9])
    loss_fn = jax.jit(pi0.compute_loss, static_argnums=0)
    loss = loss_fn(config, params, obs, actions, noise, t)
    x_t = t[:, None, None] * noise + (1 - t[:, None, None]) * actions
    v = jax.jit(functools.partial(pi0._apply, method=pi0.Pi0.joint_velocity), static_argnums=0)(
        config, params, obs, x_t, t)
    assert loss.shape == (2, config.action_horizon)
    np.testing.assert_allclose(loss, np.mean((np.asarray(v) - (noise - actions)) ** 2, -1), rtol=1e-5)
    grads = jax.jit(jax.grad(lambda p: loss_fn(config, p, obs, actions, noise, t).mean()))(params)
    assert all(np.isfinite(g).all() for g in jax.tree.leaves(grads))


def test_make_attn_mask_worked_example():
    # prefix of 3 (bidirectional), then a state token (new block), then 2 actions (new block, bidirectional)
    input_mask = jnp.asarray([[True, True, False, True, True, True]])
    ar = jnp.asarray([False, False, False, True, True, False])
    m = np.asarray(pi0.make_attn_mask(input_mask, ar)[0]).astype(int)
    expected = np.array([
        [1, 1, 0, 0, 0, 0],
        [1, 1, 0, 0, 0, 0],
        [0, 0, 0, 0, 0, 0],  # a padded token sees nothing and is seen by nobody
        [1, 1, 0, 1, 0, 0],
        [1, 1, 0, 1, 1, 1],
        [1, 1, 0, 1, 1, 1],
    ])
    np.testing.assert_array_equal(m, expected)


def test_posemb_sincos_endpoints():
    e = pi0.posemb_sincos(jnp.asarray([0.0, 1.0]), 8)
    np.testing.assert_allclose(e[0], [0, 0, 0, 0, 1, 1, 1, 1], atol=1e-7)
    period = 4e-3 * (4.0 / 4e-3) ** np.linspace(0, 1, 4)
    # arguments reach 2*pi/4e-3 ~ 1571 rad, where f32 keeps ~1e-4 absolute
    np.testing.assert_allclose(e[1, :4], np.sin(2 * np.pi / period), atol=5e-4)


@pytest.mark.parametrize("name, billions", [("pi0_base", 3.24), ("pi05_base", 3.35)])
def test_full_size_shapes(name, billions):
    config = get_config(name)
    shapes = pi0.param_shapes(config)
    n = sum(x.size for x in jax.tree.leaves(shapes))
    assert abs(n / 1e9 - billions) < 0.01, n
    llm = shapes["PaliGemma"]["llm"]
    assert llm["embedder"]["input_embedding"].shape == (257152, 2048)
    assert llm["layers"]["attn"]["q_einsum_1"]["w"].shape == (18, 8, 1024, 256)
    assert shapes["PaliGemma"]["img"]["Transformer"]["encoderblock"]["MlpBlock_0"]["Dense_0"]["kernel"].shape == (
        27, 1152, 4304)
    obs = jax.eval_shape(lambda: pi0.fake_observation(config, 1))
    noise = jax.ShapeDtypeStruct((1, config.action_horizon, 32), jnp.float32)
    out = jax.eval_shape(functools.partial(pi0.sample_actions, config, num_steps=10), shapes, obs, noise)
    assert out.shape == (1, 50, 32) and out.dtype == jnp.float32
    cache = jax.eval_shape(functools.partial(pi0.fill_prefix_cache, config), shapes, obs)
    assert cache.k.shape == (18, 1, config.prefix_len, 1, 256)
