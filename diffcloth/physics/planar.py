"""Planar vector helpers of the force terms: (3, rows, cols) storage, pair forces, padding,
accumulation of spring ends and the bending stencil onto nodes."""

from __future__ import annotations

import jax.numpy as jnp

from diffcloth._math import dtype_eps
from diffcloth.physics.material import Material
from diffcloth.physics.net import Net

# ---------------------------------------------------------------------------------------------
# Internally vectors are stored planar, (3, rows, cols): every operation is then an elementwise loop
# over a (rows, cols) plane, which XLA vectorises far better than reductions over a trailing axis of 3.


def to_planar(a):
    """(rows, cols, 3) -> (3, rows, cols)."""
    return jnp.moveaxis(a, -1, 0)


def from_planar(a):
    """(3, rows, cols) -> (rows, cols, 3)."""
    return jnp.moveaxis(a, 0, -1)


def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _direction(d):
    """(rows, cols, 3)-style: length (..., 1) and unit direction (..., 3); +y fallback at zero."""
    sq = jnp.sum(d * d, axis=-1, keepdims=True)
    ok = sq > dtype_eps(d)
    length = jnp.sqrt(jnp.where(ok, sq, 1.0))
    fallback = jnp.zeros((1,) * (d.ndim - 1) + (3,), d.dtype).at[..., 1].set(1.0)
    return jnp.where(ok, length, 0.0), jnp.where(ok, d / length, fallback)


def _direction_planar(d):
    """Length (...) and unit direction (3, ...) of planar d; +y fallback at zero length."""
    sq = _dot(d, d)
    ok = sq > dtype_eps(d)
    length = jnp.sqrt(jnp.where(ok, sq, 1.0))
    fallback = jnp.zeros((3,) + (1,) * (d.ndim - 1), d.dtype).at[1].set(1.0)
    n = jnp.where(ok[None], d / length[None], fallback)
    return jnp.where(ok, length, 0.0), n


def _pair_force(d, dv, rest, k, c):
    """Force (3, ...) on the first node of each spring, d = x_second - x_first; k, c, rest: (...)."""
    length, n = _direction_planar(d)
    mag = k * (length - rest) + c * _dot(dv, n)
    return mag[None] * n


def _pair_dforce(d, dd, du, rest, k, c):
    """Differential of `_pair_force` for the implicit solver, made positive semi-definite.

    The transverse stiffness k (1 - rest/L) is clamped at 0 (Choi & Ko), and the change of the damping
    direction is neglected: this is the Newton matrix, not the exact derivative.
    """
    length, n = _direction_planar(d)
    nd = _dot(n, dd)
    pos = length > 0
    trans = jnp.where(pos, jnp.maximum(1.0 - rest / jnp.where(pos, length, 1.0), 0.0), 0.0)
    return (
        k[None] * (nd[None] * n + trans[None] * (dd - nd[None] * n)) + (c * _dot(n, du))[None] * n
    )


def _pad(a, top, bottom, left, right):
    return jnp.pad(a, ((0, 0), (top, bottom), (left, right)))


def _accumulate(fh, fv, fd1, fd2):
    """Node forces from per-spring forces on each spring's first node (second gets the opposite)."""
    out = _pad(fh, 0, 0, 0, 1) - _pad(fh, 0, 0, 1, 0)
    out = out + _pad(fv, 0, 1, 0, 0) - _pad(fv, 1, 0, 0, 0)
    out = out + _pad(fd1, 0, 1, 0, 1) - _pad(fd1, 1, 0, 1, 0)
    out = out + _pad(fd2, 0, 1, 1, 0) - _pad(fd2, 1, 0, 0, 1)
    return out


def _pairs(a):
    """(second - first) for the four spring sets of the planar array a (3, rows, cols)."""
    return (
        a[:, :, 1:] - a[:, :, :-1],
        a[:, 1:, :] - a[:, :-1, :],
        a[:, 1:, 1:] - a[:, :-1, :-1],
        a[:, 1:, :-1] - a[:, :-1, 1:],
    )


def _stiffness(net: Net, material: Material):
    kh = material.stretch * net.weight_h
    kv = material.stretch * net.weight_v
    kd = material.shear * net.weight_d
    return kh, kv, kd


def _second_diff(a):
    sh = a[:, :, :-2] - 2.0 * a[:, :, 1:-1] + a[:, :, 2:]
    sv = a[:, :-2] - 2.0 * a[:, 1:-1] + a[:, 2:]
    return sh, sv


def _bend_accumulate(gh, gv):
    """Node forces from per-triplet g = dE/ds: f_a = -g, f_b = 2g, f_c = -g."""
    out = -_pad(gh, 0, 0, 0, 2) + 2.0 * _pad(gh, 0, 0, 1, 1) - _pad(gh, 0, 0, 2, 0)
    out = out - _pad(gv, 0, 2, 0, 0) + 2.0 * _pad(gv, 1, 1, 0, 0) - _pad(gv, 2, 0, 0, 0)
    return out


def _cross(a, b):
    return jnp.stack(
        [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    )
