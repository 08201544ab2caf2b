"""The classic Provot mass-spring cloth, as an alternative to the continuum-scaled `Material`.

Use a `MassSpring` wherever a `Material` goes (`physics.step`, `rollout`, a Scene's `material`): the
symplectic integrator, pins and colliders are shared; only the forces and the node masses differ.
Every spring class has its own stiffness (N/m) and dashpot (N s/m), independent of the spacing, as
in Provot (1995) and most textbook and engine implementations, so parameters can be matched to
another engine or a paper directly:

    structural  (i, j)-(i, j+1), (i, j)-(i+1, j)        k_struct, d_struct
    shear       (i, j)-(i+1, j+1), (i, j+1)-(i+1, j)    k_shear,  d_shear
    flexion     (i, j)-(i, j+2), (i, j)-(i+2, j)        k_flex,   d_flex

Spring (a, b), e = x_b - x_a, L = |e|, n = e / L: force on a (k (L - L0) + d (v_b - v_a).n) n, the
opposite on b; zero for L = 0. Air: -air_damping (v - wind) per node. Gravity m g. Masses are
uniform (total area * density / nodes) or area-lumped (density * net.area). Border springs are not
scaled.
See docs/physics.md for every modelling choice.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from diffcloth.representable import check_representable

LUMPINGS = ("uniform", "area")

# name -> (lower bound, lower bound inclusive?, unit, default)
MASS_SPRING_FIELDS: dict[str, tuple[float, bool, str, float]] = {
    "k_struct": (0.0, False, "N/m", 400.0),
    "k_shear": (0.0, True, "N/m", 100.0),
    "k_flex": (0.0, True, "N/m", 20.0),
    "d_struct": (0.0, True, "N s/m", 0.05),
    "d_shear": (0.0, True, "N s/m", 0.02),
    "d_flex": (0.0, True, "N s/m", 0.005),
    "air_damping": (0.0, True, "N s/m", 0.002),
    "density": (0.0, False, "kg/m^2", 0.2),
    "friction": (0.0, True, "1", 0.3),
}

#: (row offset, column offset, class) of the six spring sets; classes 0 struct, 1 shear, 2 flex
SPRING_SETS = ((0, 1, 0), (1, 0, 0), (1, 1, 1), (1, -1, 1), (0, 2, 2), (2, 0, 2))
_CLASSES = ("struct", "shear", "flex")


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class MassSpring:
    """Provot mass-spring parameters (scalar arrays, all differentiable; `lumping` is static).

    Attributes:
      k_struct, k_shear, k_flex: stiffness of each structural, shear and flexion spring, N/m.
      d_struct, d_shear, d_flex: dashpot of each spring along its direction, N s/m.
      air_damping: linear air damping per node, N s/m (force -air_damping (v - wind)).
      density: areal density, kg/m^2 (total mass = density * net area).
      friction: Coulomb coefficient against colliders.
      lumping: "uniform" (every node the same mass) or "area" (density * the node's lumped area).
    """

    k_struct: jax.Array
    k_shear: jax.Array
    k_flex: jax.Array
    d_struct: jax.Array
    d_shear: jax.Array
    d_flex: jax.Array
    air_damping: jax.Array
    density: jax.Array
    friction: jax.Array
    lumping: str = dataclasses.field(default="uniform", metadata={"static": True})

    # duck-typed hooks used by physics.forces.node_mass / _total_forces
    def node_mass(self, net):
        """(rows, cols) node masses, kg."""
        return node_mass(net, self)

    def total_forces_planar(self, net, x, v, gravity, wind):
        """Springs, dashpots, air damping and gravity on planar (3, rows, cols) x, v, N."""
        return _total_forces(net, self, x, v, gravity, wind)


def mass_spring_range(name: str) -> str:
    """Allowed range of a MassSpring field as text, e.g. "(0, inf)".

    Shapes: none (a field name -> its range as text).
    """
    lo, inclusive, _, _ = MASS_SPRING_FIELDS[name]
    return f"{'[' if inclusive else '('}{lo:g}, inf)"


def check_mass_spring_value(name: str, value) -> float:
    """Validate one field; returns it as float. Raises ValueError naming field and range.

    Shapes: value () -> Python float.
    """
    if name not in MASS_SPRING_FIELDS:
        raise ValueError(
            f"mass-spring material: unknown field {name!r}; allowed: {sorted(MASS_SPRING_FIELDS)}"
        )
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != ():
        raise ValueError(f"material.{name}: must be a scalar, got shape {arr.shape}")
    v = float(arr)
    lo, inclusive, unit, _ = MASS_SPRING_FIELDS[name]
    if not (math.isfinite(v) and (v >= lo if inclusive else v > lo)):
        raise ValueError(
            f"material.{name} = {v!r} is out of range; allowed range "
            f"{mass_spring_range(name)} {unit}"
        )
    return v


def make_mass_spring(dtype=None, *, lumping: str = "uniform", **fields) -> MassSpring:
    """Validated constructor; unspecified fields take the defaults of MASS_SPRING_FIELDS.

    >>> ms = make_mass_spring(k_struct=400.0, k_flex=20.0, lumping="area")
    >>> float(ms.k_struct), ms.lumping
    (400.0, 'area')
    """
    if lumping not in LUMPINGS:
        raise ValueError(f"mass_lumping: must be one of {LUMPINGS}, got {lumping!r}")
    unknown = set(fields) - set(MASS_SPRING_FIELDS)
    if unknown:
        raise ValueError(
            f"mass-spring material: unknown field(s) {sorted(unknown)}; "
            f"allowed: {sorted(MASS_SPRING_FIELDS)}"
        )
    dtype = dtype or jnp.zeros(()).dtype
    values = {}
    for name, (_, _, _, default) in MASS_SPRING_FIELDS.items():
        value = check_mass_spring_value(name, fields.get(name, default))
        check_representable(f"material.{name}", value, dtype)  # in the run's dtype
        values[name] = jnp.asarray(value, dtype)
    return MassSpring(**values, lumping=lumping)


def validate_mass_spring(ms: MassSpring) -> MassSpring:
    """Eagerly check a concrete MassSpring; returns it unchanged.

    Shapes: MassSpring leaves () each, unchanged.
    """
    for name in MASS_SPRING_FIELDS:
        check_mass_spring_value(name, np.asarray(getattr(ms, name)))
    if ms.lumping not in LUMPINGS:
        raise ValueError(f"mass_lumping: must be one of {LUMPINGS}, got {ms.lumping!r}")
    return ms


def node_mass(net, ms: MassSpring):
    """(rows, cols) node masses in kg (differentiable in density)."""
    if ms.lumping == "uniform":
        total = jnp.sum(net.area)
        return jnp.broadcast_to(ms.density * total / (net.rows * net.cols), net.area.shape)
    return ms.density * net.area


# ---------------------------------------------------------------------------------------------
# forces on planar (3, rows, cols) arrays, each spring set as a pair of shifted slices


def _slices(di: int, dj: int, rows: int, cols: int):
    """Slices of the first (a) and second (b) node of the springs with offset (di >= 0, dj)."""
    a = (slice(0, rows - di), slice(max(0, -dj), cols - max(0, dj)))
    b = (slice(di, rows), slice(max(0, dj), cols - max(0, -dj)))
    return a, b


def _pads(di: int, dj: int):
    """jnp.pad widths that put a per-spring array back on the first (a) and second (b) nodes."""
    pa = ((0, 0), (0, di), (max(0, -dj), max(0, dj)))
    pb = ((0, 0), (di, 0), (max(0, dj), max(0, -dj)))
    return pa, pb


def rest_lengths(net) -> tuple:
    """Rest length (rows - di, cols - |dj|) of each of the six spring sets (SPRING_SETS), m."""
    r = jnp.moveaxis(net.rest, -1, 0)
    out = []
    for di, dj, _ in SPRING_SETS:
        if net.rows <= di or net.cols <= abs(dj):
            out.append(jnp.zeros((0, 0), r.dtype))
            continue
        a, b = _slices(di, dj, net.rows, net.cols)
        e = r[(slice(None),) + b] - r[(slice(None),) + a]
        out.append(jnp.sqrt(jnp.sum(e * e, axis=0)))
    return tuple(out)


def _spring_scalar(e, dv, rest, k, d):
    """Per-spring s with force s * e on the first node; 0 for a zero-length spring."""
    sq = jnp.sum(e * e, axis=0)
    ok = sq > 0
    safe = jnp.where(ok, sq, 1.0)
    length = jnp.sqrt(safe)
    mag = k * (length - rest) + d * jnp.sum(dv * e, axis=0) / length
    return jnp.where(ok, mag / length, 0.0)


def _coefs(ms: MassSpring):
    return (
        (ms.k_struct, ms.d_struct),
        (ms.k_shear, ms.d_shear),
        (ms.k_flex, ms.d_flex),
    )


def spring_forces_planar(net, ms: MassSpring, x, v):
    """Spring + dashpot forces (3, rows, cols), N, on planar x, v."""
    R, C = net.rows, net.cols
    rests = rest_lengths(net)
    coefs = _coefs(ms)
    f = jnp.zeros_like(x)
    for (di, dj, cls), rest in zip(SPRING_SETS, rests, strict=True):
        if R <= di or C <= abs(dj):
            continue
        a, b = _slices(di, dj, R, C)
        a, b = (slice(None),) + a, (slice(None),) + b
        k, d = coefs[cls]
        fa = _spring_scalar(x[b] - x[a], v[b] - v[a], rest, k, d)[None] * (x[b] - x[a])
        pa, pb = _pads(di, dj)
        f = f + jnp.pad(fa, pa) - jnp.pad(fa, pb)
    return f


def _total_forces(net, ms: MassSpring, x, v, gravity, wind):
    mass = node_mass(net, ms)
    f = spring_forces_planar(net, ms, x, v)
    f = f - ms.air_damping * (v - wind[:, None, None])
    return f + mass[None] * gravity[:, None, None]


# public (rows, cols, 3) forms


def spring_forces(net, ms: MassSpring, x, v):
    """Structural, shear and flexion spring forces with dashpots, N, (rows, cols, 3)."""
    p = lambda a: jnp.moveaxis(a, -1, 0)
    return jnp.moveaxis(spring_forces_planar(net, ms, p(x), p(v)), 0, -1)


def total_forces(net, ms: MassSpring, x, v, gravity, wind):
    """Springs, dashpots, air damping and gravity, N, (rows, cols, 3)."""
    p = lambda a: jnp.moveaxis(jnp.asarray(a), -1, 0)
    return jnp.moveaxis(_total_forces(net, ms, p(x), p(v), jnp.asarray(gravity),
                                      jnp.asarray(wind)), 0, -1)  # fmt: skip


def elastic_energy(net, ms: MassSpring, x):
    """sum 1/2 k (L - L0)^2 over all springs, J; minus its gradient is `spring_forces` at v = 0.

    Shapes: x (rows, cols, 3) m -> () J.
    """
    xp = jnp.moveaxis(x, -1, 0)
    coefs = _coefs(ms)
    e = 0.0
    for (di, dj, cls), rest in zip(SPRING_SETS, rest_lengths(net), strict=True):
        if net.rows <= di or net.cols <= abs(dj):
            continue
        a, b = _slices(di, dj, net.rows, net.cols)
        d = xp[(slice(None),) + b] - xp[(slice(None),) + a]
        length = jnp.sqrt(jnp.sum(d * d, axis=0))
        e = e + 0.5 * coefs[cls][0] * jnp.sum((length - rest) ** 2)
    return e


def potential_energy(net, ms: MassSpring, x, gravity):
    """Elastic energy plus gravitational energy -sum m g.x, J.

    Shapes: x (rows, cols, 3) m, gravity (3,) m/s^2 -> () J.
    """
    mass = node_mass(net, ms)
    g = jnp.asarray(gravity)[None, None, :]
    return elastic_energy(net, ms, x) - jnp.sum(mass[..., None] * x * g)


def kinetic_energy(net, ms: MassSpring, v):
    """sum 1/2 m |v|^2, J.

    Shapes: v (rows, cols, 3) m/s -> () J.
    """
    return 0.5 * jnp.sum(node_mass(net, ms) * jnp.sum(v * v, -1))


# ---------------------------------------------------------------------------------------------
# per-node Gershgorin rows for the stability estimate (eager, numpy)


def node_rows(net, ms: MassSpring) -> tuple[np.ndarray, np.ndarray]:
    """Per-node Gershgorin row sums (rows, cols) of stiffness (N/m) and damping (N s/m) matrices.

    Row i of K (linearised at rest, pinned neighbours eliminated) is bounded by
    sum_s k_s (1 + free_j) over the springs s = (i, j) at node i; likewise for the dashpots, plus
    the node's air damping.
    """
    R, C = net.rows, net.cols
    free = (~np.asarray(net.pinned)).astype(np.float64)
    coefs = [(float(k), float(d)) for k, d in _coefs(ms)]
    krow = np.zeros((R, C))
    drow = np.full((R, C), float(ms.air_damping))
    for di, dj, cls in SPRING_SETS:
        if R <= di or C <= abs(dj):
            continue
        a, b = _slices(di, dj, R, C)
        pa, pb = (p[1:] for p in _pads(di, dj))
        k, d = coefs[cls]
        # node a: diagonal k plus off-diagonal k if b is free; node b likewise
        wa = 1.0 + free[b]
        wb = 1.0 + free[a]
        krow += np.pad(k * wa, pa) + np.pad(k * wb, pb)
        drow += np.pad(d * wa, pa) + np.pad(d * wb, pb)
    return krow, drow


__all__ = [
    "LUMPINGS",
    "MASS_SPRING_FIELDS",
    "MassSpring",
    "check_mass_spring_value",
    "elastic_energy",
    "kinetic_energy",
    "make_mass_spring",
    "node_mass",
    "node_rows",
    "potential_energy",
    "rest_lengths",
    "spring_forces",
    "total_forces",
    "validate_mass_spring",
]
