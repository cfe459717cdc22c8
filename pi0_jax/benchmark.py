"""The jit benchmark: per-stage latency of the compiled engine over steps x batch x dtype.

Fixed random inputs (several sets, rotated so caches do not flatter), warm-up, `block_until_ready` before the clock
is read, median and p90 over the timed iterations. Stages are timed as separate programs (vision, prefix KV fill,
denoise), each synchronised; `total` is the whole call as `Engine.sample_actions` runs it (the vision program, then
the prefix and denoise program, with no host round trip between them), and `--one-program` adds the call as one
fused program. Each row carries its stages' roofline (`pi0_jax.roofline`: FLOPs and bytes against the device's
peaks), printed as a second table. Cold compile (empty persistent cache) and warm start (a second process reading
the cache) are measured for the call's programs. Peers (LeRobot's PyTorch policy) come
from the `peers` package, which may import torch; this module does not.

    pi0-jax benchmark --preset pi0_base --steps 1,2,3,5,10 --batch 1,8,64 --out bench.json
    pi0-jax benchmark --preset dummy --steps 1,2 --batch 1 --iters 3       # CPU smoke test
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import functools
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from pi0_jax import pi0, roofline
from pi0_jax.pi0 import random_params
from pi0_jax.config import IMAGE_KEYS, PRESETS, Pi0Config, get_config
from pi0_jax.engine import Engine, dispatch, layers, programs, store, vision
from pi0_jax.engine.paths import KERNELS, OVERLAPS, attention_spec, vision_norm
from pi0_jax.ops import expert_attention, expert_kernels, formats, pallas_base
from pi0_jax.ops.matmul import GEMMS
from pi0_jax.quant.schemes import SCHEMES


def _ints(s: str) -> list[int]:
    return [int(x) for x in s.split(",") if x]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--preset", default="pi0_base", choices=sorted(PRESETS),
                   help="model preset; random weights unless --checkpoint (default: %(default)s)")
    p.add_argument("--checkpoint", type=Path, default=None,
                   help="a pi0-jax checkpoint directory to benchmark instead of random weights of --preset")
    p.add_argument("--steps", type=_ints, default=[1, 2, 3, 5, 10], help="comma list of denoise steps")
    p.add_argument("--batch", type=_ints, default=[1, 8, 64], help="comma list of batch sizes")
    p.add_argument("--dtype", default="bfloat16", help="comma list of dtypes: bfloat16,float32")
    p.add_argument("--iters", type=int, default=50, help="timed iterations per measurement (default: %(default)s)")
    p.add_argument("--warmup", type=int, default=3, help="untimed calls before timing (default: %(default)s)")
    p.add_argument("--input-sets", type=int, default=4, help="distinct random input sets, rotated (default: 4)")
    p.add_argument("--cameras", type=int, default=3, help="active cameras (the rest are masked and skipped)")
    p.add_argument("--prompt-tokens", type=int, default=20,
                   help="valid prompt tokens; the rest of max_token_len is padding (default: %(default)s)")
    p.add_argument("--fused-steps", type=_ints, default=None,
                   help="steps at which the whole call (Engine.sample_actions: the vision program, then the prefix "
                        "and denoise program, no host round trip between them) is also timed, beside the stage "
                        "programs each timed alone (default: all of --steps)")
    p.add_argument("--one-program", action="store_true",
                   help="at those steps also time the call as one fused program (the pipeline as the simulator "
                        "embeds it), for comparison")
    p.add_argument("--quant", default=None, choices=sorted(SCHEMES),
                   help="FP8 scheme applied to the weights (random, or --checkpoint's; calibrated on synthetic "
                        "observations); a quantised --checkpoint is used as stored, without --quant. prefix-vision: "
                        "FP8 x FP8 GEMMs in the prefix and SigLIP, for large batches; every-gemm: the action "
                        "expert's too (calibrated over the denoise loop), for hundreds of samples")
    p.add_argument("--no-unroll", action="store_true", help="scan over layers instead of unrolling them")
    p.add_argument("--unroll-steps", action="store_true", help="unroll the denoise loop as well")
    p.add_argument("--attention", default="auto", type=attention_spec,
                   help="each stage's attention: xla (the reference's ops), cudnn (one fused flash kernel), auto "
                        "(the faster per stage on a GPU: in vision a Pallas kernel that reads q, k, v in place, cuDNN "
                        "in the prefix, in the denoise step the Pallas expert's split-key kernel at batch 4-8 (π0: "
                        "3-16), cuDNN from batch 3 elsewhere, XLA below; XLA on a CPU), or per stage, e.g. "
                        "vision=pallas,prefix=xla,denoise=auto (vision and denoise may be pallas) "
                        "(default: %(default)s)")
    p.add_argument("--kernels", choices=KERNELS, default="auto",
                   help="the action expert's layers as XLA ops, as the fused Pallas kernels of pi0_jax.ops "
                        "(Triton on GPU; gate/up with GeGLU on Mosaic GPU on Hopper), or auto: the kernels at "
                        "batch 1 and 2 on a GPU, XLA otherwise; each row records the path it ran (the JSON's "
                        "env.expert_blocks the kernels' launches). SigLIP's LayerNorm likewise, auto: the kernel on "
                        "a GPU from 24 images a call (default: %(default)s)")
    p.add_argument("--gemm", choices=GEMMS, default="auto",
                   help="the library of XLA's GEMMs on a GPU: xla (XLA's autotuned choice of Triton or cuBLAS per "
                        "GEMM), cublas (XLA's Triton GEMMs off, so bias, GELU and residual adds become cuBLASLt "
                        "epilogues; faster in the vision tower, slower in the prefix and denoise), or auto (cublas in "
                        "the vision program, xla in the others); programs with FP8 weights always get cublas; the "
                        "reference always runs XLA's defaults (default: %(default)s)")
    p.add_argument("--overlap", choices=OVERLAPS, default="auto",
                   help="the first denoise step beside the prefix fill in the call's second program (its command "
                        "buffers in XLA's CONCURRENT mode, the other steps a third program): on, off, or auto (on a "
                        "GPU where the expert runs its Pallas kernels, at batch 1 and 2); each row records it "
                        "(default: %(default)s)")
    p.add_argument("--reference", action="store_true",
                   help="also time the reference model (pi0_jax.pi0.sample_actions: openpi's structure, layers "
                        "scanned, one jit) at each batch for the largest step count")
    p.add_argument("--compare", choices=["lerobot"], default=None,
                   help="also time LeRobot's PyTorch policy of the same preset (random weights) on the same device")
    p.add_argument("--torch-compile", action="store_true", help="with --compare: also time torch.compile")
    p.add_argument("--peer-batch", type=_ints, default=[1, 8], help="batch sizes for peers (default: 1,8)")
    p.add_argument("--peer-iters", type=int, default=10, help="timed iterations for peers (default: %(default)s)")
    p.add_argument("--torch-compile-mode", default="default",
                   help="torch.compile mode for --torch-compile (default: %(default)s; LeRobot's own, max-autotune, "
                        "did not finish compiling in 9 minutes on an H100, even per stage: docs/BENCHMARKS.md)")
    p.add_argument("--torch-compile-scope", choices=["sample_actions", "stages"], default="stages",
                   help="what --torch-compile compiles: sample_actions (the whole call at once, LeRobot's own way; "
                        "its unrolled step loop makes the first call compile for minutes at full size) or "
                        "stages (LeRobot's embed_prefix, the prefix pass of its language model and denoise_step, "
                        "each its own graph, with the loop over steps left in Python) (default: %(default)s)")
    p.add_argument("--warm-start", action="store_true",
                   help="measure the warm start: a second process loads the B=1 call's programs from the cache")
    p.add_argument("--cache-dir", type=Path, default=None,
                   help="persistent compilation cache (default: a fresh temp dir, so the cold compile is cold)")
    p.add_argument("--out", type=Path, default=Path("benchmark.json"),
                   help="JSON results, rewritten as each batch size and peer is done, so a run stopped midway keeps "
                        "them (\"complete\": false until the end; default: %(default)s)")
    p.add_argument("--chart", type=Path, default=None, help="PNG chart (default: --out with .png)")
    p.add_argument("--seed", type=int, default=0, help="seed of weights and inputs")


def fp8_params(config: Pi0Config, params: dict, scheme: str, *, seed: int = 0, num_steps: int = 10) -> dict:
    """`params` in FP8 by `scheme`, calibrated on 4 sample observations (static scales), as --quant does."""
    from pi0_jax.quant import schemes

    stats = schemes.calibrate(config, params, schemes.sample_observations(config, 4, seed=seed), scheme,
                              percentile=None, num_steps=num_steps)
    return schemes.quantize_params(params, scheme, stats["amax"])


def make_inputs(config: Pi0Config, batch: int, cameras: int, prompt_tokens: int, seed: int):
    rng = np.random.default_rng(seed)
    s, keys = config.image_size, IMAGE_KEYS[: config.num_cameras]
    L = config.max_token_len
    tmask = np.arange(L)[None, :] < min(prompt_tokens, L)
    obs = pi0.Observation(
        images={k: jnp.asarray(rng.uniform(-1, 1, (batch, s, s, 3)), jnp.float32) for k in keys},
        image_masks={k: jnp.full((batch,), i < cameras) for i, k in enumerate(keys)},
        state=jnp.asarray(rng.normal(size=(batch, config.action_dim)), jnp.float32),
        tokenized_prompt=jnp.asarray(np.where(tmask, rng.integers(2, config.vocab_size, (batch, L)), 0), jnp.int32),
        tokenized_prompt_mask=jnp.asarray(np.broadcast_to(tmask, (batch, L))),
    )
    noise = jnp.asarray(rng.normal(size=(batch, config.action_horizon, config.action_dim)), jnp.float32)
    return obs, noise


def time_calls(fn, inputs: list, iters: int, warmup: int) -> dict:
    """fn(*inputs[i % n]) timed one call at a time, synchronised; returns median / p90 / min in ms."""
    for i in range(warmup):
        jax.block_until_ready(fn(*inputs[i % len(inputs)]))
    times = []
    for i in range(iters):
        args = inputs[i % len(inputs)]
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append((time.perf_counter() - start) * 1e3)
    return {"median_ms": float(np.median(times)), "p90_ms": float(np.percentile(times, 90)),
            "min_ms": float(np.min(times))}


def _peak_bytes() -> int | None:
    stats = jax.devices()[0].memory_stats() or {}
    return stats.get("peak_bytes_in_use")


def fp8_kernel_rows() -> dict:
    """From how many rows each FP8 MLP runs `ops.fp8_geglu`'s kernels on this backend (None: never): the prefix's
    (any), the action expert's and SigLIP's fc1 (`engine.layers.FP8_GEGLU_EXPERT_ROWS`, `vision.FP8_GELU_ROWS`)."""
    on = layers.fp8_mlp_kernel()
    return {"prefix_mlp": 1 if on else None, "expert_mlp": layers.FP8_GEGLU_EXPERT_ROWS if on else None,
            "vision_fc1": vision.FP8_GELU_ROWS if on else None}


def environment() -> dict:
    import flax

    dev = jax.devices()[0]
    return {"device": getattr(dev, "device_kind", str(dev)), "platform": dev.platform, "jax": jax.__version__,
            "flax": flax.__version__, "python": platform.python_version(),
            "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "commit": _git_commit(), "source": source_digest(), "xla_flags": os.environ.get("XLA_FLAGS", ""),
            "pallas_triton": pallas_base.TRITON, "dispatch": "direct" if dispatch.DIRECT else "jax"}


def _git_commit() -> str | None:
    """PI0_JAX_COMMIT if set (a copied tree without .git, e.g. a remote GPU machine), else `git describe --always
    --dirty`: HEAD's short hash, "-dirty" where tracked files differ from it (a copy whose .git is older than its
    files says so, rather than naming a commit it is not)."""
    if os.environ.get("PI0_JAX_COMMIT"):
        return os.environ["PI0_JAX_COMMIT"]
    try:
        return subprocess.run(["git", "describe", "--always", "--dirty"], capture_output=True, text=True,
                              cwd=Path(__file__).parent, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None


def source_digest(root: Path | None = None) -> str:
    """The first 12 hex digits of the program store's digest of the package's Python sources (`store.tree_digest`):
    the code a result came from, comparable with `python -c "from pi0_jax.benchmark import source_digest as d;
    print(d())"` at any checkout, with or without git. root: the package directory (None: this one)."""
    return (store.source_digest() if root is None else store.tree_digest(root))[:12]


def denoise_attention(engine: Engine, batch: int) -> str:
    """Each stage's attention in a program of this batch, as it runs: where the Pallas expert runs the step (B <= 2 on
    a GPU), its own split-key kernel ("pallas"), which `Attention.at_batch` leaves to the XLA expert's choice."""
    attention = engine.attention.at_batch(batch, suffix_mask=not engine.config.pi05)
    if engine.kernels_for(batch) == "pallas":
        attention = dataclasses.replace(attention, denoise="pallas")
    return str(attention)


def bench_engine(engine: Engine, args, batch: int) -> list[dict]:
    cfg = engine.config
    sets = [make_inputs(cfg, batch, args.cameras, args.prompt_tokens, args.seed + i) for i in range(args.input_sets)]
    cameras, bucket = engine.plan(sets[0][0])
    packed = [engine.pack(obs, cameras, bucket) for obs, _ in sets]
    w = engine.weights
    gemm_formats, device = roofline.gemm_formats(w), jax.devices()[0].device_kind
    enc = engine.executable("encode_images", batch, 0, cameras, bucket)
    pre = engine.executable("fill_prefix_cache", batch, 0, cameras, bucket)
    t_vis = time_calls(lambda im: enc(w, im), [(p[0],) for p in packed], args.iters, args.warmup)
    tokens = [enc(w, p[0]) for p in packed]
    t_pre = time_calls(lambda it, p: pre(w, it, p[1], p[2], p[3]), list(zip(tokens, packed)), args.iters, args.warmup)
    caches = [pre(w, it, p[1], p[2], p[3]) for it, p in zip(tokens, packed)]
    rows = []
    for steps in args.steps:
        sched = engine.schedule(steps)
        den = engine.executable("denoise", batch, steps, cameras, bucket)
        t_den = time_calls(lambda c, p, n: den(w, sched, c, p[4], n),
                           [(c, p, n) for c, p, (_, n) in zip(caches, packed, sets)], args.iters, args.warmup)
        row = {"dtype": cfg.dtype, "batch": batch, "steps": steps, "cameras": len(cameras), "prompt_bucket": bucket,
               "attention": denoise_attention(engine, batch), "kernels": engine.kernels_for(batch),
               "vision_norm": vision_norm(engine.kernels, batch * len(cameras)),
               "gemm": engine.gemm,
               "gemm_library": {s: engine.gemm_library(s, batch) for s in engine.call_stages(batch, steps)},
               "overlap": engine.overlaps(batch), "call_stages": list(engine.call_stages(batch, steps)),
               "vision": t_vis, "prefix": t_pre, "denoise": t_den,
               "denoise_per_step_ms": t_den["median_ms"] / steps}
        if "denoise=pallas" in row["attention"]:   # the Pallas expert's, or the XLA expert's on the kernel attention
            launch = expert_kernels.attention_blocks(batch, xla_expert=row["kernels"] == "xla")
            row["denoise_attention_launch"] = expert_attention.attention_launch(launch, caches[0].mask.shape[-1])
        if args.fused_steps is None or steps in args.fused_steps:
            row["total"] = time_calls(lambda p, n: engine.sample_packed(p, n, steps, cameras, bucket),
                                      [(p, n) for p, (_, n) in zip(packed, sets)], args.iters, args.warmup)
            row["compile_s"] = sum(engine.compile_seconds.get(engine.key(s, batch, steps, cameras, bucket), 0.0)
                                   for s in engine.call_stages(batch, steps))
            if args.one_program:
                fused = engine.executable("infer", batch, steps, cameras, bucket)
                row["one_program"] = time_calls(lambda p, n: fused(w, sched, *p, n),
                                                [(p, n) for p, (_, n) in zip(packed, sets)], args.iters, args.warmup)
        total = row.get("total", {}).get("median_ms") or (t_vis["median_ms"] + t_pre["median_ms"] + t_den["median_ms"])
        row["total_ms"], row["hz"], row["samples_per_s"] = total, 1e3 / total, 1e3 * batch / total
        row["roofline"] = roofline.row_figures(cfg, gemm_formats, device, row)
        rows.append(row)
        print(_row_line(row), flush=True)
        if "one_program" in row:
            print(_one_program_line(row), flush=True)
    return rows


def bench_reference(engine: Engine, params: dict, args, batch: int, steps: int) -> dict:
    """Time the reference model, and check the engine's call (`sample_actions`) against it on the same inputs."""
    config = engine.config
    sets = [make_inputs(config, batch, args.cameras, args.prompt_tokens, args.seed + i) for i in range(args.input_sets)]
    fn = jax.jit(functools.partial(pi0.sample_actions, config, num_steps=steps))
    start = time.perf_counter()
    fn.lower(params, *sets[0]).compile()
    compile_s = time.perf_counter() - start
    t = time_calls(lambda o, n: fn(params, o, n), sets, args.iters, args.warmup)
    ref = np.asarray(fn(params, *sets[0]), np.float64)
    got = np.asarray(engine.sample_actions(sets[0][0], sets[0][1], steps), np.float64)
    return {"impl": "reference (pi0_jax.pi0, openpi structure)", "dtype": config.dtype, "batch": batch,
            "steps": steps, "total": t, "compile_s": compile_s,
            "engine_vs_reference": {"rel_l2": float(np.linalg.norm(got - ref) / np.linalg.norm(ref)),
                                    "max_abs": float(np.abs(got - ref).max())}}


_WARM_CHILD = """
import json, sys, time
t0 = time.perf_counter()
from pi0_jax import benchmark
from pi0_jax.config import get_config
from pi0_jax.engine import Engine
from pi0_jax.engine.paths import attention_spec
cfg = get_config(sys.argv[1], dtype=sys.argv[2])
params = benchmark.random_params(cfg, 0)
engine = Engine(cfg, params, unroll=sys.argv[4] == "1", kernels=sys.argv[8], attention=sys.argv[9],
                gemm=sys.argv[10], overlap=sys.argv[11], cache_dir=sys.argv[3])
obs, noise = benchmark.make_inputs(cfg, 1, int(sys.argv[5]), int(sys.argv[6]), 0)
start = time.perf_counter()
engine.call_programs(1, int(sys.argv[7]), *engine.plan(obs))
print(json.dumps({"warm_compile_s": time.perf_counter() - start, "process_s": time.perf_counter() - t0,
                  "programs_loaded": engine.store.loaded}))
"""


def measure_warm_start(config: Pi0Config, args, cache_dir: Path, steps: int) -> dict:
    out = subprocess.run([sys.executable, "-c", _WARM_CHILD, config.name, config.dtype, str(cache_dir),
                          "0" if args.no_unroll else "1", str(args.cameras), str(args.prompt_tokens), str(steps),
                          args.kernels, args.attention, args.gemm, args.overlap],
                         capture_output=True, text=True, check=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def _row_line(r: dict) -> str:
    return (f"| {r['dtype']} | {r['batch']} | {r['steps']} | {r['total_ms']:.2f} | {r['hz']:.1f} | "
            f"{r['vision']['median_ms']:.2f} | {r['prefix']['median_ms']:.2f} | {r['denoise']['median_ms']:.2f} | "
            f"{r['denoise_per_step_ms']:.3f} | {r['samples_per_s']:.1f} |")


def _one_program_line(r: dict) -> str:
    return (f"  B={r['batch']}, {r['steps']} steps as one fused program: {r['one_program']['median_ms']:.2f} ms "
            f"(the call: {r['total']['median_ms']:.2f} ms)")


TABLE_HEADER = ("| dtype | batch | steps | total ms | Hz | vision ms | prefix KV ms | denoise ms | ms/step | samples/s |\n"
                "|---|---|---|---|---|---|---|---|---|---|")


ROOFLINE_HEADER = ("| batch | steps | stage | ms | TFLOP (of it FP8) | GB read | floor ms | bound | of the floor |\n"
                   "|---|---|---|---|---|---|---|---|---|")


def _roofline_lines(r: dict) -> list[str]:
    """A row's stages against the device's peaks (`pi0_jax.roofline`); blank where the device has no peaks."""
    lines = []
    for stage, f in r.get("roofline", {}).get("stages", {}).items():
        ms = f"{f['ms']:.2f}" if "ms" in f else ""
        floor = f"{f['floor_ms']:.3f}" if "floor_ms" in f else ""
        of = f"{100 * f['of_floor']:.0f} %" if "of_floor" in f else ""
        lines.append(f"| {r['batch']} | {r['steps']} | {stage} | {ms} | {f['tflop']:.4g} ({f['tflop_fp8']:.4g}) | "
                     f"{f['gb']:.4g} | {floor} | {f.get('bound', '')} | {of} |")
    return lines


def markdown(results: dict) -> str:
    lines = [f"{results['env']['device']} · {results['preset']} · kernels {results['env'].get('kernels', 'xla')} · "
             f"attention {results['env'].get('attention', 'xla')} · overlap {results['env'].get('overlap', 'off')} · "
             f"quant {results['env'].get('quant', 'none')} · {results['env']['date']} · commit "
             f"{results['env']['commit']}", "", TABLE_HEADER]
    lines += [_row_line(r) for r in results["rows"]]
    one = [_one_program_line(r) for r in results["rows"] if "one_program" in r]
    lines += [""] + one if one else []   # below the table, not a row of it
    roof = [line for r in results["rows"] for line in _roofline_lines(r)]
    if roof:
        peaks = next((r["roofline"]["peaks"] for r in results["rows"] if "peaks" in r.get("roofline", {})), None)
        lines += ["", "roofline (pi0_jax.roofline): " + (f"dense peaks bf16 {peaks['bf16_tflops']:.0f} TFLOP/s, FP8 "
                                                         f"{peaks['fp8_tflops']:.0f}, memory {peaks['memory_tbs']:.2f} "
                                                         "TB/s" if peaks else "no peaks for this device"),
                  "", ROOFLINE_HEADER] + roof
    for peer in results.get("peers", []):
        lines.append(f"\n{peer['impl']} ({peer['dtype']}, B={peer['batch']}, {peer['steps']} steps): "
                     f"{peer['total']['median_ms']:.2f} ms median; pi0-jax is {peer.get('ratio', float('nan')):.2f}x "
                     "faster")
    if results.get("compile"):
        lines.append(f"\ncompile: {json.dumps(results['compile'])}")
    return "\n".join(lines)


def chart(results: dict, path: Path) -> None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib not installed: no chart", file=sys.stderr)
        return
    rows = results["rows"]
    groups = sorted({(r["dtype"], r["batch"]) for r in rows})
    fig, axes = plt.subplots(1, len(groups), figsize=(4 * len(groups), 3.6), squeeze=False)
    for ax, (dtype, batch) in zip(axes[0], groups):
        sel = [r for r in rows if (r["dtype"], r["batch"]) == (dtype, batch)]
        x = np.arange(len(sel))
        bottom = np.zeros(len(sel))
        for stage, color in (("vision", "#4c72b0"), ("prefix", "#dd8452"), ("denoise", "#55a868")):
            h = np.array([r[stage]["median_ms"] for r in sel])
            ax.bar(x, h, bottom=bottom, color=color, label=stage)
            bottom += h
        ax.set_xticks(x, [str(r["steps"]) for r in sel])
        ax.set_xlabel("denoise steps")
        ax.set_title(f"{dtype}, batch {batch}")
    axes[0][0].set_ylabel("ms (median, per stage)")
    axes[0][-1].legend()
    fig.suptitle(f"{results['preset']} on {results['env']['device']}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def quant_label(args: argparse.Namespace) -> str:
    """The FP8 scheme the benchmarked weights carry: --quant's, a quantised checkpoint's recorded scheme
    ("stored" where it records none), or "none". Raises where --quant names a scheme for a quantised checkpoint."""
    stored = None
    if args.checkpoint is not None:
        from pi0_jax import checkpoint

        meta = checkpoint.read_meta(args.checkpoint)
        stored = meta["quant"].get("scheme", "stored") if "quant" in meta else None
    if args.quant and stored:
        raise ValueError(f"--checkpoint {args.checkpoint} is already quantised ({stored}): drop --quant {args.quant}")
    return args.quant or stored or "none"


def write_results(path: Path, results: dict) -> None:
    """results as JSON at path, atomically (a temporary file beside it, then a rename): a run stopped midway leaves
    its last whole write, never half a file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(results, indent=2, default=str) + "\n")
    os.replace(tmp, path)


def run(args: argparse.Namespace, save=None) -> dict:
    """The benchmark's measurements. save(results), when given, is called whenever a batch size, a peer or a
    dtype's compile figures are done, with "complete" False until `main`'s last write."""
    save = save or (lambda results: None)
    quant = quant_label(args)
    cache_dir = args.cache_dir or Path(tempfile.mkdtemp(prefix="pi0-jax-xla-"))
    results = {"preset": args.preset, "env": {**environment(), "kernels": args.kernels, "attention": args.attention,
                                               "gemm": args.gemm, "overlap": args.overlap, "quant": quant,
                                               "expert_blocks": dataclasses.asdict(expert_kernels.Blocks()),
                                               "fp8_mlp_kernel": layers.fp8_mlp_kernel(),
                                               "fp8_kernel_from_rows": fp8_kernel_rows(),
                                               "fp8_row_pad": programs.FP8_ROW_PAD,
                                               "pack_attention_input": layers.PACK_ATTENTION_INPUT,
                                               "attention_ends_in_merge": layers.ATTENTION_ENDS_IN_MERGE},
               "complete": False, "rows": [], "peers": [],
               "compile": {},
               "args": {k: str(v) for k, v in vars(args).items() if k != "func"}}
    print(f"{results['env']['device']} · jax {jax.__version__} · quant {results['env']['quant']}\n\n{TABLE_HEADER}",
          flush=True)
    for dtype in args.dtype.split(","):
        if args.checkpoint is not None:
            from pi0_jax import checkpoint

            config, params = checkpoint.load_checkpoint(args.checkpoint, dtype=dtype)
            config = config.replace(dtype=dtype)
        else:
            config = get_config(args.preset, dtype=dtype)
            params = random_params(config, args.seed)
        if args.quant:
            params = fp8_params(config, params, args.quant, seed=args.seed, num_steps=max(args.steps))
        engine = Engine(config, params, unroll=not args.no_unroll, unroll_steps=args.unroll_steps,
                        attention=args.attention, kernels=args.kernels, gemm=args.gemm, overlap=args.overlap,
                        cache_dir=cache_dir)
        quantised = len(formats.quantized_paths(params))   # the weights in FP8: what --quant did
        for batch in args.batch:
            results["rows"] += [{**r, "quantised_leaves": quantised} for r in bench_engine(engine, args, batch)]
            if args.reference:
                ref = bench_reference(engine, params, args, batch, max(args.steps))
                mine = next(r for r in results["rows"] if (r["dtype"], r["batch"], r["steps"]) ==
                            (dtype, batch, max(args.steps)))
                ref["ratio"] = ref["total"]["median_ms"] / mine["total_ms"]
                results["peers"].append(ref)
                print(f"reference B={batch}: {ref['total']['median_ms']:.2f} ms ({ref['ratio']:.2f}x); engine vs "
                      f"reference: {ref['engine_vs_reference']}", flush=True)
            save(results)
        cold = {f"B{r['batch']}_S{r['steps']}": round(r["compile_s"], 2) for r in results["rows"]
                if r["dtype"] == dtype and "compile_s" in r}
        results["compile"][dtype] = {"cold_compile_s_call": cold, "peak_device_bytes": _peak_bytes()}
        if args.warm_start:
            results["compile"][dtype]["warm_start"] = measure_warm_start(config, args, cache_dir, max(args.steps))
        save(results)
        if args.compare == "lerobot":
            from peers import lerobot_torch

            for peer in lerobot_torch.benchmark(config, args):
                mine = next(r for r in results["rows"] if (r["dtype"], r["batch"], r["steps"]) ==
                            (dtype, peer["batch"], peer["steps"]))
                peer["ratio"] = peer["total"]["median_ms"] / mine["total_ms"]
                results["peers"].append(peer)
                print(f"{peer['impl']} B={peer['batch']}: {peer['total']['median_ms']:.2f} ms "
                      f"({peer['ratio']:.2f}x)", flush=True)
                save(results)
        del engine, params
    return results


def main(args: argparse.Namespace) -> int:
    results = run(args, save=lambda partial: write_results(args.out, partial))
    results["complete"] = True
    write_results(args.out, results)
    print("\n" + markdown(results))
    chart(results, args.chart or args.out.with_suffix(".png"))
    print(f"\nwrote {args.out}")
    return 0
