"""The FP8 MLP kernels (`pi0_jax.ops.fp8_geglu`: gate/up GEMM, GeGLU and the down GEMM's e4m3 input in one Mosaic
GPU kernel; SigLIP's fc1 GEMM, bias, GELU and fc2's e4m3 input in another; their CPU interpreter here) equal their
XLA forms, stay within one e4m3 step of the engine's XLA paths, and the engine's FP8 call with them
(`engine.layers.FP8_GEGLU`, `FP8_GEGLU_EXPERT_ROWS`, `engine.vision.FP8_GELU_ROWS`) matches the call without."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pi0_jax import benchmark
from pi0_jax.config import GEMMA_VARIANTS, SIGLIP_VARIANTS, GemmaConfig, SiglipConfig, get_config
from pi0_jax.engine import Engine, layers, vision
from pi0_jax.ops import formats, fp8_geglu, layout
from pi0_jax.ops.fp8_geglu import Launch
from pi0_jax.quant import schemes
from test_engine import call_loop_invariants


def _operands(m, k, f, down_scale):
    key = jax.random.key(m + k + f)
    x = jax.random.normal(key, (m, k), jnp.float32)
    w = jax.random.normal(jax.random.fold_in(key, 1), (2 * f, k), jnp.float32) * k**-0.5
    gate_up = formats.quantize_fp8(w, contract=(-1,), act_scale=formats.act_scale_from_amax(np.abs(x).max()))
    down = formats.quantize_fp8(jnp.ones((8, f)), contract=(-1,), act_scale=down_scale)
    return formats.quantise(x, gate_up.act_scale), gate_up, down


@pytest.mark.parametrize("m,k,f,launch", [(200, 256, 128, Launch()),   # 2 warpgroups, 2 K steps, a partial row tile
                                          (128, 64, 160, Launch()),    # the dummy prefix's MLP: one warpgroup
                                          (130, 128, 256, Launch(stages=2, delay=1, minor=1, snake=2)),
                                          (200, 256, 128, Launch(folded=True)),   # GELU folded into one exp2
                                          (200, 256, 128, Launch(tanh=True))])   # GELU with one tanh
def test_kernel_equals_its_xla_form(m, k, f, launch):
    xq, gate_up, down = _operands(m, k, f, 0.01)
    assert fp8_geglu.applies(gate_up, down)
    got = fp8_geglu.geglu(xq, gate_up, down.act_scale, launch)
    want = fp8_geglu.reference(xq, gate_up, down.act_scale, launch)
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


def _fp8_call(config, scheme):
    """A function of nothing that runs the engine's 2-step call on `config`'s random weights in FP8 (`scheme`, scales
    calibrated on two observations) as the module flags stand when it is called; its `engine` the last call's,
    its `obs` the observation."""
    params = benchmark.random_params(config, 0)
    calib = schemes.sample_observations(config, 2, seed=1)
    qp = schemes.quantize_params(params, scheme, schemes.calibrate(config, params, calib, scheme,
                                                                   percentile=None)["amax"])
    noise = jnp.asarray(np.random.default_rng(0).normal(size=(1, config.action_horizon, config.action_dim)),
                        jnp.float32)

    def call():
        call.engine = Engine(config, qp, cache_dir=False)
        return np.asarray(call.engine.sample_actions(calib[1], noise, num_steps=2))

    call.obs = calib[1]
    return call


def test_engine_fp8_call_with_the_kernel_matches_the_call_without(monkeypatch):
    """`prefix-all` at the dummy size: the prefix's MLPs (all but the last layer's, which is dead code) run the
    kernel; the actions equal XLA's path's to e4m3 rounding (gate and up swapped in the kernel: 0.35)."""
    config = get_config("dummy", dtype="float32")
    call = _fp8_call(config, "prefix-all")
    want = call()
    calls = []
    own = fp8_geglu.geglu
    monkeypatch.setattr(layers, "FP8_GEGLU", True)
    monkeypatch.setattr(fp8_geglu, "geglu", lambda *a, **kw: calls.append(a[0].shape) or own(*a, **kw))
    got = call()
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
                                            (50, 1024, 8192, Launch()),   # the expert's at B = 1: 50 rows
                                            # clusters of two sharing the weight tile's loads (the engine's launch):
                                            # B = 8's 51 row tiles (the last cluster's second tile past the rows),
                                            # the expert's 4 at B = 8
                                            (6528, 2048, 32768, fp8_geglu.LAUNCH),
                                            (400, 1024, 8192, fp8_geglu.LAUNCH)])
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


def test_whole_ref_load_takes_each_jaxs_signature():
    """`plgpu.load` of a whole ref as each jax spells it (the signatures of jax 0.10.2, 0.11.2 and 0.12.1): the module
    imports, and the GPU lowering passes an index only where one is required (0.12 has none: reading it raised at
    import, and with it every `pi0_jax.engine` import)."""
    not_specified = object()

    def load_010(src, idx, *, layout=None, optimized=True): ...
    def load_011(src, idx=not_specified, *, layout=None, optimized=True): ...
    def load_012(src, *, layout=None, optimized=True): ...

    assert fp8_geglu.whole_index(load_010) == ((),)
    assert fp8_geglu.whole_index(load_011) == ()
    assert fp8_geglu.whole_index(load_012) == ()


def test_clusters_only_where_the_rows_fill_them():
    """The engine's launches run in clusters of two where the row tiles are even or many (`clusters_pay`): at π0's
    prefix at B = 8 (51 tiles), the expert's 400 rows at B = 8 (4) and 3,200 at B = 64 (25), SigLIP's 768 rows
    (6); not at the prefix at B = 1 (816 rows: 7 tiles, the last cluster half idle)."""
    assert fp8_geglu.LAUNCH.cluster and fp8_geglu.GELU_LAUNCH.cluster
    assert not fp8_geglu.clusters_pay(fp8_geglu.LAUNCH, 816)
    assert all(fp8_geglu.clusters_pay(fp8_geglu.LAUNCH, m) for m in (6528, 400, 768, 52224))
    assert not fp8_geglu.clusters_pay(fp8_geglu.LAUNCH, 15 * 128) and fp8_geglu.clusters_pay(
        fp8_geglu.LAUNCH, 3200)   # the expert's 25 tiles at B = 64
    assert not fp8_geglu.clusters_pay(Launch(), 6528)   # a launch without clusters keeps none


def _gelu_operands(m, k, n, next_scale):
    key = jax.random.key(m + k + n)
    x = jax.random.normal(key, (m, k), jnp.float32)
    w = jax.random.normal(jax.random.fold_in(key, 1), (n, k), jnp.float32) * k**-0.5 * 3
    fc1 = formats.quantize_fp8(w, contract=(-1,), act_scale=formats.act_scale_from_amax(np.abs(x).max()))
    fc2 = formats.quantize_fp8(jnp.ones((8, n)), contract=(-1,), act_scale=next_scale)
    bias = jax.random.normal(jax.random.fold_in(key, 2), (n,), jnp.float32)
    return formats.quantise(x, fc1.act_scale), fc1, bias, fc2


@pytest.mark.optimized   # e4m3 boundaries: at -O0 0.9988 of the values match (conftest.py)
@pytest.mark.parametrize("m,k,n,launch", [(200, 256, 80, None),   # one warpgroup, N padded to a tile, 2 K steps
                                          (130, 128, 304, None),   # 2 warpgroups, 2 column tiles, the last ragged
                                          (64, 96, 128, Launch(stages=2, delay=1, minor=1, snake=2)),   # K = 3 x 32
                                          (130, 128, 304, Launch(stages=3)),   # session 57's: x sigmoid(2 z)
                                          (130, 128, 304, Launch(tile_n=128, tanh=True))])   # GELU with one tanh
def test_gelu_kernel_equals_its_xla_form(m, k, n, launch):
    """`fp8_geglu.gelu` (SigLIP's fc1: GEMM, bias, GELU-tanh, fc2's e4m3 input) against `gelu_reference`; within one
    e4m3 step of the engine's XLA path (`engine.vision.block`: scale and bias rounded to the dtype, then GELU)."""
    xq, fc1, bias, fc2 = _gelu_operands(m, k, n, 0.004)
    assert fp8_geglu.gelu_applies(fc1, fc2)
    got = np.asarray(fp8_geglu.gelu(xq, fc1, bias, fc2.act_scale, launch), np.float32)
    want = np.asarray(fp8_geglu.gelu_reference(xq, fc1, bias, fc2.act_scale, launch), np.float32)
    assert got.shape == (m, n)
    # the interpreter sums K in tile_k steps, the reference in one: a value on an e4m3 rounding boundary may move one
    # step (2^-9 at zero: one tanh's form cancels in GELU's negative tail, where a value may round to 0 or not)
    assert np.mean(got == want) > 0.999 and np.all(np.abs(got - want) <= np.maximum(np.abs(want) / 8, 2.0**-9))
    assert np.abs(want).max() == formats.E4M3_MAX and (want < 0).any()   # saturated, and GELU's negative lobe
    y = jnp.einsum("md,nd->mn", xq, fc1.q, preferred_element_type=jnp.float32)
    xla = formats.quantise(jax.nn.gelu(y * formats.output_scale("...D,FD->...F", fc1) + bias, approximate=True),
                           fc2.act_scale)
    xla = np.asarray(xla, np.float32)
    assert np.all(np.abs(got - xla) <= np.maximum(np.abs(xla), 2.0**-6) / 8 + 1e-6) and np.mean(got == xla) > 0.95
    unbiased = np.asarray(fp8_geglu.gelu_reference(xq, fc1, jnp.zeros_like(bias), fc2.act_scale), np.float32)
    assert np.mean(got == unbiased) < 0.5


def test_gelu_folded_is_gelu_tanh():
    """The kernel's folded GELU-tanh (an exp2 of x (A + B x^2)) is GELU-tanh to f32 rounding over both tails, the
    negative one included (x sigmoid(2 z) in float64 as the truth: jax's 0.5 x (1 + tanh z) cancels to 0 there), and
    no NaN where the exp2 overflows."""
    x = jnp.concatenate([jnp.linspace(-12.0, 12.0, 4001, dtype=jnp.float32), jnp.array([-300.0, 300.0, 0.0])])
    got = np.asarray(fp8_geglu.gelu_folded(x))
    x64 = np.asarray(x, np.float64)
    with np.errstate(over="ignore"):
        want = x64 / (1 + np.exp(-2 * 0.7978845608028654 * (x64 + 0.044715 * x64**3)))
    assert np.isfinite(got).all()
    # the tail's relative error grows with the exp's argument (|x (A + B x^2)| up to 200 here), in both f32 forms
    np.testing.assert_allclose(got, want, rtol=3e-5, atol=1e-30)
    np.testing.assert_allclose(got, np.asarray(fp8_geglu.gelu_tanh(x)), rtol=3e-5, atol=1e-30)
    assert np.abs(got - want).max() < 1e-6
    # 0.5 x (1 + tanh z) (`Launch.tanh`) cancels in the negative tail: equal to f32 rounding in absolute terms only
    half = np.asarray(fp8_geglu.gelu_half_tanh(x))
    assert np.isfinite(half).all() and np.abs(half - want).max() < 1e-6


def test_gelu_applies_only_where_it_fits():
    _, fc1, _, fc2 = _gelu_operands(64, 128, 80, 0.1)
    assert fp8_geglu.gelu_applies(fc1, fc2)
    assert not fp8_geglu.gelu_applies(formats.QArray(fc1.q, fc1.scale, None, (-1,)), fc2)   # weight-only
    assert not fp8_geglu.gelu_applies(fc1, formats.QArray(fc2.q, fc2.scale, None, (-1,)))   # the next GEMM in bf16
    assert fp8_geglu.fit_gelu(Launch(), 40, 88) is None   # SigLIP's dummy width: no e4m3 wgmma step divides it
    assert fp8_geglu.fit_gelu(Launch(), 64, 88) is None   # no TMA store tiles 88 columns (16 bytes at least)
    assert fp8_geglu.gelu_block(4304) == 16 and fp8_geglu.gelu_block(4352) == 64


def test_engine_vision_with_the_gelu_kernel_matches_without(monkeypatch):
    """`prefix-vision` with a SigLIP whose width an e4m3 wgmma divides (the dummy's 40 does not): every block's fc1
    runs the kernel; the actions equal XLA's path's to e4m3 rounding."""
    monkeypatch.setitem(SIGLIP_VARIANTS, "dummy-64", SiglipConfig(width=64, depth=2, mlp_dim=80, num_heads=2))
    config = get_config("dummy", dtype="float32", siglip_variant="dummy-64")
    call = _fp8_call(config, "prefix-vision")
    monkeypatch.setattr(layers, "FP8_GEGLU", True)
    monkeypatch.setattr(vision, "FP8_GELU_ROWS", None)
    want = call()
    calls, own = [], fp8_geglu.gelu
    monkeypatch.setattr(vision, "FP8_GELU_ROWS", 256)   # a camera's rows
    monkeypatch.setattr(fp8_geglu, "gelu", lambda *a, **kw: calls.append(a[0].shape) or own(*a, **kw))
    got = call()
    assert len(calls) >= config.siglip.depth and all(c[1] == 64 for c in calls)
    assert np.isfinite(got).all()
    # f32 here: the paths differ only where GELU's two forms' last bits move a value across an e4m3 boundary
    assert np.linalg.norm(got - want) / np.linalg.norm(want) < 5e-3


@pytest.mark.parametrize("m,cluster", [(768, False), (49152, False), (49152, True)])   # SigLIP's fc1, B = 1, 64
def test_gelu_kernel_lowers_for_hopper(m, cluster):
    """The GPU form of `gelu` at SigLIP's shapes lowers for sm_90 here: its 4,304 columns end in a ragged column
    tile, stored 16 columns at a time (a TMA layout's tiles must divide the array: 64 did not lower); also with
    CTAs in clusters of two (`Launch.cluster`)."""
    k, n = 1152, 4304
    launch = fp8_geglu.fit_gelu(dataclasses.replace(fp8_geglu.GELU_LAUNCH, cluster=cluster), k, n)
    avals = (jax.ShapeDtypeStruct((m, k), formats.E4M3), jax.ShapeDtypeStruct((n, k), formats.E4M3),
             jax.ShapeDtypeStruct((3, -(-n // launch.tile_n) * launch.tile_n), jnp.float32))   # whole column tiles
    call = jax.jit(lambda x, w, t: fp8_geglu.run(x, w, t, launch, sms=132, act="gelu"))
    text = call.trace(*avals).lower(lowering_platforms=("cuda",)).as_text()
    assert "mosaic_gpu" in text and f"tensor<{m}x{n}xf8E4M3FN>" in text


@pytest.mark.optimized   # its time is the interpreter's run
def test_engine_expert_on_the_kernel_matches_xla(monkeypatch):
    """`every-gemm` with an action expert whose width an e4m3 wgmma divides (the dummy's 48 does not), from
    `FP8_GEGLU_EXPERT_ROWS`: the expert's MLPs run the kernel too; the actions equal XLA's path's to e4m3 rounding."""
    monkeypatch.setitem(GEMMA_VARIANTS, "dummy_expert_64", GemmaConfig(width=64, depth=3, mlp_dim=96, num_heads=4,
                                                                        num_kv_heads=1, head_dim=16))
    config = get_config("dummy", dtype="float32", action_expert_variant="dummy_expert_64")
    call = _fp8_call(config, "every-gemm")
    calls, own = [], fp8_geglu.geglu
    monkeypatch.setattr(layers, "FP8_GEGLU", True)
    monkeypatch.setattr(layers, "FP8_GEGLU_EXPERT_ROWS", None)
    monkeypatch.setattr(fp8_geglu, "geglu", lambda *a, **kw: calls.append(a[1].q.shape) or own(*a, **kw))
    want = call()
    prefix = len(calls)
    assert prefix and all(c == (2 * config.paligemma.mlp_dim, 64) for c in calls)
    monkeypatch.setattr(layers, "FP8_GEGLU_EXPERT_ROWS", 1)   # the expert's 51 rows at B = 1
    got = call()
    expert = [c for c in calls[prefix:] if c == (2 * config.action_expert.mlp_dim, 64)]
    assert len(expert) >= config.action_expert.depth
    assert np.isfinite(got).all() and np.linalg.norm(got - want) / np.linalg.norm(want) < 5e-3
    # the kernel's column scales are the weights' alone: made before the denoise loop, not in every step
    loops = call_loop_invariants(call.engine, call.obs, 1, 2)
    assert loops and not any(loops), loops
