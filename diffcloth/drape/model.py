"""The simulated drape test: a disc specimen held on a round pedestal, its rest shapes from seeded
imperfect starts, and differentiable, rotation-invariant measures of a rest shape.

A symmetric disc on a pedestal is multistable: it settles into 4 to 12 folds ("nodes") whose
count and orientation depend on small imperfections. `imperfect_start` makes such imperfections
reproducible (a seed, or one fold mode k); `DrapeModel.solve` finds the rest shape from there
(`physics.mesh.equilibrium`: Newton on the total energy, gradients by the implicit function
theorem). The measures read the projected rim of the specimen, a closed polygon that is the
drape's outline (the hanging cloth lies inside it): its shoelace area gives the drape
coefficient, its radius r(phi) the harmonic spectrum, both smooth functions of the positions.

    model = make_drape_model(CUSICK, edge=0.011)
    fabric = make_fabric("wang2011-gray-interlock", dtype=jnp.float64)
    res = model.solve(fabric, imperfect_start(model, seed=3))
    dc, spectrum = rim_dc(model, res.x), rim_spectrum(model, res.x)
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from diffcloth.drape.images import CUSICK, DrapeGeometry, check_geometry
from diffcloth.physics.mesh import (
    ClothMesh,
    MeshColliders,
    SolverSettings,
    disc,
    equilibrium,
    make_cloth,
    make_mesh_colliders,
)

__all__ = [
    "DEFAULT_EDGE",
    "DrapeModel",
    "imperfect_start",
    "make_drape_model",
    "rim_dc",
    "rim_polar",
    "rim_spectrum",
]

#: m, the default target edge length of the simulated specimen (about 690 vertices for a 0.15 m
#: radius: a drape in one to a few seconds)
DEFAULT_EDGE = 0.011
GRAVITY = (0.0, -9.81, 0.0)


@dataclasses.dataclass(frozen=True)
class DrapeModel:
    """A simulated drape tester (static description; not a pytree).

    Attributes:
      geometry: the specimen and pedestal radii.
      edge: target edge length of the triangulation, m.
      cloth: the disc (centre held within the pedestal radius), resting `thickness` above the
        pedestal top at y = 0.
      faces: (m, 3) numpy, for measurements and images.
      rim: (r,) numpy vertex indices of the specimen's edge, counter-clockwise seen from above.
      colliders: the pedestal (a capped cylinder, top at y = 0).
      settings: the equilibrium solver's settings.
      solve: jitted (fabric, x_start (n, 3)) -> EquilibriumResult (differentiable in fabric).
    """

    geometry: DrapeGeometry
    edge: float
    cloth: ClothMesh
    faces: np.ndarray
    rim: np.ndarray
    colliders: MeshColliders
    settings: SolverSettings
    solve: Callable

    @property
    def num_vertices(self) -> int:
        return self.cloth.num_vertices


def make_drape_model(
    geometry: DrapeGeometry = CUSICK,
    *,
    edge: float = DEFAULT_EDGE,
    thickness: float = 1e-3,
    max_iters: int = 400,
    tol: float = 1e-3,
    dtype=jnp.float64,
) -> DrapeModel:
    """A drape tester for `geometry` with a disc of target edge length `edge` (m, at most a
    quarter of the hanging width R - r_pedestal). thickness: the pedestal's contact layer, m.
    max_iters, tol: `SolverSettings`. Raises ValueError naming a bad value."""
    g = check_geometry(geometry)
    hang = g.specimen_radius - g.pedestal_radius
    if not (math.isfinite(edge) and 0 < edge <= hang / 4):
        raise ValueError(f"edge: must be in (0, {hang / 4:.4g}] m (a quarter of the hanging "
                         f"width), got {edge!r}")  # fmt: skip
    if not (math.isfinite(thickness) and 0 < thickness <= edge):
        raise ValueError(f"thickness: must be in (0, edge = {edge}] m, got {thickness!r}")
    mesh = disc(g.specimen_radius, edge, rings_at=(g.pedestal_radius,),
                center=(0.0, thickness, 0.0))  # fmt: skip
    v = mesh.vertices
    r = np.hypot(v[:, 0], v[:, 2])
    cloth = make_cloth(mesh, pinned=r <= g.pedestal_radius * (1 + 1e-9), dtype=dtype)
    rim = np.flatnonzero(r >= g.specimen_radius * (1 - 1e-6))
    # counter-clockwise seen from above (+y): the plane axes (x, -z) of `measure.projection_axes`
    rim = rim[np.argsort(np.arctan2(-v[rim, 2], v[rim, 0]))]
    cols = make_mesh_colliders(cylinders=[((0.0, 0.0, 0.0), g.pedestal_radius, 0.3)],
                               thickness=thickness, dtype=dtype)  # fmt: skip
    settings = SolverSettings(max_iters=int(max_iters), tol=float(tol))
    grav = jnp.asarray(GRAVITY, dtype)
    solve = jax.jit(lambda fabric, x0: equilibrium(cloth, fabric, x0, gravity=grav,
                                                   colliders=cols, settings=settings))  # fmt: skip
    return DrapeModel(g, float(edge), cloth, np.asarray(mesh.faces), rim, cols, settings, solve)


def imperfect_start(
    model: DrapeModel,
    seed: int = 0,
    *,
    mode: int | None = None,
    amplitude: float = 2e-3,
    harmonics: tuple[int, int] = (2, 12),
) -> np.ndarray:
    """The flat specimen with a small, reproducible out-of-plane imperfection of the hanging part
    (n, 3) m: dy = amplitude s^2 w(phi), s = (r - r_p) / (R - r_p), where w is cos(mode phi +
    random phase) if `mode` is given (seeds that many folds) and otherwise a random sum of the
    harmonics in `harmonics` (inclusive) with Gaussian coefficients, scaled to unit RMS (the
    specimen chooses its own node count). amplitude: m at the rim (1-5 mm is a hand-laid
    specimen's unevenness)."""
    if not (math.isfinite(amplitude) and 0 <= amplitude <= 0.1 * model.geometry.specimen_radius):
        raise ValueError(f"amplitude: must be in [0, {0.1 * model.geometry.specimen_radius}] m, "
                         f"got {amplitude!r}")  # fmt: skip
    rng = np.random.default_rng(seed)
    x = np.asarray(model.cloth.rest, np.float64).copy()
    r = np.hypot(x[:, 0], x[:, 2])
    phi = np.arctan2(-x[:, 2], x[:, 0])
    g = model.geometry
    s = np.clip((r - g.pedestal_radius) / (g.specimen_radius - g.pedestal_radius), 0.0, None)
    if mode is not None:
        if not (isinstance(mode, int | np.integer) and 1 <= mode <= 24):
            raise ValueError(f"mode: must be an integer fold count in [1, 24], got {mode!r}")
        w = np.cos(mode * phi + rng.uniform(0, 2 * np.pi))
    else:
        lo, hi = harmonics
        if not (1 <= lo <= hi <= 24):
            raise ValueError(f"harmonics: need 1 <= low <= high <= 24, got {harmonics!r}")
        ks = np.arange(lo, hi + 1)
        a = rng.normal(size=(ks.size, 2))
        w = (a[:, :1] * np.cos(ks[:, None] * phi) + a[:, 1:] * np.sin(ks[:, None] * phi)).sum(0)
        w = w / np.sqrt(0.5 * np.sum(a**2))
    x[:, 1] += amplitude * s**2 * w
    return x


def rim_polar(model: DrapeModel, x):
    """The projected rim in polar form about the pedestal axis: (rho (r,) m, phi (r,) rad,
    unwrapped and increasing for a star-shaped outline), phi from +x towards -z (counter-clockwise
    seen from above). Shapes: x (n, 3) m."""
    p = x[model.rim]
    rho = jnp.hypot(p[:, 0], p[:, 2])
    phi = jnp.arctan2(-p[:, 2], p[:, 0])
    # unwrap: consecutive differences in (-pi, pi]
    d = jnp.diff(phi)
    d = d - 2 * jnp.pi * jnp.round(d / (2 * jnp.pi))
    phi = jnp.concatenate([phi[:1], phi[0] + jnp.cumsum(d)])
    return rho, phi


def rim_dc(model: DrapeModel, x):
    """The drape coefficient from the shoelace area of the projected rim polygon (the shadow, as
    long as no cloth projects outside its own rim): (A - A_p) / (A_s - A_p) with the nominal
    circle areas. Shapes: x (n, 3) m -> ()."""
    p = x[model.rim]
    u, v = p[:, 0], -p[:, 2]
    area = 0.5 * jnp.sum(u * jnp.roll(v, -1) - jnp.roll(u, -1) * v)
    g = model.geometry
    a_p = math.pi * g.pedestal_radius**2
    return (area - a_p) / (math.pi * g.specimen_radius**2 - a_p)


def rim_spectrum(model: DrapeModel, x, max_harmonic: int = 16):
    """Rotation-invariant spectrum of the projected rim radius r(phi): for k = 1..max_harmonic,
    2 |c_k| / c_0 with c_k = (1 / 2 pi) sum_i r_i exp(-i k phi_i) dphi_i (the trapezoid rule on
    the rim's own angles), as `outline.outline_spectrum` defines it for images.
    Shapes: x (n, 3) m -> (max_harmonic,)."""
    c = rim_harmonics(model, x, max_harmonic)
    return 2 * jnp.abs(c[1:]) / c[0].real


def rim_harmonics(model: DrapeModel, x, max_harmonic: int = 16):
    """Complex Fourier coefficients c_0..c_K of the projected rim radius r(phi) (phase: phi from
    +x towards -z). Shapes: x (n, 3) m -> (max_harmonic + 1,) complex."""
    rho, phi = rim_polar(model, x)
    span = phi[-1] - phi[0]
    # dphi per vertex: half the gaps to both neighbours, the closing gap from the full turn
    gap = jnp.diff(phi, append=phi[:1] + jnp.where(span > 0, 2 * jnp.pi, -2 * jnp.pi))
    w = 0.5 * (gap + jnp.roll(gap, 1)) / (2 * jnp.pi)
    k = jnp.arange(max_harmonic + 1)
    return jnp.sum((rho * w)[None, :] * jnp.exp(-1j * k[:, None] * phi[None, :]), axis=1)
