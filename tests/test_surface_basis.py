"""Spline bases: partition of unity, closed forms, reproduction, continuity, affine invariance."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from diffcloth.surface import basis as B
from diffcloth.surface import tessellate

RNG = np.random.default_rng(0)


@pytest.mark.parametrize("basis,n", [("bspline", 6), ("bezier", 7), ("clamped", 7), ("bspline", 4)])
def test_partition_of_unity_and_derivatives_sum_to_zero(basis, n):
    t = np.linspace(0, B.num_patches(n, basis), 37)
    w = B.basis_matrix(n, t, basis)
    np.testing.assert_allclose(w.sum(1), 1.0, atol=1e-14)
    assert np.all(w >= -1e-15)
    for d in (1, 2):
        np.testing.assert_allclose(B.basis_matrix(n, t, basis, d).sum(1), 0.0, atol=1e-12)


@settings(max_examples=20, deadline=None)
@given(st.lists(st.floats(0.0, 1.0), min_size=1, max_size=8), st.sampled_from(B.BASES))
def test_partition_of_unity_property(ts, basis):
    n = 10
    t = np.asarray(ts) * B.num_patches(n, basis)
    np.testing.assert_allclose(B.basis_matrix(n, t, basis).sum(1), 1.0, atol=1e-13)


def test_uniform_bspline_matches_closed_form():
    s = np.linspace(0, 1, 11)
    ref = (
        np.stack([(1 - s) ** 3, 3 * s**3 - 6 * s**2 + 4, -3 * s**3 + 3 * s**2 + 3 * s + 1, s**3], 1)
        / 6
    )
    for k in range(3):  # every patch of a 6-point net uses points k..k+3
        w = B.patch_weights(6, k, s, "bspline")
        np.testing.assert_allclose(w[:, k : k + 4], ref, atol=1e-14)
        assert np.all(np.delete(w, np.s_[k : k + 4], axis=1) == 0)


def test_bezier_is_bernstein_and_interpolates_every_third_point():
    s = np.linspace(0, 1, 9)
    bern = np.stack([(1 - s) ** 3, 3 * s * (1 - s) ** 2, 3 * s**2 * (1 - s), s**3], 1)
    np.testing.assert_allclose(B.patch_weights(7, 1, s, "bezier")[:, 3:7], bern, atol=1e-14)
    w = B.basis_matrix(10, [0.0, 1.0, 2.0, 3.0], "bezier")
    np.testing.assert_allclose(w, np.eye(10)[[0, 3, 6, 9]], atol=1e-14)


def test_bezier_and_clamped_surfaces_pass_through_net_corners():
    net = jnp.asarray(RNG.normal(size=(7, 4, 3)))
    for basis in ("bezier", "clamped"):
        s = _tess3(net, basis)
        vr, vc = s.grid_shape
        grid = s.positions.reshape(vr, vc, 3)
        for (i, j), (a, b) in zip(
            [(0, 0), (0, -1), (-1, 0), (-1, -1)], [(0, 0), (0, -1), (-1, 0), (-1, -1)], strict=True
        ):
            np.testing.assert_allclose(grid[i, j], net[a, b], atol=1e-12)


def test_uniform_bspline_does_not_interpolate():
    net = jnp.asarray(RNG.normal(size=(5, 5, 3)))
    s = _tess3(net)
    assert np.abs(np.asarray(s.positions[0]) - np.asarray(net[0, 0])).max() > 1e-3


def test_quadratic_reproduction_of_cubic_bspline():
    # Greville abscissae of the knots -3..n are g_i = i - 1; the blossom of x^2 gives g^2 - 1/3.
    rows, cols = 6, 7
    gx = np.arange(cols) - 1.0
    gy = np.arange(rows) - 1.0
    X, Y = np.meshgrid(gx, gy)
    c = [0.3, -0.7, 0.2, 0.5, -0.4, 0.9]
    z = c[0] + c[1] * X + c[2] * Y + c[3] * (X**2 - 1 / 3) + c[4] * X * Y + c[5] * (Y**2 - 1 / 3)
    net = jnp.asarray(np.stack([X, Y, z], -1))
    p = np.asarray(tessellate(net, 4).positions)
    x, y = p[:, 0], p[:, 1]
    q = c[0] + c[1] * x + c[2] * y + c[3] * x**2 + c[4] * x * y + c[5] * y**2
    np.testing.assert_allclose(p[:, 2], q, atol=1e-12)
    # x(t) = t exactly (linear precision): the grid is uniform over [0, patches].
    np.testing.assert_allclose(np.unique(np.round(x, 12)), np.linspace(0, cols - 3, (cols - 3) * 4))


@pytest.mark.parametrize(
    "basis,n,smooth", [("bspline", 8, 2), ("clamped", 8, 2), ("bezier", 10, 0)]
)
def test_continuity_across_seams_on_random_nets(basis, n, smooth):
    net = RNG.normal(size=(n, 3))
    for k in range(1, B.num_patches(n, basis)):
        for d in range(smooth + 1):
            left = B.patch_weights(n, k - 1, [1.0], basis, d) @ net
            right = B.patch_weights(n, k, [0.0], basis, d) @ net
            np.testing.assert_allclose(left, right, atol=1e-12)
        # one order higher is generically discontinuous (C2 -> C3 jump, C0 -> C1 jump)
        d = smooth + 1
        left = B.patch_weights(n, k - 1, [1.0], basis, d) @ net
        right = B.patch_weights(n, k, [0.0], basis, d) @ net
        assert np.abs(left - right).max() > 1e-6


@functools.partial(jax.jit, static_argnames="basis")
def _tess3(net, basis="bspline"):
    return tessellate(net, 3, basis)


def _positions(net, basis):
    return _tess3(net, basis).positions


@settings(max_examples=8, deadline=None)
@given(
    st.integers(0, 2**31 - 1),
    st.sampled_from(B.BASES),
)
def test_affine_invariance(seed, basis):
    rng = np.random.default_rng(seed)
    net = rng.normal(size=(7, 7, 3))
    a = rng.normal(size=(3, 3))
    b = rng.normal(size=3)
    lhs = _positions(jnp.asarray(net @ a.T + b), basis)
    rhs = np.asarray(_positions(jnp.asarray(net), basis)) @ a.T + b
    np.testing.assert_allclose(lhs, rhs, atol=1e-10)


def test_errors_name_the_minimum():
    with pytest.raises(ValueError, match="minimum 4"):
        B.check_num_points(3, "bspline")
    with pytest.raises(ValueError, match="3\\*m \\+ 1"):
        B.check_num_points(5, "bezier")
    with pytest.raises(ValueError, match="basis must be one of"):
        B.check_basis("nurbs")
    with pytest.raises(ValueError, match="patch must be in"):
        B.patch_weights(5, 2, [0.5])


def test_sampled_basis_is_cached_and_readonly():
    a = B.sampled_basis(13, 13, "bspline")
    assert B.sampled_basis(13, 13, "bspline") is a
    assert a[0].shape == (130, 13) and not a[0].flags.writeable
