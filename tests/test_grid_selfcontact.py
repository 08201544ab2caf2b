"""Self-contact of the grid control net (physics.grid_contact, issue 34): a sheet folded onto
itself lands on its lower half without any intersecting triangle pair of the control net (an
independent numpy check, tests/tri_intersections.py), and passes through it with self-contact
off; friction between the layers; the config switch for grid configs, through the CLI; the
broad phase's overflow named; the off path traces no self-contact op. The float64 central
difference check of the gradient and the implicit integrator are in the slow tier."""

import dataclasses
import functools
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from tri_intersections import intersecting_pairs, intersecting_pairs_bruteforce

from diffcloth import physics
from diffcloth.physics import grid_contact as gc

B, M, COLS, S = 5, 2, 5, 0.02  # flat rows of each layer, fold segments, columns, spacing (m)
THICK = 4e-3


def folded_sheet():
    """(net, x0): a 13 x 5 horizontal net, its first B + 1 rows pinned flat at y = 0, a half
    circle of M segments, and the rest back over the pinned half, 2 M S / pi above it."""
    rows = 2 * B + M + 1
    pins = np.array([[i, j] for i in range(B + 1) for j in range(COLS)])
    net = physics.grid_net(rows, COLS, ((COLS - 1) * S, (rows - 1) * S), pinned=pins)
    r = M * S / np.pi
    i = np.arange(rows, dtype=float)
    th = np.clip(i - B, 0, M) * np.pi / M
    z = np.where(i <= B, i * S, np.where(i <= B + M, B * S + r * np.sin(th), (2 * B + M - i) * S))
    y = np.where(i <= B, 0.0, np.where(i <= B + M, r * (1 - np.cos(th)), 2 * r))
    x = np.array(net.rest)
    x[:, :, 1] = y[:, None]
    x[:, :, 2] = z[:, None] + x[0, 0, 2]
    return net, jnp.asarray(x)


NET, X0 = folded_sheet()
FACES = np.asarray(gc.grid_triangles(NET).faces)
MAT = physics.make_material(stretch=20.0, shear=5.0)


def sim_with(contact=None, substeps=12, integrator="symplectic"):
    sim = physics.make_sim(1 / 60, num_substeps=substeps, integrator=integrator)
    return dataclasses.replace(sim, self_contact=contact)


@functools.cache
def _rollout(frames):
    return jax.jit(lambda sim, s: physics.rollout(NET, sim, MAT, s, num_frames=frames))


def start(v=None):
    return physics.ClothState(x=X0, v=jnp.zeros_like(X0) if v is None else v)


def crossing_frames(traj):
    xs = np.asarray(traj.x)
    return [k for k in range(xs.shape[0]) if len(intersecting_pairs(xs[k].reshape(-1, 3), FACES))]


def test_triangles_cover_the_net_and_the_thickness_is_checked():
    tri = gc.grid_triangles(NET)
    f, e = np.asarray(tri.faces), np.asarray(tri.edges)
    assert f.shape == (2 * (NET.rows - 1) * (NET.cols - 1), 3)
    edges = {tuple(sorted(p)) for p in e.tolist()}
    assert len(edges) == len(e)
    for a, b, c in f.tolist():  # every triangle side is an edge (the edge-edge pairs see it)
        assert {tuple(sorted(p)) for p in ((a, b), (b, c), (c, a))} <= edges
    # the rest net has no intersecting pair, and the numpy checks agree
    assert len(intersecting_pairs_bruteforce(np.asarray(X0).reshape(-1, 3), f)) == 0
    # shortest altitude: the quad's diagonal, S / sqrt(2)
    assert gc.min_rest_height(NET) == pytest.approx(S / np.sqrt(2))
    with pytest.raises(ValueError, match="half the shortest rest triangle height"):
        gc.make_grid_self_contact(0.008, net=NET)
    assert float(gc.make_grid_self_contact(THICK, net=NET).thickness) == THICK


def test_off_path_traces_no_self_contact_op():
    state = start()
    jaxpr = lambda sim: str(jax.make_jaxpr(lambda s: physics.step(NET, sim, MAT, s))(state))
    for integrator in ("symplectic", "implicit"):
        off = jaxpr(sim_with(None, 2, integrator))
        on = jaxpr(sim_with(gc.make_grid_self_contact(THICK, net=NET), 2, integrator))
        assert not re.search(r"\bsort\[", off)  # the broad phase's key sort
        assert re.search(r"\bsort\[", on)


def test_folded_sheet_lands_on_itself_without_intersections():
    frames = 16
    sc = gc.make_grid_self_contact(THICK, net=NET)
    on = _rollout(frames)(sim_with(sc), start())
    off = _rollout(frames)(sim_with(None), start())
    assert np.all(np.isfinite(np.asarray(on.x)))
    assert crossing_frames(on) == []
    assert len(crossing_frames(off)) >= 3  # the upper layer falls through the lower one
    top = np.asarray(on.x[-1, B + M + 1 :, :, 1])
    assert top.min() > 0.5 * THICK and top.max() < 2.5 * THICK  # resting on the lower layer
    assert np.asarray(off.x[-1, B + M + 1 :, :, 1]).max() < -0.02


_respond = jax.jit(gc.respond)


def test_impulse_stops_the_approach_and_friction_is_coulomb():
    """The upper layer moved to half the thickness above the lower (pinned) one, sliding at
    0.3 m/s and approaching at 0.5 m/s: the impulses stop its approach, and friction between
    the layers follows the colliders' Coulomb rule (the tangential speed drops by mu x the
    normal speed change, to zero at most)."""
    x = X0.at[B + M + 1 :, :, 1].set(0.5 * THICK).reshape(-1, 3)
    v = jnp.zeros_like(X0).at[B + M + 1 :, :, :2].set(jnp.array([0.3, -0.5])).reshape(-1, 3)
    free = ~NET.pinned.reshape(-1)
    inv_mass = jnp.where(free, 1.0 / (MAT.density * NET.area.reshape(-1)), 0.0)
    h = 1 / 1200
    top = np.zeros((NET.rows, NET.cols), bool)
    top[B + M + 2 :, 1:-1] = True  # interior of the upper layer
    top = top.reshape(-1)
    out = {}
    for mu in (0.0, 1.0, 10.0):
        sc = gc.make_grid_self_contact(THICK, net=NET, friction=mu, capacity=24)
        pairs = jax.jit(gc.contact_pairs)(NET, sc, x, gc.reach(NET, sc, v, h))
        assert not bool(pairs.overflow) and int(pairs.count) > 0
        out[mu] = np.asarray(_respond(NET, sc, pairs, x, v, inv_mass, MAT.friction, h))[top]
        assert np.all(out[mu][:, 1] > -0.02)  # the approach (0.5 m/s) all but stopped
    assert np.allclose(out[0.0][:, 0], 0.3)  # no friction: the tangential speed is kept
    # sliding: the speed drops by mu x the normal speed change, mu = 0.3 (material) x 1.0
    assert np.allclose(out[1.0][:, 0], 0.3 - 0.3 * 0.5, atol=0.01)
    # sticking (mu = 3): stopped (up to the mix of a point's pairs), not reversed
    assert np.all(np.abs(out[10.0][:, 0]) < 0.01)


def test_overflow_is_reported_with_the_setting_to_raise():
    """The broad phase's overflow flag, and the note a failed rollout gets (`checked_rollout`,
    `diffcloth simulate` / `render`; the CLI run is in the config test)."""
    sc = gc.make_grid_self_contact(THICK, net=NET, capacity=1)
    pairs = jax.jit(gc.contact_pairs)(
        NET, sc, X0.reshape(-1, 3), jnp.full(NET.rows * NET.cols, 0.01)
    )
    assert bool(pairs.overflow)
    with pytest.raises(ValueError, match=r"self_contact_capacity"):
        gc.check_overflow(NET, sim_with(sc), X0)
    assert "raise SelfContact.capacity ([sim] self_contact_capacity)" in gc.failure_note(
        NET, sim_with(sc), X0
    )
    fits = sim_with(gc.make_grid_self_contact(THICK, net=NET))
    gc.check_overflow(NET, fits, X0)  # capacity 16: no overflow at rest
    assert "self_contact_capacity" in gc.failure_note(NET, fits, X0)  # the in-frame hint
    assert gc.failure_note(NET, sim_with(None), X0) == ""


GRID_TOML = """
[net]
rows = 6
cols = 6
width = 0.1
height = 0.1
center = [0.0, 0.05, 0.0]
plane = "xz"
pinned = "none"

[material]
stretch = 50.0
shear = 12.5

[sim]
dt = 0.0166666666667
num_frames = 3
num_substeps = 20
self_contact = true
self_contact_thickness = 0.003
{extra}
"""


def test_config_switch_runs_a_grid_config_through_the_cli(tmp_path, capsys):
    from diffcloth.cli import main
    from diffcloth.config import ConfigError, build_physics, load_config

    cfg = tmp_path / "grid.toml"
    cfg.write_text(GRID_TOML.format(extra=""))
    sim = build_physics(load_config(cfg)).sim
    assert sim.self_contact is not None and sim.self_contact.capacity == 16
    assert float(sim.self_contact.thickness) == pytest.approx(0.003)
    off = tmp_path / "off.toml"
    off.write_text(GRID_TOML.format(extra="").replace("self_contact = true", ""))
    assert build_physics(load_config(off)).sim.self_contact is None  # off by default
    thick = tmp_path / "thick.toml"
    thick.write_text(GRID_TOML.format(extra="").replace("0.003", "0.02"))
    with pytest.raises(ConfigError, match="self_contact_thickness"):
        build_physics(load_config(thick))
    assert main(["simulate", str(cfg), "--out", str(tmp_path / "o")]) == 0
    x = np.load(tmp_path / "o" / "trajectory.npz")["x"]
    assert x.shape == (3, 6, 6, 3) and np.all(np.isfinite(x))
    small = tmp_path / "small.toml"
    small.write_text(GRID_TOML.format(extra="self_contact_capacity = 1"))
    capsys.readouterr()
    assert main(["simulate", str(small), "--out", str(tmp_path / "o2")]) == 1
    assert "self_contact_capacity" in capsys.readouterr().err


@pytest.mark.slow
def test_implicit_integrator_keeps_the_fold_free_of_intersections():
    sc = gc.make_grid_self_contact(THICK, net=NET)
    traj = _rollout(24)(sim_with(sc, 4, "implicit"), start())
    assert np.all(np.isfinite(np.asarray(traj.x)))
    assert crossing_frames(traj) == []
    top = np.asarray(traj.x[-1, B + M + 1 :, :, 1])
    assert top.min() > 0.5 * THICK and top.max() < 3 * THICK


@pytest.mark.slow
def test_gradient_matches_central_differences_on_the_resting_fold():
    """float64: 3 frames from the settled fold (the upper layer resting on the lower one, its
    contact set fixed under the perturbation), friction between the layers off (the
    Coulomb rule's stick-slip switch is a kink); inputs: the bend stiffness and a lift of the
    pinned lower layer (pin positions)."""
    assert X0.dtype == jnp.float64
    sc = gc.make_grid_self_contact(THICK, net=NET, friction=0.0)
    sim = sim_with(sc)
    traj = _rollout(30)(sim, start())
    assert crossing_frames(traj) == []
    s0 = physics.ClothState(x=traj.x[-1], v=traj.v[-1])
    pairs = gc.contact_pairs(NET, sc, s0.x.reshape(-1, 3), jnp.zeros(NET.rows * NET.cols))
    assert int(pairs.count) > 20  # pairs closer than the thickness: the layers touch
    w = jnp.asarray(np.random.default_rng(0).normal(size=X0.shape))
    up = jnp.zeros_like(X0).at[..., 1].set(1.0)

    def loss(bend, lift):
        m = dataclasses.replace(MAT, bend=bend)
        st = s0
        for _ in range(3):
            st = physics.step(NET, sim, m, st, pin_target=s0.x + lift * up)
        return jnp.sum(w * st.x)

    f = jax.jit(loss)
    b0, l0 = MAT.bend, jnp.asarray(0.0)
    gb, gl = jax.jit(jax.grad(loss, argnums=(0, 1)))(b0, l0)
    eb, el = 1e-5 * float(b0), 1e-8
    fd_b = (f(b0 + eb, l0) - f(b0 - eb, l0)) / (2 * eb)
    fd_l = (f(b0, l0 + el) - f(b0, l0 - el)) / (2 * el)
    assert float(gb) == pytest.approx(float(fd_b), rel=1e-4)
    assert float(gl) == pytest.approx(float(fd_l), rel=1e-4)
