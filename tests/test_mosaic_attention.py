"""The denoise attention's key splits on Mosaic GPU (`pi0_jax.ops.mosaic_attention`, Mosaic GPU's interpreter on CPU)
equal XLA's attention, merged by the Pallas merge kernel or by XLA's ops, with a masked camera, padded prompts and
π0's and π0.5's suffix masks; also through the XLA expert's call with a kv head's query heads folded into rows. The
kernel takes whole 64-blocks, so these shapes are their own: two heads of 64 (one kv head), 40 suffix tokens (64
rows), a 100-key prefix (padded to 128, two blocks). f32: the kernel and XLA differ only in summation order."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pi0_jax import gemma, pi0
from pi0_jax.config import GemmaConfig
from pi0_jax.engine import layers
from pi0_jax.ops import expert_attention as ea
from pi0_jax.ops import expert_kernels as ek
from pi0_jax.ops import layout, mosaic_attention
from test_kernels import kernel_attention, kernel_operands

TOL = {"rtol": 1e-5, "atol": 1e-5}
CFG = GemmaConfig(width=128, depth=1, mlp_dim=256, num_heads=2, num_kv_heads=1, head_dim=64)
B, S, P = 2, 40, 100


def _rand(key, *shape):
    return jax.random.normal(jax.random.key(key), shape, jnp.float32)


def _inputs(pi05: bool):
    n, kh, h = CFG.num_heads, CFG.num_kv_heads, CFG.head_dim
    q = _rand(0, B, S, kh, n // kh, h)
    k, v = _rand(1, B, S, kh, h), _rand(2, B, S, kh, h)
    ck, cv = _rand(3, B, P, kh, h), _rand(4, B, P, kh, h)
    idx = np.arange(P)   # element 0: keys 40-79 masked (a camera) and a short prompt; element 1: a longer prompt
    pmask = jnp.asarray(np.stack([(idx < 40) | ((idx >= 80) & (idx < 90)), idx < 97]))
    ar = [True, True] + [False] * (S - 2) if not pi05 else [True] + [False] * (S - 1)
    smask = jnp.broadcast_to(pi0.make_attn_mask(jnp.ones((1, S), bool), jnp.asarray(ar)), (B, S, S))
    want = layers._attend(q, [ck, k], [cv, v], [jnp.broadcast_to(pmask[:, None], (B, S, P)), smask], jnp.float32)
    return (q, k, v, ck, cv, pmask, smask), want


_kernel_attention = functools.partial(kernel_attention, CFG)


def test_constants_are_the_models():
    assert mosaic_attention.BIG_NEG == ea.BIG_NEG == gemma._BIG_NEG
    assert mosaic_attention.BLOCK == layout.KEY_PAD


def test_suffix_ends():
    """A row's visible suffix keys as a count: π0's state row sees 1, its action rows all 40, padded rows none."""
    sp = layout.suffix_rows(S)
    smask = jnp.pad(_inputs(False)[0][-1], ((0, 0), (0, sp - S), (0, sp - S))).reshape(B * sp, sp)
    ends = mosaic_attention.suffix_ends(smask.astype(jnp.int32))
    np.testing.assert_array_equal(ends[:sp], [1] + [S] * (S - 1) + [0] * (sp - S))
    np.testing.assert_array_equal(jnp.arange(sp)[None] < ends[:, None], smask)   # the mask is exactly its prefix


@pytest.mark.parametrize("pi05", [False, True])
def test_mosaic_attention_matches_xla(pi05, monkeypatch):
    args, want = _inputs(pi05)
    # 3 key blocks (2 of the prefix, the suffix's): one run of all three, two runs of two (the second's last block lies
    # past the keys, masked), three runs of one (element 0's first block is half masked); through a ring of as many
    # slots as fit (3 here) and of 2 (the first slot refilled with the third block)
    for ring in (None, 2):
        if ring:
            monkeypatch.setattr(mosaic_attention, "max_slots", lambda *a: ring)
        for splits in (0, 1, 2):
            for xla_merge in (False, True):
                blocks = ek.Blocks(mosaic_attention=True, xla_merge=xla_merge, kv_splits=splits)
                np.testing.assert_allclose(_kernel_attention(*args, blocks), want, **TOL)
    # the masks matter: the camera unmasked, or π0.5's suffix mask for π0, changes the result
    blocks = ek.Blocks(mosaic_attention=True)
    q, k, v, ck, cv, pmask, smask = args
    wrong = _kernel_attention(q, k, v, ck, cv, pmask.at[0, 40:80].set(True), smask, blocks)
    assert not np.allclose(wrong, want, **TOL)
    if not pi05:
        other = _inputs(True)[0][-1]
        assert not np.allclose(_kernel_attention(q, k, v, ck, cv, pmask, other, blocks), want, **TOL)


def test_kernel_splits_equal_the_triton_kernels(monkeypatch):
    """The Mosaic kernel's per-split outputs and log-sum-exps are the Triton kernel's (lse in its own layout)."""
    qkv, ck, cv, pmask, smask = kernel_operands(CFG, *_inputs(False)[0])
    sp, h = layout.suffix_rows(S), CFG.head_dim
    monkeypatch.setattr(ea, "merge_xla", lambda o, lse, **kw: (o, lse))   # the splits themselves
    (o_t, lse_t), (o_m, lse_m) = (
        ea._attention(qkv, qkv, ck, cv, pmask, smask, None, B, CFG.num_heads, CFG.num_kv_heads, (2 * h, 3 * h),
                      ek.Blocks(mosaic_attention=mosaic, xla_merge=True, kv_splits=2))
        for mosaic in (False, True))
    assert o_t.shape == o_m.shape == (3 * B * sp, 2 * h) and lse_m.shape == (3, CFG.num_heads, B * sp)
    rows = np.concatenate([np.arange(S), sp + np.arange(S)])   # each element's real rows
    o_t, o_m = (np.asarray(o).reshape(3, B * sp, -1)[:, rows] for o in (o_t, o_m))
    np.testing.assert_allclose(o_m, o_t, **TOL)
    lse_t = np.asarray(lse_t).reshape(3, B * sp, -1).transpose(0, 2, 1)[:, :, rows]
    np.testing.assert_allclose(np.asarray(lse_m)[:, :, rows], lse_t, **TOL)


@pytest.mark.parametrize("pi05", [False, True])
def test_xla_experts_call_folds_query_heads_on_the_mosaic_kernel(pi05, monkeypatch):
    """`layers._attend_kernel` with a kv head's 2 query heads folded into its rows (80 an element, padded to 128)."""
    (q, k, v, ck, cv, pmask, smask), want = _inputs(pi05)
    blocks = ek.Blocks(q=64, kv=64, kv_splits=2, fold=True, mosaic_attention=True)
    monkeypatch.setattr(ek, "blocks_at", lambda batch: blocks)
    ck, cv = (layout.cache_kv(c, CFG.head_dim) for c in (ck, cv))
    tables = layers.pallas_tables(CFG, jnp.zeros((B, S), jnp.int32), layout.cache_mask(pmask), smask, blocks)
    got = layers._attend_kernel(CFG, q, k, v, ck, cv, *tables[2:])
    np.testing.assert_allclose(got, want.reshape(got.shape), **TOL)


def test_applies_and_shared_memory():
    shapes = dict(head_dim=64, query_rows=64, suffix_keys=64, prefix_keys=128)
    assert mosaic_attention.applies(jnp.float32, **shapes)
    for name in shapes:   # every dimension in whole blocks
        assert not mosaic_attention.applies(jnp.float32, **{**shapes, name: 48})
    assert not mosaic_attention.applies(jnp.float32, **{**shapes, "suffix_keys": 128})   # the suffix is one block
    # at head_dim 256 a CTA holds two 64-key blocks in shared memory beside q and p
    assert mosaic_attention.max_slots(256, jnp.bfloat16) == 2
    assert mosaic_attention.max_slots(64, jnp.float32) >= 4
    q = jax.ShapeDtypeStruct((64, 4 * 256), jnp.bfloat16)
    cache = jax.ShapeDtypeStruct((192, 256), jnp.bfloat16)
    operands = (q, q, cache, cache, jax.ShapeDtypeStruct((1, 192), jnp.int32), jax.ShapeDtypeStruct((64,), jnp.int32))
    for splits, parts in ((1, 1), (2, 2), (3, 2), (4, 4), (9, 4)):   # 4 key blocks: 3 of the prefix, the suffix
        o, lse = jax.eval_shape(functools.partial(mosaic_attention.attention, batch=1, num_heads=2, num_kv_heads=1,
                                                  kv_cols=(512, 768), sk=64, splits=splits), *operands)
        assert lse.shape == (parts, 2, 64) and o.shape == (parts * 64, 512)


def test_blocks_at_a_batch_keeps_short_splits_on_the_mosaic_kernel():
    """The XLA expert's attention launch: the Triton kernel's splits shared out over the batch, the Mosaic kernel's
    half the base launch's at any batch (π0's 13 prefix blocks and the suffix's: 7 parts of 2 blocks)."""
    assert ek.blocks_at(8, ek.Blocks()).kv_splits == 2 and ek.blocks_at(1, ek.Blocks()).kv_splits == 13
    for batch in (1, 3, 8, 16):
        at = ek.blocks_at(batch, ek.TRITON_FREE)
        assert at.kv_splits == 6 and at.fold == (batch >= 8)
    splits = ek.blocks_at(8, ek.TRITON_FREE).kv_splits + 1   # as `ea._attention` passes it
    shape = functools.partial(jax.ShapeDtypeStruct, dtype=jnp.bfloat16)
    args = (shape((8 * 448, 256)), shape((8 * 64, 512)), shape((8 * 832, 256)), shape((8 * 832, 256)),
            jax.ShapeDtypeStruct((8, 832), jnp.int32), jax.ShapeDtypeStruct((8 * 448,), jnp.int32))
    _, lse = jax.eval_shape(functools.partial(mosaic_attention.attention, batch=8, num_heads=1, num_kv_heads=1,
                                              kv_cols=(0, 256), sk=64, splits=splits), *args)
    assert lse.shape == (7, 1, 8 * 448)


@pytest.mark.parametrize("pi05", [False, True])
def test_expert_without_triton_equals_xla(pi05, monkeypatch):
    """The Pallas expert on Mosaic GPU kernels alone (`ek.TRITON_FREE`'s form, at launches this expert tiles), as on a
    jax without Pallas's Triton backend: no Triton kernel is called, the merge is XLA's, and the layers equal XLA's."""
    from pi0_jax.ops import pallas_base
    from pi0_jax.ops.mosaic_gemm import Launch

    d, f, n, kh, h = CFG.width, CFG.mlp_dim, CFG.num_heads, CFG.num_kv_heads, CFG.head_dim
    w = {"qkv": _rand(10, d, (n + 2 * kh) * h) * d**-0.5, "attn_out": _rand(11, n * h, d) * 0.1,
         "gate_up": _rand(12, d, 2 * f) * d**-0.5, "down": _rand(13, f, d) * f**-0.5}
    mods = (_rand(14, 1, 3 * d) * 0.3, _rand(15, 1, 3 * d) * 0.3) if pi05 else None
    if not pi05:
        w.update(pre_attn=_rand(16, d) * 0.2, pre_ffw=_rand(17, d) * 0.2)
    (_, _, _, ck, cv, pmask, smask), _ = _inputs(pi05)
    x, positions = _rand(18, B, S, d), 100 + jnp.arange(S)[None].repeat(B, 0)
    want, _, _ = layers.suffix_layer(CFG, w, x, gemma.rope_angles(positions, CFG.head_dim), ck, cv,
                                     jnp.broadcast_to(pmask[:, None], (B, S, P)), smask, mods)
    blocks = ek.Blocks(mosaic_qkv=Launch(64, 2, 2), mosaic_mlp=Launch(64, 1, 3, geglu=True),
                       mosaic_out=Launch(64, 2, 1, 2), mosaic_down=Launch(128, 4, 1), mosaic_attention=True)
    assert ek.TRITON_FREE.mosaic_attention and ek.TRITON_FREE.xla_merge
    monkeypatch.setattr(pallas_base, "TRITON", False)   # the merge then runs as XLA's ops
    monkeypatch.setattr(pallas_base, "call", lambda *a, **kw: pytest.fail(f"a Triton kernel: {kw.get('name')}"))
    cache_k, cache_v = ([layout.cache_kv(c, h)] for c in (ck, cv))
    got = layers.suffix_layers_pallas(CFG, [w], x, positions, cache_k, cache_v, layout.cache_mask(pmask), smask, mods,
                                      blocks=blocks)
    np.testing.assert_allclose(got, want, **TOL)


def test_kernel_lowers_for_hopper(monkeypatch):
    """The GPU form (not the interpreter's) lowers for sm_90 on this CPU, bf16 at π0's denoise shape: 8 heads of 256
    on one kv head, 64 suffix rows, 832 prefix keys in 4 splits."""
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")   # the kernel picks the GPU form by the backend
    bf, aval = jnp.bfloat16, jax.ShapeDtypeStruct
    m, hd, pp, n = 64, 256, 832, 8
    args = (aval((m, n * hd), bf), aval((m, 2 * hd), bf), aval((pp, hd), bf), aval((pp, hd), bf),
            aval((1, pp), jnp.int32), aval((m,), jnp.int32))
    call = functools.partial(mosaic_attention.attention, batch=1, num_heads=n, num_kv_heads=1, kv_cols=(0, hd),
                             sk=m, splits=4)
    text = jax.jit(call).trace(*args).lower(lowering_platforms=("cuda",)).as_text()
    assert "mosaic_gpu" in text and f"tensor<{4 * m}x{n * hd}xbf16>" in text
