"""diffcloth: differentiable cloth simulation and rendering in JAX.

    control-net physics -> patch tessellation -> vertex collision -> rasterize + shade -> image loss
"""

from diffcloth.shapes import Plane, Sphere

__version__ = "0.1.0"

__all__ = ["Plane", "Sphere", "__version__"]
