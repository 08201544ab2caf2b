"""diffcloth.render stage."""

# ruff: noqa: F401  (re-exports)
import sys
import types
import warnings

# viewing, culling, rasterizer, analytic spheres
# plain meshes (smooth vertex normals) and box bodies as triangles
from diffcloth.render import boxes, frame, mesh, sky
from diffcloth.render.boxes import BoxPoses, box_triangles
from diffcloth.render.camera import (
    Camera,
    axonometric_view,
    cabinet,
    camera_from_matrices,
    cavalier,
    dimetric_view,
    eye_position,
    front_view,
    frustum,
    isometric_view,
    look_at,
    make_camera,
    oblique,
    orthographic,
    perspective,
    pixel_rays,
    side_view,
    top_view,
    trimetric_view,
    view_direction,
    view_from_vrp,
)
from diffcloth.render.capture import Capture, make_capture, perturb_camera
from diffcloth.render.culling import facing_camera, frustum_planes, sphere_in_frustum
from diffcloth.render.frame import (  # one frame; the module was render/render.py
    PLANE_COLOR,
    frame_shadow_maps,
    render,
    surface_gbuffer,
)

# shading (lights, appearance, textures, G-buffer shading modes); `shade` stays the module name
from diffcloth.render.lights import (
    Appearance,
    Light,
    Lights,
    appearance_fields,
    make_appearance,
    make_lights,
)
from diffcloth.render.mesh import mesh_surface, vertex_normals
from diffcloth.render.prepared import PreparedFrame, prepare_frame, render_prepared
from diffcloth.render.raster import (
    Fragments,
    GBuffer,
    antialias,
    antialias_weights,
    composite,
    edge_neighbors,
    interpolate,
    rasterize,
    rasterize_gbuffer,
    render_mesh,
)
from diffcloth.render.shade import MODES as SHADING_MODES
from diffcloth.render.shade import ShadingBuffer, light_vertices
from diffcloth.render.shadows import ShadowMaps, shadow_maps, shadow_visibility, sphere_visibility
from diffcloth.render.sky import SkyMaps, frame_sky_maps, sky_maps, sky_visibility
from diffcloth.render.spheres import raycast_spheres
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


class _RenamedModule(types.ModuleType):
    """`diffcloth.render.render` as a module path (deprecated): the module is now
    `diffcloth.render.frame`, so the function `diffcloth.render.render` no longer shares its name
    with a module. Old `from diffcloth.render.render import X` imports keep working, with a
    DeprecationWarning."""

    def __getattr__(self, name):
        if name.startswith("__"):  # introspection (pytest, inspect): not an old import
            raise AttributeError(name)
        warnings.warn(
            "the module diffcloth.render.render is renamed diffcloth.render.frame "
            "(diffcloth.render.render is the render function)",
            DeprecationWarning,
            stacklevel=2,
        )
        return getattr(frame, name)


sys.modules[__name__ + ".render"] = _RenamedModule(__name__ + ".render")
