"""`engine.dispatch.Direct`: a compiled program called straight through its loaded executable once the compiled call
has accepted its weights, with the compiled call's results and errors."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pi0_jax.engine.dispatch import Direct


def _program():
    def f(w, x, y):
        return {"sum": w["a"] @ x + w["b"], "y": y * 2}

    w = {"a": jnp.arange(12.0).reshape(3, 4), "b": jnp.ones(3), "unused": jnp.zeros(5)}
    x, y = jnp.arange(4.0), jnp.arange(6, dtype=jnp.int32)
    return f, w, x, y, jax.jit(f).lower(w, x, y).compile()


def _forbid_checked_call(direct):
    def checked(*args):
        pytest.fail("the compiled call ran where the loaded executable should have")
    direct.compiled = checked


def test_the_direct_call_equals_the_compiled_call_and_skips_it_once_the_weights_are_trusted():
    f, w, x, y, compiled = _program()
    direct = Direct(compiled)
    assert direct.loaded is not None and direct.trusted is None
    want = f(w, x, y)
    first = direct(w, x, y)   # the compiled call: it checks the weights, which are then trusted
    assert direct.trusted is not None
    _forbid_checked_call(direct)
    for got in (first, direct(w, x, y), direct(w, np.asarray(x), np.asarray(y))):   # numpy inputs: one transfer
        assert jax.tree.structure(got) == jax.tree.structure(want)
        np.testing.assert_array_equal(got["sum"], want["sum"])
        np.testing.assert_array_equal(got["y"], want["y"])
        assert got["y"].dtype == jnp.int32


def test_anything_it_cannot_vouch_for_takes_the_compiled_call():
    f, w, x, y, compiled = _program()
    direct = Direct(compiled)
    direct(w, x, y)
    calls = []
    checked = direct.compiled
    direct.compiled = lambda *a: calls.append(1) or checked(*a)
    other = {k: v + 1 for k, v in w.items()}   # other weight arrays: checked, then trusted in their place
    np.testing.assert_array_equal(direct(other, x, y)["sum"], f(other, x, y)["sum"])
    assert len(calls) == 1 and direct.trusted[0] is jax.tree.leaves(other)[0]
    with pytest.raises(TypeError, match="float32"):   # a wrong dtype gets jit's own error, not a reinterpretation
        direct(other, x.astype(jnp.int32), y)
    with pytest.raises(TypeError, match=r"float32\[5\]"):
        direct(other, jnp.arange(5.0), y)
    deleted = jnp.arange(4.0)
    deleted.delete()
    with pytest.raises(RuntimeError, match="deleted"):
        direct(other, deleted, y)
    assert len(calls) == 4
    np.testing.assert_array_equal(direct(other, x, y)["sum"], f(other, x, y)["sum"])
    assert len(calls) == 4


def test_a_program_it_cannot_call_directly_is_left_to_the_compiled_call():
    compiled = jax.jit(lambda w, x: (jax.debug.print("{}", x), x + w)[1]).lower(1.0, 2.0).compile()
    direct = Direct(compiled)
    assert direct.loaded is None   # a host callback
    assert float(direct(1.0, 2.0)) == 3.0
