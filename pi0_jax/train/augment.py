"""Training-time image augmentation (spec §5.1; openpi `preprocess_observation(train=True)` with augmax), in JAX.

openpi, per image, on [0, 1] pixels:
  non-wrist cameras: RandomCrop(95 % of each side) -> Resize back -> Rotate(uniform ±5°)
  every camera:      ColorJitter(brightness=0.3, contrast=0.4, saturation=0.5)
The crop, resize and rotation compose into one affine map from output to source pixel coordinates, sampled once
(bilinear, `jax.scipy.ndimage.map_coordinates`; outside the source is black, as a rotation's corners). Every random
draw is per image; all functions are batched over the leading axis.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

CROP = 0.95
MAX_ROTATE_DEG = 5.0
BRIGHTNESS, CONTRAST, SATURATION = 0.3, 0.4, 0.5
_LUMA = jnp.array([0.299, 0.587, 0.114])


def crop_resize_rotate(rng: jax.Array, image: jax.Array) -> jax.Array:
    """One (H, W, C) image in [0, 1]: a random 95 % crop resized back to (H, W), then rotated about its centre."""
    h, w = image.shape[:2]
    k_crop, k_rot = jax.random.split(rng)
    # top-left corner of the crop window (in source pixels), uniform over the valid range
    off = jax.random.uniform(k_crop, (2,)) * jnp.array([h * (1 - CROP), w * (1 - CROP)])
    theta = jnp.deg2rad(jax.random.uniform(k_rot, (), minval=-MAX_ROTATE_DEG, maxval=MAX_ROTATE_DEG))
    # output pixel centre p -> rotate back about the centre -> resized-image coords q -> source = off + q * CROP
    ys, xs = jnp.meshgrid(jnp.arange(h) + 0.5, jnp.arange(w) + 0.5, indexing="ij")
    cy, cx = h / 2, w / 2
    c, s = jnp.cos(theta), jnp.sin(theta)
    qy = c * (ys - cy) - s * (xs - cx) + cy
    qx = s * (ys - cy) + c * (xs - cx) + cx
    sy, sx = off[0] + qy * CROP - 0.5, off[1] + qx * CROP - 0.5       # back to index coordinates
    sample = lambda ch: jax.scipy.ndimage.map_coordinates(ch, [sy, sx], order=1, mode="constant", cval=0.0)
    return jax.vmap(sample, in_axes=2, out_axes=2)(image)


def color_jitter(rng: jax.Array, image: jax.Array) -> jax.Array:
    """One (H, W, 3) image in [0, 1]: brightness, contrast and saturation factors uniform in 1 ± their strength."""
    kb, kc, ks = jax.random.split(rng, 3)
    factor = lambda k, a: jax.random.uniform(k, (), minval=1 - a, maxval=1 + a)
    image = jnp.clip(image * factor(kb, BRIGHTNESS), 0, 1)
    gray_mean = jnp.mean(image @ _LUMA)
    image = jnp.clip((image - gray_mean) * factor(kc, CONTRAST) + gray_mean, 0, 1)
    gray = (image @ _LUMA)[..., None]
    return jnp.clip((image - gray) * factor(ks, SATURATION) + gray, 0, 1)


def augment(rng: jax.Array, images: jax.Array, *, geometric: bool) -> jax.Array:
    """(B, H, W, 3) in [-1, 1] -> augmented, same shape and range. `geometric`: crop/resize/rotate too (the
    non-wrist cameras)."""
    keys = jax.random.split(rng, (2, images.shape[0]))
    x = images.astype(jnp.float32) / 2 + 0.5
    if geometric:
        x = jax.vmap(crop_resize_rotate)(keys[0], x)
    x = jax.vmap(color_jitter)(keys[1], x)
    return x * 2 - 1
