"""Mesh cloth against textile-lab tests (slow): the ASTM D1388 cantilever recovers the bending
rigidity that was set, warp and weft separately, and refining the mesh keeps a hanging square's
sag and a Cusick drape's coefficient.

Each test compiles one equilibrium program per mesh shape (the cloth is an argument, so meshes
of one topology share it) and solves several to many equilibria.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcloth.physics.mesh import (
    SolverSettings,
    check_equilibrium,
    disc,
    equilibrium,
    make_cloth,
    make_fabric,
    make_mesh_colliders,
    measure,
    rectangle,
)

pytestmark = pytest.mark.slow

G = 9.81
GRAVITY = jnp.asarray([0.0, -G, 0.0])


@pytest.fixture(scope="module", autouse=True)
def _solver_rank_promotion():
    """hessian._membrane_blocks broadcasts rank 5 against rank 2 (hessian.py:48), which
    conftest's jax_numpy_rank_promotion = "raise" refuses; allowed here until it is fixed."""
    with jax.numpy_rank_promotion("allow"):
        yield


# ------------------------------------------------------------------------------------ cantilever

TIP_ANGLE = 41.5  # degrees
# the strip for a unit overhang, scaled to each overhang (one topology: one compiled solve): an
# offset-row lattice of near-equilateral triangles whose rows run across the strip (so the ledge
# edge and the tip are straight rows of vertices), 24 edges along the overhang, half as wide as
# the overhang, held over 4 rows behind the ledge edge (a clamp: zero slope)
STRIP_EDGES, STRIP_WIDTH = 24, 0.5
STRIP_LEDGE = 4 / STRIP_EDGES


def _unit_strip():
    """(vertices, faces, uv) of the strip for an overhang of 1: the ledge row at x = 0."""
    m = rectangle(STRIP_WIDTH, 1.0 + STRIP_LEDGE, 1.0 / STRIP_EDGES, smooth=0)
    v = m.vertices
    x = np.stack([v[:, 2], v[:, 1], -v[:, 0]], axis=1)  # a quarter turn about y: rows across x
    uv = np.stack([-m.uv[:, 1], m.uv[:, 0]], axis=1)  # the same turn in the material plane
    rows = np.unique(np.round(x[:, 0], 9))
    ledge = rows[np.argmin(np.abs(rows - (rows[0] + STRIP_LEDGE)))]
    x[:, 0] -= ledge
    uv[:, 0] -= ledge
    scale = 1.0 / x[:, 0].max()
    return x * scale, m.faces, uv * scale


def _strip(overhang: float, warp_angle: float):
    """The strip along x, its ledge edge at x = 0 (pinned behind), `overhang` m beyond it, flat at
    y = 0."""
    x, faces, uv = _unit_strip()
    pinned = x[:, 0] <= 1e-9
    return make_cloth((x * overhang, faces, uv * overhang), pinned=pinned, warp_angle=warp_angle)


@pytest.fixture(scope="module")
def cantilever_solve():
    settings = SolverSettings(tol=1e-7, max_iters=300)
    return jax.jit(
        lambda cloth, fabric: equilibrium(
            cloth, fabric, cloth.rest, gravity=GRAVITY, settings=settings
        )  # fmt: skip
    )


def _tip_angle(solve, fabric, overhang, warp_angle) -> float:
    cloth = _strip(overhang, warp_angle)
    res = check_equilibrium(solve(cloth, fabric), f"cantilever, overhang {overhang:.5f} m")
    x = np.asarray(res.x)
    rest = np.asarray(cloth.rest)
    tip = x[rest[:, 0] >= rest[:, 0].max() - 1e-12].mean(axis=0)
    return math.degrees(math.atan2(-tip[1], tip[0]))


def _elastica_load() -> float:
    """w l^3 / B of an inextensible heavy elastica clamped horizontally whose tip chord is 41.5
    degrees below horizontal (B theta'' = -w (l - s) cos theta, theta(0) = 0, theta'(l) = 0).
    8.0042: Peirce's c = l / 2 (w l^3 / B = 8) is 0.05 % off the exact elastica."""
    from scipy.integrate import solve_ivp
    from scipy.optimize import brentq

    def tip(q, a):
        rhs = lambda s, y: [y[1], -q * (1 - s) * math.cos(y[0]), math.cos(y[0]), math.sin(y[0])]
        return solve_ivp(rhs, (0, 1), [0, a, 0, 0], rtol=1e-11, atol=1e-12).y[:, -1]

    def chord(q):
        a = brentq(lambda a: tip(q, a)[1], 0, q)
        y = tip(q, a)
        return math.degrees(math.atan2(y[3], y[2]))

    return brentq(lambda q: chord(q) - TIP_ANGLE, 4, 16)


@pytest.mark.parametrize("direction", ["warp", "weft"])
def test_cantilever_recovers_the_bending_rigidity(cantilever_solve, direction):
    """ASTM D1388 option A: the overhang at which the ledge-to-tip line reaches 41.5 degrees
    (bisection; one equilibrium from flat per overhang) gives c = overhang / 2 and G = w c^3."""
    fabric = make_fabric(density=0.2, stretch=500.0, shear=20.0, bend_warp=5e-5,
                         bend_weft=2e-5, bend_bias=3e-5)  # fmt: skip
    warp_angle, rigidity = {"warp": (0.0, 5e-5), "weft": (90.0, 2e-5)}[direction]
    w = float(fabric.density) * G
    guess = 2 * (rigidity / w) ** (1 / 3)
    lo, hi = 0.8 * guess, 1.25 * guess
    assert _tip_angle(cantilever_solve, fabric, lo, warp_angle) < TIP_ANGLE
    assert _tip_angle(cantilever_solve, fabric, hi, warp_angle) > TIP_ANGLE
    for _ in range(22):
        mid = 0.5 * (lo + hi)
        if _tip_angle(cantilever_solve, fabric, mid, warp_angle) < TIP_ANGLE:
            lo = mid
        else:
            hi = mid
    overhang = 0.5 * (lo + hi)
    measured = float(measure.cantilever_rigidity(overhang, float(fabric.density), G))
    error = measured / rigidity - 1
    exact_error = w * overhang**3 / _elastica_load() / rigidity - 1
    print(f"{direction}: overhang {overhang * 1e3:.3f} mm, G {measured:.4e} N m, "
          f"error {error:+.4%} (vs the exact elastica {exact_error:+.4%})")  # fmt: skip
    # measured (2026-11-28, JUMP_PENALTY 0.6): warp overhang 58.529 mm, G -1.65 % (-1.71 % against
    # the exact elastica); weft 43.130 mm, -1.62 % (-1.67 %); 2 x 30 s. Without the curvature-jump
    # term the strip was far too soft (tip line at 69 degrees at 0.8 x the expected overhang)
    assert abs(error) < 0.03
    assert abs(exact_error) < 0.02


# ------------------------------------------------------------------- resolution independence


def _hanging_square(h: float):
    """A 30 cm square in the xy-plane held along 5 cm of its top edge at each corner. (Held at
    single vertices, the drop would grow by F / (2 pi shear) ln 2 per halving of h, about 1 mm
    here: a point force's displacement is logarithmically infinite in a membrane; measured
    -8.5 % between h = 0.02 and 0.01.)"""
    m = rectangle(0.3, 0.3, h, smooth=0)
    uv = m.uv
    verts = np.stack([uv[:, 0], uv[:, 1], np.zeros(len(uv))], axis=1)
    pins = (verts[:, 1] >= 0.15 - 1e-9) & (np.abs(verts[:, 0]) >= 0.1 - 1e-9)
    return make_cloth((verts, m.faces, uv), pinned=pins)


def test_hanging_square_sag_is_resolution_independent():
    fabric = make_fabric(density=0.2, stretch_warp=50.0, stretch_weft=30.0, shear=10.0,
                         bend=1e-5)  # fmt: skip
    settings = SolverSettings(tol=1e-6, max_iters=400)
    out = {}
    for h in (0.02, 0.01):
        cloth = _hanging_square(h)
        res = check_equilibrium(
            jax.jit(lambda c: equilibrium(c, fabric, c.rest, gravity=GRAVITY, settings=settings))(cloth),
            f"hanging square h = {h}",
        )  # fmt: skip
        y = np.asarray(res.x)[:, 1]
        out[h] = (0.15 - y.min(), -0.15 - y.min(), cloth.num_vertices)  # sag, drop of the lowest
    (sag_c, drop_c, n_c), (sag_f, drop_f, n_f) = out[0.02], out[0.01]
    print(f"sag {sag_c:.5f} m ({n_c} vertices) vs {sag_f:.5f} m ({n_f}): "
          f"{sag_c / sag_f - 1:+.3%}; drop below rest {drop_c:.5f} vs {drop_f:.5f} m: "
          f"{drop_c / drop_f - 1:+.3%}")  # fmt: skip
    # measured: sag 0.30498 m (297 vertices) vs 0.30545 m (1134): -0.155 %. The elastic part
    # alone, the lowest point's drop below its rest position, differs much more: 4.98 vs 5.45 mm
    # (-8.7 %; -8.5 % with single-vertex pins): the coarse mesh is stiffer in the plane. Not
    # asserted (the criterion is the sag); 130 s.
    assert abs(sag_c / sag_f - 1) < 0.02


PEDESTAL = 0.09
SPECIMEN = 0.15
NODES = 8  # seeded fold count


def _cusick(h: float):
    m = disc(SPECIMEN, h, rings_at=(PEDESTAL,))
    x = m.vertices
    r = np.hypot(x[:, 0], x[:, 2])
    cloth = make_cloth(m, pinned=r <= PEDESTAL * (1 + 1e-9))
    # the start: the part beyond the pedestal turned down by 50 +- 25 degrees in NODES lobes
    theta = np.arctan2(-x[:, 2], x[:, 0])
    phi = np.radians(50.0 + 25.0 * np.cos(NODES * theta))
    out = np.clip(r - PEDESTAL, 0.0, None)
    rad = PEDESTAL + out * np.cos(phi)
    start = np.where(
        (r > PEDESTAL)[:, None],
        np.stack([rad * np.cos(theta), -out * np.sin(phi), -rad * np.sin(theta)], axis=1),
        x,
    )
    return cloth, m.faces, jnp.asarray(start)


def test_drape_coefficient_is_resolution_independent():
    fabric = make_fabric()  # mid-weight cotton: 0.2 kg/m^2, 500 N/m, bending 2e-5 N m
    pedestal = make_mesh_colliders(cylinders=[((0.0, -1.5e-3, 0.0), PEDESTAL, 0.3)])
    settings = SolverSettings(tol=1e-4, max_iters=400)
    out = {}
    for h in (0.012, 0.006):
        cloth, faces, start = _cusick(h)
        solve = jax.jit(lambda c, s: equilibrium(c, fabric, s, gravity=GRAVITY,
                                                 colliders=pedestal, settings=settings))  # fmt: skip
        res = check_equilibrium(solve(cloth, start), f"Cusick drape h = {h}")
        x = np.asarray(res.x)
        dc = measure.drape_coefficient(x, faces, SPECIMEN, PEDESTAL)
        nodes = measure.node_count(measure.outline_radius(x, faces))
        out[h] = (dc, nodes, cloth.num_vertices, int(res.iterations))
    (dc_c, n_c, v_c, it_c), (dc_f, n_f, v_f, it_f) = out[0.012], out[0.006]
    print(f"DC {dc_c.value:.4f} +- {dc_c.error:.1e} ({v_c} vertices, {n_c} nodes, {it_c} its) "
          f"vs {dc_f.value:.4f} +- {dc_f.error:.1e} ({v_f} vertices, {n_f} nodes, {it_f} its)")  # fmt: skip
    # measured (2026-11-28, JUMP_PENALTY 0.6): DC 0.7504 (630 vertices, 8 nodes, 127 iterations)
    # vs 0.7330 (2389 vertices, 8 nodes, 59 iterations): 0.017 apart; 100 s. Without the
    # curvature-jump term: 0.6474 vs 0.6923 (the coarse mesh softer); with weight 1: 0.7806 vs
    # 0.7498 (stiffer)
    assert n_c == n_f
    assert abs(dc_c.value - dc_f.value) < 0.02
    assert max(dc_c.error, dc_f.error) < 0.002
