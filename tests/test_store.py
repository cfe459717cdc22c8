"""`engine.store.ProgramStore`: compiled programs on disk, keyed by what they are made from."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pi0_jax.engine import store as store_lib
from pi0_jax.engine.store import ProgramStore


@pytest.fixture(autouse=True)
def _on_this_cpu(monkeypatch):
    """The store is off on a CPU (`store.PLATFORMS`); these tests write and read in one process, where it works."""
    monkeypatch.setattr(store_lib, "PLATFORMS", ("cpu", "gpu"))


def _fn(w, x):
    return {"y": jnp.tanh(x @ w["a"] + w["b"])}


def _args(n=4):
    w = {"a": jnp.arange(n * n, dtype=jnp.float32).reshape(n, n) / 10, "b": jnp.ones(n)}
    return w, jnp.linspace(-1, 1, n)


def test_a_stored_program_is_loaded_and_computes_the_same(tmp_path):
    args = _args()
    first = ProgramStore(tmp_path).compile("f", ("v",), _fn, args)
    again = ProgramStore(tmp_path)
    loaded = again.compile("f", ("v",), _fn, args)
    assert again.loaded == 1
    np.testing.assert_array_equal(first(*args)["y"], loaded(*args)["y"])
    with pytest.raises(TypeError, match="Argument types differ"):   # a loaded program still checks its inputs
        loaded(*_args(5))


def test_the_key_names_every_ingredient(tmp_path):
    s, args = ProgramStore(tmp_path), _args()
    base = s.key("f", ("v",), args, None)
    assert base == s.key("f", ("v",), args, {})
    others = {s.key("g", ("v",), args, None), s.key("f", ("w",), args, None), s.key("f", ("v",), _args(5), None),
              s.key("f", ("v",), (args[0], args[1].astype(jnp.bfloat16)), None),
              s.key("f", ("v",), ({"a": args[0]["a"]}, args[1]), None),
              s.key("f", ("v",), args, {"xla_gpu_enable_triton_gemm": False})}
    assert base not in others and len(others) == 6


def test_the_source_digest_is_in_the_key(tmp_path, monkeypatch):
    s, args = ProgramStore(tmp_path), _args()
    base = s.key("f", (), args, None)
    monkeypatch.setattr(store_lib, "source_digest", lambda: "edited")
    assert s.key("f", (), args, None) != base


def test_a_broken_entry_is_reported_removed_and_compiled_again(tmp_path):
    args = _args()
    s = ProgramStore(tmp_path)
    s.compile("f", (), _fn, args)
    (entry,) = tmp_path.glob("f-*.pkl")
    entry.write_bytes(entry.read_bytes()[:100])   # a truncated write from some other tool
    again = ProgramStore(tmp_path)
    with pytest.warns(UserWarning, match="did not load"):
        out = again.compile("f", (), _fn, args)
    assert again.loaded == 0
    np.testing.assert_array_equal(out(*args)["y"], jax.jit(_fn)(*args)["y"])
    assert list(tmp_path.glob("*.tmp")) == []   # the entry was written again, whole
    reread = ProgramStore(tmp_path)
    reread.compile("f", (), _fn, args)
    assert reread.loaded == 1


def test_off_where_the_platform_is_not_listed(tmp_path, monkeypatch):
    monkeypatch.setattr(store_lib, "PLATFORMS", ("gpu",))
    args = _args()
    s = ProgramStore(tmp_path)
    for _ in range(2):
        np.testing.assert_array_equal(s.compile("f", (), _fn, args)(*args)["y"], jax.jit(_fn)(*args)["y"])
    assert s.loaded == 0 and list(tmp_path.iterdir()) == []
