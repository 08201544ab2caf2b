"""Rigid bodies: spheres and boxes with forces, thrusters, collisions and impulse response.

The model follows the "Virtual Environments" deck (slides 19-33, SEEDS.md section 9):

* A `RigidBody` carries position, orientation (unit quaternion, w x y z), linear and angular
  velocity (world frame), mass, restitution, friction, and drag coefficients. Its inertia tensor
  is derived from its shape and mass (`inertia_tensor`), so gradients w.r.t. mass reach the
  rotation too.
* Forces applied at points are split into a force through the centre (F = m a) and a torque
  (M = I alpha) by `force_and_torque`. Gravity, drag (`linear_drag` along the body's front axis,
  `orthogonal_drag` along its right and top axes; body axes x = right, y = top, z = front) and
  thrusters (body-fixed points and directions, switched by a control signal per frame) are
  integrated each substep with semi-implicit Euler. Rotation integrates the world angular momentum
  L (dL/dt = torque) and maps it back with w = R I^-1 R^T L, so torque-free bodies keep L exactly.
* Collision detection sphere-sphere, sphere-plane, box-plane, box-sphere and box-box
  (vertices against the other box's face planes, as in the seed) gives a `Contact`: depth,
  normal (pointing from the second body to the first) and point.
* Impulse response (slide 29): j = -(1 + e) v_rel . n / (1/m_a + 1/m_b
  + n . ((I_a^-1 (r_a x n)) x r_a + (I_b^-1 (r_b x n)) x r_b)), with Coulomb friction
  (tangential impulse min(mu j, |v_t| / k_t) against the sliding direction). For spheres hit
  along the line of centres the arms are parallel to n and it reduces to the linear response
  of slide 26.

Differentiability and the smoothing used
----------------------------------------
Contacts are detected and resolved once per substep (pairs in a fixed order, one sequential
pass). The impulse itself is a smooth function of masses, restitution, friction and velocities.
What would make the final position jump is *when* the contact is seen: a penetration is only
noticed at the end of a substep. We therefore use a continuous-time correction: a contact of depth
d with approach speed |v_n| happened d/|v_n| ago, and since then the bodies would have separated
at e |v_n|, so the pair is pushed apart by (1 + e) d along n (split by inverse mass; the centre of
mass does not move). In the absence of other forces within the substep this is exact, so the final
position is continuous (and smooth away from the contact time landing on a substep boundary) in
restitution, initial velocity and mass; e.g. a sphere thrown at a plane in zero gravity ends at
exactly the analytic position whichever substep sees the hit. The correction is linear only (it
does not rotate bodies) and ignores forces acting during the fraction of the substep. Box-box
contact checks vertices against faces only (edge-edge contacts are missed, as in the seed).
Pair restitution and friction are the mean of the two bodies' values; planes use the body's.

Pairwise collision code is unrolled in Python over the (static, small) set of bodies: meant for a
handful of bodies, not for granular media.
"""

# ruff: noqa: F401  (re-exports: the package's public names stay importable from here)
from diffcloth.physics.rigid.bodies import (
    BODY_KEYS,
    SHAPES,
    Contact,
    RigidBody,
    RigidSettings,
    Thrusters,
    _scalar,
    _vec,
    bodies_from_config,
    make_body,
    make_settings,
    make_thrusters,
)
from diffcloth.physics.rigid.contact import (
    _box_axes_contact,
    _Patch,
    _patch_box_box,
    _patch_box_plane,
    _patch_mean,
    contact,
    contact_box_box,
    contact_box_plane,
    contact_box_sphere,
    contact_plane,
    contact_sphere_plane,
    contact_sphere_sphere,
)
from diffcloth.physics.rigid.impulse import (
    _correct,
    _Dyn,
    _dyn,
    _friction,
    _put,
    _resolve,
    _resolve_patch,
    _static_dyn,
    collide_pair,
    collide_plane,
)
from diffcloth.physics.rigid.integrate import (
    _check_controls,
    _plane_list,
    _step,
    _substep_bodies,
    body_at,
    collide_all,
    drag_force,
    force_and_torque,
    integrate_body,
    rigid_rollout,
    rigid_step,
    thruster_force,
)
from diffcloth.physics.rigid.quat import (
    _inv_inertia_world,
    _quat_exp_step,
    angular_momentum,
    box_vertices,
    inertia_tensor,
    kinetic_energy,
    linear_momentum,
    quat_from_axis_angle,
    quat_multiply,
    quat_to_matrix,
    world_inertia,
)
