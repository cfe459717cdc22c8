"""Where the host's time goes inside a program's dispatch, by native stack samples (py-spy, not a dependency of the
project: `pip install py-spy`): `run` calls a jitted chain of 128 XLA fusions in one command buffer
(`graph_launch_probe.chain`) N times, its previous output alive during each call; `summary` reads py-spy's raw
output and prints, over the samples inside XLA's `Execute`, each function's inclusive and self share. GPU only (to
be meaningful):

    py-spy record --native --format raw -r 400 -o spy.txt -- python3 scripts/dispatch_spy.py run 3000
    python3 scripts/dispatch_spy.py summary spy.txt
"""

import argparse
import collections
import sys
from pathlib import Path


def run(n: int) -> None:
    import jax
    import jax.numpy as jnp
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import graph_launch_probe
    x = jax.random.normal(jax.random.PRNGKey(0), (graph_launch_probe.ROWS, graph_launch_probe.WIDTH), jnp.bfloat16)
    fn = jax.jit(graph_launch_probe.chain("fusion", 128)).lower(x, x).compile()
    print("median dispatch us", graph_launch_probe.dispatch_us(fn, (x, x), n, blocked=True))


def summary(path: str, top: int = 60) -> None:
    inclusive, own, total = collections.Counter(), collections.Counter(), 0
    for line in open(path):
        stack, _, count = line.rstrip("\n").rpartition(" ")
        if not stack:
            continue
        frames = [f.split(" (")[0] for f in stack.split(";")]
        if not any("Execute" in f for f in frames):
            continue
        total += int(count)
        for f in set(frames):
            inclusive[f] += int(count)
        own[frames[-1]] += int(count)
    print("samples inside Execute:", total)
    for title, counter in (("inclusive", inclusive), ("self", own)):
        print("---", title)
        for f, n in counter.most_common(top):
            print(f"{n:6d} {100 * n / max(total, 1):5.1f}% {f[:150]}")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="command", required=True)
    r = sub.add_parser("run", help="call the toy program N times (run it under py-spy)")
    r.add_argument("calls", type=int, nargs="?", default=300, help="calls (default: %(default)s)")
    m = sub.add_parser("summary", help="the functions of py-spy's raw output inside XLA's Execute")
    m.add_argument("raw", help="py-spy's --format raw output")
    m.add_argument("--top", type=int, default=60, help="functions listed of each kind (default: %(default)s)")
    args = p.parse_args()
    if args.command == "run":
        run(args.calls)
    else:
        summary(args.raw, args.top)


if __name__ == "__main__":
    main()
