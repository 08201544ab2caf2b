"""A whole run of a mesh cloth, as the pipeline takes it: the run's settings (`MeshSim`), the
seeded start state, and `mesh_trajectory`, which is either the dynamic rollout or the static
equilibrium, with a per-frame status that says why a frame is not a shape.

The trajectory has the grid's layout (a ClothState with a leading frame axis), so the pipeline's
checks (`physics.frames_ok`) and renderers take it unchanged. A frame whose solve did not
converge is NaN: it is never returned as a plausible shape.
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from diffcloth.physics.mesh.dynamics import mesh_rollout
from diffcloth.physics.mesh.selfcontact import SelfContact
from diffcloth.physics.mesh.solve import SolverSettings, equilibrium
from diffcloth.physics.mesh.topology import ClothMesh
from diffcloth.physics.state import ClothState

__all__ = [
    "MESH_INTEGRATORS",
    "MESH_MODES",
    "MeshSim",
    "MeshStatus",
    "make_mesh_sim",
    "mesh_trajectory",
    "perturbed_start",
    "status_message",
]

#: [sim] mode of a mesh cloth: "dynamic" (a rollout over frames) or "equilibrium" (the rest shape)
MESH_MODES = ("dynamic", "equilibrium")
#: integrators of the dynamic mode (`dynamics.mesh_rollout`)
MESH_INTEGRATORS = ("implicit", "symplectic")


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class MeshSim:
    """How a mesh cloth is run. Arrays follow the run's dtype; the rest is static.

    Attributes:
      dt: () s per frame.
      gravity: (3,) m/s^2, y up.
      wind: (3,) m/s (drag acts relative to it; dynamic mode only).
      num_substeps: static, solver steps per frame (dynamic).
      integrator: static, "implicit" or "symplectic" (dynamic).
      mode: static, "dynamic" or "equilibrium" (MESH_MODES).
      solver: static `SolverSettings` of the Newton solves.
      gradient: static, always "reverse" (the equilibrium's gradient is the implicit function
        theorem's; forward sensitivities do not apply); kept for the pipeline's interface.
      self_contact: `selfcontact.SelfContact` or None (off; [sim] self_contact).
    """

    dt: jax.Array
    gravity: jax.Array
    wind: jax.Array
    num_substeps: int = dataclasses.field(default=1, metadata={"static": True})
    integrator: str = dataclasses.field(default="implicit", metadata={"static": True})
    mode: str = dataclasses.field(default="dynamic", metadata={"static": True})
    solver: SolverSettings = SolverSettings()
    gradient: str = dataclasses.field(default="reverse", metadata={"static": True})
    self_contact: SelfContact | None = None


def make_mesh_sim(
    dt: float = 1.0 / 30.0,
    *,
    gravity=(0.0, -9.81, 0.0),
    wind=(0.0, 0.0, 0.0),
    num_substeps: int = 1,
    integrator: str = "implicit",
    mode: str = "dynamic",
    solver_iters: int | None = None,
    solver_tol: float = 1e-3,
    dtype=None,
) -> MeshSim:
    """Validated MeshSim. solver_iters: Newton iterations at most (default 200 for the
    equilibrium, 20 per implicit step); solver_tol: `SolverSettings.tol` (the largest free
    force over its vertex weight at convergence; float32 cannot resolve much below 1e-2 on stiff
    fabrics). Raises ValueError naming the bad setting."""
    if mode not in MESH_MODES:
        raise ValueError(f"mode: must be one of {MESH_MODES}, got {mode!r}")
    if integrator not in MESH_INTEGRATORS:
        raise ValueError(f"integrator: must be one of {MESH_INTEGRATORS}, got {integrator!r}")
    if not (isinstance(num_substeps, int) and num_substeps >= 1):
        raise ValueError(f"num_substeps: must be an integer >= 1, got {num_substeps!r}")
    if not (math.isfinite(float(dt)) and float(dt) > 0):
        raise ValueError(f"dt: must be finite and > 0 s, got {dt!r}")
    if solver_iters is None:
        solver_iters = 200 if mode == "equilibrium" else 20
    if not (isinstance(solver_iters, int) and solver_iters >= 1):
        raise ValueError(f"solver_iters: must be an integer >= 1, got {solver_iters!r}")
    if not (0 < solver_tol < 1):
        raise ValueError(f"solver_tol: must be in (0, 1), got {solver_tol!r}")
    dtype = dtype or jnp.zeros(()).dtype
    return MeshSim(
        dt=jnp.asarray(dt, dtype),
        gravity=jnp.asarray(gravity, dtype),
        wind=jnp.asarray(wind, dtype),
        num_substeps=int(num_substeps),
        integrator=integrator,
        mode=mode,
        solver=SolverSettings(max_iters=int(solver_iters), tol=float(solver_tol)),
    )


def perturbed_start(
    cloth: ClothMesh, x, *, mode: int, amplitude: float, seed: int = 0
) -> np.ndarray:
    """x (n, 3) m plus a fold-seeding bump along +y on the free vertices (numpy, eager):

        dy = amplitude * (r / r_max)^2 * cos(mode * phi + phase)

    with r, phi the polar coordinates in the xz-plane about the vertex mean, and the phase
    drawn from `seed`. Pinned vertices do not move. mode: number of waves around (>= 1);
    amplitude: m."""
    x = np.asarray(x, np.float64)
    rel = x - x.mean(axis=0)
    r = np.hypot(rel[:, 0], rel[:, 2])
    phi = np.arctan2(rel[:, 2], rel[:, 0])
    phase = np.random.default_rng(seed).uniform(0.0, 2.0 * np.pi)
    bump = amplitude * (r / max(float(r.max()), 1e-12)) ** 2 * np.cos(mode * phi + phase)
    bump = np.where(np.asarray(cloth.pinned), 0.0, bump)
    out = x.copy()
    out[:, 1] += bump
    return out


class MeshStatus(NamedTuple):
    """Per-frame status of a mesh run: converged (T,) bool (dynamic: the frame is finite);
    iterations (T,) int (equilibrium; -1 in dynamic mode); residual (T,) the largest free force
    over its vertex weight (equilibrium; NaN in dynamic mode)."""

    converged: jax.Array
    iterations: jax.Array
    residual: jax.Array


def mesh_trajectory(
    cloth: ClothMesh, sim: MeshSim, fabric, state: ClothState, colliders, *, num_frames: int
) -> tuple[ClothState, MeshStatus]:
    """The run of a mesh cloth: (trajectory, status).

    Dynamic: `dynamics.mesh_rollout` over num_frames frames of sim.dt (a non-converged implicit
    step is already NaN). Equilibrium: one frame, the rest shape reached from state.x (pins held
    there; `solve.equilibrium`), v = 0; NaN unless the solve converged.
    Shapes: state x, v (n, 3) -> trajectory x, v (T, n, 3), T = num_frames (dynamic) or 1.
    Differentiable in fabric, colliders, gravity and the pins (equilibrium: implicit function
    theorem).
    """
    if sim.mode == "equilibrium":
        res = equilibrium(cloth, fabric, state.x, gravity=sim.gravity, colliders=colliders,
                          settings=sim.solver, self_contact=sim.self_contact)  # fmt: skip
        x = jnp.where(res.converged, res.x, jnp.nan)
        traj = ClothState(x=x[None], v=jnp.zeros_like(x)[None])
        status = MeshStatus(res.converged[None], jnp.asarray(res.iterations)[None],
                            res.residual[None])  # fmt: skip
        return traj, status
    traj = mesh_rollout(
        cloth, fabric, state, dt=sim.dt, num_frames=num_frames, num_substeps=sim.num_substeps,
        integrator=sim.integrator, gravity=sim.gravity, wind=sim.wind, colliders=colliders,
        settings=sim.solver, self_contact=sim.self_contact,
    )  # fmt: skip
    finite = jnp.all(jnp.isfinite(traj.x), axis=(1, 2)) & jnp.all(jnp.isfinite(traj.v), axis=(1, 2))
    status = MeshStatus(finite, jnp.full((num_frames,), -1), jnp.full((num_frames,), jnp.nan))
    return traj, status


def status_message(sim: MeshSim, status: MeshStatus) -> str | None:
    """Eager: why a mesh run is not a shape (None when every frame converged).
    Shapes: none.
    """
    ok = np.asarray(status.converged)
    if ok.all():
        return None
    k = int(np.argmin(ok))
    if sim.mode == "equilibrium":
        its, res = int(np.asarray(status.iterations)[k]), float(np.asarray(status.residual)[k])
        return (
            f"the equilibrium solve did not converge after {its} Newton iterations (largest "
            f"free force {res:.3g} x its vertex weight, tolerance {sim.solver.tol:g}); raise "
            "[sim] solver_iters, seed the drape with [sim] perturb, or check the fabric values"
        )
    return (
        f"the {sim.integrator} step of frame {k} did not converge or became non-finite; lower "
        "[sim] dt, raise num_substeps or solver_iters"
        + (" (with [sim] self_contact: raise solver_iters to 200, or self_contact_capacity if "
           "the broad phase overflowed)" if sim.self_contact is not None else "")
    )  # fmt: skip
