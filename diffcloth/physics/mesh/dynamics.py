"""Time stepping of the mesh cloth: implicit (backward) Euler by the Newton minimisation of
`solve` (the incremental potential, differentiable by the implicit function theorem),
symplectic Euler for small steps, and a checkpointed rollout.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from diffcloth.physics.mesh import colliders as mc
from diffcloth.physics.mesh import energy
from diffcloth.physics.mesh import selfcontact_step as scs
from diffcloth.physics.mesh.solve import SolverSettings, _argmin, _Problem, potential
from diffcloth.physics.state import ClothState

__all__ = ["implicit_step", "mesh_rollout", "symplectic_step"]

_STEP = SolverSettings(max_iters=30)  # an implicit step's Newton iterations at most
_ROLLOUT = SolverSettings(max_iters=20)  # ... inside a rollout


def _project_out(colliders, x, v):
    """Move vertices found inside a collider back to its surface and remove their inward
    velocity (a safety net: the penalty keeps them in the contact layer)."""
    if not mc.has_colliders(colliders):
        return x, v
    phi = mc.signed_distance(colliders, x)
    n = mc.contact_normals(colliders, x)
    inside = (phi < 0)[:, None]
    x = jnp.where(inside, x - phi[:, None] * n, x)
    vn = jnp.sum(v * n, axis=-1, keepdims=True)
    v = jnp.where(inside & (vn < 0), v - vn * n, v)
    return x, v


def implicit_step(cloth, fabric, state: ClothState, h, *, gravity, wind=None, colliders=None,
                  settings: SolverSettings = _STEP, self_contact=None) -> ClothState:  # fmt: skip
    """One implicit (backward) Euler step of length h (s): minimises the incremental potential
    (`solve`'s module docstring) by Newton; differentiable by the implicit function theorem. Pinned
    vertices keep their state. Non-convergence shows as non-finite positions (NaN), which the
    rollout's checks report. self_contact: `selfcontact.SelfContact` or None (off); on, the
    solve starts from x_n (intersection-free) instead of the inertial prediction.
    Shapes: state leaves (n, 3) m and m/s -> ClothState with (n, 3) leaves; h () s.
    """
    x_n, v_n = state.x, state.v
    dtype = x_n.dtype
    theta = {
        "cloth": cloth,
        "fabric": fabric,
        "colliders": colliders,
        "gravity": jnp.asarray(gravity, dtype),
        "x_pins": x_n,
        "free": ~cloth.pinned,
        "h": jnp.asarray(h, dtype),
        "x_n": x_n,
        "v_n": v_n,
        "wind": jnp.zeros(3, dtype) if wind is None else jnp.asarray(wind, dtype),
        "el_prev": energy.elastic_energy(cloth, fabric, x_n),
        "g_prev": jax.grad(lambda y: energy.elastic_energy(cloth, fabric, y))(x_n),
        "self_contact": self_contact,
    }
    start = x_n + h * v_n
    if self_contact is not None:
        # the candidate pairs at x_n (selfcontact_step): the friction frame's and the solve's
        theta["sc_pairs"] = scs.candidates(cloth, self_contact, jax.lax.stop_gradient(x_n))
        theta["sc_frame"] = scs.frame(cloth, self_contact, x_n, theta["sc_pairs"][0])
        start = x_n
    problem = _Problem("implicit", settings, 0.0, mc.has_colliders(colliders),
                       self_contact is not None)  # fmt: skip
    res = _argmin(problem, theta, jax.lax.stop_gradient(start))
    free = ~cloth.pinned
    x = jnp.where(res.converged, res.x, jnp.nan)
    v = jnp.where(free[:, None], (x - x_n) / h, v_n)
    x, v = _project_out(colliders, x, v)
    x = jnp.where(free[:, None], x, x_n)
    return ClothState(x=x, v=v)


def symplectic_step(cloth, fabric, state: ClothState, h, *, gravity, wind=None,
                    colliders=None) -> ClothState:  # fmt: skip
    """One symplectic (semi-implicit) Euler step of length h (s); stable for h below about
    sqrt(m / k) of the stiffest element (small steps only).
    Shapes: state leaves (n, 3) m and m/s -> ClothState with (n, 3) leaves; h () s.
    """
    free = ~cloth.pinned
    mass = energy.vertex_mass(cloth, fabric)
    wind = jnp.zeros(3, state.x.dtype) if wind is None else wind
    force = -jax.grad(lambda y: potential(cloth, fabric, y, gravity, colliders))(state.x)
    # Rayleigh damping: -damping K v as a directional derivative of the elastic force
    kv = jax.jvp(jax.grad(lambda y: energy.elastic_energy(cloth, fabric, y)), (state.x,),
                 (state.v,))[1]  # fmt: skip
    force = (
        force
        - fabric.damping * kv
        - fabric.drag * cloth.vertex_area[:, None] * (state.v - wind[None, :])
    )
    v = state.v + h * force / jnp.maximum(mass, 1e-30)[:, None]
    v = jnp.where(free[:, None], v, state.v)
    x = state.x + h * v
    x, v = _project_out(colliders, x, v)
    x = jnp.where(free[:, None], x, state.x)
    return ClothState(x=x, v=v)


def mesh_rollout(cloth, fabric, state: ClothState, *, dt, num_frames: int, num_substeps: int = 1,
                 integrator: str = "implicit", gravity, wind=None, colliders=None,
                 settings: SolverSettings = _ROLLOUT, self_contact=None) -> ClothState:  # fmt: skip
    """The trajectory: ClothState with leaves (num_frames, n, 3), frame k being the state after
    k + 1 frames of dt seconds (num_substeps steps each). lax.scan with a checkpointed body.
    self_contact (implicit integrator only): `selfcontact.SelfContact` or None."""
    h = dt / num_substeps
    if integrator == "implicit":
        step = lambda s: implicit_step(cloth, fabric, s, h, gravity=gravity, wind=wind,
                                       colliders=colliders, settings=settings,
                                       self_contact=self_contact)  # fmt: skip
    elif self_contact is not None:
        raise ValueError("self_contact: needs integrator = 'implicit' (the barrier lives in the "
                         f"implicit step's minimisation), got {integrator!r}")  # fmt: skip
    elif integrator == "symplectic":
        step = lambda s: symplectic_step(cloth, fabric, s, h, gravity=gravity, wind=wind,
                                         colliders=colliders)  # fmt: skip
    else:
        raise ValueError(f"integrator must be 'implicit' or 'symplectic', got {integrator!r}")

    @jax.checkpoint
    def frame(s, _):
        s = (
            jax.lax.fori_loop(0, num_substeps, lambda i, c: step(c), s)
            if num_substeps > 1
            else step(s)
        )
        return s, s

    return jax.lax.scan(frame, state, length=num_frames)[1]
