"""SigLIP's attention on Mosaic GPU (`pi0_jax.ops.mosaic_vision_attention`, Mosaic GPU's interpreter on CPU) equals
Flax's attention: head dims 20 (the dummy tower's), 24 and 72 (So400m's) in f32 to 1e-5 and in bf16 to its rounding,
images of 64 and 256 tokens, two and four heads (the kernel takes them in pairs); the engine's tower with it equals
the reference sampler; and its GPU form lowers for sm_90 here."""

import functools

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pi0_jax import pi0
from pi0_jax.config import get_config
from pi0_jax.engine import Engine
from pi0_jax.ops import mosaic_vision_attention as mva
from pi0_jax.ops import vision_attention
from test_model import make_obs, randomize

TOL = {"rtol": 1e-5, "atol": 1e-5}


def _qkv(images, tokens, heads, head_dim, dtype=jnp.float32):
    qkv = jax.random.normal(jax.random.key(head_dim), (images * tokens, 3 * heads * head_dim), jnp.float32)
    return qkv.astype(dtype)


def _flax(qkv, images, heads):
    r, c = qkv.shape
    hd = c // (3 * heads)
    x = qkv.astype(jnp.float32).reshape(images, r // images, 3, heads, hd)
    return nn.dot_product_attention(x[:, :, 0], x[:, :, 1], x[:, :, 2]).reshape(r, heads * hd)


@pytest.mark.parametrize("images,tokens,heads,head_dim", [(3, 64, 2, 20), (2, 64, 4, 24), (1, 64, 2, 72)])
def test_kernel_matches_flax_f32(images, tokens, heads, head_dim):
    """Every head of every image: each of a pair's two windows (at 20 and 24 the second starts inside the first
    head, at 72 at column 64)."""
    qkv = _qkv(images, tokens, heads, head_dim)
    np.testing.assert_allclose(mva.attention(qkv, images=images, num_heads=heads), _flax(qkv, images, heads), **TOL)


def test_kernel_bf16_at_so400m_shape():
    """So400m's head (72) and image (256 tokens) in bf16, where the f32 form does not fit a CTA's shared memory: within
    bf16's rounding of the f32 attention of the same inputs; and the heads of a pair are not swapped or mixed (each
    head's output against the other head's attention is far off)."""
    qkv = _qkv(1, 256, 4, 72, jnp.bfloat16)
    assert not mva.applies(jnp.float32, tokens=256, num_heads=4, head_dim=72)
    got = mva.attention(qkv, images=1, num_heads=4).astype(jnp.float32)
    want = _flax(qkv, 1, 4)
    assert float(jnp.linalg.norm(got - want) / jnp.linalg.norm(want)) < 4e-3
    swapped = want.reshape(256, 2, 2, 72)[:, :, ::-1].reshape(256, -1)
    assert float(jnp.linalg.norm(got - swapped) / jnp.linalg.norm(want)) > 0.5


def test_applies_and_refuses():
    assert mva.applies(jnp.bfloat16, tokens=256, num_heads=16, head_dim=72)
    assert not mva.applies(jnp.bfloat16, tokens=256, num_heads=15, head_dim=72)   # heads in pairs
    assert not mva.applies(jnp.bfloat16, tokens=96, num_heads=16, head_dim=72)    # whole 64-row warpgroups
    assert not mva.applies(jnp.bfloat16, tokens=320, num_heads=16, head_dim=72)   # one wgmma's 256 keys
    assert not mva.applies(jnp.bfloat16, tokens=64, num_heads=2, head_dim=20)     # a pair's 80 bytes: no swizzle
    with pytest.raises(ValueError, match="does not take it"):
        mva.attention(_qkv(1, 64, 3, 24), images=1, num_heads=3)


def test_engine_tower_on_the_kernel_matches_the_reference(monkeypatch):
    """The dummy π0 with SigLIP's attention on this kernel (in the interpreter; one element, three cameras, as the
    interpreter takes about 1 s a layer and camera): the engine's actions equal the reference sampler's."""
    calls = []
    own = mva.attention
    monkeypatch.setattr(vision_attention, "MOSAIC", True)
    monkeypatch.setattr(vision_attention, "MOSAIC_ON_CPU", True)
    monkeypatch.setattr(mva, "attention", lambda *a, **kw: calls.append(kw) or own(*a, **kw))
    config = get_config("dummy")
    params = randomize(pi0.param_shapes(config))
    obs = make_obs(config, batch=1, valid_lens=(5,))
    noise = jax.random.normal(jax.random.key(2), (1, config.action_horizon, config.action_dim))
    ref = jax.jit(pi0.sample_actions, static_argnums=(0, 4))(config, params, obs, noise, 2)
    engine = Engine(config, params, kernels="xla", attention="vision=pallas", cache_dir=False)
    np.testing.assert_allclose(engine.sample_actions(obs, jnp.array(noise), 2), ref, **TOL)
    assert calls   # the tower took the kernel


def test_kernel_lowers_for_hopper(monkeypatch):
    """The GPU form (TMA, wgmma; not the interpreter's) lowers for sm_90 on this CPU through Mosaic GPU's layout
    inference, bf16 at π0's B = 1 (3 images of 256 tokens, 16 heads of 72); and the Pallas attention of
    `ops.vision_attention` takes it there with `MOSAIC` on."""
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")   # the kernel picks the GPU form by the backend
    monkeypatch.setattr(mva, "hopper", lambda: True)
    monkeypatch.setattr(vision_attention, "MOSAIC", True)
    qkv = jax.ShapeDtypeStruct((768, 3456), jnp.bfloat16)
    call = functools.partial(vision_attention.attention, images=3, num_heads=16)
    text = jax.jit(call).trace(qkv).lower(lowering_platforms=("cuda",)).as_text()
    assert "mosaic_gpu" in text and "tensor<768x1152xbf16>" in text
    assert "xla.gpu.triton" not in text
