"""The PyTorch -> pi0-jax converter: exact round trips from synthetic openpi / LeRobot files, layout semantics,
full-size planning by shape only, and every bad input (the error names the culprit; nothing is left behind)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import ml_dtypes
import numpy as np
import pytest
from convert_utils import (EMBED, EX, EX_HEAD, LM, LM_HEAD, PROJ, V, flatten, full_size_header, random_params,
                           torch_state_dict, write_safetensors)
from safetensors.numpy import save_file

import converters
from converters import ConversionError
from converters import cli as convert_cli
from converters import detect, table
from pi0_jax.checkpoint import load_checkpoint, read_meta
from pi0_jax.config import get_config

FIXTURES = Path(__file__).parent / "fixtures"


@pytest.fixture(scope="module", autouse=True)
def _memoised_param_shapes():
    """param_shapes traces the whole model (~0.5 s) and is pure in the (frozen, hashable) config: memoise it here
    so the many small conversions of this file stay fast. Callers only read the tree."""
    import functools

    import pi0_jax.pi0

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(pi0_jax.pi0, "param_shapes", functools.lru_cache(maxsize=None)(pi0_jax.pi0.param_shapes))
        yield


@pytest.fixture(scope="module")
def trees():
    """Random param trees per preset: full-precision f32, and bf16-representable (for mixed-dtype sources)."""
    return {(name, exact): random_params(get_config(name), seed=7 + exact, bf16_exact=exact)
            for name in ("dummy", "dummy_pi05") for exact in (False, True)}


def lerobot_config(kind: str, **kw) -> dict:
    cfg = {"type": kind, "chunk_size": 10, "n_action_steps": 10, "max_state_dim": 32, "max_action_dim": 32,
           "tokenizer_max_length": 48 if kind == "pi0" else 200, "paligemma_variant": "dummy",
           "action_expert_variant": "dummy_expert", "dtype": "float32",
           "normalization_mapping": {"STATE": "MEAN_STD", "ACTION": "MEAN_STD", "VISUAL": "IDENTITY"}}
    return cfg | kw


def openpi_config(**kw) -> dict:
    return {"action_dim": 32, "action_horizon": 10, "paligemma_variant": "dummy",
            "action_expert_variant": "dummy_expert", "precision": "float32"} | kw


def make_source(root: Path, trees, preset: str = "dummy", *, exact: bool = False, prefix: str = "",
                shards: int = 1, mixed: bool = False, bf16_keys=(), config: dict | None = None, edit=None,
                **sd_kw) -> Path:
    """Write a synthetic PyTorch checkpoint directory; `edit(sd)` may break the state dict first.
    mixed: every other key (sorted) is stored as bf16, plus `bf16_keys`."""
    cfg = get_config(preset)
    sd = torch_state_dict(trees[preset, exact], cfg, **sd_kw)
    if edit is not None:
        edit(sd)
    bf16 = [*(sorted(sd)[::2] if mixed else ()), *bf16_keys]
    write_safetensors(root, sd, prefix=prefix, shards=shards, bf16=bf16)
    if config is not None:
        (root / "config.json").write_text(json.dumps(config))
    return root


def out_dir(tmp_path: Path) -> Path:
    out = tmp_path / "out"
    out.mkdir(exist_ok=True)
    return out


def assert_tree_equal(expected: dict, got: dict, dtype) -> None:
    e, g = flatten(expected), flatten(got)
    assert sorted(e) == sorted(g)
    for k in e:
        want = np.asarray(e[k]).astype(dtype)
        assert g[k].dtype == want.dtype, k
        assert g[k].shape == want.shape, k
        assert np.array_equal(g[k], want), k


# ------------------------------------------------------------------------------------------------ round trips
ROUND_TRIPS = {
    # openpi's converter: bare keys, embedding only as the tied lm_head, unused expert lm_head, its config.json.
    "openpi_pi0": dict(preset="dummy", config=openpi_config()),
    "openpi_pi05_no_config": dict(preset="dummy_pi05"),
    # LeRobot-saved: `model.` prefix, embed_tokens (alone, or with a *different* lm_head that must lose).
    "lerobot_pi0_embed_tokens": dict(preset="dummy", prefix="model.", embed="embed_tokens",
                                     config=lerobot_config("pi0")),
    "lerobot_pi05_both_embeddings": dict(preset="dummy_pi05", prefix="model.", embed="both",
                                         config=lerobot_config("pi05")),
    "pi0_time_mlp_spelling": dict(preset="dummy", swap_time_spelling=True),
    "pi05_action_time_mlp_spelling": dict(preset="dummy_pi05", swap_time_spelling=True, prefix="model."),
    "no_expert_lm_head": dict(preset="dummy", expert_head=False),
    "sharded_pi05": dict(preset="dummy_pi05", shards=3, config=lerobot_config("pi05")),
    "sharded_pi0_prefixed": dict(preset="dummy", shards=4, prefix="model."),
    "mixed_bf16_fp32_to_float32": dict(preset="dummy_pi05", mixed=True, exact=True),
    "mixed_bf16_fp32_to_bfloat16": dict(preset="dummy", mixed=True, exact=True, dtype="bfloat16"),
    "fp32_to_bfloat16": dict(preset="dummy_pi05", dtype="bfloat16"),
}


@pytest.mark.parametrize("case", list(ROUND_TRIPS))
def test_round_trip_is_exact(case, trees, tmp_path):
    kw = dict(ROUND_TRIPS[case])
    dtype = kw.pop("dtype", "float32")
    preset = kw["preset"]
    src = make_source(tmp_path / "src", trees, **kw)
    dst = converters.convert(src, out_dir(tmp_path) / "ckpt", dtype=dtype)
    config, params = load_checkpoint(dst)
    assert config.name == preset and config.dtype == dtype
    assert config.pi05 == get_config(preset).pi05
    np_dtype = np.dtype(ml_dtypes.bfloat16) if dtype == "bfloat16" else np.dtype(np.float32)
    assert_tree_equal(trees[preset, kw.get("exact", False)], params, np_dtype)
    meta = read_meta(dst)
    assert meta["source_dtypes"] == (["BF16", "F32"] if kw.get("mixed") else ["F32"])
    assert meta["source_format"] == ("lerobot" if kw.get("prefix") or "type" in kw.get("config", {})
                                     else "openpi-pytorch")
    if kw.get("expert_head", True):
        assert EX_HEAD in meta["ignored_keys"]
    if kw.get("embed") == "both":
        assert "superseded" in meta["ignored_keys"][LM_HEAD]
    assert sorted(p.name for p in dst.parent.iterdir()) == ["ckpt"]  # no temp dirs left


def test_config_json_sets_horizon_prompt_length_and_state_tokens(trees, tmp_path):
    src = make_source(tmp_path / "src", trees, "dummy_pi05", prefix="model.",
                      config=lerobot_config("pi05", chunk_size=7, tokenizer_max_length=33))
    config, _ = load_checkpoint(converters.convert(src, out_dir(tmp_path) / "ckpt"))
    assert (config.action_horizon, config.max_token_len) == (7, 33)
    assert config.discrete_state_input  # LeRobot's π0.5 always writes the state into the prompt
    assert config.dtype == "bfloat16"  # the default


def test_preset_flag_overrides_detection(trees, tmp_path):
    src = make_source(tmp_path / "src", trees, "dummy", config=lerobot_config("pi0", chunk_size=7))
    config, _ = load_checkpoint(converters.convert(src, out_dir(tmp_path) / "ckpt", preset="dummy"))
    assert config == get_config("dummy", dtype="bfloat16")  # the preset as is: horizon 10, not 7


def test_assets_are_carried_over(trees, tmp_path):
    src = make_source(tmp_path / "src", trees, "dummy", config=lerobot_config("pi0"))
    stats = {"norm_stats": {"state": {"mean": [0.5], "std": [2.0]}, "actions": {"mean": [1.0], "std": [3.0]}}}
    (src / "assets" / "physical-intelligence" / "libero").mkdir(parents=True)
    (src / "assets" / "physical-intelligence" / "libero" / "norm_stats.json").write_text(json.dumps(stats))
    (src / "policy_preprocessor.json").write_text('{"name": "policy_preprocessor", "steps": []}')
    (src / "policy_postprocessor.json").write_text('{"name": "policy_postprocessor", "steps": []}')
    save_file({"action.mean": np.zeros(7, np.float32)},
              str(src / "policy_preprocessor_step_3_normalizer_processor.safetensors"))
    (src / "tokenizer.model").write_bytes(b"sentencepiece bytes")
    dst = converters.convert(src, out_dir(tmp_path) / "ckpt")
    for rel, orig in [("assets/physical-intelligence/libero/norm_stats.json",
                       "assets/physical-intelligence/libero/norm_stats.json"),
                      ("assets/policy_preprocessor.json", "policy_preprocessor.json"),
                      ("assets/policy_postprocessor.json", "policy_postprocessor.json"),
                      ("assets/policy_preprocessor_step_3_normalizer_processor.safetensors",
                       "policy_preprocessor_step_3_normalizer_processor.safetensors"),
                      ("tokenizer.model", "tokenizer.model"),
                      ("assets/source_config.json", "config.json")]:
        assert (dst / rel).read_bytes() == (src / orig).read_bytes(), rel


def test_layout_semantics_match_pytorch_math(trees, tmp_path):
    """Converted weights compute what the PyTorch modules compute (not just a self-consistent round trip)."""
    cfg = get_config("dummy")
    sd = torch_state_dict(trees["dummy", False], cfg)
    write_safetensors(tmp_path / "src", sd)
    _, p = load_checkpoint(converters.convert(tmp_path / "src", out_dir(tmp_path) / "ckpt", dtype="float32"))
    rng = np.random.default_rng(0)
    # f32 matmuls in different summation orders: a tolerance, not bit equality.
    close = lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-4)  # noqa: E731
    llm, img = p["PaliGemma"]["llm"], p["PaliGemma"]["img"]
    for s, prefix, g in (("", LM, cfg.paligemma), ("_1", EX, cfg.action_expert)):
        x = rng.standard_normal((5, g.width), dtype=np.float32)
        W = lambda n: sd[f"{prefix}.layers.2.{n}.weight"]  # noqa: E731
        close((x @ W("self_attn.q_proj").T).reshape(5, g.num_heads, g.head_dim),
              np.einsum("TD,NDH->TNH", x, llm["layers"]["attn"][f"q_einsum{s}"]["w"][2]))
        kv = np.einsum("TD,SKDH->STKH", x, llm["layers"]["attn"][f"kv_einsum{s}"]["w"][2])
        close((x @ W("self_attn.k_proj").T).reshape(5, 1, g.head_dim), kv[0])
        close((x @ W("self_attn.v_proj").T).reshape(5, 1, g.head_dim), kv[1])
        a = rng.standard_normal((5, g.num_heads, g.head_dim), dtype=np.float32)
        close(a.reshape(5, -1) @ W("self_attn.o_proj").T,
              np.einsum("TNH,NHD->TD", a, llm["layers"]["attn"][f"attn_vec_einsum{s}"]["w"][2]))
        gating = llm["layers"][f"mlp{s}"]["gating_einsum"][2]
        close(x @ W("mlp.gate_proj").T, x @ gating[0])
        close(x @ W("mlp.up_proj").T, x @ gating[1])
        h = rng.standard_normal((5, g.mlp_dim), dtype=np.float32)
        close(h @ W("mlp.down_proj").T, h @ llm["layers"][f"mlp{s}"]["linear"][2])
    # SigLIP attention (with biases) and the patch convolution (torch OIHW on NCHW vs flax HWIO on NHWC).
    sg = cfg.siglip
    x = rng.standard_normal((5, sg.width), dtype=np.float32)
    L, mha = f"{V}.encoder.layers.1.self_attn", img["Transformer"]["encoderblock"]["MultiHeadDotProductAttention_0"]
    close((x @ sd[f"{L}.k_proj.weight"].T + sd[f"{L}.k_proj.bias"]).reshape(5, sg.num_heads, -1),
          np.einsum("TD,DNH->TNH", x, mha["key"]["kernel"][1]) + mha["key"]["bias"][1])
    a = rng.standard_normal((5, sg.num_heads, sg.width // sg.num_heads), dtype=np.float32)
    close(a.reshape(5, -1) @ sd[f"{L}.out_proj.weight"].T + sd[f"{L}.out_proj.bias"],
          np.einsum("TNH,NHD->TD", a, mha["out"]["kernel"][1]) + mha["out"]["bias"][1])
    P = sg.patch_size
    image = rng.standard_normal((2 * P, 3 * P, 3), dtype=np.float32)  # HWC, a 2x3 grid of patches
    patches = image.reshape(2, P, 3, P, 3)  # (gy, p, gx, q, c)
    torch_out = np.einsum("ypxqc,ocpq->yxo", patches, sd[f"{V}.embeddings.patch_embedding.weight"])
    close(torch_out, np.einsum("ypxqc,pqco->yxo", patches, img["embedding"]["kernel"]))
    close(x @ sd[f"{PROJ}.linear.weight"].T, x @ img["head"]["kernel"])


@pytest.mark.parametrize("preset,n_keys", [("pi0_base", 777), ("pi05_base", 812)])
def test_full_size_checkpoints_plan_by_shape_only(preset, n_keys):
    """Full-size openpi files (headers built by eval_shape, nothing allocated) are detected and fully planned."""
    header = full_size_header(preset)
    assert len(header) == n_keys  # spec §11.2's inferred key counts
    config, evidence = detect.detect(header, None, lerobot=False, dtype="bfloat16")
    assert config == get_config(preset, dtype="bfloat16") and evidence["preset"] == preset
    plan = table.make_plan(config, header)
    assert plan.ignored.keys() == {EX_HEAD}
    consumed = {k for step in plan.steps for ks in step.keys for k in ks}
    assert consumed | plan.ignored.keys() == header.keys()
    # A LeRobot pi05 config with horizon 10 picks the preset that already has it.
    if config.pi05:
        config, evidence = detect.detect(header, {"type": "pi05", "chunk_size": 10}, lerobot=True, dtype="float32")
        assert evidence["preset"] == "pi05_libero" and config.action_horizon == 10 and config.discrete_state_input


# ------------------------------------------------------------------------------------------------ bad inputs
def _del(*keys):
    def edit(sd):
        for k in keys:
            del sd[k]
    return edit


def _set(key, fn):
    def edit(sd):
        sd[key] = fn(sd[key])
    return edit


def _poison(key, value):
    def fn(x):
        x = x.copy()
        x.flat[3] = value
        return x
    return _set(key, fn)


EXO = f"{EX}.layers.2.self_attn.o_proj.weight"
# name -> (make_source kwargs, convert kwargs, substrings the message must contain)
BAD = {
    "missing_key": (dict(edit=_del(f"{EX}.layers.1.mlp.up_proj.weight")), {},
                    ["missing 1 key", f"{EX}.layers.1.mlp.up_proj.weight"]),
    "missing_embedding": (dict(edit=_del(LM_HEAD)), {}, [EMBED, LM_HEAD]),
    "missing_detection_key": (dict(edit=_del(f"{V}.embeddings.position_embedding.weight")), {},
                              [f"{V}.embeddings.position_embedding.weight"]),
    "unexpected_key": (dict(edit=lambda sd: sd.update({f"{LM}.layers.0.self_attn.q_norm.weight": np.ones(16)})), {},
                       ["unexpected 1 key", f"{LM}.layers.0.self_attn.q_norm.weight"]),
    "stray_layer_key": (dict(edit=lambda sd: sd.update({f"{EX}.layers.3.mlp.down_proj.weight": np.ones((48, 96))})),
                        {}, ["unexpected", f"{EX}.layers.3.mlp.down_proj.weight"]),
    "wrong_shape": (dict(edit=_set(EXO, lambda x: x.T.copy())), {}, [EXO, "(64, 48)", "(48, 64)"]),
    "wrong_shape_bias": (dict(edit=_set("action_out_proj.bias", lambda x: x[:-1].copy())), {},
                         ["action_out_proj.bias", "(31,)", "(32,)"]),
    "action_dims_disagree": (dict(edit=_set("action_out_proj.weight", lambda x: x[:-2].copy())), {},
                             ["action_in_proj.weight", "action_out_proj.weight", "(30, 48)"]),
    "nan": (dict(edit=_poison(f"{EX}.layers.1.mlp.down_proj.weight", np.nan)), {},
            [f"{EX}.layers.1.mlp.down_proj.weight", "1 NaN"]),
    "inf": (dict(edit=_poison(f"{V}.encoder.layers.0.mlp.fc1.bias", -np.inf)), {},
            [f"{V}.encoder.layers.0.mlp.fc1.bias", "1 Inf"]),
    "nan_in_bf16_tensor": (dict(bf16_keys=[f"{LM}.norm.weight"], edit=_poison(f"{LM}.norm.weight", np.nan)), {},
                           [f"{LM}.norm.weight", "NaN"]),
    "nan_in_prefixed_file": (dict(prefix="model.", edit=_poison("state_proj.bias", np.nan)), {},
                             ["model.state_proj.bias", "NaN"]),
    "int_tensor": (dict(edit=_set("state_proj.bias", lambda x: x.astype(np.int32))), {}, ["state_proj.bias", "I32"]),
    "unknown_type": (dict(config=lerobot_config("smolvla")), {}, ["unknown variant", "smolvla"]),
    "unknown_variant_name": (dict(config=openpi_config(paligemma_variant="gemma_7b")), {},
                             ["unknown variant", "paligemma_variant='gemma_7b'"]),
    "unknown_variant_shapes": (dict(edit=lambda sd: sd.update(
        {k: (v[:80] if "gate_proj" in k or "up_proj" in k else v[:, :80]) for k, v in sd.items()
         if k.startswith(f"{LM}.layers.") and ".mlp." in k})), {},
        ["unknown variant", f"{LM}.layers.0.self_attn.q_proj.weight", "match no known Gemma variant"]),
    "variant_name_disagrees_with_shapes": (dict(config=openpi_config(paligemma_variant="gemma_2b")), {},
                                           ["paligemma_variant='gemma_2b'", "(64, 64)"]),
    "type_disagrees_with_keys": (dict(preset="dummy_pi05", config=lerobot_config("pi0")), {},
                                 ["type='pi0'", "π0.5", "dense"]),
    "cannot_tell_pi0_from_pi05": (dict(edit=lambda sd: [sd.pop(k) for k in list(sd)
                                                        if k.startswith(f"{EX}.") and "norm" in k
                                                        or k.startswith("state_proj")]), {}, ["cannot tell"]),
    "two_time_spellings": (dict(edit=lambda sd: sd.update({"time_mlp_in.weight": sd["action_time_mlp_in.weight"],
                                                             "time_mlp_in.bias": sd["action_time_mlp_in.bias"]})),
                           {}, ["action_time_mlp_in.weight", "time_mlp_in.weight", "two spellings"]),
    "preset_does_not_fit": (dict(), dict(preset="pi0_base"), ["--preset 'pi0_base'", "paligemma_variant"]),
    "preset_wrong_model": (dict(), dict(preset="dummy_pi05"), ["--preset 'dummy_pi05'", "pi05"]),
    "mem_feature": (dict(config=lerobot_config("pi0", use_proprioceptive_memory=True)), {},
                    ["use_proprioceptive_memory", "config.json"]),
    "bad_dtype": (dict(), dict(dtype="float16"), ["float16"]),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_input_is_named_and_leaves_nothing(case, trees, tmp_path):
    src_kw, kw, needles = BAD[case]
    src = make_source(tmp_path / "src", trees, **src_kw)
    out = out_dir(tmp_path)
    with pytest.raises(ConversionError) as err:
        converters.convert(src, out / "ckpt", **kw)
    for needle in needles:
        assert needle in str(err.value), (needle, str(err.value))
    assert list(out.iterdir()) == []


def _convert_fails(src, tmp_path, *needles, **kw) -> str:
    out = out_dir(tmp_path)
    with pytest.raises(ConversionError) as err:
        converters.convert(src, out / "ckpt", **kw)
    for needle in needles:
        assert str(needle) in str(err.value), (needle, str(err.value))
    assert list(out.iterdir()) == []
    return str(err.value)


def test_duplicate_key_with_and_without_prefix(trees, tmp_path):
    src = make_source(tmp_path / "src", trees)
    save_file({**{k: v for k, v in _read(src / "model.safetensors").items()},
               "model.state_proj.bias": np.zeros(48, np.float32)}, str(src / "model.safetensors"))
    _convert_fails(src, tmp_path, "state_proj.bias", "model.state_proj.bias", "twice")


def _read(path):
    from safetensors.numpy import load_file
    return load_file(str(path))


def test_truncated_file(trees, tmp_path):
    src = make_source(tmp_path / "src", trees)
    f = src / "model.safetensors"
    f.write_bytes(f.read_bytes()[:-1000])
    _convert_fails(src, tmp_path, f, "truncated")


def test_truncated_shard(trees, tmp_path):
    src = make_source(tmp_path / "src", trees, shards=3)
    shard = src / "model-00002-of-00003.safetensors"
    shard.write_bytes(shard.read_bytes()[:-10])
    _convert_fails(src, tmp_path, shard, "truncated")


def test_index_names_a_missing_shard(trees, tmp_path):
    src = make_source(tmp_path / "src", trees, shards=3)
    (src / "model-00003-of-00003.safetensors").unlink()
    _convert_fails(src, tmp_path, "model-00003-of-00003.safetensors", "missing")


def test_index_disagrees_with_shards(trees, tmp_path):
    src = make_source(tmp_path / "src", trees, shards=2)
    index = json.loads((src / "model.safetensors.index.json").read_text())
    index["weight_map"]["action_in_proj.bias"] = "model-00002-of-00002.safetensors"
    index["weight_map"]["ghost.weight"] = "model-00001-of-00002.safetensors"
    (src / "model.safetensors.index.json").write_text(json.dumps(index))
    _convert_fails(src, tmp_path, "action_in_proj.bias")


@pytest.mark.parametrize("content,needle", [(b"this is not a safetensors file at all", "not a safetensors file"),
                                            (b"", "not a safetensors file"),
                                            (b"PK\x03\x04" + bytes(100), "torch pickle")])
def test_not_a_safetensors_file(content, needle, tmp_path):
    (tmp_path / "src").mkdir()
    (tmp_path / "src" / "model.safetensors").write_bytes(content)
    _convert_fails(tmp_path / "src", tmp_path, tmp_path / "src" / "model.safetensors", needle)


@pytest.mark.parametrize("name", ["pytorch_model.bin", "model.pt", "weights.pth"])
@pytest.mark.parametrize("as_file", [False, True])
def test_pickle_is_refused_without_allow_pickle(name, as_file, tmp_path):
    (tmp_path / "src").mkdir()
    pickle = tmp_path / "src" / name
    pickle.write_bytes(b"\x80\x04 not loaded: refused before reading")
    _convert_fails(pickle if as_file else tmp_path / "src", tmp_path, pickle, "--allow-pickle")


def test_allow_pickle_without_torch_says_so(tmp_path):
    try:
        import torch  # noqa: F401
        pytest.skip("torch is installed")
    except ImportError:
        pass
    (tmp_path / "src").mkdir()
    (tmp_path / "src" / "model.pt").write_bytes(b"\x80\x04")
    _convert_fails(tmp_path / "src", tmp_path, "model.pt", "torch is not installed", allow_pickle=True)


def test_allow_pickle_round_trip(trees, tmp_path):
    torch = pytest.importorskip("torch")
    cfg = get_config("dummy")
    sd = torch_state_dict(trees["dummy", False], cfg)
    (tmp_path / "src").mkdir()
    torch.save({k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in sd.items()}, tmp_path / "src" / "model.pt")
    _, params = load_checkpoint(converters.convert(tmp_path / "src", out_dir(tmp_path) / "ckpt", dtype="float32",
                                                   allow_pickle=True))
    assert_tree_equal(trees["dummy", False], params, np.dtype(np.float32))


def test_missing_source(tmp_path):
    _convert_fails(tmp_path / "nope", tmp_path, tmp_path / "nope", "does not exist")
    (tmp_path / "empty").mkdir()
    _convert_fails(tmp_path / "empty", tmp_path, tmp_path / "empty", "model.safetensors")


def test_destination_exists_is_refused_then_overwritten_atomically(trees, tmp_path):
    out = out_dir(tmp_path)
    dst = out / "ckpt"
    converters.convert(make_source(tmp_path / "a", trees, "dummy"), dst, dtype="float32")
    (dst / "marker").write_text("old")
    src_b = make_source(tmp_path / "b", trees, "dummy", exact=True)
    with pytest.raises(ConversionError) as err:
        converters.convert(src_b, dst)
    assert str(dst) in str(err.value) and "--overwrite" in str(err.value)
    assert (dst / "marker").read_text() == "old" and sorted(p.name for p in out.iterdir()) == ["ckpt"]

    converters.convert(src_b, dst, dtype="float32", overwrite=True)
    assert not (dst / "marker").exists()
    _, params = load_checkpoint(dst)
    assert_tree_equal(trees["dummy", True], params, np.dtype(np.float32))
    assert sorted(p.name for p in out.iterdir()) == ["ckpt"]  # no .tmp / .old dirs left


def test_overwrite_refuses_what_is_not_a_checkpoint(trees, tmp_path):
    src = make_source(tmp_path / "src", trees)
    precious = out_dir(tmp_path) / "ckpt"
    precious.mkdir()
    (precious / "thesis.tex").write_text("do not delete")
    with pytest.raises(ConversionError, match="not a pi0-jax checkpoint"):
        converters.convert(src, precious, overwrite=True)
    assert (precious / "thesis.tex").read_text() == "do not delete"
    with pytest.raises(ConversionError, match="source or contains it"):
        converters.convert(src, src, overwrite=True)
    with pytest.raises(ConversionError, match="source or contains it"):
        converters.convert(src / "model.safetensors", tmp_path, overwrite=True)
    assert (src / "model.safetensors").is_file()


def test_failure_while_writing_leaves_nothing(trees, tmp_path, monkeypatch):
    import pi0_jax.checkpoint as ckpt

    def broken_save(path, params):
        Path(path).mkdir()
        (Path(path) / "half-written").write_text("x")
        raise OSError("disk full")

    monkeypatch.setattr(ckpt, "save_params", broken_save)
    out = out_dir(tmp_path)
    with pytest.raises(OSError, match="disk full"):
        converters.convert(make_source(tmp_path / "src", trees), out / "ckpt")
    assert list(out.iterdir()) == []


# ------------------------------------------------------------------------------------------------ CLI
def test_cli_help_explains_every_flag(capsys):
    parser = argparse.ArgumentParser(prog="pi0-jax")
    sub = parser.add_subparsers(dest="command")
    convert_cli.add_convert_parser(sub)
    with pytest.raises(SystemExit):
        parser.parse_args(["convert", "--help"])
    text = capsys.readouterr().out
    for flag in ("SRC", "DST", "--dtype", "--preset", "--overwrite", "--allow-pickle", "bfloat16", "pi05_base"):
        assert flag in text
    args = parser.parse_args(["convert", "a", "b", "--dtype", "float32", "--allow-pickle"])
    assert args.func is convert_cli.run and args.dtype == "float32" and args.allow_pickle and not args.overwrite


def test_cli_runs_and_reports_errors(trees, tmp_path, capsys):
    src = make_source(tmp_path / "src", trees, "dummy_pi05")
    dst = out_dir(tmp_path) / "ckpt"
    assert convert_cli.main([str(src), str(dst), "--dtype", "float32"]) == 0
    assert (dst / "params").is_dir()
    assert convert_cli.main([str(src), str(dst)]) == 1
    assert "already exists" in capsys.readouterr().err
    assert convert_cli.main([str(src), str(dst), "--overwrite"]) == 0


# ------------------------------------------------------------------------------------------------ LeRobot fixtures
@pytest.mark.parametrize("name", ["lerobot_pi0", "lerobot_pi05"])
def test_real_lerobot_fixture(name, tmp_path):
    """A checkpoint written by LeRobot's own save_pretrained (scripts/make_lerobot_fixtures.py): every leaf is
    produced, and mapping the result back with the independent spec §11.2 helper gives the file's tensors."""
    from safetensors.numpy import load_file

    from convert_utils import to_torch

    src = FIXTURES / name
    if not (src / "model.safetensors").exists():
        pytest.skip(f"{src} not generated (scripts/make_lerobot_fixtures.py)")
    dst = converters.convert(src, tmp_path / "ckpt", dtype="float32")
    config, params = load_checkpoint(dst)  # check_params: every leaf present, with its shape
    assert config.pi05 == (name == "lerobot_pi05") and config.name == ("dummy_pi05" if config.pi05 else "dummy")
    meta = read_meta(dst)
    assert meta["source_format"] == "lerobot"
    assert set(meta["ignored_keys"]) == {EX_HEAD, LM_HEAD}  # LeRobot saves both embeddings, untied

    source = {k.removeprefix("model."): v for k, v in load_file(str(src / "model.safetensors")).items()}
    back = {k: np.asarray(v) for k, v in to_torch(params, config.pi05).items()}
    back[EMBED] = back.pop(LM_HEAD)  # the embedding came from embed_tokens, not the (different) lm_head
    assert back.keys() == source.keys() - {EX_HEAD, LM_HEAD}
    for k, v in back.items():
        assert np.array_equal(v, source[k]), k
    for f in ["config.json", "policy_preprocessor.json", "policy_postprocessor.json"]:
        assert (src / f).is_file() == (dst / "assets" / ("source_config.json" if f == "config.json" else f)).is_file()
