"""The vision program cut in two or more: does the call start sooner?

The call's first program is the vision tower, and the host dispatches it before any kernel runs: its 115 weight
buffers and 202 kernels (π0, B = 1), all on the call's critical path (docs/BENCHMARKS.md, "The host's share of a
call", sessions 49 and 69). The programs after it are dispatched while the GPU runs the one before. Here the tower
runs as two programs: the patch embedding and the first `n` blocks (4 buffers a block), then the other blocks, the
final norm and the projection, dispatched while the GPU runs the first. A cut of several points (`--split 3,9`) runs the
blocks between them as programs of their own, each dispatched while the GPU runs the one before: a small first
program starts the GPU sooner, and the next ones must each be dispatched before the GPU has run the one before.
Every program here is called as the engine calls its own (`engine.dispatch`). The call's other programs are the
engine's own.

Timed round-robin in one process against the call with the tower as one program (the engine's call before session
46, when this probe led to `runtime.VISION_SPLIT`) and the engine's own call, with each variant's host time until
its first program is dispatched (the call returns before the GPU is done), its kernel span and count from a trace,
and its actions against the one-program call's. Each call is timed twice: right after the other variants' calls,
and after `--settle` untimed calls of its own (XLA may first update the CUDA graphs' nodes of a call whose buffers
moved since its last: session 78 found the first way 0.3-1.4 ms slower at the median on two H100s, and the last
variant of a round, run twice in a row at each turn, favoured; docs/BENCHMARKS.md).

    python scripts/vision_split_probe.py --split 3 --split 6 --split 9 --split 13 --out vision_split.json
    python scripts/vision_split_probe.py --split 9 --split 1,9 --split 3,9 --iters 100 --out vision_splits.json
"""

from __future__ import annotations

import functools
import sys
import time
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
import profile_engine  # noqa: E402

from pi0_jax.engine import dispatch, paths, programs, runtime, vision  # noqa: E402
from pi0_jax.ops import matmul  # noqa: E402


def split_programs(engine, images, cuts: tuple[int, ...]):
    """[(program, weights), ...]: the tower cut before each block of `cuts` as the engine's two vision programs run
    it (`programs.encode_images_head` / `encode_images_tail` on `runtime.stage_tree`'s weights), with the blocks
    between two cuts as programs of their own (`encode_middle`), compiled for `images` (C, B, H, W, 3) and called
    through `engine.dispatch`."""
    kw = {"attention": engine.attention, "kernels": engine.kernels}
    head_w, tail_w = runtime.stage_tree(engine.weights, "vision_head", cuts[0]), \
        runtime.stage_tree(engine.weights, "vision_tail", cuts[-1])
    options = matmul.compiler_options(head_w, engine.gemm, vision_tower=True)
    head = jax.jit(functools.partial(programs.encode_images_head, engine.config, **kw)).lower(head_w, images)
    out = [(head.compile(options), head_w)]
    img = engine.weights["img"]
    for a, b in zip(cuts, cuts[1:]):
        w = {"img": {"blocks": img["blocks"][a:b], "vectors": img["vectors"]}}
        fn = functools.partial(encode_middle, engine.config, first=a, attention=engine.attention,
                               kernels=engine.kernels)
        out.append((jax.jit(fn).lower(w, *out[-1][0].out_info).compile(options), w))
    tail = functools.partial(programs.encode_images_tail, engine.config, cameras=images.shape[0], **kw)
    out.append((jax.jit(tail).lower(tail_w, *out[-1][0].out_info).compile(options), tail_w))
    return [(dispatch.Dispatch(c), w) for c, w in out]


def encode_middle(config, w, x, f, *, first: int, attention, kernels):
    """Blocks first .. first + len(w["img"]["blocks"]) of the tower from the (x, f) of the blocks before them, as
    `vision.encode_head` returns it -> the same (x, f) after them."""
    x, f = vision.blocks_from(config.siglip, w["img"], x, f, first, attention=attention.vision,
                              norm=paths.vision_norm(kernels, x.shape[0]))
    return x, (f[0], f[2])


def run_split(parts, images):
    """The image tokens through `split_programs`' programs, each taking the (x, f) of the one before."""
    (head, hw), *rest = parts
    out = head(hw, images)
    for prog, w in rest:
        out = prog(w, *out)
    return out


def main() -> None:
    p = profile_engine.probe_arguments(__doc__, 40, "each variant's call, dispatch and kernels")
    p.add_argument("--split", action="append", default=None,
                   help="blocks in the first vision program, or the blocks before each of several programs "
                        "comma-separated (3,9: blocks 0-2, 3-8 and 9 on); repeatable (default: 3, 6, 9, 13)")
    p.add_argument("--settle", type=int, default=1,
                   help="also time each variant's call after this many untimed calls of it in a row, its buffers "
                        "where its CUDA graphs last saw them (0: not; default: %(default)s)")
    args = p.parse_args()
    config, engine, noise, cameras, bucket, packed = profile_engine.probe_engine(args)
    images = packed[0]
    after = [s for s in engine.call_stages(args.batch, args.steps) if s not in runtime.VISION_STAGES]
    vision_p, act, *rest = (engine.executable(s, args.batch, args.steps, cameras, bucket)
                            for s in ("encode_images", *after))
    w, sched = engine.weights, engine.schedule(args.steps)

    def call_with(vision):   # the engine's call with the tower as `vision(weights, images)` runs it
        return runtime.run_call((vision, act, *rest), False, w, sched, packed, noise)

    calls = {"one program": lambda: call_with(vision_p),
             "the engine's call": lambda: engine.sample_packed(packed, noise, args.steps, cameras, bucket)}
    head_p = engine.call_programs(args.batch, args.steps, cameras, bucket)[0]
    firsts = {"one program": lambda: vision_p(w, images), "the engine's call": lambda: head_p(w, images)}
    for spec in args.split or ["3", "6", "9", "13"]:
        cuts = tuple(int(c) for c in spec.split(",") if c.strip().isdigit())
        if len(cuts) != len(spec.split(",")) or list(cuts) != sorted(set(cuts)) or not 0 < cuts[0] \
                or cuts[-1] >= config.siglip.depth:
            p.error(f"--split {spec}: cuts must rise within 1 .. {config.siglip.depth - 1}")
        parts = split_programs(engine, images, cuts)
        calls[f"split {spec}"] = functools.partial(lambda parts: call_with(lambda _, x: run_split(parts, x)), parts)
        firsts[f"split {spec}"] = functools.partial(lambda h, hw: h(hw, images), *parts[0])
        print(f"split {spec}: buffers " + ", ".join(str(len(jax.tree.leaves(w))) for _, w in parts), flush=True)
    want = np.asarray(calls["one program"](), np.float64)
    report = {"env": profile_engine.benchmark.environment(), "rows": {}}
    for name, fn in calls.items():
        jax.block_until_ready(fn())
        got = np.asarray(fn(), np.float64)
        t = profile_engine.kernel_times(fn, 3)
        report["rows"][name] = {"rel_l2_vs_one": float(np.linalg.norm(got - want) / np.linalg.norm(want)),
                                "kernels_per_call": t["kernels_per_call"], "span_ms": t["span_ms"],
                                "idle_ms": t["idle_ms"]}
    # the host's time to dispatch each variant's first program (it returns before its kernels run), after a call of
    # the variant itself (after another's, the program's buffers may have moved: see the module doc)
    for name, fn in firsts.items():
        ts = []
        for _ in range(args.iters):
            jax.block_until_ready(calls[name]())
            start = time.perf_counter()
            out = fn()
            ts.append((time.perf_counter() - start) * 1e3)
            jax.block_until_ready(out)
        report["rows"][name]["first_dispatch_ms"] = float(np.median(ts))
    # the phases' times on `time.perf_counter`'s clock, which `launch_shim.py`'s log of graph launches shares
    report["phases_s"] = {"round_robin": [time.perf_counter()]}
    times = profile_engine.round_robin(calls, args.iters, settle=0)
    report["phases_s"]["round_robin"].append(time.perf_counter())
    report["phases_s"]["settled"] = [time.perf_counter()]
    settled = profile_engine.round_robin(calls, args.iters, settle=args.settle) if args.settle else {}
    report["phases_s"]["settled"].append(time.perf_counter())
    for name, row in report["rows"].items():
        for key, t in (("call", times), ("settled_call", settled)):
            if t:
                row[f"{key}_ms"] = float(np.median(t[name]))
                row[f"{key}_p10_p90_ms"] = [float(np.percentile(t[name], q)) for q in (10, 90)]
        print(name, {k: round(v, 4) if isinstance(v, float) else v for k, v in row.items()}, flush=True)
    profile_engine.write_json(args.out, report)


if __name__ == "__main__":
    main()
