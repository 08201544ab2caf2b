"""Two-level checkpointed scans: same values and gradients as lax.scan, sublinear gradient memory."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcloth import physics
from diffcloth.physics.rollout import NESTED_FRAMES, checkpointed_scan


def _body(c, x):
    c = jnp.tanh(1.3 * c + x) * jnp.cos(c)
    return c, c**2


@pytest.mark.parametrize("length", [NESTED_FRAMES, 70, 100])  # plain; blocks + rest; blocks only
def test_checkpointed_scan_matches_lax_scan(length):
    xs = jnp.sin(jnp.arange(length, dtype=jnp.float64))[:, None] * jnp.ones((1, 3))
    c0 = jnp.array([0.1, -0.2, 0.3])

    def loss(c, scan):
        final, ys = scan(c)
        return jnp.sum(final**2) + jnp.sum(ys * jnp.arange(length)[:, None])

    ref = lambda c: jax.lax.scan(_body, c, xs)
    ours = lambda c: checkpointed_scan(_body, c, xs, length)
    np.testing.assert_allclose(ours(c0)[1], ref(c0)[1], rtol=1e-14)
    g_ref = jax.grad(loss)(c0, ref)
    g = jax.grad(loss)(c0, ours)
    assert np.all(np.abs(g_ref) > 0)
    np.testing.assert_allclose(g, g_ref, rtol=1e-12)
    final, ys = checkpointed_scan(_body, c0, xs, length, collect=False)
    assert ys is None
    np.testing.assert_allclose(final, ref(c0)[0], rtol=1e-14)


def _grad_temp_mb(frames):
    net = physics.grid_net(4, 4, (0.3, 0.3), pinned="top_row")
    sim = physics.make_sim(1 / 60, num_substeps=2)
    s0 = physics.rest_state(net)

    def loss(m):
        return jnp.sum(physics.advance(net, sim, m, s0, num_frames=frames).x ** 2)

    compiled = jax.jit(jax.grad(loss)).lower(physics.make_material()).compile()
    return compiled.memory_analysis().temp_size_in_bytes / 2**20


def test_gradient_memory_grows_sublinearly():
    small, large = _grad_temp_mb(100), _grad_temp_mb(1600)  # 16x the frames
    assert large < 4.0 * small, (small, large)  # sqrt growth: about 4x at most; linear would be 16x
