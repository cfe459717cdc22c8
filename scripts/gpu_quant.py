"""FP8 on the GPU: per-stage timings per scheme and batch, the FP8 GEMM custom calls in the optimized HLO, and
the accuracy of every scheme (and FP4 emulation) against bf16 at full size. Random weights, realistic inputs.

    PYTHONPATH=$PWD python scripts/gpu_quant.py --out $OUT                 # H200: pi0_base timings + 2 presets
    PYTHONPATH=$PWD python scripts/gpu_quant.py --preset dummy --quick --out /tmp/q   # CPU smoke test

Writes OUT/quant_gpu.json and OUT/quant_gpu.md. The HLO check (every GEMM a scheme quantises with activations is a
`__cublas$lt$matmul$f8` custom call, weight-only GEMMs are not) is asserted on GPU only, after everything is
written; on CPU the counts are reported as skipped.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import jax

from pi0_jax import benchmark
from pi0_jax.config import get_config
from pi0_jax.quant import report, schemes

FP8_CALL = "__cublas$lt$matmul$f8"
STAGE_NAMES = {"encode_images": "vision", "fill_prefix_cache": "prefix", "denoise": "denoise"}


def expected_fp8_calls(config, prog: str, stage: str) -> int:
    """FP8 x FP8 GEMMs in a stage program. The prefix program returns only K/V, so its last layer's attention
    output and MLP are dead code; the expert is weight-only (bf16 x FP8 is not an FP8 GEMM)."""
    L, V = config.paligemma.depth, config.siglip.depth
    if stage == "encode_images":
        return 6 * V + 1 if prog == "vision" else 0  # q, k, v, out, 2 MLP per block + head
    if stage == "fill_prefix_cache":
        return {"prefix-mlp": 2 * (L - 1), "prefix-all": L + (L - 1) + 2 * (L - 1)}.get(prog, 0)
    return 0


def time_scheme_stages(variants, config, batch, args, timings, hlo):
    sets = [benchmark.make_inputs(config, batch, config.num_cameras, args.prompt_tokens, args.seed + i)
            for i in range(2)]
    base = variants.engine("bf16")
    cameras, bucket = base.plan(sets[0][0])
    packed = [base.pack(obs, cameras, bucket) for obs, _ in sets]
    rows = []
    for scheme in ("bf16", *schemes.SCHEMES):
        row = {"scheme": scheme, "batch": batch, "steps": args.steps}
        for stage, short in STAGE_NAMES.items():
            prog = report.canonical(scheme, stage) if scheme != "bf16" else "bf16"
            key = (stage, prog, batch)
            if key not in timings:
                t0 = time.perf_counter()
                exe, eng = variants.stage(prog, stage, batch, args.steps, cameras, bucket)
                compile_s = time.perf_counter() - t0
                w = eng.weights
                if stage == "encode_images":
                    fn, inputs = (lambda im: exe(w, im)), [(p[0],) for p in packed]
                elif stage == "fill_prefix_cache":
                    toks = [variants.stage("bf16", "encode_images", batch, args.steps, cameras, bucket)[0](
                        variants.engine("bf16").weights, p[0]) for p in packed]
                    fn, inputs = (lambda it, p: exe(w, it, p[1], p[2], p[3])), list(zip(toks, packed))
                else:
                    pre, e2 = variants.stage("bf16", "fill_prefix_cache", batch, args.steps, cameras, bucket)
                    enc = variants.stage("bf16", "encode_images", batch, args.steps, cameras, bucket)[0]
                    caches = [pre(e2.weights, enc(e2.weights, p[0]), p[1], p[2], p[3]) for p in packed]
                    sched = eng.schedule(args.steps)
                    fn = lambda c, p, n: exe(w, sched, c, p[4], n)  # noqa: E731
                    inputs = [(c, p, n) for c, p, (_, n) in zip(caches, packed, sets)]
                timings[key] = {**benchmark.time_calls(fn, inputs, args.iters, args.warmup), "compile_s": compile_s}
                text = exe.as_text()
                hlo[key] = {"stage": short, "program": prog, "batch": batch, "found": text.count(FP8_CALL),
                            "expected": expected_fp8_calls(config, prog, stage)}
                print(f"  {short:8s} {prog:15s} B={batch:3d}: {timings[key]['median_ms']:8.3f} ms "
                      f"(compile {compile_s:.1f} s)  FP8 GEMMs {hlo[key]['found']}/{hlo[key]['expected']}",
                      flush=True)
            row[short] = timings[key]["median_ms"]
        row["denoise_per_step_ms"] = row["denoise"] / args.steps
        row["total_ms"] = row["vision"] + row["prefix"] + row["denoise"]
        rows.append(row)
    return rows


def timing_markdown(rows):
    lines = ["| scheme | batch | vision ms | prefix ms | denoise ms/step | total ms (10 steps) | vs bf16 |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        bf = next(b for b in rows if b["batch"] == r["batch"] and b["scheme"] == "bf16")
        lines.append(f"| {r['scheme']} | {r['batch']} | {r['vision']:.3f} | {r['prefix']:.3f} | "
                     f"{r['denoise_per_step_ms']:.3f} | {r['total_ms']:.2f} | {bf['total_ms'] / r['total_ms']:.2f}x |")
    return "\n".join(lines)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--preset", default="pi0_base", help="preset timed (default: %(default)s)")
    p.add_argument("--acc-presets", default=None, help="comma list for the accuracy report (default: preset, and "
                   "pi05_base when the preset is pi0_base)")
    p.add_argument("--batch", default="1,8,64", help="timed batch sizes (default: %(default)s)")
    p.add_argument("--steps", type=int, default=10)
    p.add_argument("--iters", type=int, default=20)
    p.add_argument("--warmup", type=int, default=3)
    p.add_argument("--prompt-tokens", type=int, default=20)
    p.add_argument("--calib-samples", type=int, default=4)
    p.add_argument("--percentile", type=float, default=99.99)
    p.add_argument("--eval-batch", type=int, default=8, help="accuracy batch (reuses its timed programs)")
    p.add_argument("--eval-batches", type=int, default=1)
    p.add_argument("--no-timing", action="store_true")
    p.add_argument("--quick", action="store_true", help="batch 1,8; 10 iters; accuracy on --preset only")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()
    if args.quick:
        args.batch, args.iters = "1,8", 10
        args.acc_presets = args.acc_presets or args.preset
    batches = [int(b) for b in args.batch.split(",") if b]
    acc_presets = (args.acc_presets or (f"{args.preset},pi05_base" if args.preset == "pi0_base" else args.preset))
    gpu = jax.devices()[0].platform == "gpu"
    results = {"env": benchmark.environment(), "args": vars(args) | {"out": str(args.out)}, "timing": [],
               "hlo": [], "accuracy": {}, "hlo_asserted": gpu}
    args.out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()

    def save():
        (args.out / "quant_gpu.json").write_text(json.dumps(results, indent=2, default=str) + "\n")
        md = [f"{results['env']['device']} · jax {results['env']['jax']} · commit {results['env']['commit']}", ""]
        if results["timing"]:
            md += [f"## FP8 vs bf16 per stage ({args.preset}, {args.steps} steps)", "", timing_markdown(
                results["timing"]), "", "## FP8 GEMM custom calls in the optimized HLO (`" + FP8_CALL + "`)", "",
                "| stage | program | batch | expected | found | ok |", "|---|---|---|---|---|---|"]
            md += [f"| {h['stage']} | {h['program']} | {h['batch']} | {h['expected']} | {h['found']} | "
                   f"{'yes' if h['found'] == h['expected'] else ('**no**' if gpu else 'skipped (CPU)')} |"
                   for h in results["hlo"]]
        for preset, rows in results["accuracy"].items():
            md += ["", report.markdown(rows, f"## Accuracy vs bf16: {preset} (random weights, realistic inputs, "
                                             f"fixed noise, {args.steps} steps)")]
        (args.out / "quant_gpu.md").write_text("\n".join(md) + "\n")

    for preset in dict.fromkeys([args.preset] + acc_presets.split(",")):
        config = get_config(preset, dtype="bfloat16")
        print(f"== {preset} ({time.perf_counter() - t_start:.0f} s)", flush=True)
        params = benchmark.random_params(config, args.seed)
        tok = report.demo_tokenizer(config)
        calib = schemes.sample_observations(config, args.calib_samples, seed=args.seed + 1000, tokenizer=tok)
        stats = schemes.calibrate(config, params, calib, percentile=args.percentile, num_steps=args.steps)
        variants = report.Variants(config, params, stats)
        if preset == args.preset and not args.no_timing:
            timings, hlo = {}, {}
            for batch in batches:
                results["timing"] += time_scheme_stages(variants, config, batch, args, timings, hlo)
                variants.drop()
                results["hlo"] = list(hlo.values())
                save()
        if preset in acc_presets.split(","):
            data = report.eval_set(config, args.eval_batches, args.eval_batch, args.seed + 2000, tok)
            results["accuracy"][preset] = report.accuracy(variants, data, args.steps, methods=("amax", "percentile"))
            print(report.markdown(results["accuracy"][preset]), flush=True)
            save()
        del variants, params
    results["wall_s"] = time.perf_counter() - t_start
    save()
    print((args.out / "quant_gpu.md").read_text())
    bad = [h for h in results["hlo"] if h["found"] != h["expected"]]
    if gpu and bad:
        print(f"FP8 HLO check FAILED for {len(bad)} programs: {bad}", file=sys.stderr)
        return 1
    print("FP8 HLO check: " + ("passed" if gpu else "skipped (not a GPU)"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
