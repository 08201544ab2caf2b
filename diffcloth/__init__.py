"""diffcloth: differentiable cloth simulation and rendering in JAX.

control-net physics -> patch tessellation -> vertex collision -> rasterize + shade -> image loss

import diffcloth as dc
scene = dc.load_scene("configs/drape_fit.toml")
video = dc.simulate_and_render(scene, {"bend": 2e-3})        # (cameras, T, H, W, 3)
result = dc.fit.fit(scene, video, free=["bend"], steps=50)   # FitResult
"""

from importlib import metadata as _metadata

from diffcloth import fit, io, physics, render, surface
from diffcloth.physics import ClothState, Material, Net
from diffcloth.physics.rigid import RigidBody
from diffcloth.pipeline import (
    PARAMETERS,
    apply_params,
    simulate,
    simulate_and_render,
    simulate_and_render_checked,
)
from diffcloth.render import Camera, Light
from diffcloth.runtime import tune_malloc, tune_xla_cpu
from diffcloth.scene import Scene, build_scene, load_scene
from diffcloth.shapes import Plane, Sphere

try:  # the installed distribution's version (pyproject.toml)
    __version__ = _metadata.version("diffcloth")
except _metadata.PackageNotFoundError:  # a source tree on sys.path, not installed
    __version__ = "0.2.0"

tune_xla_cpu()  # no import above starts a JAX backend; XLA reads XLA_FLAGS once, when one starts
tune_malloc()  # freed buffers stay mapped for the next call of a compiled program

__all__ = [
    "PARAMETERS",
    "Camera",
    "ClothState",
    "Light",
    "Material",
    "Net",
    "Plane",
    "RigidBody",
    "Scene",
    "Sphere",
    "__version__",
    "apply_params",
    "build_scene",
    "fit",
    "io",
    "load_scene",
    "physics",
    "render",
    "simulate",
    "simulate_and_render",
    "simulate_and_render_checked",
    "surface",
]
