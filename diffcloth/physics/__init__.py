"""diffcloth.physics: mass-spring cloth on a grid control net (Provot springs), colliders, integrators.

net = grid_net(10, 13, (1.2, 0.9), pinned="top_corners")
traj = rollout(net, make_sim(), make_material(), rest_state(net), num_frames=60)
"""

from diffcloth.physics import coupled, rigid, sensitivity  # noqa: E402  (bodies; mixed-mode gradients)
from diffcloth.physics.collide import Colliders, as_colliders, collide, make_colliders
from diffcloth.physics.coupled import body_colliders, coupled_rollout, coupled_step
from diffcloth.physics.forces import (
    bend_forces,
    drag_forces,
    elastic_energy,
    external_forces,
    internal_forces,
    kinetic_energy,
    node_mass,
    potential_energy,
    spring_forces,
    total_forces,
)
from diffcloth.physics.integrate import (
    STEPS,
    Contacts,
    implicit_euler,
    step,
    step_with_contacts,
    symplectic_euler,
)
from diffcloth.physics.massspring import (
    MASS_SPRING_FIELDS,
    MassSpring,
    make_mass_spring,
    validate_mass_spring,
)
from diffcloth.physics.material import (
    MATERIAL_FIELDS,
    Material,
    make_material,
    material_from_raw,
    material_to_raw,
    to_physical,
    to_raw,
    validate_material,
)
from diffcloth.physics.net import Net, grid_net, make_net
from diffcloth.physics.rigid import (
    RigidBody,
    RigidSettings,
    Thrusters,
    bodies_from_config,
    make_body,
    make_thrusters,
    rigid_rollout,
    rigid_step,
)
from diffcloth.physics.rigid import make_settings as make_rigid_settings
from diffcloth.physics.rollout import (
    StabilityWarning,
    UnstableSimulationError,
    UnstableStepError,
    advance,
    blowup_bound,
    check_stability,
    checked_rollout,
    first_bad_frame,
    frames_ok,
    rollout,
    simulate,
    stable_substep,
    trajectory_ok,
)
from diffcloth.physics.state import ClothState, SimSettings, make_sim, rest_state, validate_state

__all__ = [
    "RigidBody",
    "RigidSettings",
    "Thrusters",
    "bodies_from_config",
    "body_colliders",
    "coupled",
    "coupled_rollout",
    "coupled_step",
    "make_body",
    "make_rigid_settings",
    "make_thrusters",
    "rigid",
    "sensitivity",
    "rigid_rollout",
    "rigid_step",
    "Colliders",
    "ClothState",
    "Contacts",
    "MATERIAL_FIELDS",
    "MASS_SPRING_FIELDS",
    "MassSpring",
    "make_mass_spring",
    "validate_mass_spring",
    "Material",
    "Net",
    "STEPS",
    "SimSettings",
    "StabilityWarning",
    "UnstableSimulationError",
    "UnstableStepError",
    "advance",
    "as_colliders",
    "bend_forces",
    "check_stability",
    "collide",
    "drag_forces",
    "elastic_energy",
    "external_forces",
    "grid_net",
    "implicit_euler",
    "internal_forces",
    "kinetic_energy",
    "make_colliders",
    "make_material",
    "make_net",
    "make_sim",
    "material_from_raw",
    "material_to_raw",
    "node_mass",
    "potential_energy",
    "rest_state",
    "blowup_bound",
    "first_bad_frame",
    "frames_ok",
    "rollout",
    "simulate",  # deprecated name of checked_rollout
    "checked_rollout",
    "spring_forces",
    "stable_substep",
    "step",
    "step_with_contacts",
    "symplectic_euler",
    "to_physical",
    "to_raw",
    "total_forces",
    "trajectory_ok",
    "validate_material",
    "validate_state",
]
