"""diffcloth.physics.mesh: triangle-mesh cloth of any shape, with an orthotropic fabric model in
textile units, colliders, and static-equilibrium / implicit / symplectic solvers. It hands the
rest of the pipeline the same kind of surface the grid net's tessellation does (`cloth_surface`).

    cloth = make_cloth(disc(0.15, 0.008, rings_at=(0.09,)), pinned=...)
    fabric = make_fabric("wang2011-gray-interlock")
    rest = equilibrium(cloth, fabric, cloth.rest, gravity=g, colliders=pedestal)
"""

from diffcloth.physics.mesh.builders import (
    MeshData,
    MeshError,
    check_mesh,
    disc,
    grid_square,
    read_cloth_obj,
    rectangle,
)
from diffcloth.physics.mesh.colliders import (
    MeshColliders,
    contact_energy,
    make_mesh_colliders,
    signed_distance,
)
from diffcloth.physics.mesh.dynamics import implicit_step, mesh_rollout, symplectic_step
from diffcloth.physics.mesh.energy import (
    bending_energy,
    curvatures,
    dihedral_angles,
    elastic_energy,
    gravity_energy,
    green_strain,
    membrane_energy,
    vertex_mass,
)
from diffcloth.physics.mesh.fabric import (
    FABRIC_FIELDS,
    Fabric,
    bending_length,
    fabric_preset,
    fabric_presets,
    fabric_to_dict,
    make_fabric,
    validate_fabric,
)
from diffcloth.physics.mesh.measure import (
    DrapeCoefficient,
    Shadow,
    cantilever_rigidity,
    drape_coefficient,
    drape_shadow,
    node_count,
    outline_radius,
)
from diffcloth.physics.mesh.solve import (
    EquilibriumResult,
    NotConvergedError,
    SolverSettings,
    check_equilibrium,
    equilibrium,
    potential,
)
from diffcloth.physics.mesh.surface import DisplayMesh, cloth_surface, display_mesh, texture_uv
from diffcloth.physics.mesh.topology import ClothMesh, active_part, make_cloth, pin_mask

__all__ = [
    "FABRIC_FIELDS",
    "ClothMesh",
    "active_part",
    "DisplayMesh",
    "EquilibriumResult",
    "Fabric",
    "MeshColliders",
    "MeshData",
    "MeshError",
    "NotConvergedError",
    "SolverSettings",
    "bending_energy",
    "bending_length",
    "check_equilibrium",
    "check_mesh",
    "cloth_surface",
    "contact_energy",
    "curvatures",
    "dihedral_angles",
    "disc",
    "display_mesh",
    "elastic_energy",
    "equilibrium",
    "fabric_preset",
    "fabric_presets",
    "fabric_to_dict",
    "gravity_energy",
    "green_strain",
    "grid_square",
    "implicit_step",
    "make_cloth",
    "make_fabric",
    "make_mesh_colliders",
    "membrane_energy",
    "mesh_rollout",
    "pin_mask",
    "potential",
    "read_cloth_obj",
    "rectangle",
    "signed_distance",
    "symplectic_step",
    "texture_uv",
    "validate_fabric",
    "vertex_mass",
    "DrapeCoefficient",
    "Shadow",
    "cantilever_rigidity",
    "drape_coefficient",
    "drape_shadow",
    "node_count",
    "outline_radius",
]
