"""Gradients of every Material field through a rollout vs central finite differences (float64)."""

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcloth import physics
from diffcloth.physics.material import MATERIAL_FIELDS
from diffcloth.shapes import make_sphere

NET = physics.grid_net(3, 4, (0.3, 0.2), center=(0.0, 0.12, 0.0))
MAT = physics.make_material(
    stretch=40.0,
    shear=10.0,
    bend=2e-3,
    damping=5e-3,
    density=0.3,
    drag_normal=0.8,
    drag_tangent=0.2,
    friction=0.4,
)
BALL = physics.as_colliders(make_sphere((0.05, 0.0, 0.02), 0.1))
RNG = np.random.default_rng(1)
S0 = physics.ClothState(
    NET.rest + 0.005 * jnp.asarray(RNG.normal(size=NET.rest.shape)),
    jnp.zeros_like(NET.rest).at[..., 0].set(0.4),
)
TARGET = NET.rest + 0.05 * jnp.asarray(RNG.normal(size=NET.rest.shape))


def _sim(integrator):
    if integrator == "symplectic":
        return physics.make_sim(1 / 60, wind=(0.5, 0.0, 0.3), num_substeps=8)
    return physics.make_sim(
        1 / 60,
        wind=(0.5, 0.0, 0.3),
        num_substeps=2,
        integrator="implicit",
        newton_iters=6,
        cg_iters=200,
        cg_tol=1e-12,
    )


@functools.cache
def _loss_and_grad(integrator, num_frames):
    sim = _sim(integrator)

    def loss(m):
        traj = physics.rollout(NET, sim, m, S0, num_frames=num_frames, colliders=BALL)
        return jnp.sum((traj.x - TARGET[None]) ** 2) + 0.1 * jnp.sum(traj.v[-1] ** 2)

    # one compiled function serves both the gradient and the finite differences
    value_and_grad = jax.jit(jax.value_and_grad(loss))
    return (lambda m: value_and_grad(m)[0]), (lambda m: value_and_grad(m)[1])


def _check(integrator, num_frames):
    loss, grad = _loss_and_grad(integrator, num_frames)
    g = grad(MAT)
    # the cloth actually touches the ball, so friction matters
    for name in MATERIAL_FIELDS:
        value = float(getattr(MAT, name))
        eps = 1e-5 * value
        # strongly typed like MAT's fields (a weakly typed scalar would trigger a recompile)
        up = dataclasses.replace(MAT, **{name: jnp.asarray(value + eps, MAT.stretch.dtype)})
        dn = dataclasses.replace(MAT, **{name: jnp.asarray(value - eps, MAT.stretch.dtype)})
        fd = (float(loss(up)) - float(loss(dn))) / (2 * eps)
        ad = float(getattr(g, name))
        assert np.isfinite(ad) and ad != 0.0, name
        np.testing.assert_allclose(ad, fd, rtol=2e-4, atol=1e-9 * abs(fd) + 1e-12, err_msg=name)


@pytest.mark.parametrize(
    "integrator",
    ["symplectic", pytest.param("implicit", marks=[pytest.mark.slow, pytest.mark.gate])],
)
def test_material_gradients_short_rollout(integrator):
    _check(integrator, 6)


@pytest.mark.slow
@pytest.mark.gate  # the gating slow tier (.ci/run)
@pytest.mark.parametrize("integrator", ["symplectic", "implicit"])
def test_material_gradients_30_frames(integrator):
    _check(integrator, 30)
