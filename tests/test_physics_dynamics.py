"""Integrators, colliders and rollouts: known answers and invariants (rows 5-10)."""

import dataclasses
import functools
import math
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.experimental import checkify
from scipy.optimize import minimize

from diffcloth import physics
from diffcloth.shapes import make_plane, make_sphere

QUIET = dict(damping=0.0, drag_normal=0.0, drag_tangent=0.0)


@functools.cache
def _rollout_fn(num_frames):
    return jax.jit(
        lambda net, sim, m, s, col: physics.rollout(
            net, sim, m, s, num_frames=num_frames, colliders=col
        )
    )


def run(net, sim, m, s, num_frames, colliders=None):
    return _rollout_fn(num_frames)(net, sim, m, s, physics.as_colliders(colliders))


# ----------------------------------------------------------------------------- oscillator (row 10)


def _oscillator(h_per_period):
    """2x2 net, top row pinned, bottom row moves vertically on two springs: a spring-mass pair."""
    net = physics.grid_net(2, 2, (0.2, 0.1), plane="xy", pinned="top_row")
    m = physics.make_material(stretch=100.0, shear=1e-9, density=0.5, **QUIET)
    k = float(m.stretch * net.weight_v[0, 0])
    mass = float(m.density * net.area[1, 0])
    period = 2 * math.pi * math.sqrt(mass / k)
    return net, m, period


def _oscillate(integrator, substeps_per_period, periods=3, frames_per_period=100):
    net, m, period = _oscillator(substeps_per_period)
    sub = max(1, substeps_per_period // frames_per_period)
    sim = physics.make_sim(
        period / frames_per_period,
        gravity=(0, 0, 0),
        num_substeps=sub,
        integrator=integrator,
        cg_tol=1e-12,
        newton_iters=4,
    )
    s0 = physics.rest_state(net)
    s0 = physics.ClothState(s0.x.at[1, :, 1].add(-0.002), s0.v)
    traj = run(net, sim, m, s0, periods * frames_per_period)
    y = np.asarray(traj.x[:, 1, 0, 1] - net.rest[1, 0, 1])
    return net, m, sim, traj, y, period


def test_spring_mass_period_matches_analytic():
    net, m, sim, traj, y, period = _oscillate("symplectic", 2000)
    t = (np.arange(len(y)) + 1) * float(sim.dt)
    up = np.where((y[:-1] < 0) & (y[1:] >= 0))[0]
    crossings = t[up] + (t[up + 1] - t[up]) * (-y[up] / (y[up + 1] - y[up]))
    measured = np.mean(np.diff(crossings))
    assert len(crossings) >= 2
    assert abs(measured / period - 1) < 0.01


def test_undamped_spring_energy_drift_below_one_percent():
    net, m, sim, traj, y, period = _oscillate("symplectic", 2000)
    e = jax.vmap(
        lambda x, v: physics.kinetic_energy(net, m, v) + physics.elastic_energy(net, m, x)
    )(traj.x, traj.v)
    e = np.asarray(e)
    assert e[0] > 0 and np.ptp(e) / e.mean() < 0.01


@pytest.mark.parametrize(
    "integrator", ["symplectic", pytest.param("implicit", marks=pytest.mark.slow)]
)
def test_convergence_order_is_one(integrator):
    """Halving the substep halves the error at a fixed time (first-order methods)."""
    errors = []
    for n in (100, 200):
        net, m, sim, traj, y, period = _oscillate(integrator, n, periods=1)
        t = (np.arange(len(y)) + 1) * float(sim.dt)
        exact = -0.002 * np.cos(2 * np.pi * t / period)
        errors.append(np.abs(y - exact).max())
    order = np.log2(errors[0] / errors[1])
    assert 0.8 < order < 1.3, order


# ----------------------------------------------------------------------------- free net invariants


SMALL = physics.grid_net(4, 4, (0.3, 0.3))
FREE_MAT = physics.make_material(stretch=50.0, shear=10.0, bend=1e-3, density=0.2, **QUIET)


def _perturbed(net, seed=0, speed=0.2):
    rng = np.random.default_rng(seed)
    x = net.rest + 0.01 * jnp.asarray(rng.normal(size=net.rest.shape))
    v = speed * jnp.asarray(rng.normal(size=net.rest.shape))
    return physics.ClothState(x, v)


def test_momentum_conserved_without_external_forces():
    sim = physics.make_sim(1 / 30, gravity=(0, 0, 0), num_substeps=20)
    s0 = _perturbed(SMALL)
    traj = run(SMALL, sim, dataclasses.replace(FREE_MAT, damping=jnp.asarray(0.01)), s0, 20)
    mass = physics.node_mass(SMALL, FREE_MAT)[None, :, :, None]
    p0 = jnp.sum(mass[0] * s0.v, axis=(0, 1))
    p = jnp.sum(mass * traj.v, axis=(1, 2))
    np.testing.assert_allclose(p, jnp.broadcast_to(p0, p.shape), atol=1e-12)
    assert float(jnp.abs(traj.x[-1] - s0.x).max()) > 1e-3


def _energy_over(num_frames):
    sim = physics.make_sim(1 / 30, gravity=(0, 0, 0), num_substeps=100)
    physics.check_stability(SMALL, sim, FREE_MAT, error=True)
    traj = run(SMALL, sim, FREE_MAT, _perturbed(SMALL), num_frames)
    e = jax.vmap(
        lambda x, v: (
            physics.kinetic_energy(SMALL, FREE_MAT, v) + physics.elastic_energy(SMALL, FREE_MAT, x)
        )
    )(traj.x, traj.v)
    return np.asarray(e)


@pytest.mark.slow  # 6 s; moved out of the default suite (10-minute budget)
def test_undamped_free_net_energy_bounded_10000_substeps():
    e = _energy_over(100)  # 100 frames x 100 substeps
    assert np.all(np.isfinite(e))
    assert np.ptp(e) / e.mean() < 0.05


@pytest.mark.slow
def test_undamped_free_net_energy_bounded_100000_substeps():
    e = _energy_over(1000)
    assert np.ptp(e) / e.mean() < 0.05


def test_free_fall_matches_half_g_t_squared():
    """Row 9: a net at rest falls as 1/2 g t^2 (no drag)."""
    sim = physics.make_sim(0.05, num_substeps=50)
    traj = run(SMALL, sim, FREE_MAT, physics.rest_state(SMALL), 10)
    t = 0.5
    drop = SMALL.rest[..., 1] - traj.x[-1, ..., 1]
    np.testing.assert_allclose(drop, 0.5 * 9.81 * t**2, rtol=0.01)
    np.testing.assert_allclose(traj.x[-1, ..., 0], SMALL.rest[..., 0], atol=1e-12)


def test_all_pinned_state_is_constant_and_none_pinned_moves():
    """Row 8."""
    net = physics.grid_net(4, 4, (0.3, 0.3), pinned="all")
    sim = physics.make_sim(1 / 30, num_substeps=10)
    s0 = physics.ClothState(_perturbed(net).x, jnp.zeros_like(net.rest))
    traj = run(net, sim, FREE_MAT, s0, 5)
    assert bool(jnp.all(traj.x == s0.x[None])) and bool(jnp.all(traj.v == 0))
    traj2 = run(SMALL, sim, FREE_MAT, s0, 5)
    assert float(jnp.abs(traj2.x[-1] - s0.x).max()) > 1e-2


def test_zero_frames_returns_initial_state_and_bad_counts_raise():
    """Row 5."""
    sim = physics.make_sim(1 / 30, num_substeps=10)
    s0 = _perturbed(SMALL)
    assert physics.advance(SMALL, sim, FREE_MAT, s0, num_frames=0) is s0
    assert physics.rollout(SMALL, sim, FREE_MAT, s0, num_frames=0).x.shape == (0, 4, 4, 3)
    with pytest.raises(TypeError, match="num_frames"):
        physics.rollout(SMALL, sim, FREE_MAT, s0, num_frames=2.5)
    with pytest.raises(ValueError, match="num_frames"):
        physics.rollout(SMALL, sim, FREE_MAT, s0, num_frames=-1)


# ----------------------------------------------------------------------------- stability (row 6, 7)


STIFF = physics.make_material(stretch=5e4, shear=1e4, density=0.2)


@pytest.mark.slow  # 8 s
def test_stability_estimate_warns_and_explicit_blows_up_where_implicit_holds():
    sim = physics.make_sim(1 / 30, num_substeps=2)
    h_max = physics.stable_substep(SMALL, sim, STIFF)
    m_min = float(physics.node_mass(SMALL, STIFF).min())
    assert 0 < h_max < 2 * math.sqrt(m_min / float(STIFF.stretch))
    with pytest.warns(physics.StabilityWarning, match="implicit integrator"):
        physics.check_stability(SMALL, sim, STIFF)
    with pytest.raises(ValueError, match="lower dt"):
        physics.check_stability(SMALL, sim, STIFF, error=True)
    s0 = _perturbed(SMALL, speed=0.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", physics.StabilityWarning)
        with pytest.raises(physics.UnstableSimulationError, match="unstable: .*implicit"):
            physics.checked_rollout(SMALL, sim, STIFF, s0, num_frames=30)
    traj = run(SMALL, sim, STIFF, s0, 30)
    assert not bool(physics.trajectory_ok(SMALL, traj))
    sim_i = dataclasses.replace(sim, integrator="implicit")
    traj_i = physics.checked_rollout(SMALL, sim_i, STIFF, s0, num_frames=30)
    assert bool(physics.trajectory_ok(SMALL, traj_i))
    # stiff springs keep their rest lengths (the net falls and tumbles as a stiff sheet)
    edges = jnp.linalg.norm(traj_i.x[:, :, 1:] - traj_i.x[:, :, :-1], axis=-1)
    np.testing.assert_allclose(edges, 0.1, rtol=0.5)


def test_nan_initial_state_is_rejected_eagerly_and_flagged_in_debug():
    sim = physics.make_sim(1 / 30, num_substeps=10)
    s0 = physics.rest_state(SMALL)
    bad = physics.ClothState(s0.x.at[2, 2, 1].set(jnp.nan), s0.v)
    with pytest.raises(ValueError, match=r"state\.x: must be finite"):
        physics.checked_rollout(SMALL, sim, FREE_MAT, bad, num_frames=3)
    with (  # the old name still works, with a deprecation warning
        pytest.warns(DeprecationWarning, match="renamed checked_rollout"),
        pytest.raises(ValueError, match=r"state\.x: must be finite"),
    ):
        physics.simulate(SMALL, sim, FREE_MAT, bad, num_frames=3)
    checked = checkify.checkify(
        jax.jit(lambda s: physics.rollout(SMALL, sim, FREE_MAT, s, num_frames=3, debug=True))
    )
    err, _ = checked(bad)
    assert err.get() is not None and "non-finite" in err.get()
    err, _ = checked(s0)
    assert err.get() is None


# ----------------------------------------------------------------------------- colliders


BALL = make_sphere((0.02, 0.0, 0.01), 0.1)
DROP_NET = physics.grid_net(5, 5, (0.3, 0.3), center=(0.0, 0.15, 0.0))


@pytest.mark.parametrize(
    "integrator, substeps",
    [pytest.param("symplectic", 20, marks=pytest.mark.slow), ("implicit", 4)],
)  # symplectic: 8 s
def test_no_point_inside_the_sphere_after_any_step(integrator, substeps):
    m = physics.make_material(stretch=50.0, shear=10.0, friction=0.5)
    sim = physics.make_sim(1 / 30, num_substeps=substeps, integrator=integrator)
    traj = run(
        DROP_NET, sim, m, physics.rest_state(DROP_NET), 20, [BALL, make_plane((0, 1, 0), -0.5)]
    )
    dist = jnp.linalg.norm(traj.x - BALL.center[None, None, None, :], axis=-1)
    assert float(dist.min()) >= 0.1 * (1 - 1e-9)
    assert float(dist.min()) < 0.101  # it does touch
    assert float(traj.x[..., 1].min()) >= -0.5 - 1e-12
    # one step with contacts reports the impulse the ball gave (upwards)
    state, contacts = physics.step_with_contacts(
        DROP_NET, sim, m, jax.tree_util.tree_map(lambda a: a[5], traj), physics.as_colliders(BALL)
    )
    assert contacts.sphere.shape == (1, 3) and float(contacts.sphere[0, 1]) > 0


def test_point_at_sphere_centre_goes_out_along_y_with_finite_gradient():
    x = jnp.zeros((3, 1, 1))
    col = physics.as_colliders(make_sphere((0.0, 0.0, 0.0), 0.5))

    @jax.jit
    def pushed(center_y):
        c = dataclasses.replace(
            col,
            spheres=dataclasses.replace(
                col.spheres, center=col.spheres.center.at[0, 1].set(center_y)
            ),
        )
        xo, _, _, _ = physics.collide(x, x, jnp.ones((1, 1)), jnp.ones((1, 1), bool), c, 0.3, 0.0)
        return xo

    np.testing.assert_allclose(pushed(0.0)[:, 0, 0], [0, 0.5, 0])
    assert bool(jnp.isfinite(jax.grad(lambda c: pushed(c)[1, 0, 0])(0.0)))


def test_friction_slows_sliding_on_a_plane():
    net = physics.grid_net(3, 3, (0.2, 0.2), center=(0, 0.0, 0))
    sim = physics.make_sim(1 / 30, num_substeps=10)
    s0 = physics.rest_state(net, velocity=(1.0, 0.0, 0.0))
    floor = make_plane((0, 1, 0), 0.0)
    slid = []
    for mu in (0.0, 0.5):
        m = physics.make_material(stretch=5.0, shear=1.0, friction=mu, **QUIET)
        slid.append(float(run(net, sim, m, s0, 6, floor).x[-1, 1, 1, 0]))
    # Coulomb: deceleration mu g for 0.2 s -> v = 1 - 0.98; x = 0.2 - mu g t^2 / 2
    np.testing.assert_allclose(slid[0], 0.2, rtol=1e-6)
    np.testing.assert_allclose(slid[1], 0.2 - 0.5 * 9.81 * 0.2**2 / 2, rtol=0.05)


def test_moving_sphere_per_frame_and_pin_path():
    net = physics.grid_net(4, 4, (0.3, 0.3), plane="xy", pinned="top_corners")
    m = physics.make_material()
    sim = physics.make_sim(1 / 30, num_substeps=20)
    n = 10
    centers = jnp.stack([jnp.asarray([0.0, -0.5 + 0.05 * i, 0.3 - 0.04 * i]) for i in range(n)])[
        :, None, :
    ]
    path = physics.Colliders(
        spheres=dataclasses.replace(BALL, center=centers, radius=jnp.full((n, 1), 0.1)),
        sphere_velocity=jnp.zeros_like(centers),
        planes=physics.make_colliders().planes,
    )
    pins = (
        net.rest[None]
        + jnp.linspace(0, 0.1, n)[:, None, None, None]
        * jnp.asarray([1.0, 0, 0])[None, None, None, :]
    )
    traj = physics.rollout(
        net, sim, m, physics.rest_state(net), num_frames=n, colliders=path, pin_path=pins
    )
    np.testing.assert_allclose(traj.x[:, 0, 0], pins[:, 0, 0], atol=1e-12)
    dist = jnp.linalg.norm(traj.x - centers[:, :, None, :], axis=-1)
    assert float(dist.min()) >= 0.1 * (1 - 1e-9)


# ----------------------------------------------------------------------------- statics


def _settle(net, m, frames=150):
    sim = physics.make_sim(
        0.05, num_substeps=2, integrator="implicit", cg_tol=1e-10, newton_iters=4
    )
    return run(net, sim, m, physics.rest_state(net), frames)


def _minimise(net, m):
    g = jnp.asarray([0.0, -9.81, 0.0])
    free = ~np.asarray(net.pinned)
    base = np.asarray(net.rest)
    energy = jax.jit(jax.value_and_grad(lambda x: physics.potential_energy(net, m, x, g)))

    def fun(z):
        x = base.copy()
        x[free] = z.reshape(-1, 3)
        e, gx = energy(jnp.asarray(x))
        return float(e), np.asarray(gx)[free].ravel()

    res = minimize(
        fun,
        base[free].ravel(),
        jac=True,
        method="L-BFGS-B",
        options=dict(maxiter=5000, gtol=1e-12, ftol=1e-15),
    )
    x = base.copy()
    x[free] = res.x.reshape(-1, 3)
    return x


def test_hanging_net_settles_to_the_static_equilibrium():
    net = physics.grid_net(5, 4, (0.3, 0.3), plane="xy", pinned="top_row")
    m = physics.make_material(
        stretch=2.0, shear=1.0, bend=1e-4, damping=0.01, drag_normal=0.5, drag_tangent=0.5
    )
    settled = np.asarray(_settle(net, m).x[-1])
    x_star = _minimise(net, m)
    assert np.abs(x_star - np.asarray(net.rest)).max() > 0.02  # it does sag
    assert np.abs(settled - x_star).max() < 0.01 * 0.3


def test_refined_net_sags_by_nearly_the_same_amount():
    m = physics.make_material(stretch=10.0, shear=2.0, bend=1e-4)
    sags = []
    for rows, cols in ((10, 13), (19, 25)):
        net = physics.grid_net(rows, cols, (1.2, 0.9), plane="xy", pinned="top_row")
        x = _minimise(net, m)
        sags.append(float(np.mean(net.rest[-1, :, 1] - x[-1, :, 1])))
    assert sags[0] > 0.05
    assert abs(sags[0] / sags[1] - 1) < 0.03, sags
