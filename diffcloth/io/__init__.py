"""Files in and out: meshes (OBJ) and media (PNG, GIF, MP4, JSON)."""

from diffcloth.io.media import *  # noqa: F403
from diffcloth.io.mesh import *  # noqa: F403
