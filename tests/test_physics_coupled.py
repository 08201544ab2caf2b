"""Tests for diffcloth.physics.coupled: rigid bodies as moving colliders of the control net."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcloth import physics
from diffcloth.physics import coupled, rigid
from diffcloth.physics.forces import node_mass

FRAMES = 8
NET_FREE = physics.grid_net(5, 5, (0.4, 0.4), plane="xy", pinned="none")
NET_HANG = physics.grid_net(5, 5, (0.4, 0.4), plane="xy", pinned="top_row")
SIM0 = physics.make_sim(1 / 60, num_substeps=8, gravity=(0.0, 0.0, 0.0))
SIMG = physics.make_sim(1 / 60, num_substeps=8, gravity=(0.0, -9.81, 0.0))
MAT = physics.make_material(drag_normal=0.0, drag_tangent=0.0, friction=0.3)
BALL = rigid.make_body(
    "sphere", mass=0.05, radius=0.12, position=(0.02, -0.05, 0.17), velocity=(0.0, 0.0, -3.0)
)
BOX = rigid.make_body(
    "box", mass=0.05, half_extents=(0.1, 0.08, 0.06), position=(0.03, -0.05, 0.15),
    velocity=(0.0, 0.0, -3.0), orientation=(0.95, 0.1, 0.2, 0.0),
)  # fmt: skip


@jax.jit
def _free(ball, box):
    """Zero gravity, free cloth (no pins, no drag), two-way coupling."""
    state = physics.rest_state(NET_FREE)
    return coupled.coupled_rollout(NET_FREE, SIM0, MAT, state, (ball, box), num_frames=FRAMES)


def _momentum(net, cloth, bodies):
    m = node_mass(net, MAT)
    p = jnp.einsum("rc,trcj->tj", m, cloth.v)
    for b in bodies:
        p = p + b.mass[:, None] * b.velocity
    return p


@pytest.fixture(scope="module")
def free_run():
    # the box starts far away in the first run's x so only the ball touches the cloth, and the
    # ball far away in the second; both share one compiled function.
    away = jnp.asarray([5.0, 0.0, 0.0])
    ball_only = _free(BALL, dataclasses.replace(BOX, position=BOX.position + away))
    box_only = _free(dataclasses.replace(BALL, position=BALL.position + away), BOX)
    return ball_only, box_only


def test_two_way_conserves_momentum_and_slows_the_ball(free_run):
    (cloth, bodies), _ = free_run
    p = _momentum(NET_FREE, cloth, bodies)
    p0 = BALL.mass * BALL.velocity + BOX.mass * BOX.velocity
    np.testing.assert_allclose(p, np.tile(np.asarray(p0), (FRAMES, 1)), atol=1e-12)
    ball = bodies[0]
    assert float(ball.velocity[-1, 2]) > -2.9  # slowed down by the cloth
    assert float(jnp.max(jnp.abs(cloth.v[-1, ..., 2]))) > 0.3  # the cloth was pushed


def test_box_pushes_cloth_out_and_conserves_momentum(free_run):
    _, (cloth, bodies) = free_run
    p = _momentum(NET_FREE, cloth, bodies)
    p0 = BALL.mass * BALL.velocity + BOX.mass * BOX.velocity
    np.testing.assert_allclose(p, np.tile(np.asarray(p0), (FRAMES, 1)), atol=1e-12)
    box = bodies[1]
    assert float(box.velocity[-1, 2]) > -2.9
    # no control point inside the box at the end of any frame
    rot = jax.vmap(rigid.quat_to_matrix)(box.orientation)
    local = jnp.einsum("trcj,tjk->trck", cloth.x - box.position[:, None, None, :], rot)
    gaps = jnp.min(box.half_extents[:, None, None, :] - jnp.abs(local), axis=-1)
    assert float(jnp.max(gaps)) < 1e-9
    assert float(jnp.max(jnp.abs(cloth.v[-1, ..., 2]))) > 0.3


@jax.jit
def _hang(ball):
    state = physics.rest_state(NET_HANG)
    two = coupled.coupled_rollout(NET_HANG, SIMG, MAT, state, (ball,), num_frames=FRAMES)
    one = coupled.coupled_rollout(
        NET_HANG, SIMG, MAT, state, (ball,), num_frames=FRAMES, two_way=False
    )
    alone = rigid.rigid_rollout(coupled.rigid_settings(SIMG), (ball,), num_frames=FRAMES)
    return two, one, alone


def test_hanging_cloth_ball_no_point_inside_and_one_way_matches_rigid():
    (cloth, (ball,)), (cloth1, (ball1,)), (alone,) = _hang(BALL)
    for c, b in ((cloth, ball), (cloth1, ball1)):
        dist = jnp.linalg.norm(c.x - b.position[:, None, None, :], axis=-1)
        assert float(jnp.min(dist)) >= 0.12 - 1e-9
        assert np.all(np.isfinite(np.asarray(c.x)))
    # one-way: the ball does not feel the cloth and moves exactly as on its own
    np.testing.assert_allclose(ball1.position, alone.position, atol=1e-12)
    # two-way: the ball is slowed down compared with the one-way run, the cloth is pushed back
    assert float(ball.velocity[-1, 2]) > float(ball1.velocity[-1, 2]) + 0.05
    assert float(jnp.min(cloth.x[-1, ..., 2])) < -0.02


@pytest.mark.slow
@pytest.mark.gate  # the gating slow tier (.ci/run)
def test_gradient_of_ball_position_wrt_mass():
    state = physics.rest_state(NET_HANG)
    sim = physics.make_sim(1 / 60, num_substeps=4, gravity=(0.0, -9.81, 0.0))

    def final_z(mass):
        ball = dataclasses.replace(BALL, mass=mass)
        _, (b,) = coupled.coupled_rollout(NET_HANG, sim, MAT, state, (ball,), num_frames=4)
        return b.position[-1, 2] + 0.5 * b.position[-1, 1]

    f = jax.jit(final_z)
    g = float(jax.jit(jax.grad(final_z))(jnp.asarray(0.05)))
    eps = 1e-6
    fd = (float(f(jnp.asarray(0.05 + eps))) - float(f(jnp.asarray(0.05 - eps)))) / (2 * eps)
    assert abs(g) > 1e-3
    np.testing.assert_allclose(g, fd, rtol=1e-5)


def test_body_colliders_and_validation():
    cols = coupled.body_colliders((BALL, BOX))
    assert cols.num_spheres == 1 and cols.num_planes == 0
    np.testing.assert_allclose(cols.spheres.center[0], BALL.position)
    state = physics.rest_state(NET_HANG)
    with pytest.raises(ValueError, match="num_frames"):
        coupled.coupled_rollout(NET_HANG, SIMG, MAT, state, (BALL,), num_frames=0)
    with pytest.raises(TypeError, match="bodies"):
        coupled.coupled_rollout(NET_HANG, SIMG, MAT, state, (object(),), num_frames=1)


def test_ball_into_cloth_config_bodies():
    import pathlib
    import tomllib

    path = pathlib.Path(__file__).parents[1] / "configs" / "ball_into_cloth.toml"
    cfg = tomllib.loads(path.read_text())
    (ball,) = rigid.bodies_from_config(cfg["bodies"])
    assert ball.shape == "sphere"
    np.testing.assert_allclose(ball.mass, 0.15)
    assert float(ball.velocity[2]) < 0  # thrown towards the cloth at z = 0
    bad = [dict(cfg["bodies"][0], mass=0.0)]
    with pytest.raises(ValueError, match=r"bodies\[0\].*mass"):
        rigid.bodies_from_config(bad)
