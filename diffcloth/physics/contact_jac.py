"""The "impact" contact rule with a per-node Jacobian derivative (fast reverse mode on CPU).

`collide._impact_contact` is a per-node map: each node's new position and velocity depend only on
that node's own inputs. Differentiated by plain autodiff, its backward pass is a long chain of small
elementwise pieces split at many broadcasts and selects, which XLA's CPU fusion recomputes in every
consumer: it made the main job's physics gradient 2.4x slower than the "coulomb" rule while the
forward cost was the same (benchmarks/RESULTS.md, fit step). Here the derivative is a `custom_jvp`
whose rule builds each node's (6, k) Jacobian (forward mode, vmapped over nodes; k <= 19: only the
inputs whose tangent is not a symbolic zero, e.g. h, friction and a resting sphere's velocity are
skipped, 0.95x gradient time on drape_fit) and applies it with one contraction; transposed for
reverse mode, that is one contraction too. Forward mode
(jacfwd: the LM engine) works as before. Values are those of `_impact_contact` exactly; derivatives
agree to rounding.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import SymbolicZero

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


@functools.partial(impact_contact.defjvp, symbolic_zeros=True)
def _impact_contact_jvp(primals, tangents):
    out = impact_contact(*primals)
    shape = primals[7].shape
    n = primals[7].size
    ins = [p for i, p in enumerate(primals) if i != 5]
    tans = [t for i, t in enumerate(tangents) if i != 5]
    # only the columns of inputs that carry a tangent (h, friction and the sphere velocity are
    # often constants: symbolic zeros): each node's (6, k) Jacobian by forward mode
    live = [not isinstance(t, SymbolicZero) for t in tans]
    cols, i = [], 0
    for size, on in zip(_SIZES, live, strict=True):
        cols += list(range(i, i + size)) if on else []
        i += size
    if not cols:
        return out, tuple(jnp.zeros_like(o) for o in out)
    basis = jnp.asarray(np.eye(i, dtype=np.float32)[cols], primals[0].dtype)  # (k, 19)
    inside = (primals[5] > 0).reshape(-1)

    def node_jac(zn, inn):
        push = lambda e: jax.jvp(lambda q: _node(q, inn), (zn,), (e,))[1]
        return jax.vmap(push, out_axes=1)(basis)  # (6, k)

    jac = jax.vmap(node_jac)(_stack(*ins), inside)  # (N, 6, k)
    vec = lambda a: jnp.broadcast_to(a, (3,) + shape).reshape(3, n).T
    sca = lambda a: jnp.broadcast_to(a, shape).reshape(n, 1)
    pick = zip(tans, _SIZES, live, strict=True)
    parts = [(vec if size == 3 else sca)(t) for t, size, on in pick if on]
    tz = jnp.concatenate(parts, axis=1)  # (N, k)
    dout = jnp.einsum("nij,nj->ni", jac, tz)  # (N, 6)
    dx = dout[:, :3].T.reshape((3,) + shape)
    dv = dout[:, 3:].T.reshape((3,) + shape)
    return out, (dx, dv)
