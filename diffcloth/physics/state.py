"""Evolving state (ClothState) and fixed simulation settings (SimSettings)."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from diffcloth.representable import check_representable

INTEGRATORS = ("symplectic", "implicit")
#: contact velocity rules: "auto" is "displacement" for the implicit integrator, else "coulomb"
FRICTION_RULES = ("auto", "coulomb", "displacement", "impact")
#: how the pipeline differentiates the rollout (see SimSettings.gradient, physics.sensitivity)
GRADIENT_MODES = ("auto", "forward", "reverse")


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ClothState:
    """Positions x (rows, cols, 3) in m and velocities v (rows, cols, 3) in m/s.

    A trajectory is a ClothState whose leaves carry a leading frame axis: (frames, rows, cols, 3).
    """

    x: jax.Array
    v: jax.Array


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class SimSettings:
    """How the cloth is stepped. Fixed for a run; arrays follow the run's dtype.

    Attributes:
      dt: () seconds per frame (one rendered frame = num_substeps substeps).
      gravity: (3,) m/s^2, y up.
      wind: (3,) m/s, the air velocity the drag acts relative to.
      collision_margin: () m, colliders are inflated by this much (cloth thickness).
      num_substeps: static, substeps per frame.
      integrator: static, "symplectic" (explicit symplectic Euler) or "implicit" (backward Euler,
        Newton + conjugate gradients).
      newton_iters, cg_iters: static, iterations of the implicit solver.
      cg_tol: static, relative tolerance of the CG and of the gradient's linear solve.
      friction_rule: static, contact velocity rule (FRICTION_RULES): "coulomb" removes the
        approaching normal velocity and shrinks the tangential one by friction * that speed;
        "displacement" first resets a projected point's velocity to its displacement over the
        substep (position-based); "impact" is "coulomb" with the friction also moving the point
        from the estimated time of impact on (continuous in the parameters); "auto" picks
        "displacement" for implicit, "impact" otherwise.
        `collision_margin` is the contact thickness.
      gradient: static, how the pipeline differentiates the rollout (`physics.sensitivity`):
        "forward" carries the tangents of the differentiated inputs along the rollout (forward
        sensitivities, cheap for a few scalar parameters), "reverse" replays it backwards
        (checkpointed), "reverse" is the default; "auto" picks forward when at most 2 scalars are
        differentiated and their Jacobian fits 256 MB, else reverse.
      self_contact: None (off, the default) or a `mesh.selfcontact.SelfContact` from
        `grid_contact.make_grid_self_contact`: self-contact between the net's layers
        (`physics.grid_contact`; a pytree child, so None traces the same program as before).
    """

    dt: jax.Array
    gravity: jax.Array
    wind: jax.Array
    collision_margin: jax.Array
    num_substeps: int = dataclasses.field(default=16, metadata={"static": True})
    integrator: str = dataclasses.field(default="symplectic", metadata={"static": True})
    newton_iters: int = dataclasses.field(default=3, metadata={"static": True})
    cg_iters: int = dataclasses.field(default=200, metadata={"static": True})
    cg_tol: float = dataclasses.field(default=1e-5, metadata={"static": True})
    friction_rule: str = dataclasses.field(default="auto", metadata={"static": True})
    gradient: str = dataclasses.field(default="reverse", metadata={"static": True})
    self_contact: Any = None

    @property
    def h(self):
        """Substep length in s."""
        return self.dt / self.num_substeps


def _check_int(name: str, value, lo: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise TypeError(f"{name}: must be an int, got {value!r}")
    if value < lo:
        raise ValueError(f"{name}: must be >= {lo} (allowed range [{lo}, inf)), got {value}")
    return int(value)


def _check_vec3(name: str, value) -> np.ndarray:
    arr = np.asarray(value, np.float64)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: must be a finite 3-vector, got {np.asarray(value).tolist()}")
    return arr


def make_sim(
    dt: float = 1.0 / 30.0,
    *,
    gravity=(0.0, -9.81, 0.0),
    wind=(0.0, 0.0, 0.0),
    num_substeps: int = 16,
    integrator: str = "symplectic",
    collision_margin: float = 0.0,
    newton_iters: int = 3,
    cg_iters: int = 200,
    cg_tol: float = 1e-5,
    friction_rule: str = "auto",
    gradient: str = "reverse",
    dtype=None,
) -> SimSettings:
    """Validated constructor for SimSettings (see its attributes).

    Raises ValueError for dt <= 0 or non-finite, num_substeps < 1, an unknown integrator, and
    TypeError for non-integer counts.

    Shapes: gravity, wind (3,) m/s^2, m/s; dt () s -> SimSettings with those leaves.
    """
    dt_f = float(np.asarray(dt, np.float64))
    if not math.isfinite(dt_f) or dt_f <= 0:
        raise ValueError(f"dt: must be finite and > 0 s (allowed range (0, inf)), got {dt!r}")
    _check_int("num_substeps", num_substeps, 1)
    _check_int("newton_iters", newton_iters, 1)
    _check_int("cg_iters", cg_iters, 1)
    if integrator not in INTEGRATORS:
        raise ValueError(f"integrator: must be one of {INTEGRATORS}, got {integrator!r}")
    margin = float(collision_margin)
    if not math.isfinite(margin) or margin < 0:
        raise ValueError(f"collision_margin: must be in [0, inf) m, got {collision_margin!r}")
    if friction_rule not in FRICTION_RULES:
        raise ValueError(f"friction_rule: must be one of {FRICTION_RULES}, got {friction_rule!r}")
    if gradient not in GRADIENT_MODES:
        raise ValueError(f"gradient: must be one of {GRADIENT_MODES}, got {gradient!r}")
    if not (0 < cg_tol < 1):
        raise ValueError(f"cg_tol: must be in (0, 1), got {cg_tol!r}")
    dtype = dtype or jnp.zeros(()).dtype
    gravity, wind = _check_vec3("gravity", gravity), _check_vec3("wind", wind)
    for what, value in (("dt", dt_f), ("gravity", gravity), ("wind", wind),
                        ("collision_margin", margin)):  # fmt: skip
        check_representable(what, value, dtype)  # in the run's dtype
    return SimSettings(
        dt=jnp.asarray(dt_f, dtype),
        gravity=jnp.asarray(gravity, dtype),
        wind=jnp.asarray(wind, dtype),
        collision_margin=jnp.asarray(margin, dtype),
        num_substeps=int(num_substeps),
        integrator=integrator,
        newton_iters=int(newton_iters),
        cg_iters=int(cg_iters),
        cg_tol=float(cg_tol),
        friction_rule=friction_rule,
        gradient=gradient,
    )


def rest_state(net, velocity=None) -> ClothState:
    """The net at rest: x = net.rest, v = 0 (or a uniform (3,) velocity in m/s)."""
    v = jnp.zeros_like(net.rest)
    if velocity is not None:
        v = v + jnp.asarray(velocity, net.rest.dtype)[None, None, :]
    return ClothState(x=net.rest, v=v)


def validate_state(net, state: ClothState) -> ClothState:
    """Eager check of a concrete state: shapes match the net and every value is finite.

    Shapes: state x, v (rows, cols, 3), matching the net.
    """
    for name in ("x", "v"):
        arr = np.asarray(getattr(state, name))
        if arr.shape != (net.rows, net.cols, 3):
            raise ValueError(
                f"state.{name}: expected shape ({net.rows}, {net.cols}, 3), got {arr.shape}"
            )
        if not np.all(np.isfinite(arr)):
            bad = np.argwhere(~np.isfinite(arr))[0].tolist()
            raise ValueError(f"state.{name}: must be finite, found {arr[tuple(bad)]} at {bad}")
    return state
