"""One frame of cloth dynamics: `num_substeps` substeps of one integrator, then pins and colliders.

Both integrators share one signature. `step` is the public per-frame function that coupled code (rigid
bodies, the pipeline) can call inside its own `lax.scan`:

    step(net, sim, material, state, colliders=None, *, pin_target=None) -> ClothState

- symplectic: semi-implicit (symplectic) Euler, v += h f(x, v) / m; x += h v. Conditionally stable:
  h below the limit of `rollout.stable_substep` (docs/physics.md, "Stability estimate").
- implicit: backward Euler in the velocity, m (v' - v) = h f(x + h v', v'), solved by Newton with
  matrix-free conjugate gradients on a positive semi-definite Newton matrix. Its gradient is taken
  implicitly (`jax.lax.custom_root`, BiCGSTAB on the exact linearisation), not through the iterations.
  Gravity and drag are explicit; springs, bending and spring damping are implicit.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from diffcloth.physics.collide import Colliders, collide
from diffcloth.physics.forces import (
    _external_forces,
    _internal_force_differential,
    _internal_forces,
    _total_forces,
    from_planar,
    hand_vjp,
    node_mass,
    to_planar,
    total_forces_fn,
)
from diffcloth.physics.grid_contact import planar_hooks
from diffcloth.physics.material import Material
from diffcloth.physics.net import Net
from diffcloth.physics.state import ClothState, SimSettings


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Contacts:
    """Impulses (N s) that the colliders gave to the cloth during one step.

    sphere: (n, 3) per sphere; plane: (m, 3) per plane. For two-way coupling apply the opposite
    impulse to the rigid body.
    """

    sphere: jax.Array
    plane: jax.Array


def cg(matvec, b, *, tol, maxiter, precond=None):
    """Matrix-free (Jacobi-preconditioned) conjugate gradients for a symmetric positive operator.

    A plain while-loop (no custom_linear_solve inside), stopping at |r| <= tol |b| or maxiter.
    `precond` is the inverse diagonal (same shape as b) or None. Returns (solution, iterations).
    """
    pre = (lambda r: r) if precond is None else (lambda r: precond * r)
    bb = jnp.sum(b * b)
    stop = (tol * tol) * bb

    def cond(c):
        _, r, _, _, k = c
        return (jnp.sum(r * r) > stop) & (k < maxiter)

    def body(c):
        x, r, p, rz, k = c
        ap = matvec(p)
        pap = jnp.sum(p * ap)
        alpha = jnp.where(pap > 0, rz / jnp.where(pap > 0, pap, 1.0), 0.0)
        x = x + alpha * p
        r = r - alpha * ap
        z = pre(r)
        rz_new = jnp.sum(r * z)
        beta = jnp.where(rz > 0, rz_new / jnp.where(rz > 0, rz, 1.0), 0.0)
        return x, r, z + beta * p, rz_new, k + 1

    z0 = pre(b)
    x, _, _, _, k = jax.lax.while_loop(cond, body, (jnp.zeros_like(b), b, z0, jnp.sum(b * z0), 0))
    return x, k


def bicgstab(matvec, b, *, tol, maxiter):
    """Matrix-free BiCGSTAB for a general (non-symmetric) operator; a plain while-loop.

    Shapes: b (...) any shape, matvec (...) -> (...) -> solution with b's shape.
    """
    bb = jnp.sum(b * b)
    stop = (tol * tol) * bb
    safe = lambda d: jnp.where(jnp.abs(d) > 0, d, 1.0)

    def cond(c):
        return (c[7] > stop) & (c[8] < maxiter)

    def body(c):
        x, r, p, v, rho, alpha, omega, _, k = c
        rho_new = jnp.sum(b * r)
        beta = (rho_new / safe(rho)) * (alpha / safe(omega))
        p = r + beta * (p - omega * v)
        v = matvec(p)
        alpha = rho_new / safe(jnp.sum(b * v))
        s = r - alpha * v
        t = matvec(s)
        omega = jnp.sum(t * s) / safe(jnp.sum(t * t))
        x = x + alpha * p + omega * s
        r = s - omega * t
        return x, r, p, v, rho_new, alpha, omega, jnp.sum(r * r), k + 1

    one = jnp.ones((), b.dtype)
    z = jnp.zeros_like(b)
    x, *_ = jax.lax.while_loop(cond, body, (z, b, z, z, one, one, one, bb, 0))
    return x


def _stiffness_diagonal(net, material):
    """(rows, cols) sum of the stiffnesses (N/m) of the springs at each node, plus bending."""
    kh = material.stretch * net.weight_h
    kv = material.stretch * net.weight_v
    kd = material.shear * net.weight_d
    p = lambda a, t, b, l, r: jnp.pad(a, ((t, b), (l, r)))
    out = p(kh, 0, 0, 0, 1) + p(kh, 0, 0, 1, 0) + p(kv, 0, 1, 0, 0) + p(kv, 1, 0, 0, 0)
    out = out + p(kd, 0, 1, 0, 1) + p(kd, 1, 0, 1, 0) + p(kd, 0, 1, 1, 0) + p(kd, 1, 0, 0, 1)
    bh = material.bend * net.weight_bh
    bv = material.bend * net.weight_bv
    out = out + p(bh, 0, 0, 0, 2) + 4.0 * p(bh, 0, 0, 1, 1) + p(bh, 0, 0, 2, 0)
    out = out + p(bv, 0, 2, 0, 0) + 4.0 * p(bv, 1, 1, 0, 0) + p(bv, 2, 0, 0, 0)
    return out


# Substeps work on planar arrays (3, rows, cols); free is (rows, cols) bool, mass (rows, cols).


def _symplectic_substep(net, sim, material, x, v, mass, free, h):
    f = _total_forces(net, material, x, v, sim.gravity, sim.wind)
    safe_mass = jnp.where(free, mass, 1.0)
    # the barrier keeps XLA from recomputing the whole force loop a second time for x
    v1 = jax.lax.optimization_barrier(v + h * f / safe_mass[None])
    return x + h * v1, v1


def _implicit_substep(net, sim, material, x, v, mass, free, h, pin_v):
    f_ext = _external_forces(net, material, x, v, sim.gravity, sim.wind)
    safe_mass = jnp.where(free, mass, 1.0)[None]
    free3 = free[None]

    def residual(v1):
        fi = _internal_forces(net, material, x + h * v1, v1)
        r = safe_mass * (v1 - v) - h * (fi + f_ext)
        return jnp.where(free3, r, v1 - pin_v)

    # The Newton solver is not differentiated (custom_root differentiates the root implicitly), so
    # everything it closes over is cut from the gradient.
    ng = jax.lax.stop_gradient
    net_ng, mat_ng, x_ng, h_ng, m_ng = ng(net), ng(material), ng(x), ng(h), ng(safe_mass)

    # Jacobi preconditioner: m + (h^2 + h c) * (sum of incident spring stiffnesses + bending).
    kdiag = _stiffness_diagonal(net_ng, mat_ng)
    diag = m_ng + ((h_ng * h_ng + h_ng * mat_ng.damping) * kdiag)[None]
    precond = jnp.where(free3, 1.0 / diag, 0.0)

    def newton(res, v1):
        def body(_, v1):
            r = res(v1)
            xn = x_ng + h_ng * v1

            def matvec(d):
                d = jnp.where(free3, d, 0.0)
                df = _internal_force_differential(net_ng, mat_ng, xn, h_ng * h_ng * d, h_ng * d)
                return jnp.where(free3, m_ng * d - df, 0.0)

            delta, _ = cg(
                matvec,
                -jnp.where(free3, r, 0.0),
                tol=sim.cg_tol,
                maxiter=sim.cg_iters,
                precond=precond,
            )
            return v1 + jnp.where(free3, delta, 0.0)

        return jax.lax.fori_loop(0, sim.newton_iters, body, v1)

    def tangent_solve(g, y):
        solve = lambda op, rhs: bicgstab(op, rhs, tol=sim.cg_tol, maxiter=4 * sim.cg_iters)
        return jax.lax.custom_linear_solve(g, y, solve=solve, transpose_solve=solve)

    f0 = _internal_forces(net, material, x, v) + f_ext
    guess = jax.lax.stop_gradient(jnp.where(free3, v + h * f0 / safe_mass, pin_v))
    v1 = jax.lax.custom_root(residual, guess, newton, tangent_solve)
    return x + h * v1, v1


def _displacement_rule(sim) -> bool:
    rule = getattr(sim, "friction_rule", "auto")
    return rule == "displacement" or (rule == "auto" and sim.integrator == "implicit")


def _impact_rule(sim) -> bool:
    rule = getattr(sim, "friction_rule", "auto")
    return rule == "impact" or (rule == "auto" and sim.integrator != "implicit")


def step_with_contacts(
    net: Net,
    sim: SimSettings,
    material: Material,
    state: ClothState,
    colliders: Colliders | None = None,
    *,
    pin_target=None,
) -> tuple[ClothState, Contacts]:
    """Advance one frame (sim.dt seconds); also return the collider impulses.

    Args:
      net, sim: fixed structure and settings.
      material: differentiable material parameters.
      state: ClothState at the start of the frame.
      colliders: Colliders for this frame (no frame axis), or None. Spheres move with their
        `sphere_velocity` during the frame.
      pin_target: optional (rows, cols, 3) positions the pinned points reach at the end of the frame
        (they move linearly during it); None keeps pinned points where they are, at rest.
    Returns:
      (state at the end of the frame, Contacts).
    """
    if sim.integrator == "implicit" and hasattr(material, "total_forces_planar"):
        raise ValueError(
            "integrator: 'implicit' supports the continuum Material only; "
            f"{type(material).__name__} runs with integrator = 'symplectic'"
        )
    num = sim.num_substeps
    h = sim.dt / num
    mass = node_mass(net, material)
    free = ~net.pinned
    free3 = free[None]
    x0 = to_planar(state.x)
    if pin_target is None:
        pin_v = jnp.zeros_like(x0)
    else:
        pin_v = (to_planar(pin_target) - x0) / sim.dt
    dtype = state.x.dtype
    n_s = 0 if colliders is None else colliders.num_spheres
    n_p = 0 if colliders is None else colliders.num_planes

    def constrain(x, x1, v1, t, v0=None):
        """Pins and colliders after the substep that ends at time t."""
        x1 = jnp.where(free3, x1, x0 + pin_v * t)
        v1 = jnp.where(free3, v1, pin_v)
        dsi = jnp.zeros((n_s, 3), dtype)
        dpi = jnp.zeros((n_p, 3), dtype)
        if colliders is not None:
            x1, v1, dsi, dpi = collide(
                x1,
                v1,
                mass,
                free,
                colliders,
                material.friction,
                sim.collision_margin,
                t,
                x_prev=x if _displacement_rule(sim) else None,
                h=h,
                x_start=x if _impact_rule(sim) else None,
                v_start=v0 if _impact_rule(sim) else None,
            )
        return x1, v1, dsi, dpi

    # self-contact (grid_contact): a static switch, off leaves the traced program unchanged
    sc = getattr(sim, "self_contact", None)
    if sc is not None:
        g = jnp.sqrt(jnp.sum(sim.gravity**2)) if sim.integrator == "implicit" else 0.0
        contact = planar_hooks(net, sc, material, mass, free, h, g)
    else:
        contact = None
    zeros_si = jnp.zeros((n_s, 3), dtype)
    zeros_pi = jnp.zeros((n_p, 3), dtype)
    if sim.integrator == "symplectic":
        safe_mass = jnp.where(free, mass, 1.0)[None]
        # material-dependent stencil frames built once per frame, outside the substep loop
        forces = total_forces_fn(net, material, sim.gravity, sim.wind)

        def kick(x, v):
            return v + h * forces(x, v) / safe_mass

        # Kick-drift order with the drift first in the loop body: iteration s drifts substep s - 1
        # (x += h v, pins, colliders) and then kicks substep s. Each loop output then depends on the
        # force loop once (x and v computed in one body would make XLA evaluate the forces twice).
        # vk: the velocity before the last kick (the "impact" rule credits the kick's lift-off)
        # with self-contact the carry also holds the pairs (`grid_contact.PairCache`); at s = 0
        # they are found at x0 and kept
        def substep(carry, s):
            x, v, vk, si, pi = carry[:5]
            t = s.astype(dtype) * h
            x1, v1, dsi, dpi, *cache = drift(x, v, t, vk, *carry[5:])
            first = s == 0
            x1 = jnp.where(first, x, x1)
            v1 = jnp.where(first, v, v1)
            si = jnp.where(first, si, si + dsi)
            pi = jnp.where(first, pi, pi + dpi)
            return (x1, kick(x1, v1), v1, si, pi, *cache), None

        v_init = to_planar(state.v)
        init = (x0, v_init, v_init, zeros_si, zeros_pi)
        # With the hand-written force VJP the substeps are not checkpointed (the frame is, in
        # `rollout`): the VJP keeps only (x, v) and the force itself (for the mass's cotangent),
        # three (3, R, C) arrays per substep, no more than a checkpointed substep's carry, and the
        # backward pass evaluates the forces twice instead of three times (0.75x gradient time at
        # 128 x 128). Only the colliders are checkpointed (their many per-collider intermediates
        # are cheap to recompute). Autodiff forces (another force model, `autodiff_forces`) would
        # keep every intermediate of the force loop, so their whole substeps stay checkpointed.
        constrain_remat = jax.checkpoint(constrain, prevent_cse=False)

        def drift(x, v, t, vk, *cache):  # x += h v, pins, colliders (and self-contact)
            if contact is None:
                return constrain_remat(x, x + h * v, v, t, vk)
            c, r = contact.refresh(cache[0], x, v)
            v = contact.respond(c, x, v)
            x1, v1, dsi, dpi = constrain_remat(x, x + h * v, v, t, vk)
            return (*contact.bound(c, r, x, x1, v1), dsi, dpi, c)

        if not hand_vjp(material):
            substep = jax.checkpoint(substep, prevent_cse=False)
        if contact is not None:
            init = (*init, contact.empty(x0))
        (x, v, vk, si, pi, *cache), _ = jax.lax.scan(substep, init, jnp.arange(num))
        if contact is None:
            x, v, dsi, dpi = constrain_remat(x, x + h * v, v, num * h, vk)
        else:
            x, v, dsi, dpi, _ = drift(x, v, num * h, vk, *cache)
        si, pi = si + dsi, pi + dpi
    elif sim.integrator == "implicit":

        def substep(carry, s):
            x, v, si, pi = carry[:4]
            t = (s + 1).astype(dtype) * h
            if contact is not None:
                c, r = contact.refresh(carry[4], x, v)
                v = contact.respond(c, x, v)
            x1, v1 = _implicit_substep(net, sim, material, x, v, mass, free, h, pin_v)
            x1, v1, dsi, dpi = constrain(x, x1, v1, t, v)
            if contact is not None:
                x1, v1 = contact.bound(c, r, x, x1, v1)
                return (x1, v1, si + dsi, pi + dpi, c), None
            return (x1, v1, si + dsi, pi + dpi), None

        init = (x0, to_planar(state.v), zeros_si, zeros_pi)
        if contact is not None:
            init = (*init, contact.empty(x0))
        (x, v, si, pi, *_), _ = jax.lax.scan(substep, init, jnp.arange(num))
    else:
        raise ValueError(f"integrator: unknown {sim.integrator!r}")
    x, v = from_planar(x), from_planar(v)
    return ClothState(x=x, v=v), Contacts(sphere=si, plane=pi)


def step(
    net: Net,
    sim: SimSettings,
    material: Material,
    state: ClothState,
    colliders: Colliders | None = None,
    *,
    pin_target=None,
) -> ClothState:
    """Advance one frame (sim.dt seconds, sim.num_substeps substeps of sim.integrator).

    See `step_with_contacts` for the arguments. Pure and jit-able; differentiable in material,
    state, collider arrays and pin targets.
    """
    return step_with_contacts(net, sim, material, state, colliders, pin_target=pin_target)[0]


def symplectic_euler(net, sim, material, state, colliders=None, *, pin_target=None) -> ClothState:
    """One frame with the explicit symplectic integrator, whatever sim.integrator says.

    Shapes: state x, v (rows, cols, 3); pin_target (rows, cols, 3) m -> state (rows, cols, 3).
    """
    sim = dataclasses.replace(sim, integrator="symplectic")
    return step(net, sim, material, state, colliders, pin_target=pin_target)


def implicit_euler(net, sim, material, state, colliders=None, *, pin_target=None) -> ClothState:
    """One frame with the implicit (backward Euler) integrator, whatever sim.integrator says.

    Shapes: state x, v (rows, cols, 3); pin_target (rows, cols, 3) m -> state (rows, cols, 3).
    """
    sim = dataclasses.replace(sim, integrator="implicit")
    return step(net, sim, material, state, colliders, pin_target=pin_target)


STEPS = {"symplectic": symplectic_euler, "implicit": implicit_euler}
