"""Camera matrices against the OpenGL closed forms, projections, validation (ROBUSTNESS row 20)."""

import dataclasses
import math

import jax
import jax.numpy as jnp
import jax.test_util  # noqa: F401
import numpy as np
import pytest

from diffcloth.render import camera as C


def glu_look_at(eye, target, up):
    eye, target, up = (np.asarray(v, float) for v in (eye, target, up))
    f = target - eye
    f /= np.linalg.norm(f)
    s = np.cross(f, up)
    s /= np.linalg.norm(s)
    u = np.cross(s, f)
    m = np.eye(4)
    m[0, :3], m[1, :3], m[2, :3] = s, u, -f
    return m @ np.block([[np.eye(3), -eye[:, None]], [np.zeros((1, 3)), np.ones((1, 1))]])


def test_look_at_matches_glu():
    rng = np.random.default_rng(0)
    for _ in range(5):
        eye, target = rng.normal(size=3) * 3, rng.normal(size=3)
        up = np.array([0.1, 1.0, -0.2])
        np.testing.assert_allclose(
            C.look_at(eye, target, up), glu_look_at(eye, target, up), atol=1e-12
        )


def test_view_from_vrp_equals_look_at():
    eye, target, up = (
        np.array([1.0, 2.0, 3.0]),
        np.array([0.0, 0.5, -1.0]),
        np.array([0.0, 1.0, 0.0]),
    )
    np.testing.assert_allclose(
        C.view_from_vrp(eye, eye - target, up), C.look_at(eye, target, up), atol=1e-12
    )


def test_perspective_and_frustum_closed_forms():
    fov, aspect, n, f = 60.0, 1.5, 0.5, 20.0
    t = 1.0 / math.tan(math.radians(fov) / 2)
    want = np.array(
        [
            [t / aspect, 0, 0, 0],
            [0, t, 0, 0],
            [0, 0, (f + n) / (n - f), 2 * f * n / (n - f)],
            [0, 0, -1, 0],
        ]
    )
    np.testing.assert_allclose(C.perspective(fov, aspect, n, f), want, atol=1e-12)
    top = n / t
    np.testing.assert_allclose(
        C.frustum(-top * aspect, top * aspect, -top, top, n, f), want, atol=1e-12
    )


def test_orthographic_closed_form():
    l, r, b, t, n, f = -1.0, 3.0, -2.0, 0.5, 0.1, 7.0
    want = np.array(
        [
            [2 / (r - l), 0, 0, -(r + l) / (r - l)],
            [0, 2 / (t - b), 0, -(t + b) / (t - b)],
            [0, 0, -2 / (f - n), -(f + n) / (f - n)],
            [0, 0, 0, 1],
        ]
    )
    np.testing.assert_allclose(C.orthographic(l, r, b, t, n, f), want, atol=1e-12)


@pytest.mark.parametrize(
    "kind,scale,alpha", [("cavalier", 1.0, 45.0), ("cabinet", 0.5, 63.43494882292201)]
)
def test_oblique_receding_axis(kind, scale, alpha):
    fn = getattr(C, kind)
    box = (-2.0, 2.0, -2.0, 2.0, 0.1, 10.0)
    P = fn(*box, depth_ref=3.0)
    ortho = C.orthographic(*box)
    # a point on the reference plane is undistorted; one unit further is shifted by scale*(cos, sin)
    p_ref = jnp.array([0.3, -0.2, -3.0, 1.0])
    np.testing.assert_allclose(P @ p_ref, ortho @ p_ref, atol=1e-12)
    p_far = jnp.array([0.3, -0.2, -4.0, 1.0])
    shift = (P @ p_far - ortho @ p_far)[:2] * 2.0  # NDC units -> view units (half width 2)
    a = math.radians(alpha)
    np.testing.assert_allclose(shift, [scale * math.cos(a), scale * math.sin(a)], atol=1e-12)


def _foreshortening(view):
    # length on screen of the unit world axes under an orthographic view
    return np.linalg.norm(np.asarray(view)[:2, :3], axis=0)


def test_axonometric_foreshortening():
    iso = _foreshortening(C.isometric_view(jnp.zeros(3), 5.0))
    np.testing.assert_allclose(iso, math.sqrt(2 / 3), atol=1e-12)
    dim = _foreshortening(C.dimetric_view(jnp.zeros(3), 5.0))
    assert abs(dim[0] - dim[1]) < 1e-12 and abs(dim[2] - dim[0]) > 0.1
    tri = _foreshortening(C.trimetric_view(jnp.zeros(3), 5.0))
    assert min(abs(tri[0] - tri[1]), abs(tri[1] - tri[2]), abs(tri[0] - tri[2])) > 0.05


@pytest.mark.parametrize(
    "kind,hidden", [("front", 2), ("top", 1), ("side", 0)]
)  # multiview: the principal axis along the view vanishes, the others keep full length
def test_multiview(kind, hidden):
    f = _foreshortening(C.axonometric_view(kind, jnp.zeros(3), 4.0))
    want = np.ones(3)
    want[hidden] = 0.0
    np.testing.assert_allclose(f, want, atol=1e-12)


@pytest.mark.parametrize("projection", C.PROJECTION_KINDS)
def test_make_camera_kinds_frame_the_target(projection):
    cam = C.make_camera(
        (0.5, 1.0, 4.0), (0.0, 0.0, 0.0), (0, 1, 0), width=20, height=10, projection=projection
    )
    clip, depth = C.project(jnp.zeros((1, 3)), cam)
    ndc = clip[0, :3] / clip[0, 3]
    np.testing.assert_allclose(ndc[:2], 0.0, atol=1e-9)  # target at the image centre
    assert float(depth[0]) > 0 and cam.kind == projection


def test_eye_and_rays():
    eye = jnp.array([0.3, 1.0, 2.0])
    cam = C.make_camera(eye, (0.0, 0.0, 0.0), (0, 1, 0), width=6, height=4)
    np.testing.assert_allclose(C.eye_position(cam), eye, atol=1e-12)
    o, d = C.pixel_rays(cam)
    assert o.shape == (4, 6, 3) and d.shape == (4, 6, 3)
    # perspective rays start on the near plane and point away from the eye
    to_o = o - eye[None, None]
    np.testing.assert_allclose(np.cross(to_o, d), 0.0, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-12)
    # the ray through pixel (row 0, col 0) goes up and left in view space
    dv = np.asarray(cam.view)[:3, :3] @ np.asarray(d[0, 0])
    assert dv[0] < 0 and dv[1] > 0 and dv[2] < 0
    ortho = C.make_camera(
        eye, (0.0, 0.0, 0.0), (0, 1, 0), width=6, height=4, projection="orthographic"
    )
    _, d2 = C.pixel_rays(ortho)
    np.testing.assert_allclose(d2, jnp.broadcast_to(C.view_direction(ortho), d2.shape), atol=1e-9)


def test_fixed_camera_rays_are_computed_while_tracing():
    """A concrete camera closed over by jit gets its rays as constants (no matrix inverse in the
    program); a traced camera computes them in the program; both give the same rays, and the
    rays stay differentiable in the camera."""
    cam = C.make_camera((0.3, 1.0, 2.0), (0.0, 0.0, 0.0), (0, 1, 0), width=6, height=4)
    eager = C.pixel_rays(cam)
    closed = jax.jit(lambda: C.pixel_rays(cam))
    traced = jax.jit(C.pixel_rays)
    # the matrix inverse (an LU factorization, "getrf") is in the traced program only
    assert "getrf" not in closed.lower().as_text()
    assert "getrf" in traced.lower(cam).as_text()
    big = C.make_camera((0.3, 1.0, 2.0), (0.0, 0.0, 0.0), (0, 1, 0), width=600, height=500)
    assert "getrf" in jax.jit(lambda: C.pixel_rays(big)).lower().as_text()  # over 512^2: no
    for got in (closed(), traced(cam)):
        for a, b in zip(got, eager, strict=True):
            np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-7)

    def total(view):
        return jnp.sum(C.pixel_rays(dataclasses.replace(cam, view=view))[1][..., 0])

    g = jax.jit(jax.grad(total))(cam.view)
    assert float(np.abs(g).max()) > 0
    f, h = jax.jit(total), 1e-6  # central differences in float64 (the tests enable x64)
    for i, j in ((0, 0), (1, 2), (2, 3)):
        e = jnp.zeros((4, 4)).at[i, j].set(h)
        fd = (f(cam.view + e) - f(cam.view - e)) / (2 * h)
        np.testing.assert_allclose(g[i, j], fd, rtol=1e-5, atol=1e-8)


def test_float32_and_gradient():
    eye = jnp.array([0.0, 1.0, 3.0], jnp.float32)
    cam = C.make_camera(
        eye, jnp.zeros(3, jnp.float32), jnp.array([0, 1, 0], jnp.float32), width=4, height=4
    )
    assert cam.view.dtype == jnp.float32 and cam.projection.dtype == jnp.float32

    def f(e):
        v = C.look_at(e, jnp.zeros(3), jnp.array([0.0, 1.0, 0.0]))
        return jnp.sum(
            (C.perspective(50.0, 1.0, 0.1, 10.0) @ v @ jnp.array([0.2, 0.1, 0.0, 1.0])) ** 2
        )

    g = jax.grad(f)(jnp.array([0.1, 1.0, 3.0]))
    assert np.all(np.isfinite(g)) and np.abs(g).max() > 0
    jax.test_util.check_grads(f, (jnp.array([0.1, 1.0, 3.0]),), order=1, modes=("rev",))


# ROBUSTNESS row 20: bad image size, fov, near/far, singular or non-orthonormal view -> ValueError
@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(width=0, height=4), "width"),
        (dict(width=4, height=-2), "height"),
        (dict(width=4.5, height=4), "width"),
        (dict(width=4, height=4, fov_y=-10.0), "fov_y"),
        (dict(width=4, height=4, fov_y=0.0), "fov_y"),
        (dict(width=4, height=4, fov_y=180.0), "fov_y"),
        (dict(width=4, height=4, near=2.0, far=1.0), "near"),
        (dict(width=4, height=4, near=1.0, far=1.0), "near"),
        (dict(width=4, height=4, near=0.0), "near"),
        (dict(width=4, height=4, near=-1.0), "near"),
        (dict(width=4, height=4, projection="fisheye"), "projection"),
    ],
)
def test_make_camera_rejects_bad_values(kwargs, match):
    with pytest.raises(ValueError, match=match):
        C.make_camera((0, 0, 3), (0, 0, 0), (0, 1, 0), **kwargs)


def test_singular_views_rejected():
    with pytest.raises(ValueError, match="singular"):
        C.make_camera((1, 1, 1), (1, 1, 1), (0, 1, 0), width=4, height=4)
    with pytest.raises(ValueError, match="parallel"):
        C.make_camera((0, 3, 0), (0, 0, 0), (0, 1, 0), width=4, height=4)
    with pytest.raises(ValueError, match="parallel"):
        C.view_from_vrp((0, 0, 0), (0, 2, 0), (0, 1, 0))
    with pytest.raises(ValueError, match="fov"):
        C.perspective(200.0, 1.0, 0.1, 1.0)
    with pytest.raises(ValueError, match="near"):
        C.orthographic(-1, 1, -1, 1, 5.0, 1.0)
    # ortho cameras may have near <= 0
    C.make_camera(
        (0, 0, 3), (0, 0, 0), (0, 1, 0), width=4, height=4, near=-1.0, projection="orthographic"
    )


def test_camera_from_matrices_validates_view():
    proj = C.perspective(45.0, 1.0, 0.1, 10.0)
    good = C.look_at((0, 0, 3), (0, 0, 0), (0, 1, 0))
    cam = C.camera_from_matrices(good, proj, width=8, height=8, near=0.1, far=10.0)
    assert cam.width == 8
    for bad in (good.at[0, 0].mul(2.0), jnp.zeros((4, 4)), good.at[:3, :3].set(-jnp.eye(3))):
        with pytest.raises(ValueError, match="view matrix"):
            C.camera_from_matrices(bad, proj, width=8, height=8, near=0.1, far=10.0)
    with pytest.raises(ValueError, match="singular"):
        C.camera_from_matrices(good, jnp.zeros((4, 4)), width=8, height=8, near=0.1, far=10.0)
    with pytest.raises(ValueError, match="width"):
        C.camera_from_matrices(good, proj, width=0, height=8, near=0.1, far=10.0)


def test_camera_is_a_pytree_and_vmaps():
    eyes = jnp.array([[0.0, 0.0, 3.0], [1.0, 0.0, 3.0]])
    cams = jax.vmap(
        lambda e: C.make_camera(e, jnp.zeros(3), jnp.array([0.0, 1.0, 0.0]), width=4, height=4)
    )(eyes)
    assert cams.view.shape == (2, 4, 4) and cams.width == 4
    leaves, tree = jax.tree_util.tree_flatten(cams)
    assert len(leaves) == 4
