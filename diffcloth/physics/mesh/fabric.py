"""The fabric model of mesh cloth: per-unit, SI, resolution-independent parameters, and presets
of measured fabrics (data in fabrics.toml, loaded by name).

Membrane: orthotropic St. Venant-Kirchhoff in the warp / weft frame,

    psi_m = 1/2 (C11 E_uu^2 + 2 C12 E_uu E_vv + C22 E_vv^2 + 4 G E_uv^2)     [J/m^2 = N/m]

with the Green strain E, C11 = stretch_warp, C22 = stretch_weft, C12 = poisson sqrt(C11 C22),
G = shear (all N/m). Bending: a quadratic energy in the curvature tensor k of the surface,

    psi_b = 1/2 (B_warp k_uu^2 + B_weft k_vv^2 + 4 B_66 k_uv^2)               [J/m^2]

with B_66 = bend_bias - (bend_warp + bend_weft) / 4, so that bending along the warp, the weft and
the 45-degree bias takes exactly the rigidity set (N m). Isotropic: all three equal.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import tomllib
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "FABRIC_FIELDS",
    "Fabric",
    "bending_length",
    "fabric_preset",
    "fabric_presets",
    "make_fabric",
    "validate_fabric",
]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Fabric:
    """Fabric parameters (scalar float arrays; every field is differentiable).

    Attributes:
      density: areal density, kg/m^2.
      stretch_warp, stretch_weft: membrane tensile stiffness along warp / weft, N/m.
      shear: in-plane shear stiffness, N/m.
      poisson: membrane Poisson coupling, dimensionless in [0, 1); C12 = poisson sqrt(C11 C22).
      bend_warp, bend_weft, bend_bias: bending rigidity for bending along the warp, the weft and
        the 45-degree bias, N m.
      damping: stiffness-proportional (Rayleigh) damping time, s.
      drag: aerodynamic (linear) drag, N s/m^3 (force per area per m/s of relative velocity).
      friction: Coulomb friction coefficient against colliders.
    """

    density: jax.Array
    stretch_warp: jax.Array
    stretch_weft: jax.Array
    shear: jax.Array
    poisson: jax.Array
    bend_warp: jax.Array
    bend_weft: jax.Array
    bend_bias: jax.Array
    damping: jax.Array
    drag: jax.Array
    friction: jax.Array


# name -> (low, low inclusive, high, high inclusive, unit, default). A mid-weight cotton.
FABRIC_FIELDS: dict[str, tuple[float, bool, float, bool, str, float]] = {
    "density": (0.0, False, math.inf, False, "kg/m^2", 0.2),
    "stretch_warp": (0.0, False, math.inf, False, "N/m", 500.0),
    "stretch_weft": (0.0, False, math.inf, False, "N/m", 500.0),
    "shear": (0.0, False, math.inf, False, "N/m", 20.0),
    "poisson": (0.0, True, 1.0, False, "1", 0.0),
    "bend_warp": (0.0, False, math.inf, False, "N m", 2e-5),
    "bend_weft": (0.0, False, math.inf, False, "N m", 2e-5),
    "bend_bias": (0.0, False, math.inf, False, "N m", 2e-5),
    "damping": (0.0, True, math.inf, False, "s", 1e-3),
    "drag": (0.0, True, math.inf, False, "N s/m^3", 0.0),
    "friction": (0.0, True, math.inf, False, "1", 0.3),
}


def fabric_range(name: str) -> str:
    """Allowed range of a Fabric field as text, e.g. "(0, inf)"."""
    lo, lo_in, hi, hi_in, _, _ = FABRIC_FIELDS[name]
    return f"{'[' if lo_in else '('}{lo:g}, {hi:g}{']' if hi_in else ')'}"


def validate_fabric(values: dict, dtype=None) -> None:
    """Raise ValueError naming the field, its value and the allowed range for any value out of
    range, non-finite, or not representable in `dtype` (overflow, or a positive value that
    underflows to zero); and for bend_bias < (bend_warp + bend_weft) / 4 (a bending energy that
    is not positive definite)."""
    info = np.finfo(np.dtype(dtype or jnp.zeros(()).dtype))
    for name, value in values.items():
        if name not in FABRIC_FIELDS:
            continue
        lo, lo_in, hi, hi_in, unit, _ = FABRIC_FIELDS[name]
        v = np.asarray(value, np.float64)
        if v.shape != ():
            raise ValueError(f"fabric.{name}: must be a scalar, got shape {v.shape}")
        v = float(v)
        ok = math.isfinite(v) and (v >= lo if lo_in else v > lo) and (v <= hi if hi_in else v < hi)
        if not ok:
            raise ValueError(
                f"fabric.{name} = {v!r} {unit} is out of range: allowed {fabric_range(name)}"
            )
        if abs(v) > info.max or (v != 0 and abs(v) < info.tiny):
            raise ValueError(
                f"fabric.{name} = {v!r} {unit} is not representable in {info.dtype} "
                f"(normal range {info.tiny:.3g} to {info.max:.3g})"
            )
    if all(k in values for k in ("bend_warp", "bend_weft", "bend_bias")):
        w, f, b = (float(values[k]) for k in ("bend_warp", "bend_weft", "bend_bias"))
        if b < 0.25 * (w + f):
            raise ValueError(
                f"fabric.bend_bias = {b:.4g} N m must be at least (bend_warp + bend_weft) / 4 = "
                f"{0.25 * (w + f):.4g} N m (otherwise bending along some direction costs no energy)"
            )


def make_fabric(
    preset: str | None = None, *, dtype=None, validate: bool = True, **values
) -> Fabric:
    """A Fabric from defaults, optionally a preset (`fabric_presets()`), and keyword overrides.

    `bend` sets bend_warp, bend_weft and bend_bias together and `stretch` both stretch fields
    (isotropic shorthands); explicit directional values win.
    Shapes: scalars in the units of `FABRIC_FIELDS` -> Fabric of () arrays.
    """
    merged = {k: spec[-1] for k, spec in FABRIC_FIELDS.items()}
    if preset is not None:
        merged.update(fabric_preset(preset))
    short = {k: values.pop(k) for k in ("bend", "stretch") if k in values}
    if "bend" in short:
        for k in ("bend_warp", "bend_weft", "bend_bias"):
            merged[k] = short["bend"]
    if "stretch" in short:
        merged["stretch_warp"] = merged["stretch_weft"] = short["stretch"]
    unknown = sorted(set(values) - set(FABRIC_FIELDS))
    if unknown:
        raise ValueError(
            f"unknown fabric field(s) {', '.join(unknown)}; known: "
            f"{', '.join([*FABRIC_FIELDS, 'bend', 'stretch'])}"
        )
    merged.update(values)
    if validate:
        validate_fabric(merged, dtype)
    dtype = dtype or jnp.zeros(()).dtype
    return Fabric(**{k: jnp.asarray(merged[k], dtype) for k in FABRIC_FIELDS})


_PRESET_FILE = Path(__file__).with_name("fabrics.toml")


@functools.lru_cache(maxsize=1)
def _presets() -> dict[str, dict]:
    with open(_PRESET_FILE, "rb") as fh:
        data = tomllib.load(fh)
    return {name: dict(entry) for name, entry in data["fabric"].items()}


def fabric_presets() -> tuple[str, ...]:
    """Names of the fabric presets (see docs/fabrics.md for their sources).
    Shapes: none.
    """
    return tuple(sorted(_presets()))


def fabric_preset(name: str) -> dict[str, float]:
    """The Fabric fields of a preset (a dict; unset fields keep the defaults). Also accepts a
    path to a TOML file holding a [fabric] table (a fitted fabric written by the drape test).
    Shapes: none.
    """
    presets = _presets()
    if name in presets:
        entry = presets[name]
    elif name.endswith(".toml") and Path(name).is_file():
        with open(name, "rb") as fh:
            data = tomllib.load(fh)
        entry = data.get("fabric", data)
    else:
        raise ValueError(
            f"unknown fabric preset {name!r}; known: {', '.join(fabric_presets())} "
            "(or the path of a .toml file with a [fabric] table)"
        )
    return {k: float(v) for k, v in entry.items() if k in FABRIC_FIELDS}


def bending_length(bend, density, g: float = 9.81):
    """Peirce's cantilever bending length c = (B / (rho g))^(1/3), m, of a rigidity B (N m) and an
    areal density rho (kg/m^2); FAST: B [uN m] = 9.81e-6 W [g/m^2] c [mm]^3.
    Shapes: bend and density broadcast (...) -> c (...).
    """
    return (jnp.asarray(bend) / (jnp.asarray(density) * g)) ** (1.0 / 3.0)


def fabric_to_dict(fabric: Fabric) -> dict[str, float]:
    """Plain floats of every field (for reports and preset files).
    Shapes: none.
    """
    return {k: float(getattr(fabric, k)) for k in FABRIC_FIELDS}
