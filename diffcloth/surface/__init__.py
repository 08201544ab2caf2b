"""Stage 2: control net -> smooth surface (tessellation), vertex collision, vertex deformation."""

from diffcloth.surface.basis import (
    BASES,
    basis_matrix,
    knots,
    num_patches,
    patch_weights,
    sample_parameters,
    sampled_basis,
)
from diffcloth.surface.collide import collide_surface, push_out_of_sphere, push_out_of_spheres
from diffcloth.surface.deform import displace_along_normals, ripples, waves
from diffcloth.surface.lod import focal_length_pixels, projected_size_pixels, select_level
from diffcloth.surface.tessellate import (
    Surface,
    frames_from_derivatives,
    grid_faces,
    grid_frames,
    grid_uv,
    orthonormal_tangent,
    tessellate,
    vertex_grid_shape,
)

__all__ = [
    "BASES",
    "Surface",
    "basis_matrix",
    "collide_surface",
    "displace_along_normals",
    "focal_length_pixels",
    "frames_from_derivatives",
    "grid_faces",
    "grid_frames",
    "grid_uv",
    "knots",
    "num_patches",
    "orthonormal_tangent",
    "patch_weights",
    "projected_size_pixels",
    "push_out_of_sphere",
    "push_out_of_spheres",
    "ripples",
    "sample_parameters",
    "sampled_basis",
    "select_level",
    "tessellate",
    "vertex_grid_shape",
    "waves",
]
