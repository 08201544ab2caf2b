"""Vertex deformation: waves and ripples in time, displacement along normals, recomputed frames."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcloth.surface import displace_along_normals, ripples, tessellate, waves


def flat_net():
    # the net spans x in [-1, 2], z in [-1, 2]; the B-spline surface covers [0, 1] x [0, 1]
    x, z = np.meshgrid(np.linspace(-1.0, 2.0, 4), np.linspace(-1.0, 2.0, 4))
    return jnp.asarray(np.stack([x, np.zeros_like(x), z], -1))


@functools.partial(jax.jit, static_argnames="level")
def wavy(net, time, amplitude, level=24):
    s = tessellate(net, level, flip=True)  # flip: normals along +y for this net
    h = waves(s.uv, time, amplitude=amplitude, wavelength=0.5, speed=0.25)
    return displace_along_normals(s, h)


def test_wave_height_and_recomputed_normals_on_a_flat_sheet():
    s = wavy(flat_net(), 0.3, 0.02)
    p = np.asarray(s.positions)
    x = p[:, 0]  # u == x on this sheet
    k = 2 * np.pi / 0.5
    np.testing.assert_allclose(p[:, 1], 0.02 * np.sin(k * (x - 0.25 * 0.3)), atol=1e-12)
    # exact normal of y = h(x): (-h'(x), 1, 0) normalised; the grid normal is a central difference
    dh = 0.02 * k * np.cos(k * (x - 0.075))
    exact = np.stack([-dh, np.ones_like(dh), np.zeros_like(dh)], 1)
    exact /= np.linalg.norm(exact, axis=1, keepdims=True)
    n = np.asarray(s.normals)
    assert np.sum(n * exact, 1).min() > 0.995
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.sum(n * np.asarray(s.tangents), 1), 0.0, atol=1e-12)


def test_wave_is_periodic_in_time_and_moves():
    a = wavy(flat_net(), 0.0, 0.02)
    b = wavy(flat_net(), 0.5 / 0.25, 0.02)  # one period later
    c = wavy(flat_net(), 0.5, 0.02)
    np.testing.assert_allclose(a.positions, b.positions, atol=1e-12)
    assert np.abs(np.asarray(a.positions - c.positions)).max() > 1e-3


def test_zero_amplitude_keeps_positions_and_normals_close_to_analytic():
    s0 = jax.jit(tessellate, static_argnums=1)(flat_net(), 24)
    s = wavy(flat_net(), 0.3, 0.0)
    np.testing.assert_allclose(s.positions, s0.positions, atol=1e-15)
    np.testing.assert_allclose(s.normals, -s0.normals, atol=1e-12)  # wavy() flips


def test_gradient_wrt_time_and_amplitude_is_finite_and_nonzero():
    @jax.jit
    def loss(t, a):
        s = wavy(flat_net(), t, a, level=4)
        return jnp.sum(s.positions[:, 1] ** 2) + jnp.sum(s.normals[:, 0])

    g = jax.jit(jax.grad(loss, argnums=(0, 1)))(0.3, 0.02)
    assert all(np.isfinite(v) and abs(float(v)) > 1e-6 for v in g)
    eps = 1e-6
    fd = (loss(0.3 + eps, 0.02) - loss(0.3 - eps, 0.02)) / (2 * eps)
    np.testing.assert_allclose(g[0], fd, rtol=1e-5)


def test_ripple_is_finite_with_finite_gradient_at_its_centre():
    pts = jnp.asarray([[0.5, 0.5], [0.7, 0.5], [0.5, 0.9]])

    @jax.jit
    def f(pts, t):
        return ripples(pts, t, amplitude=0.1, wavelength=0.2, speed=0.1, decay=1.0).sum()

    h = jax.jit(lambda p: ripples(p, 0.0, amplitude=0.1, wavelength=0.2, decay=1.0))(pts)
    np.testing.assert_allclose(h[0], 0.0)
    np.testing.assert_allclose(h[1], 0.1 * np.exp(-0.2) * np.sin(2 * np.pi), atol=1e-12)
    gp, gt = jax.jit(jax.grad(f, argnums=(0, 1)))(pts, 0.4)
    assert np.all(np.isfinite(gp)) and np.isfinite(gt) and abs(float(gt)) > 1e-6


def test_bad_arguments_raise():
    pts = jnp.zeros((3, 2))
    with pytest.raises(ValueError, match="wavelength"):
        waves(pts, 0.0, amplitude=1.0, wavelength=0.0)
    with pytest.raises(ValueError, match="wavelength"):
        ripples(pts, 0.0, amplitude=1.0, wavelength=-1.0)
    s = wavy(flat_net(), 0.0, 0.0, level=2)
    with pytest.raises(ValueError, match="height must have shape"):
        displace_along_normals(s, jnp.zeros(3))


def test_float32_strict_promotion():
    net = flat_net().astype(jnp.float32)
    with jax.numpy_dtype_promotion("strict"):
        s = jax.jit(lambda n: wavy.__wrapped__(n, 0.1, 0.02, level=2))(net)
        h = jax.jit(lambda p: ripples(p, 0.1, amplitude=0.1, wavelength=0.2))(s.uv)
    assert s.positions.dtype == s.normals.dtype == h.dtype == jnp.float32
