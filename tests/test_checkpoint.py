"""Checkpoint I/O: openpi's orbax `params/` loads without conversion; our format round-trips; errors name the file."""

import json

import jax
import numpy as np
import orbax.checkpoint as ocp
import pytest
from flax import traverse_util

from pi0_jax import checkpoint, pi0
from pi0_jax.config import get_config


@pytest.fixture(scope="module")
def params():
    leaves, treedef = jax.tree.flatten(pi0.param_shapes(get_config("dummy_pi05")))   # shapes: values are redrawn
    rng = np.random.default_rng(0)
    return jax.tree.unflatten(treedef, [rng.normal(size=x.shape).astype(np.float32) for x in leaves])


def assert_same(a, b):
    fa, fb = traverse_util.flatten_dict(a, sep="/"), traverse_util.flatten_dict(b, sep="/")
    assert fa.keys() == fb.keys()
    for k in fa:
        np.testing.assert_array_equal(np.asarray(fa[k], np.float32), np.asarray(fb[k], np.float32), err_msg=k)


@pytest.mark.parametrize("training_layout", [False, True])
def test_openpi_params_dir_loads_without_conversion(tmp_path, params, training_layout):
    """openpi writes {"params": tree} with orbax's PyTreeCheckpointer; training saves wrap each leaf in `value`."""
    tree = jax.tree.map(lambda x: {"value": x}, params) if training_layout else params
    with ocp.PyTreeCheckpointer() as ckptr:
        ckptr.save(tmp_path / "ckpt" / "params", {"params": tree})
    config, loaded = checkpoint.load_openpi_params(tmp_path / "ckpt", dtype="bfloat16")
    assert config.name == "dummy_pi05"  # matched by shapes: openpi params carry no config
    assert jax.tree.leaves(loaded)[0].dtype == np.dtype("bfloat16")
    assert_same(jax.tree.map(lambda x: x.astype("bfloat16"), params), loaded)
    _, loaded = checkpoint.load_openpi_params(tmp_path / "ckpt" / "params", preset="dummy_pi05")
    assert_same(params, loaded)


def test_save_load_round_trip_and_meta(tmp_path, params):
    config = get_config("dummy_pi05")
    dst = checkpoint.save_checkpoint(tmp_path / "ck", params, config, assets={"norm_stats.json": b"{}"},
                                     extra_meta={"source": "test"})
    meta = json.loads((dst / "config.json").read_text())
    assert meta["format"] == "pi0-jax" and meta["source"] == "test" and meta["params_dtype"] == "float32"
    assert (dst / "assets" / "norm_stats.json").read_bytes() == b"{}"
    loaded_config, loaded = checkpoint.load_checkpoint(dst)
    assert loaded_config == config
    assert_same(params, loaded)


def test_wrong_params_are_named_and_nothing_is_written(tmp_path, params):
    flat = traverse_util.flatten_dict(params, sep="/")
    del flat["action_out_proj/bias"]
    flat["PaliGemma/llm/final_norm/scale"] = np.zeros(7, np.float32)
    bad = traverse_util.unflatten_dict(flat, sep="/")
    with pytest.raises(ValueError) as e:
        checkpoint.save_checkpoint(tmp_path / "ck", bad, get_config("dummy_pi05"))
    assert "missing action_out_proj/bias" in str(e.value)
    assert "PaliGemma/llm/final_norm/scale: (7,), expected (64,)" in str(e.value)
    assert list(tmp_path.iterdir()) == []


def test_not_a_checkpoint(tmp_path):
    with pytest.raises(FileNotFoundError, match="config.json"):
        checkpoint.load_checkpoint(tmp_path)
    (tmp_path / "config.json").write_text('{"type": "pi05"}')
    with pytest.raises(ValueError, match="not a pi0-jax config"):
        checkpoint.load_checkpoint(tmp_path)
