"""The symplectic step's hand-written stencil VJP against JAX's derivative (float64), and
forward mode through `autodiff_forces`."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcloth import physics
from diffcloth.physics import forces as F

NET = physics.grid_net(5, 6, (0.4, 0.3), pinned="top_row")
MAT = physics.make_material(
    stretch=80.0,
    shear=20.0,
    bend=1e-2,
    damping=0.01,
    density=0.3,
    drag_normal=0.7,
    drag_tangent=0.1,
)


@pytest.mark.slow  # 13 s each; the reverse-mode FD tests of the material gradients use the hand VJP
@pytest.mark.parametrize("wind", [True, False])
def test_hand_vjp_matches_autodiff(wind):
    rng = np.random.default_rng(0)
    x = NET.rest + 0.03 * jnp.asarray(rng.normal(size=NET.rest.shape))
    x = x.at[1, 2].set(x[1, 3])  # one zero-length spring
    v = 0.5 * jnp.asarray(rng.normal(size=x.shape))
    w = jnp.array([0.3, -0.1, 0.5]) if wind else None
    g = jnp.asarray(rng.normal(size=(3, 5, 6)))
    mat = MAT
    xp, vp = F.to_planar(x), F.to_planar(v)

    def auto(m, x, v, w):
        return jnp.sum(g * F._forces_planar(NET, m, x, v, wind=w))

    def hand(m, x, v, w):
        return jnp.sum(g * F._stencil_forces(NET, m, x, v, w))

    argnums = (0, 1, 2, 3) if wind else (0, 1, 2)
    np.testing.assert_allclose(hand(mat, xp, vp, w), auto(mat, xp, vp, w), rtol=1e-12)
    ga = jax.grad(auto, argnums)(mat, xp, vp, w)
    gh = jax.grad(hand, argnums)(mat, xp, vp, w)
    assert "custom_vjp" in str(jax.make_jaxpr(hand)(mat, xp, vp, w))
    for a, b in zip(jax.tree.leaves(ga), jax.tree.leaves(gh), strict=True):
        np.testing.assert_allclose(b, a, rtol=1e-10, atol=1e-12 * (1 + float(jnp.abs(a).max())))
    assert float(jnp.abs(ga[1]).max()) > 1.0


@pytest.mark.slow  # keeps the default suite under 10 min; runs with -m slow
def test_forward_mode_through_autodiff_forces():
    sim = physics.make_sim(1 / 30, num_substeps=4)
    net = physics.grid_net(4, 5, (0.4, 0.3), pinned="top_row")
    s0 = physics.rest_state(net)
    m0 = physics.make_material()

    def f(st):
        m = dataclasses.replace(m0, stretch=st)
        return jnp.sum(physics.rollout(net, sim, m, s0, num_frames=3).x[-1] ** 2)

    st = jnp.asarray(50.0)
    with pytest.raises(TypeError, match="forward-mode"):
        jax.jvp(f, (st,), (jnp.ones_like(st),))
    with F.autodiff_forces():
        fwd = jax.jvp(f, (st,), (jnp.ones_like(st),))[1]
    rev = jax.grad(f)(st)
    assert abs(float(rev)) > 1e-6
    np.testing.assert_allclose(fwd, rev, rtol=1e-9)
