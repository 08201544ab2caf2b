"""Property-based tests (hypothesis) of the geometry and shading functions.

Every function under test is jitted once at module level with fixed small shapes; hypothesis
draws array *values* only, so nothing recompiles per example. Runs are derandomized (fixed seed,
no example database) so CI is reproducible.
"""

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from diffcloth import _math as M
from diffcloth import physics
from diffcloth.render import camera as C
from diffcloth.render import lights as Lm
from diffcloth.render import shade as S
from diffcloth.render import textures as T
from diffcloth.render.rays import ray_sphere
from diffcloth.shapes import Sphere
from diffcloth.surface import basis as B
from diffcloth.surface import tessellate

PROPERTY = settings(max_examples=30, deadline=None, derandomize=True, database=None)
F64 = jnp.float64


def floats(lo, hi):
    return st.floats(lo, hi, allow_nan=False, allow_infinity=False)


def arrays(shape, lo=-1.0, hi=1.0, special=()):
    """float64 arrays of a fixed shape; `special` values (e.g. exact zeros) are drawn often."""
    elems = floats(lo, hi)
    if special:
        elems = st.one_of(st.sampled_from(special), elems)
    return hnp.arrays(np.float64, shape, elements=elems)


def rotation(q):
    """Rotation matrix of a (non-normalised) quaternion."""
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


QUATERNIONS = arrays((4,), -1.0, 1.0).filter(lambda q: np.linalg.norm(q) > 0.2)


def all_finite(tree):
    return all(bool(np.all(np.isfinite(np.asarray(x)))) for x in jax.tree_util.tree_leaves(tree))


# ----------------------------------------------------------------------------- safe math


SPECIAL = (0.0, -0.0, 1e-300, -1e-300, 1e-30, 1e-12, -1e-7, 1.0)


@jax.jit
def _safe_all(x, y, v, k):
    def values(x, y, v):
        return (
            M.safe_sqrt(x),
            M.safe_norm(v),
            M.safe_normalize(v),
            M.safe_div(y, x),
            M.safe_pow(jnp.abs(x), k),
            M.safe_atan2(y, x),
        )

    def total(x, y, v):
        return sum(jnp.sum(jnp.sin(o)) for o in values(x, y, v))

    return values(x, y, v), jax.grad(total, argnums=(0, 1, 2))(x, y, v)


@PROPERTY
@given(
    arrays((8,), -1e3, 1e3, SPECIAL),
    arrays((8,), -1e3, 1e3, SPECIAL),
    arrays((8, 3), -10.0, 10.0, SPECIAL),
    floats(-3.0, 3.0),
)
def test_safe_functions_finite_with_finite_gradients_everywhere(x, y, v, k):
    vals, grads = _safe_all(x, y, v, k)
    assert all_finite(vals) and all_finite(grads)
    sqrt, norm, unit, _, _, _ = (np.asarray(a) for a in vals)
    np.testing.assert_allclose(sqrt, np.sqrt(np.maximum(x, 0.0)), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(norm, np.linalg.norm(v, axis=-1), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(np.linalg.norm(unit, axis=-1), 1.0, atol=1e-12)


# ----------------------------------------------------------------------------- splines


@PROPERTY
@given(
    st.sampled_from(B.BASES),
    st.lists(floats(0.0, 1.0), min_size=4, max_size=4),
)
def test_basis_partition_of_unity_nonnegative_and_derivatives_sum_to_zero(basis, ts):
    n = 7 if basis != "bspline" else 6
    t = np.asarray(ts) * B.num_patches(n, basis)
    w = B.basis_matrix(n, t, basis)
    np.testing.assert_allclose(w.sum(1), 1.0, atol=1e-13)
    assert np.all(w >= -1e-15)
    np.testing.assert_allclose(B.basis_matrix(n, t, basis, 1).sum(1), 0.0, atol=1e-11)


_TESS = jax.jit(lambda net: tessellate(net, 3))
GRID = np.stack([*np.meshgrid(np.arange(5.0), np.arange(4.0)), np.zeros((4, 5))], -1)


@PROPERTY
@given(
    arrays((4, 5, 3), -1.0, 1.0),
    arrays((3, 3), -0.4, 0.4),
    arrays((3,), -2.0, 2.0),
    QUATERNIONS,
    floats(0.5, 2.0),
)
def test_tessellation_is_affine_invariant(net, a, b, q, scale):
    """tess(A net + b) = A tess(net) + b; under a rotation and uniform scale the frames rotate."""
    net = GRID + 0.3 * net  # a generic, non-degenerate net
    affine = np.eye(3) + a
    base = _TESS(jnp.asarray(net))
    moved = _TESS(jnp.asarray(net @ affine.T + b))
    np.testing.assert_allclose(
        moved.positions, np.asarray(base.positions) @ affine.T + b, atol=1e-10
    )
    rot = scale * rotation(q)
    turned = _TESS(jnp.asarray(net @ rot.T + b))
    r = rotation(q)
    for name in ("normals", "tangents", "bitangents"):
        np.testing.assert_allclose(
            getattr(turned, name), np.asarray(getattr(base, name)) @ r.T, atol=1e-9
        )


# ----------------------------------------------------------------------------- physics forces

_NET = physics.grid_net(4, 4, (0.6, 0.6), dtype=F64)
_MAT = physics.make_material(stretch=50.0, shear=20.0, bend=0.1, damping=0.3, dtype=F64)
_FORCES = jax.jit(lambda x, v: physics.internal_forces(_NET, _MAT, x, v))


@PROPERTY
@given(
    arrays((4, 4, 3), -0.1, 0.1, (0.0,)),
    arrays((4, 4, 3), -1.0, 1.0),
    QUATERNIONS,
    arrays((3,), -5.0, 5.0),
)
def test_internal_forces_invariant_under_rigid_motion_and_sum_to_zero(dx, v, q, shift):
    x = np.asarray(_NET.rest) + dx
    r = rotation(q)
    f = np.asarray(_FORCES(jnp.asarray(x), jnp.asarray(v)))
    f_moved = np.asarray(_FORCES(jnp.asarray(x @ r.T + shift), jnp.asarray(v @ r.T)))
    assert np.all(np.isfinite(f))
    scale = 1.0 + np.abs(f).max()
    np.testing.assert_allclose(f_moved, f @ r.T, atol=1e-10 * scale)
    np.testing.assert_allclose(f.sum(axis=(0, 1)), 0.0, atol=1e-10 * scale)


# ----------------------------------------------------------------------------- rays, cameras

_RAY = jax.jit(
    lambda o, d, c, r: (
        ray_sphere(o, d, c, r),
        jax.grad(lambda c, r: jnp.sum(ray_sphere(o, d, c, r)[0] * 1e-10), argnums=(0, 1))(c, r),
    )
)
DIRECTIONS = arrays((16, 3), -1.0, 1.0).filter(lambda d: np.linalg.norm(d, axis=-1).min() > 0.1)


@PROPERTY
@given(arrays((16, 3), -3.0, 3.0), DIRECTIONS, arrays((3,), -1.0, 1.0), floats(0.05, 2.0))
def test_ray_sphere_hits_lie_on_the_sphere_in_front(o, d, c, r):
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    (t, hit, disc), grads = _RAY(jnp.asarray(o), jnp.asarray(d), jnp.asarray(c)[None], r)
    t, hit, disc = np.asarray(t), np.asarray(hit), np.asarray(disc)
    assert np.all(np.isfinite(t)) and np.all(np.isfinite(disc)) and all_finite(grads)
    p = o + t[:, None] * d
    np.testing.assert_allclose(np.linalg.norm(p[hit] - c, axis=-1), r, rtol=1e-9, atol=1e-9)
    assert np.all(t[hit] > 0)
    # a miss: the line passes outside, or the whole sphere is behind the origin
    oc = o - c
    b = np.sum(oc * d, -1)
    behind = (b > 0) & (np.sum(oc * oc, -1) > r * r)
    assert np.all(((disc <= 1e-12) | behind)[~hit])


_PROJECT_ROUND_TRIP = jax.jit(
    lambda p, cam: (
        C.project(p, cam),
        jnp.linalg.inv(cam.projection @ cam.view),
    )
)


@PROPERTY
@given(
    arrays((3,), -5.0, 5.0),
    arrays((3,), -1.0, 1.0),
    arrays((8, 3), -2.0, 2.0),
    st.sampled_from(["perspective", "orthographic"]),
)
def test_project_then_unproject_returns_the_point(eye, target, points, kind):
    eye = eye + np.array([0.0, 0.0, 6.0])  # at least a few metres from the targets
    forward = (target - eye) / np.linalg.norm(target - eye)
    cam = C.make_camera(eye, target, (0.0, 1.0, 0.0), width=8, height=8, projection=kind)
    (clip, depth), inv = _PROJECT_ROUND_TRIP(jnp.asarray(points), cam)
    clip, depth = np.asarray(clip), np.asarray(depth)
    np.testing.assert_allclose(depth, (points - eye) @ forward, rtol=1e-10, atol=1e-10)
    ndc = clip[:, :3] / clip[:, 3:]
    back = np.concatenate([ndc, np.ones((8, 1))], 1) @ np.asarray(inv).T
    np.testing.assert_allclose(back[:, :3] / back[:, 3:], points, rtol=1e-8, atol=1e-8)


# ----------------------------------------------------------------------------- shading

N_PIX = 8
MODES = S.MODES
_TEXTURES = T.default_textures(size=16, threads=4, dtype=F64)
_SPHERES = Sphere(jnp.asarray([[0.0, 1.5, 0.0], [1.0, 0.0, 1.0]]), jnp.asarray([0.5, 0.3]))
_POS = jnp.asarray(np.linspace(-0.5, 0.5, N_PIX * 3).reshape(1, N_PIX, 3))
_UV = jnp.asarray(np.linspace(0.05, 0.95, N_PIX * 2).reshape(1, N_PIX, 2))
AMBIENT, INTENSITY = 0.2, 1.0


def _cases(modes):
    """(mode, refraction) pairs: reflect_refract with both refraction models."""
    return [
        (m, r)
        for m in modes
        for r in (("shortened", "snell") if m == "reflect_refract" else ("shortened",))
    ]


def _shade_all(modes, normal, tangent, eyes, light_dir, k, ior, shininess):
    lights = Lm.make_lights(
        ambient=(AMBIENT,) * 3, directional=[((0.0, 1.0, 0.0), (1.0, 1.0, 1.0), INTENSITY)]
    )
    lights = dataclasses.replace(lights, direction=light_dir[None])
    app = Lm.make_appearance(dtype=F64)
    app = dataclasses.replace(app, minnaert_k=k, ior=ior, shininess=shininess)
    gb = S.ShadingBuffer(
        position=_POS,
        normal=normal,
        tangent=tangent,
        bitangent=jnp.cross(normal, tangent),
        uv=_UV,
        mask=jnp.ones((1, N_PIX), F64),
        face_normal=normal,
        color=S.light_vertices(_POS[0], normal[0], eyes[0, 0] + _POS[0, 0], lights, app)[None],
    )
    return jnp.stack(
        [
            S.shade(
                gb, eyes, lights, app, mode=m, textures=_TEXTURES, spheres=_SPHERES, refraction=r
            )
            for m, r in _cases(modes)
        ]
    )


@functools.partial(jax.jit, static_argnums=0)
def _shade_and_grad(modes, *args):
    images = _shade_all(modes, *args)
    loss = lambda *a: jnp.sum(jnp.sin(_shade_all(modes, *a)))
    return images, jax.grad(loss, argnums=tuple(range(7)))(*args)


UNIT_OR_ZERO = arrays((1, N_PIX, 3), -1.0, 1.0, (0.0,))
SHADING_INPUTS = st.tuples(
    UNIT_OR_ZERO,  # normals (exact zeros drawn often)
    UNIT_OR_ZERO,  # tangents
    UNIT_OR_ZERO,  # per-pixel vectors toward the eye
    arrays((3,), -1.0, 1.0).filter(lambda d: np.linalg.norm(d) > 0.1),  # toward the light
    st.one_of(st.just(0.05), st.just(2.0), floats(0.05, 2.0)),  # Minnaert k
    floats(0.5, 2.0),  # ior (> 1: total internal reflection happens)
    floats(1.0, 64.0),  # shininess
    st.booleans(),  # exactly perpendicular light, grazing eye, a zero normal
)


def _check_shading(modes, normal, tangent, eyes, light, k, ior, shininess, degenerate):
    """Random (and zero, perpendicular, grazing) normals, tangents, view and light directions."""
    if degenerate:  # normal exactly perpendicular to the light, eye exactly grazing
        light = np.array([1.0, 0.0, 0.0])
        normal = np.broadcast_to([0.0, 1.0, 0.0], normal.shape).copy()
        normal[0, 0] = 0.0  # one zero-length normal
        eyes = np.broadcast_to([0.0, 0.0, 1.0], eyes.shape).copy()
    args = [jnp.asarray(a, F64) for a in (normal, tangent, eyes, light, k, ior, shininess)]
    images, grads = _shade_and_grad(modes, *args)
    images = np.asarray(images)
    assert np.all(np.isfinite(images)), "non-finite colour"
    assert all_finite(grads), "non-finite gradient"
    rgb = images[..., :3]
    assert rgb.min() >= -1e-12, "negative colour"
    # documented range: ambient + lights (+ specular); Minnaert may brighten at grazing angles by
    # at most MINNAERT_EPS^(k - 1) for k < 1 (cosines clamped before pow)
    bound = AMBIENT + INTENSITY * (1.0 + 1.0) + 1.0
    minnaert = AMBIENT + INTENSITY * max(1.0, T.MINNAERT_EPS ** (k - 1.0)) * 1.01
    for i, (mode, _) in enumerate(_cases(modes)):
        limit = minnaert if mode.startswith("minnaert") else bound
        assert rgb[i].max() <= limit, f"{mode}: {rgb[i].max()} > {limit}"


@pytest.mark.slow  # keeps the default suite under 10 min; runs with -m slow
@settings(PROPERTY, max_examples=20)
@given(SHADING_INPUTS)
def test_shading_modes_finite_bounded_with_finite_gradients(inputs):
    """The common modes (default run); every mode: the slow test below."""
    _check_shading(("phong", "minnaert", "reflect_refract"), *inputs)


@pytest.mark.slow
@settings(PROPERTY, max_examples=20)
@given(SHADING_INPUTS)
def test_every_shading_mode_finite_bounded_with_finite_gradients(inputs):
    _check_shading(MODES, *inputs)


@functools.partial(jax.jit, static_argnames="snell")
def _refract_and_grad(e, n, eta, snell=True):
    if snell:
        f = lambda e, n, eta: S.refract(-e, n, eta)
    else:
        f = lambda e, n, eta: S.refract_shortened(e, n, eta)
    return f(e, n, eta), jax.grad(lambda *a: jnp.sum(jnp.sin(f(*a))), argnums=(0, 1, 2))(e, n, eta)


@PROPERTY
@given(DIRECTIONS, DIRECTIONS, floats(0.3, 2.5))
def test_refract_is_unit_snell_or_mirror(e, n, eta):
    """Snell: unit result; sin_t = eta sin_i where it exists, else (total internal reflection) the
    mirror direction; finite gradients at and past the critical angle. Energy: |t| = 1 always."""
    e = e / np.linalg.norm(e, axis=-1, keepdims=True)
    n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    t, grads = _refract_and_grad(jnp.asarray(e), jnp.asarray(n), eta)
    t = np.asarray(t)
    assert np.all(np.isfinite(t)) and all_finite(grads)
    np.testing.assert_allclose(np.linalg.norm(t, axis=-1), 1.0, atol=1e-12)
    cos_i = np.sum(e * n, -1)
    sin_i = np.linalg.norm(np.cross(e, n), axis=-1)
    sin_t = np.linalg.norm(np.cross(t, n), axis=-1)
    tir = eta * sin_i > 1
    ok = ~tir & (eta * sin_i < 1 - 1e-6)
    np.testing.assert_allclose(sin_t[ok], eta * sin_i[ok], atol=1e-9)
    mirror = -e + 2 * cos_i[:, None] * n
    np.testing.assert_allclose(
        t[tir & (eta * sin_i > 1 + 1e-6)], mirror[tir & (eta * sin_i > 1 + 1e-6)], atol=1e-9
    )
    # the seed's shortened-normal refraction: unit and finite for any s
    t2, g2 = _refract_and_grad(jnp.asarray(e), jnp.asarray(n), eta - 0.3, snell=False)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(t2), axis=-1), 1.0, atol=1e-12)
    assert all_finite(g2)


_MINNAERT = jax.jit(
    lambda nl, ne, k: (
        S.minnaert_factor(nl, ne, k),
        jax.grad(lambda a, b, k: jnp.sum(S.minnaert_factor(a, b, k)), argnums=(0, 1, 2))(nl, ne, k),
    )
)


@PROPERTY
@given(
    arrays((16,), -1.0, 1.0, (0.0, -0.0, 1e-300, 1.0)),
    arrays((16,), -1.0, 1.0, (0.0, 1e-300, 1.0)),
    st.one_of(st.just(2.0), floats(1e-3, 2.0)),
)
def test_minnaert_factor_finite_for_k_in_0_2(nl, ne, k):
    """pow(0, k - 1) is inf for k < 1: cosines are clamped to MINNAERT_EPS first."""
    f, grads = _MINNAERT(jnp.asarray(nl), jnp.asarray(ne), k)
    f = np.asarray(f)
    assert np.all(np.isfinite(f)) and all_finite(grads)
    assert np.all(f > 0)
    assert f.max() <= T.MINNAERT_EPS ** (2 * min(k - 1.0, 0.0)) * (1 + 1e-12)
    if k == 1.0:
        np.testing.assert_allclose(f, 1.0)
