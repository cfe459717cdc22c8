"""The fused expert kernels and the vision attention and LayerNorm kernels (`pi0_jax.ops`, interpret mode on CPU)
compute what the engine's XLA ops compute, at the `dummy` sizes (every width, head half and key count padded), and
the engine with kernels="pallas" (the expert's kernels and SigLIP's LayerNorm; with attention="vision=pallas" also
SigLIP's attention) matches the reference sampler. f32 throughout: the kernels and XLA differ only in summation
order (measured ~1e-6)."""

import dataclasses

import jax
import jax.extend
import jax.numpy as jnp
import numpy as np
import pytest

from pi0_jax import gemma, pi0
from pi0_jax.config import IMAGE_KEYS, get_config
from pi0_jax.engine import Engine, layers, paths, programs
from pi0_jax.ops import expert_attention as ea
from pi0_jax.ops import expert_kernels as ek
from pi0_jax.ops import formats, layout
from pi0_jax.ops.expert_kernels import Blocks, Gemm
from pi0_jax.ops.formats import E4M3
from pi0_jax.quant import schemes
from test_model import make_obs, randomize

CFG = get_config("dummy").action_expert  # width 48, 4 heads x 16 (1 kv head), mlp 96: all padded by the layout
B, S, P = 2, 11, 2 * 64 + 32  # two cameras of 64 tokens and a 32-token prompt bucket: 160 keys, padded to 192
TOL = {"rtol": 1e-5, "atol": 1e-5}


def _rand(key, *shape, scale=1.0):
    return jax.random.normal(jax.random.key(key), shape, jnp.float32) * scale


def _layer_weights(seed=0):
    d, f, n, k, h = CFG.width, CFG.mlp_dim, CFG.num_heads, CFG.num_kv_heads, CFG.head_dim
    return {"qkv": _rand(seed, d, (n + 2 * k) * h, scale=d**-0.5), "attn_out": _rand(seed + 1, n * h, d, scale=0.1),
            "gate_up": _rand(seed + 2, d, 2 * f, scale=d**-0.5), "down": _rand(seed + 3, f, d, scale=f**-0.5),
            "pre_attn": _rand(seed + 4, d, scale=0.2), "pre_ffw": _rand(seed + 5, d, scale=0.2)}


def _prefix_mask():
    """Element 0: its second camera masked and 13 prompt tokens; element 1: both cameras and 21 prompt tokens."""
    idx = np.arange(P)
    m0 = (idx < 64) | ((idx >= 128) & (idx < 128 + 13))
    m1 = idx < 128 + 21
    return jnp.asarray(np.stack([m0, m1]))


def _suffix_mask(pi05: bool):
    ar = [True] + [True] + [False] * (S - 2) if not pi05 else [True] + [False] * (S - 1)
    return jnp.broadcast_to(pi0.make_attn_mask(jnp.ones((1, S), bool), jnp.asarray(ar)), (B, S, S))


def _unrows(rows, width):
    """Kernel rows (B Sp, Dpad) -> (B, S, width)."""
    return rows.reshape(B, layout.suffix_rows(S), -1)[:, :S, :width]


def _mods(adaptive, w):
    """(mods, row, gate_row) of the kernels and the XLA path's mod / scale, for layer 1 of a 2-layer table."""
    if not adaptive:
        wk = layout.expert_weights(w, CFG)
        return (wk["pre_attn"], 0, None), {"scale": w["pre_attn"]}, None
    table = _rand(7, 2, 3 * CFG.width, scale=0.3)
    return (layout.mods(table, CFG.width), 3, 5), {"mod": table[1:2]}, table[1, 2 * CFG.width:]


def test_big_negative_fill_is_the_models():
    assert ea.BIG_NEG == gemma._BIG_NEG


@pytest.mark.parametrize("adaptive", [False, True])
def test_norm_qkv_rope_matches_xla(adaptive):
    w = _layer_weights()
    x = _rand(10, B, S, CFG.width)
    positions = jnp.asarray([[77], [149]]) + jnp.arange(S)  # each element's valid prefix length, then the suffix
    (mods, row, _), norm_kw, _ = _mods(adaptive, w)
    h, _ = layers.rms_norm(x, **norm_kw)
    q, k, v = layers._qkv(h, w["qkv"], CFG, gemma.rope_angles(positions, CFG.head_dim))
    sp = layout.suffix_rows(S)
    cos, sin = layout.rope_tables(jnp.pad(positions, ((0, 0), (0, sp - S))), CFG.head_dim)
    for splits in (1, 3):  # one K chunk; three (width 48: the sums of squares and shift products of 3 chunks)
        out = ek.norm_qkv_rope(layout.rows(x, sp), mods, row, adaptive, layout.expert_weights(w, CFG)["qkv"], cos,
                               sin, width=CFG.width, num_heads=CFG.num_heads, num_kv_heads=CFG.num_kv_heads,
                               head_dim=CFG.head_dim, blocks=Blocks(qkv=Gemm(128, splits)))
        got = layout.unheads(out.reshape(B, sp, -1)[:, :S], CFG.head_dim).reshape(B, S, -1, CFG.head_dim)
        np.testing.assert_allclose(got[:, :, : CFG.num_heads], q.reshape(B, S, CFG.num_heads, -1), **TOL)
        np.testing.assert_allclose(got[:, :, CFG.num_heads: -1], k, **TOL)
        np.testing.assert_allclose(got[:, :, -1:], v, **TOL)
    if adaptive:   # the table as step 1 of a stack of three steps' tables, read in place at a traced step
        table = _rand(7, 2, 3 * CFG.width, scale=0.3)
        stack = jnp.stack([_rand(8, 2, 3 * CFG.width), table, _rand(9, 2, 3 * CFG.width)])
        stacked = layout.mods(stack.reshape(-1, 3 * CFG.width), CFG.width)

        @jax.jit
        def at_step(step):
            return ek.norm_qkv_rope(layout.rows(x, sp), stacked, row, True, layout.expert_weights(w, CFG)["qkv"], cos,
                                    sin, width=CFG.width, num_heads=CFG.num_heads, num_kv_heads=CFG.num_kv_heads,
                                    head_dim=CFG.head_dim, blocks=Blocks(qkv=Gemm(128, 3)), step=ek.Step(step, 6))
        np.testing.assert_allclose(at_step(jnp.int32(1)), out, **TOL)
        assert not np.allclose(at_step(jnp.int32(2)), out, **TOL)


def _attention_inputs(pi05):
    n, kh, h = CFG.num_heads, CFG.num_kv_heads, CFG.head_dim
    q = _rand(20, B, S, kh, n // kh, h)
    k, v = _rand(21, B, S, kh, h), _rand(22, B, S, kh, h)
    ck, cv = _rand(23, B, P, kh, h), _rand(24, B, P, kh, h)
    return q, k, v, ck, cv, _prefix_mask(), _suffix_mask(pi05)


def kernel_operands(cfg, q, k, v, ck, cv, pmask, smask) -> tuple:
    """The attention kernel's operands from the XLA path's q (B,S,K,G,H), k, v (B,S,K,H), caches (B,P,K,H), prefix
    mask (B,P) and suffix mask (B,S,S): (qkv rows, cache_k, cache_v, prefix mask, suffix mask), as
    `engine.layers.suffix_layers_pallas` lays them out."""
    b, s = q.shape[:2]
    sp, h = layout.suffix_rows(s), cfg.head_dim
    qkv = jnp.concatenate([q.reshape(b, s, -1), k.reshape(b, s, -1), v.reshape(b, s, -1)], axis=-1)
    ck, cv = (layout.cache_kv(c, h) for c in (ck, cv))
    smask = jnp.pad(smask, ((0, 0), (0, sp - s), (0, sp - s))).reshape(b * sp, sp).astype(jnp.int32)
    return (layout.rows(layout.heads(qkv, -1, h), sp), ck.reshape(-1, ck.shape[2] * ck.shape[3]),
            cv.reshape(-1, cv.shape[2] * cv.shape[3]), layout.cache_mask(pmask).astype(jnp.int32), smask)


def kernel_attention(cfg, q, k, v, ck, cv, pmask, smask, blocks):
    """`ea.attention` on these inputs (`kernel_operands`) -> (B, S, N H), as the XLA path returns it."""
    b, s = q.shape[:2]
    out = ea.attention(*kernel_operands(cfg, q, k, v, ck, cv, pmask, smask), batch=b, num_heads=cfg.num_heads,
                       num_kv_heads=cfg.num_kv_heads, blocks=blocks)
    return layout.unheads(out.reshape(b, layout.suffix_rows(s), -1)[:, :s], cfg.head_dim)


def _pallas_attention(q, k, v, ck, cv, pmask, smask, splits=4):
    return kernel_attention(CFG, q, k, v, ck, cv, pmask, smask, Blocks(kv=32, kv_splits=splits))


@pytest.mark.parametrize("pi05", [False, True])
def test_attention_matches_xla_with_masked_camera_and_padded_prompt(pi05):
    q, k, v, ck, cv, pmask, smask = _attention_inputs(pi05)
    want = layers._attend(q, [ck, k], [cv, v], [jnp.broadcast_to(pmask[:, None], (B, S, P)), smask], jnp.float32)
    # 6 key blocks of 32: one split; 3 splits of 2 blocks (element 0's second split is all masked: its camera);
    # 4 splits of 2 blocks (the last split lies past the cache)
    for splits in (1, 3, 4):
        np.testing.assert_allclose(_pallas_attention(q, k, v, ck, cv, pmask, smask, splits), want, **TOL)
    # the masks matter: a prefix mask without the masked camera, or π0.5's suffix mask for π0, changes the result
    wrong_prefix = _pallas_attention(q, k, v, ck, cv, pmask.at[0, 64:128].set(True), smask)
    assert not np.allclose(wrong_prefix, want, **TOL)
    if not pi05:
        assert not np.allclose(_pallas_attention(q, k, v, ck, cv, pmask, _suffix_mask(True)), want, **TOL)


def test_the_attention_launches_no_split_past_the_cache(monkeypatch):
    """The prefix's key blocks are shared out so that no split is empty: 6 blocks of 32 keys asked into 4 splits run
    as 3 splits of 2 (and the suffix's part), 16 blocks into 13 as 8 of 2 (π0.5's 1,024 prefix keys)."""
    assert [ea.key_splits(n, s) for n, s in ((16, 13), (13, 13), (6, 4), (6, 3), (6, 1), (2, 13), (0, 13))] == [
        (8, 2), (13, 1), (3, 2), (3, 2), (1, 6), (2, 1), (1, 1)]
    parts = []
    own_merge = ea.merge
    monkeypatch.setattr(ea, "merge", lambda o, lse, *, parts_=parts, **kw: parts_.append(kw["parts"]) or own_merge(
        o, lse, **kw))
    q, k, v, ck, cv, pmask, smask = _attention_inputs(False)
    want = layers._attend(q, [ck, k], [cv, v], [jnp.broadcast_to(pmask[:, None], (B, S, P)), smask], jnp.float32)
    np.testing.assert_allclose(_pallas_attention(q, k, v, ck, cv, pmask, smask, 4), want, **TOL)
    assert parts == [3 + 1]


@pytest.mark.parametrize("pi05", [False, True])
def test_xla_experts_call_of_the_attention_kernel_folds_query_heads(pi05, monkeypatch):
    """`layers._attend_kernel` (the XLA expert on the kernel) with a kv head's 4 query heads folded into its rows
    (44 rows an element, padded to whole query blocks), in one buffer with the suffix's keys and values or apart, or
    not folded, and its masks from `layers.pallas_tables`."""
    q, k, v, ck, cv, pmask, smask = _attention_inputs(pi05)
    want = layers._attend(q, [ck, k], [cv, v], [jnp.broadcast_to(pmask[:, None], (B, S, P)), smask], jnp.float32)
    ck, cv = (layout.cache_kv(c, CFG.head_dim) for c in (ck, cv))
    packed = []
    own = ea.attention
    monkeypatch.setattr(ea, "attention", lambda *a, **kw: packed.append(kw.get("packed", False)) or own(*a, **kw))
    for fold, rows, q_block, pack in ((False, 16, 16, True), (True, 48, 16, True), (True, 64, 32, True),
                                      (True, 48, 16, False)):
        blocks = Blocks(q=q_block, kv=32, kv_splits=3, fold=fold)
        monkeypatch.setattr(ek, "blocks_at", lambda batch, blocks=blocks: blocks)
        monkeypatch.setattr(layers, "PACK_ATTENTION_INPUT", pack)
        assert layers.query_rows(CFG, S, blocks) == rows
        tables = layers.pallas_tables(CFG, jnp.zeros((B, S), jnp.int32), layout.cache_mask(pmask), smask, blocks)
        assert tables[3].shape == (B * rows, layout.suffix_rows(S))
        got = layers._attend_kernel(CFG, q, k, v, ck, cv, *tables[2:])
        np.testing.assert_allclose(got, want.reshape(got.shape), **TOL)
    assert packed == [False, True, True, False]
    with pytest.raises(ValueError, match="suffix rows"):
        own(jnp.zeros((B * 48, ck.shape[-1])), ck, cv, tables[2], tables[3], batch=B, num_heads=1, num_kv_heads=1,
            kv=jnp.zeros((B * S, 2 * ck.shape[-1])))
    with pytest.raises(ValueError, match="packed takes qkv"):   # 48 query rows and no room for the suffix's
        own(jnp.zeros((B * 48, ck.shape[-1])), ck, cv, tables[2], tables[3], batch=B, num_heads=1, num_kv_heads=1,
            packed=True)


def test_attention_merge_cuts_pad_rows_and_quantises():
    """`merge`'s kept and scale: each element's first rows only, in e4m3 as `formats.quantise` makes them from the
    merged output in its dtype (past ±448 scales, saturated); rows cut in the kernel (24 or 20 of 32: blocks of
    8 or 4) or after it (18 of 32), as `merge_xla` does."""
    parts, batch, rows, heads, hd = 3, 2, 32, 2, 64
    o = _rand(60, parts * batch * rows, heads * hd).astype(jnp.bfloat16)
    lse = _rand(61, parts * batch * rows, heads, scale=3.0)
    kw = dict(parts=parts, num_heads=heads, batch=batch)
    full = np.asarray(ea.merge(o, lse, **kw)).reshape(batch, rows, -1)
    np.testing.assert_allclose(full.astype(np.float32), np.asarray(ea.merge_xla(o, lse, **kw), np.float32).reshape(
        full.shape), rtol=1e-2, atol=1e-2)
    scale = jnp.full((1, 1), 0.004, jnp.float32)   # |x| > 1.8 saturates
    for kept in (24, 20, 18):
        cut = ea.merge(o, lse, kept=kept, **kw)
        np.testing.assert_array_equal(cut, full[:, :kept].reshape(batch * kept, -1))
        q = ea.merge(o, lse, kept=kept, scale=scale, **kw)
        assert q.dtype == E4M3 and q.shape == (batch * kept, heads * hd)
        np.testing.assert_array_equal(q.astype(np.float32), formats.quantise(cut, scale).astype(np.float32))
        assert np.abs(q.astype(np.float32)).max() == formats.E4M3_MAX
        qx = ea.merge_xla(o, lse, kept=kept, scale=scale, **kw).astype(np.float32)
        assert qx.shape == q.shape and np.mean(np.asarray(qx) == np.asarray(q.astype(np.float32))) > 0.95


@pytest.mark.parametrize("adaptive", [False, True])
def test_mlp_kernels_match_xla(adaptive):
    w = _layer_weights(30)
    wk = layout.expert_weights(w, CFG)
    x = _rand(40, B, S, CFG.width)
    (mods, row, gate_row), norm_kw, gate = _mods(adaptive, w)
    h, _ = layers.rms_norm(x, **norm_kw)
    gate_up = layout.split_gate_up(h @ w["gate_up"])   # the engine's layout: gate and up in blocks of 32 units
    hidden = jax.nn.gelu(gate_up[0], approximate=True) * gate_up[1]
    down = hidden @ w["down"]
    want = x + (down if gate is None else down * gate)
    sp = layout.suffix_rows(S)
    for splits in (3, 1):
        got_hidden = ek.norm_geglu(layout.rows(x, sp), mods, row, adaptive, wk["gate_up"], width=CFG.width,
                                   blocks=Blocks(mlp=Gemm(64, splits)))
        np.testing.assert_allclose(_unrows(got_hidden, CFG.mlp_dim), hidden, **TOL)
    for splits in (1, 2):  # one kernel, and split-K (96 = 2 x 48)
        gate_kw = {} if gate_row is None else {"gate": mods[gate_row]}
        got = ek.matmul_residual(got_hidden, wk["down"], layout.rows(x, sp), gemm=Gemm(64, splits), **gate_kw)
        np.testing.assert_allclose(_unrows(got, CFG.width), want, **TOL)


def test_split_k_kernel_widens_an_e4m3_weight_exactly():
    """An e4m3 weight (weight-only FP8, `scripts/fp8_expert_probe.py`) enters the split-K GEMM widened to the
    activation dtype: the partials (and the norm's sums of squares) equal those of the same weight widened first."""
    x = _rand(50, 32, 64).astype(jnp.bfloat16)
    w = _rand(51, 64, 48, scale=0.1)
    w8 = (w / (jnp.max(jnp.abs(w)) / 448)).astype(E4M3)
    got = ek.matmul_partials(x, w8, jnp.zeros((1, 64), jnp.bfloat16), scaled=True, gemm=Gemm(16, 2))
    want = ek.matmul_partials(x, w8.astype(jnp.bfloat16), jnp.zeros((1, 64), jnp.bfloat16), scaled=True,
                              gemm=Gemm(16, 2))
    assert got[0].dtype == jnp.float32
    for g, ww in zip(got[:2], want[:2]):
        np.testing.assert_array_equal(np.asarray(g), np.asarray(ww))


@pytest.fixture(scope="module", params=["dummy", "dummy_pi05"])
def model(request):
    config = get_config(request.param)
    return config, randomize(pi0.param_shapes(config))   # every leaf redrawn: init values are never read


def test_engine_with_kernels_matches_reference(model):
    """Element 1 has its last camera masked and prompts are padded (valid 13 / 31 of a 32 bucket)."""
    config, params = model
    obs = make_obs(config)
    noise = jax.random.normal(jax.random.key(1), (2, config.action_horizon, config.action_dim))
    ref = jax.jit(pi0.sample_actions, static_argnums=(0, 4))(config, params, obs, noise, 3)
    engine = Engine(config, params, kernels="pallas", cache_dir=False)
    np.testing.assert_allclose(engine.sample_actions(obs, jnp.array(noise), 3), ref, **TOL)
    _, cache, staged = engine.run_stages(obs, jnp.array(noise), 3)
    assert cache.mask.shape[1] % layout.KEY_PAD == 0 and cache.k[0].shape[-1] == 2 * layout.half_dim(16)
    np.testing.assert_allclose(staged, ref, **TOL)


def test_xla_expert_with_the_attention_kernel_matches_reference(model, monkeypatch):
    """attention denoise=pallas: the XLA expert's layers with the Pallas split-key attention over a cache in its
    layout, layers unrolled or scanned (a stacked cache), with the prefix's fused attention (valid keys first) or
    XLA's, the query heads folded into rows or not (`blocks_at` folds from B = 8). Element 1 has its last camera
    masked and its prompt padded."""
    config, params = model
    obs = make_obs(config)
    noise = jax.random.normal(jax.random.key(3), (2, config.action_horizon, config.action_dim))
    ref = jax.jit(pi0.sample_actions, static_argnums=(0, 4))(config, params, obs, noise, 2)
    at = ek.blocks_at
    assert not at(2).fold and at(8).fold
    for unroll, attention, fold in ((True, "denoise=pallas", False), (False, "prefix=cudnn,denoise=pallas", True)):
        monkeypatch.setattr(ek, "blocks_at", lambda batch, fold=fold: dataclasses.replace(at(batch), fold=fold))
        engine = Engine(config, params, kernels="xla", attention=attention, unroll=unroll, cache_dir=False)
        _, cache, got = engine.run_stages(obs, jnp.array(noise), 2)
        assert cache.mask.shape[1] % layout.KEY_PAD == 0, cache.mask.shape
        np.testing.assert_allclose(got, ref, **TOL)


def test_fp8_expert_rows_padded_to_16_leave_the_actions(monkeypatch):
    """`programs.FP8_ROW_PAD`: with FP8 x FP8 expert weights (`every-gemm`, fixed scales) and the Pallas attention,
    π0's 2 x 11 step rows run as 2 x 16 (the multiple of 16 that cuBLASLt's FP8 GEMM takes), the extra rows masked
    as keys: the actions are those of the unpadded step. Where the step pads nothing: π0.5, bf16, another attention, rows
    already a multiple of 16, or a pad that no whole row count per element reaches (B = 5)."""
    config = get_config("dummy")
    params = randomize(pi0.param_shapes(config))
    obs = make_obs(config)
    depth = {"img": config.siglip.depth, "vlm": config.paligemma.depth, "expert": config.action_expert.depth}
    amax = {key: np.full(() if key == "img/head" else depth[key.split("/")[0]], 4.0, np.float32)   # no calibration
            for *_, key in schemes._leaves("every-gemm")}
    qp = schemes.quantize_params(params, "every-gemm", amax)
    noise = jnp.asarray(jax.random.normal(jax.random.key(4), (2, config.action_horizon, config.action_dim)))
    pads = []
    own = programs.fp8_row_pad
    monkeypatch.setattr(programs, "fp8_row_pad", lambda *a: pads.append(own(*a)) or pads[-1])

    engine = Engine(config, qp, kernels="xla", attention="denoise=pallas", cache_dir=False)

    def actions():   # traced anew: the switch is read when a program is traced
        return np.asarray(Engine(config, qp, kernels="xla", attention="denoise=pallas",
                                 cache_dir=False).sample_actions(obs, noise, 2))

    padded = actions()
    assert pads and set(pads) == {5}   # 11 + 5 rows an element: 32 a step
    monkeypatch.setattr(layers, "ATTENTION_ENDS_IN_MERGE", False)   # out-projection's e4m3 input made by XLA
    np.testing.assert_allclose(padded, actions(), **TOL)
    monkeypatch.setattr(layers, "ATTENTION_ENDS_IN_MERGE", True)
    monkeypatch.setattr(programs, "FP8_ROW_PAD", False)
    pads.clear()
    np.testing.assert_allclose(padded, actions(), **TOL)
    assert set(pads) == {0}
    monkeypatch.setattr(programs, "FP8_ROW_PAD", True)
    pallas = paths.Attention(vision="xla", prefix="xla", denoise="pallas")
    w = engine.weights
    assert own(config, w, 2, 11, pallas) == 5 and own(config, w, 8, 11, pallas) == 1   # 88 -> 96 rows
    assert own(config, w, 5, 11, pallas) == 0   # 55 -> 64 rows: not a whole count per element
    assert own(config, w, 16, 11, pallas) == 0 and own(config, w, 2, 8, pallas) == 0   # already 16-aligned
    assert own(config, w, 2, 11, dataclasses.replace(pallas, denoise="xla")) == 0
    plain = Engine(config, params, kernels="xla", cache_dir=False).weights
    assert own(config, plain, 2, 11, pallas) == 0   # weights not FP8 x FP8
    assert own(get_config("dummy_pi05"), w, 2, 11, pallas) == 0


def test_engine_with_kernels_skips_a_camera_masked_everywhere():
    """Also with the fused prefix attention, whose cache puts each element's valid keys first."""
    config = get_config("dummy")
    params = randomize(pi0.param_shapes(config))
    obs = make_obs(config, valid_lens=(5, 21))
    last = IMAGE_KEYS[config.num_cameras - 1]
    obs = obs.replace(image_masks={**obs.image_masks, last: jnp.zeros((2,), bool)})
    noise = jax.random.normal(jax.random.key(2), (2, config.action_horizon, config.action_dim))
    ref = jax.jit(pi0.sample_actions, static_argnums=(0, 4))(config, params, obs, noise, 2)
    engine = Engine(config, params, kernels="pallas", attention="prefix=cudnn", cache_dir=False)
    assert engine.plan(obs)[0] == IMAGE_KEYS[:config.num_cameras - 1]      # the masked camera is not encoded
    np.testing.assert_allclose(engine.sample_actions(obs, jnp.array(noise), 2), ref, **TOL)


@pytest.mark.parametrize("head_dim", [20, 64, 72])
def test_vision_attention_kernel_matches_xla(head_dim):
    """SigLIP's attention kernel reads q, k, v in place from the fused GEMM's output. Head dims: 20 (the dummy
    tower's: two overlapping pieces), 64 (one piece), 72 (So400m's: 64 + the last 16). f32 against Flax's attention;
    bf16 against f32 within bf16 rounding."""
    import flax.linen as nn

    from pi0_jax.ops import vision_attention as va

    images, t, heads = 3, 64, 2
    qkv = _rand(7, images * t, 3 * heads * head_dim)
    x = qkv.reshape(images, t, 3, heads, head_dim)
    ref = nn.dot_product_attention(x[:, :, 0], x[:, :, 1], x[:, :, 2]).reshape(images * t, heads * head_dim)
    for blocks in (va.Blocks(), va.Blocks(q=16, kv=32)):   # one key block, and an online softmax over two
        got = va.attention(qkv, images=images, num_heads=heads, blocks=blocks)
        np.testing.assert_allclose(got, ref, **TOL)
    low = va.attention(qkv.astype(jnp.bfloat16), images=images, num_heads=heads).astype(jnp.float32)
    assert float(jnp.linalg.norm(low - ref) / jnp.linalg.norm(ref)) < 1e-2
    assert [p[1] for p in va.pieces(head_dim)] == {20: [16, 16], 64: [64], 72: [64, 16]}[head_dim]
    with pytest.raises(ValueError, match="head dim"):
        va.pieces(8)
    with pytest.raises(ValueError, match="not 5 images"):
        va.attention(qkv, images=5, num_heads=heads)
    with pytest.raises(ValueError, match="T divisible by 16"):
        va.attention(qkv[: images * 8], images=images, num_heads=heads)


@pytest.mark.parametrize("width", [40, 1152])
def test_layer_norm_kernel_matches_xla(width):
    """SigLIP's LayerNorm kernel, alone and with the residual add (a Dense's product and bias) before it, against the
    engine's XLA path: widths 40 (the dummy tower's, 5 chunks of 8) and 1152 (So400m's, 9 chunks of 128), 24 rows
    in blocks of 8; and again in blocks of 2 rows and 16 columns (72 chunks); f32 1e-5, bf16 to its rounding."""
    from pi0_jax.engine import vision
    from pi0_jax.ops import layer_norm as ln

    x, y = _rand(1, 2, 12, width, scale=3.0) + 1.5, _rand(2, 2, 12, width)
    # one table as a block's `vectors`: a zero row, then the norm's scale and bias (rows 1, 2), then y's bias
    table = jnp.stack([jnp.zeros(width), _rand(3, width), _rand(4, width), _rand(5, width)])
    norm = (table, (1, 2))
    for f in (None, (y, (table, 3))):
        want = vision.add_norm(x, f, norm, jnp.float32, "xla")
        for blocks in (ln.Blocks(), ln.Blocks(rows=2, cols=16)):
            got = (x, ln.layer_norm(x, table, (1, 2), blocks=blocks)) if f is None else ln.layer_norm(
                x, table, (1, 2), residual=(y, table, 3), blocks=blocks)
            for g, w in zip(got, want):
                np.testing.assert_allclose(g, w, **TOL)
    low = lambda a: a.astype(jnp.bfloat16)  # noqa: E731
    want = vision.add_norm(low(x), (low(y), (table, 3)), norm, jnp.bfloat16, "xla")
    got = vision.add_norm(low(x), (low(y), (table, 3)), norm, jnp.bfloat16, "pallas")
    assert got[0].dtype == got[1].dtype == jnp.bfloat16
    np.testing.assert_array_equal(got[0], want[0])   # the same two bf16 roundings
    np.testing.assert_allclose(got[1].astype(jnp.float32), want[1].astype(jnp.float32), rtol=1e-2, atol=1e-2)
    # the rows matter: another row as the bias changes the result
    assert not np.allclose(ln.layer_norm(x, table, (1, 3)), vision.add_norm(x, None, norm, jnp.float32, "xla")[1])
    with pytest.raises(ValueError, match=r"vectors \(4, 3\)"):
        ln.layer_norm(x, table[:, :3], (1, 2))
    with pytest.raises(ValueError, match="rows \\(1, 4\\)"):
        ln.layer_norm(x, table, (1, 4))
    with pytest.raises(ValueError, match="residual"):
        ln.layer_norm(x, table, (1, 2), residual=(y[:1], table, 3))


def test_layer_norm_kernel_reads_the_block_tables_in_place():
    """In the engine's tower every LayerNorm kernel takes its vectors as the blocks' whole `vectors` table, (L, R, D)
    seen as (L R, D) (a reshape: on a GPU a bitcast), or the encoder's final `norm` table, rows chosen statically: no
    slice of a weight is made before the kernel, which on a GPU would be a copy kernel of its own
    (docs/BENCHMARKS.md, "The host's share of a call")."""
    import functools

    from pi0_jax import benchmark
    from pi0_jax.engine import paths, programs

    config = get_config("dummy", dtype="float32")
    engine = Engine(config, benchmark.random_params(config, 0), cache_dir=False)
    images = jax.ShapeDtypeStruct((2, 1, config.image_size, config.image_size, 3), jnp.float32)
    fn = functools.partial(programs.encode_images, config, unroll=True,
                           attention=paths.Attention(vision="pallas"), kernels="pallas")
    jaxpr = jax.make_jaxpr(fn)(engine.weights, images).jaxpr
    norms = [e for e in jaxpr.eqns
             if e.primitive.name == "custom_partitioning" and "name=layer_norm" in str(e.params["call"])]
    assert len(norms) == 2 * config.siglip.depth + 1
    tables = {id(v) for v in jaxpr.invars if v.aval.ndim in (2, 3) and v.aval.shape[-1] == config.siglip.width}
    tables |= {id(e.outvars[0]) for e in jaxpr.eqns if e.primitive.name == "reshape" and id(e.invars[0]) in tables}
    for eqn in norms:   # (x, vectors, act) or (x, f, f_vectors, f_scale, vectors, act)
        operands = [eqn.invars[1]] if len(eqn.invars) == 3 else [eqn.invars[2], eqn.invars[4]]
        assert all(id(v) in tables for v in operands)


def _e4m3_close(got, want):
    """e4m3 tensors from two paths whose inputs agree to f32 rounding: equal but for rare ties broken apart, each
    one e4m3 step (2^-3 relative) at most."""
    assert got.dtype == want.dtype == jnp.float8_e4m3fn
    g, w = np.asarray(got, np.float32), np.asarray(want, np.float32)
    assert np.mean(g != w) < 1e-3
    np.testing.assert_allclose(g, w, rtol=2.0**-3, atol=2.0**-9)


def test_fp8_ends_in_the_vision_kernels_match_xla():
    """With FP8 GEMMs in SigLIP, the LayerNorm kernel scales the residual's raw product (its FP8 output scale) as it
    adds it and writes the next GEMM's e4m3 input, and the attention kernel takes the raw q/k/v product with its
    scale and bias and writes the out-projection's e4m3 input: each equals XLA's ops (`formats.quantise`,
    `vision._finish`) to f32 rounding, the attention with k's and v's scales moved where they cost least. f32,
    So400m's widths (1152, 16 heads of 72), 2 images of 16 tokens."""
    import flax.linen as nn

    from pi0_jax.engine import vision
    from pi0_jax.ops import formats, layer_norm as ln, vision_attention as va

    width, heads, hd = 1152, 16, 72
    x, y = _rand(1, 2, 16, width, scale=3.0) + 1.5, _rand(2, 2, 16, width, scale=20.0)
    table, y_scale = jnp.stack([_rand(3, width), _rand(4, width), _rand(5, width)]), _rand(6, width) * 0.1
    norm = (table, (0, 1))   # y's bias at row 2
    act = jnp.float32(4.0 / 448)   # |LN| up to ~4 fills e4m3's range; larger values saturate
    for f in (None, (y, (table, 2), y_scale)):
        want = vision.add_norm(x, f, norm, jnp.float32, "xla", quantise=act)
        got = vision.add_norm(x, f, norm, jnp.float32, "pallas", quantise=act)
        np.testing.assert_allclose(got[0], want[0], **TOL)
        _e4m3_close(got[1], want[1])
    assert float(jnp.max(jnp.abs(want[0] - vision.add_norm(x, f[:2], norm, jnp.float32, "xla")[0]))) > 1e-2
    with pytest.raises(ValueError, match="residual"):
        ln.layer_norm(x, table, (0, 1), residual=(y, table, 2, y_scale[:3]))

    qkv = _rand(7, 2 * 16, 3 * heads * hd, scale=8.0)
    q_scale, q_bias = jnp.abs(_rand(8, 3 * heads * hd)) * 0.1 + 0.05, _rand(9, 3 * heads * hd)
    act = jnp.float32(2.0 / 448)
    z = va.scale_bias(qkv, q_scale, q_bias).reshape(2, 16, 3, heads, hd)
    want = formats.quantise(nn.dot_product_attention(z[:, :, 0], z[:, :, 1], z[:, :, 2]).reshape(32, -1), act)
    _e4m3_close(va.attention(qkv, images=2, num_heads=heads, col_scale=q_scale, bias=q_bias, quantise=act), want)
    with pytest.raises(ValueError, match="col_scale and bias go together"):
        va.attention(qkv, images=2, num_heads=heads, col_scale=q_scale)


def test_fp8_vision_quantises_only_the_mlp_in_xla_with_the_kernels():
    """The engine's FP8 tower with the LayerNorm and attention kernels leaves XLA one e4m3 conversion per block
    (the GELU output, fc2's input) where XLA's path has four (before q/k/v, the out-projection, fc1 and fc2)."""
    import functools

    from pi0_jax import benchmark
    from pi0_jax.engine import paths, programs
    from pi0_jax.quant import schemes

    config = get_config("dummy", dtype="float32")
    params = benchmark.random_params(config, 0)
    calib = schemes.sample_observations(config, 1, seed=1)
    qp = schemes.quantize_params(params, "vision",
                                 schemes.calibrate(config, params, calib, "vision", percentile=None)["amax"])
    engine = Engine(config, qp, cache_dir=False)
    images = jax.ShapeDtypeStruct((2, 1, config.image_size, config.image_size, 3), jnp.float32)

    def outside_kernels(jaxpr) -> int:   # e4m3 conversions, not counting those inside kernels
        n = 0
        for eqn in jaxpr.eqns:
            if eqn.primitive.name in ("pallas_call", "custom_partitioning"):
                continue
            n += eqn.primitive.name == "convert_element_type" and eqn.params["new_dtype"] == jnp.float8_e4m3fn
            n += sum(outside_kernels(sub) for sub in jax.extend.core.jaxprs_in_params(eqn.params))
        return n

    counts = {}
    for attention, kernels in (("xla", "xla"), ("pallas", "pallas")):
        fn = functools.partial(programs.encode_images, config, unroll=True, attention=paths.Attention(
            vision=attention), kernels=kernels)
        counts[kernels] = outside_kernels(jax.make_jaxpr(fn)(engine.weights, images).jaxpr)
    depth = config.siglip.depth   # + 1: the head's input
    assert counts == {"xla": 4 * depth + 1, "pallas": depth + 1}, counts


def test_vision_norm_choice():
    """SigLIP's LayerNorm kernel: as asked, or with kernels="auto" on a GPU from 24 images a call (on a CPU it runs
    interpreted)."""
    from pi0_jax.engine import paths

    n = paths.VISION_NORM_MIN_IMAGES
    assert paths.vision_norm("pallas", 3, "cpu") == "pallas" and paths.vision_norm("xla", n, "gpu") == "xla"
    assert paths.vision_norm("auto", n, "gpu") == "pallas" and paths.vision_norm("auto", n, "cpu") == "xla"
    assert paths.vision_norm("auto", n - 1, "gpu") == "xla"


def test_engine_with_vision_kernel_matches_reference(model):
    """The engine with the Pallas vision attention (the dummy tower: 2 heads of 20) samples the reference's actions;
    element 1's last camera is masked, the prompts padded."""
    config, params = model
    obs = make_obs(config, valid_lens=(13, 21))
    noise = jax.random.normal(jax.random.key(3), (2, config.action_horizon, config.action_dim))
    ref = jax.jit(pi0.sample_actions, static_argnums=(0, 4))(config, params, obs, noise, 2)
    engine = Engine(config, params, attention="vision=pallas", cache_dir=False)
    np.testing.assert_allclose(engine.sample_actions(obs, jnp.array(noise), 2), ref, **TOL)
    both = Engine(config, params, attention="vision=pallas", kernels="pallas", cache_dir=False)  # + the LayerNorm
    np.testing.assert_allclose(both.sample_actions(obs, jnp.array(noise), 2), ref, **TOL)


def test_kernel_flag_is_checked():
    config = get_config("dummy")
    params = randomize(pi0.param_shapes(config))
    with pytest.raises(ValueError, match="kernels must be"):
        Engine(config, params, kernels="triton", cache_dir=False)
    with pytest.raises(ValueError, match="needs unroll"):
        Engine(config, params, kernels="pallas", unroll=False, cache_dir=False)


@pytest.mark.parametrize("hidden", [96, 40])
def test_the_fused_gate_up_weight_splits_back_into_gate_and_up(hidden):
    """The engine's gate/up weight (`engine.weights`) holds gate and up in alternating blocks of 32 units
    (`layout.gate_up_block`; one block of all units where 32 does not divide them), and `split_gate_up` of a product
    with it is the products with openpi's gate and up; the kernel layout pads it in the same blocks."""
    from pi0_jax.engine import weights as engine_weights

    d = 16
    gating = _rand(80, 1, 2, d, hidden)   # openpi's (L, two, D, F)
    fused = engine_weights._expert_weights(
        {"q_einsum": {"w": _rand(81, 1, 2, d, 8)}, "kv_einsum": {"w": _rand(82, 1, 2, 1, d, 8)},
         "attn_vec_einsum": {"w": _rand(83, 1, 2, 8, d)}},
        {"gating_einsum": gating, "linear": _rand(84, 1, hidden, d)}, "", jnp.float32)["gate_up"][0]
    assert layout.gate_up_block(hidden) == (32 if hidden % 32 == 0 else hidden)
    if hidden % 32 == 0:
        np.testing.assert_array_equal(fused[:, 32:64], gating[0, 1, :, :32])   # up of units 0-31 after their gate
    x = _rand(85, 5, d)
    gate, up = layout.split_gate_up(x @ fused)
    np.testing.assert_allclose(gate, x @ gating[0, 0], **TOL)
    np.testing.assert_allclose(up, x @ gating[0, 1], **TOL)
    cfg = CFG.__class__(width=d, depth=1, mlp_dim=hidden, num_heads=2, num_kv_heads=1, head_dim=8)
    padded = layout.expert_weights({"qkv": _rand(86, d, 32), "attn_out": _rand(87, 16, d), "gate_up": fused,
                                    "down": _rand(88, hidden, d)}, cfg)["gate_up"]
    pg, pu = layout.split_gate_up(x @ padded)
    np.testing.assert_allclose(pg[:, :hidden], gate, **TOL)
    np.testing.assert_allclose(pu[:, :hidden], up, **TOL)
    assert not np.any(pg[:, hidden:]) and not np.any(pu[:, hidden:])
