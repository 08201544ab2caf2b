"""The TOML schema, in one place: one module per pipeline stage, parsed once into typed settings.

    physics.py  [net] [material] [sim] [[spheres]] [[planes]]  -> NetConfig, MaterialConfig, ...
    cloth.py    [cloth] [fabric] [[cylinders]] [[boxes]] [[meshes]] -> ClothConfig, ... (mesh cloth)
    render.py   [render] [[cameras]] [lights] [appearance]     -> RenderConfig, CameraConfig, ...
    bodies.py   [[bodies]] [coupling]                          -> BodiesConfig
    fit.py      [fit] [fit.initial] [truth]                    -> FitSettings

`load_config(path)` reads a file and validates every section up front: any unknown key, value out
of range, or NaN/inf is a `ConfigError` (a ValueError) naming the file, the section, the key, the
bad value and the allowed range. The settings then flow down the stages: `build_physics(config)`
makes the physics pytrees, `diffcloth.scene.build_scene(config)` the whole `Scene`, and
`diffcloth.experiment.run_fit_config` reads `config.fit`. `schema()` lists every section's keys;
docs/config.md documents them (a test keeps the two in step).
"""

from __future__ import annotations

import dataclasses
import tomllib
import types
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from diffcloth.config._fields import (
    ConfigError,
    array_of_tables,
    check_keys,
    dataclass_keys,
    get_bool,
    get_choice,
    get_number,
    get_table,
    get_vec3,
)
from diffcloth.config.bodies import BodiesConfig, parse_bodies_section
from diffcloth.config.cloth import (
    BoxColliderConfig,
    ClothConfig,
    CylinderConfig,
    FabricConfig,
    MeshColliderConfig,
    parse_boxes,
    parse_cloth,
    parse_cylinders,
    parse_fabric,
    parse_meshes,
)
from diffcloth.config.fit import FitSettings, check_devices, parse_fit
from diffcloth.config.physics import (
    MaterialConfig,
    NetConfig,
    PhysicsScene,
    PlaneConfig,
    SimConfig,
    SphereConfig,
    build_physics,
    parse_material,
    parse_net,
    parse_planes,
    parse_sim,
    parse_spheres,
)
from diffcloth.config.render import (
    CameraConfig,
    DeformConfig,
    DirectionalLightConfig,
    LightsConfig,
    PointLightConfig,
    RenderConfig,
    parse_appearance,
    parse_cameras,
    parse_deform,
    parse_lights,
    parse_render,
)

__all__ = [
    "BodiesConfig",
    "CameraConfig",
    "ClothConfig",
    "Config",
    "ConfigError",
    "DirectionalLightConfig",
    "FitSettings",
    "LightsConfig",
    "MaterialConfig",
    "NetConfig",
    "PhysicsScene",
    "PlaneConfig",
    "PointLightConfig",
    "RenderConfig",
    "SimConfig",
    "SphereConfig",
    "array_of_tables",
    "build_physics",
    "check_config_path",
    "check_devices",
    "check_keys",
    "dataclass_keys",
    "get_bool",
    "get_choice",
    "get_number",
    "get_table",
    "get_vec3",
    "load_config",
    "parse_config",
    "parse_fit",
    "schema",
]

SECTIONS = (
    "net", "material", "sim", "spheres", "planes",  # physics
    "render", "camera", "cameras", "lights", "appearance", "deform",  # render
    "bodies", "coupling",  # rigid bodies
    "fit", "truth",  # fitting
    "cloth", "fabric", "cylinders", "boxes", "meshes",  # mesh cloth
)  # fmt: skip
#: sections only a mesh cloth reads, and those only the grid reads
MESH_SECTIONS = ("fabric", "cylinders", "boxes", "meshes")
GRID_SECTIONS = ("material", "bodies", "coupling")


@dataclasses.dataclass(frozen=True)
class Config:
    """A whole validated scene config: one typed field per section.

    `fit` is None for a config without a [fit] section. `sections` keeps the raw tables
    (read-only), for tools that want to show or copy them.
    """

    net: NetConfig = NetConfig()
    material: MaterialConfig = MaterialConfig()
    sim: SimConfig = SimConfig()
    spheres: tuple[SphereConfig, ...] = ()
    planes: tuple[PlaneConfig, ...] = ()
    render: RenderConfig = RenderConfig()
    cameras: tuple[CameraConfig, ...] = (CameraConfig(),)
    lights: LightsConfig = LightsConfig()
    appearance: Mapping[str, Any] = dataclasses.field(
        default_factory=lambda: types.MappingProxyType({})
    )
    bodies: BodiesConfig = BodiesConfig()
    deform: tuple[DeformConfig, ...] = ()
    fit: FitSettings | None = None
    cloth: ClothConfig = ClothConfig()
    fabric: FabricConfig = FabricConfig()
    cylinders: tuple[CylinderConfig, ...] = ()
    boxes: tuple[BoxColliderConfig, ...] = ()
    meshes: tuple[MeshColliderConfig, ...] = ()
    sections: Mapping[str, Any] = dataclasses.field(
        default_factory=lambda: types.MappingProxyType({}), compare=False, hash=False
    )
    path: str | None = None


def parse_config(data: Mapping[str, Any], path: str | None = None) -> Config:
    """Validate a TOML-like dict into a Config (ConfigError names any bad key or value)."""
    check_keys(data, SECTIONS, "top level")
    for name in ("net", "material", "sim", "render", "lights", "appearance", "coupling", "fit",
                 "cloth", "fabric"):  # fmt: skip
        if name in data and not isinstance(data[name], Mapping):
            raise ConfigError(f"[{name}] must be a table, got {data[name]!r}")
    base_dir = Path(path).parent if path else None
    cloth = parse_cloth(data.get("cloth", {}), base_dir)
    _check_cloth_sections(data, cloth)
    config = Config(
        net=parse_net(data.get("net", {})),
        material=parse_material(data.get("material", {})),
        sim=parse_sim(data.get("sim", {})),
        spheres=parse_spheres(data),
        planes=parse_planes(data),
        render=parse_render(data.get("render", {})),
        cameras=parse_cameras(data),
        lights=parse_lights(data.get("lights", {})),
        appearance=types.MappingProxyType(parse_appearance(data.get("appearance", {}))),
        bodies=parse_bodies_section(data),
        deform=parse_deform(data),
        fit=parse_fit(data, base_dir) if ("fit" in data or "truth" in data) else None,
        cloth=cloth,
        fabric=parse_fabric(data.get("fabric", {}), base_dir),
        cylinders=parse_cylinders(data),
        boxes=parse_boxes(data),
        meshes=parse_meshes(data, base_dir),
        sections=types.MappingProxyType(
            {k: data[k] for k in SECTIONS if k in data and k not in ("net", "material", "sim")}
        ),
        path=path,
    )
    _check_across_sections(config)
    return config


def _check_cloth_sections(data: Mapping[str, Any], cloth: ClothConfig) -> None:
    """The sections and [sim] keys of one cloth kind are refused for the other (named)."""
    sim = data.get("sim", {}) if isinstance(data.get("sim", {}), Mapping) else {}
    if not cloth.is_mesh:
        extra = [f"[{k}]" for k in MESH_SECTIONS if k in data]
        extra += [f"[sim] {k}" for k in ("mode", "perturb", "solver_iters", "solver_tol")
                  if k in sim]  # fmt: skip
        if extra:
            raise ConfigError(
                f"{', '.join(extra)} apply to a mesh cloth only; set [cloth] shape = 'disc', "
                "'rectangle', 'square_grid' or 'obj' (the grid net reads [net] and [material])"
            )
        return
    extra = [f"[{k}]" for k in GRID_SECTIONS if k in data]
    if "net" in data and cloth.shape != "square_grid":
        extra.append("[net]")
    if extra:
        raise ConfigError(
            f"{', '.join(extra)} do(es) not apply to [cloth] shape = {cloth.shape!r}: a mesh "
            "cloth reads its material from [fabric] and its shape from [cloth] (rigid bodies "
            "need the grid net)"
        )
    grid_only = [k for k in ("friction_rule", "newton_iters", "cg_iters", "cg_tol", "gradient")
                 if k in sim]  # fmt: skip
    if grid_only:
        raise ConfigError(
            f"[sim] {', '.join(grid_only)} apply to the grid net only; a mesh cloth's solver "
            "reads [sim] solver_iters and solver_tol"
        )


def _check_across_sections(config: Config) -> None:
    """Rules that tie two sections together."""
    if config.cloth.is_mesh and config.sim.mode == "equilibrium":
        rc = config.render
        if rc.frame_stride != 1 or rc.first_frame != 1:
            raise ConfigError(
                "[render] frame_stride and first_frame must be 1 with [sim] mode = "
                "'equilibrium' (the video is the one rest shape)"
            )
        return
    stride, frames = config.render.frame_stride, config.sim.num_frames
    if stride > frames:
        raise ConfigError(
            f"[render] frame_stride = {stride} is larger than [sim] num_frames = {frames}, so no "
            f"frame would be rendered; allowed range [1, {frames}]"
        )


def check_config_path(path) -> Path:
    """The path of a config file, refused (ConfigError) unless it names a regular file: a FIFO
    would block the read forever, a device would read garbage, a folder cannot be read."""
    import stat

    path = Path(path)
    try:
        mode = path.stat().st_mode  # follows symlinks: a link to a regular file is fine
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such config file") from None
    except OSError as err:
        raise ConfigError(f"{path}: cannot read the config ({err.strerror or err})") from None
    if not stat.S_ISREG(mode):
        kind = (
            "a folder" if stat.S_ISDIR(mode)
            else "a FIFO (named pipe)" if stat.S_ISFIFO(mode)
            else "a socket" if stat.S_ISSOCK(mode)
            else "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode)
            else "not a regular file"
        )  # fmt: skip
        raise ConfigError(f"{path} is {kind}, not a config file; give a TOML file")
    return path


def load_config(path) -> Config:
    """Read and validate a TOML scene config. Raises ConfigError (a ValueError) on bad content,
    and for a path that is not a regular file (`check_config_path`: a FIFO is refused, not read)."""
    path = check_config_path(path)
    try:
        with path.open("rb") as fh:
            data = tomllib.load(fh)
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{path}: invalid TOML: {err}") from err
    try:
        return parse_config(data, str(path))
    except ConfigError as err:
        raise ConfigError(f"{path}: {err}") from None


def schema() -> dict[str, tuple[str, ...]]:
    """{section: allowed keys} of every section (array-of-table entries by their entry name)."""
    from diffcloth.config.footage import FOOTAGE_KEYS
    from diffcloth.physics.mesh.fabric import FABRIC_FIELDS
    from diffcloth.physics.rigid import BODY_KEYS
    from diffcloth.render import appearance_fields

    fit_keys = tuple(k for k in dataclass_keys(FitSettings) if k != "truth")
    return {
        "net": dataclass_keys(NetConfig),
        "material": dataclass_keys(MaterialConfig),
        "sim": dataclass_keys(SimConfig),
        "spheres": dataclass_keys(SphereConfig),
        "planes": dataclass_keys(PlaneConfig),
        "render": dataclass_keys(RenderConfig),
        "cameras": dataclass_keys(CameraConfig),
        "lights": ("ambient", "directional", "point"),
        "lights.directional": dataclass_keys(DirectionalLightConfig),
        "lights.point": dataclass_keys(PointLightConfig),
        "appearance": appearance_fields(),
        "bodies": tuple(sorted(BODY_KEYS)),
        "coupling": ("two_way",),
        "deform": dataclass_keys(DeformConfig),
        "fit": fit_keys,
        "fit.footage": FOOTAGE_KEYS,
        "cloth": dataclass_keys(ClothConfig),
        "fabric": ("preset", "bend", "stretch", *FABRIC_FIELDS),
        "cylinders": dataclass_keys(CylinderConfig),
        "boxes": dataclass_keys(BoxColliderConfig),
        "meshes": dataclass_keys(MeshColliderConfig),
    }
