import jax.numpy as jnp
import numpy as np
import pytest

from pi0_jax.preprocess import resize_with_pad as _resize, to_hwc, to_signed_float

RNG = np.random.default_rng(0)


def preprocess_image(image, *, float_range=(0.0, 1.0)):
    """The host checks and the device resize, as the policy pipeline chains them."""
    image = to_hwc(image)
    image = image if image.ndim == 4 else image[None]
    return np.asarray(_resize(jnp.asarray(to_signed_float(image, float_range)), 224, 224))


def resize_with_pad(images, height, width, **kw):
    return np.asarray(_resize(jnp.asarray(images), height, width, **kw))


def bilinear_ref(img, out_h, out_w):
    """Half-pixel-centre bilinear with edge clamping (what jax.image.resize 'linear' does when upsampling)."""
    def axis_weights(n_in, n_out):
        src = np.clip((np.arange(n_out) + 0.5) * n_in / n_out - 0.5, 0, n_in - 1)
        lo = np.floor(src).astype(int)
        hi = np.minimum(lo + 1, n_in - 1)
        w = src - lo
        m = np.zeros((n_out, n_in))
        m[np.arange(n_out), lo] += 1 - w
        m[np.arange(n_out), hi] += w
        return m
    wh, ww = axis_weights(img.shape[0], out_h), axis_weights(img.shape[1], out_w)
    return np.einsum("oh,hwc,pw->opc", wh, img.astype(np.float64), ww)


def test_uint8_range():
    img = RNG.integers(0, 256, (224, 224, 3), dtype=np.uint8)
    out = preprocess_image(img)
    assert out.shape == (1, 224, 224, 3) and out.dtype == np.float32
    np.testing.assert_allclose(out[0], img / 255.0 * 2 - 1, atol=1e-6)
    assert to_signed_float(np.array([0, 255], np.uint8)).tolist() == [-1.0, 1.0]


def test_float_ranges():
    img = RNG.uniform(0, 1, (224, 224, 3)).astype(np.float32)
    np.testing.assert_allclose(preprocess_image(img)[0], img * 2 - 1, atol=1e-6)
    np.testing.assert_allclose(preprocess_image(img * 2 - 1, float_range=(-1, 1))[0], img * 2 - 1, atol=1e-6)
    np.testing.assert_allclose(to_signed_float(np.array([0.0, 127.5, 255.0]), float_range=(0, 255)), [-1, 0, 1])
    with pytest.raises(ValueError, match="outside the declared range"):
        preprocess_image(img * 255)  # a float frame in [0, 255] is a bug, not something to clip
    with pytest.raises(TypeError):
        to_signed_float(np.zeros((2, 2, 3), np.int32))


def test_layouts():
    hwc = RNG.integers(0, 256, (2, 224, 224, 3), dtype=np.uint8)
    chw = np.ascontiguousarray(hwc.transpose(0, 3, 1, 2))
    ref = preprocess_image(hwc)
    assert ref.shape == (2, 224, 224, 3)
    np.testing.assert_array_equal(preprocess_image(chw), ref)
    np.testing.assert_array_equal(preprocess_image(chw[0]), ref[:1])
    # (3, H, 3) fits both; HWC wins unless told otherwise.
    amb = RNG.integers(0, 256, (3, 5, 3), dtype=np.uint8)
    assert to_hwc(amb).shape == (3, 5, 3)
    np.testing.assert_array_equal(to_hwc(amb, "chw"), amb.transpose(1, 2, 0))
    with pytest.raises(ValueError, match="3-channel"):
        to_hwc(np.zeros((10, 10, 4)))
    with pytest.raises(ValueError, match="3-D"):
        to_hwc(np.zeros((10, 10)))


def test_resize_upsample_matches_bilinear():
    img = RNG.uniform(-1, 1, (4, 6, 3)).astype(np.float32)
    out = resize_with_pad(img[None], 224, 224)[0]
    # ratio = 6/224: content 149 x 224, padded (37, 38) rows of -1 above and below.
    new_h = int(4 / (6 / 224))
    assert new_h == 149
    top = (224 - new_h) // 2
    assert (out[:top] == -1).all() and (out[top + new_h:] == -1).all()
    np.testing.assert_allclose(out[top: top + new_h], bilinear_ref(img, new_h, 224), atol=1e-5)


def test_resize_no_op_and_odd_padding():
    img = RNG.uniform(-1, 1, (1, 224, 223, 3)).astype(np.float32)
    out = resize_with_pad(img, 224, 224)
    np.testing.assert_allclose(out[:, :, :223], img, atol=1e-6)
    assert (out[:, :, 223] == -1).all()  # the odd pixel of padding goes right
    same = RNG.uniform(-1, 1, (1, 224, 224, 3)).astype(np.float32)
    np.testing.assert_array_equal(resize_with_pad(same, 224, 224), same)


def test_resize_downsample():
    # LIBERO renders 256x256; a constant frame stays constant, a checkerboard is smoothed (antialiasing).
    const = np.full((1, 256, 256, 3), 0.25, np.float32)
    np.testing.assert_allclose(resize_with_pad(const, 224, 224), 0.25, atol=1e-6)
    board = np.where((np.arange(256)[:, None] + np.arange(256)) % 2, 1.0, -1.0).astype(np.float32)
    board = np.repeat(board[None, :, :, None], 3, -1)
    assert np.abs(resize_with_pad(board, 224, 224)).max() < 0.5  # about 0.44
    assert np.abs(resize_with_pad(board, 224, 224, antialias=False)).max() > 0.7  # about 0.73
    # non-square uint8 frame through the full path: black bars, values in range
    out = preprocess_image(RNG.integers(0, 256, (240, 320, 3), dtype=np.uint8))
    assert out.shape == (1, 224, 224, 3) and out.min() >= -1 and out.max() <= 1
    assert (out[:, :28] == -1).all() and (out[:, 28 + 168:] == -1).all()
