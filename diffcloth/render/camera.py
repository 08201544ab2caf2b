"""Viewing: view and projection matrices (OpenGL conventions) and the `Camera` pytree.

Every matrix is 4 x 4, acts on column vectors (`clip = projection @ view @ [p, 1]`), and has the
same numbers as gluLookAt, gluPerspective, glFrustum and glOrtho. View space is right-handed and
looks down -z; NDC z runs from -1 (near) to 1 (far). All matrix builders are differentiable in
every argument; argument checks (ValueError) run only on concrete values, never on tracers.

Projections (SEEDS.md section 6):
  perspective / frustum              converging projectors
  orthographic                       parallel projectors perpendicular to the view plane
  oblique (cavalier, cabinet)        parallel projectors at an angle: receding axis drawn at
                                     `alpha` degrees, foreshortening 1 (cavalier) or 1/2 (cabinet)
  axonometric (isometric, dimetric,  orthographic from a direction that foreshortens the three
  trimetric)                         world axes equally / two equally / all differently
  multiview (front, top, side)       orthographic along a principal axis
"""

from __future__ import annotations

import contextlib
import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from diffcloth._math import EPS, materialize_value, safe_normalize

PARALLEL_KINDS = (
    "orthographic",
    "cavalier",
    "cabinet",
    "isometric",
    "dimetric",
    "trimetric",
    "front",
    "top",
    "side",
)
PROJECTION_KINDS = ("perspective",) + PARALLEL_KINDS

# Unit directions from the target towards the eye for axonometric and multiview cameras, and the
# up vector used with them. Isometric: all axes foreshortened equally (sqrt(2/3)); dimetric: x and
# y equally, z by half as much (directions with components 1/3, 1/3, sqrt(7)/3); trimetric: three
# different foreshortenings.
VIEW_DIRECTIONS = {
    "isometric": ((1.0, 1.0, 1.0), (0.0, 1.0, 0.0)),
    "dimetric": ((1.0, 1.0, math.sqrt(7.0)), (0.0, 1.0, 0.0)),
    "trimetric": ((1.0, 2.0, 3.0), (0.0, 1.0, 0.0)),
    "front": ((0.0, 0.0, 1.0), (0.0, 1.0, 0.0)),
    "top": ((0.0, 1.0, 0.0), (0.0, 0.0, -1.0)),
    "side": ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0)),
}
OBLIQUE = {"cavalier": (1.0, 45.0), "cabinet": (0.5, 63.43494882292201)}  # scale, alpha degrees


def _concrete(*xs) -> bool:
    return not any(isinstance(x, jax.core.Tracer) for x in xs)


def _dtype(*xs):
    """The floating dtype of the inputs (Python numbers are weak); default float if none."""
    dt = jnp.result_type(*[x if isinstance(x, int | float) else jnp.asarray(x) for x in xs])
    return dt if jnp.issubdtype(dt, jnp.floating) else jnp.zeros(()).dtype


def look_at(eye, target, up):
    """View matrix of gluLookAt: camera at `eye` looking at `target`, `up` roughly up.

    Args:
      eye, target, up: (3,) world vectors in m; differentiable.
    Returns:
      (4, 4) world -> view matrix.
    Raises:
      ValueError: eye == target, or up parallel to the viewing direction (singular view).
    """
    dtype = _dtype(eye, target, up)
    eye, target, up = (jnp.asarray(v, dtype) for v in (eye, target, up))
    if _concrete(eye, target, up):
        e, t, u = (np.asarray(v, np.float64) for v in (eye, target, up))
        f = t - e
        if not np.all(np.isfinite(np.concatenate([e, t, u]))):
            raise ValueError(f"look_at: eye, target and up must be finite, got {e}, {t}, {u}")
        if np.linalg.norm(f) <= 1e-12:
            raise ValueError(f"look_at: eye {e.tolist()} equals target (singular view)")
        if np.linalg.norm(np.cross(f / np.linalg.norm(f), u)) <= 1e-9:
            raise ValueError(
                f"look_at: up {u.tolist()} is parallel to the view direction (singular view)"
            )
    f = safe_normalize(target - eye)
    s = safe_normalize(jnp.cross(f, up))
    u = jnp.cross(s, f)
    rot = jnp.stack([s, u, -f])
    return _rigid(rot, eye)


def _rigid(rot, eye):
    top = jnp.concatenate([rot, -(rot @ eye)[:, None]], axis=1)
    last = jnp.zeros((1, 4), rot.dtype).at[0, 3].set(1.0)
    return jnp.concatenate([top, last], axis=0)


def view_from_vrp(vrp, vpn, vup):
    """View matrix from the view reference point, view plane normal and view up vector.

    The camera sits at `vrp` and looks along -`vpn` (VPN points from the scene towards the viewer,
    as in PHIGS/Foley: view axes u = VUP x n, v = n x u, n = VPN). So
    `view_from_vrp(eye, eye - target, up) == look_at(eye, target, up)`.

    Args:
      vrp: (3,) eye position in m; vpn: (3,) view plane normal; vup: (3,) view up; differentiable.
    Returns:
      (4, 4) world -> view matrix.
    """
    dtype = _dtype(vrp, vpn, vup)
    vrp, vpn, vup = (jnp.asarray(v, dtype) for v in (vrp, vpn, vup))
    if _concrete(vpn, vup):
        n_, u_ = np.asarray(vpn, np.float64), np.asarray(vup, np.float64)
        if (
            np.linalg.norm(n_) <= 1e-12
            or np.linalg.norm(np.cross(n_ / np.linalg.norm(n_), u_)) <= 1e-9
        ):
            raise ValueError(
                f"view_from_vrp: vpn {n_.tolist()} is zero or parallel to vup {u_.tolist()}"
            )
    n = safe_normalize(vpn)
    u = safe_normalize(jnp.cross(vup, n))
    v = jnp.cross(n, u)
    return _rigid(jnp.stack([u, v, n]), vrp)


def _check_near_far(name, near, far, *, perspective):
    if not _concrete(near, far):
        return
    n, f = float(near), float(far)
    if not (np.isfinite(n) and np.isfinite(f)):
        raise ValueError(f"{name}: near and far must be finite, got near={n}, far={f}")
    if perspective and n <= 0:
        raise ValueError(f"{name}: near must be > 0 for a perspective projection, got near={n}")
    if n >= f:
        raise ValueError(f"{name}: near must be < far, got near={n}, far={f}")


def perspective(fov_y_degrees, aspect, near, far):
    """gluPerspective: vertical fov in degrees, aspect = width / height, near/far > 0 in m.

    Raises:
      ValueError: fov outside (0, 180), aspect <= 0, near <= 0 or near >= far.
    """
    if _concrete(fov_y_degrees, aspect):
        fov, a = float(fov_y_degrees), float(aspect)
        if not 0.0 < fov < 180.0:
            raise ValueError(f"perspective: fov_y_degrees must be in (0, 180), got {fov}")
        if not a > 0.0:
            raise ValueError(f"perspective: aspect must be > 0, got {a}")
    _check_near_far("perspective", near, far, perspective=True)
    dtype = _dtype(fov_y_degrees, aspect, near, far)
    fov, aspect, near, far = (jnp.asarray(v, dtype) for v in (fov_y_degrees, aspect, near, far))
    f = 1.0 / jnp.tan(jnp.deg2rad(fov) / 2.0)
    z = jnp.zeros((), dtype)
    return jnp.stack(
        [
            jnp.stack([f / aspect, z, z, z]),
            jnp.stack([z, f, z, z]),
            jnp.stack([z, z, (far + near) / (near - far), 2.0 * far * near / (near - far)]),
            jnp.stack([z, z, -jnp.ones((), dtype), z]),
        ]
    )


def frustum(left, right, bottom, top, near, far):
    """glFrustum: perspective projection of the view-space box on the near plane (m).

    Shapes: scalars () m -> (4, 4) projection matrix.
    """
    l, r, b, t, n, f, z = _view_box("frustum", left, right, bottom, top, near, far, True)
    dtype = z.dtype
    return jnp.stack(
        [
            jnp.stack([2 * n / (r - l), z, (r + l) / (r - l), z]),
            jnp.stack([z, 2 * n / (t - b), (t + b) / (t - b), z]),
            jnp.stack([z, z, -(f + n) / (f - n), -2 * f * n / (f - n)]),
            jnp.stack([z, z, -jnp.ones((), dtype), z]),
        ]
    )


def _view_box(name, left, right, bottom, top, near, far, perspective: bool):
    """Checked view-space box as arrays of one dtype: l, r, b, t, n, f and a zero, each ()."""
    _check_near_far(name, near, far, perspective=perspective)
    _check_box(name, left, right, bottom, top)
    dtype = _dtype(left, right, bottom, top, near, far)
    box = (jnp.asarray(v, dtype) for v in (left, right, bottom, top, near, far))
    return (*box, jnp.zeros((), dtype))


def _check_box(name, left, right, bottom, top):
    if _concrete(left, right, bottom, top) and not (
        float(left) < float(right) and float(bottom) < float(top)
    ):
        raise ValueError(
            f"{name}: need left < right and bottom < top, got {float(left)}, {float(right)}, "
            f"{float(bottom)}, {float(top)}"
        )


def orthographic(left, right, bottom, top, near, far):
    """glOrtho: parallel projection of the view-space box [l, r] x [b, t] x [-far, -near] (m).

    Shapes: scalars () m -> (4, 4) projection matrix.
    """
    l, r, b, t, n, f, z = _view_box("orthographic", left, right, bottom, top, near, far, False)
    dtype = z.dtype
    return jnp.stack(
        [
            jnp.stack([2 / (r - l), z, z, -(r + l) / (r - l)]),
            jnp.stack([z, 2 / (t - b), z, -(t + b) / (t - b)]),
            jnp.stack([z, z, -2 / (f - n), -(f + n) / (f - n)]),
            jnp.stack([z, z, z, jnp.ones((), dtype)]),
        ]
    )


def oblique(alpha_degrees, scale, left, right, bottom, top, near, far, depth_ref=0.0):
    """Oblique parallel projection: orthographic(...) @ shear.

    A point at view depth d = -z is shifted by scale * (d - depth_ref) * (cos alpha, sin alpha), so
    lines along the viewing axis are drawn at `alpha` degrees to the horizontal with foreshortening
    `scale`, and the plane at `depth_ref` is drawn undistorted.
    """
    dtype = _dtype(alpha_degrees, scale, left, right, bottom, top, near, far, depth_ref)
    a = jnp.deg2rad(jnp.asarray(alpha_degrees, dtype))
    s = jnp.asarray(scale, dtype)
    dr = jnp.asarray(depth_ref, dtype)
    cx, cy = s * jnp.cos(a), s * jnp.sin(a)
    shear = (
        jnp.eye(4, dtype=dtype)
        .at[0, 2]
        .set(-cx)
        .at[1, 2]
        .set(-cy)
        .at[0, 3]
        .set(-cx * dr)
        .at[1, 3]
        .set(-cy * dr)
    )
    return orthographic(left, right, bottom, top, near, far).astype(dtype) @ shear


def cavalier(left, right, bottom, top, near, far, depth_ref=0.0, alpha_degrees=45.0):
    """Cavalier oblique projection (receding axis at full length).

    Shapes: scalars () m, degrees -> (4, 4) projection matrix.
    """
    return oblique(alpha_degrees, 1.0, left, right, bottom, top, near, far, depth_ref)


def cabinet(
    left, right, bottom, top, near, far, depth_ref=0.0, alpha_degrees=OBLIQUE["cabinet"][1]
):
    """Cabinet oblique projection (receding axis at half length, 63.4 degrees)."""
    return oblique(alpha_degrees, 0.5, left, right, bottom, top, near, far, depth_ref)


def axonometric_view(kind: str, target, distance):
    """View matrix for an axonometric or multiview camera looking at `target` from `distance` m.

    kind: one of "isometric", "dimetric", "trimetric", "front", "top", "side" (VIEW_DIRECTIONS).
    Use with an orthographic projection.

    Shapes: target (3,) m, distance () m -> (4, 4) view matrix.
    """
    if kind not in VIEW_DIRECTIONS:
        raise ValueError(
            f"axonometric_view: kind must be one of {tuple(VIEW_DIRECTIONS)}, got {kind!r}"
        )
    direction, up = VIEW_DIRECTIONS[kind]
    dtype = _dtype(target, distance)
    d = jnp.asarray(direction, dtype)
    d = d / jnp.linalg.norm(d)
    target = jnp.asarray(target, dtype)
    return look_at(target + jnp.asarray(distance, dtype) * d, target, jnp.asarray(up, dtype))


def _named_view(kind: str):
    def view(target, distance):
        return axonometric_view(kind, target, distance)

    view.__name__ = view.__qualname__ = f"{kind}_view"
    view.__doc__ = f'`axonometric_view("{kind}", ...)`: target (3,) m, distance () m -> (4, 4).'
    return view


isometric_view, dimetric_view, trimetric_view, front_view, top_view, side_view = map(
    _named_view, ("isometric", "dimetric", "trimetric", "front", "top", "side")
)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Camera:
    """A camera: world -> view -> clip matrices, clip depths and image size.

    view: (4, 4) world -> view (rigid); projection: (4, 4) view -> clip;
    near, far: () view-space depths in m that bound what is drawn;
    width, height: image size in pixels (static); kind: projection kind (static), one of
    PROJECTION_KINDS; only "perspective" has converging rays.
    """

    view: jax.Array
    projection: jax.Array
    near: jax.Array
    far: jax.Array
    width: int = dataclasses.field(metadata={"static": True})
    height: int = dataclasses.field(metadata={"static": True})
    kind: str = dataclasses.field(default="perspective", metadata={"static": True})

    @property
    def is_perspective(self) -> bool:
        return self.kind == "perspective"


def _check_size(width, height):
    for name, v in (("width", width), ("height", height)):
        if not isinstance(v, int | np.integer) or isinstance(v, bool) or v <= 0:
            raise ValueError(f"camera {name} must be a positive int (pixels), got {v!r}")


def make_camera(
    eye,
    target,
    up,
    *,
    width: int,
    height: int,
    fov_y: float = 45.0,
    near: float = 0.1,
    far: float = 100.0,
    projection: str = "perspective",
) -> Camera:
    """Build a validated camera looking from `eye` at `target`.

    Parallel projections frame the same view-space height at the target as the perspective camera
    would (half height = |target - eye| tan(fov_y / 2)). Axonometric and multiview kinds keep the
    target and the eye distance but replace the viewing direction by theirs (VIEW_DIRECTIONS).

    Raises:
      ValueError: width/height not positive ints, fov_y outside (0, 180), near >= far,
      near <= 0 (perspective), unknown projection, or a singular view (eye == target, up parallel).

    >>> cam = make_camera((0, 0, 3), (0, 0, 0), (0, 1, 0), width=32, height=24)
    >>> cam.view.shape, cam.projection.shape, (cam.width, cam.height)
    ((4, 4), (4, 4), (32, 24))
    """
    _check_size(width, height)
    if projection not in PROJECTION_KINDS:
        raise ValueError(
            f"make_camera: projection must be one of {PROJECTION_KINDS}, got {projection!r}"
        )
    if _concrete(fov_y) and not 0.0 < float(fov_y) < 180.0:
        raise ValueError(f"make_camera: fov_y must be in (0, 180) degrees, got {float(fov_y)}")
    _check_near_far("make_camera", near, far, perspective=projection == "perspective")
    dtype = _dtype(eye, target, up, fov_y, near, far)
    eye, target, up = (jnp.asarray(v, dtype) for v in (eye, target, up))
    aspect = width / height
    if projection in VIEW_DIRECTIONS:
        distance = jnp.linalg.norm(target - eye)
        if _concrete(distance) and float(distance) <= 1e-12:
            raise ValueError("make_camera: eye equals target (singular view)")
        view = axonometric_view(projection, target, distance)
    else:
        view = look_at(eye, target, up)
    if projection == "perspective":
        proj = perspective(fov_y, aspect, near, far)
    else:
        distance = jnp.linalg.norm(target - eye)
        half_h = distance * jnp.tan(jnp.deg2rad(jnp.asarray(fov_y, dtype)) / 2.0)
        half_w = half_h * aspect
        if projection in OBLIQUE:
            scale, alpha = OBLIQUE[projection]
            proj = oblique(alpha, scale, -half_w, half_w, -half_h, half_h, near, far, distance)
        else:
            proj = orthographic(-half_w, half_w, -half_h, half_h, near, far)
    return Camera(
        view=view.astype(dtype),
        projection=proj.astype(dtype),
        near=jnp.asarray(near, dtype),
        far=jnp.asarray(far, dtype),
        width=int(width),
        height=int(height),
        kind=projection,
    )


def camera_from_matrices(
    view, projection, *, width, height, near, far, kind="perspective"
) -> Camera:
    """A camera from explicit matrices, validated (view must be rigid: orthonormal rotation).

    Raises:
      ValueError: bad size, near >= far, non-finite, singular or non-orthonormal view matrix,
      singular projection.

    Shapes: view, projection (4, 4) -> Camera.
    """
    _check_size(width, height)
    if kind not in PROJECTION_KINDS:
        raise ValueError(
            f"camera_from_matrices: kind must be one of {PROJECTION_KINDS}, got {kind!r}"
        )
    _check_near_far("camera_from_matrices", near, far, perspective=kind == "perspective")
    if _concrete(view, projection):
        v, p = np.asarray(view, np.float64), np.asarray(projection, np.float64)
        if v.shape != (4, 4) or p.shape != (4, 4):
            raise ValueError(f"view and projection must be (4, 4), got {v.shape} and {p.shape}")
        if not (np.all(np.isfinite(v)) and np.all(np.isfinite(p))):
            raise ValueError("view and projection matrices must be finite")
        rot = v[:3, :3]
        err = np.abs(rot @ rot.T - np.eye(3)).max()
        if err > 1e-4 or abs(np.linalg.det(rot) - 1.0) > 1e-4 or np.any(v[3] != [0, 0, 0, 1]):
            raise ValueError(
                f"view matrix must be rigid (orthonormal rotation, det 1, last row 0 0 0 1); "
                f"|R R^T - I| = {err:.3g}, det = {np.linalg.det(rot):.3g}"
            )
        if abs(np.linalg.det(p)) <= 1e-12:
            raise ValueError("projection matrix is singular")
    dtype = _dtype(view, projection, near, far)
    return Camera(
        jnp.asarray(view, dtype),
        jnp.asarray(projection, dtype),
        jnp.asarray(near, dtype),
        jnp.asarray(far, dtype),
        int(width),
        int(height),
        kind,
    )


def eye_position(camera: Camera):
    """(3,) world position of the eye (perspective: centre of projection; else view origin)."""
    rot = camera.view[:3, :3]
    return -(rot.T @ camera.view[:3, 3])


def view_direction(camera: Camera):
    """(3,) unit world direction the camera looks along (-z of view space)."""
    return -camera.view[2, :3]


def pixel_centers(width: int, height: int, dtype=None):
    """(H, W, 2) NDC (x, y) of pixel centres; row 0 is the top (y = +1 side)."""
    dtype = dtype or jnp.zeros(()).dtype
    x = (jnp.arange(width, dtype=dtype) + 0.5) / width * 2.0 - 1.0
    y = 1.0 - (jnp.arange(height, dtype=dtype) + 0.5) / height * 2.0
    xx, yy = jnp.meshgrid(x, y)
    return jnp.stack([xx, yy], axis=-1)


def pixel_rays(camera: Camera):
    """World rays through every pixel centre, starting on the near plane.

    Returns:
      (origins (H, W, 3) in m, directions (H, W, 3) unit). Perspective rays diverge from the eye;
      parallel (orthographic, oblique, axonometric) rays share one direction. Differentiable in
      the camera matrices. A concrete (fixed) camera's rays are computed while tracing
      (`jax.ensure_compile_time_eval`), constants up to 512^2 pixels (6 MB); else in the program.
    """
    small = camera.width * camera.height <= 512 * 512
    with jax.ensure_compile_time_eval() if small else contextlib.nullcontext():
        dtype = camera.view.dtype
        ndc = pixel_centers(camera.width, camera.height, dtype)
        inv = jnp.linalg.inv(camera.projection @ camera.view)
        x, y = ndc[..., 0], ndc[..., 1]
        # per component: XLA's CPU loops run a 3- or 4-long minor-axis sum several times slower
        base = [inv[i, 0] * x + inv[i, 1] * y + inv[i, 3] for i in range(4)]
        near_h = [b - inv[i, 2] for i, b in enumerate(base)]
        far_h = [b + inv[i, 2] for i, b in enumerate(base)]
        p0 = [near_h[i] / near_h[3] for i in range(3)]
        d = [far_h[i] / far_h[3] - p0[i] for i in range(3)]
        sq = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
        ok = sq > EPS.get(jnp.dtype(dtype), 1e-12)  # as safe_normalize: +y for a zero vector
        n = jnp.sqrt(jnp.where(ok, sq, 1.0))
        fallback = (0.0, 1.0, 0.0)
        # each component in a loop of its own (fused into the stack: one branch per entry)
        d = [
            materialize_value(jnp.where(ok, jnp.where(ok, d[i], 1.0) / n, fallback[i]))
            for i in range(3)
        ]
        return jnp.stack(p0, axis=-1), jnp.stack(d, axis=-1).astype(dtype)


def project(points, camera: Camera):
    """World points (..., 3) -> (clip (..., 4), view depth (...) = -z_view in m)."""
    V, P = camera.view, camera.projection
    p = [points[..., j] for j in range(3)]
    # written out per component (see pixel_rays)
    view = [V[i, 0] * p[0] + V[i, 1] * p[1] + V[i, 2] * p[2] + V[i, 3] for i in range(4)]
    clip = [sum(P[i, j] * view[j] for j in range(4)) for i in range(4)]
    return jnp.stack(clip, axis=-1), -view[2]
