"""Fittable scene parameters: their names (cloth material, wind, appearance, rigid bodies and the
nuisance parameters of a real capture), allowed ranges, checks, and writing values into a scene
(`apply_params`). `pipeline` re-exports every name."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import jax
import jax.numpy as jnp
import numpy as np

from diffcloth import render
from diffcloth.physics.massspring import MASS_SPRING_FIELDS
from diffcloth.physics.material import MATERIAL_FIELDS
from diffcloth.physics.mesh.fabric import FABRIC_FIELDS
from diffcloth.render.lights import appearance_fields
from diffcloth.representable import check_physics, check_representable

#: body parameter name -> RigidBody field; values are per body, (num_bodies,) or (num_bodies, 3).
BODY_PARAMETERS = {
    "body_mass": "mass",
    "body_restitution": "restitution",
    "body_friction": "friction",
    "body_velocity": "velocity",
    "body_position": "position",
}

#: nuisance parameter name -> (scene field, field inside it): what a real capture adds.
#: Lights: per light ((nd, 3) / (nd,) / (np, 3) / (np,) / (3,)); capture: per camera (see
#: `render.Capture`). Albedos are the appearance parameters "diffuse" and "sphere_color".
NUISANCE_PARAMETERS: dict[str, tuple[str, str]] = {
    "light_direction": ("lights", "direction"),
    "light_intensity": ("lights", "direction_intensity"),
    "point_light_position": ("lights", "point_position"),
    "point_light_intensity": ("lights", "point_intensity"),
    "ambient_light": ("lights", "ambient"),
    "exposure": ("capture", "exposure"),
    "camera_rotation": ("capture", "rotation"),
    "camera_translation": ("capture", "translation"),
    "background": ("capture", "background"),
}

#: allowed (low, high) of the nuisance parameters (inclusive; None = unbounded). apply_params
#: checks concrete values against them; `fit.default_constraint` keeps fits inside.
NUISANCE_RANGES: dict[str, tuple[float | None, float | None]] = {
    "light_direction": (None, None),
    "light_intensity": (0.0, None),
    "point_light_position": (None, None),
    "point_light_intensity": (0.0, None),
    "ambient_light": (0.0, None),
    "exposure": (0.0, None),
    "camera_rotation": (-0.2, 0.2),  # rad per axis: a small pose error, not a new camera
    "camera_translation": (-0.2, 0.2),  # m per axis
    "background": (0.0, 1.0),
}

#: name -> (scene field, field inside it). Every fittable parameter of a scene.
PARAMETERS: dict[str, tuple[str, str]] = {
    **{name: ("material", name) for name in MATERIAL_FIELDS},
    # the Provot mass-spring model's own fields (density and friction are shared)
    **{name: ("material", name) for name in MASS_SPRING_FIELDS},
    # the mesh cloth's Fabric fields (density, shear, damping and friction are shared names)
    **{name: ("material", name) for name in FABRIC_FIELDS},
    "wind": ("sim", "wind"),
    **{name: ("appearance", name) for name in appearance_fields()},
    **{name: ("bodies", field) for name, field in BODY_PARAMETERS.items()},
    **NUISANCE_PARAMETERS,
}


@dataclasses.dataclass(frozen=True)
class ParamRange:
    """Allowed values of a parameter: lo/hi bounds (None: unbounded), inclusive or not, unit."""

    lo: float | None = None
    hi: float | None = None
    lo_inclusive: bool = True
    hi_inclusive: bool = True
    unit: str = ""

    def text(self) -> str:
        left = "[" if self.lo_inclusive and self.lo is not None else "("
        right = "]" if self.hi_inclusive and self.hi is not None else ")"
        lo = "-inf" if self.lo is None else f"{self.lo:g}"
        hi = "inf" if self.hi is None else f"{self.hi:g}"
        return f"{left}{lo}, {hi}{right}" + (f" {self.unit}" if self.unit else "")

    def contains(self, a) -> bool:
        """True when every element of the array `a` is finite and inside the range."""
        a = np.asarray(a, np.float64)
        ok = np.isfinite(a)
        if self.lo is not None:
            ok &= a >= self.lo if self.lo_inclusive else a > self.lo
        if self.hi is not None:
            ok &= a <= self.hi if self.hi_inclusive else a < self.hi
        return bool(np.all(ok))


def _fabric_range(name: str) -> ParamRange:
    lo, lo_in, hi, hi_in, unit, _ = FABRIC_FIELDS[name]
    return ParamRange(lo, None if hi == float("inf") else hi, lo_in, hi_in, unit)


#: name -> ParamRange of a mesh cloth's Fabric fields (`param_range` picks them for mesh scenes)
FABRIC_RANGES: dict[str, ParamRange] = {}


def _parameter_ranges() -> dict[str, ParamRange]:
    from diffcloth.render.lights import NONNEGATIVE_FIELDS, POSITIVE_FIELDS

    table = {
        name: ParamRange(lo, None, inclusive, True, unit)
        for fields in (MASS_SPRING_FIELDS, MATERIAL_FIELDS)
        for name, (lo, inclusive, unit, _) in fields.items()
    }
    table.update({name: ParamRange(lo, hi) for name, (lo, hi) in NUISANCE_RANGES.items()})
    table.update({name: ParamRange(0.0, None, False) for name in POSITIVE_FIELDS})
    table.update({name: ParamRange(0.0) for name in NONNEGATIVE_FIELDS})
    for name in FABRIC_FIELDS:  # mesh-only names; shared ones keep the grid's row here
        table.setdefault(name, _fabric_range(name))
    table.update(
        body_mass=ParamRange(0.0, None, False, unit="kg"),
        body_restitution=ParamRange(0.0, 1.0),
        body_friction=ParamRange(0.0),
    )
    return table


#: name -> ParamRange: the values `apply_params` accepts (the config sections' ranges). A parameter
#: not listed only has to be finite. New parameters add a row here.
PARAMETER_RANGES: dict[str, ParamRange] = _parameter_ranges()
FABRIC_RANGES.update({name: _fabric_range(name) for name in FABRIC_FIELDS})


def _is_mesh(scene) -> bool:
    from diffcloth.physics.mesh.fabric import Fabric

    return isinstance(getattr(scene, "material", None), Fabric)


def param_range(scene, name: str) -> ParamRange:
    """The allowed values of parameter `name` in `scene`: a mesh cloth's Fabric fields have the
    ranges of FABRIC_FIELDS (density, shear, damping, friction included), everything else
    PARAMETER_RANGES."""
    if _is_mesh(scene) and name in FABRIC_RANGES:
        return FABRIC_RANGES[name]
    return PARAMETER_RANGES.get(name, ParamRange())


def check_param_values(scene, params: Mapping) -> None:
    """Eager check of concrete parameter values: names, shapes (broadcastable to the scene's
    value) and ranges (PARAMETER_RANGES; NaN/inf never allowed). Traced values (inside jit) are
    skipped; use `simulate_and_render_checked` for those. Raises ValueError naming the parameter,
    the value and the allowed range."""
    check_param_names(params)
    for name, value in params.items():
        old = param_value(scene, name)
        shape = np.shape(value)  # works for lists and tracers alike
        try:
            np.broadcast_shapes(shape, old.shape)
            ok_shape = np.broadcast_shapes(shape, old.shape) == tuple(old.shape)
        except ValueError:
            ok_shape = False
        if not ok_shape:
            raise ValueError(
                f"parameter {name}: shape {shape} does not fit the scene's value of shape "
                f"{tuple(old.shape)} (give a scalar or an array of that shape)"
            )
        if isinstance(value, jax.core.Tracer):
            continue
        a = np.asarray(value, np.float64)
        rng = param_range(scene, name)
        if not rng.contains(a):
            raise ValueError(
                f"parameter {name} = {a.tolist()} is out of range; allowed {rng.text()} "
                "(finite values only)"
            )
        # the value as the run holds it: the scene's dtype (float32 unless x64)
        check_representable(f"parameter {name}", a, old.dtype)


def check_param_names(names) -> None:
    """Raise ValueError for any name that is not a fittable parameter."""
    unknown = [n for n in names if n not in PARAMETERS]
    if unknown:
        raise ValueError(
            f"unknown parameter name(s) {unknown}; allowed: {', '.join(sorted(PARAMETERS))}"
        )


def _check_bodies(scene, name: str) -> None:
    if not scene.bodies:
        raise ValueError(f"{name}: the scene has no rigid bodies (add [[bodies]] to the config)")


def scene_capture(scene) -> render.Capture:
    """The scene's Capture, or the neutral one (gain 1, no pose error, the scene's background)."""
    if getattr(scene, "capture", None) is not None:
        return scene.capture
    n, dtype = len(scene.cameras), scene.cameras[0].view.dtype
    bg = jnp.asarray(scene.background, dtype)  # static, but maybe jnp values (traced as consts)
    return render.Capture(
        exposure=jnp.ones((n,), dtype),
        rotation=jnp.zeros((n, 3), dtype),
        translation=jnp.zeros((n, 3), dtype),
        background=jnp.broadcast_to(bg, (n, 3)),
    )


def check_nuisance_ranges(params: Mapping[str, jax.Array]) -> None:
    """ValueError naming the parameter and its range for a concrete nuisance value outside
    NUISANCE_RANGES (traced values are not checked)."""
    import numpy as np

    for name, value in params.items():
        if name not in NUISANCE_RANGES or isinstance(value, jax.core.Tracer):
            continue
        lo, hi = NUISANCE_RANGES[name]
        v = np.asarray(value, np.float64)
        bad = ~np.isfinite(v)
        if lo is not None:
            bad |= v < lo
        if hi is not None:
            bad |= v > hi
        if np.any(bad):
            lo_s = "-inf" if lo is None else f"{lo:g}"
            hi_s = "inf" if hi is None else f"{hi:g}"
            raise ValueError(f"{name} = {v.tolist()} is outside its range [{lo_s}, {hi_s}]")


def param_value(scene, name: str) -> jax.Array:
    """The scene's current value of a named parameter (body parameters: stacked over bodies)."""
    check_param_names([name])
    group, field = PARAMETERS[name]
    if group == "bodies":
        _check_bodies(scene, name)
        return jnp.stack([getattr(b, field) for b in scene.bodies])
    if group == "capture":
        return getattr(scene_capture(scene), field)
    target = getattr(scene, group)
    if group == "material" and not hasattr(target, field):
        mesh_only = name in FABRIC_FIELDS and name not in MATERIAL_FIELDS
        if _is_mesh(scene) or mesh_only:
            kind, other = (
                ("a mesh cloth's [fabric]", "the grid net's [material]")
                if _is_mesh(scene)
                else ("the grid net's [material]", "a mesh cloth's [fabric] ([cloth] shape)")
            )
            names = [f.name for f in dataclasses.fields(target)]
            raise ValueError(
                f"parameter {name!r} is a parameter of {other}, not of {kind}; this scene's "
                f"material parameters are: {', '.join(names)}"
            )
    if not hasattr(target, field):
        raise ValueError(
            f"parameter {name!r} does not exist in this scene's {group} "
            f"({type(target).__name__}; [material] model decides which names apply)"
        )
    return getattr(target, field)


def apply_params(scene, params: Mapping[str, jax.Array] | None):
    """The scene with `params` (name -> value) written into its material, sim, appearance and
    rigid bodies. Body parameters take one value per body ((num_bodies,) or (num_bodies, 3)) or
    one value for all of them."""
    if not params:
        return scene
    check_param_values(scene, params)
    check_nuisance_ranges(params)
    groups: dict[str, dict] = {}
    for name, value in params.items():
        group, field = PARAMETERS[name]
        old = param_value(scene, name)
        groups.setdefault(group, {})[field] = jnp.broadcast_to(
            jnp.asarray(value, old.dtype), old.shape
        )
    concrete = not any(isinstance(v, jax.core.Tracer) for v in params.values())
    if concrete and _is_mesh(scene) and "material" in groups:  # the fabric's own rules
        from diffcloth.physics.mesh.fabric import fabric_to_dict, validate_fabric

        merged = fabric_to_dict(dataclasses.replace(scene.material, **groups["material"]))
        validate_fabric(merged, scene.material.density.dtype)
    elif concrete and not _is_mesh(scene) and ("material" in groups or "sim" in groups):
        # concrete values: the masses and substep they make, in the scene's dtype
        names = sorted(n for n in params if PARAMETERS[n][0] in ("material", "sim"))
        check_physics(
            scene.net,
            dataclasses.replace(scene.sim, **groups.get("sim", {})),
            dataclasses.replace(scene.material, **groups.get("material", {})),
            names={k: f"parameter(s) {', '.join(names)} with the scene" for k in
                   ("net", "mass", "substep")},
        )  # fmt: skip
    body_fields = groups.pop("bodies", None)
    capture_fields = groups.pop("capture", None)
    changes = {g: dataclasses.replace(getattr(scene, g), **f) for g, f in groups.items()}
    if capture_fields:
        changes["capture"] = dataclasses.replace(scene_capture(scene), **capture_fields)
    if body_fields:
        changes["bodies"] = tuple(
            dataclasses.replace(b, **{f: v[i] for f, v in body_fields.items()})
            for i, b in enumerate(scene.bodies)
        )
    return dataclasses.replace(scene, **changes)
