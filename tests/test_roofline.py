"""`pi0_jax.roofline`: each stage's counted work equals the dot products of the engine's programs, traced at test
sizes after dead-code elimination; the formats follow the weights; the floor at full size is the issue's figure."""

import jax
import numpy as np
import pytest
from jax._src.interpreters import partial_eval as pe
from jax.extend import core as jcore

from pi0_jax import benchmark, roofline
from pi0_jax.config import get_config
from pi0_jax.engine import Engine
from pi0_jax.engine.runtime import shapes


def _dot_flops(jaxpr) -> float:
    """2 x output elements x contracted length, summed over every dot_general (a scan's body times its length)."""
    total = 0.0
    for eqn in jaxpr.eqns:
        if eqn.primitive.name == "dot_general":
            (contract, _), _ = eqn.params["dimension_numbers"]
            lhs = eqn.invars[0].aval.shape
            total += 2.0 * np.prod(eqn.outvars[0].aval.shape) * np.prod([lhs[i] for i in contract])
        if eqn.primitive.name == "while":
            raise AssertionError("a while loop's trip count is not in its jaxpr: trace with the steps unrolled")
        for sub in jcore.jaxprs_in_params(eqn.params):
            total += _dot_flops(sub) * (eqn.params["length"] if eqn.primitive.name == "scan" else 1)
    return total


def _program_flops(engine, stage, batch, steps, cameras, bucket) -> float:
    fn, args = engine._stage(stage, shapes(engine.stage_weights(stage)), batch, steps, cameras, bucket)
    jaxpr = jax.make_jaxpr(fn)(*args).jaxpr
    live, _ = pe.dce_jaxpr(jaxpr, [True] * len(jaxpr.outvars))   # what XLA keeps: the outputs' inputs
    return _dot_flops(live)


@pytest.mark.parametrize("preset,cameras", [("dummy", 3), ("dummy_pi05", 2)])
def test_the_counted_work_is_what_the_engines_programs_compute(preset, cameras):
    config = get_config(preset)
    engine = Engine(config, benchmark.random_params(config, 0), kernels="xla", unroll_steps=True)
    obs, _ = benchmark.make_inputs(config, 2, cameras, 20, 0)
    used, bucket = engine.plan(obs)
    assert len(used) == cameras   # a masked camera is skipped, and so is its work
    works = roofline.call_work(config, 2, cameras, bucket, steps=3)
    assert _program_flops(engine, "encode_images", 2, 0, used, bucket) == works["vision"].flops()
    assert _program_flops(engine, "fill_prefix_cache", 2, 0, used, bucket) == works["prefix"].flops()
    assert _program_flops(engine, "denoise", 2, 3, used, bucket) == works["denoise"].flops()


def test_formats_follow_the_weights():
    config = get_config("dummy")
    params = benchmark.random_params(config, 0)
    assert set(roofline.gemm_formats(Engine(config, params).weights).values()) == {(False, 4)}   # f32 preset
    for scheme, expert in (("every-gemm", (True, 1)), ("all", (False, 1))):   # "all": the expert weight-only
        quantised = benchmark.fp8_params(config, params, scheme, num_steps=2)
        formats = roofline.gemm_formats(Engine(config, quantised).weights)
        assert formats["vlm/gate_up"] == formats["img/fc1"] == formats["img/head"] == (True, 1)
        assert formats["expert/down"] == expert
        assert formats["img/embedding"] == formats["top/action_out_proj"] == (False, 4)


def test_the_floor_at_full_size():
    """π0 at B = 1 on an H200: the denoise step is bound by its weights (0.62 GB of expert, 15 MB of cache: about
    0.13 ms, the issue's floor); the prefix fill's 3.1 TFLOP by the tensor cores, twice as fast in FP8."""
    config = get_config("pi0_base")
    h200 = roofline.peaks_of("NVIDIA H200")
    works = roofline.call_work(config, 1, 3, 48, steps=10)
    bf16 = {name: (False, 2) for name in works["denoise"].gemm_flops | works["prefix"].gemm_flops}
    step = roofline.floor(works["denoise"], bf16, h200, ms=7.7)
    assert step["bound"] == "memory" and 0.635 < step["gb"] / 10 < 0.645 and 0.131 < step["floor_ms"] / 10 < 0.135
    assert 0.16 < step["of_floor"] < 0.18
    prefix = roofline.floor(works["prefix"], bf16, h200, ms=None)
    assert prefix["bound"] == "compute" and 3.0 < prefix["tflop"] < 3.2 and "of_floor" not in prefix
    fp8 = {name: (name.startswith("vlm/"), 1 if name.startswith("vlm/") else 2) for name in bf16}
    assert roofline.floor(works["prefix"], fp8, h200, ms=None)["floor_ms"] < 0.55 * prefix["floor_ms"]
    assert roofline.peaks_of("NVIDIA H100 80GB HBM3").memory == 3.35e12 and roofline.peaks_of("cpu") is None
    assert roofline.peaks_of("NVIDIA GH200 480GB") is None
