"""The denoise program at one batch size, XLA expert: attention "auto" against the Pallas split-key attention
(denoise=pallas) at several launches (key splits, pipelining depth), timed round-robin in one process on the same
weights, cache and noise; prints and writes each variant's median and its actions' relative L2 against auto's.

    python scripts/denoise_attention_sweep.py pi0_base 8 48 sweep.json 1/3,2/3,4/1
"""
import argparse
import dataclasses
import json
import sys

import numpy as np
from pi0_jax import benchmark
from pi0_jax.config import get_config
from pi0_jax.engine import Engine
from pi0_jax.ops import expert_kernels as ek
sys.path.insert(0, "scripts")
from profile_engine import round_robin

p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
p.add_argument("preset", help="model preset, random weights (e.g. pi0_base)")
p.add_argument("batch", type=int)
p.add_argument("prompt_tokens", type=int, help="valid prompt tokens (π0: 48, π0.5: 200)")
p.add_argument("out", help="JSON results")
p.add_argument("variants", help="comma list of SPLITS/DEPTH launches of the Pallas attention, e.g. 2/3,4/1")
args = p.parse_args()
preset, b, prompt, out = args.preset, args.batch, args.prompt_tokens, args.out
variants = [tuple(int(x) for x in v.split("/")) for v in args.variants.split(",")]
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
