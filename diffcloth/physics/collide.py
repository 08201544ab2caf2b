"""Colliders acting on control-net points: spheres and planes, with Coulomb friction.

After every substep each free point that lies inside a collider is projected onto its surface, the
approaching normal component of its velocity (relative to the collider) is removed, and the tangential
part is reduced by friction * (removed normal speed), Coulomb style. So no control point ends a step
inside a collider. A point exactly at a sphere's centre is pushed out along +y. A non-finite point
(a blown-up simulation) is never "inside": it is left non-finite, so the blow-up stays visible
instead of being painted onto the collider by the fallback direction.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from diffcloth._math import safe_div
from diffcloth.physics.forces import _direction_planar, _dot
from diffcloth.physics.sphere_contact import sphere_impact
from diffcloth.shapes import Plane, Sphere


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Colliders:
    """Batched colliders for one frame, or for every frame with a leading frame axis.

    Attributes:
      spheres: Sphere with center (n, 3) and radius (n,), m ((T, n, 3), (T, n) per frame).
      sphere_velocity: (n, 3) m/s, the spheres' velocity during the step ((T, n, 3) per frame).
      planes: Plane with normal (m, 3) (unit) and offset (m,) ((T, m, 3), (T, m) per frame).

    Within a step, a sphere moves from `center` at velocity `sphere_velocity`: at the end of substep
    s (0-based) its centre is center + sphere_velocity * (s + 1) * h. Planes are fixed during a step.
    """

    spheres: Sphere
    sphere_velocity: jax.Array
    planes: Plane

    @property
    def num_spheres(self) -> int:
        return self.spheres.radius.shape[-1]

    @property
    def num_planes(self) -> int:
        return self.planes.offset.shape[-1]


def make_colliders(spheres=(), planes=(), *, sphere_velocity=None, dtype=None) -> Colliders:
    """Collect Sphere/Plane objects (single or batched) into one Colliders record (no frame axis).

    Shapes: spheres' centres (k, 3) m, radii (k,) m, planes' normals (p, 3), offsets (p,) m -> Colliders
      with those leaves.
    """
    dtype = dtype or jnp.zeros(()).dtype
    if isinstance(spheres, Sphere):
        spheres = [spheres]
    if isinstance(planes, Plane):
        planes = [planes]
    sb = [s.batched() for s in spheres]
    pb = [p.batched() for p in planes]
    for s in sb:  # eager check only: under jit the radius is a tracer (validated at build time)
        if not isinstance(s.radius, jax.core.Tracer) and not np.all(np.asarray(s.radius) >= 0):
            raise ValueError(f"sphere radius must be >= 0 (allowed range [0, inf)), got {s.radius}")
    centers = jnp.concatenate([s.center for s in sb], 0) if sb else jnp.zeros((0, 3), dtype)
    radii = jnp.concatenate([s.radius for s in sb], 0) if sb else jnp.zeros((0,), dtype)
    normals = jnp.concatenate([p.normal for p in pb], 0) if pb else jnp.zeros((0, 3), dtype)
    offsets = jnp.concatenate([p.offset for p in pb], 0) if pb else jnp.zeros((0,), dtype)
    if sphere_velocity is None:
        sphere_velocity = jnp.zeros_like(centers)
    sphere_velocity = jnp.asarray(sphere_velocity, centers.dtype).reshape(centers.shape)
    return Colliders(Sphere(centers, radii), sphere_velocity, Plane(normals, offsets))


def as_colliders(obj, dtype=None) -> Colliders | None:
    """None, a Colliders, a Sphere, a Plane, or a list/tuple of them -> Colliders (or None).

    Shapes: as `make_colliders`: (k, 3) / (k,) sphere and (p, 3) / (p,) plane leaves.
    """
    if obj is None or isinstance(obj, Colliders):
        return obj
    if isinstance(obj, Sphere | Plane):
        obj = [obj]
    spheres = [o for o in obj if isinstance(o, Sphere)]
    planes = [o for o in obj if isinstance(o, Plane)]
    if len(spheres) + len(planes) != len(obj):
        raise TypeError(f"colliders: expected Sphere/Plane objects, got {[type(o) for o in obj]}")
    return make_colliders(spheres, planes, dtype=dtype)


def collide(
    x,
    v,
    mass,
    free,
    colliders: Colliders,
    friction,
    margin,
    sphere_shift=0.0,
    x_prev=None,
    h=None,
    x_start=None,
    v_start=None,
):
    """Project points out of every collider and apply friction to their velocities.

    Works on planar arrays (3, rows, cols) (see `forces.to_planar`); `collide_points` is the
    (rows, cols, 3) form.

    Args:
      x, v: (3, rows, cols) positions (m) and velocities (m/s) after an unconstrained substep.
      mass: (rows, cols) kg, only used for the contact impulses.
      free: (rows, cols) bool, False for pinned points (left untouched).
      colliders: one frame's Colliders (no frame axis).
      friction: () Coulomb coefficient. margin: () m added to every collider.
      sphere_shift: () s, time since the start of the step (sphere centres move by velocity * shift).
      x_prev, h: optional positions before the substep and the substep length (s). When given, a
        projected point's velocity is first reset to its actual displacement over the substep,
        (x_projected - x_prev) / h (position-based style), so large substeps inject less energy.
      x_start, v_start: the "impact" rule (needs h): positions before the substep and the velocity
        before its force kick (v - v_start = h * acceleration). A contacting point is resolved at
        its estimated time of impact, the fraction 1 - beta of the substep (beta from the signed
        distances before and after, 1 for a point already in contact): the approaching normal
        velocity is removed there, the outward part of the kick that falls after the impact,
        max(beta * (v - v_start).n, 0), is kept (lift-off), and the tangential velocity shrinks
        by friction x the removed normal speed; the point also moves by beta * h x these velocity
        changes. So a point that reaches the collider at the end of one substep and one that
        reaches it at the start of the next end in the same state: the trajectory is continuous
        in the parameters (with "coulomb" it jumps by about h x friction x |v.n| when the moment
        of contact crosses a substep boundary).
    Returns:
      (x, v, sphere_impulse (n, 3), plane_impulse (m, 3)): impulses in N s that the colliders gave
      to the cloth in this substep (apply the opposite to a rigid body for two-way coupling).
    """
    sphere_imp = []
    for k in range(colliders.num_spheres):
        if x_start is not None and _hand_contact():
            vel = colliders.sphere_velocity[k]
            c = colliders.spheres.center[k] + vel * sphere_shift
            r = colliders.spheres.radius[k] + margin
            v_start = v if v_start is None else v_start
            args = tuple(jnp.asarray(a, x.dtype) for a in (c, vel, r))
            args += (free, jnp.asarray(friction, x.dtype), jnp.asarray(h, x.dtype))
            x, v_new = sphere_impact(x, v, x_start, v_start, *args)
            sphere_imp.append(jnp.sum(mass[None] * (v_new - v), axis=(1, 2)))
            v = v_new
            continue
        vel = colliders.sphere_velocity[k][:, None, None]
        c = colliders.spheres.center[k][:, None, None] + vel * sphere_shift
        r = colliders.spheres.radius[k] + margin
        dist, nrm = _direction_planar(x - c)
        inside = (dist < r) & free & _finite_points(x)
        x = jnp.where(inside[None], c + r * nrm, x)
        if x_start is not None:
            d0 = _direction_planar(x_start - (c - vel * h))[0] - r
            x, v_new = _contact(x, v, v_start, vel, nrm, inside, d0, dist - r, friction, h)
        else:
            v_in = v if x_prev is None else jnp.where(inside[None], (x - x_prev) / h, v)
            v_new = _contact_velocity(v_in, vel, nrm, inside, friction)
        sphere_imp.append(jnp.sum(mass[None] * (v_new - v), axis=(1, 2)))
        v = v_new
    plane_imp = []
    for k in range(colliders.num_planes):
        nrm = colliders.planes.normal[k][:, None, None]
        s = _dot(x, nrm) - colliders.planes.offset[k] - margin
        inside = (s < 0) & free & _finite_points(x)
        x = jnp.where(inside[None], x - s[None] * nrm, x)
        if x_start is not None:
            d0 = _dot(x_start, nrm) - colliders.planes.offset[k] - margin
            x, v_new = _contact(x, v, v_start, jnp.zeros_like(nrm), nrm, inside, d0, s, friction, h)
        else:
            v_in = v if x_prev is None else jnp.where(inside[None], (x - x_prev) / h, v)
            v_new = _contact_velocity(v_in, jnp.zeros_like(nrm), nrm, inside, friction)
        plane_imp.append(jnp.sum(mass[None] * (v_new - v), axis=(1, 2)))
        v = v_new
    zeros = jnp.zeros((0, 3), x.dtype)
    si = jnp.stack(sphere_imp) if sphere_imp else zeros
    pi = jnp.stack(plane_imp) if plane_imp else zeros
    return x, v, si, pi


#: [True] while tracing forward sensitivities (`sensitivity.forward_tracing`): the contact is
#: differentiated by plain autodiff, whose JVP costs a few elementwise passes per tangent instead
#: of the per-node (6, 19) Jacobian that makes reverse mode fast.
_PLAIN_CONTACT = [False]


def _hand_contact() -> bool:
    """True when the sphere contact takes `sphere_contact.sphere_impact` (hand-written VJP,
    reverse mode only): outside forward-sensitivity tracing and `autodiff_forces`."""
    from diffcloth.physics.stencil_vjp import _HAND_VJP

    return _HAND_VJP[0] and not _PLAIN_CONTACT[0]


def _contact(x, v, v_start, vel, nrm, inside, d0, d1, friction, h):
    """`_impact_contact` with the per-node Jacobian derivative (`contact_jac`), same values."""
    from diffcloth.physics.contact_jac import impact_contact

    dt = x.dtype
    v_start = v if v_start is None else v_start  # no kick
    if _PLAIN_CONTACT[0]:
        return _impact_contact(x, v, v_start, vel, nrm, inside, d0, d1, friction, h)
    as_ = lambda a: jnp.asarray(a, dt)
    return impact_contact(
        x, v, v_start, as_(vel), nrm, inside.astype(dt), as_(d0), as_(d1), as_(friction), as_(h)
    )


def _finite_points(x):
    """(rows, cols) bool: the planar point (3, rows, cols) is finite in every coordinate."""
    return jnp.all(jnp.isfinite(x), axis=0)


def collide_points(x, v, colliders, friction, margin=0.0, *, mass=None, free=None):
    """`collide` on (rows, cols, 3) arrays: returns (x, v) with every free point outside."""
    colliders = as_colliders(colliders, dtype=x.dtype)
    shape = x.shape[:-1]
    mass = jnp.ones(shape, x.dtype) if mass is None else mass
    free = jnp.ones(shape, bool) if free is None else free
    xp, vp, _, _ = collide(
        jnp.moveaxis(x, -1, 0), jnp.moveaxis(v, -1, 0), mass, free, colliders, friction, margin
    )
    return jnp.moveaxis(xp, 0, -1), jnp.moveaxis(vp, 0, -1)


def _contact_velocity(v, vel, nrm, inside, friction):
    u = v - vel
    un = _dot(u, nrm)
    approach = inside & (un < 0)
    dvn = jnp.where(approach, -un, 0.0)
    ut = u - un[None] * nrm
    ut_len, _ = _direction_planar(ut)
    scale = jnp.maximum(1.0 - safe_div(friction * dvn, ut_len), 0.0)
    u_new = jnp.where(approach[None], ut * scale[None], u)
    return vel + u_new


def _impact_contact(x, v, v_start, vel, nrm, inside, d0, d1, friction, h):
    """The "impact" rule on projected points x: returns (x, v), planar (3, rows, cols).

    d0, d1: signed distances to the collider before and after the substep (d1 < 0 inside);
    beta = d1 / (d1 - d0) is the fraction of the substep after the impact (1 when d0 <= 0).
    v_start: velocity before the substep's kick (None: no kick). The kick k = v - v_start is
    spread over the substep: the contact (normal speed removed, tangential speed shrunk by
    friction x the removed speed) acts on the velocity at the impact, v - beta k; the kick after
    it, beta k, is then added under the same contact (absorbed when it presses inwards, kept when
    it lifts off). Continuous in d0, d1 and the velocities, and equal to "coulomb" for beta = 0."""
    started_in = d0 <= 0
    gap = d0 - d1
    ok = ~started_in & (gap > 0)  # outside points too: keep the division finite for gradients
    beta = jnp.where(started_in, 1.0, jnp.clip(-d1 / jnp.where(ok, gap, 1.0), 0.0, 1.0))
    kick = jnp.zeros_like(v) if v_start is None else beta[None] * (v - v_start)
    u = v - vel
    approach = inside & (_dot(u, nrm) < 0)

    def contact(w):  # one Coulomb contact on relative velocity w: returns (tangential, normal)
        wn = _dot(w, nrm)
        wt = w - wn[None] * nrm
        wt_len, _ = _direction_planar(wt)
        scale = jnp.maximum(1.0 - safe_div(friction * jnp.maximum(-wn, 0.0), wt_len), 0.0)
        return wt * scale[None], jnp.maximum(wn, 0.0)

    ut1, un1 = contact(u - kick)  # at the impact
    ut2, un2 = contact(ut1 + un1[None] * nrm + kick)  # the rest of the kick
    u_new = ut2 + un2[None] * nrm
    ut = u - _dot(u, nrm)[None] * nrm
    dx = (beta * h)[None] * (ut2 - ut + un2[None] * nrm)  # drift after the impact, changed
    return jnp.where(approach[None], x + dx, x), jnp.where(approach[None], vel + u_new, v)
