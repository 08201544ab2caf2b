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


def _grad_temp_mb(length):
    """XLA temporaries of the gradient of a final-carry loss through `length` steps."""
    xs = jnp.zeros((length, 1))

    def loss(c):
        final, _ = checkpointed_scan(_body, c, xs, length, collect=False)
        return jnp.sum(final**2)

    compiled = jax.jit(jax.grad(loss)).lower(jnp.ones(4096)).compile()
    return compiled.memory_analysis().temp_size_in_bytes / 2**20


def test_gradient_memory_grows_sublinearly():
    small, large = _grad_temp_mb(100), _grad_temp_mb(1600)  # 16x the steps
    # sqrt growth: about 4x at most; one stored carry per step would be 16x (0.03 MB per carry)
    assert large < 4.0 * small and large < 0.25 * 1600 * 4096 * 8 / 2**20, (small, large)


def test_advance_is_the_last_frame_of_rollout():
    net = physics.grid_net(4, 4, (0.3, 0.3), pinned="top_row")
    sim = physics.make_sim(1 / 60, num_substeps=2)
    s0, mat = physics.rest_state(net), physics.make_material()
    frames = NESTED_FRAMES + 6
    last = physics.advance(net, sim, mat, s0, num_frames=frames)
    traj = physics.rollout(net, sim, mat, s0, num_frames=frames)
    np.testing.assert_array_equal(last.x, traj.x[-1])
    np.testing.assert_array_equal(last.v, traj.v[-1])
