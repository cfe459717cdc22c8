"""Compiled programs on disk, found without tracing: a second process loads its executables in well under a second.

XLA's persistent compilation cache is keyed by the lowered module, so a warm process still traces and lowers every
program first (π0's call at B = 1: about 4-5 s on an H100), and the key is not stable across processes: Mosaic GPU
(jax 0.11) names each kernel module it lowers with a process-wide counter (`mosaic_gpu.dump_basename`,
"expert_gate_up_<n>"), so a process that lowered other programs first computes another key and compiles again
(docs/BENCHMARKS.md, "Warm start").

Here a program is keyed by what it is made from instead: the engine's choices and shapes (the caller's `parts`),
the argument tree (structure, shapes, dtypes, shardings), the compiler options, the device and backend, jax and
jaxlib, XLA_FLAGS, the jax settings that change lowering, and a digest of this package's source. Module state
changed at run time (a probe that patches a constant or a default) is not in the key: such code runs with
`cache_dir=False`, as the tests and `scripts/` do. Entries are written whole (a temporary file, then a rename); one
that fails to load is reported, removed and compiled again. Each source change or upgrade makes new keys (about
2 MB a program), so the store prunes itself when it writes: an entry not loaded or written for `max_age_days` goes,
as does a temporary file a killed writer left.

GPU only (`PLATFORMS`): on a CPU (jaxlib 0.10.2) a loaded executable failed to run where the process that wrote it,
or the one that read it, had compiled other programs first ("Function broadcast_maximum_fusion not found", "Function
dot_kernel not found"), so there the programs compile as before, from XLA's cache; the CPU tests run loaded programs
only in fresh processes. A loaded program's first call is checked wherever the store is on (`_Loaded`): one that
fails to run is compiled again and its entry written anew.
"""

from __future__ import annotations

import functools
import hashlib
import os
import pickle
import tempfile
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import jax
import jaxlib
from jax.experimental import serialize_executable

FORMAT = 1  # bump when the entry layout changes
PLATFORMS = ("gpu",)  # where stored executables are used (the module doc says why not on a CPU)


def tree_digest(root: Path) -> str:
    """sha256 over the Python sources under root (relative paths and contents, sorted)."""
    h = hashlib.sha256()
    for path in sorted(Path(root).rglob("*.py")):
        h.update(str(path.relative_to(root)).encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()


@functools.lru_cache(maxsize=1)
def source_digest() -> str:
    """`tree_digest` of this package's source."""
    return tree_digest(Path(__file__).resolve().parents[1])


def _environment() -> tuple:
    dev = jax.devices()[0]
    return (FORMAT, jax.__version__, jaxlib.__version__, dev.platform, dev.device_kind, jax.device_count(),
            getattr(dev.client, "platform_version", ""), os.environ.get("XLA_FLAGS", ""),
            jax.config.jax_enable_x64, str(jax.config.jax_default_matmul_precision), source_digest())


def _signature(args) -> tuple:
    """The arguments' tree and each leaf's shape, dtype and sharding (None for abstract leaves)."""
    leaves, tree = jax.tree.flatten(args)
    return str(tree), tuple((tuple(x.shape), str(x.dtype), str(getattr(x, "sharding", None))) for x in leaves)


class ProgramStore:
    """Serialized executables under `root`, one file per key; root None: nothing kept, every program compiled.
    max_age_days: an entry neither loaded nor written for that long is removed at the next write."""

    def __init__(self, root: str | os.PathLike | None, max_age_days: float = 30.0):
        self.root = None if root is None else Path(root)
        self.max_age_s = max_age_days * 86400.0
        self.loaded = 0   # programs this store handed back from disk (tests and benchmarks read it)

    def key(self, name: str, parts: tuple, args, options: dict | None) -> str:
        blob = repr((name, parts, _signature(args), sorted((options or {}).items()), _environment()))
        return f"{name}-{hashlib.sha256(blob.encode()).hexdigest()[:32]}"

    def compile(self, name: str, parts: tuple, fn: Callable, args, options: dict | None = None):
        """`jax.jit(fn).lower(*args).compile(options)`, or the stored executable of the same key."""
        def fresh():
            return jax.jit(fn).lower(*args).compile(options)

        if self.root is None or jax.devices()[0].platform not in PLATFORMS:
            return fresh()
        path = self.root / f"{self.key(name, parts, args, options)}.pkl"
        if path.exists():
            try:
                payload, in_tree, out_tree = pickle.loads(path.read_bytes())
                compiled = serialize_executable.deserialize_and_load(payload, in_tree, out_tree)
                self.loaded += 1
                _touch(path)   # in use: the age the pruning reads
                return _Loaded(compiled, path, fresh, functools.partial(self._store, path))
            except Exception as e:   # a truncated or foreign file: say so, drop it, compile again
                warnings.warn(f"compiled program {path} did not load ({type(e).__name__}: {e}); compiling again",
                              stacklevel=2)
                path.unlink(missing_ok=True)
        compiled = fresh()
        self._store(path, compiled)
        self.prune()
        return compiled

    def _store(self, path: Path, compiled) -> None:
        self._write(path, pickle.dumps(serialize_executable.serialize(compiled)))

    def prune(self, now: float | None = None) -> list[Path]:
        """Remove entries older than `max_age_s` (by modification time, which a load renews) and temporary files
        over a day old; returns what went. Another process's removal or a read-only directory is not an error."""
        if self.root is None or not self.root.is_dir():
            return []
        now = time.time() if now is None else now
        gone = []
        for path in self.root.iterdir():
            limit = self.max_age_s if path.suffix == ".pkl" else 86400.0 if path.suffix == ".tmp" else None
            try:
                if limit is not None and now - path.stat().st_mtime > limit:
                    path.unlink()
                    gone.append(path)
            except OSError:
                pass
        return gone

    def _write(self, path: Path, data: bytes) -> None:
        self.root.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=self.root, prefix=path.name, suffix=".tmp")
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(data)
            os.chmod(tmp, 0o644)   # mkstemp's file is private; a cache directory may be shared
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise


def _touch(path: Path) -> None:
    try:
        os.utime(path)
    except OSError:   # a read-only shared store: its entries just age
        pass


class _Loaded:
    """A stored executable whose first call waits for its result: if it fails to run for want of a function of its
    own (the CPU failure of the module doc: "Function ... not found"), the program is compiled here, written over
    its entry (the failure is the process's: a fresh one loads it) and the call made again (programs donate no
    input, so the arguments are intact). Any other error (out of memory, say) is the caller's, and the entry
    stays."""

    def __init__(self, compiled, path: Path, recompile: Callable, write: Callable):
        self._compiled, self._path, self._recompile, self._write = compiled, path, recompile, write
        self._checked = False

    def __call__(self, *args):
        if self._checked:
            return self._compiled(*args)
        try:
            out = jax.block_until_ready(self._compiled(*args))
        except jax.errors.JaxRuntimeError as e:
            if "not found" not in str(e):
                raise
            warnings.warn(f"compiled program {self._path} failed to run ({e}); compiling it again", stacklevel=2)
            self._compiled = self._recompile()
            try:
                self._write(self._compiled)
            except OSError as err:   # a read-only store: the call still runs, the old entry stays
                warnings.warn(f"could not write {self._path} again ({err})", stacklevel=2)
            out = self._compiled(*args)
        self._checked = True
        return out

    def as_text(self) -> str:
        return self._compiled.as_text()

    @property
    def compiled(self):
        """The loaded (or, after a failed first call, recompiled) program."""
        return self._compiled

    @property
    def out_info(self):
        return self._compiled.out_info


def shapes(tree):
    """Shape-and-dtype structs of a tree of arrays, or of a compiled or stored program's `out_info` (its outputs,
    read off the executable, not traced again): the arguments to compile a program that takes them."""
    return jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), tree)
