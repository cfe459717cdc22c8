"""openpi's msgpack-numpy wire format: encode replies, decode requests safely.

A frame is one msgpack value. numpy values travel as msgpack maps whose keys are byte strings (msgpack `bin`), so
they never collide with an observation's `str` keys:

    array  {b"__ndarray__": True, b"data": <raw bytes, C order>, b"dtype": dtype.str, b"shape": [d0, d1, ...]}
    scalar {b"__npgeneric__": True, b"data": <the scalar as a msgpack value>, b"dtype": dtype.str}

`dtype.str` is numpy's "<f4" / "|u1" / "<U12" form. This is what `openpi_client.msgpack_numpy` writes and reads,
so an unchanged openpi client talks to `pi0_jax.serve` (and this module talks to an openpi server).

Decoding trusts nothing in the frame. It refuses, with a `ProtocolError` that says why:
  - dtypes that are not bool, int, uint, float, str or bytes (object, void/structured, complex, datetime), and
    zero-size items (an "<U0" array of a billion elements in zero bytes);
  - shapes that are not a list of non-negative ints, more than `MAX_NDIM` axes, or any axis above `MAX_DIM`;
  - `data` whose length is not prod(shape) x itemsize (a truncated or padded image is never reinterpreted);
  - anything msgpack itself refuses (truncated frame, trailing bytes, nesting too deep, non-str/bytes map keys).
Decoded arrays are zero-copy, read-only views of the frame, converted to native byte order when sent big-endian.
"""

from __future__ import annotations

import math
from typing import Any

import msgpack
import numpy as np

ALLOWED_KINDS = "biufUS"           # bool, int, uint, float, unicode str, bytes
MAX_NDIM = 32                       # numpy allows 64; no observation or action has more than a handful of axes
MAX_DIM = 2**31                     # a single axis above this is a malformed (or hostile) header
MAX_DTYPE_LEN = 16                  # "<U2147483647" is 12 characters; longer strings are not numpy dtype codes
_ND, _NG = b"__ndarray__", b"__npgeneric__"
_DATA, _DTYPE, _SHAPE = b"data", b"dtype", b"shape"


class ProtocolError(ValueError):
    """A frame that is not valid msgpack-numpy, or carries a value the server refuses to decode."""


# ---------------------------------------------------------------------------------------------------------------------
def _check_dtype(dtype: np.dtype, what: str) -> None:
    if dtype.kind not in ALLOWED_KINDS:
        raise ProtocolError(f"{what}: dtype {dtype.str!r} (kind {dtype.kind!r}) is not allowed; "
                            "send bool, int, uint, float, str or bytes arrays")
    if dtype.itemsize == 0:
        raise ProtocolError(f"{what}: dtype {dtype.str!r} has zero-size items")


def _encode(obj: Any) -> Any:
    """msgpack's `default` hook: numpy (and anything with `__array__`, e.g. jax arrays) -> tagged maps."""
    if isinstance(obj, np.generic):
        _check_dtype(obj.dtype, "scalar")
        return {_NG: True, _DATA: obj.item(), _DTYPE: obj.dtype.str}
    if isinstance(obj, np.ndarray) or hasattr(obj, "__array__"):
        arr = np.asarray(obj)
        _check_dtype(arr.dtype, "array")
        return {_ND: True, _DATA: arr.tobytes(order="C"), _DTYPE: arr.dtype.str, _SHAPE: list(arr.shape)}
    raise TypeError(f"cannot encode {type(obj).__name__} in msgpack-numpy")


def packb(obj: Any) -> bytes:
    """Encode a (nested) dict / list of python values and numpy arrays / scalars as one msgpack frame."""
    return msgpack.packb(obj, default=_encode, use_bin_type=True)


# ---------------------------------------------------------------------------------------------------------------------
def _parse_dtype(raw: Any, what: str) -> np.dtype:
    if isinstance(raw, bytes):  # old encoders sent the dtype string as bytes
        raw = raw.decode("ascii", "replace")
    if not isinstance(raw, str) or not 0 < len(raw) <= MAX_DTYPE_LEN:
        raise ProtocolError(f"{what}: dtype must be a numpy dtype string like '<f4', got {raw!r:.40}")
    try:
        dtype = np.dtype(raw)
    except (TypeError, ValueError) as e:
        raise ProtocolError(f"{what}: unknown dtype {raw!r}") from e
    _check_dtype(dtype, what)
    return dtype


def _decode_array(obj: dict) -> np.ndarray:
    dtype = _parse_dtype(obj.get(_DTYPE), "array")
    shape = obj.get(_SHAPE)
    if not isinstance(shape, (list, tuple)) or len(shape) > MAX_NDIM:
        raise ProtocolError(f"array: shape must be a list of at most {MAX_NDIM} ints, got {shape!r:.80}")
    for d in shape:
        if isinstance(d, bool) or not isinstance(d, int) or not 0 <= d <= MAX_DIM:
            raise ProtocolError(f"array: shape {list(shape)!r:.80} has an axis that is not an int in [0, {MAX_DIM}]")
    data = obj.get(_DATA)
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise ProtocolError(f"array: data must be raw bytes, got {type(data).__name__}")
    want = math.prod(shape) * dtype.itemsize
    if len(data) != want:
        raise ProtocolError(f"array: shape {list(shape)} of {dtype.str!r} needs {want} bytes of data, "
                            f"the frame carries {len(data)}")
    arr = np.frombuffer(data, dtype=dtype).reshape(shape)
    if not dtype.isnative:
        arr = arr.astype(dtype.newbyteorder("="))
    return arr


def _decode_scalar(obj: dict) -> np.generic:
    dtype = _parse_dtype(obj.get(_DTYPE), "scalar")
    data = obj.get(_DATA)
    if not isinstance(data, (bool, int, float, str, bytes)):
        raise ProtocolError(f"scalar: data must be a msgpack bool/int/float/str/bytes, got {type(data).__name__}")
    try:
        return dtype.type(data)
    except (TypeError, ValueError, OverflowError) as e:
        raise ProtocolError(f"scalar: {data!r:.40} is not a valid {dtype.str!r}: {e}") from e


def _object_hook(obj: dict) -> Any:
    if obj.get(_ND) is True:
        return _decode_array(obj)
    if obj.get(_NG) is True:
        return _decode_scalar(obj)
    return obj


def unpackb(frame: bytes) -> Any:
    """Decode one msgpack-numpy frame (see the module docstring); any problem raises `ProtocolError`."""
    if not isinstance(frame, (bytes, bytearray, memoryview)):
        raise ProtocolError(f"expected a binary frame, got {type(frame).__name__}")
    try:
        return msgpack.unpackb(frame, object_hook=_object_hook, raw=False, strict_map_key=True)
    except ProtocolError:
        raise
    except Exception as e:  # msgpack's FormatError / StackError / ExtraData / UnicodeDecodeError / ValueError ...
        raise ProtocolError(f"not a valid msgpack frame ({type(e).__name__}: {e})") from e
