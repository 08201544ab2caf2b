"""What the viewer shows, without the viewer: frames of a scene, re-simulated on demand.

`ViewModel` holds a Scene, the current slider values and the frames on screen (tessellated cloth
vertices per frame, sphere and box bodies per frame). `resimulate(params)` runs the jitted
pipeline (physics -> tessellation -> per-vertex sphere collision) again; `push(...)` and
`fire(...)` re-simulate from the current frame on with an impulse or a thruster on a rigid body.
The compiled function is cached at module level (one compile per scene structure), so a slider
move costs one run of the physics, not a compile. Nothing here imports viser.

A triangle-mesh cloth (`scene.cloth_kind(scene) == "mesh"`, [cloth] shape) takes the functions of
`view.mesh`: its frames are `pipeline.mesh_simulate`'s (a dynamic rollout, or one frame: the
static equilibrium) drawn as the renderer draws them, its sliders are the fabric's fields.
"""

# ruff: noqa: F401  (re-exports: names moved to sibling modules stay importable here)
from __future__ import annotations

import dataclasses
import json
import math
import threading
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from diffcloth import physics, surface
from diffcloth.pipeline import apply_params, param_value
from diffcloth.scene import cloth_kind
from diffcloth.view.fitdata import FitData, _read_fit, _srgb, camera_pose
from diffcloth.view.frames import (
    _RENDER,
    _SIMULATE,
    SLIDERS,
    WIND_LIMIT,
    Frames,
    _render_one,
    _simulate_frames,
    _sphere_radii,
    _stack_bodies,
    _thrusters,
    _to_numpy,
    slider_range,
)

__all__ = ["SLIDERS", "FitData", "Frames", "ViewModel", "load_view", "slider_range"]


class ViewModel:
    """A scene's frames and the state of the viewer's controls.

    Args:
      scene: the Scene (grid or mesh cloth: `kind`).
      level: tessellation level of the drawn grid cloth (default max(scene level, 8)); a mesh
        cloth is drawn as the renderer draws it ([cloth] subdivide) and ignores it.
      base_params: parameters applied to the scene before the sliders' (e.g. a fit's result).
      target_params: if given, a second, fixed sequence (a fit's target) is simulated with them.
      fit: the FitData of a result folder.
      name: a title.
    """

    def __init__(
        self,
        scene,
        *,
        level: int | None = None,
        base_params: Mapping[str, Any] | None = None,
        target_params: Mapping[str, Any] | None = None,
        fit: FitData | None = None,
        name: str = "scene",
    ):
        self.scene = apply_params(scene, base_params) if base_params else scene
        self.kind = cloth_kind(scene)
        self.fit = fit
        self.name = name
        #: slider name -> (label, unit, "log" | "lin"); the wind has its own three sliders
        self.sliders: dict[str, tuple[str, str, str]] = dict(SLIDERS)
        #: why the sliders are disabled (shown in the viewer), or None
        self.sliders_note: str | None = None
        if self.kind == "mesh":
            from diffcloth.view import mesh as vm

            self.level = None
            self.faces = vm.mesh_faces(scene)
            self.sliders = vm.mesh_sliders(scene)
            self.sliders_note = vm.slider_note(scene)
            self.has_wind = scene.sim.mode == "dynamic"
        else:
            self.level = int(level or max(scene.level, 8))
            self.faces = np.asarray(
                surface.grid_faces(surface.vertex_grid_shape(scene.net.rest.shape, self.level,
                                                             scene.basis))
            )  # fmt: skip
            if scene.flip:
                self.faces = np.ascontiguousarray(self.faces[:, ::-1])
            self.has_wind = True
        self.values = {n: float(param_value(self.scene, n)) for n in self.sliders}
        if self.has_wind:
            self.values["wind"] = np.asarray(param_value(self.scene, "wind"), np.float64)
        #: mesh runs: per-frame Newton iterations and residuals of the last run (equilibrium)
        self.mesh_status: dict[str, np.ndarray] | None = None
        self.log: list[str] = []
        self.resim_count = 0
        self._lock = threading.Lock()
        nb = len(scene.bodies)
        dtype = self.dtype
        self._no_thrust = (
            jnp.zeros((nb, scene.num_frames, 1), dtype),
            jnp.tile(jnp.asarray([[0.0, 0.0, 1.0]], dtype), (nb, 1)),
            jnp.zeros((nb,), dtype),
        )
        t0 = time.perf_counter()
        self.frames = self._run(self._params(), self.scene.state, self.scene.bodies)
        self.compile_s = time.perf_counter() - t0
        if self.kind == "mesh" and not bool(self.frames.ok):
            raise ValueError(f"{name}: {self._mesh_failure()}")
        self.target = None
        if target_params:
            self.target = self._run(
                {**self._params(), **{k: jnp.asarray(v) for k, v in target_params.items()}},
                self.scene.state,
                self.scene.bodies,
            )

    # ---- properties -------------------------------------------------------------------------
    @property
    def num_frames(self) -> int:
        """Frames on screen: the scene's, or 1 for a mesh cloth's static equilibrium."""
        return int(self.frames.cloth.shape[0])

    @property
    def dtype(self):
        return self.scene.net.rest.dtype

    def describe(self) -> str:
        """One line on the cloth: the grid net's size, or the mesh's vertices, faces and mode."""
        s = self.scene
        if self.kind == "mesh":
            n, m = int(s.net.rest.shape[0]), int(self.faces.shape[0])
            mode = (
                "static equilibrium (the rest shape: one frame)"
                if s.sim.mode == "equilibrium"
                else f"dynamic, {s.sim.integrator} Euler, {self.num_frames} frames"
            )
            return f"mesh cloth, {n:,} vertices ({m:,} drawn faces), {mode}"
        net = s.net.rest.shape
        return f"net {net[1]} x {net[0]}, {self.num_frames} frames, {len(s.bodies)} rigid bodies"

    @property
    def dt(self) -> float:
        return float(self.scene.sim.dt)

    @property
    def cloth_color(self) -> tuple[int, int, int]:
        """The scene's diffuse colour as 8-bit sRGB."""
        return _srgb(self.scene.appearance.diffuse)

    @property
    def sphere_color(self) -> tuple[int, int, int]:
        return _srgb(self.scene.appearance.sphere_color)

    def cameras(self) -> list[dict[str, Any]]:
        """Each scene camera's pose (see `camera_pose`)."""
        return [camera_pose(c) for c in self.scene.cameras]

    def static_spheres(self) -> list[tuple[np.ndarray, float]]:
        if self.scene.spheres is None:
            return []
        s = self.scene.spheres.batched()
        return [(np.asarray(c), float(r)) for c, r in zip(s.center, s.radius, strict=True)]

    def planes(self) -> list[tuple[np.ndarray, float]]:
        cs = self.scene.colliders
        if self.kind == "mesh":
            from diffcloth.view.mesh import collider_planes

            return collider_planes(cs)
        if cs is None or cs.planes.offset.shape[0] == 0:
            return []
        p = cs.planes.batched()
        return [(np.asarray(n), float(o)) for n, o in zip(p.normal, p.offset, strict=True)]

    def bodies(self) -> list[dict[str, Any]]:
        """shape, radius, half_extents and mass of each rigid body."""
        return [
            {
                "shape": b.shape,
                "radius": float(np.reshape(b.radius, ())),
                "half_extents": np.asarray(b.half_extents),
                "mass": float(b.mass),
            }
            for b in self.scene.bodies
        ]

    def boxes(self) -> list[dict[str, Any]]:
        """Static box colliders (a mesh cloth's [[boxes]]): center, half_extents, wxyz each."""
        if self.kind != "mesh":
            return []
        from diffcloth.view.mesh import collider_boxes

        return collider_boxes(self.scene.colliders)

    def collider_meshes(self) -> list[tuple[str, np.ndarray, np.ndarray]]:
        """Other static colliders as (kind, vertices, faces): a mesh cloth's [[cylinders]]
        (capped, e.g. the drape tester's pedestal) and [[meshes]]."""
        if self.kind != "mesh":
            return []
        from diffcloth.view.mesh import collider_meshes

        return collider_meshes(self.scene.colliders)

    # ---- simulation -------------------------------------------------------------------------
    def _params(self) -> dict[str, jax.Array]:
        dtype = self.dtype
        p = {n: jnp.asarray(self.values[n], dtype) for n in self.sliders}
        if self.has_wind:
            p["wind"] = jnp.asarray(self.values["wind"], dtype)
        return p

    def _mesh_failure(self) -> str:
        from diffcloth.physics.mesh.run import MeshStatus, status_message

        st = self.mesh_status
        status = MeshStatus(st["converged"], st["iterations"], st["residual"])
        return status_message(self.scene.sim, status) or (
            "the mesh cloth's frames are not finite (check the fabric values)"
        )

    def _run(self, params, state, bodies, thrust=None) -> Frames:
        if self.kind == "mesh":
            from diffcloth.view.mesh import _SIMULATE_MESH

            frames, converged, iterations, residual = _SIMULATE_MESH(self.scene, params)
            self.mesh_status = {
                "converged": np.asarray(converged),
                "iterations": np.asarray(iterations),
                "residual": np.asarray(residual),
            }
            return _to_numpy(frames)
        controls, directions, strengths = thrust or self._no_thrust
        out = _SIMULATE(
            self.scene, params, state, tuple(bodies), controls, directions, strengths,
            level=self.level,
        )  # fmt: skip
        return _to_numpy(out)

    def _note(self, text: str) -> None:
        self.log.append(text)

    def resimulate(self, changes: Mapping[str, Any] | None = None) -> float:
        """Set slider values (name -> value; "wind" (3,)) and re-simulate from the start.

        Returns the wall time in s. If the new run is unstable (non-finite or blown up), the
        previous values and frames are kept and ValueError is raised naming the values.
        """
        with self._lock:
            if self.sliders_note:
                raise ValueError(self.sliders_note)
            old = {k: np.copy(v) for k, v in self.values.items()}
            allowed = (["wind"] if self.has_wind else []) + list(self.sliders)
            for name in changes or {}:
                if name not in allowed:
                    raise ValueError(f"unknown slider {name!r}; allowed: {', '.join(allowed)}")
            for name, value in (changes or {}).items():
                self.values[name] = (
                    np.asarray(value, np.float64) if name == "wind" else float(value)
                )
            if self.kind == "mesh":  # the fabric's own rules (e.g. bend_bias >= bends / 4)
                try:
                    apply_params(self.scene, {k: np.asarray(v) for k, v in self.values.items()})
                except ValueError as err:
                    self.values = old
                    msg = f"refused {dict(changes or {})}: {err}"
                    self._note(msg)
                    raise ValueError(msg) from None
            t0 = time.perf_counter()
            frames = self._run(self._params(), self.scene.state, self.scene.bodies)
            wall = time.perf_counter() - t0
            self.resim_count += 1
            if not bool(frames.ok):
                self.values = old
                why = (
                    self._mesh_failure()
                    if self.kind == "mesh"
                    else "the explicit integrator needs a smaller dt or more substeps for such "
                    "stiff or light cloth"
                )
                msg = (
                    f"re-simulation {self.resim_count} unstable with {dict(changes or {})}: kept "
                    f"the previous frames ({why})"
                )
                self._note(msg)
                raise ValueError(msg)
            self.frames = frames
            self._note(
                f"re-simulation {self.resim_count}: {dict(changes or {})} in {1e3 * wall:.0f} ms"
            )
            return wall

    def _state_at(self, t: int):
        f = self.frames
        state = physics.ClothState(jnp.asarray(f.x[t]), jnp.asarray(f.v[t]))
        bodies = tuple(
            dataclasses.replace(
                b,
                position=jnp.asarray(f.body_position[t, i], b.position.dtype),
                orientation=jnp.asarray(f.body_orientation[t, i], b.orientation.dtype),
                velocity=jnp.asarray(f.body_velocity[t, i], b.velocity.dtype),
                angular_velocity=jnp.asarray(f.body_angular_velocity[t, i], b.velocity.dtype),
            )
            for i, b in enumerate(self.scene.bodies)
        )
        return state, bodies

    def _continue_from(self, t: int, state, bodies, thrust=None) -> float:
        t0 = time.perf_counter()
        new = self._run(self._params(), state, bodies, thrust)
        wall = time.perf_counter() - t0
        self.resim_count += 1
        if not bool(new.ok):
            raise ValueError(f"re-simulation {self.resim_count} from frame {t} is unstable")
        keep = t + 1
        self.frames = Frames(
            **{
                f.name: (
                    getattr(new, f.name)
                    if f.name == "ok"
                    else np.concatenate(
                        [getattr(self.frames, f.name)[:keep], getattr(new, f.name)[: -keep or None]]
                    )
                )
                for f in dataclasses.fields(Frames)
            }
        )
        return wall

    def _check_body(self, body: int) -> None:
        if not self.scene.bodies:
            raise ValueError("the scene has no rigid bodies (add [[bodies]] to the config)")
        if not 0 <= body < len(self.scene.bodies):
            raise ValueError(f"body = {body} out of range [0, {len(self.scene.bodies) - 1}]")

    def push(self, body: int, frame: int, delta_v) -> float:
        """Add delta_v (3,) m/s to a rigid body's velocity after `frame` and re-simulate the
        frames after it. Returns the wall time in s."""
        self._check_body(body)
        frame = int(np.clip(frame, 0, self.num_frames - 1))
        with self._lock:
            state, bodies = self._state_at(frame)
            b = bodies[body]
            dv = jnp.asarray(delta_v, b.velocity.dtype)
            bodies = list(bodies)
            bodies[body] = dataclasses.replace(b, velocity=b.velocity + dv)
            wall = self._continue_from(frame, state, bodies)
            self._note(
                f"re-simulation {self.resim_count}: push body {body} by "
                f"{np.round(delta_v, 3).tolist()} m/s after frame {frame} in {1e3 * wall:.0f} ms"
            )
            return wall

    def fire(self, body: int, frame: int, direction, accel: float, frames: int) -> float:
        """Fire a thruster at a rigid body's centre for `frames` frames after `frame`: force
        mass * accel (N) along the world direction (3,) it had when fired (it turns with the body).
        Re-simulates the frames after `frame`; returns the wall time in s."""
        self._check_body(body)
        frame = int(np.clip(frame, 0, self.num_frames - 1))
        d = np.asarray(direction, np.float64)
        if d.shape != (3,) or not np.all(np.isfinite(d)) or np.linalg.norm(d) == 0:
            raise ValueError(f"thruster direction must be a finite non-zero 3-vector, got {d}")
        if not (math.isfinite(accel) and accel >= 0):
            raise ValueError(f"thruster acceleration must be >= 0 m/s^2, got {accel}")
        with self._lock:
            state, bodies = self._state_at(frame)
            controls, directions, strengths = (np.array(a) for a in self._no_thrust)
            w, x, y, z = np.asarray(bodies[body].orientation, np.float64)
            rot = np.array(
                [
                    [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                    [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                    [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
                ]
            )
            directions[body] = rot.T @ (d / np.linalg.norm(d))  # world -> body frame
            strengths[body] = float(bodies[body].mass) * accel
            controls[body, : max(0, int(frames)), 0] = 1.0
            thrust = tuple(jnp.asarray(a) for a in (controls, directions, strengths))
            wall = self._continue_from(frame, state, bodies, thrust)
            self._note(
                f"re-simulation {self.resim_count}: thruster on body {body}, {accel:g} m/s^2 along "
                f"{np.round(d, 3).tolist()} for {frames} frames after frame {frame} in "
                f"{1e3 * wall:.0f} ms"
            )
            return wall

    # ---- rendering --------------------------------------------------------------------------
    def render(self, frame: int, camera: int = 0, shading: str | None = None) -> np.ndarray:
        """The diffcloth render of `frame` from scene camera `camera` with a shading mode
        (default the scene's): (H, W, 3) uint8 sRGB."""
        from diffcloth.render import SHADING_MODES

        shading = shading or self.scene.shading
        if shading not in SHADING_MODES:
            raise ValueError(f"shading = {shading!r}; allowed: {', '.join(SHADING_MODES)}")
        if not 0 <= camera < len(self.scene.cameras):
            raise ValueError(f"camera = {camera} out of range [0, {len(self.scene.cameras) - 1}]")
        frame = int(np.clip(frame, 0, self.num_frames - 1))
        scene = dataclasses.replace(
            self.scene, cameras=(self.scene.cameras[camera],), shading=shading
        )
        if self.kind == "mesh":
            from diffcloth.view.mesh import _RENDER_MESH

            c = (
                np.asarray(scene.spheres.batched().center)
                if scene.spheres is not None
                else np.zeros((0, 3))
            )
            img = _RENDER_MESH(scene, self._params(), jnp.asarray(self.frames.x[frame]),
                               jnp.asarray(c, self.dtype))  # fmt: skip
            img = np.clip(np.asarray(img, np.float64), 0.0, 1.0) ** (1.0 / 2.2)
            return (255 * img + 0.5).astype(np.uint8)
        centers = []
        if scene.spheres is not None:
            centers.append(np.asarray(scene.spheres.batched().center))
        balls = [i for i, b in enumerate(scene.bodies) if b.shape == "sphere"]
        if balls:
            centers.append(self.frames.body_position[frame, balls])
        c = np.concatenate(centers) if centers else np.zeros((0, 3))
        dtype = self.dtype
        img = _RENDER(
            scene, self._params(), jnp.asarray(self.frames.x[frame]), jnp.asarray(c, dtype)
        )
        img = np.clip(np.asarray(img, np.float64), 0.0, 1.0) ** (1.0 / 2.2)
        return (255 * img + 0.5).astype(np.uint8)


def load_view(path, *, level: int | None = None, size: int | None = None) -> ViewModel:
    """A ViewModel from a scene config (TOML) or a fit result folder (config.toml + result.json).

    For a result folder the cloth is simulated with the fitted parameters and the target with the
    config's [truth] values (when it has them). size: override the render image size (pixels).
    """
    from diffcloth.config import ConfigError, load_config
    from diffcloth.scene import build_scene

    path = Path(path)
    overrides = {"width": int(size), "height": int(size)} if size else None
    if path.is_dir():
        cfg_path, result = path / "config.toml", path / "result.json"
        if not cfg_path.exists() or not result.exists():
            raise ConfigError(
                f"{path} is a folder but not a fit result (it needs config.toml and result.json, "
                "as `diffcloth fit CONFIG --out DIR` writes)"
            )
        config = load_config(cfg_path)
        scene = build_scene(config, overrides=overrides)
        summary, fitted, loss = _read_fit(path)
        truth: dict[str, np.ndarray] = {}
        if "truth" in config.sections:
            from diffcloth.config.fit import parse_fit

            truth = dict(parse_fit(config.sections, path).truth)
        fit = FitData(path, fitted, truth, summary, loss)
        return ViewModel(
            scene, level=level, base_params=fitted, target_params=truth or None, fit=fit,
            name=path.name,
        )  # fmt: skip
    if not path.exists():
        raise ConfigError(f"{path}: no such config file or result folder")
    scene = build_scene(load_config(path), overrides=overrides)
    return ViewModel(scene, level=level, name=path.stem)
