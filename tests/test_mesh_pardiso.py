"""MKL PARDISO behind the mesh cloth's host solves (`diffcloth.physics.mesh.pardiso`, chosen by
`linsolve` where MKL loads; tests/test_mesh_linsolve.py runs each of its checks with PARDISO and
with SuperLU): the backend setting, slot reuse, float32 solves, a drape-sized equilibrium that
agrees with SuperLU's."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_mesh_linsolve import _grid_system, require_pardiso

from diffcloth.physics.mesh import linsolve


@pytest.fixture
def pardiso_on(monkeypatch):
    require_pardiso()
    monkeypatch.setenv("DIFFCLOTH_SPARSE_SOLVER", "pardiso")


def test_the_backend_setting_is_checked(monkeypatch):
    h, nbr, _ = _grid_system(3)
    monkeypatch.setenv("DIFFCLOTH_SPARSE_SOLVER", "cholmod")
    with pytest.raises(ValueError, match="DIFFCLOTH_SPARSE_SOLVER='cholmod': use auto"):
        linsolve._factor_now(h, nbr, np.ones(nbr.shape[0], bool))


def test_pardiso_slots_are_reused_and_solve_in_both_precisions(pardiso_on):
    """PARDISO keeps up to _KEEP + 1 factorizations per analysed pattern: evicted tokens give
    their slot back (hundreds of factorizations never run out of slots), and its solves match
    a dense solve in float64, and in float32 to float32 rounding."""
    h, nbr, a = _grid_system(8)
    free = np.ones(nbr.shape[0], bool)
    rhs = np.random.default_rng(3).standard_normal((nbr.shape[0], 3))
    want = np.linalg.solve(a.toarray(), rhs.reshape(-1)).reshape(rhs.shape)
    for _ in range(4 * linsolve._KEEP):
        tok = linsolve._on_owner(linsolve._factor_now, h, nbr, free)
    np.testing.assert_allclose(linsolve._solve_now(tok, rhs), want, rtol=1e-9, atol=1e-12)
    tok32 = linsolve._on_owner(linsolve._factor_now, h.astype(np.float32), nbr, free)
    z32 = linsolve._solve_now(tok32, rhs.astype(np.float32))
    assert z32.dtype == np.float32
    np.testing.assert_allclose(z32, want, rtol=2e-4, atol=2e-5)


def test_an_equilibrium_is_the_same_with_either_factorization(monkeypatch):
    """The factorization only preconditions the Newton-Krylov steps and the adjoint: a float64
    hanging sheet's equilibrium and its gradient agree between PARDISO and SuperLU to the
    solver's tolerance."""
    require_pardiso()
    from diffcloth.physics import mesh as pm

    cloth = pm.make_cloth(pm.rectangle(0.2, 0.2, 0.02), pinned="top_edge", dtype=jnp.float64)
    fabric = pm.make_fabric("wang2011-gray-interlock", dtype=jnp.float64)
    g = jnp.asarray([0.0, -9.81, 0.0])

    def sag(fab):
        res = pm.equilibrium(
            cloth, fab, cloth.rest, gravity=g, settings=pm.SolverSettings(tol=1e-9)
        )
        return jnp.mean(res.x[:, 1]), res

    fn = jax.jit(jax.value_and_grad(sag, has_aux=True))
    out = {}
    for name in ("superlu", "pardiso"):
        monkeypatch.setenv("DIFFCLOTH_SPARSE_SOLVER", name)
        (_, res), grad = fn(fabric)
        assert bool(res.converged), name
        out[name] = (np.asarray(res.x), grad)
    np.testing.assert_allclose(out["pardiso"][0], out["superlu"][0], rtol=0, atol=1e-9)
    leaves = [jax.tree.leaves(out[name][1]) for name in ("pardiso", "superlu")]
    for a, b in zip(*leaves, strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6, atol=1e-12)
