"""The Provot mass-spring model: against the independent Warp reference (benchmarks/peers), physics
checks (energy, momentum, a single spring's period and decay), FD gradients, stability estimate,
and the push-out offset of the rendered surface."""

import dataclasses
import math
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcloth import physics, pipeline
from diffcloth.physics import massspring
from diffcloth.shapes import Plane, Sphere
from diffcloth.surface import collide_surface, push_out_of_spheres, tessellate

H = 1.0 / 2400.0  # substep, s
SUB = 40  # substeps per frame (60 fps)
PARAMS = dict(
    k_struct=400.0,
    k_shear=100.0,
    k_flex=20.0,
    d_struct=0.05,
    d_shear=0.02,
    d_flex=0.005,
    air_damping=0.002,
    density=0.2,
    friction=0.4,
)

_ROLLOUTS = {}


def roll(net, sim, ms, state, frames, colliders=None):
    """Jitted rollout shared by the tests (one compile per static setting)."""
    key = (frames, sim.num_substeps, sim.friction_rule, ms.lumping, colliders is None)
    if key not in _ROLLOUTS:
        _ROLLOUTS[key] = jax.jit(
            lambda n, s, m, s0, c: physics.rollout(n, s, m, s0, num_frames=frames, colliders=c)
        )
    return _ROLLOUTS[key](net, sim, ms, state, colliders)


def with_initial(traj, state):
    return np.concatenate([np.asarray(state.x)[None], np.asarray(traj.x)])


def diffcloth_run(rows, cols, size, params, *, height, pins=None, sphere=None, planes=(),
                  frames=60, thickness=0.005, rule="coulomb", lumping="uniform",
                  dtype=jnp.float64):  # fmt: skip
    net = physics.grid_net(rows, cols, size, center=(0.0, height, 0.0), pinned=pins, dtype=dtype)
    ms = physics.make_mass_spring(dtype, lumping=lumping, **params)
    sim = physics.make_sim(
        H * SUB, num_substeps=SUB, collision_margin=thickness, friction_rule=rule, dtype=dtype
    )
    cols_ = [Sphere(jnp.asarray(sphere[0], dtype), jnp.asarray(sphere[1], dtype))] if sphere else []
    cols_ += [Plane(jnp.asarray(n, dtype), jnp.asarray(o, dtype)) for n, o in planes]
    colliders = physics.as_colliders(cols_, dtype=dtype) if cols_ else None
    s0 = physics.rest_state(net)
    return with_initial(roll(net, sim, ms, s0, frames, colliders), s0)


def warp_run(rows, cols, size, params, *, height, pins=None, sphere=None, planes=(), frames=60,
             thickness=0.005, rule="coulomb", lumping="uniform", dtype=np.float64):  # fmt: skip
    pytest.importorskip("warp", reason="the Warp reference needs warp-lang (the bench extra)")
    from benchmarks.peers.warp_massspring import simulate

    p = dict(params, height=height, pins=pins, planes=list(planes), contact_thickness=thickness,
             friction_rule=rule, mass_lumping=lumping)  # fmt: skip
    return simulate(rows, cols, size, p, sphere=sphere, dt=H, substeps=SUB, frames=frames,
                    dtype=dtype)  # fmt: skip


def compare(a, b):
    d = np.linalg.norm(np.asarray(a, np.float64) - np.asarray(b, np.float64), axis=-1)
    return float(d.max()), float(d.mean())


# ----------------------------------------------------------------------------- vs Warp reference


def test_matches_warp_before_contact_within_1mm_over_1s():
    """Float64, identical parameters, 1 s of a net hanging from two corners (large swing)."""
    kw = dict(height=0.5, pins="top_corners")
    a = diffcloth_run(6, 6, (0.4, 0.4), PARAMS, **kw)
    b = warp_run(6, 6, (0.4, 0.4), PARAMS, **kw)
    dmax, dmean = compare(a, b)
    print(f"before contact: max {dmax * 1e3:.3g} mm, mean {dmean * 1e3:.3g} mm")
    assert float(np.max(np.abs(a[-1] - a[0]))) > 0.2  # the net really moved
    assert dmax < 1e-3
    assert dmax < 1e-6  # same operations in float64: only roundoff differs


def test_matches_warp_with_sphere_contact_and_friction_within_1cm():
    """Dropped off-centre onto a sphere over a ground plane; Coulomb friction 0.4, 1 s."""
    kw = dict(height=0.45, sphere=((0.03, 0.2, 0.02), 0.12), planes=[((0.0, 1.0, 0.0), 0.0)])
    a = diffcloth_run(6, 6, (0.4, 0.4), PARAMS, **kw)
    b = warp_run(6, 6, (0.4, 0.4), PARAMS, **kw)
    dmax, dmean = compare(a, b)
    print(f"sphere contact: max {dmax * 1e3:.3g} mm, mean {dmean * 1e3:.3g} mm")
    centre = np.array([0.03, 0.2, 0.02])
    dist = np.linalg.norm(a[-1] - centre, axis=-1)
    assert dist.min() < 0.12 + 0.005 + 1e-6  # some nodes rest on the sphere
    assert dist.min() > 0.12 + 0.005 - 1e-9  # and none inside it
    assert dmean < 1e-2
    assert dmax < 1e-3


@pytest.mark.slow
@pytest.mark.gate  # the gating slow tier (.ci/run)
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_matches_warp_hanging_on_ground_displacement_rule_area_masses(dtype):
    """The other options: area lumping, the displacement friction rule, a plane, float32."""
    kw = dict(height=0.3, pins="top_row", planes=[((0.0, 1.0, 0.0), 0.0)], rule="displacement",
              lumping="area", frames=60)  # fmt: skip
    p = dict(PARAMS, k_struct=200.0)
    a = diffcloth_run(7, 6, (0.4, 0.6), p, dtype=jnp.dtype(dtype), **kw)
    b = warp_run(7, 6, (0.4, 0.6), p, dtype=dtype, **kw)
    assert a.dtype == b.dtype == np.dtype(dtype)
    dmax, dmean = compare(a, b)
    print(f"{np.dtype(dtype).name}: max {dmax * 1e3:.3g} mm, mean {dmean * 1e3:.3g} mm")
    assert dmean < 1e-2
    assert dmax < (1e-6 if dtype == np.float64 else 1e-2)


# ----------------------------------------------------------------------------- physics checks

NOGRAV = dict(gravity=(0.0, 0.0, 0.0))


def _perturbed_state(net, scale=0.01, speed=0.0, seed=0):
    rng = np.random.default_rng(seed)
    dx = rng.normal(size=net.rest.shape) * scale
    dv = rng.normal(size=net.rest.shape) * speed
    return physics.ClothState(net.rest + dx, jnp.asarray(dv, net.rest.dtype))


@pytest.mark.slow
def test_energy_is_conserved_without_damping_at_small_dt():
    net = physics.grid_net(4, 4, (0.3, 0.3))
    ms = physics.make_mass_spring(
        k_struct=50.0, k_shear=10.0, k_flex=2.0, d_struct=0.0, d_shear=0.0, d_flex=0.0,
        air_damping=0.0, density=1.0,
    )  # fmt: skip
    g = jnp.array([0.0, -9.81, 0.0])
    s0 = _perturbed_state(net, 0.01)

    @jax.jit
    def energy(x, v):
        return massspring.potential_energy(net, ms, x, g) + massspring.kinetic_energy(net, ms, v)

    drift = {}
    for h in (1e-5, 2e-5):
        sim = physics.make_sim(h * 100, num_substeps=100)
        traj = roll(net, sim, ms, s0, 30)
        e = jax.vmap(energy)(traj.x, traj.v)
        e0 = energy(s0.x, s0.v)
        elastic0 = jax.jit(lambda x: massspring.elastic_energy(net, ms, x))(s0.x)
        assert float(jnp.max(jnp.abs(traj.x[-1] - s0.x))) > 0.01  # it moved (falls, vibrates)
        drift[h] = float(jnp.max(jnp.abs(e - e0)) / elastic0)
    assert drift[1e-5] < 2e-3
    # symplectic Euler: a bounded energy error of order h
    assert 1.5 < drift[2e-5] / drift[1e-5] < 2.5


@pytest.mark.slow
def test_linear_and_angular_momentum_are_conserved_with_dashpots():
    net = physics.grid_net(4, 5, (0.3, 0.4))
    ms = physics.make_mass_spring(**dict(PARAMS, air_damping=0.0))
    sim = physics.make_sim(1 / 60, num_substeps=40, **NOGRAV)
    s0 = _perturbed_state(net, 0.02, speed=0.3, seed=1)
    traj = roll(net, sim, ms, s0, 30)
    m = np.asarray(massspring.node_mass(net, ms))[..., None]

    def momenta(x, v):
        x, v = np.asarray(x), np.asarray(v)
        return (m * v).sum((0, 1)), (m * np.cross(x, v)).sum((0, 1))

    p0, l0 = momenta(s0.x, s0.v)
    p1, l1 = momenta(traj.x[-1], traj.v[-1])

    @jax.jit
    def energy(x, v):
        return massspring.kinetic_energy(net, ms, v) + massspring.elastic_energy(net, ms, x)

    assert energy(traj.x[-1], traj.v[-1]) < 0.9 * energy(s0.x, s0.v)  # the dashpots dissipate
    np.testing.assert_allclose(p1, p0, atol=1e-12 * np.abs(p0).max())
    np.testing.assert_allclose(l1, l0, atol=1e-11 * np.abs(l0).max())


def _single_spring(d_struct):
    """2 x 2 net, top row pinned, bottom nodes moved 1 cm along the rows: each bottom node hangs on
    one structural spring (the bottom spring stays at rest length, shear springs are off)."""
    net = physics.grid_net(2, 2, (0.2, 0.2), pinned="top_row")
    ms = physics.make_mass_spring(
        k_struct=40.0, k_shear=0.0, k_flex=0.0, d_struct=d_struct, d_shear=0.0, d_flex=0.0,
        air_damping=0.0, density=0.5,
    )  # fmt: skip
    h = 5e-5
    sim = physics.make_sim(5 * h, num_substeps=5, **NOGRAV)
    x0 = net.rest.at[1, :, 2].add(0.01)
    traj = roll(net, sim, ms, physics.ClothState(x0, jnp.zeros_like(x0)), 1200)
    z = np.concatenate([[0.01], np.asarray(traj.x[:, 1, 0, 2] - net.rest[1, 0, 2])])
    h = 5 * h  # one sample per frame
    m = float(massspring.node_mass(net, ms)[1, 0])
    return z, h, m, 40.0


def test_single_spring_oscillates_with_the_analytic_period():
    z, h, m, k = _single_spring(0.0)
    t = np.arange(z.size) * h
    up = np.where((z[:-1] < 0) & (z[1:] >= 0))[0]
    cross = t[up] + h * (-z[up]) / (z[up + 1] - z[up])
    period = float(np.mean(np.diff(cross)))
    omega = math.sqrt(k / m)
    discrete = 2 * math.pi / ((2 / h) * math.asin(h * omega / 2))
    assert len(cross) >= 3
    assert period == pytest.approx(2 * math.pi / omega, rel=1e-3)
    assert period == pytest.approx(discrete, rel=1e-4)


def test_single_dashpot_decays_at_the_analytic_rate():
    d = 0.02
    z, h, m, k = _single_spring(d)
    peaks = np.where((z[1:-1] > z[:-2]) & (z[1:-1] >= z[2:]) & (z[1:-1] > 0))[0] + 1
    assert len(peaks) >= 2
    rate = math.log(z[peaks[0]] / z[peaks[-1]]) / ((peaks[-1] - peaks[0]) * h)
    assert rate == pytest.approx(d / (2 * m), rel=2e-2)


def test_mass_lumping_and_forces_sum_to_zero():
    net = physics.grid_net(5, 4, (0.4, 0.3))
    uni = physics.make_mass_spring(density=0.3)
    area = physics.make_mass_spring(density=0.3, lumping="area")
    mu, ma = np.asarray(massspring.node_mass(net, uni)), np.asarray(massspring.node_mass(net, area))
    assert mu.sum() == pytest.approx(0.3 * 0.12) and ma.sum() == pytest.approx(0.3 * 0.12)
    assert np.ptp(mu) == 0 and ma[0, 0] == pytest.approx(ma[2, 2] / 4)
    s = _perturbed_state(net, 0.02, 0.5)
    forces = jax.jit(lambda x, v: massspring.spring_forces(net, uni, x, v))
    f = forces(s.x, s.v)
    np.testing.assert_allclose(np.asarray(f).sum((0, 1)), 0.0, atol=1e-12)
    # forces are minus the energy gradient (at v = 0)
    g = jax.jit(jax.grad(lambda x: massspring.elastic_energy(net, uni, x)))(s.x)
    f0 = forces(s.x, jnp.zeros_like(s.x))
    np.testing.assert_allclose(np.asarray(f0), -np.asarray(g), rtol=1e-10, atol=1e-12)


def test_bad_values_and_the_implicit_integrator_are_refused():
    with pytest.raises(ValueError, match=r"material\.k_struct = -1.0 .*\(0, inf\)"):
        physics.make_mass_spring(k_struct=-1.0)
    with pytest.raises(ValueError, match="mass_lumping"):
        physics.make_mass_spring(lumping="corner")
    with pytest.raises(ValueError, match="unknown field"):
        physics.make_mass_spring(stretch=3.0)
    with pytest.raises(ValueError, match="friction_rule"):
        physics.make_sim(1 / 60, friction_rule="sticky")
    net = physics.grid_net(3, 3, (0.2, 0.2))
    sim = physics.make_sim(1 / 60, num_substeps=4, integrator="implicit")
    with pytest.raises(ValueError, match="implicit.*symplectic"):
        physics.step(net, sim, physics.make_mass_spring(), physics.rest_state(net))


# ----------------------------------------------------------------------------- gradients


@pytest.mark.slow
@pytest.mark.gate  # the gating slow tier (.ci/run)
def test_gradient_wrt_every_parameter_matches_central_differences():
    net = physics.grid_net(4, 4, (0.3, 0.3), center=(0.0, 0.5, 0.0), pinned="top_corners")
    sim = physics.make_sim(1 / 60, num_substeps=20, wind=(0.5, 0.0, 0.2))
    names = [n for n in massspring.MASS_SPRING_FIELDS if n != "friction"]  # no contact here
    base = physics.make_mass_spring(**PARAMS)
    s0 = _perturbed_state(net, 0.005, 0.1, seed=3)
    rng = np.random.default_rng(4)
    w = jnp.asarray(rng.normal(size=(2,) + net.rest.shape))

    def loss(vals):
        ms = dataclasses.replace(base, **dict(zip(names, vals, strict=True)))
        traj = physics.rollout(net, sim, ms, s0, num_frames=6)
        return jnp.sum(w[0] * traj.x[-1]) + 0.01 * jnp.sum(w[1] * traj.v[-1])

    vals = [getattr(base, n) for n in names]
    f = jax.jit(jax.value_and_grad(loss))
    _, grad = f(vals)
    for i, name in enumerate(names):
        eps = 1e-5 * max(abs(float(vals[i])), 1e-3)
        up = [v + eps if j == i else v for j, v in enumerate(vals)]
        dn = [v - eps if j == i else v for j, v in enumerate(vals)]
        fd = (float(f(up)[0]) - float(f(dn)[0])) / (2 * eps)
        assert float(grad[i]) == pytest.approx(fd, rel=1e-5, abs=1e-9), name


@pytest.mark.slow
def test_parameters_are_fittable_by_name_through_the_pipeline():
    from diffcloth import config as cfg
    from diffcloth import scene as scene_mod

    small = {
        "net": {"rows": 5, "cols": 5, "width": 0.4, "height": 0.4, "center": [0.0, 0.6, 0.0]},
        "sim": {"dt": 1.0 / 60.0, "num_frames": 6, "num_substeps": 20},
        "render": {"width": 16, "height": 16, "level": 2},
    }
    sc = scene_mod.build_scene(cfg.parse_config(small), dtype=jnp.float64)
    sc = dataclasses.replace(sc, material=physics.make_mass_spring(**PARAMS))
    names = ("k_struct", "k_flex", "d_struct", "air_damping", "density")
    for n in names:
        assert pipeline.PARAMETERS[n] == ("material", n)
    assert float(pipeline.param_value(sc, "k_flex")) == 20.0
    with pytest.raises(ValueError, match="'bend' does not exist.*MassSpring"):
        pipeline.apply_params(sc, {"bend": 1e-3})
    w = jnp.asarray(np.random.default_rng(5).normal(size=(5, 5, 3)))

    def loss(p):
        return jnp.sum(w * pipeline.simulate(sc, p).x[-1])

    p0 = {n: jnp.asarray(float(getattr(sc.material, n))) for n in names}
    f = jax.jit(jax.value_and_grad(loss))
    _, g = f(p0)
    for n in names:
        eps = 1e-5 * float(p0[n])
        fd = (float(f({**p0, n: p0[n] + eps})[0]) - float(f({**p0, n: p0[n] - eps})[0])) / (2 * eps)
        assert float(g[n]) == pytest.approx(fd, rel=1e-5, abs=1e-10), n


# ----------------------------------------------------------------------------- stability estimate


def _blows_up(net, sim, material, frames=15):
    s0 = _perturbed_state(net, 1e-4, seed=6)
    traj = jax.jit(lambda m: physics.rollout(net, sim, m, s0, num_frames=frames))(material)
    x = np.asarray(traj.x[-1])
    if not np.all(np.isfinite(x)):
        return True
    shape = (x - x.mean((0, 1))) - (np.asarray(net.rest) - np.asarray(net.rest).mean((0, 1)))
    return float(np.abs(shape).max()) > 1.0


def test_stability_estimate_is_quiet_on_the_stable_e400_run():
    """The issue's case: E = 400 at dt = 1/2400 on the default drape net (the old global estimate
    paired the lightest corner with the stiffest spring and warned)."""
    net = physics.grid_net(10, 13, (1.2, 0.9), center=(0.0, 1.0, 0.0))
    mat = physics.make_material(stretch=400.0, shear=100.0)
    sim = physics.make_sim(1 / 60, num_substeps=40)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        h_max = physics.check_stability(net, sim, mat)
    assert h_max > 1 / 2400
    # and the Provot default parameters at the reference engine's dt (needs the modal stage)
    net16 = physics.grid_net(16, 16, (0.6, 0.6), center=(0.0, 1.0, 0.0))
    ms = physics.make_mass_spring()
    assert physics.stable_substep(net16, sim, ms, method="gershgorin") < 1 / 2400
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert physics.check_stability(net16, sim, ms) > 1 / 2400


@pytest.mark.slow
@pytest.mark.parametrize("model", ["continuum", "provot"])
def test_stability_estimate_is_tight_both_ways(model):
    """Below 0.8 x the estimate the run holds without a warning; above 1.25 x it warns, raises
    with error=True, and really blows up."""
    net = physics.grid_net(8, 8, (0.5, 0.5), center=(0.0, 1.0, 0.0))
    if model == "continuum":
        mat = physics.make_material(stretch=2000.0, shear=500.0, bend=1e-3, damping=1e-4)
    else:
        mat = physics.make_mass_spring(k_struct=2000.0, k_shear=500.0, k_flex=100.0)
    est = physics.stable_substep(net, physics.make_sim(1 / 60), mat)
    gersh = physics.stable_substep(net, physics.make_sim(1 / 60), mat, method="gershgorin")
    assert gersh <= est * (1 + 1e-9)
    ok = physics.make_sim(0.8 * est * 10, num_substeps=10)
    bad = physics.make_sim(1.25 * est * 10, num_substeps=10)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        physics.check_stability(net, ok, mat)
    assert not _blows_up(net, ok, mat, frames=30)
    with pytest.warns(physics.StabilityWarning, match="stiffest mode"):
        physics.check_stability(net, bad, mat)
    with pytest.raises(ValueError, match="num_substeps >="):
        physics.check_stability(net, bad, mat, error=True)
    assert _blows_up(net, bad, mat, frames=30)


# ----------------------------------------------------------------------------- push-out offset


def test_push_out_offset_places_vertices_outside_the_drawn_sphere():
    sph = Sphere(jnp.zeros(3), jnp.asarray(1.0))
    p = jnp.array([[0.0, 0.5, 0.0], [0.0, 1.01, 0.0], [0.0, 1.05, 0.0], [0.0, 0.0, 0.0]])
    q = np.asarray(push_out_of_spheres(p, sph, offset=0.02))
    np.testing.assert_allclose(np.linalg.norm(q[:3], axis=1), [1.02, 1.02, 1.05])
    np.testing.assert_allclose(q[3], [0.0, 1.02, 0.0])
    np.testing.assert_allclose(np.asarray(push_out_of_spheres(p, sph))[1], [0.0, 1.01, 0.0])
    with pytest.raises(ValueError, match=r"push_out_offset.*\[0, inf\)"):
        push_out_of_spheres(p, sph, offset=-0.01)
    # on a surface: pushed vertices sit at r + offset, and the offset is differentiable
    net = physics.grid_net(4, 4, (0.6, 0.6), center=(0.0, 0.2, 0.0))
    ball = Sphere(jnp.array([0.0, 0.0, 0.0]), jnp.asarray(0.3))

    def lifted(o):
        pos = collide_surface(tessellate(net.rest, 2), ball, offset=o).positions
        return jnp.sum(pos[:, 1]), pos

    (_, pos), g = jax.jit(jax.value_and_grad(lifted, has_aux=True))(0.01)
    dist = np.linalg.norm(np.asarray(pos), axis=1)
    assert dist.min() == pytest.approx(0.31)
    assert float(g) > 0


# ----------------------------------------------------------------------------- config


def test_provot_config_example_loads_and_bad_combinations_name_the_key():
    from pathlib import Path

    from diffcloth import config as cfg
    from diffcloth.scene import load_scene

    root = Path(__file__).resolve().parents[1]
    sc = load_scene(root / "configs" / "drape_provot.toml", dtype=jnp.float64)
    assert isinstance(sc.material, physics.MassSpring) and sc.material.lumping == "uniform"
    assert float(sc.material.k_flex) == 20.0 and float(sc.material.air_damping) == 0.002
    assert sc.sim.friction_rule == "coulomb" and float(sc.sim.collision_margin) == 0.005
    assert sc.push_out_offset == 0.005
    bad = [
        ({"material": {"k_struct": 300.0}}, r"k_struct belong\(s\) to another model"),
        ({"material": {"model": "provot", "bend": 1e-3}}, r"bend belong\(s\) to another model"),
        ({"material": {"model": "provot", "k_flex": -1.0}}, r"k_flex = -1.0 .*\[0, inf\) N/m"),
        ({"material": {"mass_lumping": "uniform"}}, "needs model = 'provot'"),
        ({"material": {"model": "spring"}}, "model = 'spring'; allowed values"),
        ({"sim": {"friction_rule": "sticky"}}, "friction_rule = 'sticky'"),
        ({"sim": {"contact_thickness": 0.01, "collision_margin": 0.01}}, "same thing"),
        ({"render": {"push_out_offset": -0.1}}, r"push_out_offset = -0.1 is out of range"),
    ]
    for data, match in bad:
        with pytest.raises(cfg.ConfigError, match=match):
            cfg.parse_config(data)
    implicit = cfg.parse_config(
        {"material": {"model": "provot"}, "sim": {"integrator": "implicit"}}
    )
    with pytest.raises(cfg.ConfigError, match="symplectic"):
        cfg.build_physics(implicit)
    cont = cfg.build_physics(cfg.parse_config({"sim": {"contact_thickness": 0.01}}))
    assert isinstance(cont.material, physics.Material)
    assert float(cont.sim.collision_margin) == 0.01
