"""Image losses and target validation (ROBUSTNESS rows 26 and 27)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from diffcloth.fit.losses import (
    blur,
    gaussian_pyramid,
    image_loss,
    pyramid_loss,
    validate_targets,
)

KINDS = ["l2", "l1", "charbonnier"]


def _images(key=0, shape=(2, 16, 16, 3)):
    k1, k2 = jax.random.split(jax.random.PRNGKey(key))
    return jax.random.uniform(k1, shape), jax.random.uniform(k2, shape)


def test_known_values():
    a = jnp.zeros((2, 4, 4, 3))
    b = jnp.full((2, 4, 4, 3), 0.5)
    np.testing.assert_allclose(image_loss(a, b, kind="l2"), [0.25, 0.25])
    np.testing.assert_allclose(image_loss(a, b, kind="l1"), [0.5, 0.5])
    mask = jnp.zeros((4, 4)).at[:2].set(1.0)
    b2 = b.at[:, 2:].set(0.0)  # differences only where the mask is 0 ... and 0.5 where it is 1
    np.testing.assert_allclose(image_loss(a, b2, kind="l2", mask=mask), [0.25, 0.25])
    np.testing.assert_allclose(image_loss(a, b2, kind="l2"), [0.125, 0.125])


def test_shapes_and_dtype():
    a, b = _images(shape=(3, 8, 8, 3))
    a32, b32 = a.astype(jnp.float32), b.astype(jnp.float32)
    for fn in (image_loss, pyramid_loss):
        out = jax.jit(fn)(a32, b32)
        assert out.shape == (3,) and out.dtype == jnp.float32
    assert image_loss(a[0], b[0]).shape == ()


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("which", ["image", "pyramid", "masked"])
def test_equal_images_give_exact_zero_loss_and_grad(kind, which):
    img, _ = _images()
    mask = jnp.ones(img.shape[:-1]).at[:, :4].set(0.0)

    def loss(p):
        if which == "image":
            return jnp.sum(image_loss(p, img, kind=kind))
        if which == "pyramid":
            return jnp.sum(pyramid_loss(p, img, kind=kind, num_levels=3))
        return jnp.sum(image_loss(p, img, kind=kind, mask=mask))

    value, grad = jax.jit(jax.value_and_grad(loss))(img)
    assert float(value) == 0.0
    assert bool(jnp.all(grad == 0.0))


@pytest.mark.parametrize("kind", KINDS)
def test_gradients_match_finite_differences(kind):
    a, b = _images(shape=(1, 8, 8, 2))
    mask = jnp.linspace(0.0, 1.0, 64).reshape(1, 8, 8)
    f1 = jax.jit(lambda p: jnp.sum(image_loss(p, b, kind=kind, mask=mask)))
    f2 = jax.jit(lambda p: jnp.sum(pyramid_loss(p, b, kind=kind, num_levels=3)))
    check_grads(f1, (a,), order=1, modes=("rev",))
    check_grads(f2, (a,), order=1, modes=("rev",))
    g = jax.grad(f2)(a)
    assert float(jnp.abs(g).max()) > 0


def test_zero_mask_gives_zero_not_nan():
    a, b = _images()
    mask = jnp.zeros(a.shape[:-1])
    val, g = jax.jit(jax.value_and_grad(lambda p: jnp.sum(image_loss(p, b, mask=mask))))(a)
    assert float(val) == 0.0 and bool(jnp.all(jnp.isfinite(g)))


def test_blur_and_pyramid():
    x = jnp.zeros((1, 9, 9, 1)).at[0, 4, 4, 0].set(1.0)
    y = jax.jit(blur)(x)
    np.testing.assert_allclose(float(y.sum()), 1.0, rtol=1e-12)  # mass preserved away from edges
    np.testing.assert_allclose(float(y[0, 4, 4, 0]), (6 / 16) ** 2)
    const = jnp.full((2, 8, 8, 3), 0.3)
    np.testing.assert_allclose(jax.jit(blur)(const), const, rtol=1e-12)
    levels = jax.jit(gaussian_pyramid, static_argnums=1)(jnp.zeros((2, 32, 32, 3)), 4)
    assert [lv.shape[1:3] for lv in levels] == [(32, 32), (16, 16), (8, 8), (4, 4)]
    assert len(jax.eval_shape(lambda x: gaussian_pyramid(x, 10), jnp.zeros((5, 5, 1)))) == 2


def _blob(center, size=32):
    x = jnp.arange(size, dtype=jnp.result_type(float))
    img = jnp.exp(-0.5 * ((x[None, :] - center) / 1.5) ** 2) * jnp.ones((size, 1))
    return img[:, :, None]


def test_pyramid_widens_the_basin():
    # A narrow blob 12 px away from the target: the plain pixel loss gives an almost-zero gradient,
    # the pyramid loss a clear one pointing the right way.
    target = _blob(8.0)

    def plain(c):
        return image_loss(_blob(c), target)

    def pyr(c):
        return pyramid_loss(_blob(c), target, num_levels=4)

    gp, gy = jax.jit(jax.grad(plain))(20.0), jax.jit(jax.grad(pyr))(20.0)
    assert float(gy) > 0  # pushes the centre towards 8
    assert abs(float(gy)) > 100 * abs(float(gp))


def test_validate_targets_converts_uint8():
    u8 = np.array([[[[0, 51, 255]]]], dtype=np.uint8)
    out = validate_targets(u8, (1, 1, 1, 3))
    assert out.dtype == np.float32
    np.testing.assert_allclose(out.ravel(), [0.0, 0.2, 1.0], rtol=1e-6)
    out16 = validate_targets(np.full((1, 2, 2, 3), 65535, np.uint16), (None, 2, 2, 3))
    assert float(out16.min()) == 1.0
    f64 = validate_targets(np.zeros((2, 2, 3)), (2, 2, 3))
    assert f64.dtype == np.float64


def test_validate_targets_errors():
    good = np.zeros((4, 8, 8, 3), np.float32)
    with pytest.raises(ValueError, match=r"shape \(4, 8, 8, 4\).*\(4, 8, 8, 3\).*4 channels"):
        validate_targets(np.zeros((4, 8, 8, 4)), (4, 8, 8, 3))
    with pytest.raises(ValueError, match=r"\(3, 8, 8, 3\).*3 frames instead of 4"):
        validate_targets(good[:3], (4, 8, 8, 3))
    with pytest.raises(ValueError, match=r"axis 1 has size 8 instead of 16"):
        validate_targets(good, (4, 16, 8, 3))
    with pytest.raises(ValueError, match=r"3 axes.*4 axes"):
        validate_targets(good[0], (4, 8, 8, 3))
    bad = good.copy()
    bad[2, 3, 4, 1] = np.nan
    with pytest.raises(ValueError, match=r"1 NaN or inf.*\(2, 3, 4, 1\)"):
        validate_targets(bad, (4, 8, 8, 3))
    with pytest.raises(ValueError, match="divide 0..255"):
        validate_targets(good + 200.0, (4, 8, 8, 3))
    with pytest.raises(ValueError, match="dtype int64"):
        validate_targets(good.astype(np.int64), (4, 8, 8, 3))
    assert validate_targets(good, (None, 8, 8, 3)).shape == (4, 8, 8, 3)


def test_bad_arguments():
    a, b = _images()
    with pytest.raises(ValueError, match="kind"):
        image_loss(a, b, kind="l3")
    with pytest.raises(ValueError, match="target shape"):
        image_loss(a, b[:1])
    with pytest.raises(ValueError, match="num_levels"):
        pyramid_loss(a, b, num_levels=0)
    with pytest.raises(ValueError, match="mask shape"):
        image_loss(a, b, mask=jnp.ones((3, 3)))
