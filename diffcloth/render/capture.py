"""Per-camera capture nuisances of real footage: exposure gain, small pose error, background.

`Capture` holds, for each of a scene's cameras,

  exposure     (cams,)    multiplicative gain on the whole image (sensor gain / exposure time)
  rotation     (cams, 3)  small rotation error, axis-angle in rad, in the camera's view frame
  translation  (cams, 3)  small translation error in m, in the camera's view frame
  background   (cams, 3)  linear RGB behind the scene

`perturb_camera` applies a pose error: view' = [R(rotation) | translation] @ view, so rotation =
translation = 0 leaves the camera exactly as it was. All leaves are arrays: every field can be
fitted (see `diffcloth.pipeline.PARAMETERS`: exposure, camera_rotation, camera_translation,
background).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from diffcloth.render.camera import Camera

__all__ = ["Capture", "make_capture", "perturb_camera", "rotation_matrix"]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Capture:
    """Per-camera nuisances; see the module docstring. Leaves: exposure (cams,), rotation,
    translation, background (cams, 3)."""

    exposure: jax.Array
    rotation: jax.Array
    translation: jax.Array
    background: jax.Array


def make_capture(
    num_cameras: int,
    *,
    exposure=1.0,
    rotation=(0.0, 0.0, 0.0),
    translation=(0.0, 0.0, 0.0),
    background=(0.05, 0.05, 0.08),
    dtype=None,
) -> Capture:
    """A validated Capture; each value is one for all cameras or one per camera.

    Raises ValueError naming the field for a wrong shape, a non-finite value, exposure <= 0 or a
    background outside [0, 1].

    Shapes: exposure (num_cameras,) or (), rotation, translation, background (num_cameras, 3) or (3,) ->
      Capture with (num_cameras, ...) leaves.
    """
    if not isinstance(num_cameras, int | np.integer) or num_cameras < 1:
        raise ValueError(f"num_cameras must be an int >= 1, got {num_cameras!r}")
    dtype = dtype or jnp.zeros(()).dtype
    out = {}
    for name, value, shape in (
        ("exposure", exposure, (num_cameras,)),
        ("rotation", rotation, (num_cameras, 3)),
        ("translation", translation, (num_cameras, 3)),
        ("background", background, (num_cameras, 3)),
    ):
        v = np.asarray(value, np.float64)
        try:
            v = np.broadcast_to(v, shape)
        except ValueError:
            raise ValueError(
                f"capture {name} has shape {v.shape}; expected {shape[1:] or '()'} or {shape}"
            ) from None
        if not np.all(np.isfinite(v)):
            raise ValueError(f"capture {name} must be finite, got {v.tolist()}")
        out[name] = jnp.asarray(v, dtype)
    if np.any(np.asarray(out["exposure"]) <= 0):
        raise ValueError(f"capture exposure must be > 0 (range (0, inf)), got {exposure!r}")
    bg = np.asarray(out["background"])
    if np.any(bg < 0) or np.any(bg > 1):
        raise ValueError(f"capture background must be in [0, 1], got {background!r}")
    return Capture(**out)


def rotation_matrix(axis_angle):
    """(3, 3) rotation exp([w]_x) of an axis-angle vector w (rad), Rodrigues' formula, smooth at
    w = 0 (series there), differentiable."""
    w = jnp.asarray(axis_angle)
    t2 = jnp.sum(w * w)
    small = t2 < 1e-8
    t2s = jnp.where(small, 1.0, t2)
    t = jnp.sqrt(t2s)
    a = jnp.where(small, 1.0 - t2 / 6.0, jnp.sin(t) / t)
    b = jnp.where(small, 0.5 - t2 / 24.0, (1.0 - jnp.cos(t)) / t2s)
    zero = jnp.zeros((), w.dtype)
    k = jnp.stack(
        [
            jnp.stack([zero, -w[2], w[1]]),
            jnp.stack([w[2], zero, -w[0]]),
            jnp.stack([-w[1], w[0], zero]),
        ]
    )
    return jnp.eye(3, dtype=w.dtype) + a * k + b * (k @ k)


def perturb_camera(camera: Camera, rotation, translation) -> Camera:
    """The camera with a small pose error: view' = [R(rotation) | translation] @ view.

    Args:
      rotation: (3,) axis-angle in rad, in the view frame (x right, y up, z toward the viewer).
      translation: (3,) in m, in the view frame.
    """
    dtype = camera.view.dtype
    r = rotation_matrix(jnp.asarray(rotation, dtype))
    top = jnp.concatenate([r, jnp.asarray(translation, dtype)[:, None]], axis=1)
    delta = jnp.concatenate([top, jnp.eye(4, dtype=dtype)[3:]], axis=0)
    return dataclasses.replace(camera, view=delta @ camera.view)
