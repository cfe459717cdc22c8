"""Finding and reading the source tensors of a PyTorch π0 / π0.5 checkpoint, lazily, one tensor at a time.

A source is `model.safetensors`, a sharded `model.safetensors.index.json`, or (only with `allow_pickle`) a torch
pickle `.pt` / `.pth` / `.bin`. Keys are normalised by stripping LeRobot's optional leading `model.`; the headers
(shape, dtype) are read up front so that every key and shape can be checked before any tensor is loaded.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import math
from pathlib import Path

import ml_dtypes
import numpy as np

from converters.errors import ConversionError, listing

log = logging.getLogger(__name__)

SAFETENSORS_FILE = "model.safetensors"
SAFETENSORS_INDEX = "model.safetensors.index.json"
PICKLE_SUFFIXES = (".pt", ".pth", ".bin")
# LeRobot's policy wrapper registers the network as `self.model`, so its files prefix every key with this.
LEROBOT_PREFIX = "model."
# safetensors stores little-endian data; bf16 comes from ml_dtypes (numpy has none).
NUMPY_DTYPES = {"F64": np.dtype("<f8"), "F32": np.dtype("<f4"), "F16": np.dtype("<f2"),
                "BF16": np.dtype(ml_dtypes.bfloat16)}
FLOAT_DTYPES = tuple(NUMPY_DTYPES)


@dataclasses.dataclass(frozen=True)
class Entry:
    """One source tensor as its header describes it. `key` is normalised; `raw_key` is the name in `file`."""

    key: str
    raw_key: str
    file: Path
    shape: tuple[int, ...]
    dtype: str  # safetensors spelling: F32, BF16, ...


def locate(src: Path, allow_pickle: bool) -> tuple[list[Path], str]:
    """SRC (a directory or a file) -> (weight files, kind) with kind in {"safetensors", "pickle"}."""
    if not src.exists():
        raise ConversionError(f"source {str(src)!r} does not exist")
    if src.is_file():
        if src.name.endswith(".index.json"):
            return _shards(src), "safetensors"
        if src.suffix in PICKLE_SUFFIXES:
            return [_check_pickle(src, allow_pickle)], "pickle"
        return [src], "safetensors"
    single, index = src / SAFETENSORS_FILE, src / SAFETENSORS_INDEX
    if single.exists() and index.exists():
        raise ConversionError(f"{str(src)!r} holds both {SAFETENSORS_FILE} and {SAFETENSORS_INDEX}; "
                              f"pass the one to convert as SRC")
    if single.exists():
        return [single], "safetensors"
    if index.exists():
        return _shards(index), "safetensors"
    pickles = sorted(p for p in src.iterdir() if p.is_file() and p.suffix in PICKLE_SUFFIXES)
    if len(pickles) == 1:
        return [_check_pickle(pickles[0], allow_pickle)], "pickle"
    hint = ""
    if (src / "pretrained_model" / SAFETENSORS_FILE).exists():
        hint = f"; did you mean {str(src / 'pretrained_model')!r}?"
    if pickles:
        hint = f"; several pickle files ({listing(p.name for p in pickles)}): pass the one to convert as SRC"
    raise ConversionError(f"no {SAFETENSORS_FILE} or {SAFETENSORS_INDEX} in {str(src)!r}{hint}")


def _check_pickle(path: Path, allow_pickle: bool) -> Path:
    if not allow_pickle:
        raise ConversionError(
            f"{str(path)!r} is a torch pickle; loading pickles can run arbitrary code, so it is refused. "
            f"Convert it to safetensors, or pass --allow-pickle if you trust the file")
    return path


def _shards(index: Path) -> list[Path]:
    try:
        weight_map = json.loads(index.read_text())["weight_map"]
        files = sorted(set(weight_map.values()))
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as e:
        raise ConversionError(f"{str(index)!r} is not a safetensors index (no readable 'weight_map'): {e}") from e
    paths = [index.parent / f for f in files]
    missing = [str(p) for p in paths if not p.is_file()]
    if missing:
        raise ConversionError(f"shard(s) named in {str(index)!r} are missing: {listing(missing)}")
    return paths


class TensorSource(contextlib.AbstractContextManager):
    """All source tensors of one checkpoint, by normalised key. Headers are read (and validated) on construction;
    `get` reads one tensor. As a context manager it drops a loaded pickle on exit."""

    def __init__(self, src: Path, *, allow_pickle: bool = False):
        self.src = src
        self.files, self.kind = locate(src, allow_pickle)
        self._offsets: dict[Path, dict[str, int]] = {}  # safetensors: file -> raw key -> byte offset of its data
        self._pickled: dict[str, object] = {}  # pickle: raw key -> torch tensor
        self.entries: dict[str, Entry] = {}
        self.had_prefix = False
        if self.kind == "pickle":
            self._open_pickle(self.files[0])
        else:
            for f in self.files:
                self._open_safetensors(f)
            if len(self.files) > 1 or src.name.endswith(".index.json"):
                self._check_index()

    def __exit__(self, *exc):
        self._pickled.clear()
        return None

    # --- headers -----------------------------------------------------------------------------------------------
    def _add(self, raw_key: str, file: Path, shape, dtype: str):
        key = raw_key[len(LEROBOT_PREFIX):] if raw_key.startswith(LEROBOT_PREFIX) else raw_key
        self.had_prefix |= key != raw_key
        if key in self.entries:
            other = self.entries[key]
            raise ConversionError(f"key {key!r} appears twice: as {other.raw_key!r} in {str(other.file)!r} and as "
                                  f"{raw_key!r} in {str(file)!r}")
        if dtype not in FLOAT_DTYPES:
            raise ConversionError(f"tensor {raw_key!r} in {str(file)!r} has dtype {dtype}; weights must be one of "
                                  f"{', '.join(FLOAT_DTYPES)}")
        self.entries[key] = Entry(key, raw_key, file, tuple(int(d) for d in shape), dtype)

    def _open_safetensors(self, path: Path):
        from safetensors import SafetensorError, safe_open

        try:
            with safe_open(str(path), framework="numpy") as handle:
                listed = [(raw, handle.get_slice(raw)) for raw in handle.keys()]
                listed = [(raw, sl.get_shape(), sl.get_dtype()) for raw, sl in listed]
        except (SafetensorError, OSError) as e:
            raise ConversionError(f"cannot read {str(path)!r} as safetensors: {_describe(path, e)}") from e
        for raw, shape, dtype in listed:
            self._add(raw, path, shape, dtype)
        # safe_open has validated the header (offsets inside the file, no overlaps); read the offsets once more so
        # tensors can be memory-mapped: no transient copy, pages come from the OS cache and are reclaimable.
        with open(path, "rb") as f:
            n = int.from_bytes(f.read(8), "little")
            table = json.loads(f.read(n))
        self._offsets[path] = {k: (8 + n + v["data_offsets"][0]) for k, v in table.items() if k != "__metadata__"}

    def _check_index(self):
        index = self.src if self.src.is_file() else self.src / SAFETENSORS_INDEX
        weight_map = json.loads(index.read_text())["weight_map"]
        for e in self.entries.values():
            if weight_map.get(e.raw_key) != e.file.name:
                raise ConversionError(f"key {e.raw_key!r} is in shard {str(e.file)!r} but {str(index)!r} maps it "
                                      f"to {weight_map.get(e.raw_key)!r}")
        found = {e.raw_key for e in self.entries.values()}
        lost = set(weight_map) - found
        if lost:
            raise ConversionError(f"{str(index)!r} lists key(s) absent from their shard: "
                                  f"{listing(f'{k} ({weight_map[k]})' for k in lost)}")

    def _open_pickle(self, path: Path):
        try:
            import torch  # only here, only with --allow-pickle: the pi0_jax package never needs torch
        except ImportError as e:
            raise ConversionError(f"--allow-pickle needs torch to read {str(path)!r}, and torch is not installed; "
                                  f"convert the file to safetensors instead") from e
        try:
            try:
                obj = torch.load(str(path), map_location="cpu", weights_only=True, mmap=True)
            except RuntimeError:  # mmap needs the zip format; legacy pickles load without it
                obj = torch.load(str(path), map_location="cpu", weights_only=True)
        except Exception as e:  # noqa: BLE001 - torch raises many types for a bad file
            raise ConversionError(f"cannot load {str(path)!r} with torch.load(weights_only=True): {e}") from e
        for wrapper in ("state_dict", "model"):
            if isinstance(obj, dict) and isinstance(obj.get(wrapper), dict):
                obj = obj[wrapper]
        if not isinstance(obj, dict):
            raise ConversionError(f"{str(path)!r} holds a {type(obj).__name__}, not a state dict")
        names = {torch.float32: "F32", torch.bfloat16: "BF16", torch.float16: "F16", torch.float64: "F64"}
        for raw, t in obj.items():
            if not isinstance(t, torch.Tensor):
                raise ConversionError(f"{str(path)!r}: entry {raw!r} is a {type(t).__name__}, not a tensor")
            self._add(raw, path, t.shape, names.get(t.dtype, str(t.dtype)))
            self._pickled[raw] = t

    # --- data --------------------------------------------------------------------------------------------------
    def get(self, key: str) -> np.ndarray:
        """The tensor under normalised `key` as a read-only numpy array or memmap (bf16 via ml_dtypes), checked
        to be finite. Safetensors data is memory-mapped, so only what the caller keeps stays resident."""
        e = self.entries[key]
        if self.kind == "pickle":
            x = _torch_to_numpy(self._pickled[e.raw_key])
        elif math.prod(e.shape) == 0:
            x = np.empty(e.shape, NUMPY_DTYPES[e.dtype])
        else:
            try:
                x = np.memmap(e.file, NUMPY_DTYPES[e.dtype], mode="r", offset=self._offsets[e.file][e.raw_key],
                              shape=e.shape)
            except (OSError, ValueError) as err:
                raise ConversionError(f"cannot read tensor {e.raw_key!r} from {str(e.file)!r}: {err}") from err
        if tuple(x.shape) != e.shape:
            raise ConversionError(f"tensor {e.raw_key!r} in {str(e.file)!r}: header says {e.shape}, data {x.shape}")
        check_finite(x, e)
        return x


def check_finite(x: np.ndarray, e: Entry, rows: int = 4096):
    """Raise naming the tensor if it holds NaN or Inf. Checked in row blocks: no full-size bool temporary."""
    flat = x.reshape(x.shape[0], -1) if x.ndim > 1 else x.reshape(1, -1)
    for start in range(0, flat.shape[0], rows):
        block = flat[start:start + rows]
        if not np.isfinite(block).all():
            full = np.asarray(x)
            n_nan, n_inf = int(np.isnan(full).sum()), int(np.isinf(full).sum())
            first = tuple(int(i) for i in np.argwhere(~np.isfinite(full))[0])
            raise ConversionError(f"tensor {e.raw_key!r} in {str(e.file)!r} (shape {e.shape}) is not finite: "
                                  f"{n_nan} NaN, {n_inf} Inf, first at index {first}")


def _torch_to_numpy(t) -> np.ndarray:
    import torch

    t = t.detach().cpu().contiguous()
    if t.dtype == torch.bfloat16:  # numpy has no bf16: reinterpret the bits
        return t.view(torch.int16).numpy().view(ml_dtypes.bfloat16)
    return t.numpy()


def _describe(path: Path, err: Exception) -> str:
    """Turn safetensors' terse header errors into a diagnosis that names what is wrong with the file."""
    msg = str(err)
    try:
        with open(path, "rb") as f:
            head = f.read(8)
    except OSError:
        head = b""
    if head[:2] == b"PK" or head[:1] == b"\x80":
        return f"{msg}; the file looks like a torch pickle, not safetensors (rename it to .pt and see --allow-pickle)"
    if "incomplete metadata" in msg or "not fully covered" in msg:
        return f"{msg}; the file is truncated (its data ends before the header says it should)"
    if "header too" in msg or "invalid" in msg.lower() or "deserializ" in msg.lower():
        return f"{msg}; the file is not a safetensors file or is truncated inside its header"
    return msg
