"""π0's state token once a call against a row of every denoise step, in one process.

The state token's row attends to the prefix and itself alone, so its keys and values at every layer depend on neither
the noisy actions nor the flow time (`programs.cached_state`). On the XLA expert the engine now runs it through the
expert once, after the prefix, and each step runs the 50 action rows alone and unmasked; before, each step ran 51
rows, and with cuDNN's attention (π0 from B = 17) the state row as an XLA attention of its own beside the kernel.
Variants, timed round-robin as the whole call (`Engine.sample_packed`) and as the denoise program alone:

  once      the engine as it is
  per_step  the state row in every step (`programs.cached_state` patched to False while its programs compile)

    python scripts/state_probe.py --preset pi0_base --batch 64 --prompt-tokens 20 --iters 20 --out state.json

Prints and writes each variant's median and p10 ms, and the largest difference between their actions.
"""

from __future__ import annotations

import sys
from pathlib import Path
from unittest import mock

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from profile_engine import probe_arguments, probe_engine, round_robin, stage_calls, write_json  # noqa: E402

from pi0_jax.engine import programs  # noqa: E402


def main() -> None:
    args = probe_arguments(__doc__, 20, "the variants' times").parse_args()
    variants = {}
    for name, cached in (("once", programs.cached_state), ("per_step", lambda *a, **k: False)):
        with mock.patch.object(programs, "cached_state", cached):   # the programs compile in stage_calls
            config, engine, noise, cameras, bucket, packed = probe_engine(args)
            engine.call_programs(args.batch, args.steps, cameras, bucket)
            variants[name] = stage_calls(engine, args.batch, args.steps, cameras, bucket, packed, noise)
    report = {"preset": args.preset, "batch": args.batch, "steps": args.steps, "device": jax.devices()[0].device_kind,
              "max_abs_once_vs_per_step": float(np.max(np.abs(np.asarray(variants["once"]["call"](), np.float32)
                                                               - np.asarray(variants["per_step"]["call"](),
                                                                            np.float32))))}
    for what in ("call", "denoise"):
        times = round_robin({name: v[what] for name, v in variants.items()}, args.iters)
        report[what + "_ms"] = {k: {"median": float(np.median(t)), "p10": float(np.percentile(t, 10))}
                                for k, t in times.items()}
    for k, v in report.items():
        print(k, v, flush=True)
    write_json(args.out, report)


if __name__ == "__main__":
    main()
