"""temporary (session 28): the denoise program at batch B with the XLA expert and attention auto against the
Pallas attention at several (key splits, pipelining depth), round-robin in one process."""
import dataclasses, json, sys
import jax, numpy as np
from pi0_jax import benchmark
from pi0_jax.config import get_config
from pi0_jax.engine import Engine
from pi0_jax.ops import expert_kernels as ek
sys.path.insert(0, "scripts")
from profile_engine import round_robin

preset, b, prompt, out = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
variants = [tuple(int(x) for x in v.split("/")) for v in sys.argv[5].split(",")]
config = get_config(preset)
params = benchmark.random_params(config, 0)
obs, noise = benchmark.make_inputs(config, b, 3, prompt, 0)
default_blocks_at = ek.blocks_at
calls, outs = {}, {}
for att in ("auto", "vision=pallas,prefix=cudnn,denoise=pallas"):
    eng = Engine(config, params, attention=att, cache_dir=False)
    cameras, bucket = eng.plan(obs)
    packed = eng.pack(obs, cameras, bucket)
    w, sched = eng.weights, eng.schedule(10)
    tokens = eng.executable("encode_images", b, 10, cameras, bucket)(w, packed[0])
    cache = eng.executable("fill_prefix_cache", b, 10, cameras, bucket)(w, tokens, *packed[1:4])
    for v in ([None] if att == "auto" else variants):
        if v is not None:
            ek.blocks_at = lambda batch, blocks=ek.Blocks(), v=v: dataclasses.replace(blocks, kv_splits=v[0],
                                                                                       attention_stages=v[1])
        eng._executables.pop(eng.key("denoise", b, 10, cameras, bucket), None)
        den = eng.executable("denoise", b, 10, cameras, bucket)
        name = "auto" if v is None else f"pallas splits {v[0]} stages {v[1]}"
        calls[name] = (lambda den=den, w=w, sched=sched, cache=cache: den(w, sched, cache, packed[4], noise))
        outs[name] = np.asarray(calls[name](), np.float64)
        print("compiled", name, flush=True)
times = round_robin(calls, 20)
first = outs["auto"]
res = {k: {"median_ms": float(np.median(t)), "rel_l2": float(np.linalg.norm(outs[k] - first) / np.linalg.norm(first))}
       for k, t in times.items()}
for k, r in res.items():
    print(f"{preset} B={b} {k:28s} denoise {r['median_ms']:.3f} ms  rel {r['rel_l2']:.1e}", flush=True)
json.dump({"preset": preset, "batch": b, "env": benchmark.environment(), "results": res}, open(out, "w"), indent=1)
