"""Scene: everything one experiment needs (physics, surface, cameras, lights, appearance), as one
pytree, built from a TOML config.

Sizes and choices that change the compiled program (net shape, frame count, tessellation level,
image size, shading mode) are static fields; everything one may differentiate is an array.

The config schema (every section and key) lives in `diffcloth.config` and docs/config.md; this
module turns a validated `Config` into the pytrees the stages take.
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

__all__ = [
    "CLOTH_KINDS",
    "Scene",
    "cloth_kind",
    "build_bodies",
    "build_scene",
    "check_run_stability",
    "load_scene",
    "RenderConfig",
]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Scene:
    """A whole scene. Leaves are arrays (differentiable); the settings from `num_frames` on are
    static.

    Attributes:
      net, sim, material, state, colliders: the physics (see `diffcloth.physics`).
      spheres: Sphere batch pushed out of the rendered surface and drawn (or None).
      cameras: tuple of `render.Camera`, all of the same image size.
      lights, appearance, textures: shading inputs (textures may be None).
      num_frames, level, basis, shading, flip, frame_stride, background: static settings.
      bodies: tuple of `physics.RigidBody` simulated with the cloth (empty: cloth only).
      two_way: static; whether the cloth pushes back on the bodies.
      first_frame: static; 1 (default): the video's first image is the state after frame_stride
        frames (images show frames k, 2k, ..., the initial state is not drawn); 0: the first
        image is the initial state (frames 0, k, 2k, ...). The number of images is the same.
      capture: optional `render.Capture`: per-camera exposure gain, small pose error and
        background colour (None: gain 1, no pose error, `background` for every camera).
      push_out_offset: static, m >= 0 (default 1 mm); rendered vertices inside a sphere are pushed
        out to radius + push_out_offset (cloth drawn that far outside the drawn sphere: the
        triangles' chords between pushed vertices would otherwise dip under the drawn sphere).
      draw_planes, plane_color: static; draw the plane colliders as matte ground of that linear
        albedo (shadow receivers).
      shadow_map_size: static shadow-map size of the lights with shadows (texels).
      ambient_occlusion: static number of sky directions of the occluded ambient light (0: off;
        `render.sky`); its maps have shadow_map_size // 2 texels.
      shadow_quality: static "full" or "fit": map sizes and filters of the shadow and sky maps
        (`render.shadow_quality`; "fit": maps sized to the image, one tap each).
      cull: static; object-level frustum culling of the cloth in each camera.
      deform: static tuple of `config.render.DeformConfig` ([[deform]] waves / ripples applied
        to the rendered surface at each frame's time).
      display: mesh cloth only: the drawn mesh (`physics.mesh.DisplayMesh`, [cloth] subdivide),
        or None (the simulated mesh is drawn; always None for the grid net).

    The cloth is either the grid net (net: `physics.Net`, material: `physics.Material` or
    `MassSpring`, sim: `SimSettings`, colliders: `physics.Colliders`) or a triangle-mesh cloth
    (net: `physics.mesh.ClothMesh`, material: `physics.mesh.Fabric`, sim: `physics.mesh.run.
    MeshSim`, colliders: `physics.mesh.MeshColliders`); `cloth_kind(scene)` tells which.
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
    first_frame: int = dataclasses.field(default=1, metadata={"static": True})
    capture: Any = None
    push_out_offset: float = dataclasses.field(default=1e-3, metadata={"static": True})
    draw_planes: bool = dataclasses.field(default=False, metadata={"static": True})
    plane_color: tuple = dataclasses.field(default=(0.6, 0.6, 0.6), metadata={"static": True})
    shadow_map_size: int = dataclasses.field(default=256, metadata={"static": True})
    ambient_occlusion: int = dataclasses.field(default=0, metadata={"static": True})
    shadow_quality: str = dataclasses.field(default="full", metadata={"static": True})
    cull: bool = dataclasses.field(default=False, metadata={"static": True})
    deform: tuple = dataclasses.field(default=(), metadata={"static": True})
    display: Any = None

    @property
    def image_shape(self) -> tuple[int, int]:
        """(H, W) of every camera."""
        return self.cameras[0].height, self.cameras[0].width

    @property
    def video_shape(self) -> tuple[int, int, int, int, int]:
        """Shape of `simulate_and_render`'s output: (cameras, T, H, W, 3)."""
        h, w = self.image_shape
        return (len(self.cameras), self.num_frames // self.frame_stride, h, w, 3)


#: the two cloth representations a Scene holds
CLOTH_KINDS = ("grid", "mesh")


def cloth_kind(scene_or_net) -> str:
    """ "grid" (control net) or "mesh" (triangle-mesh cloth) of a Scene (or of its `net`): the one
    place where the pipeline's stages choose their path."""
    from diffcloth.physics.mesh.topology import ClothMesh

    net = getattr(scene_or_net, "net", scene_or_net)
    return "mesh" if isinstance(net, ClothMesh) else "grid"


RenderConfig = cfg.RenderConfig  # re-exported: the [render] settings live in diffcloth.config


def _build_cameras(config: cfg.Config, rc: cfg.RenderConfig, dtype) -> tuple:
    cams = []
    for i, c in enumerate(config.cameras):
        try:
            cam = render.make_camera(
                c.eye,
                c.target,
                c.up,
                width=rc.width,
                height=rc.height,
                fov_y=c.fov_y,
                near=c.near,
                far=c.far,
                projection=c.projection,
            )
        except ValueError as err:
            raise cfg.ConfigError(f"[cameras #{i}] {err}") from None
        cams.append(jax.tree_util.tree_map(lambda a: a.astype(dtype) if dtype else a, cam))
    return tuple(cams)


def _build_lights(lc: cfg.LightsConfig, dtype):
    try:
        return render.make_lights(
            ambient=lc.ambient,
            directional=tuple((d.direction, d.color, d.intensity) for d in lc.directional),
            point=tuple((p.position, p.color, p.intensity) for p in lc.point),
            shadows=[d.shadows for d in lc.directional] + [p.shadows for p in lc.point],
            softness=[d.softness for d in lc.directional] + [p.softness for p in lc.point],
            dtype=dtype,
        )
    except ValueError as err:
        raise cfg.ConfigError(f"[lights] {err}") from None


def _build_appearance(values: Mapping[str, Any], dtype):
    try:
        return render.make_appearance(dtype=dtype, **dict(values))
    except (ValueError, TypeError) as err:
        raise cfg.ConfigError(f"[appearance] {err}") from None


def build_bodies(config: cfg.Config, dtype=None) -> tuple[tuple, bool]:
    """[[bodies]] and [coupling] of a config -> (tuple of RigidBody, two_way)."""
    from diffcloth.physics.rigid import bodies_from_config

    try:
        bodies = bodies_from_config(config.bodies.entries, dtype=dtype)
    except (ValueError, TypeError) as err:
        raise cfg.ConfigError(f"[[bodies]] {err}") from None
    return tuple(bodies), config.bodies.two_way


def parse_bodies(sections: Mapping[str, Any], dtype=None) -> tuple[tuple, bool]:
    """[[bodies]] and [coupling] tables -> (tuple of RigidBody, two_way). Prefer `build_bodies`."""
    return build_bodies(cfg.Config(bodies=cfg.parse_bodies_section(sections)), dtype)


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


STABILITY = ("warn", "error")


def check_run_stability(net, sim, material, *, stability: str = "error", label: str = "") -> None:
    """The one stability gate of `diffcloth simulate`, `render` and `fit`, run before any work.

    An explicit (symplectic) substep above the stability estimate (`physics.check_stability`)
    raises `physics.UnstableStepError` (a ValueError; the CLI exits 1 with the advice) when
    `stability` is "error", or warns (StabilityWarning) when it is "warn" (`--allow-unstable`).
    `label` prefixes the message (e.g. "[truth] stretch = 900: "). The implicit integrator is
    not checked.
    """
    from diffcloth import physics

    if stability not in STABILITY:
        raise ValueError(f"stability={stability!r}; allowed: {', '.join(STABILITY)}")
    if sim.integrator != "symplectic" or cloth_kind(net) == "mesh":
        return  # mesh cloth: no a-priori estimate; a blow-up is caught in the trajectory
    try:
        physics.check_stability(net, sim, material, error=stability == "error")
    except physics.UnstableStepError as err:
        raise physics.UnstableStepError(f"{label}{err}") from None


def build_scene(
    config: cfg.Config,
    dtype=None,
    *,
    overrides: Mapping[str, Any] | None = None,
    stability: str = "warn",
) -> Scene:
    """A Scene from a validated Config (physics from `config.build_physics`, the rest from the
    render sections). `overrides` replaces top-level render settings (e.g. {"level": 3}).
    `stability`: "warn" (default) or "error" (`check_run_stability`, what the CLI uses) when the
    explicit substep exceeds the stability estimate."""
    phys = cfg.build_physics(config, dtype=dtype)
    check_run_stability(phys.net, phys.sim, phys.material, stability=stability)
    rc = config.render
    if overrides:
        rc = dataclasses.replace(rc, **overrides)
    mesh = config.cloth.is_mesh
    if mesh:  # drawn spheres of a mesh cloth (its colliders are MeshColliders)
        from diffcloth.shapes import make_sphere

        spheres = None
        if config.spheres:
            balls = [make_sphere(sp.center, sp.radius, dtype=dtype) for sp in config.spheres]
            spheres = jax.tree_util.tree_map(lambda *a: jax.numpy.stack(a), *balls)
    else:
        spheres = phys.colliders.spheres if phys.colliders is not None else None
    if spheres is not None and spheres.center.shape[0] == 0:
        spheres = None
    textures = None
    if rc.textures == "default":
        textures = render.default_textures(tiling=rc.texture_tiling, dtype=dtype)
    bodies, two_way = build_bodies(config, dtype)
    _warn_small_bodies(bodies, config)
    cameras = _build_cameras(config, rc, dtype)
    level = rc.level
    display = None
    if mesh and config.cloth.subdivide:
        from diffcloth.physics.mesh.surface import display_mesh

        display = display_mesh(phys.net, config.cloth.subdivide)
    if rc.lod == "auto" and not mesh:
        from diffcloth.surface.lod import auto_level

        level = auto_level(phys.state.x, cameras, net_shape=phys.state.x.shape[:2], basis=rc.basis)
    return Scene(
        net=phys.net,
        sim=phys.sim,
        material=phys.material,
        state=phys.state,
        colliders=phys.colliders,
        spheres=spheres,
        cameras=cameras,
        lights=_build_lights(config.lights, dtype),
        appearance=_build_appearance(config.appearance, dtype),
        textures=textures,
        num_frames=phys.num_frames,
        level=level,
        basis=rc.basis,
        shading=rc.shading,
        flip=rc.flip,
        frame_stride=rc.frame_stride,
        background=rc.background,
        bodies=bodies,
        two_way=two_way,
        first_frame=rc.first_frame,
        push_out_offset=rc.push_out_offset,
        draw_planes=rc.draw_planes,
        plane_color=tuple(rc.plane_color),
        shadow_map_size=rc.shadow_map_size,
        ambient_occlusion=rc.ambient_occlusion,
        shadow_quality=rc.shadow_quality,
        cull=rc.cull,
        deform=tuple(config.deform),
        capture=_build_capture(config.cameras, rc, dtype),
        display=display,
    )


def _build_capture(cameras, rc, dtype):
    """A render.Capture when a camera sets its own background or exposure, else None."""
    if all(c.background is None and c.exposure == 1.0 for c in cameras):
        return None
    return render.make_capture(
        len(cameras),
        exposure=[c.exposure for c in cameras],
        background=[rc.background if c.background is None else c.background for c in cameras],
        dtype=dtype,
    )


def load_scene(path, dtype=None) -> Scene:
    """Read a TOML scene config into a Scene. Raises ConfigError (a ValueError) naming bad keys."""
    return build_scene(cfg.load_config(path), dtype=dtype)
