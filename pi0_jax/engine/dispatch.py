"""A compiled program called straight through its loaded executable, without jit's per-argument checks.

At B = 1 the host's dispatch of a call sits on its critical path: the vision program's buffers are handled before
its first kernel runs. jit's C++ call path checks every argument's type, shape, dtype and sharding on every call,
about 1 µs a buffer on the host (docs/BENCHMARKS.md, "The host's share of a call"), and the engine's programs take
their weights as arguments: 195 buffers for π0's vision program. `Direct` hands the buffers to PjRt itself. It
trusts the weights only after the compiled call has accepted those very arrays once (the same objects, checked by
identity on every call), and checks the call's other inputs itself (jax arrays of the program's shapes and dtypes on
its device). Anything else (numpy inputs, another weights tree, a program on several devices or with effects, a jax
whose internals differ) takes the compiled call as before, which also raises the usual errors.
"""

from __future__ import annotations

from typing import Any

import jax
import numpy as np


class Direct:
    """`compiled(weights, *args)`, dispatched to the loaded executable when the inputs allow (`__call__`)."""

    def __init__(self, compiled: jax.stages.Compiled):
        self.compiled = compiled
        self.loaded = None
        try:   # jax internals: any difference leaves the compiled call in charge
            ex = compiled._executable
            call = ex.unsafe_call
            devices = ex.xla_executable.local_devices()
            plain = not (call.ordered_effects or call.has_unordered_effects or call.has_host_callbacks or call.mut)
            if plain and len(devices) == 1:
                self.kept = tuple(sorted(ex._kept_var_idx))
                self.avals = dict(zip(self.kept, ex.in_avals, strict=True))
                self.in_tree, self.out_tree = compiled.in_tree, compiled.out_tree
                self.num_weights = len(jax.tree.leaves(compiled.args_info[0][0]))
                self.device = devices[0]
                self.loaded = ex.xla_executable
        except (AttributeError, TypeError, ValueError, IndexError):
            self.loaded = None
        self.trusted: list | None = None   # the weight arrays the compiled call last accepted

    def __call__(self, weights: Any, *args):
        if self.loaded is None:
            return self.compiled(weights, *args)
        leaves, tree = jax.tree.flatten(((weights, *args), {}))
        n = self.num_weights
        fast = (tree == self.in_tree and self.trusted is not None
                and all(a is b for a, b in zip(leaves[:n], self.trusted, strict=True)))
        if fast:   # the other inputs: on the device already, or numpy arrays to copy there in one transfer
            host = [i for i in self.kept if i >= n and isinstance(leaves[i], np.ndarray)]
            fast = all(self._fits(i, leaves[i]) for i in self.kept if i >= n and not isinstance(leaves[i], np.ndarray))
            fast = fast and all(leaves[i].shape == self.avals[i].shape and leaves[i].dtype == self.avals[i].dtype
                                for i in host)
        if not fast:
            out = self.compiled(weights, *args)
            if tree == self.in_tree and all(self._fits(i, leaves[i]) for i in self.kept if i < n):
                self.trusted = leaves[:n]
            return out
        if host:
            for i, x in zip(host, jax.device_put([leaves[i] for i in host], self.device), strict=True):
                leaves[i] = x
        results = self.loaded.execute_sharded([leaves[i] for i in self.kept])
        return jax.tree.unflatten(self.out_tree, [a[0] for a in results.disassemble_into_single_device_arrays()])

    def _fits(self, i: int, x) -> bool:
        aval = self.avals[i]
        return (isinstance(x, jax.Array) and x.shape == aval.shape and x.dtype == aval.dtype
                and x.sharding.device_set == {self.device} and not x.is_deleted())
