"""Where the host's time goes inside a program's dispatch, by native stack samples (py-spy, not a dependency of the
project: `pip install py-spy`): `run` calls a jitted chain of 128 XLA fusions in one command buffer
(`graph_launch_probe.chain`) N times, its previous output alive during each call; `summary` reads py-spy's raw
output and prints, over the samples inside XLA's `Execute`, each function's inclusive and self share. GPU only (to
be meaningful):

    py-spy record --native --format raw -r 400 -o spy.txt -- python3 scripts/dispatch_spy.py run 3000
    python3 scripts/dispatch_spy.py summary spy.txt
"""

import collections
import sys
import time
from pathlib import Path


def run(n: int) -> None:
    import jax
    import jax.numpy as jnp
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import graph_launch_probe
    x = jax.random.normal(jax.random.PRNGKey(0), (graph_launch_probe.ROWS, graph_launch_probe.WIDTH), jnp.bfloat16)
    fn = jax.jit(graph_launch_probe.chain("fusion", 128)).lower(x, x).compile()
    out = fn(x, x)
    times = []
    for _ in range(n):
        out.block_until_ready()
        start = time.perf_counter()
        out = fn(x, x)
        times.append(time.perf_counter() - start)
    out.block_until_ready()
    times.sort()
    print("median dispatch us", times[len(times) // 2] * 1e6)


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


if __name__ == "__main__":
    if sys.argv[1:2] == ["run"]:
        run(int(sys.argv[2]) if len(sys.argv) > 2 else 300)
    elif sys.argv[1:2] == ["summary"]:
        summary(sys.argv[2])
    else:
        sys.exit(__doc__)
