"""Pure force terms on the control net: (net, material, x, v) -> (rows, cols, 3) in N.

Springs are evaluated on zero-padded planar arrays as shifted slices (no gathers, no scatter-adds):
one scalar per spring (force on its first node s * (x_second - x_first)), then one loop gathers the
eight spring ends, the bending stencil and the cell drag onto each node. A gather/scatter version over
explicit spring lists (`make_gather_forces`) is kept as a reference and benchmark.

Degenerate springs (two nodes at one point): the grid kernels give them zero force (ROBUSTNESS row 1
allows it), the reference `_pair_force` falls back to +y; values and gradients stay finite.
"""

# ruff: noqa: F401  (re-exports: names moved to sibling modules stay importable here)
from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from diffcloth.physics.material import Material
from diffcloth.physics.net import Net, bend_triplets, spring_list
from diffcloth.physics.planar import (
    _accumulate,
    _bend_accumulate,
    _cross,
    _direction,
    _direction_planar,
    _dot,
    _pad,
    _pair_dforce,
    _pair_force,
    _pairs,
    _second_diff,
    _stiffness,
    from_planar,
    to_planar,
)
from diffcloth.physics.stencil import (
    _CELLS,
    _ENDS,
    _SETS,
    _cell_drag_forces,
    _cell_vectors,
    _forces_planar,
    _frame,
    _frame_coefficients,
    _frame_constants,
    _frame_forces,
    _fs,
    _ns,
    _padded,
    _spring_coef,
)
from diffcloth.physics.stencil_vjp import (
    _HAND_VJP,
    _bend_stencil,
    _cell_frame,
    _stencil,
    _stencil_bwd,
    _stencil_fwd,
    _stencil_params,
    _stencil_primal,
    _stencil_vjp,
    autodiff_forces,
)


def hand_vjp(material) -> bool:
    """True when `total_forces_fn` gives forces with the hand-written VJP (continuum Material,
    outside `autodiff_forces`): their residuals are only (x, v), nothing to checkpoint."""
    return not hasattr(material, "total_forces_planar") and _HAND_VJP[0]


def total_forces_fn(net: Net, material: Material, gravity, wind):
    """A function (x, v) -> springs + bending + drag + gravity (3, R, C) on planar x, v.

    The material-dependent frames are built once, here (call it outside a substep loop), and the
    forces carry the hand-written VJP (reverse mode only; see `autodiff_forces`).
    """
    if hasattr(material, "total_forces_planar"):  # another force model (physics.massspring)
        return lambda x, v: material.total_forces_planar(net, x, v, gravity, wind)
    mass_g = node_mass(net, material)[None] * gravity[:, None, None]
    if not _HAND_VJP[0]:
        return lambda x, v: _forces_planar(net, material, x, v, wind=wind) + mass_g
    cfg = (net.rows, net.cols, wind is not None)
    params = _stencil_params(net, material, wind)
    return lambda x, v: _stencil(cfg, params, x, v) + mass_g


def _stencil_forces(net, material, x, v, wind):
    """Springs + bending + drag (3, R, C) with the hand-written VJP (see `autodiff_forces`)."""
    if not _HAND_VJP[0]:
        return _forces_planar(net, material, x, v, wind=wind)
    cfg = (net.rows, net.cols, wind is not None)
    return _stencil(cfg, _stencil_params(net, material, wind), x, v)


def _spring_forces(net, material, x, v):
    return _forces_planar(net, material, x, v, bend=False)


def _bend_forces(net, material, x, v):
    return _forces_planar(net, material, x, v, springs=False)


def _internal_forces(net, material, x, v):
    return _forces_planar(net, material, x, v)


def _total_forces(net, material, x, v, gravity, wind):
    """Springs, bending, drag and gravity (3, R, C) on planar x, v."""
    if hasattr(material, "total_forces_planar"):  # another force model (physics.massspring)
        return material.total_forces_planar(net, x, v, gravity, wind)
    f = _stencil_forces(net, material, x, v, wind)
    return f + node_mass(net, material)[None] * gravity[:, None, None]


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


def _drag_forces(net, material, x, v, wind):
    consts = _frame_constants(net, material)
    return _cell_drag_forces(net, material, _padded(x), _padded(v), consts, wind)


def _external_forces(net, material, x, v, gravity, wind):
    mass = node_mass(net, material)
    return mass[None] * gravity[:, None, None] + _drag_forces(net, material, x, v, wind)


# ---------------------------------------------------------------------------------------------
# public forms: (rows, cols, 3) in, (rows, cols, 3) out


def spring_forces(net: Net, material: Material, x, v):
    """Structural and shear spring forces with Rayleigh damping, N, (rows, cols, 3)."""
    return from_planar(_spring_forces(net, material, to_planar(x), to_planar(v)))


def bend_forces(net: Net, material: Material, x, v):
    """Bending forces (quadratic discrete-curvature energy on skip-one triplets), N.

    Shapes: x (rows, cols, 3) m, v (rows, cols, 3) m/s -> (rows, cols, 3) N.
    """
    return from_planar(_bend_forces(net, material, to_planar(x), to_planar(v)))


def internal_forces(net: Net, material: Material, x, v):
    """All internal (spring + bend) forces; they sum to zero and are invariant to rigid motion.

    Shapes: x (rows, cols, 3) m, v (rows, cols, 3) m/s -> (rows, cols, 3) N.
    """
    return from_planar(_internal_forces(net, material, to_planar(x), to_planar(v)))


def internal_force_differential(net: Net, material: Material, x, dx, dv):
    """Linearised internal force change for position change dx and velocity change dv (PSD model).

    Shapes: x, dx (rows, cols, 3) m, dv (rows, cols, 3) m/s -> (rows, cols, 3) N.
    """
    p = to_planar
    return from_planar(_internal_force_differential(net, material, p(x), p(dx), p(dv)))


def node_mass(net: Net, material: Material):
    """Lumped node masses, kg, (rows, cols): density * area (differentiable in density)."""
    if hasattr(material, "node_mass"):  # another force model (physics.massspring)
        return material.node_mass(net)
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
    return from_planar(_total_forces(net, material, to_planar(x), to_planar(v), gravity, wind))


# ---------------------------------------------------------------------------------------------
# energies


def elastic_energy(net: Net, material: Material, x):
    """Spring + bending potential energy, J. Its negative gradient is `internal_forces` at v = 0.

    Shapes: x (rows, cols, 3) m -> () J.
    """
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
    """Elastic energy plus gravitational energy -sum m g.x, J.

    Shapes: x (rows, cols, 3) m, gravity (3,) m/s^2 -> () J.
    """
    mass = node_mass(net, material)
    return elastic_energy(net, material, x) - jnp.sum(mass[..., None] * x * gravity[None, None, :])


def kinetic_energy(net: Net, material: Material, v):
    """sum 1/2 m |v|^2, J (pinned nodes included).

    Shapes: v (rows, cols, 3) m/s -> () J.
    """
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
    """Gershgorin bound (N/m) on the largest eigenvalue of the stiffness matrix at rest, eager.

    Shapes: net and material leaves -> a Python float () N/m.
    """
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
