"""The "impact" contact with the per-node Jacobian derivative (physics/contact_jac.py) has the values
of plain `collide._impact_contact` exactly and its derivatives (reverse and forward mode) to
rounding, in float64, on nodes in every case: outside, already in contact, hitting during the
substep, approaching and lifting off, sliding and sticking."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcloth.physics.collide import _contact, _impact_contact


@pytest.fixture(scope="module")
def case():
    with jax.enable_x64(True):
        rng = np.random.default_rng(3)
        shape = (5, 7)
        f = lambda *s: jnp.asarray(rng.normal(size=s), jnp.float64)
        nrm = f(3, *shape)
        nrm = nrm / jnp.linalg.norm(nrm, axis=0, keepdims=True)
        d1 = jnp.asarray(rng.uniform(-0.02, 0.01, shape))
        d0 = jnp.asarray(rng.uniform(-0.01, 0.03, shape))
        args = dict(
            x=f(3, *shape),
            v=f(3, *shape),
            v_start=f(3, *shape),
            vel=0.1 * f(3, 1, 1),
            nrm=nrm,
            d0=d0,
            d1=d1,
            friction=jnp.float64(0.3),
            h=jnp.float64(1 / 480),
        )
        inside = d1 < 0
        yield args, inside


def _ref(a, inside):
    return _impact_contact(**{**a, "inside": inside})


def _fast(a, inside):
    return _contact(**{**a, "inside": inside})


def _cases(inside):
    """The fixture covers every branch the derivative passes through."""
    return inside.any() and (~inside).any()


def test_values_equal_plain_rule(case):
    a, inside = case
    with jax.enable_x64(True):
        assert _cases(inside)
        for r, f in zip(_ref(a, inside), _fast(a, inside), strict=True):
            assert r.dtype == jnp.float64
            np.testing.assert_array_equal(np.asarray(f), np.asarray(r))


@pytest.mark.slow  # ~14 s; the default FD test checks the same gradients
def test_vjp_and_jvp_equal_autodiff(case):
    a, inside = case
    with jax.enable_x64(True):
        rng = np.random.default_rng(4)
        cot = tuple(jnp.asarray(rng.normal(size=(3,) + inside.shape)) for _ in range(2))
        _, vjp_ref = jax.vjp(lambda p: _ref(p, inside), a)
        _, vjp_fast = jax.vjp(lambda p: _fast(p, inside), a)
        g_ref, g_fast = vjp_ref(cot)[0], vjp_fast(cot)[0]
        for k in a:
            assert np.abs(np.asarray(g_ref[k])).max() > 0 or k == "h", k
            np.testing.assert_allclose(g_fast[k], g_ref[k], rtol=1e-10, atol=1e-12, err_msg=k)
        tan = {k: jnp.asarray(rng.normal(size=np.shape(v))) for k, v in a.items()}
        _, t_ref = jax.jvp(lambda p: _ref(p, inside), (a,), (tan,))
        _, t_fast = jax.jvp(lambda p: _fast(p, inside), (a,), (tan,))
        for r, f in zip(t_ref, t_fast, strict=True):
            np.testing.assert_allclose(f, r, rtol=1e-10, atol=1e-12)


def test_gradient_matches_central_differences(case):
    """AD of the fast rule against central FD of its own values (float64)."""
    a, inside = case
    with jax.enable_x64(True):
        w = jnp.asarray(np.random.default_rng(5).normal(size=(2, 3) + inside.shape))

        def loss(p):
            x, v = _fast(p, inside)
            return jnp.sum(w[0] * x) + jnp.sum(w[1] * v)

        g = jax.grad(loss)(a)
        for k in ("friction", "h"):
            eps = 1e-6 * float(a[k])
            fd = (loss({**a, k: a[k] + eps}) - loss({**a, k: a[k] - eps})) / (2 * eps)
            np.testing.assert_allclose(float(g[k]), float(fd), rtol=1e-6, err_msg=k)
        # a node coordinate away from the branch switches
        d = jnp.zeros_like(a["v"]).at[1, 2, 3].set(1e-6)
        fd = (loss({**a, "v": a["v"] + d}) - loss({**a, "v": a["v"] - d})) / 2e-6
        np.testing.assert_allclose(float(g["v"][1, 2, 3]), float(fd), rtol=1e-6)


def test_gradient_of_some_inputs_equals_autodiff(case):
    """Inputs held constant (h, friction, vel: symbolic-zero tangents) are left out of the
    Jacobian; the gradient of the others equals plain autodiff's (float64)."""
    a, inside = case
    with jax.enable_x64(True):
        w = jnp.asarray(np.random.default_rng(6).normal(size=(2, 3) + inside.shape))
        live = ("x", "v", "nrm", "d1")

        def loss(rule, p):
            x, v = rule({**a, **p}, inside)
            return jnp.sum(w[0] * x) + jnp.sum(w[1] * v)

        p = {k: a[k] for k in live}
        g_ref = jax.grad(lambda q: loss(_ref, q))(p)
        g = jax.jit(jax.grad(lambda q: loss(_fast, q)))(p)
        for k in live:
            assert np.abs(np.asarray(g_ref[k])).max() > 0, k
            np.testing.assert_allclose(g[k], g_ref[k], rtol=1e-10, atol=1e-12, err_msg=k)
