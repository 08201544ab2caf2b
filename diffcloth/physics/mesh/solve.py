"""Solvers of the mesh cloth: the static equilibrium (the shape at rest) and the Newton
minimisation that implicit Euler (`dynamics.implicit_step`) shares with it.

Equilibrium: minimise the total potential Pi(x) = membrane + bending + gravity + contact over
the free vertices with a damped Newton method (Levenberg-Marquardt in the mass metric): each
iteration solves (H + mu M) p = -grad Pi by conjugate gradients on Hessian-vector products,
takes the longest of p, p/2, p/4 that lowers Pi (mu shrinks if the decrease is as the quadratic
model predicts, grows if far less) and rejects it otherwise (mu grows). A small mu
is Newton's method; a large one is a short implicit-Euler step of pseudo-time 1/sqrt(mu), so the
solve also crosses the buckling (fold-forming) region of a drape where the Hessian is
indefinite. Its gradient is the implicit function theorem's (`jax.lax.custom_root`): one linear
solve with the Hessian at the solution, never a pass back through the iterations.

Implicit Euler minimises the incremental potential |x - x_n - h v_n|_M^2 / (2 h^2) + Pi(x) plus
damping, drag and lagged Coulomb friction (same Newton solve, same implicit gradient).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from diffcloth.physics.mesh import colliders as mc
from diffcloth.physics.mesh import energy, hessian, linsolve
from diffcloth.physics.mesh import selfcontact_energy as sce
from diffcloth.physics.mesh import selfcontact_step as scs
from diffcloth.physics.mesh.fabric import Fabric
from diffcloth.physics.mesh.linsolve import _block_jacobi, _cg
from diffcloth.physics.mesh.topology import ClothMesh, active_part

__all__ = [
    "EquilibriumResult",
    "NotConvergedError",
    "SolverSettings",
    "check_equilibrium",
    "equilibrium",
    "potential",
]


class NotConvergedError(RuntimeError):
    """A mesh solve stopped before its tolerance, or produced non-finite values."""


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class SolverSettings:
    """Newton-CG settings (static).

    Attributes:
      max_iters: Newton iterations at most (equilibrium: accepted and rejected steps together).
      cg_iters: conjugate-gradient iterations per Newton step at most.
      cg_tol: relative residual of each CG solve (and of the gradient's adjoint solve; with
        krylov_forcing, the least one a Newton step's solve is given).
      tol: convergence: the largest free-vertex force below tol times the vertex's weight
        (|grad Pi_i| <= tol m_i |g|), dimensionless; raised to the floor that rounding the
        positions to the dtype causes (4 eps |x_i| k_ii / (m_i |g|), k_ii the vertex's
        stiffness: about 0.1-0.2 for a stiff woven fabric in float32, negligible in float64).
      mu0: initial regularisation, 1/s^2 (the mass metric's weight: 1/mu0 is a pseudo time step
        squared).
      linear_solver: "direct" (sparse LU on the host, `linsolve`; robust for stiff fabrics) or
        "cg" (block-Jacobi conjugate gradients in the compiled program).
      krylov_iters: with "direct", CG iterations per Newton step on the exact Hessian,
        preconditioned by the LU of its PSD approximation (Newton's fast final convergence).
      krylov_forcing: those iterations stop at a relative residual set by the progress of the
        last step (Eisenstat-Walker: 0.9 (|g_k| / |g_k-1|)^2, within [cg_tol, 0.5]): loose while
        the folds move, tight where Newton converges fast; False: cg_tol for every step.
      line_search: step lengths tried along each Newton direction, 1, 1/2, 1/4, ... (this many,
        evaluated together): the longest that lowers the energy by 1e-4 of the model's
        prediction is taken; 1 accepts or rejects the full step only.
      mu_update: "ratio" (after a step of length a with gain ratio rho, the energy's decrease
        over the model's: mu x0.25 if a rho >= 0.75, kept if >= 0.25, else x2; rejections: x2, x4,
        x8, ..., from 1 at least) or "fixed" (x0.25 on acceptance, x8 on rejection).
        line_search=1, mu_update="fixed", krylov_forcing=False: the solver before 2026-11-28.
      refactor_every: with "direct", the Hessian approximation is assembled and factored on
        every this many Newton steps, and sooner when the last Krylov solve took over half of
        krylov_iters or a step was rejected; between, the last factorization preconditions
        (the Krylov iterations run on the exact Hessian, so a stale one costs iterations, not
        accuracy). 1: every step.
    """

    max_iters: int = dataclasses.field(default=200, metadata={"static": True})
    cg_iters: int = dataclasses.field(default=300, metadata={"static": True})
    cg_tol: float = dataclasses.field(default=1e-3, metadata={"static": True})
    tol: float = dataclasses.field(default=1e-3, metadata={"static": True})
    mu0: float = dataclasses.field(default=1e2, metadata={"static": True})
    linear_solver: str = dataclasses.field(default="direct", metadata={"static": True})
    krylov_iters: int = dataclasses.field(default=10, metadata={"static": True})
    krylov_forcing: bool = dataclasses.field(default=True, metadata={"static": True})
    line_search: int = dataclasses.field(default=3, metadata={"static": True})
    mu_update: str = dataclasses.field(default="ratio", metadata={"static": True})
    refactor_every: int = dataclasses.field(default=5, metadata={"static": True})


class EquilibriumResult(NamedTuple):
    """x: (n, 3) m; converged: () bool; iterations: () int; residual: () the largest free force
    over its vertex weight (dimensionless); energy: () J."""

    x: jax.Array
    converged: jax.Array
    iterations: jax.Array
    residual: jax.Array
    energy: jax.Array


def potential(cloth: ClothMesh, fabric: Fabric, x, gravity, colliders=None):
    """Total potential energy in J: elastic + gravity + contact penalty. x: (n, 3) m."""
    e = energy.elastic_energy(cloth, fabric, x) + energy.gravity_energy(cloth, fabric, x, gravity)
    if mc.has_colliders(colliders):
        e = e + mc.contact_energy(colliders, x, cloth.vertex_area, ~cloth.pinned)
    return e


class _Problem(NamedTuple):
    """Static description of a minimisation (hashable): its kind and solver settings."""

    kind: str  # "static" | "implicit"
    settings: SolverSettings
    mu0: float
    colliders: bool
    self_contact: bool = False  # theta["self_contact"]: selfcontact.SelfContact


def _cloth_of(theta) -> ClothMesh:
    return theta["cloth"]


def _place(theta, x):
    return jnp.where(theta["free"][:, None], x, theta["x_pins"])


def _energy(problem: _Problem, x, theta, pairs=None, contact=True):
    """The minimised energy in J at x (n, 3) (pinned vertices placed at x_pins); with
    self-contact (and contact), the barrier on `pairs` (default: those within d_hat of x)."""
    cloth, fabric = theta["cloth"], theta["fabric"]
    cols = theta["colliders"] if problem.colliders else None
    x = _place(theta, x)
    e = potential(cloth, fabric, x, theta["gravity"], cols)
    if problem.self_contact and contact:
        sc = theta["self_contact"]
        pairs = sce.find_pairs(cloth, sc, x, sc.thickness) if pairs is None else pairs
        e = e + sce.barrier_energy(cloth, sc, x, pairs)
        if problem.kind == "implicit":
            mu = fabric.friction * sc.friction
            e = e + sce.friction_energy(theta["sc_frame"], x, theta["x_n"], mu, _FRICTION_EPS)
    if problem.kind == "implicit":
        h, x_n = theta["h"], theta["x_n"]
        mass = energy.vertex_mass(cloth, fabric)
        x_tilde = x_n + h * theta["v_n"]
        e = e + 0.5 * jnp.sum(mass[:, None] * (x - x_tilde) ** 2) / (h * h)
        # Rayleigh damping: a Bregman divergence of the elastic energy (~ dx^T K dx / 2), / h
        bregman = (energy.elastic_energy(cloth, fabric, x) - theta["el_prev"]
                   - jnp.sum(theta["g_prev"] * (x - x_n)))  # fmt: skip
        e = e + fabric.damping / h * bregman
        rel = (x - x_n) - h * theta["wind"][None, :]
        e = e + 0.5 * fabric.drag / h * jnp.sum(cloth.vertex_area[:, None] * rel * rel)
        if problem.colliders:
            e = e + mc.friction_energy(cols, x, x_n, cloth.vertex_area, theta["free"],
                                       fabric.friction, _FRICTION_EPS)  # fmt: skip
    return e


def _hessian(problem: _Problem, x, theta, pairs=None):
    """The assembled PSD Hessian approximation (n, K, 3, 3) of `_energy` at x (self-contact:
    the barrier's diagonal blocks only)."""
    cloth, fabric = theta["cloth"], theta["fabric"]
    x = _place(theta, x)
    n = cloth.num_vertices
    eye = jnp.eye(3, dtype=x.dtype)
    diag = jnp.zeros((n, 3, 3), x.dtype)
    if problem.self_contact:
        sc = theta["self_contact"]
        pairs = sce.find_pairs(cloth, sc, x, sc.thickness) if pairs is None else pairs
        diag = diag + sce.barrier_blocks(cloth, sc, x, pairs)
        if problem.kind == "implicit":
            diag = diag + sce.friction_blocks(theta["sc_frame"], x, theta["x_n"],
                                              fabric.friction * sc.friction, _FRICTION_EPS)  # fmt: skip
    scale = 1.0
    if problem.colliders:
        cols = theta["colliders"]
        pen = mc.penetration(cols, x)
        nrm = mc.contact_normals(cols, x)
        kc = jnp.where(pen > 0, cols.stiffness * cloth.vertex_area, 0.0)
        diag = diag + kc[:, None, None] * nrm[:, :, None] * nrm[:, None, :]
    if problem.kind == "implicit":
        h = theta["h"]
        mass = energy.vertex_mass(cloth, fabric)
        diag = (
            diag + (mass / (h * h) + fabric.drag * cloth.vertex_area / h)[:, None, None] * eye[None]
        )
        scale = 1.0 + fabric.damping / h
    return hessian.assemble(cloth, fabric, x, elastic_scale=scale, diag=diag)


def _couplings(problem: _Problem, x, theta, pairs=None):
    """Self-contact: the pairs' PSD couplings for `linsolve.factor` (`selfcontact_step.
    couplings`); None without self-contact."""
    if not problem.self_contact:
        return None
    cloth, sc, mu = theta["cloth"], theta["self_contact"], theta["fabric"].friction
    frame = theta["sc_frame"] if problem.kind == "implicit" else None
    return scs.couplings(cloth, sc, _place(theta, x), pairs, frame, theta.get("x_n"),
                         mu * sc.friction, _FRICTION_EPS)  # fmt: skip


def _newton(problem: _Problem, theta, x0) -> EquilibriumResult:
    """Minimise `_energy` over the free vertices from x0 (Levenberg-Marquardt-damped Newton,
    PCG on the assembled Hessian, a backtracking line search on each step)."""
    st = problem.settings
    if st.mu_update not in ("ratio", "fixed"):
        raise ValueError(f"mu_update must be 'ratio' or 'fixed', got {st.mu_update!r}")
    cloth, fabric = theta["cloth"], theta["fabric"]
    free = theta["free"]
    fmask = free[:, None]
    mass = energy.vertex_mass(cloth, fabric)
    gnorm = jnp.sqrt(jnp.sum(theta["gravity"] ** 2))
    weight = mass * jnp.maximum(gnorm, 1e-3)
    cs0 = None  # self-contact: the candidate pairs and those active at x0 (selfcontact_step)
    if problem.self_contact:
        cs0 = scs.start(cloth, theta["self_contact"], x0, theta.get("sc_pairs"))
    total = total_0 = lambda x: _energy(problem, x, theta, None if cs0 is None else cs0.active)

    def grad_with(pairs):  # self-contact: its terms' gradient taken in their size's branch
        if not problem.self_contact:
            return jax.grad(total_0)
        rest = jax.grad(lambda y: _energy(problem, y, theta, contact=False))
        return lambda y: rest(y) + scs.grad(theta, _place(theta, y), pairs, _FRICTION_EPS)

    grad_fn = grad_0 = grad_with(None if cs0 is None else cs0.active)
    eye = jnp.eye(3, dtype=x0.dtype)
    alphas = jnp.asarray(0.5 ** np.arange(max(st.line_search, 1)), x0.dtype)  # 1, 1/2, ...
    armijo = 1e-4 if st.line_search > 1 else 0.0

    def residual(g):
        r = jnp.max(jnp.where(free, jnp.sqrt(jnp.sum(g * g, axis=-1)) / weight, 0.0))
        return jnp.where(jnp.isfinite(r), r, jnp.inf)

    def cond(c):
        x, e, g, mu, nu, eta, k, res, _, _, _ = c
        # at least one step: where float32 rounding puts the tolerance above the start's
        # residual (a fine mesh's implicit step: weight-sized force noise), the start would
        # count as converged and the step would not move
        return (k < st.max_iters) & ((res > tol) | (k == 0)) & jnp.isfinite(e) & (mu < 1e14)

    def factor(x, mu, pairs=None):
        hmat = _hessian(problem, x, theta, pairs)
        hmat = hmat.at[:, 0].add((mu * mass)[:, None, None] * eye[None])
        return linsolve.factor(hmat, cloth.neighbors, free, _couplings(problem, x, theta, pairs))

    def body(c):
        x, e, g, mu, nu, eta, k, res, token, fresh, cs = c
        total, grad_fn, pairs = total_0, grad_0, None
        if problem.self_contact:  # the pairs in contact at x
            sc, pairs = theta["self_contact"], cs.active
            grad_fn = grad_with(pairs)
        if st.linear_solver == "direct":
            # Newton-Krylov: CG on the exact Hessian (+ mu M), preconditioned by the LU of the
            # PSD approximation (refactored as `refactor_every` says); at negative curvature,
            # the approximation's own step
            token = jax.lax.cond(fresh, lambda: factor(x, mu, pairs), lambda: token)
            pre = lambda r: linsolve.solve(token, r) * fmask
            # linearized once per step: each Krylov iteration's product skips the primal pass
            hvp = jax.linearize(grad_fn, x)[1]  # (self-contact: a jvp each, as a linearized
            if problem.self_contact:  # switch keeps every size's intermediates)
                hvp = lambda v: jax.jvp(grad_fn, (x,), (v,))[1]
            exact = lambda p: (hvp(p * fmask) + mu * mass[:, None] * p) * fmask
            # at a direction of negative curvature in the damped phase (mu > 0: a buckling
            # membrane, where mu M does not cover the exact Hessian's compressive part), the
            # partial Krylov iterate can be a long move along a soft mode that the energy then
            # rejects (a refactorization each): the PSD approximation's own step is taken
            # instead. At mu = 0 (the final Newton steps) the partial iterate is kept: the PSD
            # step alone stalled a float64 drape short of its tolerance. CG on a float32 HVP
            # can also break down into non-finite values (a fine mesh's stiff membrane): then
            # the PSD step too (a cond: its host solve runs only where taken)
            p, ok, kry = _cg(exact, -g, pre, st.krylov_iters, eta, fall_back=mu > 0)
            p = jax.lax.cond(ok & jnp.all(jnp.isfinite(p)), lambda: p, lambda: pre(-g))
            ok = jnp.all(jnp.isfinite(p))
            p = jnp.where(ok, p, 0.0)
        else:
            hmat = _hessian(problem, x, theta, pairs)
            hmat = hmat.at[:, 0].add((mu * mass)[:, None, None] * eye[None])
            apply_a = lambda p: hessian.matvec(cloth, hmat, p * fmask) * fmask
            pre = _block_jacobi(hessian.block_diagonal(hmat), free)
            p, ok, kry = _cg(apply_a, -g, pre, st.cg_iters, st.cg_tol)
        p, shrink = p * fmask, 1.0
        if problem.self_contact:  # step filter: the cap on a vertex's move, then CCD on the
            # pairs the step can reach (their energy is then exact along it)
            p, shrink, pairs, cs = scs.filter_step(cloth, sc, cs, x, p)
            total = lambda y: _energy(problem, y, theta, pairs)
        gp = jnp.minimum(jnp.vdot(g, p), 0.0)  # the model's slope along p
        along = lambda a: total(x + a * p)  # (a map with self-contact: each energy's pair sets)
        e_all = jax.lax.map(along, alphas) if problem.self_contact else jax.vmap(along)(alphas)
        # a decrease, up to the energy's rounding error (float32 cannot resolve the last steps
        # of a stiff membrane's solve in the total energy)
        good = jnp.isfinite(e_all) & (e_all <= e + armijo * alphas * gp + slack)
        i = jnp.argmax(good)  # the longest good step
        accept = ok & jnp.any(good)
        alpha, e_try = alphas[i], e_all[i]
        if st.mu_update == "fixed":
            f, grow = 0.25, 8.0
        else:
            # gain ratio; p^T H p = -g.p - mu p^T M p as CG solved (H + mu M) p = -g
            pmp = jnp.sum(mass[:, None] * p * p)
            # (p shrunk by the step filter: p^T H p = -shrink g.p - mu p^T M p)
            pred = alpha * (-gp) - 0.5 * alpha**2 * (-shrink * gp - mu * pmp)
            rho = jnp.clip((e - e_try) / jnp.maximum(pred, jnp.finfo(x0.dtype).tiny), 0.0, 1.0)
            f = jnp.where(alpha * rho >= 0.75, 0.25, jnp.where(alpha * rho >= 0.25, 1.0, 2.0))
            grow, nu = nu, jnp.where(accept, 2.0, 2.0 * nu)
        mu_acc = jnp.where(mu * f < 1e-3, 0.0, mu * f)
        mu_new = jnp.where(accept, mu_acc, jnp.maximum(mu * grow, 1.0))
        x = jnp.where(accept, x + alpha * p, x)
        e = jnp.where(accept, e_try, e)
        if problem.self_contact:  # the pairs in contact at the new x
            cs = scs.after_step(sc, cs, x, pairs, accept)
            grad_fn = grad_with(cs.active)
        g_new = jnp.where(accept, grad_fn(x) * fmask, g)
        if st.krylov_forcing:  # Eisenstat-Walker's choice 2, safeguarded
            drop = jnp.vdot(g_new, g_new) / jnp.maximum(jnp.vdot(g, g), jnp.finfo(x0.dtype).tiny)
            eta_new = jnp.maximum(0.9 * drop, jnp.where(0.9 * eta**2 > 0.1, 0.9 * eta**2, 0.0))
            eta = jnp.where(accept, jnp.clip(eta_new, st.cg_tol, 0.5), eta)
        fresh = (((k + 1) % max(st.refactor_every, 1)) == 0) | ~accept
        fresh = fresh | (2 * kry > st.krylov_iters)
        return x, e, g_new, mu_new, nu, eta, k + 1, residual(g_new), token, fresh, cs

    g0 = grad_fn(x0) * fmask
    eps = jnp.finfo(x0.dtype).eps
    # the force that rounding a position to the dtype's precision causes through the stiffest
    # element at that vertex, over its weight: residuals below it cannot be resolved (in float32
    # a 500 N/m membrane's quantization noise is several times a light fabric's vertex weight)
    h0 = hessian.block_diagonal(_hessian(problem, x0, theta, None if cs0 is None else cs0.active))
    stiff = jnp.trace(h0, axis1=1, axis2=2) / 3.0
    noise = eps * (jnp.max(jnp.abs(x0), axis=-1) + 1e-3) * stiff / weight
    tol = jax.lax.stop_gradient(jnp.maximum(st.tol, 4.0 * jnp.max(jnp.where(free, noise, 0.0))))
    scale = jnp.sum(weight * (jnp.sum(jnp.abs(x0), axis=-1) + 0.01))
    slack = jax.lax.stop_gradient(16.0 * eps * scale)
    mu0, eta0 = problem.mu0, max(st.cg_tol, 0.5) if st.krylov_forcing else st.cg_tol
    init = (x0, total(x0), g0, *(jnp.asarray(v, x0.dtype) for v in (mu0, 2.0, eta0)), 0,
            residual(g0), jnp.int32(0), jnp.array(True), cs0)  # fmt: skip
    x, e, g, mu, nu, eta, k, res, _, _, _ = jax.lax.while_loop(cond, body, init)
    conv = (res <= tol) & jnp.all(jnp.isfinite(x))
    return EquilibriumResult(x=_place(theta, x), converged=conv, iterations=k, residual=res,
                             energy=e)  # fmt: skip


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _argmin(problem: _Problem, theta, x0):
    return _newton(problem, theta, x0)


def _root(problem, x, theta):
    """f(x, theta) = [free: grad E(x); pinned: x - x_pins], zero at the solution."""
    fmask = theta["free"][:, None]
    g = jax.grad(lambda y: _energy(problem, y, theta))(x)
    return jnp.where(fmask, g, x - theta["x_pins"])


@_argmin.defjvp
def _argmin_jvp(problem, primals, tangents):
    """Implicit function theorem: df/dx xdot = -df/dtheta thetadot, with df/dx = diag(H_ff, I)
    (symmetric). The solve is a `lax.custom_linear_solve`, so reverse mode transposes it (the
    same solve, as the matrix is symmetric): forward and reverse mode both work, and neither
    passes back through the Newton iterations. x0 has no effect on the solution (zero tangent).
    """
    theta, x0 = primals
    theta_dot, _ = tangents
    out = _newton(problem, theta, x0)
    x = out.x
    free = theta["free"]
    fmask = free[:, None]
    rhs = jax.jvp(lambda th: _root(problem, x, th), (theta,), (theta_dot,))[1]
    grad_fn = jax.grad(lambda y: _energy(problem, y, theta))
    hvp = jax.linearize(grad_fn, x)[1]  # once: each CG iteration's product is the tangent pass
    matvec = lambda p: jnp.where(fmask, hvp(p * fmask), p)
    sc = theta["self_contact"]
    pairs = sce.find_pairs(theta["cloth"], sc, x, sc.thickness) if problem.self_contact else None
    hmat = _hessian(problem, x, theta, pairs)
    if problem.settings.linear_solver == "direct":  # the approximate Hessian's LU preconditions
        nbr = _cloth_of(theta).neighbors
        token = linsolve.factor(hmat, nbr, free, _couplings(problem, x, theta, pairs))
        pre = lambda r: jnp.where(fmask, linsolve.solve(token, r), r)
    else:
        block = _block_jacobi(hessian.block_diagonal(hmat), free)
        pre = lambda r: jnp.where(fmask, block(r), r)

    def solve(mv, b):
        # to 1e-10 in float64; float32 cannot resolve that and would spend every iteration on
        # rounding noise: 8 eps (~1e-6) there
        rtol = max(1e-10, 8.0 * float(jnp.finfo(b.dtype).eps))
        z, _, _ = _cg(mv, b, pre, 4 * problem.settings.cg_iters, rtol)
        return z

    x_dot = jax.lax.custom_linear_solve(matvec, -rhs, solve, symmetric=True)
    zero = lambda a: (
        jnp.zeros_like(a)
        if jnp.issubdtype(a.dtype, jnp.inexact)
        else np.zeros(a.shape, jax.dtypes.float0)
    )
    out_dot = EquilibriumResult(
        x=x_dot,
        converged=zero(out.converged),
        iterations=zero(out.iterations),
        residual=zero(out.residual),
        energy=zero(out.energy),
    )
    return out, out_dot


def equilibrium(
    cloth: ClothMesh,
    fabric: Fabric,
    x_start,
    *,
    gravity,
    colliders=None,
    x_pins=None,
    settings: SolverSettings = SolverSettings(),
    self_contact=None,
) -> EquilibriumResult:
    """The static equilibrium reached from x_start: a local minimum of `potential`.

    Args:
      cloth, fabric: the mesh and its material.
      x_start: (n, 3) m, the start of the solve (a flat sheet, or a perturbed one to seed folds).
      gravity: (3,) m/s^2.
      colliders: MeshColliders or None.
      x_pins: (n, 3) m, where the pinned vertices are held (default x_start).
      settings: SolverSettings.
      self_contact: `selfcontact.SelfContact` or None (off): the barrier keeps the cloth free
        of self-intersection if x_start is (docs/physics.md, self-contact).
    Returns:
      EquilibriumResult; x is differentiable with respect to fabric, colliders, gravity, the
      rest geometry and x_pins (implicit function theorem), not x_start. Check `converged` (or
      call `check_equilibrium`): a solve that stopped early is not a rest shape.
    """
    x_start = jnp.asarray(x_start)
    # the faces and hinges that move with the free vertices (self-contact: every face, as a
    # free vertex can meet a pinned one)
    part = cloth if self_contact is not None else _active(cloth)
    theta = {
        "cloth": part,
        "fabric": fabric,
        "colliders": colliders,
        "gravity": jnp.asarray(gravity, x_start.dtype),
        "x_pins": x_start if x_pins is None else jnp.asarray(x_pins, x_start.dtype),
        "free": ~cloth.pinned,
        "self_contact": self_contact,
    }
    problem = _Problem("static", settings, float(settings.mu0), mc.has_colliders(colliders),
                       self_contact is not None)  # fmt: skip
    out = _argmin(problem, theta, jax.lax.stop_gradient(x_start))
    if part is not cloth:  # the whole cloth's energy (the part's differs by a constant)
        offset = _energy(problem, out.x, dict(theta, cloth=cloth)) - _energy(problem, out.x, theta)
        out = out._replace(energy=out.energy + jax.lax.stop_gradient(offset))
    return out


def _active(cloth: ClothMesh) -> ClothMesh:
    """`topology.active_part` of the cloth where its pins and topology are known when traced
    (a cloth closed over, not a traced argument) and some face is wholly pinned; else cloth."""
    try:
        pinned = np.asarray(cloth.pinned)
        np.asarray(cloth.stencil), np.asarray(cloth.hinge_faces), np.asarray(cloth.face_hinge)
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
        return cloth
    if not pinned.any() or pinned[np.asarray(cloth.stencil)].all(axis=1).sum() == 0:
        return cloth
    return active_part(cloth, ~pinned)


def check_equilibrium(result: EquilibriumResult, what: str = "equilibrium") -> EquilibriumResult:
    """Raise NotConvergedError (with the reason) unless the solve converged; returns result.
    Shapes: none (reads the result's scalars).
    """
    if not bool(jnp.all(jnp.isfinite(result.x))):
        raise NotConvergedError(f"{what}: the solve produced non-finite positions")
    if not bool(result.converged):
        raise NotConvergedError(
            f"{what}: not converged after {int(result.iterations)} Newton iterations (largest "
            f"free force {float(result.residual):.3g} x its vertex weight); raise "
            "SolverSettings.max_iters, or start closer to the rest shape"
        )
    return result


# ---------------------------------------------------------------------------------------------
# the implicit step's friction (dynamics.py builds the step)


_FRICTION_EPS = 1e-5  # m: tangential slip below which friction is smoothed (static regime)
