"""The prefix fill's attention alone at B = 1 (8 query heads over one kv head, head dim 256; π0: L=816 S=832, π0.5:
L=968 S=1024), a chain of 18 calls in one jit, kernel µs per attention from a jax.profiler trace
(`profile_engine.kernel_times`): cuDNN's flash kernel (the engine's), XLA's ops (two GEMMs and a softmax), and jax's
own Mosaic GPU flash attention (`jax.experimental.pallas.ops.gpu.attention_mgpu`: a TMA warpgroup and two wgmma
warpgroups in ping-pong, as FlashAttention-3; f16 operands only, no masks, no scale), on a kv head's query heads
folded into rows or on 8 heads, and with the keys in two splits merged by XLA. Every variant attends all S keys
(the stock kernel has no length mask), so they compute the same function. A GPU probe (Hopper), not a test.

    L=816 S=832 OUT=. python scripts/prefix_attention_fa3_probe.py
"""
import json
import os
import sys
import time

import jax
import jax.numpy as jnp

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from profile_engine import kernel_times  # noqa: E402
from jax.experimental.pallas.ops.gpu import attention_mgpu as am  # noqa: E402

L, S, H, D = int(os.environ.get("L", 816)), int(os.environ.get("S", 832)), 8, 256
N = 18
key = jax.random.PRNGKey(0)
ks = jax.random.split(key, 3 * N + 1)
bf = jnp.bfloat16
q0 = jax.random.normal(ks[0], (1, L, H, D), bf)
kk = [jax.random.normal(ks[1 + i], (1, S, 1, D), bf) for i in range(N)]
vv = [jax.random.normal(ks[1 + N + i], (1, S, 1, D), bf) for i in range(N)]
kvlen = jnp.array([S], jnp.int32)  # every key, as the stock kernel (no mask)
res = {}

def chain(step):
    @jax.jit
    def f(q, kk, vv):
        for i in range(N):
            q = step(q, kk[i], vv[i])
        return q
    return lambda: f(q0, kk, vv)

def cudnn(q, k, v):
    return jax.nn.dot_product_attention(q, k, v, key_value_seq_lengths=kvlen, implementation="cudnn")

def xla(q, k, v):
    qf = q.reshape(L * H, D)  # rows (token, head)
    s = jnp.einsum("qd,kd->qk", qf, k[0, :, 0], preferred_element_type=jnp.float32) * D**-0.5
    p = jax.nn.softmax(s, axis=-1).astype(bf)
    return jnp.einsum("qk,kd->qd", p, v[0, :, 0]).reshape(1, L, H, D)

def mgpu_folded(cfg, rows):
    def f(q, k, v):
        qf = (q * 0.0625).astype(bf).reshape(1, L * H, 1, D)
        qf = jnp.pad(qf, ((0, 0), (0, rows - L * H), (0, 0), (0, 0))) if rows > L * H else qf
        o = am.attention(qf.astype(jnp.float16), k.astype(jnp.float16), v.astype(jnp.float16), cfg).astype(bf)
        return o[:, :L * H].reshape(1, L, H, D)
    return f

def mgpu_heads(cfg, lq):
    def f(q, k, v):
        qp = jnp.pad((q * 0.0625).astype(bf), ((0, 0), (0, lq - L), (0, 0), (0, 0)))
        return am.attention(qp.astype(jnp.float16), k.astype(jnp.float16), v.astype(jnp.float16), cfg).astype(bf)[:, :L]
    return f

def mgpu_split(cfg, rows, parts):
    per = S // parts
    def f(q, k, v):
        qf = (q * 0.0625).astype(bf).reshape(1, L * H, 1, D)
        qf = jnp.pad(qf, ((0, 0), (0, rows - L * H), (0, 0), (0, 0))) if rows > L * H else qf
        qb = jnp.broadcast_to(qf, (parts, rows, 1, D))
        kb, vb = k.reshape(parts, per, 1, D), v.reshape(parts, per, 1, D)
        o, (lse,) = am.attention(qb.astype(jnp.float16), kb.astype(jnp.float16), vb.astype(jnp.float16), cfg, save_residuals=True)
        lse = lse[:, 0, :, None]  # (parts, rows, 1)
        w = jnp.exp2(lse - jnp.max(lse, axis=0, keepdims=True))
        m = (jnp.sum(o[:, :, 0].astype(jnp.float32) * w, axis=0) / jnp.sum(w, axis=0)).astype(bf)
        return m[:L * H].reshape(1, L, H, D)
    return f

variants = {"cudnn": cudnn, "xla": xla}
for bq, bkv, st in [(64, 64, 2), (64, 64, 3)]:
    cfg = am.TuningConfig(block_q=bq, block_kv=bkv, max_concurrent_steps=st)
    variants[f"mgpu_folded_{bq}_{bkv}_{st}"] = mgpu_folded(cfg, -(-L * H // (2 * bq)) * 2 * bq)
    variants[f"mgpu_heads_{bq}_{bkv}_{st}"] = mgpu_heads(cfg, -(-L // (2 * bq)) * 2 * bq)
cfg = am.TuningConfig(block_q=64, block_kv=64, max_concurrent_steps=2)
for parts in (2,):
    if (S // parts) % 64 == 0:
        variants[f"mgpu_split{parts}"] = mgpu_split(cfg, -(-L * H // 128) * 128, parts)
ref = None
for name, step in variants.items():
    t0 = time.time()
    try:
        fn = chain(step)
        out = jax.block_until_ready(fn())
        if ref is None:
            ref = out.astype(jnp.float32)
        err = float(jnp.linalg.norm(out.astype(jnp.float32) - ref) / jnp.linalg.norm(ref))
        kt = kernel_times(fn, calls=5)
        top = [(r["name"][:60], round(r["us_per_call"] / N, 2), r["per_call"] / N) for r in kt["by_name"][:6]]
        res[name] = {"wall_us_per_attention": kt["wall_ms"] * 1e3 / N, "kernel_us_per_attention": kt["kernel_ms"] * 1e3 / N,
                     "kernels_per_attention": kt["kernels_per_call"] / N, "rel_l2_vs_cudnn": err, "top": top}
    except Exception as e:  # noqa
        res[name] = {"error": repr(e)[:800]}
    print(name, round(time.time() - t0, 1), json.dumps(res[name]), flush=True)
out = os.environ.get("OUT", "/tmp")
json.dump({"L": L, "S": S, "device": str(jax.devices()[0]), "variants": res}, open(f"{out}/prefix_attention_{L}.json", "w"), indent=1)
