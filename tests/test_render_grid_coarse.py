"""`render.grid_coarse`: attributes on a coarse sub-grid, interpolated along the grid."""

import jax
import jax.numpy as jnp
import numpy as np

from diffcloth.render.grid_coarse import coarse_axis, on_coarse_grid


def test_coarse_axis_keeps_the_ends_and_interpolates_linearly():
    idx, w = coarse_axis(100, 16)
    assert idx[0] == 0 and idx[-1] == 99 and len(idx) <= 16
    np.testing.assert_allclose(w.sum(axis=1), 1.0)
    np.testing.assert_allclose(w @ idx.astype(float), np.arange(100.0), atol=1e-12)
    idx, w = coarse_axis(10, 16)  # already coarse: every line
    np.testing.assert_array_equal(idx, np.arange(10))


def test_on_coarse_grid_is_exact_for_bilinear_attributes_and_samples_fewer_vertices():
    R, C = 40, 25
    r, c = np.meshgrid(np.arange(R, dtype=float), np.arange(C, dtype=float), indexing="ij")
    pts = jnp.asarray(np.stack([r, c, r * c], -1).reshape(-1, 3))
    nrm = jnp.ones_like(pts)
    calls = []

    def fn(p, n):
        calls.append(p.shape[0])
        return jnp.stack([2.0 * p[:, 0] + 3.0 * p[:, 1], p[:, 2]], -1) + n[:, :2]

    out = on_coarse_grid(fn, pts, nrm, (R, C), 8)
    assert calls[-1] <= 8 * 8 < R * C  # evaluated on the sub-grid only
    np.testing.assert_allclose(out, fn(pts, nrm), atol=1e-9)  # bilinear: exact
    # no grid, or a grid that coarse already: every vertex
    np.testing.assert_allclose(on_coarse_grid(fn, pts, nrm, None, 8), fn(pts, nrm))
    assert calls[-1] == R * C
    g = jax.grad(lambda p: jnp.sum(on_coarse_grid(fn, p, nrm, (R, C), 8)[:, 0]))(pts)
    # each output vertex's unit cotangent reaches the sub-grid through interpolation weights
    # that sum to one: 2 per output vertex in all, carried by the sampled vertices only
    np.testing.assert_allclose(float(jnp.sum(g[:, 0])), 2.0 * R * C, rtol=1e-9)
    assert 0 < int(jnp.sum(g[:, 0] != 0)) <= 8 * 8
