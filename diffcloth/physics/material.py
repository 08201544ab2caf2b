"""Cloth material: per-unit parameters, so a material acts the same on a coarse and a fine net."""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from diffcloth.representable import check_representable


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Material:
    """Material parameters (scalar float arrays; every field is differentiable).

    Attributes:
      stretch: membrane stiffness of the structural springs, N/m (per unit width).
      shear: membrane shear stiffness of the diagonal springs, N/m.
      bend: bending stiffness, N m (energy density bend/2 * curvature^2).
      damping: stiffness-proportional (Rayleigh) spring damping time, s: each spring's damping
        coefficient is damping * k, acting on the relative velocity along the spring.
      density: areal density, kg/m^2.
      drag_normal: aerodynamic drag normal to the cloth, N s/m^3 (force per area per m/s).
      drag_tangent: aerodynamic drag tangential to the cloth, N s/m^3.
      friction: Coulomb friction coefficient against colliders, dimensionless.
    """

    stretch: jax.Array
    shear: jax.Array
    bend: jax.Array
    damping: jax.Array
    density: jax.Array
    drag_normal: jax.Array
    drag_tangent: jax.Array
    friction: jax.Array


# name -> (lower bound, lower bound inclusive?, unit, default)
MATERIAL_FIELDS: dict[str, tuple[float, bool, str, float]] = {
    "stretch": (0.0, False, "N/m", 200.0),
    "shear": (0.0, False, "N/m", 50.0),
    "bend": (0.0, False, "N m", 1e-4),
    "damping": (0.0, True, "s", 1e-4),
    "density": (0.0, False, "kg/m^2", 0.2),
    "drag_normal": (0.0, True, "N s/m^3", 0.5),
    "drag_tangent": (0.0, True, "N s/m^3", 0.05),
    "friction": (0.0, True, "1", 0.3),
}


def material_range(name: str) -> str:
    """Allowed range of a Material field as text, e.g. "[0, inf)".

    Shapes: none (a field name -> its range as text).
    """
    lo, inclusive, _, _ = MATERIAL_FIELDS[name]
    return f"{'[' if inclusive else '('}{lo:g}, inf)"


def check_material_value(name: str, value) -> float:
    """Validate one material field; returns it as float. Raises ValueError naming field and range.

    Shapes: value () -> Python float.
    """
    if name not in MATERIAL_FIELDS:
        raise ValueError(f"material: unknown field {name!r}; allowed: {sorted(MATERIAL_FIELDS)}")
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != ():
        raise ValueError(f"material.{name}: must be a scalar, got shape {arr.shape}")
    v = float(arr)
    lo, inclusive, unit, _ = MATERIAL_FIELDS[name]
    ok = math.isfinite(v) and (v >= lo if inclusive else v > lo)
    if not ok:
        raise ValueError(
            f"material.{name} = {v!r} is out of range; allowed range {material_range(name)} {unit}"
        )
    return v


def make_material(dtype=None, **fields) -> Material:
    """Validated constructor; unspecified fields take the defaults of MATERIAL_FIELDS.

    Raises ValueError naming the field and its allowed range for NaN/inf, zero or negative stiffness
    or density, negative damping, drag or friction, and for unknown field names.

    >>> m = make_material(stretch=500.0, density=0.1)
    >>> float(m.stretch)
    500.0
    """
    unknown = set(fields) - set(MATERIAL_FIELDS)
    if unknown:
        raise ValueError(
            f"material: unknown field(s) {sorted(unknown)}; allowed: {sorted(MATERIAL_FIELDS)}"
        )
    dtype = dtype or jnp.zeros(()).dtype
    values = {}
    for name, (_, _, _, default) in MATERIAL_FIELDS.items():
        value = check_material_value(name, fields.get(name, default))
        check_representable(f"material.{name}", value, dtype)  # in the run's dtype
        values[name] = jnp.asarray(value, dtype)
    return Material(**values)


def validate_material(material: Material) -> Material:
    """Eagerly check a concrete Material (e.g. one built by hand); returns it unchanged.

    Shapes: Material leaves () each, unchanged.
    """
    for name in MATERIAL_FIELDS:
        check_material_value(name, np.asarray(getattr(material, name)))
    return material


# Unconstrained <-> physical mapping for optimisers: log space with smooth clamps, so any finite raw
# value in [-1e3, 1e3] maps to a finite, strictly positive value (exp(-50) .. exp(50)).
_LOG_LO, _LOG_HI = -50.0, 50.0


def to_physical(raw):
    """Map an unconstrained value to a strictly positive one: ~exp(raw) for |raw| < 30.

    Finite and > 0 (with a finite gradient) for every finite raw, float32 and float64.

    Shapes: raw (...) -> (...) elementwise.
    """
    raw = jnp.asarray(raw)
    y = _LOG_LO + jax.nn.softplus(raw - _LOG_LO) - jax.nn.softplus(raw - _LOG_HI)
    return jnp.exp(y)


def to_raw(value):
    """Inverse of `to_physical` for values well inside (exp(-30), exp(30)): log(value).

    Shapes: value (...) -> (...) elementwise.
    """
    return jnp.log(jnp.asarray(value))


def material_to_raw(material: Material) -> Material:
    """Every field in unconstrained (log) space. Fields that may be 0 map to a very negative raw.

    Shapes: Material leaves () each -> the same shapes.
    """
    return jax.tree_util.tree_map(lambda v: to_raw(jnp.maximum(v, 1e-30)), material)


def material_from_raw(raw: Material) -> Material:
    """Inverse of `material_to_raw`: every field strictly positive.

    Shapes: Material leaves () each -> the same shapes.
    """
    return jax.tree_util.tree_map(to_physical, raw)
