"""Exact box-filter coverage of a pixel by a straight edge, for the silhouette antialiasing.

nvdiffrast's analytic antialiasing blends each silhouette pixel pair by |t - 1/2|, t the
crossing of the edge on the segment between the two centres. That is the exact box-filtered
coverage only for an edge perpendicular to the pair: a slanted edge (slope k = |tan| of its angle
to the pair's normal direction, 0 <= k <= 1 since every edge is handled by the pair direction it is
most perpendicular to, `pair_share`) leaves the nearer pixel fully covered and the farther one empty when t >
1/2 + (1 - k)/2 ... and over- or under-covers both otherwise (up to k / 8 of a pixel at 45 degrees).
`edge_coverage` is the exact area of the unit pixel on the surface's side of the edge line; with it
the blended pair has the same coverage as a box-filtered (path-traced) pixel, so cloth masks cut by
a threshold agree with a path tracer's (benchmarks/peers/mitsuba_agreement.py), and with k = 0 it
is nvdiffrast's weight exactly.
"""

from __future__ import annotations

import jax.numpy as jnp

__all__ = ["PAIR_BAND", "edge_coverage", "pair_share"]

#: width, in u = along / (along + across), of the band around 45 degrees in which an edge's
#: antialiasing moves smoothly from one pair direction to the other (`pair_share`).
PAIR_BAND = 0.1


def edge_coverage(sigma, k):
    """Fraction of a unit pixel on the covered side of a straight edge.

    Args:
      sigma: (...) signed distance, along the pair direction, from the edge crossing to the pixel
        centre (> 0 on the covered side), in pixels; differentiable.
      k: (...) edge slope in [0, 1] relative to the pair direction (0: edge perpendicular to it);
        differentiable.
    Returns:
      (...) area in [0, 1]: 1/2 + sigma where the edge crosses both pixel sides parallel to the
      pair (|sigma| <= (1 - k) / 2), a corner triangle (quadratic) beyond, 0 / 1 past (1 + k) / 2.
      Continuous with a continuous derivative in sigma; equals clip(1/2 + sigma, 0, 1) at k = 0.
    """
    k = jnp.clip(k, 0.0, 1.0)
    lin = 0.5 * (1.0 - k)
    u = 0.5 * (1.0 + k)
    kk = jnp.where(k > 1e-6, k, 1.0)
    hi = 1.0 - jnp.square(jnp.clip(u - sigma, 0.0, None)) / (2.0 * kk)
    lo = jnp.square(jnp.clip(u + sigma, 0.0, None)) / (2.0 * kk)
    mid = 0.5 + sigma
    a = jnp.where(sigma > lin, hi, jnp.where(sigma < -lin, lo, mid))
    a = jnp.where(k > 1e-6, a, jnp.clip(mid, 0.0, 1.0))
    return jnp.clip(a, 0.0, 1.0)


def pair_share(along, across):
    """Share of an edge's antialiasing given to one pair direction (horizontal or vertical).

    nvdiffrast hands each edge to the pair direction it is most perpendicular to. That hard switch
    at 45 degrees hands a pixel's blend to a different neighbour pair as the edge turns through 45
    degrees: a jump in the image (seen as a jump in the main job's loss; tests/test_fit_smooth.py).
    Here the share moves smoothly (a smoothstep over `PAIR_BAND` in u = along / (along + across))
    from the other direction to this one, and the two directions' shares sum to 1.

    Args:
      along: (...) |component| of the edge's screen normal along this pair direction; differentiable.
      across: (...) |component| along the other direction; differentiable.
    Returns:
      (...) share in [0, 1]: 1 for an edge within about 39 degrees of perpendicular to the pair,
      0 within about 39 degrees of parallel, 1/2 at 45 degrees; share(a, b) + share(b, a) = 1.
    """
    total = along + across
    u = along / jnp.where(total > 0, total, 1.0)
    x = jnp.clip((u - 0.5) / PAIR_BAND + 0.5, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)
