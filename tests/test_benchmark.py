"""The benchmark's CPU smoke test: `pi0-jax benchmark --preset dummy` writes JSON with every stage, and a chart."""

import json

import pytest

from pi0_jax import benchmark, cli


def _benchmark(tmp_path, *args) -> dict:
    """`pi0-jax benchmark --preset dummy ARGS` -> its JSON."""
    out = tmp_path / "bench.json"
    args = ["benchmark", "--preset", "dummy", *args, "--out", str(out), "--cache-dir", str(tmp_path / "xla")]
    assert cli.main(args) == 0
    return json.loads(out.read_text())


def test_benchmark_dummy_writes_every_stage(tmp_path):
    results = _benchmark(tmp_path, "--steps", "1,2", "--batch", "1", "--iters", "2", "--warmup", "1", "--input-sets",
                         "2", "--reference", "--fused-steps", "2", "--one-program")
    assert [(r["batch"], r["steps"]) for r in results["rows"]] == [(1, 1), (1, 2)]
    for row in results["rows"]:
        timed = ("vision", "prefix", "denoise") + (("total", "one_program") if row["steps"] == 2 else ())
        assert ("total" in row) == ("one_program" in row) == (row["steps"] == 2)   # --fused-steps 2 --one-program
        for stage in timed:
            assert row[stage]["median_ms"] > 0 and row[stage]["p90_ms"] >= row[stage]["median_ms"]
        assert row["prompt_bucket"] == 32 and row["cameras"] == 3
        assert row["kernels"] == "xla" and row["attention"] == "vision=xla,prefix=xla,denoise=xla"  # auto, CPU
        assert row["gemm"] == "auto" and set(row["gemm_library"].values()) == {"xla"}
        assert "denoise_attention_launch" not in row   # only where the XLA expert runs the kernel attention
        assert row["overlap"] is False and row["quantised_leaves"] == 0   # auto: only on a GPU
        roof = row["roofline"]["stages"]   # pi0_jax.roofline: the work; no floor on a CPU (no peaks)
        assert list(roof) == ["vision", "prefix", "denoise", "call"] and "peaks" not in row["roofline"]
        assert all(f["tflop"] > 0 and f["gb"] > 0 and "floor_ms" not in f for f in roof.values())
        assert roof["denoise"]["ms"] == row["denoise"]["median_ms"] and ("ms" in roof["call"]) == ("total" in row)
    assert results["peers"][0]["impl"].startswith("reference")
    assert results["peers"][0]["engine_vs_reference"]["rel_l2"] < 1e-2  # bf16, different matmul grouping
    assert results["env"]["device"] and results["env"]["kernels"] == results["env"]["attention"] == "auto"
    assert results["env"]["source"] == benchmark.source_digest() and results["env"]["quant"] == "none"
    assert results["env"]["fp8_mlp_kernel"] is False   # ops.fp8_geglu: on a Hopper GPU only (engine.layers.FP8_GEGLU)
    assert results["env"]["fp8_kernel_from_rows"] == {"prefix_mlp": None, "expert_mlp": None, "vision_fc1": None}
    assert results["env"]["fp8_row_pad"] is True   # engine.programs.FP8_ROW_PAD: the FP8 expert's rows in 16s
    assert results["env"]["pack_attention_input"] is True   # engine.layers.PACK_ATTENTION_INPUT
    assert results["env"]["attention_ends_in_merge"] is True
    assert list(results["compile"]["bfloat16"]["cold_compile_s_call"]) == ["B1_S2"]
    assert (tmp_path / "bench.png").stat().st_size > 1000


def test_a_stopped_benchmark_keeps_the_batches_it_finished(tmp_path, monkeypatch):
    """The JSON is written (atomically) as each batch size is done: a run stopped during its second batch leaves the
    first's rows, marked incomplete; a finished run is marked complete."""
    def bench_engine(engine, args, batch):
        if batch == 2:
            raise KeyboardInterrupt
        return [{"dtype": "bfloat16", "batch": batch, "steps": 1, "total_ms": 1.0}]

    monkeypatch.setattr(benchmark, "bench_engine", bench_engine)
    out = tmp_path / "bench.json"
    args = ["benchmark", "--preset", "dummy", "--steps", "1", "--out", str(out), "--cache-dir", str(tmp_path / "xla")]
    with pytest.raises(KeyboardInterrupt):
        cli.main([*args, "--batch", "1,2"])
    results = json.loads(out.read_text())
    assert results["complete"] is False and [r["batch"] for r in results["rows"]] == [1]
    assert [p.name for p in tmp_path.iterdir() if p.name.endswith(".tmp")] == []
    monkeypatch.setattr(benchmark, "markdown", lambda results: "")   # the table and chart need real rows
    monkeypatch.setattr(benchmark, "chart", lambda results, path: None)
    assert cli.main([*args, "--batch", "1"]) == 0
    assert json.loads(out.read_text())["complete"] is True


def test_benchmark_names_the_denoise_attention_kernels_launch(tmp_path):
    """The XLA expert on the Pallas attention (interpreted here) at B = 8: the row records its launch, folded; and
    the first step beside the prefix fill, asked for (a one-step call peels its only step)."""
    results = _benchmark(tmp_path, "--steps", "1", "--batch", "8", "--iters", "1", "--warmup", "1", "--input-sets",
                         "1", "--attention", "denoise=pallas", "--kernels", "xla", "--overlap", "on")
    (row,) = results["rows"]
    assert row["attention"] == "vision=xla,prefix=xla,denoise=pallas" and row["kernels"] == "xla"
    assert row["overlap"] is True and results["env"]["overlap"] == "on" and row["total"]["median_ms"] > 0
    assert row["denoise_attention_launch"] == {"kv_splits": 2, "splits": 2, "key_blocks_per_split": 7, "kv_block": 64,
                                               "attention_warps": 4, "fold": True, "mosaic": False}


def test_the_pallas_experts_own_attention_is_named_with_its_launch(tmp_path):
    """The Pallas expert (interpreted here; B <= 2 on a GPU by default) runs its own split-key attention, which
    `Attention.at_batch` leaves at the XLA expert's choice: the row names it, with the launch the kernel makes over
    the cache. π0.5's 1,024 prefix keys run in 8 splits of 2 blocks (`expert_attention.key_splits`), π0's 832 in 13
    of 1."""
    from pi0_jax.ops import expert_attention, expert_kernels

    results = _benchmark(tmp_path, "--steps", "2", "--batch", "1", "--iters", "1", "--warmup", "1", "--input-sets",
                         "1", "--kernels", "pallas")
    (row,) = results["rows"]
    assert row["kernels"] == "pallas" and row["attention"] == "vision=xla,prefix=xla,denoise=pallas"
    launch = expert_attention.attention_launch(expert_kernels.default_blocks(), 832)
    assert row["denoise_attention_launch"] == launch and launch["splits"] == 13   # the dummy's cache: 832 keys
    blocks = expert_kernels.Blocks()
    assert [(expert_attention.attention_launch(blocks, keys)["splits"],
             expert_attention.attention_launch(blocks, keys)["key_blocks_per_split"]) for keys in (1024, 832)] == [
        (8, 2), (13, 1)]


def test_benchmark_names_the_weights_scheme(tmp_path):
    """--quant quantises a checkpoint's weights as it does random ones, and the JSON and the table's header name the
    scheme; a checkpoint quantised already is refused a second scheme, by name."""
    from pi0_jax import checkpoint
    from pi0_jax.config import get_config
    from pi0_jax.quant import schemes

    config = get_config("dummy")
    params = benchmark.random_params(config, 0)
    checkpoint.save_checkpoint(tmp_path / "bf16", params, config)
    results = _benchmark(tmp_path, "--checkpoint", str(tmp_path / "bf16"), "--quant", "prefix-mlp", "--steps", "1",
                         "--batch", "1", "--iters", "1", "--warmup", "1", "--input-sets", "1")
    assert results["env"]["quant"] == "prefix-mlp" and "· quant prefix-mlp ·" in benchmark.markdown(results)
    assert results["rows"][0]["quantised_leaves"] == 2   # the VLM's MLP GEMMs, stacked over layers: gate/up, down
    weight_only = schemes.quantize_params(params, "expert-weights", None)
    checkpoint.save_checkpoint(tmp_path / "q", weight_only, config, extra_meta={"quant": {"scheme": "expert-weights"}})
    with pytest.raises(ValueError, match=r"q is already quantised \(expert-weights\): drop --quant prefix-mlp"):
        _benchmark(tmp_path, "--checkpoint", str(tmp_path / "q"), "--quant", "prefix-mlp")


def test_source_digest_names_the_code(tmp_path):
    """The same sources give the same digest wherever they lie; a changed byte or a renamed file changes it."""
    for name in ("a", "b"):
        (tmp_path / name / "ops").mkdir(parents=True)
        (tmp_path / name / "m.py").write_text("x = 1\n")
        (tmp_path / name / "ops" / "k.py").write_text("y = 2\n")
        (tmp_path / name / "notes.txt").write_text(name)   # not a source
    a, b = tmp_path / "a", tmp_path / "b"
    assert benchmark.source_digest(a) == benchmark.source_digest(b) != benchmark.source_digest()
    (b / "ops" / "k.py").write_text("y = 3\n")
    assert benchmark.source_digest(a) != benchmark.source_digest(b)
    (b / "ops" / "k.py").write_text("y = 2\n")
    (b / "ops" / "k.py").rename(b / "ops" / "j.py")
    assert benchmark.source_digest(a) != benchmark.source_digest(b)
