"""The "impact" contact rule with a per-node Jacobian derivative (fast reverse mode on CPU).

`collide._impact_contact` is a per-node map: each node's new position and velocity depend only on
that node's own inputs. Differentiated by plain autodiff, its backward pass is a long chain of small
elementwise pieces split at many broadcasts and selects, which XLA's CPU fusion recomputes in every
consumer: it made the main job's physics gradient 2.4x slower than the "coulomb" rule while the
forward cost was the same (benchmarks/RESULTS.md, fit step). Here the derivative is a `custom_jvp`
whose rule builds each node's (6, 19) Jacobian (forward mode, vmapped over nodes) and applies it
with one contraction; transposed for reverse mode, that is one contraction too. Forward mode
(jacfwd: the LM engine) works as before. Values are those of `_impact_contact` exactly; derivatives
agree to rounding.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from diffcloth.physics.collide import _impact_contact

#: inputs per node: x, v, v_start, vel, nrm (3 each), d0, d1, friction, h (1 each)
_SIZES = (3, 3, 3, 3, 3, 1, 1, 1, 1)


def _node(z, inside):
    """One node: z (19,) stacked inputs, inside () bool -> (6,) new position and velocity."""
    parts, i = [], 0
    for n in _SIZES:
        parts.append(z[i : i + n])
        i += n
    x, v, vs, vel, nrm, d0, d1, fr, h = parts
    col = lambda a: a[:, None]  # (3,) -> planar (3, 1)
    xn, vn = _impact_contact(
        col(x), col(v), col(vs), col(vel), col(nrm), inside[None], d0, d1, fr[0], h[0]
    )
    return jnp.concatenate([xn[:, 0], vn[:, 0]])


def _stack(x, v, v_start, vel, nrm, d0, d1, friction, h):
    """Planar inputs -> (N, 19) per-node input rows (broadcast where shared)."""
    shape = d1.shape
    n = d1.size
    vec = lambda a: jnp.broadcast_to(a, (3,) + shape).reshape(3, n).T
    sca = lambda a: jnp.broadcast_to(a, shape).reshape(n, 1)
    cols = [vec(x), vec(v), vec(v_start), vec(vel), vec(nrm)]
    cols += [sca(d0), sca(d1), sca(friction), sca(h)]
    return jnp.concatenate(cols, axis=1)


@jax.custom_jvp
def impact_contact(x, v, v_start, vel, nrm, inside_f, d0, d1, friction, h):
    """`collide._impact_contact` (inside given as a float mask, > 0 inside); same shapes and
    values: x, v, v_start, nrm (3, R, C), vel (3, 1, 1) or (3, R, C), inside_f, d0, d1 (R, C),
    friction, h () -> (x, v) (3, R, C)."""
    return _impact_contact(x, v, v_start, vel, nrm, inside_f > 0, d0, d1, friction, h)


@impact_contact.defjvp
def _impact_contact_jvp(primals, tangents):
    x, v, v_start, vel, nrm, inside_f, d0, d1, friction, h = primals
    out = impact_contact(*primals)
    t = list(tangents)
    del t[5]  # the mask has no tangent
    ins = [p for i, p in enumerate(primals) if i != 5]
    shape = d1.shape
    z = _stack(*ins)
    jac = jax.vmap(jax.jacfwd(_node), in_axes=(0, 0))(z, (inside_f > 0).reshape(-1))  # (N, 6, 19)
    tz = _stack(*t)
    dout = jnp.einsum("nij,nj->ni", jac, tz)  # (N, 6)
    dx = dout[:, :3].T.reshape((3,) + shape)
    dv = dout[:, 3:].T.reshape((3,) + shape)
    return out, (dx, dv)
