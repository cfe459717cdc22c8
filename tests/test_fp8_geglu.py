"""The FP8 MLP kernel (`pi0_jax.ops.fp8_geglu`: gate/up GEMM, GeGLU and the down GEMM's e4m3 input in one Mosaic
GPU kernel, its CPU interpreter here) equals its XLA form bit for bit, stays within one e4m3 step of the engine's XLA
path, and the engine's FP8 call with it (`engine.layers.FP8_GEGLU`) matches the call without it."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pi0_jax import benchmark
from pi0_jax.config import get_config
from pi0_jax.engine import Engine, layers
from pi0_jax.ops import formats, fp8_geglu, layout
from pi0_jax.ops.fp8_geglu import Launch
from pi0_jax.quant import schemes


def _operands(m, k, f, down_scale):
    key = jax.random.key(m + k + f)
    x = jax.random.normal(key, (m, k), jnp.float32)
    w = jax.random.normal(jax.random.fold_in(key, 1), (2 * f, k), jnp.float32) * k**-0.5
    gate_up = formats.quantize_fp8(w, contract=(-1,), act_scale=formats.act_scale_from_amax(np.abs(x).max()))
    down = formats.quantize_fp8(jnp.ones((8, f)), contract=(-1,), act_scale=down_scale)
    return formats.quantise(x, gate_up.act_scale), gate_up, down


@pytest.mark.parametrize("m,k,f,launch", [(200, 256, 128, Launch()),   # 2 warpgroups, 2 K steps, a partial row tile
                                          (128, 64, 160, Launch()),    # the dummy prefix's MLP: one warpgroup
                                          (130, 128, 256, Launch(stages=2, delay=1, minor=1, snake=2))])
def test_kernel_equals_its_xla_form(m, k, f, launch):
    xq, gate_up, down = _operands(m, k, f, 0.01)
    assert fp8_geglu.applies(gate_up, down)
    got = fp8_geglu.geglu(xq, gate_up, down.act_scale, launch)
    want = fp8_geglu.reference(xq, gate_up, down.act_scale)
    assert got.shape == (m, f) and got.dtype == formats.E4M3
    np.testing.assert_array_equal(np.asarray(got, np.float32), np.asarray(want, np.float32))
    assert np.abs(np.asarray(want, np.float32)).max() == formats.E4M3_MAX   # some outputs saturate
    # the engine's XLA path (gate and up scaled, GeGLU, then divided by the down GEMM's scale): one e4m3 step at most
    y = jnp.einsum("md,nd->mn", xq, gate_up.q, preferred_element_type=jnp.float32)
    gate, up = layout.split_gate_up(y * formats.output_scale("...D,FD->...F", gate_up))
    xla = np.asarray(formats.quantise(layers.gelu_tanh(gate) * up, down.act_scale), np.float32)
    g = np.asarray(got, np.float32)
    assert np.all(np.abs(g - xla) <= np.maximum(np.abs(xla), 2.0**-6) / 8 + 1e-6)
    assert np.mean(g == xla) > 0.95
    swapped = fp8_geglu.reference(xq, formats.QArray(gate_up.q[::-1], gate_up.scale[::-1], gate_up.act_scale,
                                                     gate_up.contract), down.act_scale)
    assert not np.array_equal(g, np.asarray(swapped, np.float32))


def test_applies_only_to_fp8_x_fp8_weights_that_tile():
    _, gate_up, down = _operands(64, 128, 128, 0.1)
    assert fp8_geglu.applies(gate_up, down)
    assert not fp8_geglu.applies(formats.QArray(gate_up.q, gate_up.scale, None, (-1,)), down)   # weight-only
    assert not fp8_geglu.applies(gate_up.q.astype(jnp.float32), down)
    assert not fp8_geglu.applies(formats.QArray(gate_up.q, gate_up.scale, gate_up.act_scale, (-2,)), down)
    assert fp8_geglu.fit(Launch(), 48, 192) is None   # K = 48: no e4m3 wgmma step divides it


def test_engine_fp8_call_with_the_kernel_matches_the_call_without(monkeypatch):
    """`prefix-all` at the dummy size: the prefix's MLPs (all but the last layer's, which is dead code) run the
    kernel; the actions equal XLA's path's to e4m3 rounding (gate and up swapped in the kernel: 0.35)."""
    config = get_config("dummy", dtype="float32")
    params = benchmark.random_params(config, 0)
    calib = schemes.sample_observations(config, 2, seed=1)
    qp = schemes.quantize_params(params, "prefix-all", schemes.calibrate(config, params, calib, "prefix-all",
                                                                         percentile=None)["amax"])
    noise = jnp.asarray(np.random.default_rng(0).normal(size=(1, config.action_horizon, config.action_dim)),
                        jnp.float32)
    want = np.asarray(Engine(config, qp, cache_dir=False).sample_actions(calib[1], noise, num_steps=2))
    calls = []
    own = fp8_geglu.geglu
    monkeypatch.setattr(layers, "FP8_GEGLU", True)
    monkeypatch.setattr(fp8_geglu, "geglu", lambda *a, **kw: calls.append(a[0].shape) or own(*a, **kw))
    got = np.asarray(Engine(config, qp, cache_dir=False).sample_actions(calib[1], noise, num_steps=2))
    assert len(calls) >= config.paligemma.depth - 1
    monkeypatch.setattr(layers, "FP8_GEGLU", "auto")   # the default: on a Hopper GPU only, not the interpreter
    assert not layers.fp8_mlp_kernel()
    monkeypatch.setattr(layers.mosaic_gemm, "hopper", lambda: True)
    assert layers.fp8_mlp_kernel()
    assert np.isfinite(got).all()
    # f32 here: the two paths differ only where the folded division moves a value across an e4m3 rounding boundary
    assert np.linalg.norm(got - want) / np.linalg.norm(want) < 5e-3


@pytest.mark.parametrize("m,k,n2,launch", [(816, 2048, 32768, Launch()),   # π0's prefix MLP at B = 1
                                            (6528, 2048, 32768, Launch(tile_k=64, stages=6, delay=1)),   # B = 8
                                            (50, 1024, 8192, Launch())])   # the expert's at B = 1: 50 rows
def test_kernel_lowers_for_hopper(m, k, n2, launch):
    """Mosaic GPU lowers the kernel as a GPU runs it (the weight K-major, a ragged last row tile, 132 SMs) for sm_90
    on this CPU: layout inference, the e4m3 wgmma's operands and the TMA copies are checked here, which the
    interpreter above does not run. (An output column computed with `//` once left layout inference without a
    solution, and 50 rows failed TMA's row tiling until `run` padded them to 56.)"""
    avals = (jax.ShapeDtypeStruct((m, k), formats.E4M3), jax.ShapeDtypeStruct((n2, k), formats.E4M3),
             jax.ShapeDtypeStruct((n2,), jnp.float32))
    launch = fp8_geglu.fit(launch, k, n2)
    call = jax.jit(lambda x, w, s: fp8_geglu.run(x, w, s, launch, sms=132))
    text = call.trace(*avals).lower(lowering_platforms=("cuda",)).as_text()
    assert "mosaic_gpu" in text and f"tensor<{m}x{n2 // 2}xf8E4M3FN>" in text
