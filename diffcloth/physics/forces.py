"""Pure force terms on the control net: (net, material, x, v) -> (rows, cols, 3) in N.

Springs are evaluated as shifted slices of the (rows, cols, 3) arrays and accumulated back onto nodes
with zero padding, which XLA fuses into a few loops (no gathers, no scatter-adds). A gather/scatter
version over explicit spring lists (`internal_forces_gather`) is kept as a reference and benchmark.

Degenerate springs (two nodes at one point) use a per-element double `where`: the direction falls back
to +y, the value and the gradient stay finite.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from diffcloth._math import _eps
from diffcloth.physics.material import Material
from diffcloth.physics.net import Net, bend_triplets, spring_list

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
    ok = sq > _eps(d)
    length = jnp.sqrt(jnp.where(ok, sq, 1.0))
    fallback = jnp.zeros((1,) * (d.ndim - 1) + (3,), d.dtype).at[..., 1].set(1.0)
    return jnp.where(ok, length, 0.0), jnp.where(ok, d / length, fallback)


def _direction_planar(d):
    """Length (...) and unit direction (3, ...) of planar d; +y fallback at zero length."""
    sq = _dot(d, d)
    ok = sq > _eps(d)
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


def _spring_forces(net, material, x, v):
    kh, kv, kd = _stiffness(net, material)
    c = material.damping
    rests = (net.rest_h, net.rest_v, net.rest_d1, net.rest_d2)
    ks = (kh, kv, kd, kd)
    fs = [
        _pair_force(d, u, r, k, c * k)
        for d, u, r, k in zip(_pairs(x), _pairs(v), rests, ks, strict=True)
    ]
    return _accumulate(*fs)


def _bend_forces(net, material, x, v):
    sh, sv = _second_diff(x)
    uh, uv = _second_diff(v)
    gh = (material.bend * net.weight_bh)[None] * (sh + material.damping * uh)
    gv = (material.bend * net.weight_bv)[None] * (sv + material.damping * uv)
    return _bend_accumulate(gh, gv)


def _internal_forces(net, material, x, v):
    return _spring_forces(net, material, x, v) + _bend_forces(net, material, x, v)


def _internal_force_differential(net, material, x, dx, dv):
    kh, kv, kd = _stiffness(net, material)
    c = material.damping
    rests = (net.rest_h, net.rest_v, net.rest_d1, net.rest_d2)
    ks = (kh, kv, kd, kd)
    fs = [
        _pair_dforce(d, dd, du, r, k, c * k)
        for d, dd, du, r, k in zip(_pairs(x), _pairs(dx), _pairs(dv), rests, ks, strict=True)
    ]
    sh, sv = _second_diff(dx)
    uh, uv = _second_diff(dv)
    gh = (material.bend * net.weight_bh)[None] * (sh + c * uh)
    gv = (material.bend * net.weight_bv)[None] * (sv + c * uv)
    return _accumulate(*fs) + _bend_accumulate(gh, gv)


def _cross(a, b):
    return jnp.stack(
        [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    )


def _drag_forces(net, material, x, v, wind):
    an = 0.5 * _cross(x[:, 1:, 1:] - x[:, :-1, :-1], x[:, :-1, 1:] - x[:, 1:, :-1])
    area, n = _direction_planar(an)
    u = 0.25 * (v[:, :-1, :-1] + v[:, :-1, 1:] + v[:, 1:, :-1] + v[:, 1:, 1:]) - wind[:, None, None]
    un = _dot(u, n)
    f = (-0.25 * area)[None] * (
        material.drag_tangent * u + ((material.drag_normal - material.drag_tangent) * un)[None] * n
    )
    return _pad(f, 0, 1, 0, 1) + _pad(f, 1, 0, 1, 0) + _pad(f, 1, 0, 0, 1) + _pad(f, 0, 1, 1, 0)


def _external_forces(net, material, x, v, gravity, wind):
    mass = node_mass(net, material)
    return mass[None] * gravity[:, None, None] + _drag_forces(net, material, x, v, wind)


# ---------------------------------------------------------------------------------------------
# public forms: (rows, cols, 3) in, (rows, cols, 3) out


def spring_forces(net: Net, material: Material, x, v):
    """Structural and shear spring forces with Rayleigh damping, N, (rows, cols, 3)."""
    return from_planar(_spring_forces(net, material, to_planar(x), to_planar(v)))


def bend_forces(net: Net, material: Material, x, v):
    """Bending forces (quadratic discrete-curvature energy on skip-one triplets), N."""
    return from_planar(_bend_forces(net, material, to_planar(x), to_planar(v)))


def internal_forces(net: Net, material: Material, x, v):
    """All internal (spring + bend) forces; they sum to zero and are invariant to rigid motion."""
    return from_planar(_internal_forces(net, material, to_planar(x), to_planar(v)))


def internal_force_differential(net: Net, material: Material, x, dx, dv):
    """Linearised internal force change for position change dx and velocity change dv (PSD model)."""
    p = to_planar
    return from_planar(_internal_force_differential(net, material, p(x), p(dx), p(dv)))


def node_mass(net: Net, material: Material):
    """Lumped node masses, kg, (rows, cols): density * area (differentiable in density)."""
    return material.density * net.area


def drag_forces(net: Net, material: Material, x, v, wind):
    """Aerodynamic drag on the net's cells, relative to the wind, N, (rows, cols, 3).

    Each cell (two triangles) has vector area a = 1/2 (p11 - p00) x (p01 - p10) (the sum of its two
    triangles' area vectors, for either diagonal), area A = |a|, unit normal n = a / A, and relative
    velocity u = mean of its 4 corner velocities - wind:
    f = -A (drag_normal (u.n) n + drag_tangent (u - (u.n) n)), shared equally by its 4 corners, so a
    node's share of drag follows its lumped area (and mass) exactly.
    """
    return from_planar(_drag_forces(net, material, to_planar(x), to_planar(v), wind))


def external_forces(net: Net, material: Material, x, v, gravity, wind):
    """Gravity and aerodynamic drag, N, (rows, cols, 3)."""
    return from_planar(_external_forces(net, material, to_planar(x), to_planar(v), gravity, wind))


def total_forces(net: Net, material: Material, x, v, gravity, wind):
    """Everything that acts on the free nodes, N, (rows, cols, 3)."""
    xp, vp = to_planar(x), to_planar(v)
    f = _internal_forces(net, material, xp, vp) + _external_forces(
        net, material, xp, vp, gravity, wind
    )
    return from_planar(f)


# ---------------------------------------------------------------------------------------------
# energies


def elastic_energy(net: Net, material: Material, x):
    """Spring + bending potential energy, J. Its negative gradient is `internal_forces` at v = 0."""
    kh, kv, kd = _stiffness(net, material)
    rests = (net.rest_h, net.rest_v, net.rest_d1, net.rest_d2)
    ks = (kh, kv, kd, kd)
    xp = to_planar(x)
    e = 0.0
    for d, r, k in zip(_pairs(xp), rests, ks, strict=True):
        length, _ = _direction_planar(d)
        e = e + 0.5 * jnp.sum(k * (length - r) ** 2)
    sh, sv = _second_diff(xp)
    e = e + 0.5 * material.bend * jnp.sum(net.weight_bh * _dot(sh, sh))
    e = e + 0.5 * material.bend * jnp.sum(net.weight_bv * _dot(sv, sv))
    return e


def potential_energy(net: Net, material: Material, x, gravity):
    """Elastic energy plus gravitational energy -sum m g.x, J."""
    mass = node_mass(net, material)
    return elastic_energy(net, material, x) - jnp.sum(mass[..., None] * x * gravity[None, None, :])


def kinetic_energy(net: Net, material: Material, v):
    """sum 1/2 m |v|^2, J (pinned nodes included)."""
    return 0.5 * jnp.sum(node_mass(net, material) * jnp.sum(v * v, -1))


# ---------------------------------------------------------------------------------------------
# reference: gather + scatter-add over explicit spring lists


def make_gather_forces(net: Net):
    """A reference `internal_forces(material, x, v)` using gathers and scatter-adds over spring lists.

    Same physics as `internal_forces`; kept to test the shifted-slice version and for benchmarks.
    """
    pairs, kind, rest, weight = spring_list(net)
    trip, bweight = bend_triplets(net)
    dtype = net.rest.dtype
    i0, i1 = jnp.asarray(pairs[:, 0]), jnp.asarray(pairs[:, 1])
    is_shear = jnp.asarray(kind == 1)
    rest = jnp.asarray(rest, dtype)
    weight = jnp.asarray(weight, dtype)
    ta, tb, tc = (jnp.asarray(trip[:, i]) for i in range(3))
    bweight = jnp.asarray(np.asarray(bweight), dtype)
    n_nodes = net.rows * net.cols

    def forces(material: Material, x, v):
        xf, vf = x.reshape(-1, 3), v.reshape(-1, 3)
        k = jnp.where(is_shear, material.shear, material.stretch) * weight
        f = _pair_force((xf[i1] - xf[i0]).T, (vf[i1] - vf[i0]).T, rest, k, material.damping * k).T
        out = jnp.zeros((n_nodes, 3), x.dtype).at[i0].add(f).at[i1].add(-f)
        s = xf[ta] - 2.0 * xf[tb] + xf[tc]
        s_v = vf[ta] - 2.0 * vf[tb] + vf[tc]
        g = (material.bend * bweight)[:, None] * (s + material.damping * s_v)
        out = out.at[ta].add(-g).at[tb].add(2.0 * g).at[tc].add(-g)
        return out.reshape(x.shape)

    return forces


def max_node_stiffness(net: Net, material: Material) -> float:
    """Gershgorin bound (N/m) on the largest eigenvalue of the stiffness matrix at rest, eager."""
    kh = np.asarray(material.stretch * net.weight_h)
    kv = np.asarray(material.stretch * net.weight_v)
    kd = np.asarray(material.shear * net.weight_d)
    row = np.zeros((net.rows, net.cols))
    for k, (t, b, l, r) in (
        (kh, (0, 0, 0, 1)),
        (kh, (0, 0, 1, 0)),
        (kv, (0, 1, 0, 0)),
        (kv, (1, 0, 0, 0)),
        (kd, (0, 1, 0, 1)),
        (kd, (1, 0, 1, 0)),
        (kd, (0, 1, 1, 0)),
        (kd, (1, 0, 0, 1)),
    ):
        row += 2.0 * np.pad(k, ((t, b), (l, r)))
    bh = np.asarray(material.bend * net.weight_bh)
    bv = np.asarray(material.bend * net.weight_bv)
    for b, axis in ((bh, 1), (bv, 0)):
        for shift, coef in ((0, 4.0), (1, 8.0), (2, 4.0)):
            pad = [(0, 0), (0, 0)]
            pad[axis] = (shift, 2 - shift)
            row += coef * np.pad(b, pad)
    return float(row.max())


__all__ = [
    "spring_forces",
    "bend_forces",
    "internal_forces",
    "internal_force_differential",
    "drag_forces",
    "external_forces",
    "total_forces",
    "node_mass",
    "elastic_energy",
    "potential_energy",
    "kinetic_energy",
    "make_gather_forces",
    "max_node_stiffness",
]
