"""The vision tower before and after the engine owned it, in one process, on the same weights and images.

"flax": the Flax SigLIP as the engine ran it up to commit 7799238 (blocks unrolled, one Dense per q, k, v, cuDNN
attention; FP8 kernels went through `ops.matmul.dense_interceptor` in openpi's (in, out) layout), loaded from that
commit's `pi0_jax/siglip.py` (`--old-siglip`, e.g. `git show 7799238:pi0_jax/siglip.py > old_siglip.py`).
"engine-ATTENTION": `pi0_jax.engine.vision` (fused q/k/v, FP8 weights (out, in)) with that vision attention
(`--attention`, repeatable), and "engine-pallas-Q,KV,WARPS,STAGES" the Pallas attention with other blocks
(`--pallas-blocks`); "-ln" in a name: the Pallas LayerNorm (`--norm pallas`, `--norm-blocks`); "+cublas": every
GEMM on cuBLAS (`--gemm cublas`). Each in bf16 and, with `--fp8`, with the "vision" FP8 scheme (activation scales
calibrated on two batches of smooth random images). Tokens are compared with the first variant of each format.
Timing is round-robin over the variants (one call of each per round, the order reversed every other round), so
drift hits all alike; kernels are counted in the optimized HLO, and `--trace` sums a profiler trace's kernels at the
first batch size.

    python scripts/vision_probe.py --old-siglip old_siglip.py --batch 1,8,64 --fp8 --out vision.json
    python scripts/vision_probe.py --attention cudnn --attention pallas --pallas-blocks 128,64,8,2 --trace
"""

from __future__ import annotations

import argparse
import functools
import importlib.util
import itertools
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from profile_engine import count_ops, kernel_times  # noqa: E402

from pi0_jax import benchmark  # noqa: E402
from pi0_jax.config import get_config  # noqa: E402
from pi0_jax.engine import paths, programs, weights as weights_lib  # noqa: E402
from pi0_jax.ops import layer_norm, matmul, vision_attention  # noqa: E402
from pi0_jax.quant import schemes  # noqa: E402


def old_encoder(path: Path, config, img: dict):
    spec = importlib.util.spec_from_file_location("old_siglip", path)
    old = sys.modules["old_siglip"] = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(old)
    module = old.Siglip(config.siglip, out_dim=config.paligemma.width, dtype_mm=jnp.dtype(config.dtype), scan=False,
                        attention="cudnn")
    params = old.unstack_blocks(img, config.siglip.depth)
    return lambda p, x: module.apply({"params": p}, x)[0], params


def new_encoder(config, img: dict, attention: str = "cudnn", blocks: vision_attention.Blocks | None = None,
                norm: str = "xla", norm_blocks: layer_norm.Blocks | None = None):
    """The engine's tower with this vision attention and LayerNorm; blocks, norm_blocks: the Pallas kernels', in
    place of their defaults."""
    w = weights_lib.vision_weights(img, jnp.dtype(config.dtype))
    w["blocks"] = weights_lib.unstack(w["blocks"], config.siglip.depth)
    spec = paths.Attention(vision=attention)

    def run(w, x):
        kernels = vision_attention.attention, layer_norm.layer_norm
        if blocks:  # the kernels are looked up when the program is traced
            vision_attention.attention = functools.partial(kernels[0], blocks=blocks)
        if norm_blocks:
            layer_norm.layer_norm = functools.partial(kernels[1], blocks=norm_blocks)
        try:
            return programs.encode_images(config, {"img": w}, x[None], unroll=True, attention=spec, kernels=norm)
        finally:
            vision_attention.attention, layer_norm.layer_norm = kernels
    return run, w


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", default="pi0_base", help="model preset, random weights (default: %(default)s)")
    p.add_argument("--old-siglip", type=Path, default=None,
                   help="siglip.py of the commit before the engine owned the tower (adds the flax/* variants)")
    p.add_argument("--attention", action="append", choices=("cudnn", "xla", "pallas"), default=None,
                   help="the engine's vision attention; repeat it to compare (default: cudnn)")
    p.add_argument("--pallas-blocks", action="append", default=[], metavar="Q,KV,WARPS,STAGES",
                   help="one more engine/pallas variant with these `ops.vision_attention.Blocks`; repeatable")
    p.add_argument("--norm", action="append", choices=("xla", "pallas"), default=None,
                   help="the tower's LayerNorm (`paths.vision_norm`); repeat it to compare (default: xla)")
    p.add_argument("--norm-blocks", action="append", default=[], metavar="ROWS,COLS,WARPS",
                   help="one more engine/pallas variant with the Pallas LayerNorm and these `ops.layer_norm.Blocks` "
                        "(the first --attention's); repeatable")
    p.add_argument("--gemm", action="append", choices=("xla", "cublas"), default=None,
                   help="the library of XLA's GEMMs (`ops.matmul.compiler_options`); repeat it to compare; "
                        "\"+cublas\" in a variant's name (default: xla)")
    p.add_argument("--batch", default="1,8,64", help="images per call = batch x cameras (default: %(default)s)")
    p.add_argument("--cameras", type=int, default=3, help="images per batch element (default: %(default)s)")
    p.add_argument("--fp8", action="store_true", help="also the 'vision' FP8 scheme, both paths")
    p.add_argument("--iters", type=int, default=30, help="timed rounds (default: %(default)s)")
    p.add_argument("--trace", action="store_true", help="profiler kernel sums at the first batch size")
    p.add_argument("--out", type=Path, default=None, help="JSON of every row")
    p.add_argument("--dump-hlo", type=Path, default=None, help="write each program's optimized HLO into this folder")
    args = p.parse_args()

    config = get_config(args.preset)
    params = benchmark.random_params(config, 0)
    imgs = {"bf16": params["PaliGemma"]["img"]}
    if args.fp8:
        calib = schemes.sample_observations(config, 2, seed=1, batch=2)
        amax = schemes.calibrate(config, params, calib, "vision", percentile=None)["amax"]
        imgs["fp8"] = schemes.quantize_params(params, "vision", amax)["PaliGemma"]["img"]
    variants = {}
    for fmt, img in imgs.items():
        if args.old_siglip:
            variants[f"flax/{fmt}"] = old_encoder(args.old_siglip, config, img)
        for attention, norm, gemm in itertools.product(args.attention or ["cudnn"], args.norm or ["xla"],
                                                       args.gemm or ["xla"]):
            name = (f"engine-{attention}" + ("-ln" if norm == "pallas" else "")
                    + ("+cublas" if gemm == "cublas" else ""))
            variants[f"{name}/{fmt}"] = new_encoder(config, img, attention, norm=norm)
        for spec in args.pallas_blocks:
            blocks = vision_attention.Blocks(*(int(v) for v in spec.split(",")))
            variants[f"engine-pallas-{spec}/{fmt}"] = new_encoder(config, img, "pallas", blocks)
        for spec in args.norm_blocks:
            attention = (args.attention or ["cudnn"])[0]
            norm_blocks = layer_norm.Blocks(*(int(v) for v in spec.split(",")))
            variants[f"engine-{attention}-ln-{spec}/{fmt}"] = new_encoder(config, img, attention, norm="pallas",
                                                                          norm_blocks=norm_blocks)
    firsts = {}  # format -> the first variant of it (the reference of rel_l2_vs_first)
    for name in variants:
        firsts.setdefault(name.split("/")[1], name)
    rows, s = [], config.image_size
    for bi, batch in enumerate(int(b) for b in args.batch.split(",")):
        n = batch * args.cameras
        x = jnp.asarray(np.random.default_rng(batch).uniform(-1, 1, (n, s, s, 3)), jnp.float32)
        exes, outs = {}, {}
        for name, (fn, w) in variants.items():
            t0 = time.perf_counter()
            gemm = "cublas" if "+cublas" in name else "xla"
            exes[name] = jax.jit(fn).lower(w, x).compile(matmul.compiler_options(w, gemm))
            compile_s = time.perf_counter() - t0
            outs[name] = np.asarray(exes[name](w, x), np.float32).reshape(n, -1)
            if args.dump_hlo:
                args.dump_hlo.mkdir(parents=True, exist_ok=True)
                (args.dump_hlo / f"{name.replace('/', '_')}_b{batch}.hlo.txt").write_text(exes[name].as_text())
            counts = count_ops(exes[name].as_text())
            entry = next(v for k, v in counts.items() if k.startswith("ENTRY"))
            rows.append({"variant": name, "batch": batch, "images": n, "compile_s": compile_s, "entry_ops": entry})
        times = {name: [] for name in variants}
        for _ in range(3):
            for name, (fn, w) in variants.items():
                jax.block_until_ready(exes[name](w, x))
        for i in range(args.iters):   # the order flips every round: position in a round biases it by 1-3 %
            for name, (fn, w) in (list(variants.items()) if i % 2 else list(variants.items())[::-1]):
                t0 = time.perf_counter()
                jax.block_until_ready(exes[name](w, x))
                times[name].append(time.perf_counter() - t0)
        for row in rows[-len(variants):]:
            name = row["variant"]
            ref, bf16 = outs[firsts[name.split("/")[1]]], outs[firsts["bf16"]]
            row["median_ms"] = float(np.median(times[name]) * 1e3)
            row["p10_ms"], row["p90_ms"] = (float(np.percentile(times[name], q) * 1e3) for q in (10, 90))
            row["rel_l2_vs_first_same_format"] = float(np.linalg.norm(outs[name] - ref) / np.linalg.norm(ref))
            row["rel_l2_vs_first_bf16"] = float(np.linalg.norm(outs[name] - bf16) / np.linalg.norm(bf16))
            if args.trace and bi == 0:
                fn, w = variants[name]
                row["trace"] = kernel_times(functools.partial(exes[name], w, x))
                row["trace"]["by_name"] = row["trace"]["by_name"][:15]
            print(json.dumps({k: v for k, v in row.items() if k != "trace"}), flush=True)
            if "trace" in row:
                t = row["trace"]
                print(f"   trace: {t['kernels_per_call']:.0f} kernels, {t['kernel_ms']:.3f} ms busy of "
                      f"{t['wall_ms']:.3f} ms ({t['busy']:.0%})", flush=True)
    if args.out:
        args.out.write_text(json.dumps({"preset": args.preset, "cameras": args.cameras, "iters": args.iters,
                                        "env": benchmark.environment(), "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
