"""The rasterizer's stream compaction (`raster.scan._compact`) against numpy."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcloth.render.raster.scan import _compact


@pytest.mark.parametrize(
    ("n", "size", "p"), [(1, 4, 0.5), (95, 16, 0.1), (1000, 64, 0.03), (200, 8, 0.5)]
)
def test_compact_matches_numpy(n, size, p):
    flags = np.random.default_rng(n).random(n) < p
    idx, real = jax.jit(_compact, static_argnums=1)(jnp.asarray(flags), size)
    want = np.nonzero(flags)[0][:size]
    k = len(want)
    assert np.asarray(real).tolist() == [True] * k + [False] * (size - k)
    np.testing.assert_array_equal(np.asarray(idx)[:k], want)
    np.testing.assert_array_equal(np.asarray(idx)[k:], 0)


def test_compact_vmap():
    flags = np.random.default_rng(3).random((3, 70)) < 0.2
    idx, real = jax.vmap(lambda f: _compact(f, 12))(jnp.asarray(flags))
    for row, i, r in zip(flags, np.asarray(idx), np.asarray(real), strict=True):
        want = np.nonzero(row)[0][:12]
        assert r.sum() == len(want)
        np.testing.assert_array_equal(i[: len(want)], want)
