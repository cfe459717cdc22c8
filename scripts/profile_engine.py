"""Where the time goes: kernel counts of the compiled engine programs and a jax.profiler trace.

Counts, from the optimized HLO of each stage program: fusions (one GPU kernel each), library calls (cuBLAS GEMMs,
cuDNN, ...) and copies, in the whole program and inside the denoise loop body (i.e. per step when the loop is
rolled). Optionally writes a jax.profiler trace of a few fused calls (open it in TensorBoard / Perfetto) and sums its
GPU kernels by name (`kernel_times`): what each kernel costs inside the program, and how much of the wall time the
GPU sat idle between kernels.

    python scripts/profile_engine.py --preset pi05_base --batch 1 --steps 10 [--trace DIR]
    python scripts/profile_engine.py --preset pi0_base --attention xla --attention auto --time --trace-stages \
        --out profile.json        # two engines on the same weights: counts, stage times, per-kernel traces

Variants are the product of --attention, --kernels, --gemm, --vision-norm, --triton and --blocks; with --time they
are timed round-robin (one call of each per round, the order reversed every other round), so drift over the run hits
all alike.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import functools
import glob
import gzip
import itertools
import json
import re
import tempfile
import time
from pathlib import Path

import jax
import numpy as np

from pi0_jax import benchmark
from pi0_jax.config import get_config
from pi0_jax.engine import Engine, paths
from pi0_jax.ops import expert_kernels, matmul, pallas_base
from pi0_jax.quant import schemes


def count_ops(hlo: str) -> dict:
    """Kernel-level op counts per HLO computation ('ENTRY' and each while body). An async fusion or copy counts
    at its start (`fusion-start`: XLA runs a dynamic slice of a contiguous block as a memcpy, `memcpy32_post` in a
    trace; its `-done` is no kernel)."""
    counts, current = {}, None
    for line in hlo.splitlines():
        head = re.match(r"^(ENTRY )?%?([\w.\-]+) .*\{$", line)
        if head:
            current = ("ENTRY " if head.group(1) else "") + head.group(2)
            counts[current] = {"fusion": 0, "custom-call": 0, "copy": 0, "while": 0, "other": 0}
            continue
        m = re.search(r"=.*?\b(fusion|custom-call|copy|while|convolution|dot)(-start)?\(", line)
        if current and m:
            kind = m.group(1)
            counts[current][kind if kind in counts[current] else "other"] += 1
    return {k: v for k, v in counts.items() if sum(v.values())}


def loop_invariant_kernels(hlo: str) -> dict:
    """{while body: [(kernel, op_name)]}: each kernel-level op (`count_ops`' fusions, calls and copies) of a while
    loop's body whose inputs are all the same in every trip: constants, or carried values the body passes on
    unchanged. Each is work a loop makes every trip that could be made once before it (XLA sinks constants into a
    body and does not hoist what the body computes from invariant values: sessions 70-71, docs/BENCHMARKS.md)."""
    comps, current = {}, None
    for line in hlo.splitlines():
        head = re.match(r"^(?:ENTRY )?%?([\w.\-]+) .*\{$", line)
        if head:
            current = comps.setdefault(head.group(1), [])
        elif line.startswith("}"):
            current = None
        elif current is not None and line.strip():
            current.append(line.strip())
    found = {}
    for body in sorted(set(re.findall(r"\bwhile\(.*?body=%?([\w.\-]+)", hlo))):
        ops = {}
        for line in comps.get(body, []):
            m = re.match(r"(ROOT )?%([\w.\-]+) = .*? ([a-z\-]+)\((.*)$", line)
            if not m:
                continue
            rest, depth, end = m.group(4), 1, 0
            while depth and end < len(rest):   # the operand list ends at its closing parenthesis
                depth += {"(": 1, ")": -1}.get(rest[end], 0)
                end += 1
            index = re.search(r"\bindex=(\d+)", rest[end:])
            name = re.search(r'op_name="([^"]*)"', rest)
            ops[m.group(2)] = (m.group(3), re.findall(r"%([\w.\-]+)", rest[:end]), index and int(index.group(1)),
                               bool(m.group(1)), name.group(1) if name else "")
        param = next(n for n, o in ops.items() if o[0] == "parameter")
        root = next(o for o in ops.values() if o[3])
        passed = {i for i, r in enumerate(root[1]) if ops.get(r, ("",))[0] == "get-tuple-element"
                  and ops[r][1] == [param] and ops[r][2] == i}
        same = {}
        for n, (op, args, index, _, _) in ops.items():   # operands come before their users in HLO text
            if op == "parameter":
                same[n] = False
            elif op == "get-tuple-element" and args == [param]:
                same[n] = index in passed
            else:
                same[n] = all(same.get(a, True) for a in args if a in ops)
        found[body] = [(n, o[4]) for n, o in ops.items()
                       if same[n] and o[0] in ("fusion", "fusion-start", "custom-call", "copy", "copy-start",
                                               "convolution", "dot")]
    return found


CALL = "profile_engine.call"   # the host's span of one traced call (`traced`), from dispatch to block_until_ready


def traced(fn, calls: int) -> tuple:
    """Run fn() `calls` times under jax.profiler (after one untraced call), each call inside a `CALL` annotation ->
    (the perfetto trace's events, thread names by (pid, tid), the GPU processes' pids, the host-timed wall per call
    in s)."""
    jax.block_until_ready(fn())
    with tempfile.TemporaryDirectory() as log_dir:
        with jax.profiler.trace(log_dir, create_perfetto_trace=True):
            start = time.perf_counter()
            for _ in range(calls):
                with jax.profiler.TraceAnnotation(CALL):
                    jax.block_until_ready(fn())
            wall = (time.perf_counter() - start) / calls
        events = json.load(gzip.open(glob.glob(f"{log_dir}/**/perfetto_trace.json.gz", recursive=True)[0]))
    events = events["traceEvents"] if isinstance(events, dict) else events
    procs = {e["pid"]: e["args"]["name"] for e in events if e.get("name") == "process_name"}
    threads = {(e["pid"], e["tid"]): e["args"]["name"] for e in events if e.get("name") == "thread_name"}
    return events, threads, {pid for pid, name in procs.items() if "GPU" in name.upper()}, wall


def gpu_kernels(events, threads, gpu) -> list:
    """The trace's GPU kernels [(start us, duration us, full name)] in launch order: they sit on the device's
    "Stream #N" lines; other device lines (XLA Ops / Modules) repeat them as spans."""
    return sorted((float(e["ts"]), float(e.get("dur", 0.0)), e["name"]) for e in events
                  if e.get("ph") == "X" and e["pid"] in gpu
                  and threads.get((e["pid"], e.get("tid")), "").startswith("Stream"))


def kernel_times(fn, calls: int = 5, sequence: bool = False, host: bool = False) -> dict:
    """Run fn() `calls` times under jax.profiler and sum the GPU kernels of the trace by name (numeric suffixes
    dropped: fusion.12 and fusion.40 are one row). Per call: kernels launched, their summed time, the host-timed wall
    time, busy = summed / wall (the wall holds the host's dispatch and synchronisation too), and the device's own
    span and idle time (`idle`). sequence: also the first traced call's kernels in launch order, each with its
    full name (the optimized HLO's instruction name for XLA's fusions) and duration in us. host: also the host's
    events during each call's lead (`edges`)."""
    events, threads, gpu, wall = traced(fn, calls)
    kernels = gpu_kernels(events, threads, gpu)
    short = [(ts, dur, re.sub(r"([._]\d+)+$", "", name)) for ts, dur, name in kernels]
    rows = collections.defaultdict(lambda: [0, 0.0])
    for _, dur, name in short:
        rows[name][0] += 1
        rows[name][1] += dur
    launched = len(kernels) / calls
    first = [(name, round(dur, 3)) for _, dur, name in kernels[:round(launched)]] if sequence else []
    busy_us = sum(t for _, t in rows.values()) / calls
    top = sorted(rows.items(), key=lambda kv: -kv[1][1])
    return {"calls": calls, "wall_ms": wall * 1e3, "kernels_per_call": launched, "kernel_ms": busy_us / 1e3,
            "busy": busy_us / 1e3 / (wall * 1e3) if wall else None,
            "device_lines": sorted(name for key, name in threads.items() if key[0] in gpu),
            **idle(short, calls), **edges(events, kernels, gpu, host),
            "by_name": [{"name": n, "per_call": c / calls, "us_per_call": t / calls} for n, (c, t) in top[:60]],
            **({"sequence": first} if sequence else {})}


def edges(events, kernels, gpu=frozenset(), host: bool = False) -> dict:
    """Each traced call's edges, from its host span (the `CALL` annotation) and the GPU kernels inside it (the trace
    puts host and device on one clock): `lead_us`, the host's dispatch up to the call's first kernel; `tail_us`,
    its last kernel's end up to the host's return from block_until_ready; `gaps_us`, the device's idle between them
    (every gap, long or short, unlike `idle`). Medians over the calls; empty when the trace has no annotation.
    host: also `lead_events`, the host's traced events (not those of the `gpu` pids) that overlap the lead, summed by
    name over the calls (nested events each count: read them as a profile's inclusive times), and `lead_timeline`,
    the first call's events that start in its lead: (µs from the call's start, duration, name); and `call_events`,
    the host's events inside the whole call, summed by name (the driver's launches: one `cuGraphLaunch` a CUDA graph,
    one `cuLaunchKernel(Ex)` a kernel outside the graphs)."""
    spans = sorted((float(e["ts"]), float(e["ts"]) + float(e.get("dur", 0.0))) for e in events
                   if e.get("ph") == "X" and e.get("name") == CALL)
    lead, tail, gaps = [], [], []
    on_host = [(float(e["ts"]), float(e.get("dur", 0.0)), e["name"]) for e in events
               if e.get("ph") == "X" and e["pid"] not in gpu and e.get("name") != CALL] if host else []
    during = collections.defaultdict(lambda: [0, 0.0])
    whole = collections.defaultdict(lambda: [0, 0.0])
    timeline = []
    for start, end in spans:
        inside = [(ts, ts + dur) for ts, dur, _ in kernels if start <= ts <= end]
        if not inside:
            continue
        lead.append(inside[0][0] - start)
        if host and not timeline:   # the first call's lead, event by event (µs from the call's start)
            timeline = [(round(ts - start, 1), round(dur, 1), name) for ts, dur, name in sorted(on_host)
                        if start <= ts < inside[0][0]][:300]
        for ts, dur, name in on_host:   # clipped to the lead [start, first kernel)
            overlap = min(ts + dur, inside[0][0]) - max(ts, start)
            if overlap > 0:
                during[name][0] += 1
                during[name][1] += overlap
            if start <= ts < end:
                whole[name][0] += 1
                whole[name][1] += dur
        last, idle_us = inside[0][1], 0.0
        for ts, stop in inside[1:]:
            idle_us += max(0.0, ts - last)
            last = max(last, stop)
        tail.append(end - last)
        gaps.append(idle_us)
    if not lead:
        return {}
    def rows(sums, by):
        top = sorted(sums.items(), key=lambda kv: -kv[1][by])[:40]
        return [{"name": n, "per_call": c / len(lead), "us_per_call": t / len(lead)} for n, (c, t) in top]

    return {"lead_us": float(np.median(lead)), "tail_us": float(np.median(tail)), "gaps_us": float(np.median(gaps)),
            **({"lead_events": rows(during, 1), "lead_timeline": timeline, "call_events": rows(whole, 0)}
               if host else {})}


def idle(kernels, calls: int, between_calls_us: float = 100.0) -> dict:
    """The GPU's idle time inside the program, from the trace's kernels [(start us, duration us, name)]: `span_ms`
    is the first kernel's start to the last one's end per call (the device's time, without the host's dispatch and
    synchronisation, which `wall_ms` holds), `idle_ms` the span not covered by kernels, and `idle_before` sums each
    gap under the name of the kernel that ends it (which launch waited). A gap over `between_calls_us` is taken as
    the host's turn between two calls (`idle_max_us` says whether that cut went through a call)."""
    kernels.sort()
    span, gaps, largest = 0.0, collections.defaultdict(lambda: [0, 0.0]), 0.0
    start, end = None, None
    for ts, dur, name in kernels:
        if end is not None and ts - end <= between_calls_us:
            gap = max(0.0, ts - end)
            gaps[name][0] += 1
            gaps[name][1] += gap
            largest = max(largest, gap)
        else:
            span += 0.0 if end is None else end - start
            start = ts
        end = max(end or ts, ts + dur)
    span += 0.0 if end is None else end - start
    total = sum(t for _, t in gaps.values())
    top = sorted(gaps.items(), key=lambda kv: -kv[1][1])
    return {"span_ms": span / calls / 1e3, "idle_ms": total / calls / 1e3, "idle_max_us": largest,
            "idle_before": [{"name": n, "per_call": c / calls, "us_per_call": t / calls} for n, (c, t) in top[:25]]}


def probe_arguments(doc: str, iters: int, out: str) -> argparse.ArgumentParser:
    """The probes' parser (`dispatch_probe.py`, `chain_probe.py`, `order_probe.py`): one model, random weights,
    3 cameras; out: what --out's JSON holds."""
    p = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", default="pi0_base", help="model preset, random weights (default: %(default)s)")
    p.add_argument("--batch", type=int, default=1)
    p.add_argument("--steps", type=int, default=10)
    p.add_argument("--prompt-tokens", type=int, default=48)
    p.add_argument("--iters", type=int, default=iters, help="timed calls of each variant (default: %(default)s)")
    p.add_argument("--out", type=Path, default=None, help=f"JSON of {out}")
    return p


def write_json(path: Path | None, report: dict) -> None:
    if path:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(report, indent=2))


def probe_engine(args, **engine_options) -> tuple:
    """(config, engine, noise, cameras, prompt bucket, packed inputs) for the probes' flags."""
    config = get_config(args.preset)
    engine = Engine(config, benchmark.random_params(config, 0), cache_dir=False, **engine_options)
    obs, noise = benchmark.make_inputs(config, args.batch, 3, args.prompt_tokens, 0)
    cameras, bucket = engine.plan(obs)
    return config, engine, noise, cameras, bucket, engine.pack(obs, cameras, bucket)


def round_robin(calls: dict, iters: int, warmup: int = 3, settle: int = 1) -> dict:
    """ms of each no-argument call, blocked on its output: one call of each per round, the order reversed every
    other round (a program timed right after another runs 1-3 % slower, docs/BENCHMARKS.md). settle: untimed calls
    of a variant right before its timed one, so that its buffers lie where its CUDA graphs last saw them: after
    another variant's call they do not, and XLA updates the graphs' nodes before launching them (0.3-1.4 ms on π0's
    call on two H100s; one untimed call takes the updates to none; docs/BENCHMARKS.md, session 78). Before session
    78 the probes timed with settle = 0."""
    times = {k: [] for k in calls}
    for i in range(warmup + iters):
        for name, fn in (calls.items() if i % 2 else reversed(calls.items())):
            for _ in range(settle):
                jax.block_until_ready(fn())
            start = time.perf_counter()
            jax.block_until_ready(fn())
            if i >= warmup:
                times[name].append((time.perf_counter() - start) * 1e3)
    return times


def looping(fn, n: int):
    """A no-argument call of n calls of fn in a row, each blocked on its output (the loop a robot runs; `round_robin`
    times it against other such loops)."""
    def run():
        for _ in range(n):
            out = jax.block_until_ready(fn())
        return out
    return run


def call_marks(engine: Engine, batch: int, steps: int, cameras, bucket, packed, noise, iters: int = 30) -> dict:
    """Untraced host times of the engine's call (`Engine.sample_packed`), median µs from the call's start: when each
    program's dispatch returned (its `stage`), and when `block_until_ready` returned ("done"). The GPU starts a
    program about when its dispatch returns, so the first mark bounds the call's lead; a later program whose mark
    comes after the GPU has run the ones before it (their kernel times from a trace) left the GPU idle."""
    marks = []

    class Marked:   # a Program that notes when its dispatch returned
        def __init__(self, prog):
            self.prog, self.stage = prog, prog.stage

        def __call__(self, *a):
            out = self.prog(*a)
            marks.append((self.stage, time.perf_counter()))
            return out

    marked = tuple(Marked(p) for p in engine.call_programs(batch, steps, cameras, bucket))
    engine.call_programs = lambda *_: marked   # this instance's calls only, until the end
    rows = []
    try:
        for i in range(iters + 3):
            marks.clear()
            start = time.perf_counter()
            jax.block_until_ready(engine.sample_packed(packed, noise, steps, cameras, bucket))
            done = time.perf_counter()
            if i >= 3:
                rows.append({**{s: (t - start) * 1e6 for s, t in marks}, "done": (done - start) * 1e6})
    finally:
        del engine.call_programs
    return {k: round(float(np.median([r[k] for r in rows])), 1) for k in rows[0]}


def stage_calls(engine: Engine, batch: int, steps: int, cameras, bucket, packed, noise) -> dict:
    """Each stage program as a no-argument call on fixed inputs (the denoise gets a fresh copy of the noise), the
    fused program ("infer") and the engine's call ("call": `Engine.sample_packed`, two programs). A program is
    compiled at its call's first use, and the prefix's and the denoise's inputs made once, then."""
    w, sched = engine.weights, engine.schedule(steps)

    def prog(stage):
        return engine.executable(stage, batch, steps, cameras, bucket)

    @functools.cache
    def tokens():
        return prog("encode_images")(w, packed[0])

    @functools.cache
    def cache():
        return prog("fill_prefix_cache")(w, tokens(), *packed[1:4])

    return {"encode_images": lambda: prog("encode_images")(w, packed[0]),
            "fill_prefix_cache": lambda: prog("fill_prefix_cache")(w, tokens(), *packed[1:4]),
            "denoise": lambda: prog("denoise")(w, sched, cache(), packed[4], noise),
            "infer": lambda: prog("infer")(w, sched, *packed, noise),
            "call": lambda: engine.sample_packed(packed, noise, steps, cameras, bucket)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", default="pi05_base", help="model preset, random weights (default: %(default)s)")
    p.add_argument("--dtype", default="bfloat16")
    p.add_argument("--batch", type=int, default=1)
    p.add_argument("--steps", type=int, default=10)
    p.add_argument("--cameras", type=int, default=3)
    p.add_argument("--prompt-tokens", type=int, default=20)
    p.add_argument("--no-unroll", action="store_true")
    p.add_argument("--unroll-steps", action="store_true")
    p.add_argument("--kernels", choices=paths.KERNELS, action="append", default=None,
                   help="Engine's `kernels` (the expert's layers: XLA, Pallas, or auto by batch size); repeat it to "
                        "compare, like --attention (default: auto)")
    p.add_argument("--attention", action="append", default=None,
                   help="each stage's attention (Engine's `attention`); repeat it to compare several engines on the "
                        "same weights and inputs in one process (default: auto)")
    p.add_argument("--gemm", choices=matmul.GEMMS, action="append", default=None,
                   help="the library of XLA's GEMMs on a GPU (Engine's `gemm`); repeat it to compare (default: auto)")
    p.add_argument("--vision-norm", choices=("auto", "xla", "pallas"), action="append", default=None,
                   help="SigLIP's LayerNorm (`paths.vision_norm`; auto: as the kernels choose); repeat it to "
                        "compare (default: auto)")
    p.add_argument("--triton", choices=("on", "off"), action="append", default=None,
                   help="off: trace the variant's programs as on a jax without Pallas's Triton backend "
                        "(`pallas_base.TRITON` False: the \"auto\" choices without it); repeat it to compare "
                        "(default: on)")
    p.add_argument("--blocks", action="append", default=None,
                   help="JSON of `expert_kernels.Blocks` fields over this jax's default launch of the expert's "
                        "kernels (e.g. '{\"mosaic_attention\": true}'; a GEMM's launch as an object, "
                        "'{\"out\": {\"cols\": 32, \"splits\": 4}}'); repeat it to compare (default: {})")
    p.add_argument("--time", action="store_true",
                   help="median ms of each stage program (and the fused one), round-robin over the variants (every "
                        "engine is kept until the end: mind device memory)")
    p.add_argument("--iters", type=int, default=30, help="timed calls per program with --time")
    p.add_argument("--trace-stages", action="store_true",
                   help="sum each stage program's GPU kernels from a profiler trace (`kernel_times`)")
    p.add_argument("--kernel-sequence", action="store_true",
                   help="with --trace-stages: also each program's kernels of one call in launch order, by full name "
                        "(to read against --dump-hlo's fusions)")
    p.add_argument("--host-events", action="store_true",
                   help="with --trace-stages: also the host's traced events during each program's lead, the time from "
                        "its dispatch to its first kernel, summed by name")
    p.add_argument("--stages", default=None,
                   help="with --trace-stages: a comma list of the programs to trace (encode_images, fill_prefix_cache, "
                        "denoise, infer, call; default: all)")
    p.add_argument("--trace", type=Path, default=None, help="write a jax.profiler trace of 3 fused calls here")
    p.add_argument("--out", type=Path, default=None, help="JSON of the counts, times and traces")
    p.add_argument("--dump-hlo", type=Path, default=None, help="write each stage program's optimized HLO here")
    p.add_argument("--quant", default=None, choices=sorted(schemes.SCHEMES),
                   help="an FP8 scheme for every variant, calibrated on 4 sampled observations (as `pi0-jax "
                        "benchmark --quant`; default: none)")
    args = p.parse_args()

    config = get_config(args.preset, dtype=args.dtype)
    params = benchmark.random_params(config, 0)
    if args.quant:
        params = benchmark.fp8_params(config, params, args.quant, num_steps=args.steps)
    obs, noise = benchmark.make_inputs(config, args.batch, args.cameras, args.prompt_tokens, 0)
    report = {"preset": args.preset, "batch": args.batch, "steps": args.steps, "quant": args.quant,
              "env": benchmark.environment(),
              "variants": []}
    outputs, timed = {}, []
    vision_norm = paths.vision_norm
    has_triton, default_blocks = pallas_base.TRITON, expert_kernels.default_blocks
    for attention, kernels, gemm, norm, triton, blocks in itertools.product(
            args.attention or ["auto"], args.kernels or ["auto"], args.gemm or ["auto"], args.vision_norm or ["auto"],
            args.triton or ["on"], args.blocks or ["{}"]):
        pallas_base.TRITON = has_triton and triton == "on"   # until this variant's programs are traced
        expert_kernels.default_blocks = lambda fields=json.loads(blocks): expert_kernels.Blocks.from_dict(
            dataclasses.asdict(default_blocks()) | fields)
        # the programs are traced below, inside this variant: its LayerNorm choice holds for all of them
        paths.vision_norm = vision_norm if norm == "auto" else (lambda kernels, images, platform=None, n=norm: n)
        engine = Engine(config, params, unroll=not args.no_unroll, unroll_steps=args.unroll_steps,
                        kernels=kernels, attention=attention, gemm=gemm, cache_dir=False)
        cameras, bucket = engine.plan(obs)
        packed = engine.pack(obs, cameras, bucket)
        var = {"attention": str(engine.attention), "kernels": engine.kernels_for(args.batch), "gemm": gemm,
               "triton": pallas_base.TRITON, "blocks": json.loads(blocks),
               "vision_norm": paths.vision_norm(kernels, args.batch * len(cameras)),
               "counts": {}, "median_ms": {}, "trace": {}}
        print(f"== attention {var['attention']}, kernels {var['kernels']}, gemm {gemm}, vision norm "
              f"{var['vision_norm']}, triton {triton}, blocks {blocks}", flush=True)
        for stage in ("encode_images", "fill_prefix_cache", "denoise", "prefix_denoise", "infer"):
            exe = engine.executable(stage, args.batch, args.steps, cameras, bucket)
            counts = var["counts"][stage] = count_ops(exe.as_text())
            if args.dump_hlo:
                args.dump_hlo.mkdir(parents=True, exist_ok=True)
                tag = f"{var['attention']}_{kernels}_{gemm}_{norm}".replace(",", "_").replace("=", "-")
                (args.dump_hlo / f"{stage}_b{args.batch}_{tag}.hlo.txt").write_text(exe.as_text())
            for comp, c in counts.items():
                if comp.startswith("ENTRY") or c["fusion"] + c["custom-call"] > 20:
                    print(f"   {stage:18s} {comp[:50]:50s} {json.dumps(c)}", flush=True)
        calls = stage_calls(engine, args.batch, args.steps, cameras, bucket, packed, noise)
        outputs[f"{var['attention']} {kernels} {gemm} {norm} triton-{triton} {blocks}"] = np.asarray(
            calls["infer"](), np.float64)
        jax.block_until_ready(calls["call"]())   # the call's two programs are compiled here, under this variant
        timed.append((var, calls))
        for stage, fn in calls.items():
            if args.trace_stages and (args.stages is None or stage in args.stages.split(",")):
                t = var["trace"][stage] = kernel_times(fn, 5, sequence=args.kernel_sequence, host=args.host_events)
                print(f"   {stage:18s} {t['kernels_per_call']:.0f} kernels, {t['kernel_ms']:.3f} ms in kernels of "
                      f"{t['wall_ms']:.3f} ms ({t['busy']:.0%} busy); device span {t['span_ms']:.3f} ms, idle "
                      f"{t['idle_ms']:.3f} ms inside it (largest gap {t['idle_max_us']:.1f} us)", flush=True)
                if "lead_us" in t:
                    print(f"      host to first kernel {t['lead_us']:.1f} us, last kernel to host {t['tail_us']:.1f} "
                          f"us, device idle between {t['gaps_us']:.1f} us (medians a call)", flush=True)
                for row in t.get("lead_events", [])[:25]:
                    print(f"      lead {row['us_per_call']:9.1f} us  x{row['per_call']:6.1f}  {row['name'][:100]}",
                          flush=True)
                for row in t["by_name"][:12]:
                    print(f"      {row['us_per_call']:9.1f} us  x{row['per_call']:6.1f}  {row['name'][:80]}", flush=True)
                print("      idle before:", flush=True)
                for row in t["idle_before"][:8]:
                    print(f"      {row['us_per_call']:9.1f} us  x{row['per_call']:6.1f}  {row['name'][:80]}", flush=True)
        var["compile_s"] = {k[0]: round(v, 2) for k, v in engine.compile_seconds.items()}
        print("   compile s: " + json.dumps(var["compile_s"]), flush=True)
        report["variants"].append(var)
        if args.trace:
            fn = calls["infer"]
            name = f"{var['attention']}_{kernels}_{gemm}".replace(",", "_").replace("=", "-")
            with jax.profiler.trace(str(args.trace / name)):
                for _ in range(3):
                    jax.block_until_ready(fn())
        del engine
    paths.vision_norm = vision_norm
    pallas_base.TRITON, expert_kernels.default_blocks = has_triton, default_blocks
    if args.time:   # round-robin: one call of each variant's stage per round, so drift hits all variants alike;
        # the order flips every round: a program timed right after another runs 1-3 % slower (docs/BENCHMARKS.md)
        times = [{stage: [] for stage in calls} for _, calls in timed]
        for i in range(3 + args.iters):
            rounds = list(zip(timed, times))
            for (var, calls), per_stage in (rounds if i % 2 else rounds[::-1]):
                for stage, fn in calls.items():
                    start = time.perf_counter()
                    jax.block_until_ready(fn())
                    if i >= 3:
                        per_stage[stage].append((time.perf_counter() - start) * 1e3)
        for (var, _), per_stage in zip(timed, times):
            var["median_ms"] = {k: float(np.median(v)) for k, v in per_stage.items()}
            var["p10_p90_ms"] = {k: [float(np.percentile(v, q)) for q in (10, 90)] for k, v in per_stage.items()}
            medians = json.dumps({k: round(v, 3) for k, v in var["median_ms"].items()})
            print(f"== {var['attention']}, kernels {var['kernels']}, gemm {var['gemm']}, vision norm "
                  f"{var['vision_norm']}, triton {var['triton']}, blocks {var['blocks']}: median ms {medians}",
                  flush=True)
    first = next(iter(outputs.values()))
    report["rel_l2_vs_first"] = {k: float(np.linalg.norm(v - first) / np.linalg.norm(first)) for k, v in outputs.items()}
    print("actions, relative L2 against the first variant:", json.dumps(report["rel_l2_vs_first"]), flush=True)
    write_json(args.out, report)


if __name__ == "__main__":
    main()
