"""Colliders of the mesh cloth: planes, spheres, boxes, capped vertical cylinders (the drape
tester's pedestal) and static triangle meshes (a table, a mannequin), as signed distances.

Contact is a penalty on the signed distance phi (m, positive outside) of every free vertex:

    E_c = sum_i A_i k_c / 2 * max(0, thickness - phi_i)^2          [J]

with the vertex's area A_i (m^2) and a contact stiffness k_c (N/m^3, pressure per metre of
penetration into the contact layer). The default k_c = 1e7 lets the weight of a 0.3 kg/m^2 fabric
sink about 0.3 um into its contact layer, so with a thickness of a millimetre no vertex reaches
a collider's surface. The energy is C1 and its Hessian piecewise constant: Newton solves see it
as a stiff spring that switches on at contact.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from diffcloth._math import safe_norm, safe_normalize

__all__ = [
    "MeshColliders",
    "contact_energy",
    "friction_energy",
    "make_mesh_colliders",
    "signed_distance",
]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class MeshColliders:
    """Static colliders (a batch of each kind; empty batches have a leading 0).

    Attributes:
      plane_normal: (p, 3) unit; plane_offset: (p,) m; outside where n . x > offset.
      sphere_center: (s, 3) m; sphere_radius: (s,) m.
      box_center: (b, 3) m; box_half: (b, 3) m half extents; box_rotation: (b, 3, 3) world from
        box axes.
      cylinder_top: (c, 3) m, centre of the top cap; cylinder_radius: (c,) m; cylinder_height:
        (c,) m (the cylinder runs from the top cap down along -y).
      triangles: (t, 3, 3) m, a static triangle soup (outside is the side its counter-clockwise
        normals point to).
      thickness: () m, contact layer (cloth half-thickness plus margin).
      stiffness: () N/m^3, contact stiffness k_c.
      friction: () Coulomb coefficient scale (multiplies the fabric's friction; 1 by default).
    """

    plane_normal: jax.Array
    plane_offset: jax.Array
    sphere_center: jax.Array
    sphere_radius: jax.Array
    box_center: jax.Array
    box_half: jax.Array
    box_rotation: jax.Array
    cylinder_top: jax.Array
    cylinder_radius: jax.Array
    cylinder_height: jax.Array
    triangles: jax.Array
    thickness: jax.Array
    stiffness: jax.Array
    friction: jax.Array


def _rows(values, width, name):
    a = np.asarray(values if values is not None else np.zeros((0, width)), np.float64)
    if a.size == 0:
        return np.zeros((0, width) if width else (0,))
    a = a.reshape(-1, width) if width else a.reshape(-1)
    if not np.all(np.isfinite(a)):
        raise ValueError(f"colliders.{name}: values must be finite, got {values!r}")
    return a


def make_mesh_colliders(
    *,
    planes=(),
    spheres=(),
    boxes=(),
    cylinders=(),
    triangles=None,
    thickness: float = 1e-3,
    stiffness: float = 1e7,
    friction: float = 1.0,
    dtype=None,
) -> MeshColliders:
    """Collect colliders.

    Args:
      planes: sequence of (normal (3,), offset) pairs.
      spheres: sequence of (center (3,), radius).
      boxes: sequence of (center (3,), half_extents (3,)) or (center, half_extents, rotation
        (3, 3)).
      cylinders: sequence of (top_center (3,), radius, height): vertical capped cylinders.
      triangles: (t, 3, 3) triangle soup in m, or a (vertices, faces) pair.
      thickness: contact layer, m (> 0). stiffness: N/m^3 (> 0). friction: scale (>= 0).
    Returns:
      MeshColliders. Raises ValueError naming the collider for non-positive sizes.
    """
    for name, value, positive in (("thickness", thickness, True), ("stiffness", stiffness, True),
                                  ("friction", friction, False)):  # fmt: skip
        if not np.isfinite(value) or (value <= 0 if positive else value < 0):
            raise ValueError(
                f"colliders.{name} = {value!r} must be {'> 0' if positive else '>= 0'}"
            )
    pn = np.array([np.asarray(n, float) for n, _ in planes]).reshape(-1, 3)
    po = np.array([float(o) for _, o in planes]).reshape(-1)
    if len(pn) and np.any(np.linalg.norm(pn, axis=1) == 0):
        raise ValueError("colliders.planes: a normal is zero")
    pn = pn / np.maximum(np.linalg.norm(pn, axis=1, keepdims=True), 1e-300)
    sc = np.array([np.asarray(c, float) for c, _ in spheres]).reshape(-1, 3)
    sr = np.array([float(r) for _, r in spheres]).reshape(-1)
    for i, r in enumerate(sr):
        if not r > 0:
            raise ValueError(f"colliders.spheres #{i}: radius = {r!r} must be > 0 m")
    bc, bh, br = [], [], []
    for i, b in enumerate(boxes):
        c, h = np.asarray(b[0], float), np.asarray(b[1], float)
        if h.shape != (3,) or np.any(h <= 0):
            raise ValueError(
                f"colliders.boxes #{i}: half extents {h.tolist()} must be three values > 0 m"
            )
        rot = np.asarray(b[2], float) if len(b) > 2 else np.eye(3)
        bc.append(c), bh.append(h), br.append(rot)
    cc, cr, ch = [], [], []
    for i, (top, r, h) in enumerate(cylinders):
        if not (r > 0 and h > 0):
            raise ValueError(
                f"colliders.cylinders #{i}: radius {r!r} and height {h!r} must be > 0 m"
            )
        cc.append(np.asarray(top, float)), cr.append(float(r)), ch.append(float(h))
    if triangles is None:
        tri = np.zeros((0, 3, 3))
    elif isinstance(triangles, tuple) and len(triangles) == 2:
        v, f = np.asarray(triangles[0], float), np.asarray(triangles[1], np.int64)
        tri = v[f]
    else:
        tri = np.asarray(triangles, float).reshape(-1, 3, 3)
    dtype = dtype or jnp.zeros(()).dtype
    arr = lambda a, shape: jnp.asarray(np.asarray(a, float).reshape(shape), dtype)
    return MeshColliders(
        plane_normal=arr(pn, (-1, 3)),
        plane_offset=arr(po, (-1,)),
        sphere_center=arr(sc, (-1, 3)),
        sphere_radius=arr(sr, (-1,)),
        box_center=arr(bc or np.zeros((0, 3)), (-1, 3)),
        box_half=arr(bh or np.zeros((0, 3)), (-1, 3)),
        box_rotation=arr(br or np.zeros((0, 3, 3)), (-1, 3, 3)),
        cylinder_top=arr(cc or np.zeros((0, 3)), (-1, 3)),
        cylinder_radius=arr(cr, (-1,)),
        cylinder_height=arr(ch, (-1,)),
        triangles=arr(tri, (-1, 3, 3)),
        thickness=jnp.asarray(thickness, dtype),
        stiffness=jnp.asarray(stiffness, dtype),
        friction=jnp.asarray(friction, dtype),
    )


def _box_sdf(x, center, half, rot):
    q = jnp.abs((x - center[None, :]) @ rot) - half[None, :]
    outside = safe_norm(jnp.maximum(q, 0.0))
    return outside + jnp.minimum(jnp.max(q, axis=-1), 0.0)


def _cylinder_sdf(x, top, radius, height):
    rel = x - top[None, :]
    rho = safe_norm(rel[..., jnp.array([0, 2])]) - radius
    dy = jnp.abs(rel[..., 1] + 0.5 * height) - 0.5 * height
    d = jnp.stack([rho, dy], axis=-1)
    return jnp.minimum(jnp.max(d, axis=-1), 0.0) + safe_norm(jnp.maximum(d, 0.0))


def _closest_on_triangle(p, a, b, c):
    """Closest point to p (3,) on triangle abc (Ericson, Real-Time Collision Detection 5.1.5),
    written with `where` so that it vectorises."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = ab @ ap, ac @ ap
    bp = p - b
    d3, d4 = ab @ bp, ac @ bp
    cp = p - c
    d5, d6 = ab @ cp, ac @ cp
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    sd = lambda n, d: n / jnp.where(jnp.abs(d) > 1e-30, d, 1e-30)
    # interior (default)
    denom = va + vb + vc
    v_in, w_in = sd(vb, denom), sd(vc, denom)
    res = a + ab * v_in + ac * w_in
    # edges and vertices, in reverse priority so that the first true region wins
    w_bc = sd(d4 - d3, (d4 - d3) + (d5 - d6))
    res = jnp.where((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), b + w_bc * (c - b), res)
    w_ac = sd(d2, d2 - d6)
    res = jnp.where((vb <= 0) & (d2 >= 0) & (d6 <= 0), a + w_ac * ac, res)
    v_ab = sd(d1, d1 - d3)
    res = jnp.where((vc <= 0) & (d1 >= 0) & (d3 <= 0), a + v_ab * ab, res)
    res = jnp.where((d6 >= 0) & (d5 <= d6), c, res)
    res = jnp.where((d3 >= 0) & (d4 <= d3), b, res)
    res = jnp.where((d1 <= 0) & (d2 <= 0), a, res)
    return res


def _mesh_sdf(x, triangles):
    """(n,) signed distance to a triangle soup: the distance to the nearest triangle, negative
    behind its face (by the face normal; exact away from edges of concave regions)."""
    a, b, c = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    normal = safe_normalize(jnp.cross(b - a, c - a))

    def one(p):
        q = jax.vmap(_closest_on_triangle, in_axes=(None, 0, 0, 0))(p, a, b, c)
        d = safe_norm(p[None, :] - q)
        k = jnp.argmin(d)
        side = jnp.sign(jnp.dot(p - q[k], normal[k]))
        return jnp.where(side < 0, -d[k], d[k])

    return jax.vmap(one)(x)


def signed_distance(colliders: MeshColliders, x):
    """(n,) signed distance in m from each point of x (n, 3) to the nearest collider (inf without
    colliders). Positive outside."""
    phi = jnp.full(x.shape[:1], jnp.inf, x.dtype)
    c = colliders
    if c.plane_offset.shape[0]:
        phi = jnp.minimum(phi, jnp.min(x @ c.plane_normal.T - c.plane_offset[None, :], axis=1))
    if c.sphere_radius.shape[0]:
        d = safe_norm(x[:, None, :] - c.sphere_center[None]) - c.sphere_radius[None]
        phi = jnp.minimum(phi, jnp.min(d, axis=1))
    if c.box_center.shape[0]:
        d = jax.vmap(lambda ce, h, r: _box_sdf(x, ce, h, r))(
            c.box_center, c.box_half, c.box_rotation
        )
        phi = jnp.minimum(phi, jnp.min(d, axis=0))
    if c.cylinder_radius.shape[0]:
        d = jax.vmap(lambda t, r, h: _cylinder_sdf(x, t, r, h))(
            c.cylinder_top, c.cylinder_radius, c.cylinder_height
        )
        phi = jnp.minimum(phi, jnp.min(d, axis=0))
    if c.triangles.shape[0]:
        phi = jnp.minimum(phi, _mesh_sdf(x, c.triangles))
    return phi


def has_colliders(colliders) -> bool:
    """True if any collider is present (static: from shapes).
    Shapes: none (decided from the arrays' static shapes).
    """
    if colliders is None:
        return False
    c = colliders
    return any(
        a.shape[0]
        for a in (c.plane_offset, c.sphere_radius, c.box_center, c.cylinder_radius, c.triangles)
    )


def penetration(colliders: MeshColliders, x):
    """(n,) depth into the contact layer, m: max(0, thickness - phi)."""
    return jnp.maximum(colliders.thickness - signed_distance(colliders, x), 0.0)


def contact_energy(colliders: MeshColliders, x, area, free):
    """Penalty energy in J of the free vertices (see the module docstring). area: (n,) m^2;
    free: (n,) bool."""
    pen = penetration(colliders, x)
    return 0.5 * colliders.stiffness * jnp.sum(jnp.where(free, area * pen * pen, 0.0))


def contact_normals(colliders: MeshColliders, x):
    """(n, 3) unit outward normals of the nearest collider surface (gradient of phi)."""
    g = jax.grad(lambda y: jnp.sum(jnp.where(jnp.isfinite(signed_distance(colliders, y)),
                                             signed_distance(colliders, y), 0.0)))(x)  # fmt: skip
    return safe_normalize(g)


def friction_energy(colliders, x, x_prev, area, free, friction, eps):
    """Lagged Coulomb friction as a smooth dissipation potential (IPC style): mu lambda_i
    (sqrt(|u_T|^2 + eps^2) - eps), with the normal force lambda_i and the contact normal taken
    at the start of the step and u_T the tangential displacement (the mesh implicit step's).
    Shapes: x, x_prev (n, 3), area (n,), free (n,) -> ()."""
    pen = jax.lax.stop_gradient(penetration(colliders, x_prev))
    lam = colliders.stiffness * area * pen
    n = jax.lax.stop_gradient(contact_normals(colliders, x_prev))
    u = x - x_prev
    ut = u - jnp.sum(u * n, axis=-1, keepdims=True) * n
    slide = jnp.sqrt(jnp.sum(ut * ut, axis=-1) + eps * eps) - eps
    return jnp.sum(jnp.where(free & (pen > 0), friction * colliders.friction * lam * slide, 0.0))
