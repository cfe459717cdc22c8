"""XLA's GEMM library and command-buffer (CUDA graph) options per compiled program, in one process on one set of
weights: each variant is an Engine whose programs compile with extra XLA options; stage medians, kernels per call
and GPU busy fraction from a trace, and the fused program's actions against the first variant.

    python scripts/graph_probe.py --preset pi0_base --batch 1 --out graph_probe.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
import profile_engine  # noqa: E402

from pi0_jax import benchmark  # noqa: E402
from pi0_jax.config import get_config  # noqa: E402
from pi0_jax.engine import Engine, runtime  # noqa: E402

GRAPHS = {"xla_gpu_graph_min_graph_size": 1}
VARIANTS = {
    "default": {},
    "cublas": {"xla_gpu_enable_triton_gemm": False},
    "graphs1": GRAPHS,
    "cublas+graphs1": {"xla_gpu_enable_triton_gemm": False, **GRAPHS},
}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", default="pi0_base")
    p.add_argument("--batch", type=int, action="append", default=None, help="repeatable (default: 1)")
    p.add_argument("--prompt-tokens", type=int, default=48)
    p.add_argument("--iters", type=int, default=30)
    p.add_argument("--variant", action="append", choices=list(VARIANTS), default=None)
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args()
    config = get_config(args.preset, dtype="bfloat16")
    params = benchmark.random_params(config, 0)
    report = {"preset": args.preset, "env": benchmark.environment(), "rows": []}
    for batch in args.batch or [1]:
        obs, noise = benchmark.make_inputs(config, batch, 3, args.prompt_tokens, 0)
        first = None
        for name in args.variant or list(VARIANTS):
            options = VARIANTS[name]
            runtime.matmul.compiler_options = lambda tree, gemm="xla", platform=None, o=options, **kw: dict(o) or None
            engine = Engine(config, params, cache_dir=False)
            cameras, bucket = engine.plan(obs)
            calls = profile_engine.stage_calls(engine, batch, 10, cameras, bucket, engine.pack(obs, cameras, bucket),
                                               noise)
            row = {"variant": name, "options": options, "batch": batch, "median_ms": {}, "kernels_per_call": {},
                   "busy": {}, "compile_s": {k[0]: round(v, 2) for k, v in engine.compile_seconds.items()}}
            for stage, fn in calls.items():
                row["median_ms"][stage] = benchmark.time_calls(fn, [()], args.iters, 3)["median_ms"]
                if batch <= 8:
                    t = profile_engine.kernel_times(fn, 3)
                    row["kernels_per_call"][stage], row["busy"][stage] = t["kernels_per_call"], t["busy"]
            out = np.asarray(calls["infer"](), np.float64)
            first = out if first is None else first
            row["rel_l2_vs_first"] = float(np.linalg.norm(out - first) / np.linalg.norm(first))
            print(json.dumps({k: row[k] for k in ("variant", "batch", "median_ms", "kernels_per_call", "busy",
                                                  "compile_s", "rel_l2_vs_first")}), flush=True)
            report["rows"].append(row)
            del engine, calls
    if args.out:
        args.out.write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
