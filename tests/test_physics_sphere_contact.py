"""The sphere contact with the hand-written VJP (physics/sphere_contact.py) has the values of the
autodiff form (projection with `_direction_planar`, then `collide._impact_contact`) and its
reverse-mode derivative with respect to every input, in float64 to rounding and in float32 to
float32 rounding, on nodes in every case: outside, inside from the start, hitting during the
substep, approaching and lifting off, sliding and sticking, pinned, at the centre."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcloth.physics.collide import _direction_planar, _finite_points, _impact_contact
from diffcloth.physics.sphere_contact import sphere_impact

SHAPE = (6, 8)


def _reference(x, v, xs, vs, c, vel, r, free, f, h):
    """collide's sphere branch, written with plain JAX (autodiff derivative)."""
    cb, velb = c[:, None, None], vel[:, None, None]
    dist, nrm = _direction_planar(x - cb)
    inside = (dist < r) & free & _finite_points(x)
    x = jnp.where(inside[None], cb + r * nrm, x)
    d0 = _direction_planar(xs - (cb - velb * h))[0] - r
    return _impact_contact(x, v, vs, velb, nrm, inside, d0, dist - r, f, h)


def _case(dtype):
    """Nodes around a unit-ish sphere with every contact case present."""
    rng = np.random.default_rng(7)
    c = np.array([0.1, -0.2, 0.05])
    r = 0.5
    h = 1 / 480
    direction = rng.normal(size=(3, *SHAPE))
    direction /= np.linalg.norm(direction, axis=0)
    radius_now = rng.uniform(0.4, 0.6, SHAPE)  # about half inside
    x = c[:, None, None] + radius_now * direction
    radius_before = radius_now + rng.uniform(-0.05, 0.08, SHAPE)  # some started inside
    xs = c[:, None, None] + radius_before * direction
    v = rng.normal(size=(3, *SHAPE))
    v[:, :, :3] -= 2.0 * direction[:, :, :3]  # approaching
    v[:, 0, 4:6] = -0.8 * direction[:, 0, 4:6] + 1e-3 * rng.normal(size=(3, 2))  # sticking
    vs = v - rng.normal(scale=0.3, size=(3, *SHAPE))  # the kick of the substep
    free = np.ones(SHAPE, bool)
    free[0, 0] = free[-1, -1] = False
    x[:, 2, 2] = c  # a node at the centre: +y fallback normal
    vel = np.array([0.05, -0.1, 0.02])
    as_ = lambda a: jnp.asarray(a, dtype)
    args = (as_(x), as_(v), as_(xs), as_(vs), as_(c), as_(vel), as_(r), jnp.asarray(free))
    return args + (as_(0.4), as_(h))


def _cotangents(dtype):
    rng = np.random.default_rng(11)
    return tuple(jnp.asarray(rng.normal(size=(3, *SHAPE)), dtype) for _ in range(2))


def _vjps(fn, args, cot):
    diff = [0, 1, 2, 3, 4, 5, 6, 8, 9]  # every input but the free mask

    def f(*d):
        full = list(args)
        for i, a in zip(diff, d, strict=True):
            full[i] = a
        return fn(*full)

    out, pull = jax.vjp(f, *(args[i] for i in diff))
    return out, pull(cot)


@pytest.fixture(scope="module")
def both64():
    with jax.enable_x64(True):
        args, cot = _case(jnp.float64), _cotangents(jnp.float64)
        ref = _vjps(_reference, args, cot)
        hand = _vjps(sphere_impact, args, cot)
        yield args, ref, hand


def test_cases_covered(both64):
    args, (out, _), _ = both64
    x, v, xs, vs, c, vel, r = args[:7]
    cb = c[:, None, None]
    dist = jnp.linalg.norm(x - cb, axis=0)
    inside = dist < r
    moved = jnp.any(out[1] != v, axis=0)
    assert inside.sum() >= 10 and (~inside).sum() >= 10
    assert moved.sum() >= 8  # approaching nodes whose velocity the contact changed
    before = jnp.linalg.norm(xs - cb + vel[:, None, None] * args[9], axis=0)
    assert ((before < r) & inside).any() and ((before > r) & inside).any()


def test_values_equal_reference(both64):
    _, (ref, _), (hand, _) = both64
    with jax.enable_x64(True):
        for a, b in zip(hand, ref, strict=True):
            assert a.dtype == jnp.float64
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-13, atol=1e-14)


def test_vjp_equals_autodiff_float64(both64):
    _, (_, g_ref), (_, g_hand) = both64
    names = ("x", "v", "x_start", "v_start", "center", "velocity", "radius", "friction", "h")
    for name, a, b in zip(names, g_hand, g_ref, strict=True):
        assert np.abs(np.asarray(b)).max() > 0, name
        np.testing.assert_allclose(
            np.asarray(a), np.asarray(b), rtol=1e-9, atol=1e-11, err_msg=name
        )


@pytest.mark.slow  # ~19 s; the float64 VJP test stays in the default suite
def test_vjp_equals_autodiff_float32():
    args, cot = _case(jnp.float32), _cotangents(jnp.float32)
    (ref, g_ref), (hand, g_hand) = _vjps(_reference, args, cot), _vjps(sphere_impact, args, cot)
    for a, b in zip(hand, ref, strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=2e-6, atol=2e-6)
    for a, b in zip(g_hand, g_ref, strict=True):
        scale = float(np.abs(np.asarray(b)).max())
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-4, atol=1e-5 * scale)


def test_only_differentiated_inputs_get_cotangents():
    """A fit of the cloth alone (x, v, ...) does not pay for the sphere's cotangents: they are
    symbolic zeros in, and the compiled backward has fewer reductions."""
    args, cot = _case(jnp.float32), _cotangents(jnp.float32)

    def loss_x(x):
        xo, vo = sphere_impact(x, *args[1:])
        return jnp.sum(xo * cot[0] + vo * cot[1])

    def loss_all(x, f):
        xo, vo = sphere_impact(x, *args[1:8], f, args[9])
        return jnp.sum(xo * cot[0] + vo * cot[1])

    hlo_x = jax.jit(jax.grad(loss_x)).lower(args[0]).compile().as_text()
    hlo_all = jax.jit(jax.grad(loss_all, argnums=(0, 1))).lower(args[0], args[8]).compile()
    assert hlo_x.count(" reduce(") < hlo_all.as_text().count(" reduce(")
    np.testing.assert_allclose(
        jax.grad(loss_x)(args[0]), jax.grad(loss_all, argnums=(0, 1))(args[0], args[8])[0]
    )
