"""Self-contact of the mesh cloth end to end (slow tier): a strip that falls and piles onto
itself stays free of self-intersection by an independent numpy triangle-triangle test, and the
gradient of one implicit step of a sheet folded onto itself (float64) matches central
differences."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from tri_intersections import intersecting_pairs, intersecting_pairs_bruteforce

from diffcloth.physics.mesh import (
    SolverSettings,
    implicit_step,
    make_cloth,
    make_fabric,
    make_mesh_colliders,
    mesh_rollout,
    rectangle,
)
from diffcloth.physics.mesh import selfcontact as sc
from diffcloth.physics.state import ClothState

G = jnp.array([0.0, -9.81, 0.0])


@pytest.fixture(scope="module", autouse=True)
def _solver_rank_promotion():
    """As tests/test_physics_mesh.py: hessian.py broadcasts across ranks."""
    with jax.numpy_rank_promotion("allow"):
        yield


def test_the_intersection_check_finds_a_crossing():
    faces = np.array([[0, 1, 2], [3, 4, 5]])
    flat = np.array([[0, 0, 0], [1, 0, 0], [0, 0, 1.0]])
    through = np.array([[0.2, -0.5, 0.2], [0.3, 0.5, 0.2], [0.2, 0.5, 0.3]])
    assert len(intersecting_pairs(np.vstack([flat, through]), faces)) == 1
    assert len(intersecting_pairs(np.vstack([flat, through + [0, 0.6, 0]]), faces)) == 0


def test_the_grid_intersection_check_equals_the_full_scan():
    """The grid candidates of `intersecting_pairs` miss no pair of the m^2 / 2 scan."""
    rng = np.random.default_rng(0)
    m = 300
    x = (rng.uniform(0, 1, (m, 1, 3)) + 0.08 * rng.normal(size=(m, 3, 3))).reshape(-1, 3)
    faces = np.arange(3 * m).reshape(m, 3)
    grid = {tuple(p) for p in np.sort(intersecting_pairs(x, faces), axis=1)}
    full = {tuple(p) for p in np.sort(intersecting_pairs_bruteforce(x, faces), axis=1)}
    assert len(full) > 50 and grid == full


def strip_scene(edge=0.03):
    """A 0.2 x 0.6 m strip hanging straight down (slightly waved), its foot 4 mm above a floor:
    released, it piles onto itself."""
    cloth = make_cloth(rectangle(0.2, 0.6, edge))
    r = np.asarray(cloth.rest)
    x = np.stack([r[:, 0], r[:, 2] + 0.304, 0.01 * np.sin(7 * r[:, 2])], 1)
    return cloth, x


@pytest.fixture(scope="module")
def strip_rollout():
    """20 frames (1/3 s) of the strip released onto a floor, self-contact on: (cloth, x (T, n,
    3)); frames after a step that did not converge are NaN (experiments/
    self_contact_strip_iters.py prints each step's Newton iterations)."""
    cloth, x = strip_scene()
    fabric = make_fabric("wang2011-gray-interlock")
    floor = make_mesh_colliders(planes=[((0, 1, 0), 0.0)])
    # capacity 24: in the pile the default 8 overflows the broad phase's candidate slots when a
    # step's reach widens the cells, and every such step is rejected
    s = sc.make_self_contact(2e-3, cloth=cloth, capacity=24)
    traj = jax.jit(lambda st: mesh_rollout(cloth, fabric, st, dt=1 / 60, num_frames=20,
                                           gravity=G, colliders=floor, self_contact=s,
                                           settings=SolverSettings(max_iters=300, tol=1e-2)))(
        ClothState(x=jnp.asarray(x), v=jnp.zeros(x.shape)))  # fmt: skip
    return cloth, np.asarray(traj.x)


@pytest.mark.slow
def test_a_strip_piling_onto_itself_never_intersects(strip_rollout):
    cloth, xs = strip_rollout
    finite = [k for k, xk in enumerate(xs) if np.all(np.isfinite(xk))]
    assert len(finite) >= 12  # well into the pile (contacts from frame 9)
    faces = np.asarray(cloth.faces)
    for k in finite:
        bad = intersecting_pairs(xs[k], faces)
        assert len(bad) == 0, f"frame {k}: triangles {bad[:5].tolist()} intersect"


@pytest.mark.slow
def test_every_frame_of_the_strip_pile_converges(strip_rollout):
    _, xs = strip_rollout
    assert np.all(np.isfinite(xs))
    assert xs[-1][:, 1].max() < 0.2  # it fell and piled up


def fold_scene(edge=0.01, gap=1.5e-3, length=0.06, width=0.03):
    """A strip folded flat onto itself at x = 0: the lower half (u <= 0) pinned flat on y = 0,
    the upper half reflected over it at height gap (within the contact thickness)."""
    mesh = rectangle(2 * length, width, edge)
    r = np.asarray(make_cloth(mesh).rest)
    u = r[:, 0]
    x = np.stack([-np.abs(u), np.where(u > 0, gap, 0.0), r[:, 2]], axis=1)
    return make_cloth(mesh, pinned=u <= 1e-9), x


@pytest.mark.slow
def test_folded_sheet_gradient_matches_central_differences():
    """One implicit step of the folded strip, its upper layer held off the lower one by the
    barrier (every top-bottom pair within the thickness: the contact set does not change
    under the perturbations); inputs: the bending stiffness and the pin positions. Friction
    between the layers is off: its lagged frame (normal force, normal) is taken at the start
    of the step without gradient, so it would differ from central differences in the pins."""
    cloth, x0 = fold_scene()
    fabric = make_fabric("wang2011-gray-interlock")
    s = sc.make_self_contact(2e-3, friction=0.0, cloth=cloth)
    settings = SolverSettings(tol=1e-10, max_iters=300)
    wts = jnp.asarray(np.linspace(1.0, 2.0, x0.shape[0]))

    def step(bend, pins):
        f = dataclasses.replace(fabric, bend_warp=bend, bend_weft=bend, bend_bias=bend)
        state = ClothState(x=pins, v=jnp.zeros(x0.shape))
        return implicit_step(cloth, f, state, 1 / 60, gravity=G, settings=settings,
                             self_contact=s)  # fmt: skip

    def loss(bend, pins):
        x = step(bend, pins).x
        return jnp.sum(wts * x[:, 1]) + jnp.sum(x[:, 0] ** 2)

    b0, pins = 0.2 * fabric.bend_warp, jnp.asarray(x0)  # a soft fabric: the fold stays shut
    x1 = np.asarray(jax.jit(step)(b0, pins).x)
    assert np.all(np.isfinite(x1))
    pairs = sc.find_pairs(cloth, s, jnp.asarray(x1), s.thickness)
    assert int(pairs.count) >= 5  # the layers are in contact
    assert len(intersecting_pairs(x1, np.asarray(cloth.faces))) == 0
    gb, gp = jax.jit(jax.grad(loss, argnums=(0, 1)))(b0, pins)
    lj = jax.jit(loss)
    hb = 1e-3 * float(b0)
    fd_b = (lj(b0 + hb, pins) - lj(b0 - hb, pins)) / (2 * hb)
    dirn = np.where(np.asarray(cloth.pinned)[:, None],
                    np.random.default_rng(0).normal(size=x0.shape), 0.0)  # fmt: skip
    hp = 1e-6
    fd_p = (lj(b0, pins + hp * dirn) - lj(b0, pins - hp * dirn)) / (2 * hp)
    print(f"contact pairs {int(pairs.count)}; bend: {float(gb):.6e} vs FD {float(fd_b):.6e}; pins: "
          f"{float(jnp.sum(gp * dirn)):.6e} vs FD {float(fd_p):.6e}")  # fmt: skip
    assert float(gb) == pytest.approx(float(fd_b), rel=1e-4)
    assert float(jnp.sum(gp * dirn)) == pytest.approx(float(fd_p), rel=1e-4)
