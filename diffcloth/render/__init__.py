"""diffcloth.render stage."""
# ruff: noqa: F401  (re-exports)

# shading (lights, appearance, textures, G-buffer shading modes); `shade` stays the module name
from diffcloth.render.lights import Appearance, Light, Lights, make_appearance, make_lights
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
