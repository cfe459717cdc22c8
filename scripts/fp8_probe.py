"""Which dot patterns does this JAX/XLA rewrite into cuBLASLt FP8 GEMMs? Prints custom-call targets per pattern."""

import re

import jax
import jax.numpy as jnp

E4 = jnp.float8_e4m3fn
M, K, N = 1024, 2048, 4096
x = jax.random.normal(jax.random.key(0), (8, M // 8, K), jnp.bfloat16)
wq = jax.random.normal(jax.random.key(1), (K, N), jnp.float32).astype(E4)
s = jnp.float32(0.01)
cs = jnp.ones((1, N), jnp.float32)


def qx(x, s, dt=jnp.bfloat16):
    return jnp.clip(x.astype(jnp.float32) / s, -448, 448).astype(E4)


patterns = {
    "ours_channel": lambda x, w, s, cs: jnp.einsum("...D,DF->...F", qx(x, s).astype(x.dtype) * s.astype(x.dtype),
                                                   w.astype(x.dtype)) * cs[0].astype(x.dtype),
    "ours_tensor": lambda x, w, s, cs: jnp.einsum("...D,DF->...F", qx(x, s).astype(x.dtype) * s.astype(x.dtype),
                                                  w.astype(x.dtype) * s.astype(x.dtype)),
    "2d_f32scale": lambda x, w, s, cs: jax.lax.dot_general(
        qx(x, s).reshape(-1, K).astype(jnp.bfloat16) * s.astype(jnp.bfloat16),
        w.astype(jnp.bfloat16) * s.astype(jnp.bfloat16), (((1,), (0,)), ((), ())),
        preferred_element_type=jnp.bfloat16),
    "2d_f32_dq": lambda x, w, s, cs: jax.lax.dot_general(
        qx(x, s).reshape(-1, K).astype(jnp.float32) * s, w.astype(jnp.float32) * s, (((1,), (0,)), ((), ())),
        preferred_element_type=jnp.float32).astype(jnp.bfloat16),
    "3d_f32_dq": lambda x, w, s, cs: jnp.einsum("...D,DF->...F", qx(x, s).astype(jnp.float32) * s,
                                                w.astype(jnp.float32) * s,
                                                preferred_element_type=jnp.float32).astype(jnp.bfloat16),
    "2d_nodq": lambda x, w, s, cs: jax.lax.dot_general(
        qx(x, s).reshape(-1, K), w, (((1,), (0,)), ((), ())), preferred_element_type=jnp.bfloat16),
}
from pi0_jax.ops import formats  # noqa: E402

wf = jax.random.normal(jax.random.key(2), (K, N), jnp.float32)
for per_channel in (True, False):
    for act in (0.01, None):
        qa = formats.quantize_fp8(wf, per_channel=per_channel, act_scale=act)
        patterns[f"qmatmul_ch{int(per_channel)}_act{int(act is not None)}"] = (
            lambda x, w, s, cs, qa=qa: formats.qmatmul("BTD,DF->BTF", x, qa))
for name, fn in patterns.items():
    try:
        text = jax.jit(fn).lower(x, wq, s, cs).compile().as_text()
        targets = sorted(set(re.findall(r'custom_call_target="([^"]+)"', text)))
        print(f"{name:14s} f8={text.count('__cublas$lt$matmul$f8')} targets={targets}")
        if name == "qmatmul_ch1_act1":
            print("\n".join(line for line in text.splitlines() if "custom-call" in line or " dot(" in line)[:3000])
    except Exception as e:  # noqa: BLE001
        print(f"{name:14s} ERROR {type(e).__name__}: {str(e)[:300]}")
