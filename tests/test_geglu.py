"""The prefix MLP's Mosaic GPU kernel (`pi0_jax.ops.geglu`) in Mosaic GPU's interpreter against XLA's path."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pi0_jax.config import GEMMA_VARIANTS
from pi0_jax.engine import layers, programs
from pi0_jax.ops import geglu

# Mosaic GPU's CPU interpreter is not exported by jax.experimental.pallas.mosaic_gpu in this jax
InterpretGPUParams = pytest.importorskip("jax._src.pallas.mosaic_gpu.interpret.params").InterpretGPUParams


def _rel(a, b):
    a, b = (np.asarray(x, np.float64) for x in (a, b))
    return np.linalg.norm(a - b) / np.linalg.norm(b)


@pytest.fixture
def interpret(monkeypatch):
    monkeypatch.setattr(geglu, "INTERPRET", InterpretGPUParams())


def test_kernel_equals_xla_geglu_to_bf16_rounding(interpret):
    """200 rows (padded to the CTA's 128 and cut back), two hidden tiles, two K steps."""
    kx, kw = jax.random.split(jax.random.key(0))
    x = jax.random.normal(kx, (200, 2 * geglu.TILE_K), jnp.float32).astype(jnp.bfloat16)
    w = (jax.random.normal(kw, (2 * geglu.TILE_K, 4 * geglu.TILE_N), jnp.float32) * 0.1).astype(jnp.bfloat16)
    got = geglu.geglu_matmul(x, w)
    gate, up = jnp.split(x @ w, 2, axis=-1)
    want = jax.nn.gelu(gate, approximate=True) * up
    assert got.shape == want.shape == (200, 2 * geglu.TILE_N) and got.dtype == jnp.bfloat16
    assert _rel(got, want) < 4e-3                        # bf16 rounding (XLA rounds after each bf16 op)
    assert _rel(got, jax.nn.gelu(up, approximate=True) * gate) > 0.5   # gate and up are not interchangeable


def test_prefix_layer_with_the_kernel_equals_xla(interpret):
    """One Gemma layer (gemma_small: width 256, MLP 1024) over 2 x 40 tokens, bf16: the kernel's MLP against XLA's."""
    cfg = GEMMA_VARIANTS["gemma_small"]
    keys = iter(jax.random.split(jax.random.key(1), 8))
    d, f, heads = cfg.width, cfg.mlp_dim, (cfg.num_heads + 2 * cfg.num_kv_heads) * cfg.head_dim

    def rand(*shape, scale=0.05):
        return (jax.random.normal(next(keys), shape, jnp.float32) * scale).astype(jnp.bfloat16)

    w = {"pre_attn": rand(d), "pre_ffw": rand(d), "qkv": rand(d, heads), "attn_out": rand(cfg.num_heads * cfg.head_dim, d),
         "gate_up": rand(d, 2 * f), "down": rand(f, d)}
    x = rand(2, 40, d, scale=1.0)
    positions = jnp.broadcast_to(jnp.arange(40), (2, 40))
    mask = jnp.ones((2, 40, 40), bool)
    assert geglu.applies(x.dtype, w["gate_up"])
    got = layers.prefix_layer(cfg, w, x, positions, mask, mlp_kernel=True)
    want = layers.prefix_layer(cfg, w, x, positions, mask, mlp_kernel=False)
    np.testing.assert_array_equal(got[1], want[1])    # k, v come before the MLP
    assert _rel(got[0] - x, want[0] - x) < 1e-2        # the layer's update, bf16


def test_where_the_kernel_applies(monkeypatch):
    w = jnp.zeros((geglu.TILE_K, 2 * geglu.TILE_N), jnp.bfloat16)
    assert not geglu.applies(jnp.bfloat16, w)                       # a CPU
    assert programs.prefix_mlp_path("auto", [{"gate_up": w}], "bfloat16") == "xla"
    monkeypatch.setattr(jax, "device_count", lambda: 1)
    assert geglu.applies(jnp.bfloat16, w, platform="gpu")
    assert programs.prefix_mlp_path("auto", [{"gate_up": w}], "bfloat16", platform="gpu") == "mgpu"
    assert programs.prefix_mlp_path("pallas", {"gate_up": w[None]}, "bfloat16", platform="gpu") == "mgpu"  # stacked
    assert programs.prefix_mlp_path("xla", [{"gate_up": w}], "bfloat16", platform="gpu") == "xla"   # the one flag
    assert not geglu.applies(jnp.float32, w, platform="gpu")                         # bf16 activations only
    assert not geglu.applies(jnp.bfloat16, w.astype(jnp.float32), platform="gpu")   # and weights
    assert not geglu.applies(jnp.bfloat16, w[:, : geglu.TILE_N], platform="gpu")    # F does not tile
    assert not geglu.applies(jnp.bfloat16, w[: geglu.TILE_K // 2], platform="gpu")  # K does not tile
    monkeypatch.setattr(jax, "device_count", lambda: 2)                             # a partitioned program
    assert not geglu.applies(jnp.bfloat16, w, platform="gpu")
