"""Mesh cloth sections of the schema: [cloth] (the shape: "grid", the default, keeps the [net]
path), [fabric], and the colliders only a mesh cloth has, [[cylinders]], [[boxes]] and
[[meshes]] (docs/config.md); and `build_mesh_physics`, which turns them into the mesh pytrees.
"""

from __future__ import annotations

import dataclasses
import math
import types
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from diffcloth.config._fields import (
    _MISSING,
    ConfigError,
    array_of_tables,
    check_keys,
    get_number,
    get_vec3,
)

__all__ = [
    "CLOTH_SHAPES",
    "BoxColliderConfig",
    "ClothConfig",
    "CylinderConfig",
    "FabricConfig",
    "MeshColliderConfig",
    "build_mesh_physics",
    "parse_boxes",
    "parse_cloth",
    "parse_cylinders",
    "parse_fabric",
    "parse_meshes",
]

#: [cloth] shape values; "grid" is the control-net path of [net] and [material]
CLOTH_SHAPES = ("grid", "disc", "rectangle", "square_grid", "obj")
#: the keys each shape reads (besides shape, pinned, pin_radius, warp_angle, subdivide)
SHAPE_KEYS = {
    "grid": (),
    "disc": ("radius", "edge_length", "rings_at", "center"),
    "rectangle": ("width", "height", "edge_length", "holes", "center"),
    "square_grid": (),
    "obj": ("path", "scale", "warp"),
}
_COMMON = ("shape", "pinned", "pin_radius", "warp_angle", "subdivide")
#: the mesh's contact thickness when [sim] collision_margin is 0, m
DEFAULT_THICKNESS = 1e-3


@dataclasses.dataclass(frozen=True)
class ClothConfig:
    """[cloth]: the cloth's shape. shape = "grid" (default) uses [net] and [material]; the other
    shapes are triangle-mesh cloth (diffcloth.physics.mesh) with a [fabric]."""

    shape: str = "grid"
    radius: float = 0.15
    width: float = 1.0
    height: float = 1.0
    edge_length: float | None = None
    rings_at: tuple[float, ...] = ()
    holes: tuple[tuple[float, float, float], ...] = ()
    center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    path: str | None = None
    scale: float = 1.0
    warp: tuple[float, float, float] | None = None
    pinned: str | tuple[int, ...] = "none"
    pin_radius: float | None = None
    warp_angle: float = 0.0
    subdivide: int = 0

    @property
    def is_mesh(self) -> bool:
        return self.shape != "grid"


@dataclasses.dataclass(frozen=True)
class FabricConfig:
    """[fabric]: a preset (name, or resolved path of a TOML file with a [fabric] table) and the
    fields set explicitly (Fabric field names, plus the `bend` / `stretch` shorthands)."""

    preset: str | None = None
    values: Mapping[str, float] = dataclasses.field(
        default_factory=lambda: types.MappingProxyType({})
    )


@dataclasses.dataclass(frozen=True)
class CylinderConfig:
    """[[cylinders]]: a vertical capped cylinder from its top cap's centre down `height` m."""

    top: tuple[float, float, float]
    radius: float
    height: float


@dataclasses.dataclass(frozen=True)
class BoxColliderConfig:
    """[[boxes]]: an axis-aligned static box (also drawn)."""

    center: tuple[float, float, float]
    half_extents: tuple[float, float, float]


@dataclasses.dataclass(frozen=True)
class MeshColliderConfig:
    """[[meshes]]: a static triangle-mesh collider read from an OBJ file (resolved path)."""

    path: str
    scale: float = 1.0
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)


def _path(value, base_dir: Path | None, where: str, key: str, *, must_exist=True) -> str:
    if not isinstance(value, str) or not value:
        raise ConfigError(f"[{where}] {key} = {value!r} must be a file path (a string)")
    p = Path(value)
    if not p.is_absolute() and base_dir is not None:
        p = base_dir / p
    if must_exist and not p.is_file():
        raise ConfigError(
            f"[{where}] {key} = {value!r}: no such file ({p}; relative paths are relative to "
            "the config file)"
        )
    return str(p)


def _positive(t, key, default, where):
    return get_number(t, key, default, where=where, lo=0, lo_inclusive=False)


def _pinned(t: Mapping[str, Any], where: str):
    from diffcloth.physics.mesh.topology import PIN_RULES

    pinned = t.get("pinned", "none")
    if isinstance(pinned, str):
        if pinned not in PIN_RULES:
            raise ConfigError(
                f"[{where}] pinned = {pinned!r}; allowed rules: {', '.join(PIN_RULES)}, or a "
                "list of vertex indices"
            )
        return pinned
    if isinstance(pinned, list) and all(
        isinstance(i, int) and not isinstance(i, bool) and i >= 0 for i in pinned
    ):
        return tuple(pinned)
    raise ConfigError(
        f"[{where}] pinned = {pinned!r} must be a rule ({', '.join(PIN_RULES)}) or a list of "
        "vertex indices (integers >= 0)"
    )


def parse_cloth(t: Mapping[str, Any], base_dir: Path | None = None) -> ClothConfig:
    """[cloth] -> ClothConfig; ConfigError names the key and what is allowed."""
    w = "cloth"
    if not isinstance(t, Mapping):
        raise ConfigError(f"[cloth] must be a table, got {t!r}")
    shape = t.get("shape", "grid")
    if shape not in CLOTH_SHAPES:
        raise ConfigError(f"[cloth] shape = {shape!r}; allowed values: {', '.join(CLOTH_SHAPES)}")
    allowed = _COMMON + SHAPE_KEYS[shape]
    if shape == "grid":
        allowed = ("shape",)
    for key in t:
        if key not in allowed:
            other = [s for s, keys in SHAPE_KEYS.items() if key in keys]
            hint = f" (a key of shape = {' / '.join(map(repr, other))})" if other else ""
            raise ConfigError(
                f"[cloth] unknown key {key!r} for shape = {shape!r}{hint}; allowed keys: "
                f"{', '.join(sorted(allowed))}"
            )
    d = ClothConfig()
    kw: dict[str, Any] = {"shape": shape}
    if shape == "grid":
        return ClothConfig(**kw)
    kw["pinned"] = _pinned(t, w)
    if "pin_radius" in t:
        if shape not in ("disc", "rectangle"):
            raise ConfigError("[cloth] pin_radius applies to shape = 'disc' or 'rectangle' only")
        kw["pin_radius"] = get_number(t, "pin_radius", where=w, lo=0, lo_inclusive=False)
        if "pinned" in t:
            raise ConfigError("[cloth] give pinned or pin_radius, not both")
    kw["warp_angle"] = get_number(t, "warp_angle", 0.0, where=w, lo=-360, hi=360)
    kw["subdivide"] = get_number(t, "subdivide", 0, where=w, lo=0, hi=3, integer=True)
    if shape in ("disc", "rectangle"):
        kw["edge_length"] = _positive(t, "edge_length", None, w)
        if kw["edge_length"] is None:
            raise ConfigError(f"[cloth] missing required key 'edge_length' for shape = {shape!r}")
        kw["center"] = get_vec3(t, "center", d.center, where=w)
    if shape == "disc":
        kw["radius"] = _positive(t, "radius", d.radius, w)
        rings = t.get("rings_at", [])
        if not isinstance(rings, list) or not all(
            isinstance(r, int | float) and not isinstance(r, bool) and math.isfinite(r)
            and 0 < r < kw["radius"] for r in rings
        ):  # fmt: skip
            raise ConfigError(
                f"[cloth] rings_at = {rings!r} must be a list of radii in (0, radius = "
                f"{kw['radius']:g}) m"
            )
        kw["rings_at"] = tuple(float(r) for r in rings)
        if kw.get("pin_radius") is not None and kw["pin_radius"] > kw["radius"]:
            raise ConfigError(
                f"[cloth] pin_radius = {kw['pin_radius']:g} m is larger than radius = "
                f"{kw['radius']:g} m; allowed (0, radius]"
            )
    if shape == "rectangle":
        kw["width"] = _positive(t, "width", d.width, w)
        kw["height"] = _positive(t, "height", d.height, w)
        holes = t.get("holes", [])
        ok = isinstance(holes, list) and all(
            isinstance(h, list) and len(h) == 3
            and all(isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
                    for v in h) and h[2] > 0
            for h in holes
        )  # fmt: skip
        if not ok:
            raise ConfigError(f"[cloth] holes = {holes!r} must be a list of [cx, cz, r] (m, r > 0)")
        kw["holes"] = tuple(tuple(float(v) for v in h) for h in holes)
    if shape == "obj":
        if "path" not in t:
            raise ConfigError("[cloth] missing required key 'path' for shape = 'obj'")
        kw["path"] = _path(t["path"], base_dir, w, "path")
        kw["scale"] = _positive(t, "scale", 1.0, w)
        if "warp" in t:
            kw["warp"] = get_vec3(t, "warp", where=w)
            if math.hypot(*kw["warp"]) == 0:
                raise ConfigError("[cloth] warp = [0, 0, 0] must be a non-zero direction")
    return ClothConfig(**kw)


def parse_fabric(t: Mapping[str, Any], base_dir: Path | None = None) -> FabricConfig:
    """[fabric] -> FabricConfig: preset resolved (a name of `fabric_presets()` or a TOML path,
    relative to the config), every value checked against FABRIC_FIELDS (and the bending
    anisotropy rule of `validate_fabric`) with the preset applied."""
    from diffcloth.physics.mesh.fabric import FABRIC_FIELDS, fabric_preset, fabric_presets

    w = "fabric"
    if not isinstance(t, Mapping):
        raise ConfigError(f"[fabric] must be a table, got {t!r}")
    check_keys(t, ("preset", "bend", "stretch", *FABRIC_FIELDS), w)
    preset = t.get("preset")
    if preset is not None:
        if not isinstance(preset, str):
            raise ConfigError(f"[fabric] preset = {preset!r} must be a name or a .toml path")
        if preset not in fabric_presets():
            if preset.endswith(".toml"):
                preset = _path(preset, base_dir, w, "preset")
            else:
                raise ConfigError(
                    f"[fabric] preset = {preset!r} is not a known fabric; allowed: "
                    f"{', '.join(fabric_presets())}, or the path of a .toml file with a "
                    "[fabric] table"
                )
        try:
            fabric_preset(preset)
        except (ValueError, OSError) as err:
            raise ConfigError(f"[fabric] preset: {err}") from None
    values = {}
    for key in t:
        if key == "preset":
            continue
        v = t[key]
        if isinstance(v, bool) or not isinstance(v, int | float):
            raise ConfigError(f"[fabric] {key} = {v!r} must be a number")
        values[key] = float(v)
    fc = FabricConfig(preset=preset, values=types.MappingProxyType(values))
    try:
        _make_fabric(fc, validate_only=True)
    except ValueError as err:
        raise ConfigError(f"[fabric] {err}") from None
    return fc


def fabric_values(fc: FabricConfig) -> dict[str, float]:
    """Every Fabric field of a [fabric] section as plain floats: the defaults, then the preset,
    then the `bend` / `stretch` shorthands, then the explicit fields (as `make_fabric` merges)."""
    from diffcloth.physics.mesh.fabric import FABRIC_FIELDS, fabric_preset

    merged = {k: spec[-1] for k, spec in FABRIC_FIELDS.items()}
    if fc.preset is not None:
        merged.update(fabric_preset(fc.preset))
    values = dict(fc.values)
    if "bend" in values:
        merged.update(dict.fromkeys(("bend_warp", "bend_weft", "bend_bias"), values.pop("bend")))
    if "stretch" in values:
        merged.update(dict.fromkeys(("stretch_warp", "stretch_weft"), values.pop("stretch")))
    merged.update(values)
    return merged


def _make_fabric(fc: FabricConfig, dtype=None, *, validate_only: bool = False):
    from diffcloth.physics.mesh.fabric import make_fabric, validate_fabric

    if validate_only:  # ranges only here (as float64); the run's dtype is checked at build time
        import numpy as np

        return validate_fabric(fabric_values(fc), np.float64)
    return make_fabric(dtype=dtype, **fabric_values(fc))


def parse_cylinders(data: Mapping[str, Any]) -> tuple[CylinderConfig, ...]:
    """[[cylinders]]: vertical capped cylinders (the drape tester's pedestal)."""
    out = []
    for i, c in enumerate(array_of_tables(data, "cylinders")):
        w = f"cylinders #{i}"
        check_keys(c, ("top", "radius", "height"), w)
        out.append(
            CylinderConfig(
                top=get_vec3(c, "top", where=w),
                radius=_positive(c, "radius", _MISSING, w),
                height=_positive(c, "height", _MISSING, w),
            )
        )
    return tuple(out)


def parse_boxes(data: Mapping[str, Any]) -> tuple[BoxColliderConfig, ...]:
    """[[boxes]]: static axis-aligned boxes (a table)."""
    out = []
    for i, b in enumerate(array_of_tables(data, "boxes")):
        w = f"boxes #{i}"
        check_keys(b, ("center", "half_extents"), w)
        half = get_vec3(b, "half_extents", where=w)
        if min(half) <= 0:
            raise ConfigError(f"[{w}] half_extents = {list(half)} must be three values > 0 m")
        out.append(BoxColliderConfig(center=get_vec3(b, "center", where=w), half_extents=half))
    return tuple(out)


def parse_meshes(data: Mapping[str, Any], base_dir: Path | None = None):
    """[[meshes]]: static triangle-mesh colliders from OBJ files."""
    out = []
    for i, m in enumerate(array_of_tables(data, "meshes")):
        w = f"meshes #{i}"
        check_keys(m, ("path", "scale", "offset"), w)
        if "path" not in m:
            raise ConfigError(f"[{w}] missing required key 'path'")
        out.append(
            MeshColliderConfig(
                path=_path(m["path"], base_dir, w, "path"),
                scale=_positive(m, "scale", 1.0, w),
                offset=get_vec3(m, "offset", (0.0, 0.0, 0.0), where=w),
            )
        )
    return tuple(out)


# ----------------------------------------------------------------------------- builders


def build_cloth_mesh(config, dtype=None):
    """The ClothMesh of a config's [cloth] (and [net] for square_grid)."""
    import numpy as np

    from diffcloth.physics.mesh import builders, make_cloth

    c = config.cloth
    where = f"{config.path}: " if config.path else ""
    try:
        if c.shape == "disc":
            mesh = builders.disc(c.radius, c.edge_length, rings_at=c.rings_at, center=c.center)
        elif c.shape == "rectangle":
            mesh = builders.rectangle(c.width, c.height, c.edge_length, holes=c.holes,
                                      center=c.center)  # fmt: skip
        elif c.shape == "square_grid":
            n = config.net
            mesh = builders.grid_square(n.rows, n.cols, (n.width, n.height), center=n.center,
                                        plane=n.plane)  # fmt: skip
        else:
            mesh = builders.read_cloth_obj(c.path, warp=c.warp, scale=c.scale)
        pinned = c.pinned if isinstance(c.pinned, str) else list(c.pinned)
        if c.pin_radius is not None:
            rel = mesh.vertices - np.asarray(c.center)
            pinned = np.hypot(rel[:, 0], rel[:, 2]) <= c.pin_radius * (1 + 1e-9)
        if c.shape == "square_grid" and isinstance(config.net.pinned, tuple) and pinned == "none":
            pinned = [r * config.net.cols + col for r, col in config.net.pinned]
        return make_cloth(mesh, pinned=pinned, warp_angle=c.warp_angle, dtype=dtype)
    except ValueError as err:
        raise ConfigError(f"{where}[cloth] {err}") from None


def build_mesh_colliders(config, dtype=None):
    """MeshColliders of [[planes]], [[spheres]], [[cylinders]], [[boxes]], [[meshes]], or None."""
    from diffcloth.physics.mesh import make_mesh_colliders
    from diffcloth.physics.mesh.objfile import parse_obj

    if not (config.planes or config.spheres or config.cylinders or config.boxes or config.meshes):
        return None
    import numpy as np

    tri = []
    for i, m in enumerate(config.meshes):
        try:
            pos, _, faces, _ = parse_obj(Path(m.path))
            if len(faces) == 0 or faces.min() < 0 or faces.max() >= len(pos):
                raise ValueError("needs faces whose vertex indices name existing vertices")
            pos = np.asarray(pos, float) * m.scale + np.asarray(m.offset)
            tri.append(pos[faces])
        except (ValueError, OSError) as err:
            raise ConfigError(f"[meshes #{i}] {m.path}: {err}") from None
    s = config.sim
    margin = s.collision_margin if s.contact_thickness is None else s.contact_thickness
    try:
        return make_mesh_colliders(
            planes=[(p.normal, p.offset) for p in config.planes],
            spheres=[(sp.center, sp.radius) for sp in config.spheres],
            boxes=[(b.center, b.half_extents) for b in config.boxes],
            cylinders=[(c.top, c.radius, c.height) for c in config.cylinders],
            triangles=np.concatenate(tri) if tri else None,
            thickness=margin if margin > 0 else DEFAULT_THICKNESS,
            dtype=dtype,
        )
    except ValueError as err:
        raise ConfigError(f"[colliders] {err}") from None


def build_mesh_physics(config, dtype=None):
    """PhysicsScene of a mesh cloth: ClothMesh, MeshSim, Fabric, start ClothState (the rest mesh,
    or seeded by [sim] perturb), MeshColliders (or None); num_frames 1 in equilibrium mode."""
    import jax.numpy as jnp

    from diffcloth.config.dtype import check_config_dtype
    from diffcloth.config.physics import PhysicsScene
    from diffcloth.physics.mesh.run import make_mesh_sim, perturbed_start
    from diffcloth.physics.state import ClothState
    from diffcloth.representable import run_dtype

    check_config_dtype(config, dtype)
    where = f"{config.path}: " if config.path else ""
    try:
        fabric = _make_fabric(config.fabric, dtype=dtype)
    except ValueError as err:
        raise ConfigError(f"{where}[fabric] {err}") from None
    cloth = build_cloth_mesh(config, dtype)
    s = config.sim
    tol = s.solver_tol
    if tol is None:
        tol = 1e-3 if run_dtype(dtype) == jnp.float64 else 2e-2
    try:
        sim = make_mesh_sim(s.dt, gravity=s.gravity, wind=s.wind, num_substeps=s.num_substeps,
                            integrator=s.integrator, mode=s.mode, solver_iters=s.solver_iters,
                            solver_tol=tol, dtype=dtype)  # fmt: skip
    except ValueError as err:
        raise ConfigError(f"{where}[sim] {err}") from None
    if s.self_contact:
        from diffcloth.physics.mesh.selfcontact import make_self_contact

        try:
            cap = s.self_contact_capacity or 8  # (a grid's default is 16)
            contact = make_self_contact(s.self_contact_thickness, capacity=cap, cloth=cloth,
                                        dtype=cloth.rest.dtype)  # fmt: skip
        except ValueError as err:
            raise ConfigError(f"{where}[sim] {err} (self_contact_thickness)") from None
        sim = dataclasses.replace(sim, self_contact=contact)
    x = cloth.rest
    if s.perturb is not None:
        p = s.perturb
        x = jnp.asarray(perturbed_start(cloth, cloth.rest, mode=p["mode"],
                                        amplitude=p["amplitude"], seed=p["seed"]), x.dtype)  # fmt: skip
    v = jnp.zeros_like(x) + jnp.asarray(config.net.velocity, x.dtype)[None, :]
    num_frames = 1 if s.mode == "equilibrium" else s.num_frames
    return PhysicsScene(cloth, sim, fabric, ClothState(x=x, v=v),
                        build_mesh_colliders(config, dtype), num_frames)  # fmt: skip
