"""Scene: everything one experiment needs (physics, surface, cameras, lights, appearance), as one
pytree, built from a TOML config.

Sizes and choices that change the compiled program (net shape, frame count, tessellation level,
image size, shading mode) are static fields; everything one may differentiate is an array.

Render sections of a scene config (the physics sections are documented in docs/config.md):

    [render]    width, height (pixels), level (tessellation samples per patch), basis
                ("bspline" | "bezier" | "clamped"), shading (a mode of render.SHADING_MODES),
                background [r, g, b], frame_stride (render every k-th simulated frame), flip
                (normals up for an "xz" net; default true), textures ("default" | "none")
    [[cameras]] eye, target, up, fov_y (degrees), projection, near, far   (or a single [camera])
    [lights]    ambient [r, g, b]; [[lights.directional]] direction, color, intensity;
                [[lights.point]] position, color, intensity
    [appearance] any field of render.Appearance (diffuse = [r, g, b], minnaert_k = 0.7, ...)
    [[bodies]]  rigid bodies (see `physics.rigid.bodies_from_config`: shape, radius or half_extents,
                mass, position, velocity, restitution, friction, drag, ...), simulated with the
                cloth by `physics.coupled_rollout`; sphere bodies are drawn and pushed out of the
                rendered surface
    [coupling]  two_way = true (the cloth's contact impulses act back on the bodies)
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections.abc import Mapping
from typing import Any

import jax

from diffcloth import config as cfg
from diffcloth import render
from diffcloth.shapes import Sphere

__all__ = ["Scene", "build_scene", "load_scene", "RenderConfig"]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Scene:
    """A whole scene. Leaves are arrays (differentiable); the settings below `num_frames` are static.

    Attributes:
      net, sim, material, state, colliders: the physics (see `diffcloth.physics`).
      spheres: Sphere batch pushed out of the rendered surface and drawn (or None).
      cameras: tuple of `render.Camera`, all of the same image size.
      lights, appearance, textures: shading inputs (textures may be None).
      num_frames, level, basis, shading, flip, frame_stride, background: static settings.
      bodies: tuple of `physics.RigidBody` simulated with the cloth (empty: cloth only).
      two_way: static; whether the cloth pushes back on the bodies.
      push_out_offset: static, m >= 0; rendered vertices inside a sphere are pushed out to
        radius + push_out_offset (cloth drawn that far outside the drawn sphere).
    """

    net: Any
    sim: Any
    material: Any
    state: Any
    colliders: Any
    spheres: Sphere | None
    cameras: tuple
    lights: Any
    appearance: Any
    textures: Any
    num_frames: int = dataclasses.field(metadata={"static": True})
    level: int = dataclasses.field(default=4, metadata={"static": True})
    basis: str = dataclasses.field(default="bspline", metadata={"static": True})
    shading: str = dataclasses.field(default="phong", metadata={"static": True})
    flip: bool = dataclasses.field(default=True, metadata={"static": True})
    frame_stride: int = dataclasses.field(default=1, metadata={"static": True})
    background: tuple = dataclasses.field(default=(0.05, 0.05, 0.08), metadata={"static": True})
    bodies: tuple = ()
    two_way: bool = dataclasses.field(default=True, metadata={"static": True})
    push_out_offset: float = dataclasses.field(default=0.0, metadata={"static": True})

    @property
    def image_shape(self) -> tuple[int, int]:
        """(H, W) of every camera."""
        return self.cameras[0].height, self.cameras[0].width

    @property
    def video_shape(self) -> tuple[int, int, int, int, int]:
        """Shape of `simulate_and_render`'s output: (cameras, T, H, W, 3)."""
        h, w = self.image_shape
        return (len(self.cameras), self.num_frames // self.frame_stride, h, w, 3)


@dataclasses.dataclass(frozen=True)
class RenderConfig:
    width: int = 64
    height: int = 64
    level: int = 4
    basis: str = "bspline"
    shading: str = "phong"
    background: tuple = (0.05, 0.05, 0.08)
    frame_stride: int = 1
    flip: bool = True
    textures: str = "none"


_CAMERA_KEYS = ("eye", "target", "up", "fov_y", "projection", "near", "far")
_DEFAULT_CAMERA = {"eye": [0.0, 1.6, 2.4], "target": [0.0, 0.5, 0.0]}


def _parse_render(t: Mapping[str, Any]) -> RenderConfig:
    w = "render"
    cfg.check_keys(t, [f.name for f in dataclasses.fields(RenderConfig)], w)
    d = RenderConfig()
    flip = t.get("flip", d.flip)
    if not isinstance(flip, bool):
        raise cfg.ConfigError(f"[render] flip = {flip!r} must be true or false")
    return RenderConfig(
        width=cfg.get_number(t, "width", d.width, where=w, lo=1, hi=8192, integer=True),
        height=cfg.get_number(t, "height", d.height, where=w, lo=1, hi=8192, integer=True),
        level=cfg.get_number(t, "level", d.level, where=w, lo=2, hi=64, integer=True),
        basis=cfg.get_choice(t, "basis", d.basis, ("bspline", "bezier", "clamped"), where=w),
        shading=cfg.get_choice(t, "shading", d.shading, render.SHADING_MODES, where=w),
        background=tuple(cfg.get_vec3(t, "background", d.background, where=w)),
        frame_stride=cfg.get_number(t, "frame_stride", d.frame_stride, where=w, lo=1, integer=True),
        flip=flip,
        textures=cfg.get_choice(t, "textures", d.textures, ("none", "default"), where=w),
    )


def _parse_cameras(sections: Mapping[str, Any], rc: RenderConfig, dtype) -> tuple:
    if "camera" in sections and "cameras" in sections:
        raise cfg.ConfigError("give either [camera] or [[cameras]], not both")
    tables = sections.get("cameras", [sections.get("camera", _DEFAULT_CAMERA)])
    if isinstance(tables, Mapping):
        tables = [tables]
    if not tables:
        raise cfg.ConfigError("[[cameras]] must hold at least one camera")
    cams = []
    for i, t in enumerate(tables):
        w = f"cameras #{i}"
        cfg.check_keys(t, _CAMERA_KEYS, w)
        kw = dict(
            width=rc.width,
            height=rc.height,
            fov_y=cfg.get_number(
                t, "fov_y", 45.0, where=w, lo=0, hi=180, lo_inclusive=False, hi_inclusive=False
            ),
            near=cfg.get_number(t, "near", 0.1, where=w, lo=0, lo_inclusive=False),
            far=cfg.get_number(t, "far", 100.0, where=w, lo=0, lo_inclusive=False),
            projection=t.get("projection", "perspective"),
        )
        try:
            cam = render.make_camera(
                cfg.get_vec3(t, "eye", where=w),
                cfg.get_vec3(t, "target", (0.0, 0.0, 0.0), where=w),
                cfg.get_vec3(t, "up", (0.0, 1.0, 0.0), where=w),
                **kw,
            )
        except ValueError as err:
            raise cfg.ConfigError(f"[{w}] {err}") from None
        cams.append(jax.tree_util.tree_map(lambda a: a.astype(dtype) if dtype else a, cam))
    return tuple(cams)


def _parse_lights(t: Mapping[str, Any], dtype):
    w = "lights"
    cfg.check_keys(t, ("ambient", "directional", "point"), w)
    directional = []
    for i, d in enumerate(t.get("directional", [{}])):
        cfg.check_keys(d, ("direction", "color", "intensity"), f"lights.directional #{i}")
        directional.append(
            (
                cfg.get_vec3(d, "direction", (0.3, 1.0, 0.6), where=f"lights.directional #{i}"),
                cfg.get_vec3(d, "color", (1.0, 1.0, 1.0), where=f"lights.directional #{i}"),
                cfg.get_number(d, "intensity", 1.0, where=f"lights.directional #{i}", lo=0),
            )
        )
    point = []
    for i, p in enumerate(t.get("point", [])):
        cfg.check_keys(p, ("position", "color", "intensity"), f"lights.point #{i}")
        point.append(
            (
                cfg.get_vec3(p, "position", where=f"lights.point #{i}"),
                cfg.get_vec3(p, "color", (1.0, 1.0, 1.0), where=f"lights.point #{i}"),
                cfg.get_number(p, "intensity", 1.0, where=f"lights.point #{i}", lo=0),
            )
        )
    try:
        return render.make_lights(
            ambient=cfg.get_vec3(t, "ambient", (0.15, 0.15, 0.15), where=w),
            directional=tuple(directional),
            point=tuple(point),
            dtype=dtype,
        )
    except ValueError as err:
        raise cfg.ConfigError(f"[lights] {err}") from None


def _parse_appearance(t: Mapping[str, Any], dtype):
    try:
        return render.make_appearance(dtype=dtype, **dict(t))
    except (ValueError, TypeError) as err:
        raise cfg.ConfigError(f"[appearance] {err}") from None


def parse_bodies(sections: Mapping[str, Any], dtype=None) -> tuple[tuple, bool]:
    """[[bodies]] and [coupling] of a config -> (tuple of RigidBody, two_way)."""
    from diffcloth.physics.rigid import bodies_from_config

    entries = sections.get("bodies", [])
    if not isinstance(entries, list):
        raise cfg.ConfigError("[[bodies]] must be an array of tables ([[bodies]] per body)")
    try:
        bodies = bodies_from_config(entries, dtype=dtype)
    except (ValueError, TypeError) as err:
        raise cfg.ConfigError(f"[[bodies]] {err}") from None
    t = sections.get("coupling", {})
    cfg.check_keys(t, ("two_way",), "coupling")
    two_way = t.get("two_way", True)
    if not isinstance(two_way, bool):
        raise cfg.ConfigError(f"[coupling] two_way = {two_way!r} must be true or false")
    return tuple(bodies), two_way


class SmallBodyWarning(UserWarning):
    """A sphere body can slip between the cloth's control points."""


def _warn_small_bodies(bodies, config: cfg.Config) -> None:
    n = config.net
    half_diagonal = 0.5 * math.hypot(n.width / max(n.cols - 1, 1), n.height / max(n.rows - 1, 1))
    for i, b in enumerate(bodies):
        r = float(b.radius)
        if b.shape == "sphere" and r < half_diagonal:
            warnings.warn(
                f"[[bodies]] #{i}: sphere radius {r:.3g} m is below half a net cell's diagonal "
                f"({half_diagonal:.3g} m): only control points collide, so the ball can pass "
                "between four of them and barely move the cloth; use a finer [net] or a larger "
                "ball",
                SmallBodyWarning,
                stacklevel=3,
            )


def build_scene(
    config: cfg.Config, dtype=None, *, overrides: Mapping[str, Any] | None = None
) -> Scene:
    """A Scene from a validated Config (physics from `config.build_physics`, the rest from the
    render sections). `overrides` replaces top-level render settings (e.g. {"level": 3})."""
    from diffcloth import physics

    phys = cfg.build_physics(config, dtype=dtype)
    if phys.sim.integrator == "symplectic":
        physics.check_stability(phys.net, phys.sim, phys.material)  # warns, naming the remedy
    sections = config.sections
    rc = _parse_render(sections.get("render", {}))
    if overrides:
        rc = dataclasses.replace(rc, **overrides)
    spheres = phys.colliders.spheres if phys.colliders is not None else None
    if spheres is not None and spheres.center.shape[0] == 0:
        spheres = None
    textures = render.default_textures(dtype=dtype) if rc.textures == "default" else None
    bodies, two_way = parse_bodies(sections, dtype)
    _warn_small_bodies(bodies, config)
    return Scene(
        net=phys.net,
        sim=phys.sim,
        material=phys.material,
        state=phys.state,
        colliders=phys.colliders,
        spheres=spheres,
        cameras=_parse_cameras(sections, rc, dtype),
        lights=_parse_lights(sections.get("lights", {}), dtype),
        appearance=_parse_appearance(sections.get("appearance", {}), dtype),
        textures=textures,
        num_frames=phys.num_frames,
        level=rc.level,
        basis=rc.basis,
        shading=rc.shading,
        flip=rc.flip,
        frame_stride=rc.frame_stride,
        background=rc.background,
        bodies=bodies,
        two_way=two_way,
    )


def load_scene(path, dtype=None) -> Scene:
    """Read a TOML scene config into a Scene. Raises ConfigError (a ValueError) naming bad keys."""
    return build_scene(cfg.load_config(path), dtype=dtype)
