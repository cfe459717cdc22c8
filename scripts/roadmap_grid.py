"""The origin roadmap, measured (issue 15): task success and inference cost per control step of latency with
sync / naive / rtc execution, prefix reuse across frames, and layer dropping.

Success: a trained checkpoint (default: the embedded pi0_small) in the MJX suite, every cell on the same episodes
(K per task from initial states 0..K-1, held out from training) and the same policy noise (fold_in(seed, episode)),
with Wilson 95 % intervals. Cells, run in the order given until the time budget is spent:

  sync     the baseline: the world waits for each chunk, replan every R steps (= every execution mode at D = 0, and
           sync at any D: sync ignores the delay, so "sync at D" is this cell by construction)
  naive    D-step latency, the previous chunk executed while the next one is computed
  rtc      D-step latency with real-time chunking (frozen committed prefix, guided overlap)
  cond     D-step latency, the committed actions given to the model clean (training-time action conditioning:
           for a checkpoint trained with `pi0-jax train --max-delay`)
  reuseK   vision + prefix KV cache recomputed every K-th plan (e.g. reuse2, reuse4)
  auto     prefix recomputed when the images moved more than --auto-threshold (per environment)
  prune    the checkpoint without --prune-layers (both Gemma towers; `pi0-jax prune`), no recovery fine-tune
  NAME@N   any of these with N flow steps instead of --num-steps (e.g. sync@1, reuse2@1: the embedded model keeps
           its success at 1 step, docs/RESULTS.md, so fewer steps and reuse combine)
  -dD, -rR before @N: this cell's own latency D (naive, rtc, cond; e.g. naive-d1) or replan interval R (any cell; e.g.
           sync-r8@1: plan every 8 steps, the origin notes' "action chunking to infer less often")
  -bBETA   rtc's guidance clip instead of --rtc-beta (e.g. rtc-d1-b0.5)

Cost: the full-size model's stage timings on this device (--timing-preset, random weights, batch 1, 2 cameras, a
20-token prompt, bf16, the cells' flow steps): vision, prefix KV fill, denoise, RTC's guided denoise (a VJP per step,
XLA attention), and prefix + denoise of the preset with the same fraction of layers dropped as the prune cell
(pi0_small 4 -> 2 pairs with pi0_base 18 -> 9; the seed's guess was for 18 -> 12). Per control step:
(vision + prefix + denoise) / R; reuse counts vision + prefix at the cell's measured recompute fraction. naive and
rtc and cond cost what sync costs per step (rtc: its guided denoise); what they buy is that the robot does not wait
(D x 50 ms at 20 Hz: D = 4 is 200 ms).

Writes OUT/roadmap.json (every number, the command line, the device), OUT/roadmap.md (the table, what was not run),
OUT/roadmap.png (success against cost per control step, the Pareto front; not with --no-timing) and
OUT/roadmap_delay.png (success against the delay D, a line per execution mode; where a cell has D > 0). Cells that
did not fit the budget are listed as not run, with the command that runs them. --resume merges earlier runs' rows.

    python scripts/roadmap_grid.py --out $OUT                        # stops after ~6 minutes (--budget-s 330)
    python scripts/roadmap_grid.py --quick --out /tmp/roadmap_quick   # CPU smoke run: a few episodes per cell
"""

from __future__ import annotations

import argparse
import json
import math
import shlex
import sys
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp

import pi0_jax.sim  # noqa: F401  (sets the XLA:CPU flags MJX needs before the backend starts)
from pi0_jax import checkpoint
from pi0_jax.sim.evaluate import EvalConfig, evaluate
from pi0_jax.sim.realtime import CONTROL_HZ

sys.path.insert(0, str(Path(__file__).parent))
from results_grid import wilson  # noqa: E402

EMBEDDED = Path(pi0_jax.sim.__file__).parents[1] / "assets" / "pi0_small"
# What the origin project's notes (../shared/origin) guessed, next to each option.
GUESSED = {"reuse": "KV-cache reuse across frames: 2-3x (one table), 1.5-2x (the other)",
           "prune": "18 -> 12 layers: ~1.5x, 'large accuracy loss' risk",
           "naive": "async 3-stream pipeline: 'hides vision latency'", "rtc": "(not in the notes)",
           "cond": "(not in the notes)",
           "auto": "dynamic similarity detection + partial reuse: no number", "sync": "baseline",
           "chunk": "action chunking, infer less often: 'reduces inference frequency', no number"}


def _beta(text: str) -> bool:
    return text.replace(".", "", 1).isdigit()


def cell_spec(cell: str, args) -> dict:
    """A cell name -> its EvalConfig fields, kind, flow steps and replan interval: KIND[-dD][-rR][-bBETA][@N]."""
    name, _, steps = cell.partition("@")
    kind, *opts = name.split("-")
    own = {o[0]: o[1:] for o in opts if o[:1] in ("d", "r") and o[1:].isdigit() or o[:1] == "b" and _beta(o[1:])}
    if (len(own) != len(opts) or ("d" in own and kind not in ("naive", "rtc", "cond"))
            or ("b" in own and kind != "rtc")):
        raise SystemExit(f"unknown cell {cell!r}: sync, naive, rtc, cond, reuseK, auto, prune, then optionally -dD "
                         "(naive, rtc, cond: latency D), -rR (replan every R steps), -bBETA (rtc: guidance clip), "
                         "@N (N flow steps)")
    spec = _cell_kind(kind, args, int(own.get("d", args.latency_steps)))
    if kind == "rtc":
        spec["rtc_beta"] = float(own.get("b", args.rtc_beta))
    spec["num_steps"] = int(steps) if steps else args.num_steps
    spec["replan_steps"] = int(own.get("r", args.replan_steps))
    return spec


def _cell_kind(name: str, args, delay: int) -> dict:
    if name == "sync":
        return {"kind": "sync", "execution": "sync", "latency_steps": 0, "reuse_prefix": None}
    if name in ("naive", "rtc", "cond"):
        return {"kind": name, "execution": "conditioned" if name == "cond" else name, "latency_steps": delay,
                "reuse_prefix": None}
    if name.startswith("reuse") and name[5:].isdigit():
        return {"kind": "reuse", "execution": "sync", "latency_steps": 0, "reuse_prefix": name[5:]}
    if name == "auto":
        return {"kind": "auto", "execution": "sync", "latency_steps": 0, "reuse_prefix": f"auto:{args.auto_threshold}"}
    if name == "prune":
        return {"kind": "prune", "execution": "sync", "latency_steps": 0, "reuse_prefix": None}
    raise SystemExit(f"unknown cell {name!r}: sync, naive, rtc, cond, reuseK, auto, prune")


# ---------------------------------------------------------------------------------------------------------------------
# Stage timings of the full-size model.


def stage_timings(preset: str, num_steps: int, other_steps: list[int], drop_fraction: float, iters: int,
                  dtype: str) -> dict:
    """Median ms at batch 1 of vision, prefix, denoise (at num_steps and every other_steps count), guided denoise
    (RTC, num_steps), and prefix + denoise with round(depth * drop_fraction) layers dropped (random weights)."""
    from pi0_jax.benchmark import make_inputs, time_calls
    from pi0_jax.config import get_config
    from pi0_jax.engine import Engine, guidance
    from pi0_jax.pi0 import random_params

    def engine_stages(config, guided: bool, extra_steps=()) -> dict:
        engine = Engine(config, random_params(config, 0), kernels="xla")   # guided denoise has no Pallas path
        sets = [make_inputs(config, 1, 2, 20, seed) for seed in range(2)]
        cameras, bucket = engine.plan(sets[0][0])
        packed = [engine.pack(obs, cameras, bucket) for obs, _ in sets]
        w, sched = engine.weights, engine.schedule(num_steps)
        enc = engine.executable("encode_images", 1, 0, cameras, bucket)
        pre = engine.executable("fill_prefix_cache", 1, 0, cameras, bucket)
        den = engine.executable("denoise", 1, num_steps, cameras, bucket)
        out = {"vision": time_calls(lambda im: enc(w, im), [(p[0],) for p in packed], iters, 2)["median_ms"]}
        tokens = [enc(w, p[0]) for p in packed]
        out["prefix"] = time_calls(lambda t, p: pre(w, t, p[1], p[2], p[3]), list(zip(tokens, packed)), iters,
                                   2)["median_ms"]
        caches = [pre(w, t, p[1], p[2], p[3]) for t, p in zip(tokens, packed)]
        args = [(c, p, n) for c, p, (_, n) in zip(caches, packed, sets)]
        out["denoise"] = time_calls(lambda c, p, n: den(w, sched, c, p[4], n), args, iters, 2)["median_ms"]
        out["denoise_at"] = {str(num_steps): out["denoise"]}
        for n_steps in extra_steps:
            d_n, s_n = engine.executable("denoise", 1, n_steps, cameras, bucket), engine.schedule(n_steps)
            out["denoise_at"][str(n_steps)] = time_calls(lambda c, p, n: d_n(w, s_n, c, p[4], n), args,
                                                         iters, 2)["median_ms"]
        out.update(attention=str(engine.attention), prefix_tokens=int(caches[0].mask.shape[1]), depth=config.paligemma.depth)
        if guided:
            h, a = config.action_horizon, config.action_dim
            weight = jnp.broadcast_to(jnp.linspace(1.0, 0.0, h)[None, :, None], (1, h, a))
            fn = jax.jit(lambda c, s, n, y: guidance.guided_denoise(config, w, sched, c, s, n, y, weight,
                                                                    num_steps=num_steps, unroll=True,
                                                                    attention=engine.attention))
            out["guided_denoise"] = time_calls(lambda c, p, n: fn(c, p[4], n, n), args, iters, 2)["median_ms"]
        return out

    config = get_config(preset, dtype=dtype)
    full = engine_stages(config, guided=True, extra_steps=[n for n in other_steps if n != num_steps])
    depth = config.paligemma.depth
    n_drop = int(round(depth * drop_fraction))
    pruned = {}
    if 0 < n_drop < depth:
        small = config.replace(paligemma_variant=f"{config.paligemma_variant}_{depth - n_drop}l",
                               action_expert_variant=f"{config.action_expert_variant}_{depth - n_drop}l")
        pruned = engine_stages(small, guided=False)
    return {"preset": preset, "dtype": dtype, "num_steps": num_steps, "batch": 1, "cameras": 2, "prompt_tokens": 20,
            "full": full, "pruned": pruned}


def cost_per_step(row: dict, t: dict, replan: int) -> float | None:
    """Full-size inference ms per control step of a cell (`replan`: the run's default interval)."""
    if not t:
        return None
    replan = row.get("replan_steps", replan)
    f = t["full"]
    if row["kind"] == "prune":
        if not t["pruned"] or row["num_steps"] != t["num_steps"]:
            return None
        p = t["pruned"]
        return (p["vision"] + p["prefix"] + p["denoise"]) / replan
    den = f["guided_denoise"] if row["kind"] == "rtc" else f["denoise_at"].get(str(row["num_steps"]))
    if den is None or (row["kind"] == "rtc" and row["num_steps"] != t["num_steps"]):
        return None
    frac = row.get("prefix_recompute_fraction", 1.0) if row["kind"] in ("reuse", "auto") else 1.0
    return (frac * (f["vision"] + f["prefix"]) + den) / replan


# ---------------------------------------------------------------------------------------------------------------------


def run_cell(name: str, spec: dict, args, ckpt: Path) -> dict:
    cfg = EvalConfig(suite=args.suite, episodes_per_task=args.episodes_per_task, batch=args.batch,
                     replan_steps=spec["replan_steps"], max_steps=args.max_steps, resolution=args.resolution,
                     seed=args.seed, videos=0, num_steps=spec["num_steps"], execution=spec["execution"],
                     latency_steps=spec["latency_steps"], reuse_prefix=spec["reuse_prefix"],
                     **({"rtc_beta": spec["rtc_beta"]} if "rtc_beta" in spec else {}))
    t0 = time.perf_counter()
    info = evaluate(str(ckpt), cfg, None, progress=False, policy_kwargs={"dtype": args.dtype})
    a = info["aggregated"]
    lo, hi = wilson(a["n_success"], a["n_episodes"])
    row = {"cell": name, **spec, "latency_ms": 1000.0 * spec["latency_steps"] / CONTROL_HZ,
           "n_episodes": a["n_episodes"], "n_success": a["n_success"], "pc_success": a["pc_success"],
           "ci95": [lo, hi], "wall_s": time.perf_counter() - t0, "first_segment_s": a["first_segment_s"],
           "per_group": {g["group"]: g["pc_success"] for g in info["per_group"]}, "checkpoint": str(ckpt)}
    rt = info.get("realtime", {})
    if "prefix_recompute_fraction" in rt:
        row["prefix_recompute_fraction"] = rt["prefix_recompute_fraction"]
    return row


def guess_key(row: dict, result: dict) -> str:
    longer = row.get("replan_steps", result["replan_steps"]) > result["replan_steps"]
    return "chunk" if row["kind"] == "sync" and longer else row["kind"]


def markdown(result: dict) -> str:
    rows, base = result["rows"], next((r for r in result["rows"] if r["cell"] == "sync"), None)
    t = result.get("timing") or {}
    lines = [f"Success: {result['checkpoint_model']} on {result['device']}, {result['episodes']} episodes per cell, "
             f"{result['num_steps']} flow steps, replan every {result['replan_steps']} steps. Cost: "
             + (f"{t['preset']} ({t['dtype']}, batch 1, random weights) stage timings on the same device."
                if t else "not measured (--no-timing)."), "",
             ("| cell | setting | flow steps | replan every | D (steps / ms) | prefix recomputed | "
              "cost per control step (ms) | vs baseline | success | Δ vs baseline | in baseline CI | seed guessed |"),
             "|---|---|---:|---:|---|---:|---:|---:|---:|---:|---|---|"]
    base_cost = cost_per_step(base, t, result["replan_steps"]) if base else None
    for r in rows:
        cost = cost_per_step(r, t, result["replan_steps"])
        setting = {"sync": "sync (world waits)", "naive": "naive async",
                   "rtc": f"real-time chunking, β = {r.get('rtc_beta', 5.0):g}",
                   "cond": "training-time RTC",
                   "reuse": f"reuse prefix K={r['reuse_prefix']}", "auto": f"reuse {r['reuse_prefix']}",
                   "prune": f"drop layers {result['prune_layers']}"}[r["kind"]]
        frac = r.get("prefix_recompute_fraction")
        inside = base is not None and base["ci95"][0] <= r["pc_success"] <= base["ci95"][1]
        delta = "" if base is None else f"{r['pc_success'] - base['pc_success']:+.1f}"
        lines.append(
            f"| {r['cell']} | {setting} | {r['num_steps']} | {r.get('replan_steps', result['replan_steps'])} | "
            f"{r['latency_steps']} / {r['latency_ms']:.0f} | "
            f"{'' if frac is None else f'{100 * frac:.0f} %'} | {'' if cost is None else f'{cost:.2f}'} | "
            f"{'' if cost is None or not base_cost else f'{base_cost / cost:.2f}x'} | "
            f"{r['pc_success']:.1f} % [{r['ci95'][0]:.1f}, {r['ci95'][1]:.1f}] | "
            f"{delta} | "
            f"{'yes' if inside else 'no'} | {GUESSED[guess_key(r, result)]} |")
    if base is not None:
        lines.append(f"| sync D={result['latency_steps']} | sync (world waits) | {base['num_steps']} | "
                     f"{base.get('replan_steps', result['replan_steps'])} | "
                     f"{result['latency_steps']} / {50 * result['latency_steps']} | | = baseline | | = baseline "
                     "(sync ignores D: not run separately) | | | |")
    for name, why in result["not_run"].items():
        lines.append(f"| {name} | not run ({why}) | | | | | | | | | | |")
    if t:
        f = t["full"]
        total = f["vision"] + f["prefix"] + f["denoise"]
        lines += ["", f"Stage timings ({t['preset']}, {f['depth']} layers, {f['prefix_tokens']} prefix "
                      f"tokens, {t['num_steps']} steps): vision {f['vision']:.2f} ms, prefix {f['prefix']:.2f} ms, "
                      f"denoise {f['denoise']:.2f} ms ({f['attention']} attention; by steps "
                      f"{', '.join(f'{k}: {v:.2f} ms' for k, v in f['denoise_at'].items())}), guided denoise (RTC) "
                      f"{f['guided_denoise']:.2f} ms; one inference {total:.1f} ms = "
                      f"{math.ceil(total / (1000 / CONTROL_HZ))} control steps at {CONTROL_HZ} Hz."]
        if t["pruned"]:
            p = t["pruned"]
            lines.append(f"Pruned to {p['depth']} layers: prefix {p['prefix']:.2f} ms, denoise {p['denoise']:.2f} ms.")
    lines += ["", "Command:", "", "```", result["command"], "```", ""]
    return "\n".join(lines)


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def chart(result: dict, path: Path) -> bool:
    """Success against cost per control step, the Pareto front; False (nothing written) without a cost column."""
    t = result.get("timing") or {}
    pts = [(cost_per_step(r, t, result["replan_steps"]), r) for r in result["rows"]]
    pts = [(c, r) for c, r in pts if c is not None]
    if not pts:
        return False
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(8, 5))
    base = next((r for r in result["rows"] if r["cell"] == "sync"), None)
    if base is not None:
        ax.axhspan(*base["ci95"], color="tab:blue", alpha=0.08, label="baseline's 95 % interval")
    xs = [c for c, _ in pts] or [0.0, 1.0]
    lo_x, span_x = min(xs), max(max(xs) - min(xs), 1e-9)

    def frac(c, y, d=(0, 0)):     # axis-fraction position of a point plus an offset in points
        return (c - lo_x) / span_x * 0.85 + 0.05 + d[0] / 600, y / 100 + d[1] / 380

    taken = [frac(c, r["pc_success"]) for c, r in pts]    # markers, then labels as they are placed
    for c, r in pts:
        err = [[r["pc_success"] - r["ci95"][0]], [r["ci95"][1] - r["pc_success"]]]
        ax.errorbar(c, r["pc_success"], yerr=err, fmt="o" if r["latency_steps"] == 0 else "s", capsize=3)
        label = f"{r['cell']}" + (f" (D={r['latency_steps']})" if r["latency_steps"] else "")
        width = 5.2 * len(label)
        # the label spot farthest from every marker and label so far, inside the axes
        spots = [(dx, dy) for dy in (4, -12, 16, -24, 28) for dx in (6, -width - 6, -width / 2)]

        def clearance(d, c=c, y=r["pc_success"], width=width):
            x0, y0 = frac(c, y, (d[0] + width / 2, d[1] + 4))
            if not (0.02 < x0 - width / 1200 and x0 + width / 1200 < 0.98 and 0.0 < y0 < 0.95):
                return -1.0
            return min(abs(x0 - px) * 2.5 + abs(y0 - py) * 12 for px, py in taken) - 0.01 * abs(d[1])
        d = max(spots, key=clearance)
        taken.append(frac(c, r["pc_success"], (d[0] + width / 2, d[1] + 4)))
        ax.annotate(label, (c, r["pc_success"]), textcoords="offset points", xytext=d, fontsize=8,
                    arrowprops={"arrowstyle": "-", "color": "grey", "lw": 0.5} if abs(d[1]) > 12 else None)
    front = sorted(pts, key=lambda p: (p[0], -p[1]["pc_success"]))
    best, line = -1.0, []
    for c, r in front:            # Pareto front: no cheaper cell succeeds as often
        if r["pc_success"] > best:
            best = r["pc_success"]
            line.append((c, best))
    if line:
        ax.step(*zip(*line), where="post", color="grey", alpha=0.5, label="Pareto front")
    ax.set_xlabel(f"full-size inference per control step (ms, {t.get('preset', '?')}, {result['device']})")
    return _save(plt, fig, ax, result, path, f"success against inference cost (squares: D > 0 steps of "
                 f"{1000 // CONTROL_HZ} ms latency)")


def _save(plt, fig, ax, result: dict, path: Path, title: str) -> bool:
    """The success axis, title, grid and legend both charts share; the figure written to path."""
    ax.set_ylabel(f"success (%), {result['episodes']} episodes, 95 % Wilson")
    ax.set_ylim(-4, 100)
    ax.set_title(f"{result['checkpoint_model']}: {title}", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return True


def delay_chart(result: dict, path: Path) -> bool:
    """Success against the delay D (ms), one line per execution mode (rtc per β) at the baseline's flow steps and
    replan interval, each starting at the sync baseline (every mode is the same policy at D = 0); False (nothing
    written) where no such cell has D > 0."""
    base = next((r for r in result["rows"] if r["cell"] == "sync"), None)
    same = [r for r in result["rows"] if r["kind"] in ("naive", "rtc", "cond") and r["latency_steps"] > 0
            and r["num_steps"] == result["num_steps"]
            and r.get("replan_steps", result["replan_steps"]) == result["replan_steps"]]
    if not same:
        return False
    lines: dict[str, list] = {}
    for r in same:
        name = {"naive": "naive", "cond": "conditioned"}.get(r["kind"]) or f"rtc, β = {r.get('rtc_beta', 5.0):g}"
        lines.setdefault(name, []).append(r)
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(8, 5))
    if base is not None:
        ax.axhspan(*base["ci95"], color="tab:blue", alpha=0.08, label="sync (the world waits), 95 % interval")
    for name, rows in sorted(lines.items(), key=lambda kv: (kv[0] != "naive", kv[0])):
        rows = sorted(rows, key=lambda r: r["latency_ms"])
        pts = ([(0.0, base["pc_success"], 0.0, 0.0)] if base is not None else []) + [
            (r["latency_ms"], r["pc_success"], r["pc_success"] - r["ci95"][0], r["ci95"][1] - r["pc_success"])
            for r in rows]
        x, y, lo, hi = zip(*pts)
        ax.errorbar(x, y, yerr=[lo, hi], fmt="-o" if name == "naive" else "-s", capsize=3, label=name,
                    lw=2 if name == "naive" else 1)
    ax.set_xlabel(f"delay D (ms; {1000 // CONTROL_HZ} ms a control step), a new plan every "
                  f"{result['replan_steps']} steps, {result['num_steps']} flow steps")
    return _save(plt, fig, ax, result, path, f"success against inference delay ({result['device']})")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, required=True, help="directory for roadmap.json, roadmap.md, roadmap.png")
    p.add_argument("--checkpoint", type=Path, default=EMBEDDED, help="a trained pi0-jax checkpoint (default: the "
                   "embedded pi0_small)")
    p.add_argument("--cells", default="sync,sync@1,sync-r6@1,rtc,naive,reuse2@1,prune,reuse2,auto,reuse4",
                   help="comma list, run in this order while the budget lasts: sync, naive, rtc, cond (naive-dD, "
                        "rtc-dD, cond-dD: latency D instead of --latency-steps; rtc-bBETA: guidance clip BETA "
                        "instead of --rtc-beta, e.g. rtc-d1-b0.5), reuseK (K an integer), auto, prune, each "
                        "optionally @N for N flow steps (default: %(default)s)")
    p.add_argument("--latency-steps", type=int, default=4, help="D of the naive, rtc and cond cells, in 50 ms control "
                   "steps (default: %(default)s = 200 ms)")
    p.add_argument("--rtc-beta", type=float, default=5.0, help="the rtc cells' guidance clip, the paper's β "
                   "(default: %(default)s)")
    p.add_argument("--auto-threshold", type=float, default=0.1,
                   help="image change (mean absolute difference of 16x16 frames in [0, 1]) above which the auto "
                        "cell recomputes an environment's prefix (default: %(default)s)")
    p.add_argument("--prune-layers", default="1,2", help="layers the prune cell drops from both Gemma towers "
                   "(default: %(default)s: pi0_small keeps 0 and 3)")
    p.add_argument("--episodes-per-task", type=int, default=50, help="episodes per task (default: %(default)s: 550)")
    p.add_argument("--suite", default="all", help="task suite (default: %(default)s)")
    p.add_argument("--batch", type=int, default=550, help="environments at once (default: %(default)s)")
    p.add_argument("--replan-steps", type=int, default=5, help="actions executed per plan (default: %(default)s)")
    p.add_argument("--num-steps", type=int, default=10, help="flow steps (default: %(default)s)")
    p.add_argument("--max-steps", type=int, default=None, help="episode step limit (default: each task's own)")
    p.add_argument("--resolution", type=int, default=None, help="camera pixels (default: the checkpoint's)")
    p.add_argument("--dtype", default=None, choices=("bfloat16", "float32"),
                   help="policy dtype (default: the checkpoint's; --quick: float32, as XLA:CPU emulates bf16)")
    p.add_argument("--seed", type=int, default=0, help="policy noise seed (default: %(default)s)")
    p.add_argument("--budget-s", type=float, default=330.0,
                   help="wall-clock seconds for the whole run: a cell starts only if the time so far plus the "
                        "longest cell so far (first: 90 s) fits; the rest are reported as not run "
                        "(default: %(default)s)")
    p.add_argument("--timing-preset", default="pi0_base", help="full-size preset whose stage timings give the cost "
                   "column (default: %(default)s; random weights)")
    p.add_argument("--timing-iters", type=int, default=20, help="timed calls per stage (default: %(default)s)")
    p.add_argument("--no-timing", action="store_true", help="skip the stage timings (no cost column)")
    p.add_argument("--resume", type=Path, nargs="+", default=None, metavar="JSON",
                   help="previous runs' roadmap.json files (the same model and episodes, on one device kind): their "
                        "rows are kept (a cell's first), the first timings found too, and their cells are not run "
                        "again. A second call fills the cells the first one's budget left out; --cells '' only "
                        "merges them into one table and chart")
    p.add_argument("--cache-dir", type=Path, default=Path.home() / ".cache/pi0_jax/xla",
                   help="persistent compilation cache (default: %(default)s)")
    p.add_argument("--quick", action="store_true",
                   help="CPU smoke run: suite 'goal', 1 episode per task, 12 steps, 3 flow steps, float32, "
                        "timings of the 'dummy' preset with 2 iterations, no budget")
    args = p.parse_args()
    command = "python scripts/roadmap_grid.py " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    if args.quick:
        args.suite, args.episodes_per_task, args.batch, args.max_steps = "goal", 1, 4, 12
        args.num_steps, args.dtype, args.timing_preset, args.timing_iters = 3, args.dtype or "float32", "dummy", 2
        args.budget_s = float("inf")
    args.out.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(args.cache_dir))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)

    from pi0_jax.config import Pi0Config
    from pi0_jax.prune import parse_layers, prune

    model = Pi0Config.from_json(checkpoint.read_meta(args.checkpoint)["model"])
    args.resolution = args.resolution or model.image_size
    drop = parse_layers(args.prune_layers)
    start = time.perf_counter()
    result = {"command": command, "device": jax.devices()[0].device_kind, "jax": jax.__version__,
              "checkpoint": str(args.checkpoint), "checkpoint_model": model.name, "episodes": None,
              "num_steps": args.num_steps, "replan_steps": args.replan_steps, "latency_steps": args.latency_steps,
              "prune_layers": list(drop), "rows": [], "not_run": {}, "timing": None}

    def save():
        (args.out / "roadmap.json").write_text(json.dumps(result, indent=2) + "\n")

    for i, path in enumerate(args.resume or ()):
        prev = json.loads(path.read_text())
        if prev["checkpoint_model"] != model.name or prev["episodes"] != (result["episodes"] or prev["episodes"]):
            raise SystemExit(f"--resume {path}: {prev['checkpoint_model']} on {prev['episodes']} episodes, not "
                             f"{model.name} on {result['episodes'] or 'the same number'}")
        if i == 0:
            result.update(device=prev["device"], checkpoint=prev["checkpoint"], command="")
        elif prev["device"] != result["device"]:
            raise SystemExit(f"--resume {path}: ran on {prev['device']}, the first file on {result['device']}")
        done = {r["cell"] for r in result["rows"]}
        result["rows"] += [r for r in prev["rows"] if r["cell"] not in done]
        result["timing"], result["episodes"] = result["timing"] or prev["timing"], prev["episodes"]
        result["command"] += prev["command"] + "\n"
    if args.resume:
        result["command"] += command
    done = {r["cell"] for r in result["rows"]}
    specs = {c: cell_spec(c, args) for c in args.cells.split(",") if c}     # a bad name fails before any work
    todo = {c: s for c, s in specs.items() if c not in done}
    if todo and result["device"] != jax.devices()[0].device_kind:
        raise SystemExit(f"the resumed rows ran on {result['device']}, this device is "
                         f"{jax.devices()[0].device_kind}: one table, one device kind")
    if not args.no_timing and result["timing"] is None:
        t0 = time.perf_counter()
        steps = sorted({s["num_steps"] for s in specs.values()})
        result["timing"] = stage_timings(args.timing_preset, args.num_steps, steps, len(drop) / model.paligemma.depth,
                                         args.timing_iters, "bfloat16" if not args.quick else "float32")
        result["timing"]["wall_s"] = time.perf_counter() - t0
        print(f"timings ({result['timing']['wall_s']:.0f} s): {json.dumps(result['timing'])}", flush=True)
        save()
    longest = 90.0
    with tempfile.TemporaryDirectory(prefix="roadmap_prune_") as tmp:
        for name, spec in todo.items():
            elapsed = time.perf_counter() - start
            if elapsed + longest > args.budget_s:
                result["not_run"][name] = f"budget: {elapsed:.0f} s spent of {args.budget_s:.0f}"
                print(f"{name}: not run ({result['not_run'][name]})", flush=True)
                continue
            ckpt = args.checkpoint
            if spec["kind"] == "prune":
                ckpt = prune(args.checkpoint, Path(tmp) / "pruned", drop, overwrite=True)
            row = run_cell(name, spec, args, ckpt)
            longest = max(longest if result["rows"] else 0.0, row["wall_s"])
            result["rows"].append(row)
            result["episodes"] = row["n_episodes"]
            print(f"{name:>8}: {row['pc_success']:5.1f}% [{row['ci95'][0]:.1f}, {row['ci95'][1]:.1f}] of "
                  f"{row['n_episodes']}" + (f", prefix recomputed {100 * row['prefix_recompute_fraction']:.0f}%"
                                            if "prefix_recompute_fraction" in row else "")
                  + f" ({row['wall_s']:.0f} s)", flush=True)
            save()
    result["wall_s"] = time.perf_counter() - start
    save()
    (args.out / "roadmap.md").write_text(markdown(result))
    for name, draw in (("roadmap.png", chart), ("roadmap_delay.png", delay_chart)):
        try:
            if not draw(result, args.out / name):
                print(f"no {name}: " + ("no cost column (--no-timing)" if draw is chart else "no cell with D > 0"))
        except ImportError as e:    # the numbers are written already; the pictures need matplotlib
            print(f"no {name}: {e}")
    print(markdown(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
