"""Camera frames for the policy: value range and layout checked on the host, resize-with-pad on device.

Value range (decided here, applied by `to_signed_float`):
* uint8 -> x / 255 * 2 - 1 (openpi's `Observation.from_dict`).
* floating -> assumed in [0, 1] (LeRobot's convention, and what openpi's `LiberoInputs` and the openpi client's
  `convert_to_uint8` assume), mapped affinely to [-1, 1]. Pass `float_range=(-1, 1)` for frames that are already
  model-ready, or any other (lo, hi). Floats clearly outside the declared range (by more than 1 %, e.g. a float
  image in [0, 255]) raise instead of being silently clipped. Other dtypes raise.

Layout (`to_hwc`): 3-D arrays are one frame, 4-D a batch. The channel axis is found by size:
* last axis 3 and axis -3 not 3 -> HWC;  axis -3 is 3 and last axis not 3 -> CHW (transposed);
* both 3 (a frame 3 pixels high/wide, e.g. (3, H, 3)) is ambiguous: HWC wins (openpi's native layout) unless
  `layout="chw"` is passed; neither 3 -> error. Only 3-channel RGB is accepted.

Resize (`resize_with_pad`): as openpi's JAX `image_tools.resize_with_pad` (what `preprocess_observation` uses):
aspect-preserving bilinear `jax.image.resize` (antialiased when downsampling) of the [-1, 1] float frame, clipped to
[-1, 1], centred on a -1 (black) canvas; the extra odd pixel of padding goes bottom / right. Frames already at the
target size are passed through untouched. openpi's *server* resizes uint8 frames with PIL instead and LeRobot uses
`F.interpolate` without antialiasing; the three agree exactly only when no resize is needed (LIBERO clients send
224x224 already).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np


def to_hwc(image, layout: str | None = None) -> np.ndarray:
    """(H, W, 3) / (3, H, W) / (B, H, W, 3) / (B, 3, H, W) -> channels-last with the same batching."""
    image = np.asarray(image)
    if image.ndim not in (3, 4):
        raise ValueError(f"an image must be 3-D (one frame) or 4-D (a batch), got shape {image.shape}")
    if layout is None:
        if image.shape[-1] == 3:
            layout = "hwc"
        elif image.shape[-3] == 3:
            layout = "chw"
        else:
            raise ValueError(f"cannot find a 3-channel axis in image shape {image.shape} (HWC or CHW expected)")
    layout = layout.lower()
    if layout == "chw":
        if image.shape[-3] != 3:
            raise ValueError(f"layout='chw' but axis -3 of {image.shape} is not 3")
        return np.moveaxis(image, -3, -1)
    if layout != "hwc":
        raise ValueError(f"layout must be 'hwc', 'chw' or None, got {layout!r}")
    if image.shape[-1] != 3:
        raise ValueError(f"layout='hwc' but the last axis of {image.shape} is not 3")
    return image


def to_signed_float(image, float_range: tuple[float, float] = (0.0, 1.0)) -> np.ndarray:
    """uint8 or float pixels -> float32 in [-1, 1] (see the module docstring for the rules)."""
    image = np.asarray(image)
    if image.dtype == np.uint8:
        return image.astype(np.float32) / 255.0 * 2.0 - 1.0
    if not np.issubdtype(image.dtype, np.floating):
        raise TypeError(f"image dtype must be uint8 or floating, got {image.dtype}")
    lo, hi = float(float_range[0]), float(float_range[1])
    if not hi > lo:
        raise ValueError(f"float_range must be (lo, hi) with hi > lo, got {float_range}")
    image = image.astype(np.float32)
    if image.size:
        tol = 0.01 * (hi - lo)
        vmin, vmax = float(image.min()), float(image.max())
        if vmin < lo - tol or vmax > hi + tol:
            raise ValueError(f"float image values span [{vmin:.3g}, {vmax:.3g}], outside the declared range "
                             f"{(lo, hi)}; pass float_range=... (or send uint8)")
    out = (image - lo) * (2.0 / (hi - lo)) - 1.0
    return np.clip(out, -1.0, 1.0)


@functools.partial(jax.jit, static_argnames=("height", "width", "antialias"))
def resize_with_pad(images: jax.Array, height: int, width: int, antialias: bool = True) -> jax.Array:
    """(B, H, W, C) float in [-1, 1] -> (B, height, width, C): aspect-preserving bilinear resize, -1 padding; frames
    already at the target size pass through untouched. Traceable (the policy pipeline calls it inside its program)."""
    b, cur_h, cur_w, c = images.shape
    if (cur_h, cur_w) == (height, width):
        return images
    ratio = max(cur_w / width, cur_h / height)
    new_h, new_w = int(cur_h / ratio), int(cur_w / ratio)
    resized = jax.image.resize(images, (b, new_h, new_w, c), method="linear", antialias=antialias)
    resized = jnp.clip(resized, -1.0, 1.0)
    top, left = (height - new_h) // 2, (width - new_w) // 2
    pad = ((0, 0), (top, height - new_h - top), (left, width - new_w - left), (0, 0))
    return jnp.pad(resized, pad, constant_values=-1.0)
