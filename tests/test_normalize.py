import json

import numpy as np
import pytest
import safetensors.numpy

from pi0_jax import normalize as N

RNG = np.random.default_rng(0)
STATS = N.NormStats(mean=RNG.normal(size=7), std=RNG.uniform(0.1, 2, 7), q01=-RNG.uniform(0.5, 2, 7),
                    q99=RNG.uniform(0.5, 2, 7), min=-RNG.uniform(2, 3, 7), max=RNG.uniform(2, 3, 7))
X = RNG.normal(size=(4, 7))


# Reference formulas, written out independently of the module.
def ref_openpi(x, s, mode):
    if mode == "MEAN_STD":
        return (x - s.mean) / (s.std + 1e-6)
    return (x - s.q01) / (s.q99 - s.q01 + 1e-6) * 2 - 1


def ref_openpi_inv(y, s, mode):
    if mode == "MEAN_STD":
        return y * (s.std + 1e-6) + s.mean
    return (y + 1) / 2 * (s.q99 - s.q01 + 1e-6) + s.q01


def ref_lerobot(x, lo, hi, mode):
    if mode == "MEAN_STD":
        return (x - lo) / (hi + 1e-8)
    d = hi - lo
    d = np.where(d == 0, 1e-8, d)
    return 2 * (x - lo) / d - 1


@pytest.mark.parametrize("mode", ["MEAN_STD", "QUANTILES"])
def test_openpi_formulas(mode):
    y = N.normalize(X, STATS, mode, "openpi")
    np.testing.assert_allclose(y, ref_openpi(X, STATS, mode), rtol=1e-12)
    np.testing.assert_allclose(N.unnormalize(y, STATS, mode, "openpi"), ref_openpi_inv(y, STATS, mode), rtol=1e-12)
    np.testing.assert_allclose(N.unnormalize(y, STATS, mode, "openpi"), X, atol=1e-9)


@pytest.mark.parametrize("mode,lo,hi", [("MEAN_STD", "mean", "std"), ("QUANTILES", "q01", "q99"),
                                        ("MIN_MAX", "min", "max")])
def test_lerobot_formulas(mode, lo, hi):
    a, b = getattr(STATS, lo), getattr(STATS, hi)
    y = N.normalize(X, STATS, mode, "lerobot")
    np.testing.assert_allclose(y, ref_lerobot(X, a, b, mode), rtol=1e-12)
    back = N.unnormalize(y, STATS, mode, "lerobot")
    if mode == "MEAN_STD":  # LeRobot's inverse has no eps
        np.testing.assert_allclose(back, y * b + a, rtol=1e-12)
    else:
        np.testing.assert_allclose(back, (y + 1) * (b - a) / 2 + a, rtol=1e-12)
    np.testing.assert_allclose(back, X, atol=1e-6)


def test_lerobot_eps_only_where_quantiles_are_equal():
    s = N.NormStats(q01=[0.0, 1.0], q99=[2.0, 1.0])
    y = N.normalize(np.array([1.0, 1.5]), s, "QUANTILES", "lerobot")
    np.testing.assert_allclose(y, [0.0, 2 * 0.5 / 1e-8 - 1])
    # openpi adds its eps everywhere
    y = N.normalize(np.array([1.0, 1.5]), s, "QUANTILES", "openpi")
    np.testing.assert_allclose(y, [1.0 / (2 + 1e-6) * 2 - 1, 0.5 / 1e-6 * 2 - 1])


def test_openpi_slicing_and_padding():
    x8 = np.concatenate([X, RNG.normal(size=(4, 25))], axis=-1)  # padded to 32
    # Normalising a shorter vector uses the first dims of the stats.
    np.testing.assert_allclose(N.normalize(X[:, :5], STATS, "QUANTILES", "openpi"),
                               ref_openpi(X, STATS, "QUANTILES")[:, :5])
    # Quantile inverse: first 7 dims transformed, the rest passed through.
    y = N.unnormalize(x8, STATS, "QUANTILES", "openpi")
    np.testing.assert_allclose(y[:, :7], ref_openpi_inv(X, STATS, "QUANTILES"))
    np.testing.assert_array_equal(y[:, 7:], x8[:, 7:])
    # z-score inverse: stats padded with mean 0, std 1 (so the tail is scaled by 1 + 1e-6, as openpi does).
    y = N.unnormalize(x8, STATS, "MEAN_STD", "openpi")
    np.testing.assert_allclose(y[:, :7], ref_openpi_inv(X, STATS, "MEAN_STD"))
    np.testing.assert_allclose(y[:, 7:], x8[:, 7:] * (1 + 1e-6), rtol=1e-15)
    with pytest.raises(ValueError, match="only 7"):
        N.normalize(x8, STATS, "QUANTILES", "openpi", key="state")


def test_identity_and_unsupported():
    np.testing.assert_array_equal(N.normalize(X, N.NormStats(), "IDENTITY", "openpi"), X)
    with pytest.raises(ValueError, match="MIN_MAX"):
        N.normalize(X, STATS, "MIN_MAX", "openpi")
    with pytest.raises(ValueError):
        N.Mode("QUANTILE10")


def test_normalizer_errors_name_key_and_stat():
    with pytest.raises(ValueError, match=r"'state'.*'q01'"):
        N.Normalizer.openpi({"state": N.NormStats(mean=[0.0], std=[1.0])}, use_quantiles=True)
    norm = N.Normalizer.openpi({"state": STATS}, use_quantiles=False)
    with pytest.raises(KeyError, match="actions"):
        norm.unnormalize("actions", X)
    np.testing.assert_array_equal(N.Normalizer.identity().normalize("state", X), X)


def test_openpi_json_roundtrip(tmp_path):
    path = tmp_path / "assets" / "physical-intelligence" / "libero" / "norm_stats.json"
    N.save_openpi_norm_stats(path, {"state": STATS, "actions": STATS})
    raw = json.loads(path.read_text())
    assert set(raw["norm_stats"]["state"]) >= {"mean", "std", "q01", "q99"}
    loaded = N.load_openpi_norm_stats(path)
    np.testing.assert_array_equal(loaded["actions"].q99, STATS.q99)
    assert N.find_norm_stats(tmp_path) == (N.Convention.OPENPI, path)
    norm = N.load_normalizer(tmp_path, use_quantiles=True)
    assert norm.modes["state"] is N.Mode.QUANTILES and norm.dim("actions") == 7
    # old files carry null quantiles
    path.write_text(json.dumps({"norm_stats": {"state": {"mean": [1.0], "std": [2.0], "q01": None, "q99": None}}}))
    assert N.load_openpi_norm_stats(path)["state"].q01 is None


def test_discovery_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="norm_stats.json"):
        N.find_norm_stats(tmp_path)
    for d in ("a", "b"):
        N.save_openpi_norm_stats(tmp_path / "assets" / d / "norm_stats.json", {"state": STATS})
    with pytest.raises(ValueError, match="several"):
        N.find_norm_stats(tmp_path)
    with pytest.raises(FileNotFoundError, match="missing.json"):
        N.load_openpi_norm_stats(tmp_path / "missing.json")


def write_lerobot(directory, *, modes=("QUANTILES", "QUANTILES"), with_state=True, state_name="observation.state"):
    """Processor files in LeRobot's saved layout (DataProcessorPipeline._save_pretrained)."""
    directory.mkdir(parents=True, exist_ok=True)
    features = {state_name: {"type": "STATE", "shape": [8]},
                "observation.images.image": {"type": "VISUAL", "shape": [3, 256, 256]},
                "action": {"type": "ACTION", "shape": [7]}}
    norm_map = {"VISUAL": "IDENTITY", "STATE": modes[0], "ACTION": modes[1]}
    s8 = N.NormStats(mean=RNG.normal(size=8), std=RNG.uniform(0.1, 2, 8), q01=-np.ones(8), q99=np.full(8, 3.0))
    flat = {}
    for name, s in ((state_name, s8), ("action", STATS)):
        for stat, v in s.to_json().items():
            flat[f"{name}.{stat}"] = np.asarray(v, np.float32)
    flat["observation.images.image.mean"] = np.zeros((3, 1, 1), np.float32)
    flat["action.count"] = np.array([1000], np.int64)
    for kind, reg in (("preprocessor", "normalizer_processor"), ("postprocessor", "unnormalizer_processor")):
        idx = 2 if kind == "preprocessor" else 0
        step = {"registry_name": reg, "config": {"eps": 1e-8, "features": features if kind == "preprocessor" else
                                                 {"action": features["action"]}, "norm_map": norm_map}}
        if with_state:
            step["state_file"] = f"policy_{kind}_step_{idx}_{reg}.safetensors"
            safetensors.numpy.save_file(flat, str(directory / step["state_file"]))
        steps = [{"registry_name": "rename_observations_processor", "config": {"rename_map": {}}},
                 {"registry_name": "to_batch_processor", "config": {}}, step] if kind == "preprocessor" else [step]
        (directory / f"policy_{kind}.json").write_text(json.dumps({"name": f"policy_{kind}", "steps": steps}))
    return s8


def test_lerobot_files(tmp_path):
    s8 = write_lerobot(tmp_path, modes=("MEAN_STD", "QUANTILES"), state_name="observation.state_custom")
    norm = N.load_normalizer(tmp_path, use_quantiles=False)  # the files name their own modes
    assert norm.convention is N.Convention.LEROBOT and norm.eps == 1e-8
    assert norm.modes == {"state": N.Mode.MEAN_STD, "actions": N.Mode.QUANTILES}
    x = RNG.normal(size=8)
    # the files store float32 stats; atol covers outputs near zero, where float32 rounding is relatively large
    np.testing.assert_allclose(norm.normalize("state", x), ref_lerobot(x, s8.mean, s8.std, "MEAN_STD"), rtol=1e-6,
                               atol=1e-6)
    y = RNG.normal(size=(10, 7))
    np.testing.assert_allclose(norm.unnormalize("actions", y), (y + 1) * (STATS.q99 - STATS.q01) / 2 + STATS.q01,
                               rtol=1e-6, atol=1e-6)
    assert N.find_norm_stats(tmp_path)[0] is N.Convention.LEROBOT


def test_lerobot_base_model_has_no_stats(tmp_path):
    write_lerobot(tmp_path, with_state=False)
    norm = N.load_lerobot_normalizer(tmp_path)
    with pytest.raises(KeyError, match="'state'.*identity"):
        norm.normalize("state", np.zeros(8))


def test_lerobot_missing_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="policy_preprocessor.json"):
        N.load_lerobot_normalizer(tmp_path)
    write_lerobot(tmp_path)
    (tmp_path / "policy_preprocessor_step_2_normalizer_processor.safetensors").unlink()
    with pytest.raises(FileNotFoundError, match="step_2_normalizer_processor.safetensors"):
        N.load_lerobot_normalizer(tmp_path)
