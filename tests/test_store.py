"""`engine.store.ProgramStore`: compiled programs on disk, keyed by what they are made from."""

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pi0_jax.engine import store as store_lib
from pi0_jax.engine.store import ProgramStore


@pytest.fixture(autouse=True)
def _on_this_cpu(monkeypatch):
    """The store is off on a CPU (`store.PLATFORMS`). Here it is on; no loaded program runs in this process (the one
    that does is replaced by a stand-in), since on a CPU that may fail after other compiles (the module doc)."""
    monkeypatch.setattr(store_lib, "PLATFORMS", ("cpu", "gpu"))


def _fn(w, x):
    return {"y": jnp.tanh(x @ w["a"] + w["b"])}


def _args(n=4):
    w = {"a": jnp.arange(n * n, dtype=jnp.float32).reshape(n, n) / 10, "b": jnp.ones(n)}
    return w, jnp.linspace(-1, 1, n)


_CHILD = textwrap.dedent("""
    import json, sys
    import jax, jax.numpy as jnp
    sys.path.insert(0, sys.argv[2])
    from pi0_jax.engine import store
    from test_store import _args, _fn
    store.PLATFORMS = ("cpu",)
    s = store.ProgramStore(sys.argv[1])
    program = s.compile("f", ("v",), _fn, _args())
    out = {"loaded": s.loaded, "y": program(*_args())["y"].tolist(), "outs": repr(store.shapes(program.out_info))}
    try:
        program(*_args(5))
    except TypeError as e:   # a loaded program still checks its inputs
        out["error"] = str(e)[:40]
    print(json.dumps(out))
""")


def test_a_stored_program_is_loaded_by_a_second_process_and_computes_the_same(tmp_path):
    """Each process fresh: on a CPU a program written or read after other compiles may not run (the module doc)."""
    runs = [json.loads(subprocess.run([sys.executable, "-c", _CHILD, str(tmp_path), str(Path(__file__).parent)],
                                      check=True, capture_output=True, text=True).stdout.strip().splitlines()[-1])
            for _ in range(2)]
    assert [r["loaded"] for r in runs] == [0, 1]
    np.testing.assert_array_equal(runs[0]["y"], runs[1]["y"])
    # the outputs' shapes are read off the loaded executable as off the compiled one (`Engine`'s third program)
    assert runs[0]["outs"] == runs[1]["outs"] == repr({"y": jax.ShapeDtypeStruct((4,), jnp.float32)})
    np.testing.assert_allclose(runs[1]["y"], np.asarray(jax.jit(_fn)(*_args())["y"]), rtol=1e-6)
    assert all(r["error"].startswith("Argument types differ") for r in runs)


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


def test_xla_flags_precision_and_sharding_are_in_the_key(tmp_path, monkeypatch):
    s, args = ProgramStore(tmp_path), _args()
    base = s.key("f", (), args, None)
    with monkeypatch.context() as m:
        m.setenv("XLA_FLAGS", (os.environ.get("XLA_FLAGS", "") + " --xla_dump_to=/nowhere").strip())
        flags = s.key("f", (), args, None)
    with jax.default_matmul_precision("highest"):
        precision = s.key("f", (), args, None)
    mesh = jax.sharding.Mesh(np.array(jax.devices()[:1]), ("b",))
    sharded = jax.device_put(args, jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec()))
    assert len({base, flags, precision, s.key("f", (), sharded, None)}) == 4
    assert s.key("f", (), args, None) == base      # each change undone: the same key again


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


def test_a_loaded_program_that_fails_to_run_is_compiled_again(tmp_path, monkeypatch):
    """The CPU failure that keeps the store off there ("Function ... not found" at dispatch), simulated: the first call
    of a loaded program that fails is retried on a fresh compile, which is written over its entry (the failure is
    the process's): a later store loads it (not run here: the fixture says why)."""
    args = _args()
    ProgramStore(tmp_path).compile("f", (), _fn, args)
    load = store_lib.serialize_executable.deserialize_and_load

    def broken(*a):
        raise jax.errors.JaxRuntimeError("INTERNAL: Error dispatching computation: Function fusion not found")

    monkeypatch.setattr(store_lib.serialize_executable, "deserialize_and_load", lambda *a, **k: broken)
    s = ProgramStore(tmp_path)
    loaded = s.compile("f", (), _fn, args)
    assert s.loaded == 1
    [entry] = tmp_path.glob("*.pkl")
    entry.write_bytes(b"stale")
    with pytest.warns(UserWarning, match="failed to run"):
        out = loaded(*args)
    np.testing.assert_array_equal(out["y"], jax.jit(_fn)(*args)["y"])
    np.testing.assert_array_equal(loaded(*args)["y"], out["y"])
    assert list(tmp_path.glob("*.pkl")) == [entry] and entry.read_bytes() != b"stale"
    monkeypatch.setattr(store_lib.serialize_executable, "deserialize_and_load", load)
    again = ProgramStore(tmp_path)
    again.compile("f", (), _fn, args)
    assert again.loaded == 1


def test_a_program_compiled_again_runs_where_its_entry_cannot_be_written(tmp_path, monkeypatch):
    """A read-only store: the failed program's fresh compile is not written back, and the call still runs."""
    args = _args()
    ProgramStore(tmp_path).compile("f", (), _fn, args)

    def broken(*a):
        raise jax.errors.JaxRuntimeError("INTERNAL: Error dispatching computation: Function fusion not found")

    def read_only(self, path, data):
        raise PermissionError(13, "Permission denied", str(path))

    monkeypatch.setattr(store_lib.serialize_executable, "deserialize_and_load", lambda *a, **k: broken)
    monkeypatch.setattr(ProgramStore, "_write", read_only)
    loaded = ProgramStore(tmp_path).compile("f", (), _fn, args)
    with pytest.warns(UserWarning) as said:
        out = loaded(*args)
    assert ["failed to run" in str(w.message) for w in said] == [True, False]
    assert "could not write" in str(said[1].message)
    np.testing.assert_array_equal(out["y"], jax.jit(_fn)(*args)["y"])


def test_a_loaded_program_that_runs_out_of_memory_keeps_its_entry(tmp_path, monkeypatch):
    args = _args()
    ProgramStore(tmp_path).compile("f", (), _fn, args)

    def oom(*a):
        raise jax.errors.JaxRuntimeError("RESOURCE_EXHAUSTED: Out of memory while trying to allocate 64 GiB")

    monkeypatch.setattr(store_lib.serialize_executable, "deserialize_and_load", lambda *a, **k: oom)
    loaded = ProgramStore(tmp_path).compile("f", (), _fn, args)
    with pytest.raises(jax.errors.JaxRuntimeError, match="RESOURCE_EXHAUSTED"):
        loaded(*args)
    assert len(list(tmp_path.glob("*.pkl"))) == 1


def test_the_store_prunes_entries_unused_for_max_age_days(tmp_path):
    """A write removes entries neither loaded nor written for max_age_days and a killed writer's temporary files over
    a day old; fresh entries, other files and a store without a directory are left alone."""
    import os
    import time

    s = ProgramStore(tmp_path / "programs", max_age_days=2)
    assert s.prune() == []   # no directory yet
    s.root.mkdir()
    now = time.time()
    ages = {"old-1.pkl": 3, "fresh-2.pkl": 1, "left.pkl.tmp": 1.5, "new.pkl.tmp": 0.5, "notes.txt": 9}
    for name, days in ages.items():
        (s.root / name).write_bytes(b"x")
        os.utime(s.root / name, (now - days * 86400, now - days * 86400))
    assert sorted(p.name for p in s.prune(now)) == ["left.pkl.tmp", "old-1.pkl"]
    assert sorted(p.name for p in s.root.iterdir()) == ["fresh-2.pkl", "new.pkl.tmp", "notes.txt"]
    program = s.compile("f", ("v",), _fn, _args())   # a write prunes too
    assert len(list(s.root.glob("f-*.pkl"))) == 1 and program is not None
    os.utime(s.root / "fresh-2.pkl", (now - 5 * 86400, now - 5 * 86400))
    s.compile("f", ("w",), _fn, _args())
    assert not (s.root / "fresh-2.pkl").exists() and len(list(s.root.glob("f-*.pkl"))) == 2
