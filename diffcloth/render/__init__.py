"""diffcloth.render stage."""
# ruff: noqa: F401  (re-exports)

# viewing, culling, rasterizer, analytic spheres
from diffcloth.render.camera import (
    Camera,
    cabinet,
    camera_from_matrices,
    cavalier,
    eye_position,
    frustum,
    look_at,
    make_camera,
    oblique,
    orthographic,
    perspective,
    pixel_rays,
    view_direction,
    view_from_vrp,
)
from diffcloth.render.camera import axonometric_view, dimetric_view, isometric_view, trimetric_view
from diffcloth.render.camera import front_view, side_view, top_view
from diffcloth.render.capture import Capture, make_capture, perturb_camera
from diffcloth.render.culling import facing_camera, frustum_planes, sphere_in_frustum
from diffcloth.render.raster import Fragments, GBuffer, antialias, composite, edge_neighbors
from diffcloth.render.raster import interpolate, rasterize, rasterize_gbuffer, render_mesh
from diffcloth.render.spheres import raycast_spheres

# shading (lights, appearance, textures, G-buffer shading modes); `shade` stays the module name
from diffcloth.render.lights import Appearance, Light, Lights, make_appearance, make_lights
from diffcloth.render.lights import appearance_fields
from diffcloth.render.render import render, surface_gbuffer  # the function shadows its module
from diffcloth.render.render import PLANE_COLOR, frame_shadow_maps
from diffcloth.render.shadows import ShadowMaps, shadow_maps, shadow_visibility, sphere_visibility
from diffcloth.render.shade import MODES as SHADING_MODES
from diffcloth.render.shade import ShadingBuffer, light_vertices
from diffcloth.render.textures import (
    CubeMap,
    Textures,
    default_textures,
    load_cube_map,
    load_texture,
    make_cube_map,
    make_textures,
    sky_cube_map,
)
