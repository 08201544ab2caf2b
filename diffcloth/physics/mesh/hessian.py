"""A sparse, positive semi-definite approximation of the mesh cloth's Hessian, assembled per
Newton iteration in block-row ("ELL") form: block (i, k) couples vertex i with vertex
`cloth.neighbors[i, k]`, so a product with it is one gather and one einsum (no scatter).

- Membrane: Gauss-Newton J^T C J of the Green strain plus the geometric stiffness of the
  stress's tensile part (the compressive part is dropped, which keeps each face's block PSD:
  a compressed membrane buckles, it does not push back).
- Bending: Gauss-Newton A J^T P^T D P J of the face curvatures (J: the stencil's hinge angles),
  and of the curvature jump across each hinge (its two faces' stencils: 12 x 12 blocks).
- Contact: k_c A_i grad(phi) grad(phi)^T on vertices in the contact layer.
The Newton solves use it as the system matrix (with the exact gradient), and the implicit
gradient's exact Hessian-vector solve uses its diagonal blocks as a preconditioner.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from diffcloth.physics.mesh import energy
from diffcloth.physics.mesh.topology import ClothMesh

__all__ = ["assemble", "block_diagonal", "matvec"]

_B0 = np.array([[-1.0, -1.0], [1.0, 0.0], [0.0, 1.0]])  # numpy: no backend start at import


def _tensile_part(s):
    """The positive part (eigenvalues clipped at 0) of symmetric 2 x 2 matrices s (m, 2, 2), in
    closed form: s where both eigenvalues are >= 0, 0 where both are <= 0, else
    l1 (s - l2 I) / (l1 - l2) (the projector on the positive eigenvector, times l1)."""
    a, b, c = s[:, 0, 0], s[:, 0, 1], s[:, 1, 1]
    mid = 0.5 * (a + c)
    rad = jnp.sqrt(0.25 * (a - c) ** 2 + b * b)
    l1, l2 = mid + rad, mid - rad
    gap = jnp.where(rad > 0, 2.0 * rad, 1.0)
    part = (l1 / gap)[:, None, None] * (s - l2[:, None, None] * jnp.eye(2, dtype=s.dtype)[None])
    part = jnp.where((l1 > 0)[:, None, None], part, 0.0)
    return jnp.where((l2 >= 0)[:, None, None], s, part)


def _membrane_blocks(cloth: ClothMesh, fabric, x):
    """(m, 3, 3, 3, 3) per-face blocks [a, b] (3 x 3 each)."""
    p = x[cloth.faces]  # (m, 3, 3)
    cmat = energy.membrane_matrix(fabric)
    b = jnp.einsum("ij,mjk->mik", _B0.astype(x.dtype), cloth.dm_inv)  # (m, 3, 2): F = X^T B

    def strain(pf, bf):
        f = jnp.einsum("ai,ak->ik", pf, bf)  # (3, 2)
        c = f.T @ f
        return 0.5 * jnp.stack([c[0, 0] - 1.0, c[1, 1] - 1.0, c[0, 1]])

    e = jax.vmap(strain)(p, b)  # (m, 3)
    je = jax.vmap(jax.jacfwd(strain))(p, b)  # (m, 3, 3 vertices, 3)
    gn = jnp.einsum("mpai,pq,mqbj->mabij", je, cmat, je)
    # second Piola-Kirchhoff stress (2 x 2) and its tensile (PSD) part
    sig = e @ cmat  # (m, 3): (S_uu, S_vv, S_uv * 2)... S_uv = C33 e_uv / 2
    s2 = jnp.stack([jnp.stack([sig[:, 0], 0.5 * sig[:, 2]], -1),
                    jnp.stack([0.5 * sig[:, 2], sig[:, 1]], -1)], -2)  # fmt: skip
    s_plus = _tensile_part(s2)
    g = jnp.einsum("mai,mij,mbj->mab", b, s_plus, b)  # (m, 3, 3)
    geo = g[:, :, :, None, None] * jnp.eye(3, dtype=x.dtype)[None, None, None, :, :]
    return cloth.face_area[:, None, None, None, None] * (gn + geo)


# hinge vertex (a, b, c, d) = 0..3 at each stencil slot of a face's edge k, -1 for none: [k, s, 0]
# where the face is the hinge's (a, b, c), [k, s, 1] where it is (b, a, d) (`_stencil_theta`)
_SLOT_VERTEX = np.full((3, 6, 2), -1)
for _k in range(3):
    for _j, (_s0, _s1) in enumerate([((_k + 1) % 3, (_k + 2) % 3), ((_k + 2) % 3, (_k + 1) % 3),
                                     (_k, 3 + _k), (3 + _k, _k)]):  # fmt: skip
        _SLOT_VERTEX[_k, _s0, 0], _SLOT_VERTEX[_k, _s1, 1] = _j, _j


def _stencil_angle_jacobian(cloth: ClothMesh, x):
    """(m, 3, 6, 3) derivative of each face's three hinge angles with respect to its stencil's
    six vertices (zero on the boundary): each hinge's gradient (h, 4, 3), computed once, placed
    in the stencils of its two faces."""
    jh = jax.vmap(jax.grad(energy.hinge_angle))(x[cloth.hinges])  # (h, 4, 3)
    fh = cloth.face_hinge
    hk = jnp.maximum(fh, 0)
    rolled = cloth.faces[:, np.array([1, 2, 0])]  # the vertex (k + 1) % 3 of each edge k
    second = (cloth.hinges[hk, 0] != rolled).astype(jnp.int32)  # (m, 3)
    j = jnp.asarray(_SLOT_VERTEX)[
        jnp.arange(3)[None, :, None], jnp.arange(6)[None, None, :], second[:, :, None]
    ]  # (m, 3, 6)
    jt = jh.reshape(-1, 3)[hk[:, :, None] * 4 + jnp.maximum(j, 0)]  # (m, 3, 6, 3)
    return jnp.where(((fh >= 0)[:, :, None] & (j >= 0))[..., None], jt, 0.0)


def _bending_blocks(cloth: ClothMesh, fabric, x):
    """Gauss-Newton blocks of the bending energy: (m, 6, 6, 3, 3) per face stencil and
    (h, 6, 6, 3, 3) per hinge.

    The jump term of hinge h over its faces (f0, f1) is w_h (J0 - J1)^T D (J0 - J1) over the
    two stencils (12 x 12 blocks); its diagonal quadrants w_h J_f^T D J_f have the face term's
    form, so they are added to the face blocks (weight A_f + the sum of its hinges' w_h), and
    only the cross quadrant -w_h J0^T D J1 (and its transpose) is a hinge block of its own:
    a quarter of the 12 x 12 blocks' work and half of their scatter."""
    jt = _stencil_angle_jacobian(cloth, x)  # (m, 3, 6, 3)
    jk = jnp.einsum("mkh,mhaj->mkaj", cloth.curvature_op, jt)  # (m, 3, 6, 3)
    d = energy.bending_matrix(fabric)
    hf = cloth.hinge_faces
    m = cloth.face_area.shape[0]
    w = 0.5 * energy.JUMP_PENALTY * (cloth.face_area[hf[:, 0]] + cloth.face_area[hf[:, 1]])
    weight = cloth.face_area + jax.ops.segment_sum(
        jnp.concatenate([w, w]), jnp.concatenate([hf[:, 0], hf[:, 1]]), num_segments=m
    )
    face = jnp.einsum("mkai,kl,mlbj->mabij", jk, d, jk)
    face = weight[:, None, None, None, None] * face
    cross = jnp.einsum("hkai,kl,hlbj->habij", jk[hf[:, 0]], d, jk[hf[:, 1]])
    return face, -w[:, None, None, None, None] * cross


def assemble(cloth: ClothMesh, fabric, x, *, elastic_scale=1.0, diag=None):
    """The (n, K, 3, 3) block-row PSD Hessian approximation of the elastic energy at x (n, 3),
    scaled by elastic_scale, plus optional per-vertex (n, 3, 3) diagonal blocks `diag`."""
    blocks, cross = _bending_blocks(cloth, fabric, x)
    blocks = blocks.at[:, :3, :3].add(_membrane_blocks(cloth, fabric, x))
    n, k = cloth.neighbors.shape
    cross_t = jnp.swapaxes(jnp.swapaxes(cross, 1, 2), 3, 4)  # block (b, a) = block (a, b)^T
    flat = jax.ops.segment_sum(
        jnp.concatenate([blocks.reshape(-1, 3, 3), cross.reshape(-1, 3, 3),
                         cross_t.reshape(-1, 3, 3)]),
        jnp.concatenate([cloth.stencil_slots.reshape(-1),
                         cloth.hinge_slots[:, :6, 6:].reshape(-1),
                         cloth.hinge_slots[:, 6:, :6].reshape(-1)]),
        num_segments=n * k,
    ).reshape(n, k, 3, 3)  # fmt: skip
    flat = flat * elastic_scale
    if diag is not None:
        flat = flat.at[:, 0].add(diag)  # the diagonal block is slot 0 of each row
    return flat


def matvec(cloth: ClothMesh, h, p):
    """H p for a block-row Hessian h (n, K, 3, 3) and p (n, 3)."""
    return jnp.einsum("nkab,nkb->na", h, p[cloth.neighbors])


def block_diagonal(h):
    """(n, 3, 3) diagonal blocks of a block-row Hessian."""
    return h[:, 0]
