"""Render sections of the schema: [render], [[cameras]] (or one [camera]), [lights] and
[appearance] (docs/config.md). Parsed into plain frozen settings;
`diffcloth.scene.build_scene` turns them into the render stage's pytrees (cameras, lights,
appearance)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any

from diffcloth.config._fields import (
    ConfigError,
    check_keys,
    dataclass_keys,
    get_bool,
    get_choice,
    get_number,
    get_vec3,
)

BASES = ("bspline", "bezier", "clamped")
TEXTURE_CHOICES = ("none", "default")


@dataclasses.dataclass(frozen=True)
class RenderConfig:
    """[render]: image size, tessellation and shading choices (static: they shape the program)."""

    width: int = 64
    height: int = 64
    level: int = 4
    basis: str = "bspline"
    shading: str = "phong"
    background: tuple = (0.05, 0.05, 0.08)
    frame_stride: int = 1
    flip: bool = True
    textures: str = "none"
    texture_tiling: tuple = (4.0, 4.0)
    lod: str = "fixed"
    cull: bool = False
    first_frame: int = 1
    push_out_offset: float = 1e-3
    draw_planes: bool = False
    plane_color: tuple = (0.6, 0.6, 0.6)
    shadow_map_size: int = 256
    ambient_occlusion: int = 0
    shadow_quality: str = "full"


@dataclasses.dataclass(frozen=True)
class CameraConfig:
    """One [[cameras]] entry: look-at camera; angles in degrees, distances in m."""

    eye: tuple[float, float, float] = (0.0, 1.6, 2.4)
    target: tuple[float, float, float] = (0.0, 0.5, 0.0)
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    fov_y: float = 45.0
    projection: str = "perspective"
    near: float = 0.1
    far: float = 100.0
    background: tuple[float, float, float] | None = None  # None: the [render] background
    exposure: float = 1.0  # gain on this camera's whole image


@dataclasses.dataclass(frozen=True)
class DirectionalLightConfig:
    """One [[lights.directional]] entry: `direction` points from the scene towards the light."""

    direction: tuple[float, float, float] = (0.3, 1.0, 0.6)
    color: tuple[float, float, float] = (1.0, 1.0, 1.0)
    intensity: float = 1.0
    shadows: bool = False
    softness: float = 2.0


@dataclasses.dataclass(frozen=True)
class PointLightConfig:
    """One [[lights.point]] entry."""

    position: tuple[float, float, float] = (0.0, 2.0, 0.0)
    color: tuple[float, float, float] = (1.0, 1.0, 1.0)
    intensity: float = 1.0
    shadows: bool = False
    softness: float = 2.0


@dataclasses.dataclass(frozen=True)
class LightsConfig:
    """[lights]: ambient colour plus any number of directional and point lights."""

    ambient: tuple[float, float, float] = (0.15, 0.15, 0.15)
    directional: tuple[DirectionalLightConfig, ...] = (DirectionalLightConfig(),)
    point: tuple[PointLightConfig, ...] = ()


def _tiling(t: Mapping[str, Any], default: tuple, where: str) -> tuple:
    """[render] texture_tiling: two repeat counts > 0 (u, v)."""
    v = t.get("texture_tiling", default)
    ok = (
        isinstance(v, (list, tuple))
        and len(v) == 2
        and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v)
        and all(math.isfinite(x) and 0 < x <= 1024 for x in v)
    )
    if not ok:
        raise ConfigError(
            f"[{where}] texture_tiling = {v!r} must be two numbers in (0, 1024] (repeats of the "
            "texture across the cloth along u and v)"
        )
    return (float(v[0]), float(v[1]))


def parse_render(t: Mapping[str, Any]) -> RenderConfig:
    """Validate [render]."""
    from diffcloth.render import SHADING_MODES
    from diffcloth.render.shadow_quality import SHADOW_QUALITIES

    w = "render"
    check_keys(t, dataclass_keys(RenderConfig), w)
    d = RenderConfig()
    return RenderConfig(
        width=get_number(t, "width", d.width, where=w, lo=1, hi=8192, integer=True),
        height=get_number(t, "height", d.height, where=w, lo=1, hi=8192, integer=True),
        level=get_number(t, "level", d.level, where=w, lo=2, hi=64, integer=True),
        basis=get_choice(t, "basis", d.basis, BASES, where=w),
        shading=get_choice(t, "shading", d.shading, SHADING_MODES, where=w),
        background=tuple(get_vec3(t, "background", d.background, where=w)),
        frame_stride=get_number(t, "frame_stride", d.frame_stride, where=w, lo=1, integer=True),
        flip=get_bool(t, "flip", d.flip, where=w),
        textures=get_choice(t, "textures", d.textures, TEXTURE_CHOICES, where=w),
        texture_tiling=_tiling(t, d.texture_tiling, w),
        lod=get_choice(t, "lod", d.lod, ("fixed", "auto"), where=w),
        cull=get_bool(t, "cull", d.cull, where=w),
        first_frame=get_number(t, "first_frame", d.first_frame, where=w, lo=0, hi=1, integer=True),
        push_out_offset=get_number(t, "push_out_offset", d.push_out_offset, where=w, lo=0),
        draw_planes=get_bool(t, "draw_planes", d.draw_planes, where=w),
        plane_color=tuple(get_vec3(t, "plane_color", d.plane_color, where=w)),
        shadow_map_size=get_number(
            t, "shadow_map_size", d.shadow_map_size, where=w, lo=8, hi=4096, integer=True
        ),
        ambient_occlusion=get_number(
            t, "ambient_occlusion", d.ambient_occlusion, where=w, lo=0, hi=256, integer=True
        ),
        shadow_quality=get_choice(t, "shadow_quality", d.shadow_quality, SHADOW_QUALITIES, where=w),
    )


def _parse_camera(t: Mapping[str, Any], where: str) -> CameraConfig:
    from diffcloth.render.camera import PROJECTION_KINDS

    check_keys(t, dataclass_keys(CameraConfig), where)
    if "eye" not in t:
        raise ConfigError(f"[{where}] missing required key 'eye'")
    d = CameraConfig()
    cam = CameraConfig(
        eye=get_vec3(t, "eye", where=where),
        target=get_vec3(t, "target", (0.0, 0.0, 0.0), where=where),
        up=get_vec3(t, "up", d.up, where=where),
        fov_y=get_number(
            t, "fov_y", d.fov_y, where=where, lo=0, hi=180, lo_inclusive=False, hi_inclusive=False
        ),
        projection=get_choice(t, "projection", d.projection, PROJECTION_KINDS, where=where),
        near=get_number(t, "near", d.near, where=where, lo=0, lo_inclusive=False),
        far=get_number(t, "far", d.far, where=where, lo=0, lo_inclusive=False),
        background=get_vec3(t, "background", where=where) if "background" in t else None,
        exposure=get_number(t, "exposure", d.exposure, where=where, lo=0, lo_inclusive=False),
    )
    if cam.background is not None and not all(0.0 <= v <= 1.0 for v in cam.background):
        raise ConfigError(
            f"[{where}] background = {list(cam.background)} must be linear RGB in [0, 1]"
        )
    if cam.far <= cam.near:
        raise ConfigError(f"[{where}] far = {cam.far} must be larger than near = {cam.near}")
    view = [e - g for e, g in zip(cam.eye, cam.target, strict=True)]
    if math.hypot(*view) == 0:
        raise ConfigError(f"[{where}] eye = {list(cam.eye)} must differ from target")
    if math.hypot(*cam.up) == 0:
        raise ConfigError(f"[{where}] up = {list(cam.up)} must be non-zero")
    return cam


def parse_cameras(data: Mapping[str, Any]) -> tuple[CameraConfig, ...]:
    """[[cameras]] (or a single [camera]); a default camera when neither is given."""
    if "camera" in data and "cameras" in data:
        raise ConfigError("give either [camera] or [[cameras]], not both")
    if "cameras" in data:
        tables = data["cameras"]
        if isinstance(tables, Mapping):
            tables = [tables]
        if not isinstance(tables, list) or not all(isinstance(t, Mapping) for t in tables):
            raise ConfigError("[[cameras]] must be an array of tables ([[cameras]] per camera)")
        if not tables:
            raise ConfigError("[[cameras]] must hold at least one camera")
    elif "camera" in data:
        if not isinstance(data["camera"], Mapping):
            raise ConfigError("[camera] must be a table")
        tables = [data["camera"]]
    else:
        return (CameraConfig(),)
    return tuple(_parse_camera(t, f"cameras #{i}") for i, t in enumerate(tables))


def _softness(e: Mapping[str, Any], default: float, where: str) -> float:
    from diffcloth.render.lights import SOFTNESS_RANGE

    lo, hi = SOFTNESS_RANGE
    return get_number(e, "softness", default, where=where, lo=lo, hi=hi)


def parse_lights(t: Mapping[str, Any]) -> LightsConfig:
    """Validate [lights] with its [[lights.directional]] and [[lights.point]] entries."""
    w = "lights"
    if not isinstance(t, Mapping):
        raise ConfigError("[lights] must be a table")
    check_keys(t, dataclass_keys(LightsConfig), w)
    directional_tables = t.get("directional", [{}])
    point_tables = t.get("point", [])
    for name, tables in (("directional", directional_tables), ("point", point_tables)):
        if not isinstance(tables, list) or not all(isinstance(e, Mapping) for e in tables):
            raise ConfigError(f"[[lights.{name}]] must be an array of tables")
    directional = []
    for i, e in enumerate(directional_tables):
        where = f"lights.directional #{i}"
        check_keys(e, dataclass_keys(DirectionalLightConfig), where)
        d = DirectionalLightConfig()
        light = DirectionalLightConfig(
            direction=get_vec3(e, "direction", d.direction, where=where),
            color=get_vec3(e, "color", d.color, where=where),
            intensity=get_number(e, "intensity", d.intensity, where=where, lo=0),
            shadows=get_bool(e, "shadows", d.shadows, where=where),
            softness=_softness(e, d.softness, where),
        )
        if math.hypot(*light.direction) == 0:
            raise ConfigError(f"[{where}] direction = {list(light.direction)} must be non-zero")
        directional.append(light)
    point = []
    for i, e in enumerate(point_tables):
        where = f"lights.point #{i}"
        check_keys(e, dataclass_keys(PointLightConfig), where)
        d = PointLightConfig()
        point.append(
            PointLightConfig(
                position=get_vec3(e, "position", where=where),
                color=get_vec3(e, "color", d.color, where=where),
                intensity=get_number(e, "intensity", d.intensity, where=where, lo=0),
                shadows=get_bool(e, "shadows", d.shadows, where=where),
                softness=_softness(e, d.softness, where),
            )
        )
    return LightsConfig(
        ambient=get_vec3(t, "ambient", LightsConfig.ambient, where=w),
        directional=tuple(directional),
        point=tuple(point),
    )


def parse_appearance(t: Mapping[str, Any]) -> Mapping[str, Any]:
    """[appearance]: names and values of `render.Appearance` fields (values checked when built)."""
    from diffcloth.render import appearance_fields

    if not isinstance(t, Mapping):
        raise ConfigError("[appearance] must be a table")
    check_keys(t, appearance_fields(), "appearance")
    for key, value in t.items():
        flat = value if isinstance(value, list) else [value]
        if not all(isinstance(v, int | float) and not isinstance(v, bool) for v in flat):
            raise ConfigError(
                f"[appearance] {key} = {value!r} must be a number or a list of numbers"
            )
    return dict(t)


DEFORM_KINDS = ("waves", "ripples")


@dataclasses.dataclass(frozen=True)
class DeformConfig:
    """One [[deform]] entry: a travelling wave or a circular ripple in the cloth's uv space
    (unitless [0, 1] over the cloth), displacing the rendered vertices along their normals by
    h(uv, t) in m at the frame's time t (`surface.deform`)."""

    kind: str = "waves"
    amplitude: float = 0.01
    wavelength: float = 0.25
    speed: float = 0.0
    direction: tuple = (1.0, 0.0)
    phase: float = 0.0
    center: tuple = (0.5, 0.5)
    decay: float = 0.0


def _pair(t, key, default, where, lo=-1e6, hi=1e6):
    v = t.get(key, default)
    ok = (
        isinstance(v, (list, tuple))
        and len(v) == 2
        and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v)
        and all(math.isfinite(x) and lo <= x <= hi for x in v)
    )
    if not ok:
        raise ConfigError(f"[{where}] {key} = {v!r} must be two numbers in [{lo:g}, {hi:g}]")
    return (float(v[0]), float(v[1]))


def parse_deform(data: Mapping[str, Any]) -> tuple:
    """Validate [[deform]] entries (any number) into DeformConfig."""
    entries = data.get("deform", [])
    if not isinstance(entries, list):
        raise ConfigError("[[deform]] must be an array of tables ([[deform]] per entry)")
    out = []
    for i, t in enumerate(entries):
        w = f"deform #{i}"
        if not isinstance(t, Mapping):
            raise ConfigError(f"[{w}] must be a table, got {t!r}")
        check_keys(t, dataclass_keys(DeformConfig), w)
        d = DeformConfig()
        kind = get_choice(t, "kind", d.kind, DEFORM_KINDS, where=w)
        direction = _pair(t, "direction", d.direction, w)
        if direction[0] == 0 and direction[1] == 0:
            raise ConfigError(f"[{w}] direction = [0, 0] must be a non-zero [du, dv]")
        out.append(
            DeformConfig(
                kind=kind,
                amplitude=get_number(t, "amplitude", d.amplitude, where=w, lo=-1.0, hi=1.0),
                wavelength=get_number(
                    t, "wavelength", d.wavelength, where=w, lo=0, hi=1e3, lo_inclusive=False
                ),
                speed=get_number(t, "speed", d.speed, where=w, lo=-1e3, hi=1e3),
                direction=direction,
                phase=get_number(t, "phase", d.phase, where=w, lo=-1e3, hi=1e3),
                center=_pair(t, "center", d.center, w),
                decay=get_number(t, "decay", d.decay, where=w, lo=0, hi=1e3),
            )
        )
    return tuple(out)
