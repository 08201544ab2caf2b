"""Self-contact of the mesh cloth (physics/mesh/selfcontact*.py): the broad and narrow phase
against brute-force numpy distances, the capacity overflow report, the barrier's step filter,
and the solves with self-contact on."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcloth.physics.mesh import make_cloth, rectangle
from diffcloth.physics.mesh import selfcontact as sc

_FIND = jax.jit(sc.find_pairs)
_GAP = jax.jit(sc.gap)


@pytest.fixture(scope="module", autouse=True)
def _solver_rank_promotion():
    """As tests/test_physics_mesh.py: hessian.py broadcasts across ranks."""
    with jax.numpy_rank_promotion("allow"):
        yield


def _seg_point(p, a, b):
    ab = b - a
    t = np.clip(np.dot(p - a, ab) / max(np.dot(ab, ab), 1e-300), 0.0, 1.0)
    return np.linalg.norm(p - (a + t * ab))


def np_point_triangle(p, a, b, c):
    """Plane distance if the projection falls inside, else the nearest edge (plain numpy)."""
    n = np.cross(b - a, c - a)
    n = n / np.linalg.norm(n)
    h = np.dot(p - a, n)
    q = p - h * n
    inside = all(np.dot(np.cross(v1 - v0, q - v0), n) >= 0 for v0, v1 in ((a, b), (b, c), (c, a)))
    if inside:
        return abs(h)
    return min(_seg_point(p, a, b), _seg_point(p, b, c), _seg_point(p, c, a))


def np_edge_edge(p0, p1, q0, q1):
    """Min over the unit square of |P(s) - Q(t)|: the interior stationary point (if any) and
    the four sides (plain numpy)."""
    d1, d2, r = p1 - p0, q1 - q0, p0 - q0
    best = min(_seg_point(p0, q0, q1), _seg_point(p1, q0, q1), _seg_point(q0, p0, p1),
               _seg_point(q1, p0, p1))  # fmt: skip
    m = np.array([[d1 @ d1, -d1 @ d2], [-d1 @ d2, d2 @ d2]])
    if abs(np.linalg.det(m)) > 1e-14 * (d1 @ d1) * (d2 @ d2):
        s, t = np.linalg.solve(m, [-d1 @ r, d2 @ r])
        if 0 <= s <= 1 and 0 <= t <= 1:
            best = min(best, np.linalg.norm(p0 + s * d1 - q0 - t * d2))
    return best


def folded_sheet(edge=0.1, gap=0.02, width=0.6, height=0.5):
    """A rectangle folded over a cylinder of radius gap / 2 at x = 0 (two layers gap apart)."""
    cloth = make_cloth(rectangle(width, height, edge, center=(width / 2 - 0.15, 0.0, 0.0)))
    x = np.asarray(cloth.rest, np.float64).copy()
    r = gap / 2
    u = x[:, 0]
    th = np.clip(u / r, 0.0, np.pi)
    y = np.where(u <= 0, 0.0, r - r * np.cos(th))
    xx = np.where(u <= 0, u, r * np.sin(th))
    beyond = u > np.pi * r
    xx = np.where(beyond, -(u - np.pi * r), xx)
    y = np.where(beyond, 2 * r, y)
    x[:, 0], x[:, 1] = xx, y
    return cloth, x


def brute_pairs(cloth, x, radius):
    f = np.asarray(cloth.faces)
    e = np.asarray(cloth.edges)
    vt, ee = set(), set()
    for v in range(len(x)):
        for tri in f:
            if v in tri:
                continue
            if np_point_triangle(x[v], *x[tri]) < radius:
                vt.add((v, *tri))
    for i in range(len(e)):
        for j in range(i + 1, len(e)):
            if len({*e[i], *e[j]}) < 4:
                continue
            if np_edge_edge(*x[e[i]], *x[e[j]]) < radius:
                ee.add((*e[i], *e[j]))
    return vt, ee


def test_broad_phase_finds_the_brute_force_pairs():
    cloth, x = folded_sheet()
    x = x + np.random.default_rng(0).normal(0.0, 0.002, x.shape)
    radius = 0.03
    vt, ee = brute_pairs(cloth, x, radius)
    assert len(vt) > 20 and len(ee) > 20
    pairs = sc.check_pairs(_FIND(cloth, sc.make_self_contact(capacity=8), jnp.asarray(x),
                                         radius))  # fmt: skip
    idx, kind, valid = (np.asarray(a) for a in (pairs.idx, pairs.kind, pairs.valid))
    got_vt = {
        tuple(int(i) for i in r) for r, k, ok in zip(idx, kind, valid, strict=True) if ok and k == 0
    }
    got_ee = {
        tuple(int(i) for i in r) for r, k, ok in zip(idx, kind, valid, strict=True) if ok and k == 1
    }
    assert got_vt == vt
    assert got_ee == ee
    # the distances agree with numpy's
    d = np.asarray(jnp.linalg.norm(_GAP(jnp.asarray(x), pairs.idx, pairs.kind), axis=1))
    for r, k, ok, dist in zip(idx, kind, valid, d, strict=True):
        if ok:
            ref = np_point_triangle(*x[r]) if k == 0 else np_edge_edge(*x[r])
            assert dist == pytest.approx(ref, abs=1e-9)


def _all_pairs(cloth, x, radius):
    """Every pair closer than radius by a dense search over all vertex-face and edge-edge
    pairs (the closest-point weights are checked against numpy above)."""
    f, e = np.asarray(cloth.faces), np.asarray(cloth.edges)
    v, t = np.meshgrid(np.arange(len(x)), np.arange(len(f)), indexing="ij")
    vt = np.concatenate([v.reshape(-1, 1), f[t.reshape(-1)]], axis=1)
    vt = vt[np.all(vt[:, 1:] != vt[:, :1], axis=1)]
    i, j = np.triu_indices(len(e), 1)
    ee = np.concatenate([e[i], e[j]], axis=1)
    ee = ee[~np.any(ee[:, :2, None] == ee[:, None, 2:], axis=(1, 2))]
    out = set()
    for idx, k in ((vt, 0), (ee, 1)):
        d = np.linalg.norm(np.asarray(_GAP(jnp.asarray(x), jnp.asarray(idx, jnp.int32),
                                           jnp.full(len(idx), k, jnp.int32))), axis=1)  # fmt: skip
        out |= {(k, *(int(a) for a in r)) for r in idx[d < radius]}
    return out


def test_broad_phase_over_many_cells_finds_every_pair_once():
    """A crumpled 21 x 21 sheet searched at a radius far below its size (hundreds of cells,
    the edges' half neighbourhoods and hashed cells in use): the same pairs as a dense search,
    none twice."""
    cloth = make_cloth(rectangle(0.4, 0.4, 0.02))
    r = np.asarray(cloth.rest, np.float64)
    rng = np.random.default_rng(3)
    x = r.copy()
    x[:, 1] = 0.03 * np.sin(40 * r[:, 0]) * np.cos(30 * r[:, 2]) + 0.004 * rng.normal(size=len(r))
    x[:, 0] = r[:, 0] * (0.85 - 0.15 * np.tanh(r[:, 2] / 0.04)) + 0.003 * rng.normal(size=len(r))
    radius = 0.012
    pairs = sc.check_pairs(_FIND(cloth, sc.make_self_contact(capacity=16), jnp.asarray(x),
                                         radius))  # fmt: skip
    idx, kind, valid = (np.asarray(a) for a in (pairs.idx, pairs.kind, pairs.valid))
    rows = [(int(k), *(int(i) for i in r)) for r, k, ok in zip(idx, kind, valid, strict=True) if ok]
    assert len(rows) == len(set(rows)) == int(pairs.count)
    want = _all_pairs(cloth, x, radius)
    assert len(want) > 500
    assert set(rows) == want


def test_capacity_overflow_is_reported():
    cloth, x = folded_sheet()
    pairs = _FIND(cloth, sc.make_self_contact(capacity=1), jnp.asarray(x), 0.2)
    assert bool(pairs.overflow)
    with pytest.raises(ValueError, match="self_contact_capacity"):
        sc.check_pairs(pairs)


def _pair_set(pairs):
    idx, valid = np.asarray(pairs.idx), np.asarray(pairs.valid)
    return {tuple(int(i) for i in r) for r, ok in zip(idx, valid, strict=True) if ok}


def test_broad_phase_keeps_the_largest_radius_that_fits():
    """In a pile the pairs within the full radius overflow where a shorter radius fits: one
    broad phase returns the pairs of the largest radius that fits, as its own search finds."""
    cloth, x = folded_sheet()
    x = jnp.asarray(x)
    s = sc.make_self_contact(capacity=6)
    radii = jnp.asarray([0.1, 0.05, 0.03, 0.01])
    fits = [not bool(_FIND(cloth, s, x, r).overflow) for r in radii]
    assert not fits[0] and any(fits)  # the test's premise: the full radius overflows
    pairs, dist, radius = jax.jit(sc.find_pairs_fitting)(cloth, s, x, radii)
    assert not bool(pairs.overflow)
    assert float(radius) == pytest.approx(float(radii[fits.index(True)]))
    assert _pair_set(pairs) == _pair_set(_FIND(cloth, s, x, radius))
    assert bool(jnp.all(jnp.where(pairs.valid, dist < radius, jnp.isinf(dist))))
    # no radius fits: overflow, reported as before
    none = jax.jit(sc.find_pairs_fitting)(cloth, sc.make_self_contact(capacity=1), x, radii[:1])
    assert bool(none[0].overflow)


def test_settings_are_validated():
    with pytest.raises(ValueError, match="thickness"):
        sc.make_self_contact(-1.0)
    with pytest.raises(ValueError, match="capacity"):
        sc.make_self_contact(capacity=0)
    cloth, _ = folded_sheet()
    with pytest.raises(ValueError, match="triangle height"):
        sc.make_self_contact(0.08, cloth=cloth)


def test_barrier_is_c2_at_the_thickness_and_infinite_at_contact():
    from diffcloth.physics.mesh import selfcontact_energy as sce

    dhat = 1e-3
    b = lambda d: sce.barrier(d, dhat)
    for f, tol in ((b, 1e-18), (jax.grad(b), 1e-15), (jax.grad(jax.grad(b)), 1e-6)):
        assert abs(float(f(jnp.asarray(dhat * (1 - 1e-7))))) < tol  # -> 0 at d_hat
        assert float(f(jnp.asarray(dhat * 1.5))) == 0.0
    assert float(b(jnp.asarray(0.0))) == np.inf
    assert float(jax.grad(b)(jnp.asarray(1e-4))) < 0  # repulsive


def test_step_filter_stops_a_vertex_before_it_crosses_a_triangle():
    from diffcloth.physics.mesh import selfcontact_energy as sce

    tri = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    x = jnp.asarray(np.vstack([tri, [[0.2, 0.01, 0.2]]]))
    p = jnp.asarray(np.vstack([np.zeros((3, 3)), [[0.05, -0.03, 0.0]]]))  # through the face
    pairs = sc.Pairs(idx=jnp.array([[3, 0, 1, 2]], jnp.int32), kind=jnp.array([0], jnp.int32),
                     valid=jnp.array([True]), overflow=jnp.array(False), count=jnp.array(1))  # fmt: skip
    a = float(jax.jit(sce.step_bound)(x, p, pairs))
    assert 0.2 < a < 1.0 / 3.0  # crosses at alpha = 1/3; stops above a tenth of the gap
    assert float(x[3, 1] + a * p[3, 1]) >= 0.1 * 0.01 - 1e-12
    slide = jnp.asarray(np.vstack([np.zeros((3, 3)), [[0.04, 0.0, 0.02]]]))  # parallel: full step
    assert float(jax.jit(sce.step_bound)(x, slide, pairs)) == 1.0


def test_config_switch_is_off_by_default_and_validated():
    import tomllib

    from diffcloth.config import ConfigError, parse_config
    from diffcloth.config.cloth import build_mesh_physics

    with open("configs/tablecloth.toml", "rb") as fh:
        data = tomllib.load(fh)
    assert build_mesh_physics(parse_config(data)).sim.self_contact is None
    data.setdefault("sim", {}).update(self_contact=True, self_contact_thickness=1e-3)
    on = build_mesh_physics(parse_config(data)).sim.self_contact
    assert float(on.thickness) == pytest.approx(1e-3) and on.capacity == 8
    data["sim"]["self_contact_thickness"] = 1.0
    with pytest.raises(ConfigError, match="self_contact_thickness"):
        build_mesh_physics(parse_config(data))
    data["sim"]["self_contact"] = "yes"
    with pytest.raises(ConfigError, match="self_contact"):
        parse_config(data)
    with open("configs/hang.toml", "rb") as fh:
        grid = tomllib.load(fh)
    grid.setdefault("sim", {})["self_contact"] = True  # the grid net has its own (test_grid_)
    assert parse_config(grid).sim.self_contact
