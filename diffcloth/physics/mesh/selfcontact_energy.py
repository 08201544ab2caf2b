"""Self-contact of the mesh cloth, part 2: the IPC-style barrier energy on the pairs of
`selfcontact.find_pairs`, its diagonal Hessian blocks (the Newton solves' preconditioner), the
conservative step filter (additive CCD) and the lagged friction between layers.

Barrier (Li et al. 2020, IPC): for each vertex-triangle and edge-edge pair at unsigned distance d

    E = kappa A b(d),   b(d) = -(d - d_hat)^2 log(d / d_hat) for d < d_hat, else 0     [J]

with kappa = `SelfContact.stiffness` (N/m^3) and A the pair's area (the vertex's lumped area for
vertex-triangle pairs, half the mean of the four vertex areas for edge-edge pairs). b is C2 at
d_hat and infinite at d = 0, so a Newton solve that only takes steps the filter allows, and
lowers the energy, never lets two non-adjacent primitives touch: the cloth stays free of
self-intersection. The barrier's weight at rest is the pressure kappa |b'(d)|: a 0.3 kg/m^2
layer resting on another sits where kappa |b'(d)| = 3 Pa.

Friction: the colliders' model (`colliders.friction_energy`): lagged Coulomb friction as a smooth
dissipation potential mu lambda (sqrt(|u_T|^2 + eps^2) - eps) per pair, with the normal force
lambda = kappa A |b'(d)|, the contact normal and the closest-point weights taken at the start of
the step, and u_T the pair's relative tangential displacement.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from diffcloth._math import safe_norm
from diffcloth.physics.mesh.selfcontact import (
    Pairs,
    SelfContact,
    find_pairs,
    gap,
    step_radius,
    weights,
)

__all__ = [
    "FrictionFrame",
    "bucketed",
    "barrier",
    "barrier_blocks",
    "barrier_cores",
    "barrier_energy",
    "barrier_grad",
    "compact",
    "friction_energy",
    "friction_blocks",
    "friction_cores",
    "friction_frame",
    "friction_grad",
    "mollifier",
    "take",
    "within",
    "find_pairs",
    "step_pairs",
    "step_bound",
    "step_radius",
]


def barrier(d, dhat):
    """b(d) in m^2 (module docstring); inf at d <= 0. Shapes: d (...), dhat () -> (...)."""
    inside = (d < dhat) & (d > 0)
    ds = jnp.where(inside, d, dhat)
    b = -((ds - dhat) ** 2) * jnp.log(ds / dhat)
    return jnp.where(d <= 0, jnp.inf, jnp.where(inside, b, 0.0))


def _barrier_d(d, dhat):
    """b'(d) and b''(d) (zero beyond d_hat)."""
    inside = (d < dhat) & (d > 0)
    ds = jnp.where(inside, d, dhat)
    lg = jnp.log(ds / dhat)
    b1 = -2.0 * (ds - dhat) * lg - (ds - dhat) ** 2 / ds
    b2 = -2.0 * lg - 4.0 * (ds - dhat) / ds + (ds - dhat) ** 2 / ds**2
    return jnp.where(inside, b1, 0.0), jnp.where(inside, b2, 0.0)


def _pair_area(cloth, pairs: Pairs):
    a = cloth.vertex_area[pairs.idx]  # (P, 4)
    return jnp.where(pairs.kind == 0, a[:, 0], 0.125 * jnp.sum(a, axis=1))


def mollifier(cloth, x, pairs: Pairs):
    """(P,) IPC's edge-edge mollifier: c / c0 (2 - c / c0) below c0 and 1 above, with
    c = |e_a x e_b|^2 and c0 = 1e-3 |e_a|^2 |e_b|^2 at rest; 1 for vertex-triangle pairs. It
    takes the energy of nearly parallel edges (where their distance has a kink) smoothly to 0;
    the vertex-triangle pairs of those edges' faces hold the layers apart there.
    Shapes: x (n, 3) -> (P,)."""
    q, r = x[pairs.idx], cloth.rest[pairs.idx]
    c = jnp.sum(jnp.cross(q[:, 1] - q[:, 0], q[:, 3] - q[:, 2]) ** 2, axis=-1)
    la = jnp.sum((r[:, 1] - r[:, 0]) ** 2, axis=-1)
    lb = jnp.sum((r[:, 3] - r[:, 2]) ** 2, axis=-1)
    ee = (pairs.kind == 1) & (la * lb > 0)  # (vertex-triangle rows may repeat a vertex)
    t = jnp.where(ee, c, 1.0) / jnp.where(ee, 1e-3 * la * lb, 1.0)
    return jnp.where(~ee | (t >= 1.0), 1.0, t * (2.0 - t))


def bucketed(mask, fn):
    """fn(rows (s,) int, live (s,) bool) on the rows where mask (P,) holds, compacted into the
    smallest static size s of 0, P/64, P/8 and P (at least 256) that holds them all: a
    `lax.switch`, so only that size is computed (the pair arrays are padded to the broad
    phase's capacity; the pairs in contact are usually a small part of it). fn's outputs must
    have the same shapes for every s.
    Shapes: mask (P,) -> fn's outputs."""
    big = mask.shape[0]
    sizes = sorted({0} | {min(big, max(256, big // 8**k)) for k in range(3)})
    count = jnp.sum(mask.astype(jnp.int32))

    def branch(s):
        def run():
            (rows,) = jnp.nonzero(mask, size=s, fill_value=0)
            return fn(rows, jnp.arange(s) < count)

        return run

    if len(sizes) == 1:
        return branch(sizes[0])()
    i = jnp.searchsorted(jnp.asarray(sizes[:-1], count.dtype), count)  # the first size >= count
    return jax.lax.switch(i, [branch(s) for s in sizes])


def take(pairs: Pairs, rows, live) -> Pairs:
    """The pairs' rows (s,), valid where live (s,) and valid before.
    Shapes: pairs with P rows, rows (s,), live (s,) -> Pairs with s rows."""
    return Pairs(pairs.idx[rows], pairs.kind[rows], pairs.valid[rows] & live, pairs.overflow,
                 pairs.count)  # fmt: skip


def _lp(x, p, pairs: Pairs):
    """(P,) bound on how far the step p (n, 3) moves each pair's distance (the pair's relative
    motion: additive CCD's lp)."""
    dq = p[pairs.idx]
    rel = safe_norm(dq - jnp.mean(dq, axis=1, keepdims=True))  # (P, 4)
    vt = rel[:, 0] + jnp.max(rel[:, 1:], axis=1)
    ee = jnp.max(rel[:, :2], axis=1) + jnp.max(rel[:, 2:], axis=1)
    return jnp.where(pairs.kind == 0, vt, ee)


def within(x, pairs: Pairs, radius, p=None) -> Pairs:
    """The valid pairs closer than radius (m) at x (n, 3); with a step p (n, 3), those that
    x + a p, a in [0, 1], may bring closer than radius (distance at x less the pair's relative
    motion bound). The rows stay where they are (the others turn invalid). No gradient.
    Shapes: x (n, 3), p (n, 3) -> Pairs with the rows of pairs."""
    x = jax.lax.stop_gradient(x)

    def on(rows, live):
        sub = take(pairs, rows, live)
        d = safe_norm(gap(x, sub.idx, sub.kind))
        if p is not None:
            d = d - _lp(x, jax.lax.stop_gradient(p), sub)
        return jnp.zeros(pairs.valid.shape, bool).at[rows].max(sub.valid & (d < radius))

    return pairs._replace(valid=bucketed(pairs.valid, on))


def barrier_energy(cloth, sc: SelfContact, x, pairs: Pairs):
    """Total barrier energy in J at x (n, 3) over the valid pairs (edge-edge pairs mollified);
    NaN if the broad phase overflowed (a solve then fails rather than miss a contact).
    Shapes: x (n, 3) -> ()."""

    on = lambda rows, live: _barrier_sum(cloth, sc, x, take(pairs, rows, live))
    return jnp.where(pairs.overflow, jnp.nan, sc.stiffness * bucketed(pairs.valid, on))


def _barrier_sum(cloth, sc, x, sub: Pairs):
    # padding rows may repeat an excluded (incident, d = 0) pair: keep them off the barrier
    d = jnp.where(sub.valid, safe_norm(gap(x, sub.idx, sub.kind)), sc.thickness)
    area = _pair_area(cloth, sub) * mollifier(cloth, x, sub)
    return jnp.sum(jnp.where(sub.valid, area * barrier(d, sc.thickness), 0.0))


def barrier_grad(cloth, sc: SelfContact, x, pairs: Pairs):
    """The gradient (n, 3) of `barrier_energy`, differentiated inside each size's branch (a
    gradient through the `bucketed` switch would fill every other size's intermediates with
    zeros: the padded size's cost). Forward-differentiable (Hessian-vector products by jvp).
    Shapes: x (n, 3) -> (n, 3)."""
    dx = jax.grad(_barrier_sum, argnums=2)
    on = lambda rows, live: dx(cloth, sc, x, take(pairs, rows, live))
    return jnp.where(pairs.overflow, jnp.nan, sc.stiffness * bucketed(pairs.valid, on))


def barrier_cores(cloth, sc: SelfContact, x, pairs: Pairs):
    """The barrier's Gauss-Newton Hessian per pair as (idx (P, 4), w (P, 4), core (P, 3, 3)):
    its block between the pair's vertices idx_k and idx_l is w_k w_l core, core = kappa A b''(d)
    u u^T (u the unit gap direction; PSD, zero for invalid pairs and on overflow).
    Shapes: x (n, 3) -> ((P, 4), (P, 4), (P, 3, 3))."""
    x = jax.lax.stop_gradient(x)
    q = x[pairs.idx]
    w = weights(q, pairs.kind)
    g = jnp.einsum("pk,pki->pi", w, q)
    d = safe_norm(g)
    u = g / jnp.maximum(d, 1e-30)[:, None]
    _, b2 = _barrier_d(d, sc.thickness)
    area = _pair_area(cloth, pairs) * mollifier(cloth, x, pairs)
    s = jnp.where(pairs.valid & ~pairs.overflow, sc.stiffness * area * b2, 0.0)
    return pairs.idx, w, s[:, None, None] * (u[:, :, None] * u[:, None, :])


def _diagonal(idx, w, core, n):
    """(n, 3, 3) sums of the pairs' diagonal blocks w_k^2 core on their vertices."""
    blk = (w * w)[:, :, None, None] * core[:, None]
    return jax.ops.segment_sum(blk.reshape(-1, 3, 3), idx.reshape(-1), num_segments=n)


def barrier_blocks(cloth, sc: SelfContact, x, pairs: Pairs):
    """(n, 3, 3) PSD diagonal blocks of the barrier's Hessian (Gauss-Newton: kappa A b''(d)
    w_k^2 u u^T on each vertex k of a pair, u the unit gap direction; `barrier_cores`).
    Shapes: x (n, 3) -> (n, 3, 3)."""
    n = x.shape[0]
    return bucketed(pairs.valid, lambda rows, live: _diagonal(
        *barrier_cores(cloth, sc, x, take(pairs, rows, live)), n))  # fmt: skip


def step_bound(x, p, pairs: Pairs, iters: int = 16):
    """The longest fraction alpha in [0, 1] of the step p (n, 3) that keeps every pair's
    distance above a tenth of its start (additive CCD, Li et al. 2021: conservative advancement
    by the pair's relative-motion bound, `iters` rounds at most: they stop once every pair is
    done).
    Shapes: x, p (n, 3) -> () in [0, 1]."""
    x, p = jax.lax.stop_gradient(x), jax.lax.stop_gradient(p)
    return bucketed(pairs.valid, lambda rows, live: _ccd(x, p, take(pairs, rows, live), iters))


def _ccd(x, p, pairs: Pairs, iters):
    q, dq = x[pairs.idx], p[pairs.idx]  # (P, 4, 3)
    lp = _lp(x, p, pairs)
    dist = lambda t: safe_norm(gap_at(q + t[:, None, None] * dq, pairs.kind))
    zero = jnp.zeros(q.shape[:1], x.dtype)
    floor = 0.1 * dist(zero)

    def body(c):
        k, t, done = c
        t_new = t + 0.9 * (dist(t) - floor) / jnp.maximum(lp, 1e-30)
        fin = t_new >= 1.0
        return k + 1, jnp.where(done, t, jnp.where(fin, 1.0, t_new)), done | fin

    # the rounds after every pair is done change nothing: stop there
    cond = lambda c: (c[0] < iters) & ~jnp.all(c[2])
    _, t, _ = jax.lax.while_loop(cond, body, (0, zero, (lp <= 0) | ~pairs.valid))
    t = jnp.where(lp <= 0, 1.0, t)
    return jnp.min(jnp.where(pairs.valid, jnp.clip(t, 0.0, 1.0), 1.0), initial=1.0)


def gap_at(q, kind):
    """(P, 3) gap vectors of the pairs' points q (P, 4, 3)."""
    return jnp.einsum("pk,pki->pi", weights(q, kind), q)


class FrictionFrame(NamedTuple):
    """The lagged friction's frame at the start of a step: idx (P, 4), w (P, 4) closest-point
    weights, normal (P, 3), lam (P,) N normal force (0 where no contact), overflow ()."""

    idx: jax.Array
    w: jax.Array
    normal: jax.Array
    lam: jax.Array
    overflow: jax.Array


def friction_frame(cloth, sc: SelfContact, x_prev, pairs: Pairs | None = None) -> FrictionFrame:
    """The pairs in contact at x_prev (n, 3) and their normal forces (no gradient); pairs: a
    superset of those within the thickness at x_prev (default: found here).
    Shapes: x_prev (n, 3) -> FrictionFrame with P pairs."""
    x_prev = jax.lax.stop_gradient(x_prev)
    pairs = find_pairs(cloth, sc, x_prev, sc.thickness) if pairs is None else pairs
    q = x_prev[pairs.idx]
    w = weights(q, pairs.kind)
    g = jnp.einsum("pk,pki->pi", w, q)
    d = safe_norm(g)
    b1, _ = _barrier_d(d, sc.thickness)
    area = _pair_area(cloth, pairs) * mollifier(cloth, x_prev, pairs)
    lam = jnp.where(pairs.valid, -sc.stiffness * area * b1, 0.0)
    n = g / jnp.maximum(d, 1e-30)[:, None]
    return FrictionFrame(pairs.idx, w, n, lam, pairs.overflow)


def friction_energy(frame: FrictionFrame, x, x_prev, mu, eps):
    """Lagged friction potential in J (module docstring). mu: () Coulomb coefficient; eps: ()
    m, the slip below which friction is smoothed.
    Shapes: x, x_prev (n, 3) -> ()."""
    on = lambda rows, live: _friction_sum(_take_frame(frame, rows, live), x, x_prev, eps)
    return jnp.where(frame.overflow, jnp.nan, mu * bucketed(frame.lam != 0, on))


def _friction_sum(fr: FrictionFrame, x, x_prev, eps):
    u = jnp.einsum("pk,pki->pi", fr.w, (x - x_prev)[fr.idx])
    ut = u - jnp.sum(u * fr.normal, axis=-1, keepdims=True) * fr.normal
    slide = jnp.sqrt(jnp.sum(ut * ut, axis=-1) + eps * eps) - eps
    return jnp.sum(fr.lam * slide)


def friction_grad(frame: FrictionFrame, x, x_prev, mu, eps):
    """The gradient (n, 3) of `friction_energy` with respect to x, differentiated inside each
    size's branch (as `barrier_grad`).
    Shapes: x, x_prev (n, 3) -> (n, 3)."""
    dx = jax.grad(_friction_sum, argnums=1)
    on = lambda rows, live: dx(_take_frame(frame, rows, live), x, x_prev, eps)
    return jnp.where(frame.overflow, jnp.nan, mu * bucketed(frame.lam != 0, on))


def _take_frame(frame: FrictionFrame, rows, live) -> FrictionFrame:
    lam = jnp.where(live, frame.lam[rows], 0.0)
    return FrictionFrame(frame.idx[rows], frame.w[rows], frame.normal[rows], lam, frame.overflow)


def friction_cores(frame: FrictionFrame, x, x_prev, mu, eps):
    """The lagged friction's Hessian per pair as (idx (P, 4), w (P, 4), core (P, 3, 3)), block
    w_k w_l core between vertices idx_k and idx_l: core = mu lambda times the Hessian of
    sqrt(|u_T|^2 + eps^2) (the tangential projector over its value, less the slip direction's
    part; PSD). The friction is stiff where a layer sticks: mu lambda / eps.
    Shapes: x, x_prev (n, 3) -> ((P, 4), (P, 4), (P, 3, 3))."""
    u = jnp.einsum("pk,pki->pi", frame.w, jax.lax.stop_gradient(x - x_prev)[frame.idx])
    nrm = frame.normal
    ut = u - jnp.sum(u * nrm, axis=-1, keepdims=True) * nrm
    s = jnp.sqrt(jnp.sum(ut * ut, axis=-1) + eps * eps)
    proj = jnp.eye(3, dtype=x.dtype)[None] - nrm[:, :, None] * nrm[:, None, :]
    hess = proj / s[:, None, None] - ut[:, :, None] * ut[:, None, :] / (s**3)[:, None, None]
    lam = jnp.where(frame.overflow, 0.0, mu * frame.lam)
    return frame.idx, frame.w, lam[:, None, None] * hess


def friction_blocks(frame: FrictionFrame, x, x_prev, mu, eps):
    """(n, 3, 3) PSD diagonal blocks of the lagged friction's Hessian (`friction_cores`), for
    the preconditioner.
    Shapes: x, x_prev (n, 3) -> (n, 3, 3)."""
    n = x.shape[0]
    return bucketed(frame.lam != 0, lambda rows, live: _diagonal(
        *friction_cores(_take_frame(frame, rows, live), x, x_prev, mu, eps), n))  # fmt: skip


def compact(pairs: Pairs, frame: FrictionFrame | None, size: int):
    """The first `size` valid pairs and live friction rows (the preconditioner's couplings: the
    rest, if any, are left out of it, which keeps it PSD).
    Shapes: P rows -> (Pairs, FrictionFrame) with min(size, P) rows."""
    (rows,) = jnp.nonzero(pairs.valid, size=min(size, pairs.valid.shape[0]), fill_value=0)
    sub = take(pairs, rows, jnp.arange(rows.shape[0]) < jnp.sum(pairs.valid))
    if frame is None:
        return sub, None
    live = frame.lam != 0
    (rows,) = jnp.nonzero(live, size=min(size, live.shape[0]), fill_value=0)
    return sub, _take_frame(frame, rows, jnp.arange(rows.shape[0]) < jnp.sum(live))


def step_pairs(cloth, sc: SelfContact, x, p):
    """The pairs that the step x -> x + alpha p, alpha in [0, 1], may bring within d_hat (each
    side's reach is its vertices' largest |p_i|): the barrier's exact support on the step.
    Shapes: x, p (n, 3) -> Pairs."""
    return find_pairs(cloth, sc, x, sc.thickness, safe_norm(jax.lax.stop_gradient(p)))
