"""How an evaluation's episodes meet the devices: the episode order, batch sizes, the renderer's ray chunks, device
memory, and agreement between hosts (jax.distributed), for `evaluate`."""

from __future__ import annotations

import math
import os
import re

import jax
import numpy as np


def fetch(x) -> np.ndarray:
    """A global array's full value on every process."""
    if jax.process_count() == 1:
        return np.asarray(x)
    from jax.experimental import multihost_utils
    return np.asarray(multihost_utils.process_allgather(x, tiled=True))


def barrier(name: str, timeout_s: int = 3600) -> None:
    """Wait for every process (jax.distributed's coordination service, no device collective). The first gather
    creates the CPU backend's gloo context, which gives up after 30 s; processes that finish compiling at different
    times meet here first."""
    if jax.process_count() == 1:
        return
    try:
        from jax._src import distributed
        distributed.global_state.client.wait_at_barrier(name, timeout_in_ms=timeout_s * 1000)
    except (ImportError, AttributeError):   # private API moved: a device-level barrier instead
        from jax.experimental import multihost_utils
        multihost_utils.sync_global_devices(name)


def every_process(flag: bool, name: str) -> bool:
    """flag and-ed over processes, so that every host takes the same decision (each sees only its own devices)."""
    if jax.process_count() == 1:
        return flag
    barrier(name)
    from jax.experimental import multihost_utils
    return bool(np.asarray(multihost_utils.process_allgather(np.int32(flag))).min())


def auto_ray_chunk(height: int, width: int, local_batch: int, budget: int = 1 << 22) -> int:
    """Rays per renderer chunk so that local_batch x chunk stays under `budget` rays in flight (0 = no chunking)."""
    rays = height * width
    target = max(1, budget // max(local_batch, 1))
    if target >= rays:
        return 0
    return max(d for d in range(1, target + 1) if rays % d == 0)


def balanced_batch(n_episodes: int, cap: int, n_dev: int) -> int:
    """The batch that covers n_episodes in the fewest batches of at most `cap` (>= n_dev), evened out and rounded up
    to a multiple of the device count: 2000 episodes under a cap of 1024 -> 2 batches of 1000, not 1024 + 976."""
    cap = max(n_dev, cap // n_dev * n_dev)
    per = math.ceil(n_episodes / math.ceil(n_episodes / cap))
    return math.ceil(per / n_dev) * n_dev


def free_device_bytes(device) -> int | None:
    """Bytes the allocator can still hand out on `device` (GPU: its limit minus what is in use; CPU: the host's
    available memory; None if unknown)."""
    stats = device.memory_stats() if hasattr(device, "memory_stats") else None
    if stats and "bytes_limit" in stats:
        return int(stats["bytes_limit"] - stats.get("bytes_in_use", 0))
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def program_bytes(compiled) -> int | None:
    """Per-device memory a compiled segment needs beyond its (already resident) arguments: scratch plus outputs
    that do not reuse a donated input."""
    m = compiled.memory_analysis()
    if m is None:
        return None
    return int(m.temp_size_in_bytes + max(m.output_size_in_bytes - m.alias_size_in_bytes, 0))


def episode_plan(names: tuple[str, ...], episodes_per_task: int, num_init: int) -> tuple[np.ndarray, np.ndarray]:
    """(task index, initial-state index) per episode, init-major so batches mix tasks."""
    e = np.arange(len(names) * episodes_per_task)
    return (e % len(names)).astype(np.int32), ((e // len(names)) % num_init).astype(np.int32)


def collectives(hlo: str) -> int:
    """Cross-device collectives in an optimized HLO module's text. A segment's environments are independent, yet
    the partitioner keeps small ones: MJX's solver loop and-reduces its stop flag (one on two H200s; on the CPU a
    collision top_k also gathers its scores)."""
    return len(re.findall(r" (?:all-gather|all-reduce|all-to-all|collective-permute|reduce-scatter)(?:-start)?\(",
                          hlo))
