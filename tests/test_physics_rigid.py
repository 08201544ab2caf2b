"""Tests for diffcloth.physics.rigid: known answers, invariants, contacts, gradients, validation."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcloth.physics import rigid
from diffcloth.physics.rigid import (
    angular_momentum,
    bodies_from_config,
    kinetic_energy,
    make_body,
    make_settings,
    make_thrusters,
    rigid_rollout,
)
from diffcloth.shapes import make_plane

GROUND = make_plane((0.0, 1.0, 0.0), 0.0)


def _sim(gravity=(0.0, 0.0, 0.0), dt=1 / 60, num_substeps=8, dtype=None):
    return make_settings(dt=dt, gravity=gravity, num_substeps=num_substeps, dtype=dtype)


# ---------------------------------------------------------------------------------------------
# Head-on sphere-sphere collision


M1, M2, U1, U2, R1, R2, GAP = 1.0, 3.0, 2.0, -1.0, 0.1, 0.2, 0.2
HEAD_ON_FRAMES = 12
SIM0 = _sim()


@jax.jit
def _head_on(e):
    a = make_body("sphere", mass=M1, radius=R1, position=(0.0, 0, 0), velocity=(U1, 0, 0))
    b = make_body("sphere", mass=M2, radius=R2, position=(R1 + R2 + GAP, 0, 0), velocity=(U2, 0, 0))
    a = dataclasses.replace(a, restitution=e)
    b = dataclasses.replace(b, restitution=e)
    return rigid_rollout(SIM0, (a, b), num_frames=HEAD_ON_FRAMES)


@pytest.mark.parametrize("e", [1.0, 0.5, 0.0])
def test_head_on_closed_form(e):
    ta, tb = _head_on(jnp.asarray(e))
    v1 = (M1 * U1 + M2 * U2 + M2 * e * (U2 - U1)) / (M1 + M2)
    v2 = (M1 * U1 + M2 * U2 + M1 * e * (U1 - U2)) / (M1 + M2)
    np.testing.assert_allclose(ta.velocity[-1], [v1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(tb.velocity[-1], [v2, 0, 0], atol=1e-12)
    # Momentum conserved at every frame.
    p = M1 * ta.velocity + M2 * tb.velocity
    np.testing.assert_allclose(
        p, np.tile([M1 * U1 + M2 * U2, 0, 0], (HEAD_ON_FRAMES, 1)), atol=1e-12
    )
    # Energy conserved only for e = 1; otherwise the closed-form loss.
    ke0 = 0.5 * M1 * U1**2 + 0.5 * M2 * U2**2
    sim_ke = float(
        0.5 * M1 * jnp.sum(ta.velocity[-1] ** 2) + 0.5 * M2 * jnp.sum(tb.velocity[-1] ** 2)
    )
    loss = (1 - e**2) * M1 * M2 / (2 * (M1 + M2)) * (U1 - U2) ** 2
    np.testing.assert_allclose(sim_ke, ke0 - loss, rtol=1e-12)
    if e == 1.0:
        np.testing.assert_allclose(sim_ke, ke0, rtol=1e-12)
    else:
        assert sim_ke < ke0 - 0.1
    # Continuous-time correction: the positions equal the exact ones after the contact.
    t_c = GAP / (U1 - U2)
    t_end = HEAD_ON_FRAMES / 60
    np.testing.assert_allclose(ta.position[-1, 0], U1 * t_c + v1 * (t_end - t_c), atol=1e-12)
    np.testing.assert_allclose(
        tb.position[-1, 0], R1 + R2 + GAP + U2 * t_c + v2 * (t_end - t_c), atol=1e-12
    )


# ---------------------------------------------------------------------------------------------
# Sphere on a plane: bounce height, and continuity in the initial velocity


@jax.jit
def _bounce(e):
    ball = make_body("sphere", mass=0.5, radius=0.1, position=(0.0, 1.1, 0.0))
    ball = dataclasses.replace(ball, restitution=e)
    sim = _sim(gravity=(0.0, -9.81, 0.0), num_substeps=20)
    return rigid_rollout(sim, (ball,), num_frames=66, planes=GROUND)[0].position[:, 1] - 0.1


@pytest.mark.parametrize("e", [0.8, 0.5])
def test_bounce_height_e2h(e):
    y = np.asarray(_bounce(jnp.asarray(e)))
    hit = int(np.argmin(y))
    assert 20 < hit < 35 and y.min() > -1e-2
    np.testing.assert_allclose(y[hit:].max(), e**2 * 1.0, rtol=1e-2)


def test_plane_hit_is_exact_for_any_substep():
    """Zero gravity: a sphere thrown at the ground ends at the analytic height e*u*(T - t_c) for
    many speeds, so the contact substep changing does not make the final position jump."""
    e, h0, frames = 0.7, 0.25, 6
    speeds = jnp.linspace(2.6, 4.0, 16)  # contact in many different substeps

    def final(u):
        ball = make_body(
            "sphere", mass=1.0, radius=0.1, position=(0.0, 0.1 + h0, 0.0), restitution=e
        )
        ball = dataclasses.replace(ball, velocity=jnp.stack([0.0 * u, -u, 0.0 * u]))
        return rigid_rollout(_sim(num_substeps=4), (ball,), num_frames=frames, planes=GROUND)[0]

    traj = jax.jit(jax.vmap(final))(speeds)
    t_end = frames / 60
    expected = e * speeds * (t_end - h0 / speeds)
    np.testing.assert_allclose(traj.position[:, -1, 1] - 0.1, expected, atol=1e-12)
    assert float(jnp.ptp(expected)) > 0.05


# ---------------------------------------------------------------------------------------------
# Boxes on planes


def test_box_corner_first_spin_matches_impulse_formula():
    e, mass, he = 0.5, 2.0, np.array([0.1, 0.2, 0.3])
    q = rigid.quat_from_axis_angle(jnp.asarray([1.0, 0.3, 0.5]), 0.7)
    box = make_body("box", mass=mass, half_extents=he, orientation=np.asarray(q), restitution=e)
    verts = np.asarray(rigid.box_vertices(box))
    low = verts[np.argmin(verts[:, 1])]
    assert np.sort(verts[:, 1])[1] - low[1] > 0.05  # one corner clearly lowest
    box = dataclasses.replace(
        box,
        position=box.position - jnp.asarray([0.0, low[1] - 0.001, 0.0]),
        velocity=jnp.asarray([0.0, -1.0, 0.0]),
    )
    r = low  # the arm from the centre (at the origin above) to the lowest corner
    n = np.array([0.0, 1.0, 0.0])
    inv_i = np.linalg.inv(np.asarray(rigid.world_inertia(box)))
    vn = -1.0
    j = -(1 + e) * vn / (1 / mass + n @ np.cross(inv_i @ np.cross(r, n), r))
    (traj,) = rigid_rollout(_sim(num_substeps=4), (box,), num_frames=1, planes=GROUND)
    after = jax.tree_util.tree_map(lambda a: a[-1], traj)
    np.testing.assert_allclose(after.velocity, [0.0, -1.0 + j / mass, 0.0], atol=1e-12)
    np.testing.assert_allclose(angular_momentum(after), np.cross(r, j * n), atol=1e-12)
    assert np.linalg.norm(after.angular_velocity) > 1.0


def test_box_landing_flat_does_not_spin_and_rests():
    box = make_body(
        "box", mass=1.0, half_extents=(0.2, 0.1, 0.3), position=(0, 0.5, 0), restitution=0.3
    )
    sim = _sim(gravity=(0.0, -9.81, 0.0), num_substeps=8)
    (traj,) = rigid_rollout(sim, (box,), num_frames=90, planes=GROUND)
    np.testing.assert_allclose(traj.angular_velocity, 0.0, atol=1e-9)
    np.testing.assert_allclose(traj.position[-1, 1], 0.1, atol=2e-3)
    assert float(jnp.abs(traj.velocity[-1, 1])) < 0.05


# ---------------------------------------------------------------------------------------------
# Rotation, forces, drag, thrusters


def test_torque_free_rotation_keeps_angular_momentum():
    box = make_body("box", mass=2.0, half_extents=(0.1, 0.2, 0.3), angular_velocity=(1.0, 2.0, 3.0))
    (traj,) = rigid_rollout(_sim(num_substeps=4), (box,), num_frames=200)
    ang = jax.vmap(angular_momentum)(traj)
    np.testing.assert_allclose(
        ang, np.tile(np.asarray(angular_momentum(box)), (200, 1)), atol=1e-12
    )
    energy = jax.vmap(kinetic_energy)(traj)
    np.testing.assert_allclose(energy, kinetic_energy(box), rtol=1e-4)
    # The body frame precesses: the angular velocity is not constant.
    assert float(jnp.max(jnp.ptp(traj.angular_velocity, axis=0))) > 0.5


def test_force_and_torque_decomposition():
    c = jnp.asarray([1.0, 2.0, 3.0])
    f = jnp.asarray([[0.0, 0.0, 2.0], [1.0, 0.0, 0.0]])
    p = c[None, :] + jnp.asarray([[0.0, 0.0, -1.0], [0.0, 0.5, 0.0]])
    force, torque = rigid.force_and_torque(c, f, p)
    np.testing.assert_allclose(force, [1.0, 0.0, 2.0])
    np.testing.assert_allclose(torque, np.cross([0.0, 0.5, 0.0], [1.0, 0.0, 0.0]))


THRUST_FRAMES = 20


@jax.jit
def _thrust(controls):
    q = rigid.quat_from_axis_angle(jnp.asarray([0.0, 1.0, 0.0]), jnp.asarray(0.5))
    box = make_body("box", mass=2.0, half_extents=(0.1, 0.1, 0.3))
    box = dataclasses.replace(box, orientation=q)
    th = make_thrusters(
        [[0.0, 0.0, -0.3], [0.1, 0.0, -0.3]], [[0, 0, 1.0], [0, 0, 1.0]], [4.0, 4.0]
    )
    return rigid_rollout(
        _sim(), (box,), num_frames=THRUST_FRAMES, thrusters=(th,), controls=(controls,)
    )[0]


def test_thruster_through_centre_makes_no_rotation():
    on = jnp.zeros((THRUST_FRAMES, 2)).at[:10, 0].set(1.0)
    traj = _thrust(on)
    np.testing.assert_allclose(traj.angular_velocity, 0.0, atol=1e-14)
    front = np.array([np.sin(0.5), 0.0, np.cos(0.5)])  # body z rotated 0.5 rad about y
    np.testing.assert_allclose(traj.velocity[9], 4.0 / 2.0 * (10 / 60) * front, atol=1e-12)
    np.testing.assert_allclose(traj.velocity[-1], traj.velocity[9], atol=1e-14)  # switched off
    off_centre = _thrust(jnp.zeros((THRUST_FRAMES, 2)).at[:, 1].set(1.0))
    assert float(jnp.linalg.norm(off_centre.angular_velocity[-1])) > 0.1
    idle = _thrust(jnp.zeros((THRUST_FRAMES, 2)))
    np.testing.assert_allclose(idle.velocity, 0.0, atol=1e-14)


def test_linear_and_orthogonal_drag():
    box = make_body(
        "box", mass=1.0, half_extents=(0.1, 0.1, 0.1), velocity=(1.0, 0.0, 1.0),
        linear_drag=2.0, orthogonal_drag=0.5,
    )  # fmt: skip
    (traj,) = rigid_rollout(_sim(num_substeps=16), (box,), num_frames=60)
    np.testing.assert_allclose(traj.velocity[-1, 2], np.exp(-2.0), rtol=1e-2)  # front axis (z)
    np.testing.assert_allclose(traj.velocity[-1, 0], np.exp(-0.5), rtol=1e-2)  # right axis (x)


# ---------------------------------------------------------------------------------------------
# Contacts


def test_contact_primitives():
    s1 = make_body("sphere", mass=1.0, radius=0.3, position=(0.5, 0.0, 0.0))
    s2 = make_body("sphere", mass=1.0, radius=0.3)
    c = rigid.contact(s1, s2)
    np.testing.assert_allclose(c.depth, 0.1)
    np.testing.assert_allclose(c.normal, [1.0, 0, 0])
    np.testing.assert_allclose(c.point, [0.25, 0, 0])
    box = make_body("box", mass=1.0, half_extents=(0.2, 0.2, 0.2))
    # sphere touching the +x face
    c = rigid.contact(make_body("sphere", mass=1.0, radius=0.1, position=(0.25, 0.05, 0.0)), box)
    np.testing.assert_allclose([c.depth, *c.normal], [0.05, 1.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(c.point, [0.2, 0.05, 0.0], atol=1e-12)
    # box against sphere: normal flips (sphere -> box)
    c2 = rigid.contact(box, make_body("sphere", mass=1.0, radius=0.1, position=(0.25, 0.05, 0.0)))
    np.testing.assert_allclose(c2.normal, [-1.0, 0.0, 0.0], atol=1e-12)
    # sphere centre inside the box, nearest face +y
    c = rigid.contact(make_body("sphere", mass=1.0, radius=0.1, position=(0.0, 0.15, 0.0)), box)
    np.testing.assert_allclose([c.depth, *c.normal], [0.15, 0.0, 1.0, 0.0], atol=1e-12)
    # sphere off a corner: normal along the diagonal
    c = rigid.contact(make_body("sphere", mass=1.0, radius=0.5, position=(0.5, 0.5, 0.5)), box)
    np.testing.assert_allclose(c.normal, np.ones(3) / np.sqrt(3), atol=1e-12)
    np.testing.assert_allclose(c.depth, 0.5 - np.sqrt(3) * 0.3, atol=1e-12)
    # small box pressed into a big box's +x face: face contact, centred
    small = make_body("box", mass=1.0, half_extents=(0.05, 0.05, 0.05), position=(0.23, 0.0, 0.0))
    c = rigid.contact(small, box)
    np.testing.assert_allclose([c.depth, *c.normal], [0.02, 1.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(c.point, [0.18, 0.0, 0.0], atol=1e-12)
    c = rigid.contact(box, small)  # reversed: normal from small to box
    np.testing.assert_allclose([c.depth, *c.normal], [0.02, -1.0, 0.0, 0.0], atol=1e-12)
    # box flat on a plane: the face centre; sphere and plane apart: negative depth
    c = rigid.contact_plane(dataclasses.replace(box, position=jnp.asarray([0.0, 0.15, 0.0])),
                            GROUND.normal, GROUND.offset)  # fmt: skip
    np.testing.assert_allclose([c.depth, *c.point], [0.05, 0.0, -0.05, 0.0], atol=1e-12)
    c = rigid.contact_plane(s1, GROUND.normal, jnp.asarray(-1.0))
    np.testing.assert_allclose(c.depth, -0.7)


def test_sphere_hits_box_and_momentum_is_conserved():
    ball = make_body("sphere", mass=0.5, radius=0.1, position=(-0.5, 0.05, 0.02),
                     velocity=(3.0, 0, 0), restitution=0.9, friction=0.3)  # fmt: skip
    box = make_body("box", mass=2.0, half_extents=(0.2, 0.2, 0.2))
    ta, tb = rigid_rollout(_sim(), (ball, box), num_frames=15)
    p = 0.5 * ta.velocity + 2.0 * tb.velocity
    np.testing.assert_allclose(p, np.tile([1.5, 0.0, 0.0], (15, 1)), atol=1e-12)
    assert float(ta.velocity[-1, 0]) < 0 and float(tb.velocity[-1, 0]) > 0
    assert float(jnp.linalg.norm(tb.angular_velocity[-1])) > 0  # off-centre hit spins the box


# ---------------------------------------------------------------------------------------------
# Gradients (float64, central finite differences)

NAMES = ("mass", "restitution", "friction", "drag", "vx", "vy")
P0 = np.array([0.7, 0.6, 0.1, 0.3, 1.5, -1.0])
W = jnp.asarray([0.3, 1.0, -0.7])


def _spheres_loss(p):
    """A ball bounces on the ground (friction) and hits a second ball; weighted final positions."""
    ball = make_body("sphere", mass=1.0, radius=0.1, position=(0.0, 0.3, 0.0))
    ball = dataclasses.replace(
        ball, mass=p[0], restitution=p[1], friction=p[2], linear_drag=p[3], orthogonal_drag=p[3],
        velocity=jnp.stack([p[4], p[5], 0.4 + 0 * p[4]]),
        angular_velocity=jnp.asarray([0.0, 0.0, 2.0]),
    )  # fmt: skip
    other = make_body("sphere", mass=2.0, radius=0.15, position=(0.55, 0.15, 0.12), restitution=0.5)
    sim = _sim(gravity=(0.0, -9.81, 0.0), dt=1 / 30, num_substeps=4)
    ta, tb = rigid_rollout(sim, (ball, other), num_frames=12, planes=GROUND)
    return ta.position[-1] @ W + tb.position[-1] @ jnp.asarray([1.0, 0.2, 0.5])


def _thrust_loss(strength):
    box = make_body("box", mass=1.0, half_extents=(0.1, 0.2, 0.3), position=(-1.0, 2.0, 0.0))
    th = make_thrusters([[0.05, 0.0, -0.3]], [[0.0, 0.0, 1.0]], [1.0])
    th = dataclasses.replace(th, strengths=strength[None])
    (traj,) = rigid_rollout(_sim(num_substeps=2), (box,), num_frames=10, thrusters=(th,))
    return traj.position[-1] @ W + traj.orientation[-1] @ jnp.asarray([0.0, 1.0, 0.5, 0.2])


def _central_fd(f, x, eps=1e-6):
    x = np.atleast_1d(np.asarray(x, np.float64))
    out = []
    for i in range(x.size):
        d = eps * np.eye(x.size)[i]
        out.append(
            (float(f(jnp.asarray(x + d).reshape(np.shape(x)))) - float(f(jnp.asarray(x - d))))
            / (2 * eps)
        )
    return np.array(out)


@pytest.mark.slow  # ~28 s (compile); the thruster-strength gradient test stays default
@pytest.mark.gate  # the gating slow tier (.ci/run)
def test_gradients_match_finite_differences():
    """d(final position) / d(mass, restitution, friction, drag, initial velocity): reverse mode
    against central differences in float64 (the contact substep is fixed within +-eps; the
    continuous-time correction keeps the function continuous across substeps anyway)."""
    grad = np.asarray(jax.jit(jax.grad(_spheres_loss))(jnp.asarray(P0)))
    fd = _central_fd(jax.jit(_spheres_loss), P0)
    for name, g, f in zip(NAMES, grad, fd, strict=True):
        assert abs(g) > 1e-3, f"gradient w.r.t. {name} is zero"
        np.testing.assert_allclose(g, f, rtol=1e-5, atol=1e-7, err_msg=name)


def test_thruster_strength_gradient():
    s0 = jnp.asarray(3.0)
    # forward mode here (reverse mode is covered above)
    g = float(jax.jit(lambda s: jax.jvp(_thrust_loss, (s,), (jnp.ones_like(s),))[1])(s0))
    loss = jax.jit(_thrust_loss)
    f = float(_central_fd(lambda s: loss(s.reshape(())), np.array([3.0]))[0])
    assert abs(g) > 1e-3
    np.testing.assert_allclose(g, f, rtol=1e-6)


def test_gradients_finite_at_coincident_spheres():
    def f(x):
        a = make_body("sphere", mass=1.0, radius=0.1)
        b = make_body("sphere", mass=1.0, radius=0.1, velocity=(0.0, 0.0, 1.0))
        a, b = rigid.collide_pair(dataclasses.replace(a, position=x), b)
        return jnp.sum(a.position**2 + a.velocity**2 + b.velocity**2)

    g = jax.jit(jax.grad(f))(jnp.zeros(3))
    assert np.all(np.isfinite(np.asarray(g)))
    same = make_body("sphere", mass=1.0, radius=0.1)
    np.testing.assert_allclose(rigid.contact(same, same).normal, [0.0, 1.0, 0.0])


# ---------------------------------------------------------------------------------------------
# dtypes, compilation, validation


def test_float32_in_float32_out_and_one_compile():
    count = []

    @jax.jit
    def run(mass):
        count.append(1)
        ball = make_body("sphere", mass=1.0, radius=0.1, position=(0, 0.5, 0), dtype=jnp.float32)
        box = make_body(
            "box",
            mass=1.0,
            half_extents=(0.1, 0.1, 0.1),
            position=(0.05, 0.2, 0),
            dtype=jnp.float32,
        )
        ball = dataclasses.replace(ball, mass=mass)
        sim = _sim(gravity=(0.0, -9.81, 0.0), num_substeps=2, dtype=jnp.float32)
        return rigid_rollout(
            sim, (ball, box), num_frames=3, planes=make_plane((0, 1, 0), 0.0, dtype=jnp.float32)
        )

    out = run(jnp.float32(1.0))
    run(jnp.float32(2.0))
    assert len(count) == 1
    for leaf in jax.tree_util.tree_leaves(out):
        assert leaf.dtype == jnp.float32
        assert np.all(np.isfinite(np.asarray(leaf)))


@pytest.mark.parametrize(
    "kwargs, word",
    [
        (dict(shape="sphere", mass=0.0, radius=0.1), "mass"),
        (dict(shape="sphere", mass=-1.0, radius=0.1), "mass"),
        (dict(shape="sphere", mass=1.0, radius=-0.1), "radius"),
        (dict(shape="sphere", mass=1.0), "radius"),
        (dict(shape="box", mass=1.0, half_extents=(0.1, 0.0, 0.1)), "half_extents"),
        (dict(shape="box", mass=1.0), "half_extents"),
        (dict(shape="cone", mass=1.0), "shape"),
        (dict(shape="sphere", mass=1.0, radius=0.1, restitution=1.5), "restitution"),
        (dict(shape="sphere", mass=1.0, radius=0.1, friction=-0.1), "friction"),
        (dict(shape="sphere", mass=1.0, radius=0.1, linear_drag=float("nan")), "linear_drag"),
        (dict(shape="sphere", mass=1.0, radius=0.1, position=(0, 1)), "position"),
        (dict(shape="sphere", mass=1.0, radius=0.1, orientation=(0, 0, 0, 0)), "orientation"),
    ],
)
def test_make_body_validation(kwargs, word):
    with pytest.raises(ValueError, match=word):
        make_body(**kwargs)


def test_bodies_from_config():
    bodies = bodies_from_config(
        [
            {"shape": "sphere", "radius": 0.1, "mass": 0.2, "position": [0, 1, 0], "drag": 0.05},
            {"shape": "box", "half_extents": [0.1, 0.2, 0.3], "mass": 1.0, "restitution": 0.2},
        ]
    )
    assert [b.shape for b in bodies] == ["sphere", "box"]
    np.testing.assert_allclose(bodies[0].linear_drag, 0.05)
    np.testing.assert_allclose(bodies[0].orthogonal_drag, 0.05)
    np.testing.assert_allclose(rigid.inertia_tensor(bodies[1]), np.diag([0.13, 0.1, 0.05]) / 3)
    with pytest.raises(ValueError, match=r"bodies\[1\].*mass.*\(0"):
        bodies_from_config([{"radius": 0.1, "mass": 1.0}, {"radius": 0.1, "mass": 0.0}])
    with pytest.raises(ValueError, match="unknown key.*colour"):
        bodies_from_config([{"radius": 0.1, "mass": 1.0, "colour": 1}])
    with pytest.raises(ValueError, match="mass"):
        bodies_from_config([{"radius": 0.1}])
    with pytest.raises(ValueError, match="half_extents"):
        bodies_from_config(
            [{"shape": "sphere", "radius": 0.1, "mass": 1.0, "half_extents": [1, 1, 1]}]
        )


def test_rollout_argument_validation():
    ball = make_body("sphere", mass=1.0, radius=0.1)
    th = make_thrusters([[0, 0, 0]], [[0, 0, 1.0]], [1.0])
    with pytest.raises(ValueError, match="num_frames"):
        rigid_rollout(SIM0, (ball,), num_frames=0)
    with pytest.raises(ValueError, match="thrusters"):
        rigid_rollout(SIM0, (ball,), num_frames=2, thrusters=(th, th))
    with pytest.raises(ValueError, match=r"controls\[0\]"):
        rigid_rollout(SIM0, (ball,), num_frames=2, thrusters=(th,), controls=(jnp.ones((3, 1)),))
    with pytest.raises(ValueError, match="directions"):
        make_thrusters([[0, 0, 0]], [[0, 0, 0]], [1.0])
    with pytest.raises(ValueError, match="num_substeps"):
        make_settings(num_substeps=0)
