"""Lights and appearance parameters: the fittable pytrees the shaders read.

`Lights` holds one ambient colour plus stacks of directional and point lights (any count, including
zero). `Appearance` holds every material/shading parameter of every mode. All leaves are arrays, so
any of them can be differentiated and fitted; counts are shapes, never static fields.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from diffcloth._math import dtype_eps, safe_normalize


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Lights:
    """Ambient + directional + point lights.

    Attributes:
      ambient: (3,) ambient light colour (linear RGB, already scaled by its intensity).
      direction: (nd, 3) direction from the surface *toward* each directional light (need not be
        unit; normalised when used; a zero vector falls back to +y).
      direction_color: (nd, 3) colour of each directional light.
      direction_intensity: (nd,) scalar intensity of each directional light.
      point_position: (np, 3) world position of each point light in m.
      point_color: (np, 3) colour of each point light.
      point_intensity: (np,) scalar intensity; radiance = color * intensity / (1 + attenuation d^2).
      point_attenuation: (np,) quadratic distance attenuation in 1/m^2 (0 = none).
      direction_softness: (nd,) angular radius of each directional light in degrees (> 0): the
        width of its soft shadow edges (see `diffcloth.render.shadows`). None: DEFAULT_SOFTNESS.
      point_softness: (np,) the same for each point light (angular radius seen from the lit
        point, in degrees).
      shadows: static tuple of nl = nd + np bools (directional lights first): which lights cast
        shadows. () (the default) means none does; images are then exactly the unshadowed ones.
    """

    ambient: jax.Array
    direction: jax.Array
    direction_color: jax.Array
    direction_intensity: jax.Array
    point_position: jax.Array
    point_color: jax.Array
    point_intensity: jax.Array
    point_attenuation: jax.Array
    direction_softness: jax.Array | None = None
    point_softness: jax.Array | None = None
    shadows: tuple = dataclasses.field(default=(), metadata={"static": True})

    @property
    def casts_shadows(self) -> bool:
        """True when at least one light casts shadows (static)."""
        return any(self.shadows)

    def softness_degrees(self) -> tuple[jax.Array, jax.Array]:
        """((nd,), (np,)) angular radii in degrees (defaults filled in)."""
        nd, npt = self.direction.shape[0], self.point_position.shape[0]
        dtype = self.direction.dtype
        ds = self.direction_softness
        ps = self.point_softness
        if ds is None:
            ds = jnp.full((nd,), DEFAULT_SOFTNESS, dtype)
        if ps is None:
            ps = jnp.full((npt,), DEFAULT_SOFTNESS, dtype)
        return ds, ps


#: default angular radius of a light (degrees) when shadows are on: soft edges a few pixels wide
DEFAULT_SOFTNESS = 2.0
#: allowed softness range in degrees (0 would be a hard, non-differentiable shadow edge)
SOFTNESS_RANGE = (0.05, 30.0)

Light = Lights  # public alias used by the top-level API (`dc.Light`)


def _check_finite(name, value):
    if not np.all(np.isfinite(value)):
        raise ValueError(f"{name} must be finite, got {value.tolist()}")


def make_lights(
    *,
    ambient=(0.1, 0.1, 0.1),
    directional=(((0.3, 1.0, 0.6), (1.0, 1.0, 1.0), 1.0),),
    point=(),
    shadows=False,
    softness=DEFAULT_SOFTNESS,
    dtype=None,
) -> Lights:
    """Validated constructor.

    Args:
      ambient: ambient colour (3,).
      directional: sequence of (direction toward light (3,), colour (3,), intensity) triples.
      point: sequence of (position (3,), colour (3,), intensity) or
        (position, colour, intensity, attenuation) tuples.
      shadows: bool for every light, or a sequence of nd + np bools (directional lights first):
        which lights cast shadows (default: none; images are then exactly the unshadowed ones).
      softness: angular radius of the lights in degrees, SOFTNESS_RANGE: one value, or a sequence
        of nd + np values; sets the width of the soft shadow edges.
      dtype: float dtype of the leaves (default: JAX's default float).
    Returns:
      Lights. Raises ValueError for non-finite values, zero directions or negative intensities.

    >>> lights = make_lights(ambient=(0.05, 0.05, 0.05), directional=[((0, 1, 1), (1, 1, 1), 2.0)])
    >>> lights.direction.shape
    (1, 3)
    """
    dtype = dtype or jnp.zeros(()).dtype
    amb = np.asarray(ambient, np.float64)
    if amb.shape != (3,):
        raise ValueError(f"ambient must have shape (3,), got {amb.shape}")
    _check_finite("ambient", amb)
    dirs, dcol, dint = [], [], []
    for i, item in enumerate(directional):
        d, c, k = item
        d, c, k = np.asarray(d, np.float64), np.asarray(c, np.float64), float(k)
        if d.shape != (3,) or c.shape != (3,):
            raise ValueError(f"directional[{i}] needs a (3,) direction and (3,) colour")
        _check_finite(f"directional[{i}]", np.concatenate([d, c, [k]]))
        if np.linalg.norm(d) == 0:
            raise ValueError(f"directional[{i}] direction must be non-zero, got {d.tolist()}")
        if k < 0:
            raise ValueError(f"directional[{i}] intensity must be >= 0 (range [0, inf)), got {k}")
        dirs.append(d / np.linalg.norm(d))
        dcol.append(c)
        dint.append(k)
    pos, pcol, pint, patt = [], [], [], []
    for i, item in enumerate(point):
        p, c, k = item[:3]
        a = float(item[3]) if len(item) > 3 else 0.0
        p, c, k = np.asarray(p, np.float64), np.asarray(c, np.float64), float(k)
        if p.shape != (3,) or c.shape != (3,):
            raise ValueError(f"point[{i}] needs a (3,) position and (3,) colour")
        _check_finite(f"point[{i}]", np.concatenate([p, c, [k, a]]))
        if k < 0 or a < 0:
            raise ValueError(
                f"point[{i}] intensity and attenuation must be >= 0 (range [0, inf)), got {k}, {a}"
            )
        pos.append(p)
        pcol.append(c)
        pint.append(k)
        patt.append(a)

    def arr(x, shape):
        return jnp.asarray(np.asarray(x, np.float64).reshape(shape), dtype)

    nd, nl = len(dirs), len(dirs) + len(pos)
    flags = [shadows] * nl if isinstance(shadows, bool | np.bool_) else list(shadows)
    if len(flags) != nl or not all(isinstance(f, bool | np.bool_) for f in flags):
        raise ValueError(f"shadows must be a bool or {nl} bools (one per light), got {shadows!r}")
    if np.ndim(softness) not in (0, 1) or (np.ndim(softness) == 1 and len(softness) != nl):
        raise ValueError(f"softness must be one value or {nl} values, got {softness!r}")
    soft = np.broadcast_to(np.asarray(softness, np.float64), (nl,))
    lo, hi = SOFTNESS_RANGE
    if not np.all(np.isfinite(soft)) or np.any((soft < lo) | (soft > hi)):
        raise ValueError(f"softness must be in [{lo}, {hi}] degrees, got {soft.tolist()}")

    return Lights(
        ambient=arr(amb, (3,)),
        direction=arr(dirs, (-1, 3)),
        direction_color=arr(dcol, (-1, 3)),
        direction_intensity=arr(dint, (-1,)),
        point_position=arr(pos, (-1, 3)),
        point_color=arr(pcol, (-1, 3)),
        point_intensity=arr(pint, (-1,)),
        point_attenuation=arr(patt, (-1,)),
        direction_softness=arr(soft[:nd], (-1,)),
        point_softness=arr(soft[nd:], (-1,)),
        shadows=tuple(bool(f) for f in flags) if any(flags) else (),
    )


def light_vectors(lights: Lights, positions: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Unit vectors toward every light and the radiance arriving, at each position.

    Args:
      lights: the lights.
      positions: (..., 3) world positions in m.
    Returns:
      (L, radiance): L (..., nl, 3) unit vectors from the point toward each light and radiance
      (..., nl, 3) coloured intensity, nl = nd + np (directional lights first). Finite values and
      gradients even for a point light exactly at a position (direction falls back to +y).
    """
    batch = positions.shape[:-1]
    nd = lights.direction.shape[0]
    dir_l = safe_normalize(lights.direction)
    dir_l = jnp.broadcast_to(dir_l, (*batch, nd, 3))
    dir_rad = lights.direction_color * lights.direction_intensity[:, None]
    dir_rad = jnp.broadcast_to(dir_rad, (*batch, nd, 3))
    lead = (1,) * len(batch)
    to_light = (
        jnp.reshape(lights.point_position, (*lead, -1, 3)) - positions[..., None, :]
    )  # (..., np, 3)
    # squared lengths written out: a reduce over the minor axis of 3 is a slow loop on CPU
    d2 = (
        to_light[..., 0] * to_light[..., 0]
        + to_light[..., 1] * to_light[..., 1]
        + to_light[..., 2] * to_light[..., 2]
    )
    ok = (d2 > dtype_eps(d2))[..., None]  # safe_normalize: a light at the point looks up +y
    pt_l = jnp.where(
        ok,
        jnp.where(ok, to_light, 1.0) / jnp.sqrt(jnp.where(ok, d2[..., None], 1.0)),
        jnp.asarray([0.0, 1.0, 0.0], to_light.dtype),
    )
    falloff = 1.0 / (1.0 + jnp.reshape(lights.point_attenuation, (*lead, -1)) * d2)  # (..., np)
    pt_color = lights.point_color * lights.point_intensity[:, None]
    pt_rad = jnp.reshape(pt_color, (*lead, -1, 3)) * falloff[..., None]
    return jnp.concatenate([dir_l, pt_l], axis=-2), jnp.concatenate([dir_rad, pt_rad], axis=-2)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Appearance:
    """Every fittable shading parameter (all arrays; colours linear RGB).

    Attributes:
      ambient: (3,) ambient reflectance (multiplies the ambient light).
      diffuse: (3,) diffuse albedo / material colour (multiplies the colour texture if any).
      specular: (3,) Blinn-Phong specular colour.
      shininess: () Blinn-Phong exponent (> 0).
      bump_strength: () scale of the height-map slopes in the bumped normal (0 = no bump).
      minnaert_k: () Minnaert exponent k; F = (N.L)^(k-1) (N.E)^(k-1); k = 1 is Lambert.
      reflectance: (3,) tint of environment / sphere reflections.
      refraction_s: () the seed's shortened-normal factor s in R' = -(E - 2 s^2 (E.N) N).
      ior: () relative index of refraction eta (n_from / n_to) for the exact Snell option.
      refraction_blend: () weight of the refraction lookup against the reflection (0..1).
      sphere_color: (3,) albedo of reflected spheres.
      sphere_reflectivity: () blend factor of a head-on, zero-distance sphere hit (0..1).
      sphere_distance_falloff: () 1/m; blend *= 1 / (1 + falloff * t) for hit distance t.
      sphere_rim_power: () blend *= (disc / r^2) ^ power, fading to 0 at the sphere's rim.
      second_pass_alpha: () scale of the texture alpha used to blend the second pass over the first.
    """

    ambient: jax.Array
    diffuse: jax.Array
    specular: jax.Array
    shininess: jax.Array
    bump_strength: jax.Array
    minnaert_k: jax.Array
    reflectance: jax.Array
    refraction_s: jax.Array
    ior: jax.Array
    refraction_blend: jax.Array
    sphere_color: jax.Array
    sphere_reflectivity: jax.Array
    sphere_distance_falloff: jax.Array
    sphere_rim_power: jax.Array
    second_pass_alpha: jax.Array


_APPEARANCE_DEFAULTS = dict(
    ambient=(1.0, 1.0, 1.0),
    diffuse=(0.7, 0.15, 0.2),
    specular=(0.3, 0.3, 0.3),
    shininess=32.0,
    bump_strength=1.0,
    minnaert_k=0.7,
    reflectance=(1.0, 1.0, 1.0),
    refraction_s=0.5,
    ior=1.0 / 1.33,
    refraction_blend=0.5,
    sphere_color=(0.8, 0.8, 0.2),
    sphere_reflectivity=0.8,
    sphere_distance_falloff=0.5,
    sphere_rim_power=0.5,
    second_pass_alpha=0.5,
)

# appearance fields that must be > 0 and >= 0 (checked by make_appearance, used for fit ranges)
POSITIVE_FIELDS = ("shininess", "minnaert_k", "ior")
NONNEGATIVE_FIELDS = ("sphere_distance_falloff", "sphere_rim_power", "second_pass_alpha")


def appearance_fields() -> tuple[str, ...]:
    """Names of the `Appearance` fields, in order (the keys [appearance] allows).

    Shapes: none (names).
    """
    return tuple(_APPEARANCE_DEFAULTS)


def make_appearance(*, dtype=None, **values) -> Appearance:
    """Validated constructor; any field not given takes its default (see `Appearance`).

    Raises ValueError for unknown names, wrong shapes, non-finite values, or out-of-range values
    (shininess, minnaert_k, ior must be > 0; falloffs and blend scales >= 0).

    >>> make_appearance(shininess=8.0).shininess.shape
    ()
    """
    unknown = set(values) - set(_APPEARANCE_DEFAULTS)
    if unknown:
        raise ValueError(
            f"unknown appearance fields {sorted(unknown)}; allowed: {sorted(_APPEARANCE_DEFAULTS)}"
        )
    dtype = dtype or jnp.zeros(()).dtype
    out = {}
    for name, default in _APPEARANCE_DEFAULTS.items():
        v = np.asarray(values.get(name, default), np.float64)
        if v.shape != np.shape(default):
            raise ValueError(
                f"appearance {name} must have shape {np.shape(default)}, got {v.shape}"
            )
        _check_finite(f"appearance {name}", v)
        if name in POSITIVE_FIELDS and np.any(v <= 0):
            raise ValueError(f"appearance {name} must be > 0 (range (0, inf)), got {v.tolist()}")
        if name in NONNEGATIVE_FIELDS and np.any(v < 0):
            raise ValueError(f"appearance {name} must be >= 0 (range [0, inf)), got {v.tolist()}")
        out[name] = jnp.asarray(v, dtype)
    return Appearance(**out)
