"""Where a program's CUDA graph launches go, without a profiler: runs a command with `cuda_launch_shim.c` preloaded
(built here with gcc), which times every `cuGraphLaunch` the process makes, counts the kernel nodes XLA updated in
the graph before each launch (`cuGraphExecKernelNodeSetParams`: a command's buffers moved) and writes the first 40
graphs instantiated as DOT files (`cuGraphDebugDotPrint`: each node's type, kernel and parameters, and the edges),
then sums them up: per graph executable, its launches, their median host time and the node updates a launch (and
per phase of the command, with `--phases-from`); per DOT file, its nodes by type and its edges. XLA looks the
driver's entry points up by `dlsym`, which the shim answers for these. GPU only, Linux:

    python3 scripts/launch_shim.py --out DIR -- python3 scripts/graph_launch_probe.py --kernels 128 --kind fusion
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import re
import statistics
import subprocess
import sys
from pathlib import Path

NODE_TYPES = ("KERNEL", "MEMSET", "MEMCPY", "CHILD_GRAPH", "EMPTY", "EVENT_RECORD", "WAIT_EVENT", "CONDITIONAL", "HOST",
              "MEM_ALLOC", "MEM_FREE", "BATCH_MEM_OP")


def read_log(log: Path) -> tuple[list[tuple[str, float, float, int]], dict[str, int]]:
    """The shim's log (made at the process's first dlsym): its launches in order, (graph executable, host µs, start µs
    on the clock of `time.perf_counter`, kernel nodes updated before it), and each executable's instantiate flags."""
    launched, flags = [], {}
    for line in (log.read_text().splitlines() if log.exists() else ()):
        parts = line.split()
        if parts[0] == "launch":
            launched.append((parts[1], float(parts[2]), float(parts[3]), int(parts[4])))
        elif parts[0] == "instantiate":
            flags[parts[1]] = int(parts[3])
    return launched, flags


def graph_rows(launched: list, flags: dict) -> list[dict]:
    """Per graph executable in `launched` (`read_log`'s launches), the most launched first: its launches, their
    median and least host µs, its instantiate flags and the kernel nodes updated a launch (mean)."""
    launches, updates = collections.defaultdict(list), collections.defaultdict(list)
    for exec_, host_us, _, nodes in launched:
        launches[exec_].append(host_us)
        updates[exec_].append(nodes)
    return [{"exec": k, "launches": len(v), "median_us": round(statistics.median(v), 2), "min_us": min(v),
             "instantiate_flags": flags.get(k), "node_updates_per_launch": round(statistics.mean(updates[k]), 1)}
            for k, v in sorted(launches.items(), key=lambda kv: -len(kv[1]))]


def summary(root: Path, phases: dict | None = None) -> dict:
    """The shim's log and DOT files in root summed up; phases ({name: [start, end]} in seconds on
    `time.perf_counter`'s clock, as a probe's JSON writes them under "phases_s"): the graphs of each phase's
    launches apart."""
    launched, flags = read_log(root / "shim.log")
    graphs = graph_rows(launched, flags)
    by_phase = {name: graph_rows([x for x in launched if a <= x[2] / 1e6 <= b], flags)
                for name, (a, b) in (phases or {}).items()}
    dots = []
    for path in sorted(root.glob("*.dot")):
        text = path.read_text(errors="replace")
        types = collections.Counter(re.findall(r"\b(" + "|".join(NODE_TYPES) + r")\b", text))
        dots.append({"file": path.name, "nodes": dict(types), "edges": text.count("->")})
    return {"graphs": graphs, "dot_files": dots, **({"phases": by_phase} if phases else {})}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, required=True, help="folder for the shim's log, the DOT files and summary.json")
    p.add_argument("--phases-from", type=Path, default=None,
                   help="a JSON the command writes with its phases' times (\"phases_s\": {name: [start, end]}, "
                        "seconds on time.perf_counter's clock; vision_split_probe.py's --out): each phase's graphs "
                        "apart")
    p.add_argument("command", nargs=argparse.REMAINDER, help="the command to run, after --")
    args = p.parse_args()
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        p.error("no command given (put it after --)")
    args.out.mkdir(parents=True, exist_ok=True)
    shim = args.out / "cuda_launch_shim.so"
    source = Path(__file__).with_name("cuda_launch_shim.c")
    subprocess.run(["gcc", "-shared", "-fPIC", "-O2", "-o", str(shim), str(source), "-ldl"], check=True)
    env = {**os.environ, "LD_PRELOAD": str(shim.resolve()), "SHIM_DIR": str(args.out.resolve())}
    code = subprocess.run(command, env=env).returncode
    phases = None
    if args.phases_from:
        if not args.phases_from.exists():
            print(f"--phases-from: {args.phases_from} was not written; the summary has no phases", file=sys.stderr)
        else:
            phases = json.loads(args.phases_from.read_text()).get("phases_s")
    result = summary(args.out, phases)
    (args.out / "summary.json").write_text(json.dumps(result, indent=1))
    for g in result["graphs"][:12]:
        print(json.dumps(g))
    for name, rows in result.get("phases", {}).items():
        for g in rows[:6]:
            print(json.dumps({"phase": name, **g}))
    for d in result["dot_files"]:
        print(json.dumps(d))
    return code


if __name__ == "__main__":
    sys.exit(main())
