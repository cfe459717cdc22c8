"""How many CUDA-graph nodes XLA updates in π0's call, by what the caller does with the last call's actions: run under
`launch_shim.py` (which counts `cuGraphExecKernelNodeSetParams` before each graph launch), it times the engine's call
(π0 full size, random weights, B = 1, 10 steps, the GPU idle 2 ms before each call) with the previous actions kept on
the device during the call ("keep"), copied to a new device array that is kept ("keep-copy"), or taken to the host
and dropped ("numpy", as `Policy.infer` does), or dropped with the inputs rotating over four sets as the benchmark
rotates them ("numpy-rotating"), two rounds of 40 calls each, and prints the median call and the node updates and
graph launches a call. XLA updates each node of a graph whose buffers moved before it launches the graph. GPU only:

    python3 scripts/launch_shim.py --out DIR -- python3 scripts/engine_update_probe.py
    python3 scripts/launch_shim.py --out DIR -- python3 scripts/engine_update_probe.py --mode numpy --mode numpy-rotating
"""

import argparse
import json
import os
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from pi0_jax import benchmark
from pi0_jax.config import get_config
from pi0_jax.engine import Engine

sys.path.insert(0, str(Path(__file__).resolve().parent))
from launch_shim import read_log  # noqa: E402

MODES = ("keep", "keep-copy", "numpy", "numpy-rotating")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--mode", action="append", choices=MODES, default=None,
                   help="repeatable (default: keep, keep-copy, numpy)")
    args = p.parse_args()
    log = Path(os.environ["SHIM_DIR"]) / "shim.log"
    config = get_config("pi0_base", dtype="bfloat16")
    engine = Engine(config, benchmark.random_params(config, 0), cache_dir=False)
    sets = [benchmark.make_inputs(config, 1, 3, 48, seed) for seed in range(4)]   # as the benchmark's --input-sets
    obs, noise = sets[0]
    actions = engine.sample_actions(obs, noise)
    jax.block_until_ready(actions)
    for mode in (args.mode or list(MODES[:3])) * 2:
        actions = engine.sample_actions(obs, noise)
        jax.block_until_ready(actions)
        seen, times = len(read_log(log)[0]), []
        for k in range(40):
            if mode == "numpy-rotating":
                obs, noise = sets[k % len(sets)]
            time.sleep(0.002)
            start = time.perf_counter()
            if mode == "keep":
                actions = engine.sample_actions(obs, noise)
                jax.block_until_ready(actions)
            elif mode == "keep-copy":
                actions = jnp.array(engine.sample_actions(obs, noise), copy=True)
                jax.block_until_ready(actions)
            else:
                actions = None
                actions = np.asarray(engine.sample_actions(obs, noise))
            times.append(time.perf_counter() - start)
        obs, noise = sets[0]
        launches = read_log(log)[0][seen:]
        print(json.dumps({"mode": mode, "call_ms": round(float(np.median(times)) * 1e3, 3),
                          "node_updates_per_call": sum(r[3] for r in launches) / 40,
                          "launches_per_call": len(launches) / 40}), flush=True)


if __name__ == "__main__":
    main()
