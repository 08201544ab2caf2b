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


@pytest.mark.slow  # ~30 s loaded (two gradient compiles); the default FD tests take this path
def test_small_rollout_skips_frame_checkpoint_same_gradient(monkeypatch):
    """Small symplectic rollouts keep every substep's residuals (no frame checkpoint, no second
    forward pass): their material gradient equals the checkpointed rollout's (float64). The
    central-FD gradient tests (test_physics_gradients, 3 x 4 nets) run on this small path too."""
    import importlib

    from diffcloth.shapes import make_sphere

    ro = importlib.import_module("diffcloth.physics.rollout")
    with jax.enable_x64(True):
        net = physics.grid_net(3, 4, (0.3, 0.2), center=(0.0, 0.12, 0.0))
        sim = physics.make_sim(1 / 60, num_substeps=4)
        mat = physics.make_material(bend=2e-3, damping=5e-3, friction=0.4, drag_normal=0.8)
        s0 = physics.ClothState(net.rest, jnp.zeros_like(net.rest).at[..., 0].set(0.4))
        ball = physics.as_colliders(make_sphere((0.05, 0.0, 0.02), 0.1))

        def loss(m):
            traj = physics.rollout(net, sim, m, s0, num_frames=4, colliders=ball)
            return jnp.sum(traj.x**2 * jnp.arange(1.0, 5.0)[:, None, None, None])

        def grad_and_checkpoints():
            jaxpr = str(jax.make_jaxpr(jax.grad(loss))(mat))
            return jax.jit(jax.grad(loss))(mat), jaxpr.count("remat") + jaxpr.count("checkpoint")

        assert 3 * 4 * 4 * 4 <= ro.SMALL_ROLLOUT
        g_small, ck_small = grad_and_checkpoints()
        monkeypatch.setattr(ro, "SMALL_ROLLOUT", 0)
        g_ck, ck_ck = grad_and_checkpoints()
        assert ck_ck > ck_small  # the frame checkpoint is really gone on the small path
        for name in ("bend", "drag_normal", "stretch", "damping"):
            a, b = float(getattr(g_small, name)), float(getattr(g_ck, name))
            assert np.isfinite(b) and b != 0.0, name
            np.testing.assert_allclose(a, b, rtol=1e-7, err_msg=name)
