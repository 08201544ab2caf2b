"""Energies of the mesh cloth, each a pure function (cloth, fabric, x) -> J.

membrane_energy: orthotropic St. Venant-Kirchhoff per face (see `fabric`).
bending_energy: a quadratic energy in each face's curvature tensor, which the face's three hinge
  angles give through the rest `curvature_op` (`topology._curvature_operator`): exact for a
  surface of constant curvature on any triangulation, anisotropic in the warp / weft frame, and
  independent of the resolution. Plus an interior-penalty term on the jump of the curvature
  tensor across each hinge (zero for constant curvature, vanishing as h^2 for smooth shapes):
  without it, per-face tensors that jump from face to face form a soft mode at about half the
  energy of the smooth bending shape (a clamped cantilever sagged twice Euler-Bernoulli's).
gravity_energy: -sum_i m_i g . x_i.
"""

from __future__ import annotations

import jax.numpy as jnp

from diffcloth._math import safe_normalize
from diffcloth.physics.mesh.fabric import Fabric
from diffcloth.physics.mesh.topology import ClothMesh

__all__ = [
    "bending_energy",
    "bending_matrix",
    "curvatures",
    "face_dihedrals",
    "membrane_matrix",
    "dihedral_angles",
    "elastic_energy",
    "green_strain",
    "gravity_energy",
    "membrane_energy",
    "vertex_mass",
]


def green_strain(cloth: ClothMesh, x):
    """(m, 3) Green strain (E_uu, E_vv, E_uv) of each face in the warp / weft frame; x: (n, 3) m."""
    p = x[cloth.faces]  # (m, 3, 3)
    ds = jnp.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]], axis=-1)  # (m, 3, 2)
    f = jnp.einsum("mij,mjk->mik", ds, cloth.dm_inv)  # (m, 3, 2) deformation gradient
    c = jnp.einsum("mij,mik->mjk", f, f)  # (m, 2, 2) right Cauchy-Green
    return 0.5 * jnp.stack([c[:, 0, 0] - 1.0, c[:, 1, 1] - 1.0, c[:, 0, 1]], axis=-1)


def membrane_energy(cloth: ClothMesh, fabric: Fabric, x):
    """Orthotropic StVK membrane energy in J. x: (n, 3) m."""
    e = green_strain(cloth, x)
    c12 = fabric.poisson * jnp.sqrt(fabric.stretch_warp * fabric.stretch_weft)
    psi = 0.5 * (
        fabric.stretch_warp * e[:, 0] ** 2
        + 2.0 * c12 * e[:, 0] * e[:, 1]
        + fabric.stretch_weft * e[:, 1] ** 2
        + 4.0 * fabric.shear * e[:, 2] ** 2
    )
    return jnp.sum(cloth.face_area * psi)


def hinge_angle(q):
    """Signed dihedral angle in rad (0 when flat) of the hinge q (..., 4, 3) = [a, b, c, d]: the
    faces (a, b, c) and (b, a, d) (unchanged by swapping them: [b, a, d, c])."""
    a, b, c, d = q[..., 0, :], q[..., 1, :], q[..., 2, :], q[..., 3, :]
    na = jnp.cross(b - a, c - a)
    nb = jnp.cross(a - b, d - b)
    e = safe_normalize(b - a)
    return jnp.arctan2(jnp.sum(e * jnp.cross(na, nb), axis=-1), jnp.sum(na * nb, axis=-1))


def dihedral_angles(cloth: ClothMesh, x):
    """(h,) signed dihedral angle of each hinge in rad (0 when flat), from the faces (a, b, c) and
    (b, a, d) of hinge [a, b, c, d]."""
    return hinge_angle(x[cloth.hinges])


def face_dihedrals(cloth: ClothMesh, x):
    """(m, 3) dihedral angle across each face's edge k minus its rest angle, rad (0 on the
    boundary)."""
    # each interior angle once per hinge, then gathered by both of its faces (the stencil form,
    # `_stencil_theta`, computes it twice; the two agree: swapping the hinge's faces leaves
    # the signed angle unchanged)
    theta = dihedral_angles(cloth, x) - cloth.rest_angle
    fh = cloth.face_hinge
    return jnp.where(fh >= 0, theta[jnp.maximum(fh, 0)], 0.0)


def _stencil_theta(p, interior, rest):
    """p: (..., 6, 3) stencil positions -> (..., 3) hinge angles minus rest (0 on boundary): the
    face-stencil form, kept as the reference `face_dihedrals` and the Hessian's angle Jacobian
    are tested against (tests/test_physics_mesh.py)."""
    out = []
    for k in range(3):
        a, b, c, d = p[..., (k + 1) % 3, :], p[..., (k + 2) % 3, :], p[..., k, :], p[..., 3 + k, :]
        na = jnp.cross(b - a, c - a)
        nb = jnp.cross(a - b, d - b)
        e = safe_normalize(b - a)
        sin = jnp.sum(e * jnp.cross(na, nb), axis=-1)
        cos = jnp.sum(na * nb, axis=-1)
        ok = interior[..., k]
        theta = jnp.arctan2(jnp.where(ok, sin, 0.0), jnp.where(ok, cos, 1.0))
        out.append(jnp.where(ok, theta - rest[..., k], 0.0))
    return jnp.stack(out, axis=-1)


def curvatures(cloth: ClothMesh, x):
    """(m, 3) curvature tensor (k_uu, k_vv, k_uv) of each face in 1/m, warp / weft frame."""
    return jnp.einsum("mij,mj->mi", cloth.curvature_op, face_dihedrals(cloth, x))


def bending_matrix(fabric: Fabric):
    """(3, 3) D with psi_b = k^T D k / 2 for k = (k_uu, k_vv, k_uv), N m."""
    b66 = fabric.bend_bias - 0.25 * (fabric.bend_warp + fabric.bend_weft)
    z = jnp.zeros_like(b66)
    return jnp.stack([
        jnp.stack([fabric.bend_warp, z, z]),
        jnp.stack([z, fabric.bend_weft, z]),
        jnp.stack([z, z, 4.0 * b66]),
    ])  # fmt: skip


#: weight of the curvature-jump penalty (dimensionless), set by two resolution checks
#: (tests/test_physics_mesh_slow.py): the ASTM D1388 cantilever (24 near-equilateral edges along
#: the overhang) gives the rigidity within -1.7 % (0: far too soft; 1: +1.5 %), and a Cusick
#: drape's DC at 12 and 6 mm edges differs by 0.017 (0: 0.045, coarse softer; 1: 0.031, coarse
#: stiffer). The term vanishes for constant curvature at any weight.
JUMP_PENALTY = 0.6


def bending_energy(cloth: ClothMesh, fabric: Fabric, x):
    """Directional bending energy in J: sum_f A_f / 2 k_f^T D k_f (`bending_matrix`: B_warp
    k_uu^2 + B_weft k_vv^2 + 4 B_66 k_uv^2, B_66 = bend_bias - (bend_warp + bend_weft) / 4) plus
    JUMP_PENALTY / 2 sum_hinges (A_f + A_g) / 2 (k_f - k_g)^T D (k_f - k_g).
    Shapes: x (n, 3) m -> () J.
    """
    k = curvatures(cloth, x)
    d = bending_matrix(fabric)
    e = 0.5 * jnp.sum(cloth.face_area * jnp.einsum("mi,ij,mj->m", k, d, k))
    hf = cloth.hinge_faces
    jump = k[hf[:, 0]] - k[hf[:, 1]]
    w = 0.5 * (cloth.face_area[hf[:, 0]] + cloth.face_area[hf[:, 1]])
    return e + 0.5 * JUMP_PENALTY * jnp.sum(w * jnp.einsum("hi,ij,hj->h", jump, d, jump))


def membrane_matrix(fabric: Fabric):
    """(3, 3) C with psi_m = e^T C e / 2 for e = (E_uu, E_vv, E_uv), N/m."""
    c12 = fabric.poisson * jnp.sqrt(fabric.stretch_warp * fabric.stretch_weft)
    z = jnp.zeros_like(c12)
    return jnp.stack([
        jnp.stack([fabric.stretch_warp, c12, z]),
        jnp.stack([c12, fabric.stretch_weft, z]),
        jnp.stack([z, z, 4.0 * fabric.shear]),
    ])  # fmt: skip


def vertex_mass(cloth: ClothMesh, fabric: Fabric):
    """(n,) lumped vertex masses in kg."""
    return fabric.density * cloth.vertex_area


def gravity_energy(cloth: ClothMesh, fabric: Fabric, x, gravity):
    """-sum_i m_i g . x_i in J; gravity (3,) m/s^2."""
    return -jnp.sum(vertex_mass(cloth, fabric) * (x @ gravity))


def elastic_energy(cloth: ClothMesh, fabric: Fabric, x):
    """Membrane plus bending energy in J.
    Shapes: x (n, 3) m -> () J.
    """
    return membrane_energy(cloth, fabric, x) + bending_energy(cloth, fabric, x)
