"""The vision program cut in two: does the call start sooner?

The call's first program is the vision tower, and the host dispatches it before any kernel runs: its 195 weight
buffers cost the host about 1.2-1.7 µs each (docs/BENCHMARKS.md, "The host's share of a call"), all on the call's
critical path. The programs after it are dispatched while the GPU runs the one before. Here the tower runs as two
programs: the patch embedding and the first `n` blocks (7 buffers a block), then the other blocks, the final norm
and the projection, dispatched while the GPU runs the first. The call's other programs are the engine's own.

Timed round-robin in one process against the call with the tower as one program (the engine's call before session
46, when this probe led to `runtime.VISION_SPLIT`), with each variant's host time until its first program is
dispatched (the call returns before the GPU is done), its kernel span and count from a trace, and its actions
against the one-program call's.

    python scripts/vision_split_probe.py --split 3 --split 6 --split 9 --split 13 --out vision_split.json
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

from pi0_jax.engine import programs, runtime  # noqa: E402
from pi0_jax.ops import matmul  # noqa: E402


def split_programs(engine, images, n: int):
    """(head, tail, head weights, tail weights): the tower's first n blocks and the rest as the engine's two vision
    programs run them (`programs.encode_images_head` / `encode_images_tail` on `runtime.stage_tree`'s weights),
    compiled for `images` (C, B, H, W, 3) with the cut at n."""
    head_w, tail_w = (runtime.stage_tree(engine.weights, s, n) for s in ("vision_head", "vision_tail"))
    kw = {"attention": engine.attention, "kernels": engine.kernels}
    head = functools.partial(programs.encode_images_head, engine.config, **kw)
    tail = functools.partial(programs.encode_images_tail, engine.config, cameras=images.shape[0], **kw)
    options = matmul.compiler_options(head_w, engine.gemm, vision_tower=True)
    head_c = jax.jit(head).lower(head_w, images).compile(options)
    tail_c = jax.jit(tail).lower(tail_w, *head_c.out_info).compile(options)
    return head_c, tail_c, head_w, tail_w


def main() -> None:
    p = profile_engine.probe_arguments(__doc__, 40, "each variant's call, dispatch and kernels")
    p.add_argument("--split", type=int, action="append", default=None,
                   help="blocks in the first vision program, repeatable (default: 3, 6, 9, 13)")
    args = p.parse_args()
    config, engine, noise, cameras, bucket, packed = profile_engine.probe_engine(args)
    images, image_masks, tokens, token_mask, state = packed
    after = [s for s in engine.call_stages(args.batch, args.steps) if s not in runtime.VISION_STAGES]
    vision_p, act, *rest = (engine.executable(s, args.batch, args.steps, cameras, bucket)
                            for s in ("encode_images", *after))
    w, sched = engine.weights, engine.schedule(args.steps)

    def finish(image_tokens):
        out = act(w, sched, image_tokens, image_masks, tokens, token_mask, state, noise)
        return rest[0](w, sched, *out) if rest else out

    calls = {"one program": lambda: finish(vision_p(w, images))}
    firsts = {"one program": lambda: vision_p(w, images)}
    for n in args.split or [3, 6, 9, 13]:
        head, tail, hw, tw = split_programs(engine, images, n)
        calls[f"split {n}"] = functools.partial(lambda h, t, hw, tw: finish(t(tw, *h(hw, images))), head, tail, hw, tw)
        firsts[f"split {n}"] = functools.partial(lambda h, hw: h(hw, images), head, hw)
        print(f"split {n}: head {len(jax.tree.leaves(hw))} buffers, tail {len(jax.tree.leaves(tw))}", flush=True)
    want = np.asarray(calls["one program"](), np.float64)
    report = {"env": profile_engine.benchmark.environment(), "rows": {}}
    for name, fn in calls.items():
        jax.block_until_ready(fn())
        got = np.asarray(fn(), np.float64)
        t = profile_engine.kernel_times(fn, 3)
        report["rows"][name] = {"rel_l2_vs_one": float(np.linalg.norm(got - want) / np.linalg.norm(want)),
                                "kernels_per_call": t["kernels_per_call"], "span_ms": t["span_ms"],
                                "idle_ms": t["idle_ms"]}
    # the host's time to dispatch each variant's first program (it returns before its kernels run)
    for name, fn in firsts.items():
        ts = []
        for _ in range(args.iters):
            jax.block_until_ready(calls["one program"]())
            start = time.perf_counter()
            out = fn()
            ts.append((time.perf_counter() - start) * 1e3)
            jax.block_until_ready(out)
        report["rows"][name]["first_dispatch_ms"] = float(np.median(ts))
    times = profile_engine.round_robin(calls, args.iters)
    loops = profile_engine.round_robin({k: profile_engine.looping(fn, 10) for k, fn in calls.items()}, args.iters // 4)
    for name, row in report["rows"].items():
        row["call_ms"] = float(np.median(times[name]))
        row["in_a_loop_ms"] = float(np.median(loops[name])) / 10
        print(name, {k: round(v, 4) if isinstance(v, float) else v for k, v in row.items()}, flush=True)
    profile_engine.write_json(args.out, report)


if __name__ == "__main__":
    main()
