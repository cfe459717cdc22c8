"""An engine program's call without jax's per-argument checks of the weights it was given before.

jax's call of a compiled program (`jax.stages.Compiled`, through its C++ path) flattens every argument and checks
its type, shape, dtype and sharding before PjRt runs the executable: about 0.9 µs an argument on an H200's host (a
program of 115 small arguments 236 against 134 µs a call; 0.3-0.6 µs on a CPU core), and the engine's programs take
40-230 weight buffers. `Dispatch` makes the call that jax's ends in, the executable's `execute_sharded`, itself. A
weight that is the same array object as at an earlier call here (jax arrays are immutable; held by weak reference,
so a replaced tree is freed) is not checked again; a new weight and every other argument is checked as jax would
(type, shape, dtype, sharding against the compiled program's). Anything that does not pass goes through jax's own
call, which raises jax's error: PjRt alone checks only each buffer's size in bytes, so a transposed argument of
the same size would run. So does a program this path does not cover (more than one device, effects, host
callbacks, constants of its own, donated or relaid-out inputs, jax's NaN checks on), and the first call of each
program (a stored program checks itself on it: `store._Loaded`). On an H200 the same call without any check took
π0's vision program from 2.50 to 2.38 ms (docs/BENCHMARKS.md, session 76; these checks cost 11-13 µs more on a
CPU core at 115-300 arguments); in this form on H100s, 0-0.06 ms, and π0's call is level: it waits on the GPU
after its first program, whose ~40 weights gain 24 µs, and the host's time a call is 0.3 ms shorter (session 77).

It reads jax's internals (`Compiled._executable`, `._params`, the executable's `unsafe_call`); where a jax has moved
them, every call is jax's own. The engine's tests check that its calls take this path (`direct_calls`), so such a
jax fails a test instead of slowing the engine without a word.
"""

from __future__ import annotations

import dataclasses
import weakref
from typing import Any

import jax

try:
    from jax._src.array import ArrayImpl
except ImportError:   # a jax without it: every call is jax's own
    ArrayImpl = None

# off: every call through jax's own (the benchmark JSON's `env.dispatch`)
DIRECT = True


@dataclasses.dataclass(frozen=True)
class _Plan:
    in_tree: Any        # the flattened (args, kwargs) the program was compiled for
    avals: tuple        # each flat argument's shape and dtype
    shardings: tuple
    weights: int        # flat arguments of the first argument (the weights tree)
    kept: tuple         # the flat arguments the executable takes (XLA drops the unused)
    kept_weights: frozenset
    kept_rest: tuple
    execute: Any        # the executable's execute_sharded
    handlers: list      # its outputs' array handlers
    out_tree: Any


def plan(compiled, args: tuple) -> _Plan | None:
    """How to call `compiled` directly with arguments shaped as `args` (the weights tree first), or None where this
    path does not cover it."""
    try:
        params, run = compiled._params, compiled._executable.unsafe_call
        if (ArrayImpl is None or params.const_args or params.is_high or run.ordered_effects
                or run.has_unordered_effects or run.has_host_callbacks or run.mut or run.pgle_profiler is not None
                or len(run.xla_executable.local_devices()) != 1 or compiled.donate_argnums
                or any(x is not None for x in compiled._executable._dispatch_in_layouts)):
            return None
        # one of each a flat argument (a sharding None where the program does not read it)
        avals = params.in_tree.flatten_up_to(compiled.in_avals)
        shardings = params.in_tree.flatten_up_to(compiled.input_shardings)
        if not args:
            return None
        weights, kept = len(jax.tree.leaves(args[0])), tuple(sorted(run.kept_var_idx))
        return _Plan(params.in_tree, tuple(avals), tuple(shardings), weights, kept,
                     frozenset(i for i in kept if i < weights), tuple(i for i in kept if i >= weights),
                     run.xla_executable.execute_sharded, list(run.out_handler.handlers), compiled.out_tree)
    except (AttributeError, TypeError, ValueError):   # a jax whose internals differ
        return None


class Dispatch:
    """`compiled` (a `jax.stages.Compiled`, or a stored program, `store._Loaded`, whose `compiled` is read after the
    first call) called as `dispatch(weights, *args)`; see the module doc. direct: this program's own switch (with
    the module's `DIRECT`; the probes' "jax-dispatch"); direct_calls: the calls that took the direct path."""

    def __init__(self, compiled):
        self.compiled = compiled
        self.direct = True
        self.direct_calls = 0
        self._plan: _Plan | None = None
        self._planned = False
        self._seen: list = []   # weak references to the weights last checked, by flat position

    def __call__(self, *args):
        if not self._planned:
            out = self.compiled(*args)
            self._plan, self._planned = plan(getattr(self.compiled, "compiled", self.compiled), args), True
            self._seen = [None] * (self._plan.weights if self._plan else 0)
            return out
        p = self._plan
        if p is None or not (DIRECT and self.direct) or jax.config.jax_debug_nans or jax.config.jax_debug_infs:
            return self.compiled(*args)
        leaves, tree = jax.tree.flatten((args, {}))
        if tree != p.in_tree or not self._checked(p, leaves):
            return self.compiled(*args)
        self.direct_calls += 1
        out = p.execute([leaves[i] for i in p.kept]).consume_with_handlers(p.handlers)
        return jax.tree.unflatten(p.out_tree, out)

    def _checked(self, p: _Plan, leaves: list) -> bool:
        """Whether every argument the executable takes is the array it expects: the weights seen before by
        identity, the rest by type, shape, dtype and sharding."""
        seen = self._seen
        for i in p.kept_weights:
            x, ref = leaves[i], seen[i]
            if ref is None or ref() is not x:
                if not _fits(p, i, x):
                    return False
                seen[i] = weakref.ref(x)
        return all(_fits(p, i, leaves[i]) for i in p.kept_rest)


def _fits(p: _Plan, i: int, x) -> bool:
    aval = p.avals[i]
    return (type(x) is ArrayImpl and x.shape == aval.shape and x.dtype == aval.dtype
            and x.sharding == p.shardings[i])
