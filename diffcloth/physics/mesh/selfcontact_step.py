"""Self-contact of the mesh cloth, part 3: the pair sets a Newton solve works on.

The broad phase (`selfcontact.find_pairs`, the cost of a Newton step with self-contact before
2026-11-29) runs once per solve and again only when the cloth has moved too far: the candidate
pairs C are those within d_hat + 2 B at x_c (B = `selfcontact.step_radius`). While every
vertex's displacement from x_c, less a common translation c, stays within B
(max_i |x_i - x_c,i - c| <= B), a pair outside C is still at least d_hat apart (its distance
moves by at most the two sides' displacements, and not at all under a translation), so C holds
every pair the barrier sees. A step x -> x + a p, a in [0, 1], is checked at its end (the
displacement is then within B for every a, with the centres interpolated); where it is not, C
is found again at x. Each step is capped so that max_i |p_i - c| <= B (a translation, such as
a falling sheet's, is not capped): after a new broad phase the step always fits. Where C at
that reach overflows the broad phase's capacity (a pile of layers), the same broad phase keeps
the largest reach of a ladder (B, B/2, ..., B/16 and the step's own) whose pairs fit
(`selfcontact.find_pairs_fitting`), and a step longer than that reach is cut to it; where the
raw candidates overflow their slots (cells sized for B), the search runs again with cells for
B/4, then for the step's own reach. Before 2026-11-29 an overflow found C again with the
step's own reach, two broad phases at every step while the pile lasted.

Per Newton iteration, on C's rows (`selfcontact_energy.within`): the active pairs (closer than
d_hat at the iterate: the gradient, the Hessian-vector products, the preconditioner) and the
step's pairs (those the step can bring within d_hat, by the distance at x less the pair's
relative motion bound: the step filter's CCD and the line search). The energies on them are
the energies on every pair of the cloth (the barrier is zero beyond d_hat).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from diffcloth._math import safe_norm
from diffcloth.physics.mesh import selfcontact_energy as sce
from diffcloth.physics.mesh.selfcontact import (
    Pairs,
    SelfContact,
    find_pairs,
    find_pairs_fitting,
    step_radius,
)

__all__ = [
    "Candidates",
    "after_step",
    "candidates",
    "couplings",
    "filter_step",
    "frame",
    "grad",
    "spread",
    "start",
]


class Candidates(NamedTuple):
    """pairs: C, the candidate pairs (within d_hat + 2 reach of x_c); x_c: (n, 3) where they
    were found; reach: () m, B; active: the pairs closer than d_hat at the current iterate;
    builds: () int32, broad phases run; dist: (P,) m, C's distances at x_c."""

    pairs: Pairs
    x_c: jax.Array
    reach: jax.Array
    active: Pairs
    builds: jax.Array
    dist: jax.Array


def _ladder(big, small):
    """(K,) m, the reaches a broad phase tries, descending: big, big/2, ..., big/16 and small."""
    steps = big * 0.5 ** jnp.arange(5, dtype=jnp.result_type(big))
    return jnp.sort(jnp.concatenate([steps, jnp.reshape(small, (1,)).astype(steps.dtype)]))[::-1]


def candidates(cloth, sc: SelfContact, x, reach=None, small=0.0):
    """C at x (n, 3): every pair within d_hat + 2 r (the broad phase), r the largest reach of
    `_ladder(reach, small)` whose pairs fit the capacity (reach: default `step_radius`); each
    row's distance (inf where it holds no pair), and r.
    Shapes: x (n, 3), reach () -> (Pairs with P rows, (P,), ())."""
    reach = step_radius(cloth, sc) if reach is None else reach
    ladder = _ladder(jnp.asarray(reach, x.dtype), small)
    c, d, radius = find_pairs_fitting(cloth, sc, x, sc.thickness + 2.0 * ladder)
    return c, d, 0.5 * (radius - sc.thickness)


def _found(cloth, sc, x, small, found=None, top=None):
    """(C, distances, reach, broad phases): `candidates` at x from the reach top (default the
    full reach B; found: its result at x, reused). Where its raw candidates overflow (a pile
    fills the cells sized for top), the ladder again from max(top/4, small) (cells with about a
    third of the volume), then from the reach `small` alone."""
    small = jnp.asarray(small, x.dtype)
    top = step_radius(cloth, sc) if top is None else top
    c, d, r = candidates(cloth, sc, x, top, small) if found is None else found
    mid = jnp.maximum(0.25 * top, small)

    def from_reach(reach, builds, prev):
        return jax.lax.cond(
            prev[0].overflow,
            lambda: (*candidates(cloth, sc, x, reach, small), builds),
            lambda: prev,
        )

    out = (c, d, jnp.asarray(r, x.dtype), jnp.int32(1))
    return from_reach(small, jnp.int32(3), from_reach(mid, jnp.int32(2), out))


def spread(u):
    """() m, max_i |u_i - c| with c the centre of u's bounding box (the displacement u (n, 3)
    less a common translation). Shapes: u (n, 3) -> ()."""
    u = jax.lax.stop_gradient(u)
    c = 0.5 * (jnp.min(u, axis=0) + jnp.max(u, axis=0))
    return jnp.max(safe_norm(u - c))


def start(cloth, sc: SelfContact, x, found=None) -> Candidates:
    """The pair sets at the start x (n, 3) of a solve; found: `candidates` at x (default:
    found here).
    Shapes: x (n, 3) -> Candidates."""
    x = jax.lax.stop_gradient(x)
    c, d, reach, builds = _found(cloth, sc, x, 0.0, found)
    active = c._replace(valid=c.valid & (d < sc.thickness))
    return Candidates(c, x, reach, active, builds, d)


def filter_step(cloth, sc: SelfContact, cs: Candidates, x, p):
    """The step filter: p (n, 3) capped (max_i |p_i - c| <= B), C found again at x if x + p
    leaves its reach, the step's pairs, and the CCD bound on them.
    Shapes: x, p (n, 3) -> (p (n, 3), shrink (), step's Pairs, Candidates)."""
    x, p = jax.lax.stop_gradient(x), jax.lax.stop_gradient(p)
    reach = step_radius(cloth, sc)
    shrink = jnp.minimum(1.0, reach / jnp.maximum(spread(p), 1e-30))
    p = p * shrink
    moved = jnp.maximum(spread(x - cs.x_c), spread(x + p - cs.x_c))

    def again():  # from twice the reach that last fitted (a pile: that first search fits)
        small = 1.001 * spread(p)
        top = jnp.clip(2.0 * cs.reach, small, reach)
        c, d, r, b = _found(cloth, sc, x, small, top=top)
        return cs._replace(pairs=c, x_c=x, reach=r, builds=cs.builds + b, dist=d)

    keep = (moved <= cs.reach) & ~cs.pairs.overflow
    cs = jax.lax.cond(keep, lambda: cs, again)
    # found again where only a reach below the step's fits (a pile): the step is cut to it
    cut = jnp.where(keep, 1.0, jnp.minimum(1.0, cs.reach / jnp.maximum(spread(p), 1e-30)))
    p, shrink = p * cut, shrink * cut
    moved = jnp.where(keep, moved, spread(p))
    # C's rows that x + a p can bring within d_hat by the cloth's displacement from x_c (less a
    # translation) at most; then by the pair's own distance and relative motion
    near = cs.pairs._replace(valid=cs.pairs.valid & (cs.dist < sc.thickness + 2.0 * moved))
    pairs = sce.within(x, near, sc.thickness, p)
    bound = sce.step_bound(x, p, pairs)
    return p * bound, shrink * bound, pairs, cs


def after_step(sc: SelfContact, cs: Candidates, x, pairs: Pairs, accept) -> Candidates:
    """The active pairs at the new iterate x (n, 3) (accepted: within d_hat among the step's
    pairs; else as before).
    Shapes: x (n, 3) -> Candidates."""
    new = sce.within(x, pairs, sc.thickness)
    active = jax.tree_util.tree_map(lambda a, b: jnp.where(accept, a, b), new, cs.active)
    return cs._replace(active=active)


def couplings(cloth, sc: SelfContact, x, pairs, frame, x_prev, mu, eps):
    """The PSD couplings between the vertices of each pair in contact at x (n, 3) (the
    barrier's Gauss-Newton term and, with a friction frame, the lagged friction's), for
    `linsolve.factor`: the first P/8 of each (any more are left out of the preconditioner,
    which stays PSD). pairs: a superset of those within d_hat (default: found here).
    Shapes: x (n, 3) -> (idx (Q, 4), w (Q, 4), core (Q, 3, 3))."""
    pairs = find_pairs(cloth, sc, x, sc.thickness) if pairs is None else pairs
    pairs, frame = sce.compact(pairs, frame, max(256, pairs.valid.shape[0] // 8))
    parts = [sce.barrier_cores(cloth, sc, x, pairs)]
    if frame is not None:
        parts.append(sce.friction_cores(frame, x, x_prev, mu, eps))
    return tuple(jnp.concatenate(a) for a in zip(*parts, strict=True))


def frame(cloth, sc: SelfContact, x_prev, pairs: Pairs) -> sce.FrictionFrame:
    """`selfcontact_energy.friction_frame` at x_prev (n, 3) on the candidate pairs found there
    (`candidates`), or on the pairs within d_hat where those overflowed.
    Shapes: x_prev (n, 3) -> FrictionFrame."""
    x_prev = jax.lax.stop_gradient(x_prev)
    return jax.lax.cond(
        pairs.overflow,
        lambda: sce.friction_frame(cloth, sc, x_prev),
        lambda: sce.friction_frame(cloth, sc, x_prev, pairs),
    )


def grad(theta, x, pairs: Pairs, eps):
    """The gradient (n, 3) of the self-contact terms of a solve's energy at x (n, 3), pinned
    vertices placed (zero on them): the barrier on pairs and, in an implicit step (theta holds
    "sc_frame"), the lagged friction (`selfcontact_energy.barrier_grad`, `friction_grad`).
    Shapes: x (n, 3) -> (n, 3)."""
    cloth, sc = theta["cloth"], theta["self_contact"]
    g = sce.barrier_grad(cloth, sc, x, pairs)
    if "sc_frame" in theta:
        mu = theta["fabric"].friction * sc.friction
        g = g + sce.friction_grad(theta["sc_frame"], x, theta["x_n"], mu, eps)
    return g * theta["free"][:, None]
