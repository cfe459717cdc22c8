"""The engine's programs are called without jax's per-argument checks of weights they were given before
(`engine.dispatch`): the same outputs as jax's call, on the direct path from the second call, and every argument
that is not what the program was compiled for goes through jax's call, which raises."""

import gc
import weakref
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pi0_jax import pi0
from pi0_jax.config import get_config
from pi0_jax.engine import Engine, dispatch, runtime, store
from test_model import make_obs, randomize


@pytest.fixture(scope="module")
def model():
    config = get_config("dummy")
    return config, randomize(pi0.param_shapes(config))


@pytest.fixture(scope="module")
def engine(model):
    return Engine(*model, cache_dir=False)


def _inputs(engine, seed):
    obs = make_obs(engine.config, seed=seed)
    return obs, jax.random.normal(jax.random.key(seed), (2, engine.config.action_horizon, engine.config.action_dim))


@pytest.mark.parametrize("split", [0, 1])
def test_the_engines_calls_take_the_direct_path_and_equal_jaxs(model, split, monkeypatch):
    """Every program of the call (the tower whole or as two programs) runs direct from its second call on, inputs
    changing between calls, and gives jax's call's actions bit for bit; so a jax that moved the internals the path
    reads fails here."""
    monkeypatch.setattr(runtime, "VISION_SPLIT", split)
    eng = Engine(*model, cache_dir=False)   # its own programs, so their counts are this test's
    sets = [_inputs(eng, seed) for seed in range(2)]
    got = [np.asarray(eng.sample_actions(*sets[i % 2], 3)) for i in range(4)]
    progs = eng.call_programs(2, 3, *eng.plan(sets[0][0]))
    assert len(progs) == (3 if split else 2)
    assert all(p.dispatch.direct_calls == 3 for p in progs), [(p.stage, p.dispatch.direct_calls) for p in progs]
    monkeypatch.setattr(dispatch, "DIRECT", False)
    want = [np.asarray(eng.sample_actions(*sets[i], 3)) for i in range(2)]
    assert all(p.dispatch.direct_calls == 3 for p in progs)
    for i, g in enumerate(got):
        np.testing.assert_array_equal(g, want[i % 2])


def test_an_argument_unlike_the_compiled_goes_to_jax_and_fails_there(engine):
    """PjRt checks only a buffer's size: images transposed (the same bytes) or weights of another dtype of the same
    width would run. Here they go to jax's call, which refuses them."""
    obs, _ = _inputs(engine, 0)
    cameras, bucket = engine.plan(obs)
    images = engine.pack(obs, cameras, bucket)[0]
    prog = engine.executable("encode_images", 2, 3, cameras, bucket)
    first = np.asarray(prog(engine.weights, images))
    np.testing.assert_array_equal(np.asarray(prog(engine.weights, images)), first)
    direct = prog.dispatch.direct_calls
    assert direct >= 1
    with pytest.raises(TypeError, match="[Aa]rgument"):
        prog(engine.weights, jnp.swapaxes(images, -1, -2))
    patch = engine.weights["img"]["embedding"]["kernel"]
    other = {**engine.weights, "img": {**engine.weights["img"], "embedding": {
        **engine.weights["img"]["embedding"], "kernel": jax.lax.bitcast_convert_type(patch, jnp.int32)}}}
    with pytest.raises(TypeError, match="[Aa]rgument"):
        prog(other, images)
    assert prog.dispatch.direct_calls == direct
    np.testing.assert_array_equal(np.asarray(prog(engine.weights, images)), first)


def test_new_weights_are_checked_used_and_the_old_ones_not_kept(engine):
    """Weights of the same shapes but new arrays run direct with their own values (not the last ones'), and the
    path keeps no old weight alive."""
    obs, _ = _inputs(engine, 1)
    cameras, bucket = engine.plan(obs)
    images = engine.pack(obs, cameras, bucket)[0]
    prog = engine.executable("encode_images", 2, 3, cameras, bucket)
    first = np.asarray(prog(engine.weights, images))
    scaled = jax.tree.map(lambda x: x * 2 if x.ndim == 2 else x + 0, engine.weights)
    old_leaf = weakref.ref(jax.tree.leaves(scaled["img"])[0])
    direct = prog.dispatch.direct_calls
    got = np.asarray(prog(scaled, images))
    assert prog.dispatch.direct_calls == direct + 1
    dispatch_on = dispatch.DIRECT
    dispatch.DIRECT = False
    try:
        np.testing.assert_array_equal(got, np.asarray(prog(scaled, images)))
    finally:
        dispatch.DIRECT = dispatch_on
    assert not np.array_equal(got, first)
    np.testing.assert_array_equal(np.asarray(prog(engine.weights, images)), first)
    del scaled
    gc.collect()
    assert old_leaf() is None


def test_a_stored_program_is_called_direct_after_its_first_call():
    """A program loaded from the store checks itself on its first call (`store._Loaded`); the direct path takes
    what it loaded after that. A program with host callbacks or a donated input always goes through jax."""
    w, x = {"a": jnp.arange(6.0).reshape(2, 3)}, jnp.ones((3, 4))
    compiled = jax.jit(lambda w, x: w["a"] @ x).lower(w, x).compile()
    call = dispatch.Dispatch(store._Loaded(compiled, Path("unused.pkl"), None, None))
    want = np.asarray(compiled(w, x))
    for _ in range(3):
        np.testing.assert_array_equal(np.asarray(call(w, x)), want)
    assert call.direct_calls == 2

    def noisy(w, x):
        jax.debug.callback(lambda v: None, x)
        return w["a"] @ x

    call = dispatch.Dispatch(jax.jit(noisy).lower(w, x).compile())
    for _ in range(2):
        np.testing.assert_array_equal(np.asarray(call(w, x)), want)
    assert call.direct_calls == 0
    call = dispatch.Dispatch(jax.jit(lambda w, x: x + w["a"].sum(), donate_argnums=1).lower(w, x).compile())
    for _ in range(2):
        np.testing.assert_array_equal(np.asarray(call(w, jnp.ones((3, 4)))), np.full((3, 4), 16.0))
    assert call.direct_calls == 0
