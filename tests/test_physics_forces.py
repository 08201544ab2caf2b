"""Force terms: energy consistency, slices vs gather reference, degenerate springs, invariance
(rows 1, 11)."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from diffcloth import physics
from diffcloth.physics import forces

NET = physics.grid_net(4, 5, (0.4, 0.3), center=(0.1, 0.5, -0.2))
MAT = physics.make_material(stretch=80.0, shear=20.0, bend=1e-2, damping=0.01, density=0.3)
RNG = np.random.default_rng(0)
X = NET.rest + 0.03 * jnp.asarray(RNG.normal(size=NET.rest.shape))
V = 0.5 * jnp.asarray(RNG.normal(size=NET.rest.shape))

internal = jax.jit(lambda m, x, v: physics.internal_forces(NET, m, x, v))
grad_energy = jax.jit(jax.grad(lambda x, m: physics.elastic_energy(NET, m, x)))


def test_internal_forces_are_minus_energy_gradient():
    f = internal(MAT, X, jnp.zeros_like(V))
    np.testing.assert_allclose(f, -grad_energy(X, MAT), rtol=1e-10, atol=1e-12)
    assert float(jnp.abs(f).max()) > 1e-3


def test_rest_state_has_no_internal_force():
    np.testing.assert_allclose(internal(MAT, NET.rest, jnp.zeros_like(V)), 0.0, atol=1e-12)


def test_slices_match_gather_scatter_reference():
    ref = jax.jit(forces.make_gather_forces(NET))
    np.testing.assert_allclose(internal(MAT, X, V), ref(MAT, X, V), rtol=1e-10, atol=1e-12)


def test_internal_forces_and_damping_conserve_momentum():
    f = internal(MAT, X, V)
    np.testing.assert_allclose(jnp.sum(f, axis=(0, 1)), 0.0, atol=1e-11)
    # torque too (springs are central forces; bending is translation- and rotation-invariant)
    torque = jnp.sum(jnp.cross(X, f), axis=(0, 1))
    np.testing.assert_allclose(torque, 0.0, atol=1e-2 * float(jnp.abs(f).max()))


def test_differential_matches_jvp_for_stretched_springs():
    # For stretched springs (no transverse clamp) and v = 0 the PSD differential is exact.
    x = NET.rest * 1.2
    dx = 1e-3 * jnp.asarray(RNG.normal(size=x.shape))
    m0 = dataclasses.replace(MAT, damping=jnp.asarray(0.0))
    f = lambda x: physics.internal_forces(NET, m0, x, jnp.zeros_like(x))
    _, jvp = jax.jit(lambda x, dx: jax.jvp(f, (x,), (dx,)))(x, dx)
    diff = jax.jit(lambda x, dx: forces.internal_force_differential(NET, m0, x, dx, 0.0 * dx))(
        x, dx
    )
    np.testing.assert_allclose(diff, jvp, rtol=1e-9, atol=1e-12)


def test_coincident_nodes_give_finite_force_and_gradient():
    """Row 1: a spring whose two nodes coincide: force along the +y fallback, finite gradients."""
    x = X.at[1, 2].set(X[1, 1])
    f = internal(MAT, x, V)
    assert bool(jnp.all(jnp.isfinite(f)))

    def loss(m, x):
        return jnp.sum(physics.internal_forces(NET, m, x, V) ** 2)

    gm, gx = jax.jit(jax.grad(loss, argnums=(0, 1)))(MAT, x)
    for leaf in jax.tree_util.tree_leaves(gm) + [gx]:
        assert bool(jnp.all(jnp.isfinite(leaf)))
    assert float(jnp.abs(gm.stretch)) > 0
    # the single degenerate spring on its own: fallback direction +y, magnitude k * rest
    d = jnp.zeros((3, 1))
    f1 = forces._pair_force(d, d, jnp.ones(1), jnp.full(1, 2.0), jnp.zeros(1))
    np.testing.assert_allclose(f1[:, 0], [0.0, -2.0, 0.0])


def test_drag_acts_against_relative_velocity_and_follows_area():
    m = physics.make_material(drag_normal=2.0, drag_tangent=0.5)
    net = physics.grid_net(3, 3, (1.0, 1.0))  # horizontal, normal +-y
    v = jnp.zeros_like(net.rest).at[..., 1].set(-1.0)
    f = physics.drag_forces(net, m, net.rest, v, jnp.zeros(3))
    np.testing.assert_allclose(f[..., 1], 2.0 * net.area, rtol=1e-12)
    # tangential motion against still air, and wind with a still cloth, are the same thing
    v_t = jnp.zeros_like(net.rest).at[..., 0].set(1.0)
    f_t = physics.drag_forces(net, m, net.rest, v_t, jnp.zeros(3))
    f_w = physics.drag_forces(net, m, net.rest, jnp.zeros_like(v_t), jnp.asarray([-1.0, 0, 0]))
    np.testing.assert_allclose(f_t[..., 0], -0.5 * net.area, rtol=1e-12)
    np.testing.assert_allclose(f_t, f_w, atol=1e-14)


def _rotation(axis, angle):
    axis = np.asarray(axis, float)
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


@settings(max_examples=25, deadline=None)
@given(
    axis=st.tuples(*[st.floats(-1, 1) for _ in range(3)]).filter(lambda a: np.linalg.norm(a) > 0.1),
    angle=st.floats(-np.pi, np.pi),
    shift=st.tuples(*[st.floats(-5, 5) for _ in range(3)]),
)
def test_internal_forces_invariant_under_rigid_motion(axis, angle, shift):
    """Row 11: f(R x + t, R v) = R f(x, v); rest stays force-free; forces sum to zero."""
    r = jnp.asarray(_rotation(axis, angle))
    t = jnp.asarray(shift)
    move = lambda a: jnp.einsum("ij,rcj->rci", r, a)
    f0 = internal(MAT, X, V)
    f1 = internal(MAT, move(X) + t[None, None, :], move(V))
    np.testing.assert_allclose(f1, move(f0), rtol=1e-8, atol=1e-9)
    np.testing.assert_allclose(jnp.sum(f1, axis=(0, 1)), 0.0, atol=1e-10)
    rest = move(NET.rest) + t[None, None, :]
    np.testing.assert_allclose(internal(MAT, rest, jnp.zeros_like(V)), 0.0, atol=1e-10)
