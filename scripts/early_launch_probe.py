"""`pallas_base.EARLY_LAUNCH` on a toy chain (GPU only): 40 Pallas Triton kernels, each followed by an XLA fusion, with
and without the trigger at each kernel's start; the host-timed chain and whether the two chains agree to the bit (a
dependent that read its input too early would not). With `xla_dump_to` under $OUT it also prints the griddepcontrol
instructions of the kernel's PTX where this jaxlib dumps one.

    python3 scripts/early_launch_probe.py
"""
import glob, os, re, sys
import jax, jax.numpy as jnp, numpy as np
from pi0_jax.ops import pallas_base as pb
from jax.experimental import pallas as pl

def kern(x_ref, o_ref):
    i = pl.program_id(0)
    rows = pl.ds(i * 64, 64)
    o_ref[rows, :] = jnp.tanh(x_ref[rows, :] * 1.01) + 0.5

def chain(x, n=40):
    for _ in range(n):
        x = pb.call(kern, grid=(x.shape[0] // 64,), out_shape=jax.ShapeDtypeStruct(x.shape, x.dtype), name="chain",
                    num_warps=4, num_stages=1)(x)
        x = jnp.sin(x) * 1.5
    return x

x = jax.random.normal(jax.random.key(0), (8192, 256), jnp.float32)
outs = {}
for early in (False, True):
    pb.EARLY_LAUNCH = early
    d = f"{os.environ.get('OUT', '/tmp')}/toy_ptx_{int(early)}"
    f = jax.jit(lambda x: chain(x)).lower(x).compile({"xla_dump_to": d})
    outs[early] = np.asarray(f(x))
    for p in sorted(glob.glob(d + "/*.ptx")):
        t = open(p).read()
        if ".entry chain" in t:
            print(early, os.path.basename(p), re.findall(r"griddepcontrol\.\w+", t))
    import time
    for _ in range(3):
        f(x).block_until_ready()
    t0 = time.perf_counter()
    for _ in range(50):
        y = f(x)
    y.block_until_ready()
    print("early" if early else "default", "chain of 40 + 40 fusions:", round((time.perf_counter() - t0) / 50 * 1e6, 1), "us")
print("bit-equal:", bool(np.array_equal(outs[False], outs[True])), "max abs", float(np.max(np.abs(outs[False] - outs[True]))))
pb.EARLY_LAUNCH = False
