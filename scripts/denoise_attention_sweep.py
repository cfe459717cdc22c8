"""The denoise program at one batch size, XLA expert: attention "auto" against the Pallas split-key attention
(denoise=pallas) at several launches (key splits, pipelining depth, key block, query block, warps, query heads
folded into rows), timed round-robin in one process on the same weights, cache and noise; prints and writes each
variant's median and its actions' relative L2 against auto's. (Where "auto" is the kernel itself, π0 at B = 3-16,
it times the default launch.)

    python scripts/denoise_attention_sweep.py pi0_base 8 48 sweep.json 1/3,2/3,4/1,2/3/32/64/4
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np

from pi0_jax import benchmark
from pi0_jax.config import get_config
from pi0_jax.engine import Engine
from pi0_jax.ops import expert_kernels as ek

sys.path.insert(0, str(Path(__file__).parent))
from profile_engine import round_robin  # noqa: E402

STEPS = 10
FIELDS = ("kv_splits", "attention_stages", "kv", "q", "attention_warps", "fold")   # a variant's numbers, in order


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("preset", help="model preset, random weights (e.g. pi0_base)")
    p.add_argument("batch", type=int)
    p.add_argument("prompt_tokens", type=int, help="valid prompt tokens (π0: 48, π0.5: 200)")
    p.add_argument("out", type=Path, help="JSON results")
    p.add_argument("variants", help="comma list of the Pallas attention's launches "
                                    "SPLITS/DEPTH[/KV[/Q[/WARPS[/FOLD]]]] (key splits, pipelining depth, keys and "
                                    "queries per block, warps, 1: query heads folded into rows; unnamed ones as "
                                    "`expert_kernels.Blocks`), e.g. 2/3,4/1,2/3/32,2/3/64/64/4/1")
    p.add_argument("--iters", type=int, default=20, help="timed rounds (default: %(default)s)")
    args = p.parse_args()
    b = args.batch
    variants = [{k: (bool(int(x)) if k == "fold" else int(x)) for k, x in zip(FIELDS, v.split("/"))}
                for v in args.variants.split(",")]
    config = get_config(args.preset)
    params = benchmark.random_params(config, 0)
    obs, noise = benchmark.make_inputs(config, b, 3, args.prompt_tokens, 0)
    calls, outs, failed = {}, {}, {}
    for attention in ("auto", "vision=pallas,prefix=cudnn,denoise=pallas"):
        engine = Engine(config, params, attention=attention, cache_dir=False)
        cameras, bucket = engine.plan(obs)
        packed = engine.pack(obs, cameras, bucket)
        w, sched = engine.weights, engine.schedule(STEPS)
        tokens = engine.executable("encode_images", b, STEPS, cameras, bucket)(w, packed[0])
        cache = engine.executable("fill_prefix_cache", b, STEPS, cameras, bucket)(w, tokens, *packed[1:4])
        for v in ([None] if attention == "auto" else variants):
            if v is not None:   # the launch `layers._attend_kernel` takes, read when the program is traced
                ek.blocks_at = lambda batch, blocks=ek.Blocks(), v=v: dataclasses.replace(blocks, **v)
            engine._executables.pop(engine.key("denoise", b, STEPS, cameras, bucket), None)   # compile it again
            name = "auto" if v is None else "pallas " + " ".join(f"{k} {x}" for k, x in v.items())
            try:
                den = engine.executable("denoise", b, STEPS, cameras, bucket)
            except Exception as e:  # noqa: BLE001  (e.g. tiles over the shared memory: recorded, not timed)
                failed[name] = f"{type(e).__name__}: {str(e)[:200]}"
                print("failed", name, failed[name], flush=True)
                continue
            calls[name] = lambda den=den, w=w, sched=sched, cache=cache, state=packed[4]: den(w, sched, cache, state,
                                                                                               noise)
            outs[name] = np.asarray(calls[name](), np.float64)
            print("compiled", name, flush=True)
    times = round_robin(calls, args.iters)
    first = outs["auto"]
    res = {k: {"median_ms": float(np.median(t)),
               "rel_l2": float(np.linalg.norm(outs[k] - first) / np.linalg.norm(first))} for k, t in times.items()}
    for k, r in res.items():
        print(f"{args.preset} B={b} {k:60s} denoise {r['median_ms']:.3f} ms  rel {r['rel_l2']:.1e}", flush=True)
    args.out.write_text(json.dumps({"preset": args.preset, "batch": b, "env": benchmark.environment(),
                                    "results": res, "failed": failed}, indent=1))


if __name__ == "__main__":
    main()
