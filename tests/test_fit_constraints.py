"""Parameter transforms (ROBUSTNESS row 4: physical values stay positive and finite)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcloth.fit.constraints import (
    Bounded,
    Identity,
    Positive,
    make_constraint,
    make_constraints,
    to_physical,
    to_raw,
)

POSITIVE = [Positive(), Positive(kind="softplus"), Positive(kind="softplus", scale=10.0)]


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
@pytest.mark.parametrize("con", POSITIVE, ids=str)
def test_positive_for_any_raw(con, dtype):
    raw = jnp.linspace(-1e3, 1e3, 4001, dtype=dtype)
    phys, grad = jax.jit(
        lambda r: (to_physical({"k": r}, {"k": con})["k"], jax.vmap(jax.grad(con.forward))(r))
    )(raw)
    assert phys.dtype == dtype
    assert bool(jnp.all(phys > 0)) and bool(jnp.all(jnp.isfinite(phys)))
    assert bool(jnp.all(jnp.isfinite(grad)))
    # monotone: non-decreasing up to float rounding in the saturated tails, strictly inside
    assert bool(jnp.all(jnp.diff(phys) >= -1e-5 * phys[1:]))
    mid = jnp.linspace(-20.0, 20.0, 101, dtype=dtype)
    assert bool(jnp.all(jnp.diff(con.forward(mid)) > 0))


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_bounded_stays_in_range(dtype):
    con = Bounded(0.0, 2.0)
    raw = jnp.linspace(-1e3, 1e3, 4001, dtype=dtype)
    phys, grad = jax.jit(lambda r: (con.forward(r), jax.vmap(jax.grad(con.forward))(r)))(raw)
    assert bool(jnp.all(phys > 0)) and bool(jnp.all(phys <= 2.0))
    assert bool(jnp.all(jnp.isfinite(grad)))


@pytest.mark.parametrize(
    "con,value",
    [
        (Positive(), 1234.5),
        (Positive(), 1e-4),
        (Positive(kind="softplus"), 0.01),
        (Positive(kind="softplus"), 300.0),
        (Positive(lower=1.0), 3.0),
        (Bounded(-1.0, 3.0), 2.5),
        (Identity(), -7.0),
    ],
    ids=str,
)
def test_round_trip(con, value):
    raw = to_raw({"p": value}, {"p": con})
    back = to_physical(raw, {"p": con})["p"]
    np.testing.assert_allclose(float(back), value, rtol=1e-10)


def test_log_space_gradient_is_relative():
    # d physical / d raw = physical for the log transform (the point of optimising in log space)
    g = jax.grad(Positive().forward)(jnp.log(50.0))
    np.testing.assert_allclose(float(g), 50.0, rtol=1e-12)


def test_arrays_and_dtype_kept():
    x = jnp.array([0.5, 2.0, 8.0], dtype=jnp.float32)
    raw = to_raw({"c": x}, {"c": "positive"})
    assert raw["c"].dtype == jnp.float32 and raw["c"].shape == (3,)
    np.testing.assert_allclose(np.asarray(to_physical(raw, {"c": "positive"})["c"]), x, rtol=1e-6)


def test_out_of_range_inverse_raises():
    with pytest.raises(ValueError, match=r"stretch=-1.0 .*Positive"):
        to_raw({"stretch": -1.0}, {"stretch": Positive()})
    with pytest.raises(ValueError, match=r"damping=1.5 .*\(0.0, 1.0\)"):
        to_raw({"damping": 1.5}, {"damping": Bounded(0.0, 1.0)})
    with pytest.raises(ValueError, match=r"x=nan is outside"):
        to_raw({"x": float("nan")}, {"x": Positive()})


def test_bad_specs_raise():
    with pytest.raises(ValueError, match="lo < hi"):
        Bounded(1.0, 1.0)
    with pytest.raises(ValueError, match="kind"):
        Positive(kind="exp")
    with pytest.raises(ValueError, match="not one of"):
        make_constraint("postive")
    with pytest.raises(ValueError, match=r"unknown parameters \['bend'\]"):
        make_constraints(["stretch"], {"bend": "positive"})


def test_make_constraint_specs():
    assert make_constraint("log") == Positive()
    assert make_constraint("softplus") == Positive(kind="softplus")
    assert make_constraint((0, 1)) == Bounded(0.0, 1.0)
    assert make_constraint({"lo": 2, "hi": 5}) == Bounded(2.0, 5.0)
    assert make_constraint({"kind": "softplus", "scale": 3}) == Positive("softplus", 3.0)
    assert make_constraint(None) == Identity()
    # hashable, so they can be static arguments of jit
    assert len({Positive(), Positive(), Bounded(0, 1)}) == 2
