"""Self-contact of the mesh cloth, part 1: the settings, the unsigned vertex-triangle and
edge-edge distances, and the broad phase that finds every pair closer than a radius.

Broad phase (jit, fixed capacity): triangles are keyed by the grid cell of their centroid and
edges by that of their midpoint, the keys are sorted, and each query walks the key ranges of
the cells around its own (hashed, duplicates and other cells that share a hash dropped). A
vertex's cells are the 27 around it, sized the search radius + the largest centroid-to-corner
distance; an edge's are its own cell and the 13 after it (each pair of cells once), sized the
radius + the longest edge. The candidates are enumerated into a fixed number of slots by a
prefix sum (no per-cell limit), culled by a bounding-sphere test (the vertex within radius +
the triangle's corner distance of its centroid; the midpoints within radius + the half
lengths), compacted, filtered by the exact distance, and compacted into the pair capacity.
Pairs that share a vertex in the rest mesh (a vertex and its own faces, edges with a common
end) are excluded. When a candidate or pair count exceeds its capacity the result says so
(`Pairs.overflow`): the barrier energy is then NaN (a solve fails, never misses a contact
silently) and `check_pairs` names the setting to raise (`SelfContact.capacity`,
`[sim] self_contact_capacity`).
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from diffcloth._math import safe_div, safe_norm

__all__ = [
    "Pairs",
    "SelfContact",
    "check_pairs",
    "edge_edge",
    "find_pairs",
    "find_pairs_fitting",
    "find_pairs_with_distance",
    "make_self_contact",
    "min_rest_height",
    "min_triangle_height",
    "point_triangle",
    "step_radius",
]

_OFFSETS = np.array(list(itertools.product((-1, 0, 1), repeat=3)), np.int32)  # (27, 3)
# the cell itself and the 13 neighbours that come after it (a pair of distinct cells once)
_HALF = _OFFSETS[13:]  # (14, 3): (0, 0, 0), then the lexicographically positive offsets
_PRIMES = (73856093, 19349663, 83492791)  # Teschner et al. 2003 spatial hash


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class SelfContact:
    """Self-contact settings of a mesh cloth.

    Attributes:
      thickness: () m, the barrier's reach d_hat: pairs closer than it repel (log barrier).
      stiffness: () N/m^3, the barrier's weight kappa (energy kappa A b(d), A the pair's area).
      friction: () scale of the fabric's Coulomb coefficient between layers (1: the same as
        against the colliders).
      capacity: static, pairs per vertex kept after the distance filter (vertex-triangle, and as
        many edge-edge pairs per edge); the raw candidates get 16 times as many slots.
      step_fraction: static, a Newton step moves no vertex further than this times the mean rest
        edge length (it bounds the broad phase's cells, and so its candidate count).
    """

    thickness: jax.Array
    stiffness: jax.Array
    friction: jax.Array
    capacity: int = dataclasses.field(default=8, metadata={"static": True})
    step_fraction: float = dataclasses.field(default=0.5, metadata={"static": True})


def make_self_contact(
    thickness: float = 2e-3,
    *,
    stiffness: float = 1e5,
    friction: float = 1.0,
    capacity: int = 8,
    step_fraction: float = 0.5,
    cloth=None,
    dtype=None,
) -> SelfContact:
    """Validated SelfContact. thickness: m (> 0; with `cloth`, below half its shortest rest
    triangle height, else the rest mesh is in contact with itself); stiffness: N/m^3 (> 0);
    friction: >= 0; capacity: integer >= 1; step_fraction: in (0, 1].
    Shapes: scalars -> SelfContact of () leaves.
    """
    for name, value, lo in (("thickness", thickness, 0.0), ("stiffness", stiffness, 0.0)):
        if not (math.isfinite(float(value)) and float(value) > lo):
            raise ValueError(f"self_contact.{name} = {value!r} must be finite and > 0")
    if not (math.isfinite(float(friction)) and float(friction) >= 0):
        raise ValueError(f"self_contact.friction = {friction!r} must be >= 0")
    if not (isinstance(capacity, int) and capacity >= 1):
        raise ValueError(f"self_contact.capacity = {capacity!r} must be an integer >= 1")
    if not (0 < float(step_fraction) <= 1):
        raise ValueError(f"self_contact.step_fraction = {step_fraction!r} must be in (0, 1]")
    if cloth is not None:
        h = min_rest_height(cloth)
        if not float(thickness) < 0.5 * h:
            raise ValueError(
                f"self_contact.thickness = {thickness!r} m must be below half the shortest rest "
                f"triangle height ({0.5 * h:.3g} m): lower it or use a coarser mesh"
            )
    dtype = dtype or jnp.zeros(()).dtype
    return SelfContact(
        thickness=jnp.asarray(thickness, dtype),
        stiffness=jnp.asarray(stiffness, dtype),
        friction=jnp.asarray(friction, dtype),
        capacity=int(capacity),
        step_fraction=float(step_fraction),
    )


def min_rest_height(cloth) -> float:
    """The shortest altitude of the rest triangles (material coordinates), m (numpy, eager).
    Shapes: cloth (n vertices, m faces) -> float."""
    return min_triangle_height(cloth.uv, cloth.faces)


def min_triangle_height(points, faces) -> float:
    """The shortest altitude of the triangles faces (m, 3) over points (n, 2) or (n, 3), in the
    points' unit (numpy, eager): the bound on a self-contact thickness (below half of it the
    rest mesh is not in contact with itself).
    Shapes: points (n, 2 | 3), faces (m, 3) -> float."""
    p = np.asarray(points, np.float64)
    if p.shape[-1] == 2:
        p = np.concatenate([p, np.zeros_like(p[:, :1])], axis=1)
    p = p[np.asarray(faces)]
    e = np.stack([p[:, 2] - p[:, 1], p[:, 0] - p[:, 2], p[:, 1] - p[:, 0]], 1)
    area2 = np.linalg.norm(np.cross(e[:, 0], e[:, 1]), axis=1)
    return float(np.min(area2[:, None] / np.maximum(np.linalg.norm(e, axis=2), 1e-300)))


# ---------------------------------------------------------------------------------------------
# distances: each pair as four vertices and four weights, the gap vector sum_k w_k x_k


def point_triangle(p, a, b, c):
    """Weights (4,) [1, -wa, -wb, -wc] of the closest point of triangle abc to p (Ericson 5.1.5,
    in `where` form): the gap vector is p - (wa a + wb b + wc c).
    Shapes: p, a, b, c (3,) -> (4,)."""
    ab, ac, ap, bp, cp = b - a, c - a, p - a, p - b, p - c
    d1, d2, d3, d4, d5, d6 = ab @ ap, ac @ ap, ab @ bp, ac @ bp, ab @ cp, ac @ cp
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    den = va + vb + vc
    v, w = safe_div(vb, den), safe_div(vc, den)
    bary = jnp.stack([1.0 - v - w, v, w])
    one = jnp.ones_like(d1)
    zero = jnp.zeros_like(d1)
    t = safe_div(d4 - d3, (d4 - d3) + (d5 - d6))
    bary = jnp.where((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), jnp.stack([zero, 1 - t, t]), bary)
    t = safe_div(d2, d2 - d6)
    bary = jnp.where((vb <= 0) & (d2 >= 0) & (d6 <= 0), jnp.stack([1 - t, zero, t]), bary)
    t = safe_div(d1, d1 - d3)
    bary = jnp.where((vc <= 0) & (d1 >= 0) & (d3 <= 0), jnp.stack([1 - t, t, zero]), bary)
    bary = jnp.where((d6 >= 0) & (d5 <= d6), jnp.stack([zero, zero, one]), bary)
    bary = jnp.where((d3 >= 0) & (d4 <= d3), jnp.stack([zero, one, zero]), bary)
    bary = jnp.where((d1 <= 0) & (d2 <= 0), jnp.stack([one, zero, zero]), bary)
    return jnp.concatenate([one[None], -bary])


def edge_edge(p0, p1, q0, q1):
    """Weights (4,) [1 - s, s, -(1 - t), -t] of the closest points of segments p0p1 and q0q1
    (Ericson 5.1.9, clamped; parallel segments take s = 0 first).
    Shapes: p0, p1, q0, q1 (3,) -> (4,)."""
    d1, d2, r = p1 - p0, q1 - q0, p0 - q0
    a, e, f, c, b = d1 @ d1, d2 @ d2, d2 @ r, d1 @ r, d1 @ d2
    den = a * e - b * b
    s = jnp.where(den > 1e-8 * a * e, jnp.clip(safe_div(b * f - c * e, den), 0.0, 1.0), 0.0)
    t = safe_div(b * s + f, e)
    s = jnp.where(t < 0, jnp.clip(safe_div(-c, a), 0.0, 1.0),
                  jnp.where(t > 1, jnp.clip(safe_div(b - c, a), 0.0, 1.0), s))  # fmt: skip
    t = jnp.clip(t, 0.0, 1.0)
    return jnp.stack([1.0 - s, s, t - 1.0, -t])


def gap(x, idx, kind):
    """(P, 3) gap vectors of pairs idx (P, 4) of kind (P,) (0 vertex-triangle, 1 edge-edge),
    weights recomputed at x (their derivatives follow the closest points).
    Shapes: x (n, 3), idx (P, 4), kind (P,) -> (P, 3)."""
    q = x[idx]  # (P, 4, 3)
    w = weights(q, kind)
    return jnp.einsum("pk,pki->pi", w, q)


def weights(q, kind):
    """(P, 4) closest-point weights of the pairs' points q (P, 4, 3)."""
    wvt = jax.vmap(point_triangle)(q[:, 0], q[:, 1], q[:, 2], q[:, 3])
    wee = jax.vmap(edge_edge)(q[:, 0], q[:, 1], q[:, 2], q[:, 3])
    return jnp.where((kind == 0)[:, None], wvt, wee)


def _gap_of(x, idx, k: int):
    """(P, 3) gap vectors of pairs idx (P, 4) all of the static kind k (one closest-point
    computation per row, not both)."""
    q = x[idx]
    w = jax.vmap(point_triangle if k == 0 else edge_edge)(q[:, 0], q[:, 1], q[:, 2], q[:, 3])
    return jnp.einsum("pk,pki->pi", w, q)


# ---------------------------------------------------------------------------------------------
# broad phase


class Pairs(NamedTuple):
    """Candidate pairs within a radius, padded to a fixed capacity.

    idx: (P, 4) int32 vertices ([v, a, b, c] or [a0, a1, b0, b1]); kind: (P,) int32, 0 vertex-
    triangle, 1 edge-edge; valid: (P,) bool; overflow: () bool, some candidate or pair did not
    fit (the set is incomplete); count: () int32 pairs found (valid ones, if it fits)."""

    idx: jax.Array
    kind: jax.Array
    valid: jax.Array
    overflow: jax.Array
    count: jax.Array


def _keys(cells):
    c = cells.astype(jnp.uint32)
    return (
        (c[..., 0] * np.uint32(_PRIMES[0]))
        ^ (c[..., 1] * np.uint32(_PRIMES[1]))
        ^ (c[..., 2] * np.uint32(_PRIMES[2]))
    )


def _candidates(query, target, cell, slots, half=False):
    """(slots,) query index, target index and valid mask of the (query, target) pairs whose
    cells are neighbours (the 27 cells around a query's; half: query and target are one set,
    and each unordered pair comes once, from `_HALF`; a target whose cell only shares a hash
    with one of them is dropped), and their total count."""
    tcell = jnp.floor(target / cell).astype(jnp.int32)
    tkey = _keys(tcell)
    order = jnp.argsort(tkey)
    skey = tkey[order]
    qcell = jnp.floor(query / cell).astype(jnp.int32)
    offsets = _HALF if half else _OFFSETS
    k = offsets.shape[0]
    nkeys = _keys(qcell[:, None, :] + jnp.asarray(offsets)[None])  # (nq, K)
    earlier = jnp.asarray(np.tril(np.ones((k, k), bool), -1))
    dup = jnp.any((nkeys[:, :, None] == nkeys[:, None, :]) & earlier[None], axis=2)
    lo = jnp.searchsorted(skey, nkeys, side="left").reshape(-1)
    hi = jnp.searchsorted(skey, nkeys, side="right").reshape(-1)
    ln = jnp.where(dup.reshape(-1), 0, hi - lo)
    cum = jnp.cumsum(ln)
    s = jnp.arange(slots, dtype=cum.dtype)
    owner = jnp.minimum(jnp.searchsorted(cum, s, side="right"), ln.shape[0] - 1)
    off = s - (cum[owner] - ln[owner])
    tgt = order[jnp.clip(lo[owner] + off, 0, order.shape[0] - 1)]
    q = owner // k
    # the target's own cell is one of the query's (its key's range may hold other cells)
    diff = tcell[tgt] - qcell[q]
    near = jnp.all(jnp.abs(diff) <= 1, axis=1)
    if half:  # query = target: the lexicographically positive offsets, and in
        d0, d1, d2 = diff[:, 0], diff[:, 1], diff[:, 2]  # the cell itself the lower index first
        after = (d0 > 0) | ((d0 == 0) & ((d1 > 0) | ((d1 == 0) & (d2 > 0))))
        near = near & (after | (jnp.all(diff == 0, axis=1) & (q < tgt)))
    return q, tgt, (s < cum[-1]) & near, cum[-1]


def _compact(keep, size, *cols):
    """The rows of cols where keep (S,), packed into size rows: (*cols (size,), valid (size,),
    the count kept)."""
    (sel,) = jnp.nonzero(keep, size=size, fill_value=0)
    count = jnp.sum(keep)
    return (*(c[sel] for c in cols), jnp.arange(size) < count, count)


def step_radius(cloth, sc: SelfContact):
    """() m, the most a vertex moves in one Newton step with self-contact on
    (`SelfContact.step_fraction` times the mean rest edge length: it bounds the broad phase's
    cells).
    Shapes: cloth -> ()."""
    e = cloth.edges
    length = safe_norm(cloth.rest[e[:, 1]] - cloth.rest[e[:, 0]])
    return sc.step_fraction * jnp.mean(length)


def find_pairs(cloth, sc: SelfContact, x, radius, motion=None) -> Pairs:
    """Every vertex-triangle and edge-edge pair closer than radius (m) at x (n, 3), excluding
    pairs that share a vertex (module docstring); with motion (n,) m, the bound on each vertex's
    displacement in a step, closer than radius + the largest motion of each side's vertices (the
    pairs the step can bring within radius). Not differentiated (stop_gradient).
    Shapes: x (n, 3), radius (), motion (n,) -> Pairs with P = capacity x (n + num edges)."""
    return find_pairs_with_distance(cloth, sc, x, radius, motion)[0]


def find_pairs_with_distance(cloth, sc: SelfContact, x, radius, motion=None):
    """`find_pairs`, and each row's distance at x (m; inf on rows that hold no pair).
    Shapes: x (n, 3), radius (), motion (n,) -> (Pairs with P rows, (P,))."""
    radius = jnp.asarray(radius)
    return find_pairs_fitting(cloth, sc, x, radius[None], motion)[:2]


def find_pairs_fitting(cloth, sc: SelfContact, x, radii, motion=None):
    """`find_pairs_with_distance` at the largest of the radii (K,) m (descending) whose pairs
    fit the capacity, from one broad phase (its cells sized for radii[0]): in a pile of layers
    the pairs within the full radius can overflow where a shorter one fits. Overflow: the raw
    candidates at radii[0] or those left by the bounding-sphere test did not fit their slots,
    or no radius's pairs fit.
    Shapes: x (n, 3), radii (K,), motion (n,) -> (Pairs with P rows, (P,), () the radius)."""
    x = jax.lax.stop_gradient(x)
    radii = jax.lax.stop_gradient(radii)
    f, e = cloth.faces, cloth.edges
    n, ne = x.shape[0], e.shape[0]
    motion = jnp.zeros(n, x.dtype) if motion is None else jax.lax.stop_gradient(motion)
    elen = safe_norm(x[e[:, 1]] - x[e[:, 0]])
    cap = sc.capacity
    far = radii[0] + 2.0 * jnp.max(motion)
    sized = lambda c: jnp.where(jnp.isfinite(c) & (c > 0), c, 1.0)
    # vertex-triangle: a vertex within r of a triangle is within r + the triangle's reach from
    # its centre (the farthest corner): the exact distance runs on those only (a sixth or so)
    ctr = jnp.mean(x[f], axis=1)
    tri_r = jnp.max(safe_norm(x[f] - ctr[:, None]), axis=1)
    qi, ti, ok, tot_vt = _candidates(x, ctr, sized(1.01 * (jnp.max(tri_r) + far)), 16 * cap * n)
    ok = ok & (jnp.sum((x[qi] - ctr[ti]) ** 2, axis=1) <= (far + tri_r[ti]) ** 2)
    qi, ti, ok, near_vt = _compact(ok, 4 * cap * n, qi, ti)
    idx_vt = jnp.concatenate([qi[:, None], f[ti]], axis=1).astype(jnp.int32)
    ok = ok & jnp.all(idx_vt[:, 1:] != idx_vt[:, :1], axis=1)
    # edge-edge: within r + the two half lengths between midpoints
    mid = 0.5 * (x[e[:, 0]] + x[e[:, 1]])
    cell_ee = sized(1.01 * (jnp.max(elen) + far))
    qe, te, oke, tot_ee = _candidates(mid, mid, cell_ee, 16 * cap * ne, half=True)
    oke = oke & (safe_norm(mid[qe] - mid[te]) <= far + 0.5 * (elen[qe] + elen[te]))
    qe, te = jnp.minimum(qe, te), jnp.maximum(qe, te)  # the lower edge first
    qe, te, oke, near_ee = _compact(oke, 4 * cap * ne, qe, te)
    idx_ee = jnp.concatenate([e[qe], e[te]], axis=1).astype(jnp.int32)
    share = (idx_ee[:, :2, None] == idx_ee[:, None, 2:]).reshape(-1, 4)
    oke = oke & ~jnp.any(share, axis=1)
    rows = []
    for idx, good, k, size in ((idx_vt, ok, 0, cap * n), (idx_ee, oke, 1, cap * ne)):
        d = safe_norm(_gap_of(x, idx, k))
        m4 = motion[idx]
        reach = (m4[:, 0] + jnp.max(m4[:, 1:], axis=1) if k == 0
                 else jnp.max(m4[:, :2], axis=1) + jnp.max(m4[:, 2:], axis=1))  # fmt: skip
        gap_left = jnp.where(good, d - reach, jnp.inf)  # a pair is in at radius r if < r
        fits = jnp.sum(gap_left[None, :] < radii[:, None], axis=1) <= size  # (K,)
        rows.append((idx, k, size, d, gap_left, fits))
    fits = rows[0][5] & rows[1][5]
    pick = jnp.argmax(fits)  # the first (largest) radius that fits; 0 when none does
    radius = radii[pick]
    out = []
    for idx, k, size, d, gap_left, _ in rows:
        good = gap_left < radius
        (sel,) = jnp.nonzero(good, size=size, fill_value=0)
        live = jnp.arange(size) < jnp.sum(good)
        kind = jnp.full((size,), k, jnp.int32)
        out.append((idx[sel], kind, live, jnp.sum(good), size, jnp.where(live, d[sel], jnp.inf)))
    overflow = (tot_vt > 16 * cap * n) | (tot_ee > 16 * cap * ne) | ~jnp.any(fits)
    overflow = overflow | (near_vt > 4 * cap * n) | (near_ee > 4 * cap * ne)
    pairs = Pairs(
        idx=jnp.concatenate([out[0][0], out[1][0]]),
        kind=jnp.concatenate([out[0][1], out[1][1]]),
        valid=jnp.concatenate([out[0][2], out[1][2]]),
        overflow=overflow,
        count=(out[0][3] + out[1][3]).astype(jnp.int32),
    )
    return pairs, jnp.concatenate([out[0][5], out[1][5]]), radius


def check_pairs(pairs: Pairs, what: str = "self-contact") -> Pairs:
    """Eager: raise ValueError naming the setting to raise when the broad phase overflowed.
    Shapes: none (reads the scalars)."""
    if bool(np.asarray(pairs.overflow)):
        raise ValueError(
            f"{what}: the broad phase's capacity overflowed ({int(pairs.count)} pairs or more "
            "candidates than slots); raise SelfContact.capacity ([sim] self_contact_capacity)"
        )
    return pairs
