"""Gauss-Newton / Fisher identifiability on analytic problems."""

import jax.numpy as jnp
import numpy as np
import pytest

from diffcloth.fit.identifiability import format_identifiability, identifiability

X = jnp.linspace(0.0, 1.0, 25)


def confounded(p):
    """Only the product a*b is visible."""
    return p["a"] * p["b"] * X - 2.0 * X


def separable(p):
    """a and b act on nearly orthogonal features."""
    return (
        p["a"] * jnp.sin(6.0 * X)
        + p["b"] * jnp.cos(6.0 * X)
        - (2.0 * jnp.sin(6.0 * X) + 0.5 * jnp.cos(6.0 * X))
    )


def test_confounded_pair_is_flagged():
    rep = identifiability(confounded, {"a": 1.0, "b": 2.0}, noise_sigma=0.01)
    assert rep.names == ["a", "b"]
    assert [(a, b) for a, b, _ in rep.confounded] == [("a", "b")]
    assert rep.confounded[0][2] == pytest.approx(-1.0, abs=1e-4)
    assert rep.identifiable == {"a": False, "b": False}
    assert not np.isfinite(rep.condition_number)
    assert np.isinf(rep.std).all()
    assert len(rep.sloppy) == 1 and set(rep.sloppy[0]["params"]) == {"a", "b"}
    md = format_identifiability(rep)
    assert "**a** and **b** are confounded" in md and "near-null direction" in md


def test_separable_parameters_are_identifiable():
    sigma = 0.01
    rep = identifiability(separable, {"a": 2.0, "b": 0.5}, noise_sigma=sigma)
    assert rep.confounded == [] and rep.sloppy == []
    assert rep.identifiable == {"a": True, "b": True}
    assert np.isfinite(rep.condition_number) and rep.condition_number < 100
    # linear least squares: cov = sigma^2 (A^T A)^-1 exactly
    a = np.stack([np.sin(6.0 * np.asarray(X)), np.cos(6.0 * np.asarray(X))], axis=1)
    expected = sigma * np.sqrt(np.diag(np.linalg.inv(a.T @ a)))
    np.testing.assert_allclose(rep.std, expected, rtol=1e-8)
    np.testing.assert_allclose(rep.relative_std, expected / np.array([2.0, 0.5]), rtol=1e-8)
    assert "All parameters are identifiable" in format_identifiability(rep)


def test_raw_space_matches_log_of_physical():
    p = {"a": 2.0, "b": 0.5}
    phys = identifiability(separable, p, noise_sigma=0.01)
    raw = identifiability(
        separable, p, {"a": "positive", "b": "positive"}, space="raw", noise_sigma=0.01
    )
    # std of log(p) = std(p) / p (delta method, exact for the linearisation)
    np.testing.assert_allclose(raw.std, phys.std / np.array([2.0, 0.5]), rtol=1e-8)
    np.testing.assert_allclose(raw.relative_std, phys.relative_std, rtol=1e-8)
    np.testing.assert_allclose(raw.correlation, phys.correlation, atol=1e-10)


def test_array_parameter_names_and_json():
    def res(p):
        return p["c"][None, :] * X[:, None] - jnp.array([1.0, 2.0])[None, :] * X[:, None]

    rep = identifiability(res, {"c": jnp.array([1.0, 2.0])})
    assert rep.names == ["c[0]", "c[1]"]
    d = rep.to_dict()
    assert set(d["params"]) == {"c[0]", "c[1]"} and d["confounded"] == []


def test_bad_arguments():
    with pytest.raises(ValueError, match="space"):
        identifiability(separable, {"a": 1.0, "b": 1.0}, space="log")
    with pytest.raises(ValueError, match="noise_sigma"):
        identifiability(separable, {"a": 1.0, "b": 1.0}, noise_sigma=0.0)
