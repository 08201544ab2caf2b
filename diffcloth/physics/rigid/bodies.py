"""Rigid bodies: the records (RigidBody, Thrusters, RigidSettings, Contact), their validated
constructors and `bodies_from_config`.

See `diffcloth.physics.rigid` for the model and its smoothing.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

SHAPES = ("sphere", "box")


# ----------------------------------------------------------------------------------------------
# Records


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class RigidBody:
    """A rigid sphere or box: state and physical parameters (all arrays differentiable).

    Attributes:
      position: (3,) centre of mass in m.
      orientation: (4,) unit quaternion (w, x, y, z), body to world.
      velocity: (3,) m/s, world frame.
      angular_velocity: (3,) rad/s, world frame.
      mass: () kg, > 0.
      radius: () m; the sphere's radius (for a box, its bounding-sphere radius; unused).
      half_extents: (3,) m; the box's half sizes along body x, y, z (for a sphere r, r, r; unused).
      restitution: () in [0, 1].
      friction: () Coulomb coefficient >= 0.
      linear_drag: () N s/m, drag along the body's front axis (body z).
      orthogonal_drag: () N s/m, drag along the right (x) and top (y) axes.
      angular_drag: () N m s, torque -angular_drag * angular_velocity.
      shape: "sphere" or "box" (static).
    """

    position: jax.Array
    orientation: jax.Array
    velocity: jax.Array
    angular_velocity: jax.Array
    mass: jax.Array
    radius: jax.Array
    half_extents: jax.Array
    restitution: jax.Array
    friction: jax.Array
    linear_drag: jax.Array
    orthogonal_drag: jax.Array
    angular_drag: jax.Array
    shape: str = dataclasses.field(default="sphere", metadata={"static": True})


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Thrusters:
    """Forces fixed to a body, switched on and off by a control signal.

    Attributes:
      points: (k, 3) application points in the body frame, m.
      directions: (k, 3) unit thrust directions in the body frame.
      strengths: (k,) N at full control; differentiable.
    """

    points: jax.Array
    directions: jax.Array
    strengths: jax.Array


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class RigidSettings:
    """How bodies are stepped. dt: () s per frame; gravity: (3,) m/s^2; num_substeps static."""

    dt: jax.Array
    gravity: jax.Array
    num_substeps: int = dataclasses.field(default=8, metadata={"static": True})


class Contact(NamedTuple):
    """depth () m (> 0 when penetrating); normal (3,) unit, from body b to body a; point (3,) m."""

    depth: jax.Array
    normal: jax.Array
    point: jax.Array


# ----------------------------------------------------------------------------------------------
# Constructors and validation


def _vec(name, value, size, dtype):
    a = np.asarray(value, dtype=np.float64)
    if a.shape == () and size > 1:
        a = np.full(size, float(a))
    if a.shape != ((size,) if size > 1 else ()):
        raise ValueError(f"{name} must have {size} components, got {np.asarray(value).tolist()}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be finite, got {a.tolist()}")
    return a if dtype is None else jnp.asarray(a, dtype)


def _scalar(name, value, lo, hi, dtype, *, open_lo=False):
    a = np.asarray(value, dtype=np.float64)
    bad = a.shape != () or not np.isfinite(a) or a > hi or (a <= lo if open_lo else a < lo)
    if bad:
        lb = "(" if open_lo else "["
        raise ValueError(
            f"{name} must be a number in {lb}{lo}, {hi}], got {np.asarray(value).tolist()}"
        )
    return a if dtype is None else jnp.asarray(a, dtype)


def make_body(
    shape: str = "sphere",
    *,
    mass,
    position=(0.0, 0.0, 0.0),
    velocity=(0.0, 0.0, 0.0),
    orientation=(1.0, 0.0, 0.0, 0.0),
    angular_velocity=(0.0, 0.0, 0.0),
    radius=None,
    half_extents=None,
    restitution=0.5,
    friction=0.0,
    linear_drag=0.0,
    orthogonal_drag=0.0,
    angular_drag=0.0,
    dtype=None,
) -> RigidBody:
    """Validated `RigidBody` constructor (eager; raises ValueError naming the bad argument).

    A sphere needs `radius` > 0, a box `half_extents` (3 numbers > 0). The orientation is
    normalised. Example: ``make_body("sphere", mass=1.0, radius=0.1, position=(0, 1, 0))``.
    """
    dtype = dtype or jnp.zeros(()).dtype
    if shape not in SHAPES:
        raise ValueError(f"shape must be one of {SHAPES}, got {shape!r}")
    inf = math.inf
    if shape == "sphere":
        if radius is None:
            raise ValueError("radius is required for a sphere (allowed range (0, inf))")
        if half_extents is not None:
            raise ValueError("a sphere takes radius, not half_extents (half_extents is for boxes)")
        r = _scalar("radius", radius, 0.0, inf, None, open_lo=True)
        he = np.full(3, float(r))
    else:
        if half_extents is None:
            raise ValueError("half_extents is required for a box (3 numbers in (0, inf))")
        if radius is not None:
            raise ValueError("a box takes half_extents, not radius (radius is for spheres)")
        he = _vec("half_extents", half_extents, 3, None)
        if np.any(he <= 0):
            raise ValueError(
                f"half_extents must be > 0 (allowed range (0, inf)), got {he.tolist()}"
            )
        r = np.linalg.norm(he)
    q = _vec("orientation", orientation, 4, None)
    if np.linalg.norm(q) == 0:
        raise ValueError(
            f"orientation must be a non-zero quaternion (w, x, y, z), got {q.tolist()}"
        )
    q = q / np.linalg.norm(q)
    return RigidBody(
        position=_vec("position", position, 3, dtype),
        orientation=jnp.asarray(q, dtype),
        velocity=_vec("velocity", velocity, 3, dtype),
        angular_velocity=_vec("angular_velocity", angular_velocity, 3, dtype),
        mass=_scalar("mass", mass, 0.0, inf, dtype, open_lo=True),
        radius=jnp.asarray(r, dtype),
        half_extents=jnp.asarray(he, dtype),
        restitution=_scalar("restitution", restitution, 0.0, 1.0, dtype),
        friction=_scalar("friction", friction, 0.0, inf, dtype),
        linear_drag=_scalar("linear_drag", linear_drag, 0.0, inf, dtype),
        orthogonal_drag=_scalar("orthogonal_drag", orthogonal_drag, 0.0, inf, dtype),
        angular_drag=_scalar("angular_drag", angular_drag, 0.0, inf, dtype),
        shape=shape,
    )


def make_thrusters(points, directions, strengths, dtype=None) -> Thrusters:
    """Validated `Thrusters`: points and directions (k, 3) in the body frame, strengths (k,) N.

    Directions are normalised; a zero direction raises ValueError.
    """
    dtype = dtype or jnp.zeros(()).dtype
    p = np.asarray(points, np.float64).reshape(-1, 3) if np.size(points) else np.zeros((0, 3))
    d = (
        np.asarray(directions, np.float64).reshape(-1, 3)
        if np.size(directions)
        else np.zeros((0, 3))
    )
    s = np.asarray(strengths, np.float64).reshape(-1)
    if not (p.shape[0] == d.shape[0] == s.shape[0]):
        raise ValueError(
            f"thruster points, directions and strengths must have the same count, got "
            f"{p.shape[0]}, {d.shape[0]}, {s.shape[0]}"
        )
    n = np.linalg.norm(d, axis=-1, keepdims=True)
    if np.any(n == 0) or not (np.all(np.isfinite(d)) and np.all(np.isfinite(p))):
        raise ValueError(f"thruster directions must be finite and non-zero, got {d.tolist()}")
    if not np.all(np.isfinite(s)):
        raise ValueError(f"thruster strengths must be finite, got {s.tolist()}")
    return Thrusters(jnp.asarray(p, dtype), jnp.asarray(d / n, dtype), jnp.asarray(s, dtype))


def make_settings(dt=1.0 / 60.0, gravity=(0.0, -9.81, 0.0), num_substeps=8, dtype=None):
    """Validated `RigidSettings`: dt > 0 s, gravity (3,) m/s^2, num_substeps >= 1."""
    dtype = dtype or jnp.zeros(()).dtype
    if not isinstance(num_substeps, int | np.integer) or num_substeps < 1:
        raise ValueError(f"num_substeps must be an integer >= 1, got {num_substeps!r}")
    return RigidSettings(
        dt=_scalar("dt", dt, 0.0, math.inf, dtype, open_lo=True),
        gravity=_vec("gravity", gravity, 3, dtype),
        num_substeps=int(num_substeps),
    )


BODY_KEYS = {
    "shape", "radius", "half_extents", "position", "velocity", "orientation", "angular_velocity",
    "mass", "restitution", "friction", "linear_drag", "orthogonal_drag", "angular_drag", "drag",
}  # fmt: skip


def bodies_from_config(entries: Sequence[Mapping], dtype=None) -> tuple[RigidBody, ...]:
    """Bodies from a list of TOML `[[bodies]]` tables (dicts).

    Keys: shape ("sphere" | "box"), radius (sphere) or half_extents (box), mass (> 0), position,
    velocity, orientation (w, x, y, z), angular_velocity, restitution ([0, 1]), friction (>= 0),
    linear_drag, orthogonal_drag, angular_drag (>= 0); `drag` sets linear and orthogonal drag at
    once. Errors name the entry index, the key, its value and the allowed range.
    """
    bodies = []
    for i, entry in enumerate(entries):
        if not isinstance(entry, Mapping):
            raise ValueError(f"bodies[{i}] must be a table, got {entry!r}")
        unknown = sorted(set(entry) - BODY_KEYS)
        if unknown:
            raise ValueError(f"bodies[{i}]: unknown key(s) {unknown}; allowed: {sorted(BODY_KEYS)}")
        kw = dict(entry)
        shape = kw.pop("shape", "sphere")
        if "drag" in kw:
            drag = kw.pop("drag")
            kw.setdefault("linear_drag", drag)
            kw.setdefault("orthogonal_drag", drag)
        if "mass" not in kw:
            raise ValueError(f"bodies[{i}]: key 'mass' is required (kg, allowed range (0, inf))")
        if shape == "sphere" and "half_extents" in kw:
            raise ValueError(f"bodies[{i}]: a sphere takes 'radius', not 'half_extents'")
        if shape == "box" and "radius" in kw:
            raise ValueError(f"bodies[{i}]: a box takes 'half_extents', not 'radius'")
        try:
            bodies.append(make_body(shape, dtype=dtype, **kw))
        except ValueError as err:
            raise ValueError(f"bodies[{i}]: {err}") from None
    return tuple(bodies)
