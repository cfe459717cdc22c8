"""The Mosaic GPU GEMM (`pi0_jax.ops.mosaic_gemm`, Mosaic GPU's interpreter on CPU) equals XLA's product, the
expert's layers with every GEMM on it equal the XLA layer, for π0 and π0.5's adaRMS, and the engine's call on it
equals the reference sampler. The `dummy` expert's widths (48) do not tile its 64-wide K steps, so these tests build
their own expert: width 128, two heads of 64 (one kv head), MLP 256, which every launch below tiles (the engine's test
takes the embedded model's towers). f32: the kernel and XLA differ only in summation order."""

import dataclasses
import functools
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pi0_jax import gemma, pi0
from pi0_jax.config import GemmaConfig, get_config
from pi0_jax.engine import Engine, layers
from pi0_jax.ops import expert_kernels as ek
from pi0_jax.ops import layout, mosaic_gemm
from pi0_jax.ops.mosaic_gemm import Launch
from test_model import make_obs, randomize

TOL = {"rtol": 1e-5, "atol": 1e-5}
CFG = GemmaConfig(width=128, depth=1, mlp_dim=256, num_heads=2, num_kv_heads=1, head_dim=64)
B, S, P = 1, 11, 100   # a 100-key prefix (padded to 128, the padding masked) and 11 suffix rows (padded to 16)
MOSAIC = ek.Blocks(mosaic_qkv=Launch(64, 2, 2), mosaic_mlp=Launch(64, 1, 3, 2), mosaic_out=Launch(64, 2, 1, 2),
                   mosaic_down=Launch(128, 4, 1))
GEGLU = dataclasses.replace(MOSAIC, mosaic_mlp=Launch(64, 1, 3, geglu=True))
ROPE = dataclasses.replace(GEGLU, mosaic_qkv=Launch(32, 1, 2, rope=True))   # CFG's RoPE halves are 32 wide
# q/k/v with RoPE (`mosaic_gemm.qkv_rope`) takes x^T as a wgmma operand, which Mosaic GPU's interpreter runs from jax
# 0.11 (the GPU image's); its GPU form lowers on either (`test_kernels_lower_for_hopper`)
TRANSPOSED_WGMMA = pytest.mark.skipif(jax.__version_info__ < (0, 11),
                                      reason="Mosaic GPU's interpreter before jax 0.11 takes no transposed wgmma "
                                             "operand; jax 0.11 (the GPU image's) runs it, and the GPU form's "
                                             "lowering is tested on any jax (test_kernels_lower_for_hopper)")


# the engine's whole call in Mosaic GPU's interpreter: jax 0.10's (CI's) took 52-62 s a case on CI's 2 cores, and CI
# stood at 18:55 of its 20 minutes with one case
INTERPRETER_MINUTE = pytest.mark.skipif(jax.__version_info__ < (0, 11),
                                        reason="jax 0.10's Mosaic GPU interpreter takes most of a minute of CI for the "
                                               "engine's call; jax 0.11 (the GPU image's) runs it, and CI keeps the "
                                               "kernels' and the layers' tests on the same launch")


def _record_calls(monkeypatch, label) -> list:
    """The Mosaic GEMM entry points wrapped: each call appends label(its function's name, its keywords) to the list
    returned, then runs."""
    calls = []
    for fn in ("partials", "geglu", "qkv_rope"):
        kernel = getattr(mosaic_gemm, fn)
        monkeypatch.setattr(mosaic_gemm, fn,
                            lambda *a, fn=fn, kernel=kernel, **kw: calls.append(label(fn, kw)) or kernel(*a, **kw))
    return calls


def _rand(key, *shape, scale=1.0):
    return jax.random.normal(jax.random.key(key), shape, jnp.float32) * scale


@pytest.mark.parametrize("rows,k,n,launch", [(64, 256, 256, Launch(64, 2, 2)),
                                             (100, 128, 256, Launch(64, 1, 2, 2, delay=1)),
                                             (130, 256, 128, Launch(128, 4, 3)),
                                             (64, 512, 128, Launch(64, 2, 2, tk=128))])
def test_partials_equal_xla(rows, k, n, launch):
    """Rows padded to 64 and cut back; split-K partials in f32; one chunk in the input's dtype."""
    x, w = _rand(0, rows, k), _rand(1, k, n, scale=k**-0.5)
    assert mosaic_gemm.applies(x, w, launch)
    got = mosaic_gemm.partials(x, w, launch)
    assert got.shape == (launch.splits, rows, n) and got.dtype == jnp.float32
    np.testing.assert_allclose(got.sum(0), x @ w, **TOL)
    # bf16: one chunk comes back rounded to bf16, as XLA's x @ w does
    xb, wb = x.astype(jnp.bfloat16), w.astype(jnp.bfloat16)
    got = mosaic_gemm.partials(xb, wb, launch).astype(jnp.float32).sum(0)
    want = jnp.dot(xb, wb, preferred_element_type=jnp.float32)
    np.testing.assert_allclose(got, want, rtol=1e-2, atol=1e-2)
    assert not np.allclose(got, jnp.dot(xb, wb[::-1], preferred_element_type=jnp.float32), rtol=1e-2, atol=1e-2)


def test_geglu_equals_xla():
    """One block pair of gate and up columns (the engine's layout, `layout.gate_up_block`) a CTA; rows padded."""
    x, w = _rand(2, 100, 128), _rand(3, 128, 512, scale=128**-0.5)
    gate, up = layout.split_gate_up(x @ w)
    want = jax.nn.gelu(gate, approximate=True) * up
    for launch in (Launch(64, 1, 2, geglu=True), Launch(64, 1, 3, geglu=True, delay=1),
                   Launch(64, 1, 2, geglu=True, tk=128)):
        assert mosaic_gemm.applies(x, w, launch)
        np.testing.assert_allclose(mosaic_gemm.geglu(x, w, launch), want, **TOL)
    assert not np.allclose(jax.nn.gelu(up, approximate=True) * gate, want, **TOL)   # gate and up not swapped
    xb, wb = x.astype(jnp.bfloat16), w.astype(jnp.bfloat16)
    gate, up = layout.split_gate_up(xb @ wb)
    got = mosaic_gemm.geglu(xb, wb, Launch(64, 1, 2, geglu=True))
    assert got.dtype == jnp.bfloat16
    np.testing.assert_allclose(got.astype(jnp.float32), jax.nn.gelu(gate, approximate=True) * up, rtol=1e-2,
                               atol=4e-2)   # one bf16 ulp at |y| < 8, rounded once here and per op in XLA
    with pytest.raises(ValueError, match="GeGLU epilogue"):
        Launch(64, 2, geglu=True)
    with pytest.raises(ValueError, match="delay"):
        Launch(64, 1, 2, delay=2)
    with pytest.raises(ValueError, match="multiple of 64"):
        Launch(64, tk=96)


def test_applies_only_where_the_launch_tiles():
    x = jnp.zeros((64, 48))
    assert not mosaic_gemm.applies(x, jnp.zeros((48, 128)), Launch())        # the dummy expert's width
    assert not mosaic_gemm.applies(x, jnp.zeros((128, 96)), Launch(64))      # 96 columns in blocks of 64
    assert not mosaic_gemm.applies(x, jnp.zeros((128, 128)), Launch(64, 4))  # 4 chunks of 32 < one 64-wide step
    assert mosaic_gemm.applies(x, jnp.zeros((128, 128)), Launch(64, 2))
    assert not mosaic_gemm.applies(x, jnp.zeros((128, 128)), Launch(64, 2, 3, delay=1))  # one step per chunk
    assert not mosaic_gemm.applies(x, jnp.zeros((128, 80)), Launch(64, geglu=True))   # 40 units: one block of 40
    assert not mosaic_gemm.applies(x, jnp.zeros((128, 512)), Launch(128, geglu=True))   # a CTA is one pair of 32
    assert mosaic_gemm.applies(x, jnp.zeros((128, 192)), Launch(64, geglu=True))   # 96 units: 3 pairs of 32
    assert not mosaic_gemm.applies(x, jnp.zeros((128, 128)), Launch(64, 2, tk=128))  # chunks of 64 < a 128-row step
    assert mosaic_gemm.applies(x, jnp.zeros((256, 128)), Launch(64, 2, tk=128))


def _layers_inputs(pi05: bool, S: int = S):
    d, f, n, kh, h = CFG.width, CFG.mlp_dim, CFG.num_heads, CFG.num_kv_heads, CFG.head_dim
    weights = [{"qkv": _rand(10 * i, d, (n + 2 * kh) * h, scale=d**-0.5),
                "attn_out": _rand(10 * i + 1, n * h, d, scale=0.1),
                "gate_up": _rand(10 * i + 2, d, 2 * f, scale=d**-0.5),
                "down": _rand(10 * i + 3, f, d, scale=f**-0.5)} for i in range(CFG.depth)]
    if not pi05:
        for i, w in enumerate(weights):
            w.update(pre_attn=_rand(10 * i + 4, d, scale=0.2), pre_ffw=_rand(10 * i + 5, d, scale=0.2))
    mods = (_rand(50, CFG.depth, 3 * d, scale=0.3), _rand(51, CFG.depth, 3 * d, scale=0.3)) if pi05 else None
    x = _rand(60, B, S, d)
    positions = 90 + jnp.arange(S)[None]
    ck, cv = _rand(61, CFG.depth, B, P, kh, h), _rand(62, CFG.depth, B, P, kh, h)
    pmask = jnp.arange(P)[None] < 90   # the last 10 prefix keys are padding
    ar = jnp.asarray([True] + [False] * (S - 1) if pi05 else [True, True] + [False] * (S - 2))
    smask = jnp.broadcast_to(pi0.make_attn_mask(jnp.ones((1, S), bool), ar), (B, S, S))
    return weights, mods, x, positions, ck, cv, pmask, smask


@pytest.mark.parametrize("pi05,blocks,s", [(False, MOSAIC, S), (True, MOSAIC, S), (False, GEGLU, S), (True, GEGLU, S),
                                           pytest.param(False, ROPE, S, marks=TRANSPOSED_WGMMA),
                                           pytest.param(True, ROPE, S, marks=TRANSPOSED_WGMMA), (True, ROPE, 64)])
def test_expert_layers_on_the_mosaic_gemm_equal_xla(pi05, blocks, s, monkeypatch):
    """π0.5's q/k/v with RoPE on Mosaic GPU takes its adaRMS shift in a padding row; with 64 suffix rows (none is
    padding) it keeps the Triton kernel."""
    weights, mods, x, positions, ck, cv, pmask, smask = _layers_inputs(pi05, s)
    want = x
    for i, w in enumerate(weights):
        layer_mods = None if mods is None else (mods[0][i:i + 1], mods[1][i:i + 1])
        want, _, _ = layers.suffix_layer(CFG, w, want, gemma.rope_angles(positions, CFG.head_dim), ck[i], cv[i],
                                         jnp.broadcast_to(pmask[:, None], (B, s, P)), smask, layer_mods)
    calls = _record_calls(monkeypatch, lambda fn, kw: kw["name"])
    cache_k, cache_v = ([layout.cache_kv(c[i], CFG.head_dim) for i in range(CFG.depth)] for c in (ck, cv))
    got = layers.suffix_layers_pallas(CFG, weights, x, positions, cache_k, cache_v, layout.cache_mask(pmask), smask,
                                      mods, blocks=blocks)
    on_triton = pi05 and blocks.mosaic_qkv.rope and s == 64
    assert calls == ["expert_qkv"] * (not on_triton) + ["expert_attn_out", "expert_gate_up", "expert_down"] * CFG.depth
    np.testing.assert_allclose(got, want, **TOL)
    # the norm scale / adaRMS shift enter: without them the result differs
    if pi05:
        mods = (mods[0].at[:, CFG.width:2 * CFG.width].set(0), mods[1])
    else:
        weights = [dict(w, pre_attn=jnp.zeros_like(w["pre_attn"])) for w in weights]
    other = layers.suffix_layers_pallas(CFG, weights, x, positions, cache_k, cache_v, layout.cache_mask(pmask), smask,
                                        mods, blocks=blocks)
    assert not np.allclose(other, want, **TOL)


@pytest.mark.parametrize("preset,blocks", [
    pytest.param("dummy_pi05", GEGLU, marks=INTERPRETER_MINUTE, id="pi05-geglu"),
    pytest.param("dummy", ROPE, marks=TRANSPOSED_WGMMA, id="pi0-rope"),
    pytest.param("dummy_pi05", ROPE, marks=TRANSPOSED_WGMMA, id="pi05-rope")])
def test_engine_on_the_mosaic_gemms_matches_the_reference(preset, blocks, monkeypatch):
    """The engine's call with the expert's GEMMs on Mosaic GPU as its default launch (q/k/v with RoPE on `qkv_rope`
    or on the split-K kernel) equals the reference sampler. The test presets with the embedded model's towers, two
    layers each, whose widths and 32-wide RoPE halves the launches tile; B = 2 with element 1's last camera masked
    and prompts padded; π0.5's 2 x 10 step rows leave its adaRMS shift a padding row. π0 on the plain launches is
    left to the layers' test above."""
    config = get_config(preset, dtype="float32", paligemma_variant="gemma_small_2l",
                        action_expert_variant="gemma_small_expert_2l")
    params = randomize(pi0.param_shapes(config))
    obs = make_obs(config)
    noise = jax.random.normal(jax.random.key(1), (2, config.action_horizon, config.action_dim))
    want = jax.jit(pi0.sample_actions, static_argnums=(0, 4))(config, params, obs, noise, 2)
    calls = _record_calls(monkeypatch, lambda fn, kw: fn)
    monkeypatch.setattr(ek, "default_blocks", lambda: blocks)
    got = Engine(config, params, kernels="pallas", cache_dir=False).sample_actions(obs, jnp.asarray(noise), 2)
    layers_traced = calls.count("geglu")   # every layer's gate/up, once per program that traces it
    rope = blocks.mosaic_qkv.rope
    assert layers_traced >= config.action_expert.depth and calls.count("qkv_rope") == rope * layers_traced
    assert calls.count("partials") == (2 if rope else 3) * layers_traced   # out, down (and q/k/v without RoPE)
    np.testing.assert_allclose(got, want, **TOL)


@TRANSPOSED_WGMMA
def test_qkv_rope_equals_the_triton_kernel_and_its_epilogue():
    """`mosaic_gemm.qkv_rope` against `expert_kernels.norm_qkv_rope`'s Triton GEMM and XLA epilogue: 50 rows (padded
    to 64), two q heads, two kv heads, 64-wide RoPE halves in two blocks a CTA (cols 32); f32, so only the sums'
    order differs. RoPE turns q and k, not v; q alone is scaled; each head's two halves land in their own columns."""
    d, n, kh, hd, m = 128, 2, 2, 128, 50
    hp = layout.half_dim(hd)
    x, scale = _rand(70, m, d), _rand(71, 1, d, scale=0.2)
    w = layout.heads(_rand(72, d, (n + 2 * kh) * hd, scale=d**-0.5), -1, hd)
    cos, sin = layout.rope_tables(jnp.arange(m)[None] * 7 % 300, hd)
    kw = dict(width=d, num_heads=n, num_kv_heads=kh, head_dim=hd)
    want = ek.norm_qkv_rope(x, scale, 0, False, w, cos, sin, blocks=ek.Blocks(), **kw)
    launch = Launch(32, 1, 2, rope=True)
    assert mosaic_gemm.applies(x, w, launch, half=hp)
    got = ek.norm_qkv_rope(x, scale, 0, False, w, cos, sin, blocks=ek.Blocks(mosaic_qkv=launch), **kw)
    np.testing.assert_allclose(got, want, **TOL)
    q, k, v = np.split(np.asarray(got), [n * 2 * hp, (n + kh) * 2 * hp], axis=1)
    plain = ek.norm_qkv_rope(x, scale, 0, False, w, jnp.ones_like(cos), jnp.zeros_like(sin), blocks=ek.Blocks(), **kw)
    pq, pk, pv = np.split(np.asarray(plain), [n * 2 * hp, (n + kh) * 2 * hp], axis=1)
    np.testing.assert_allclose(v, pv, **TOL)    # v unturned, unscaled
    assert not np.allclose(k, pk, **TOL) and not np.allclose(q, pq, **TOL)
    # π0.5: adaRMS's scale and shift rows of a table (the shift rides in row 63, a padding row of the 64)
    mods = jnp.concatenate([scale, _rand(73, 1, d, scale=0.3)])
    want = ek.norm_qkv_rope(x, mods, 0, True, w, cos, sin, blocks=ek.Blocks(), **kw)
    got = ek.norm_qkv_rope(x, mods, 0, True, w, cos, sin, blocks=ek.Blocks(mosaic_qkv=launch), pad_row=True, **kw)
    np.testing.assert_allclose(got, want, **TOL)
    assert not np.allclose(ek.norm_qkv_rope(x, mods, 0, False, w, cos, sin, blocks=ek.Blocks(), **kw), want, **TOL)
    with pytest.raises(ValueError, match="RoPE"):
        Launch(64, 2, rope=True)
    assert not mosaic_gemm.applies(x, w, Launch(128, rope=True), half=hp)   # a block wider than a half


def test_interpreter_warns_where_xla_cpu_scheduler_may_hang_it(monkeypatch):
    """Without the scheduler flag (`mosaic_gemm._SCHEDULER_OFF`) the interpreter warns before it runs: the engine's
    FP8 call on it hung so; with the flag (as `pi0_jax.sim` sets it, and so these tests) it runs without a word."""
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_use_fusion_emitters=false")
    with pytest.warns(UserWarning, match="enable_concurrency_optimized_scheduler=false"):
        mosaic_gemm._interpret()
    monkeypatch.setenv("XLA_FLAGS", mosaic_gemm._SCHEDULER_OFF)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        mosaic_gemm._interpret()


def test_blocks_with_launches_round_trip_through_json():
    assert ek.Blocks.from_dict(dataclasses.asdict(GEGLU)) == GEGLU
    assert ek.Blocks.from_dict(dataclasses.asdict(ek.Blocks())) == ek.Blocks()


def test_kernels_lower_for_hopper(monkeypatch):
    """The GPU form (not the interpreter's) lowers for sm_90 on this CPU, bf16 at π0's expert shapes (50 rows, K 1024;
    q/k/v 2560 columns, gate/up 2 x 4096): Mosaic GPU's layout inference, wgmma operands and TMA copies run here."""
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")   # the kernels pick the GPU form by the backend
    bf, aval = jnp.bfloat16, jax.ShapeDtypeStruct
    for fn, w, out in ((lambda x, w: mosaic_gemm.partials(x, w, Launch(64, 2, 2)), (1024, 2560),
                        "128x2560xf32"),   # 2 K splits' f32 partials of 64 (padded) rows
                       (lambda x, w: mosaic_gemm.geglu(x, w, Launch(64, 1, 3, geglu=True)), (1024, 8192),
                        "64x4096xbf16")):
        text = jax.jit(fn).trace(aval((50, 1024), bf), aval(w, bf)).lower(lowering_platforms=("cuda",)).as_text()
        assert "mosaic_gpu" in text and f"tensor<{out}>" in text
    rope = functools.partial(mosaic_gemm.qkv_rope, launch=Launch(64, 1, 4, rope=True), width=1024, num_heads=8,
                             num_kv_heads=1, q_scale=0.0625, eps=1e-6)   # q/k/v with its norm and RoPE: 64 rows out
    for shift in (None, aval((1024,), bf)):   # π0 and π0.5 (adaRMS's shift)
        text = jax.jit(rope).trace(aval((50, 1024), bf), aval((50, 1024), bf), aval((1024, 2560), bf),
                                   *(aval((50, 128), jnp.float32),) * 2,
                                   shift=shift).lower(lowering_platforms=("cuda",)).as_text()
        assert "mosaic_gpu" in text and "tensor<64x2560xbf16>" in text
