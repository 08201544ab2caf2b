"""The mesh cloth's host-side sparse solves (`diffcloth.physics.mesh.linsolve`): solutions
against a dense solve, pinned rows as the identity, failed factorizations as NaN, fill-reducing
orderings, and no memory kept by factorizations that callbacks on other threads dropped (SciPy's
SuperLU frees a factorization's memory only from the thread that made it: factors made and
evicted on varying threads leaked GBs per drape solve)."""

from __future__ import annotations

import os
import platform
import sys
import threading

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcloth.physics.mesh import linsolve, pardiso


def require_pardiso() -> None:
    """Fail where MKL's PARDISO should load and does not (x86_64 Linux: the test extra installs
    mkl); skip on platforms the `fast` extra does not cover."""
    if pardiso.available():
        return
    if sys.platform.startswith("linux") and platform.machine() == "x86_64":
        pytest.fail("MKL's PARDISO does not load: pip install -e '.[test]' installs mkl")
    pytest.skip("MKL is not installed for this platform (the fast extra is x86_64 only)")


@pytest.fixture(autouse=True, params=["superlu", "pardiso"])
def backend(request, monkeypatch):
    """Every test here runs with each host factorization: SciPy SuperLU and MKL PARDISO."""
    monkeypatch.delenv("DIFFCLOTH_SPARSE_SOLVER", raising=False)
    if request.param == "pardiso":
        require_pardiso()
    monkeypatch.setenv("DIFFCLOTH_SPARSE_SOLVER", request.param)
    return request.param


def _grid_system(side: int, seed: int = 0):
    """A block-row SPD matrix on a side x side grid (8-neighbourhood): h (n, 9, 3, 3),
    neighbors (n, 9) (self first, padded with self), and the same matrix as a SciPy CSR."""
    import scipy.sparse as sp

    n = side * side
    r, c = np.divmod(np.arange(n), side)
    nbr = np.repeat(np.arange(n)[:, None], 9, axis=1)
    offsets = [(a, b) for a in (-1, 0, 1) for b in (-1, 0, 1) if (a, b) != (0, 0)]
    for k, (a, b) in enumerate(offsets, start=1):
        inside = (r + a >= 0) & (r + a < side) & (c + b >= 0) & (c + b < side)
        nbr[inside, k] = ((r + a) * side + c + b)[inside]
    rng = np.random.default_rng(seed)
    real = (nbr != np.arange(n)[:, None]) & (np.arange(9) > 0)
    h = np.where(real[:, :, None, None], -0.1 * rng.random((n, 9, 3, 3)), 0.0)
    rows = np.arange(n)[:, None, None, None] * 3 + np.arange(3)[:, None] + 0 * nbr[:, :, None, None]
    cols = nbr[:, :, None, None] * 3 + np.arange(3)[None, :]
    rows, cols = np.broadcast_arrays(rows, cols)
    low = sp.csr_matrix((h.ravel(), (rows.ravel(), cols.ravel())), shape=(3 * n, 3 * n))
    low = sp.tril(low, k=-1)  # one random triangle, mirrored: symmetric
    a = (low + low.T).tocsr()
    a = (a + sp.diags(np.asarray(abs(a).sum(axis=1)).ravel() + 1.0)).tocsr()  # SPD
    for k in range(9):
        for i3 in range(3):
            for j3 in range(3):
                h[:, k, i3, j3] = np.where(
                    real[:, k] | (k == 0), a[np.arange(n) * 3 + i3, nbr[:, k] * 3 + j3].A1, 0.0
                )
    return h, nbr.astype(np.int32), a


def test_direct_solve_matches_dense():
    h, nbr, a = _grid_system(6)
    dense = a.toarray()
    n = nbr.shape[0]
    rhs = np.random.default_rng(1).standard_normal((n, 3))
    z = linsolve.direct_solve(jnp.asarray(h), jnp.asarray(nbr), jnp.asarray(rhs))
    want = np.linalg.solve(dense, rhs.reshape(-1)).reshape(n, 3)
    np.testing.assert_allclose(np.asarray(z), want, rtol=1e-9, atol=1e-12)


def test_pinned_rows_are_the_identity():
    h, nbr, a = _grid_system(6)
    dense = a.toarray()
    n = nbr.shape[0]
    free = np.ones(n, bool)
    free[[0, 7, 20]] = False
    rhs = np.random.default_rng(2).standard_normal((n, 3))
    z = np.asarray(linsolve.direct_solve(jnp.asarray(h), jnp.asarray(nbr), jnp.asarray(rhs),
                                         jnp.asarray(free)))  # fmt: skip
    fd = np.repeat(free, 3)
    want = rhs.reshape(-1).copy()
    want[fd] = np.linalg.solve(dense[np.ix_(fd, fd)], rhs.reshape(-1)[fd])
    np.testing.assert_allclose(z.reshape(-1), want, rtol=1e-9, atol=1e-12)
    # the same as pin_rows' identity rows over every vertex
    hp = linsolve.pin_rows(jnp.asarray(h), jnp.asarray(nbr), jnp.asarray(free))
    z2 = linsolve.direct_solve(hp, jnp.asarray(nbr), jnp.asarray(rhs))
    np.testing.assert_allclose(np.asarray(z2), z, rtol=1e-9, atol=1e-12)


def test_failed_factorization_solves_to_nan():
    h, nbr, _ = _grid_system(4)
    h[3, 0] = np.nan
    rhs = jnp.ones((nbr.shape[0], 3))
    z = linsolve.direct_solve(jnp.asarray(h), jnp.asarray(nbr), rhs)
    assert np.all(np.isnan(np.asarray(z)))


def test_nested_dissection_is_a_permutation_with_less_fill():
    import scipy.sparse as sp
    import scipy.sparse.linalg as spl

    _, nbr, a = _grid_system(40)
    n = nbr.shape[0]
    rows = np.repeat(np.arange(n), nbr.shape[1])
    graph = sp.csr_matrix((np.ones(rows.size), (rows, nbr.ravel())), shape=(n, n))
    graph = (graph + graph.T).tocsr()
    graph.setdiag(0)
    graph.eliminate_zeros()
    perm = linsolve._nested_dissection(graph)
    assert np.array_equal(np.sort(perm), np.arange(n))

    def fill(p):
        dofs = (p[:, None] * 3 + np.arange(3)).ravel()
        lu = spl.splu(a[dofs][:, dofs].tocsc(), permc_spec="NATURAL", diag_pivot_thresh=0.0,
                      options={"SymmetricMode": True})  # fmt: skip
        return lu.L.nnz + lu.U.nnz

    assert fill(perm) < 0.75 * fill(np.arange(n))  # row by row: a band of 3 (side + 1)


@pytest.mark.skipif(not os.path.exists("/proc/self/status"), reason="reads VmRSS from /proc")
def test_factors_dropped_on_other_threads_are_freed():
    """60 factorizations (~3 MB each), each made and solved from a new thread's call, the
    16-deep cache evicting older ones on the way: the process must not grow by their size."""
    h, nbr, _ = _grid_system(30)
    n = nbr.shape[0]
    hj, nj = jnp.asarray(h), jnp.asarray(nbr)
    fn = jax.jit(lambda h, r: linsolve.solve(linsolve.factor(h, nj), r))
    rhs = jnp.ones((n, 3))

    def rss_mb() -> float:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmRSS"):
                    return int(line.split()[1]) / 1024
        raise RuntimeError("no VmRSS")

    def call(i):
        jax.block_until_ready(fn(hj * (1.0 + 1e-3 * i), rhs))

    def run(count, start):
        for i in range(start, start + count):
            t = threading.Thread(target=call, args=(i,))
            t.start()
            t.join()

    run(24, 0)  # warm-up: compile, the pattern, a full cache, the allocator's pools
    before = rss_mb()
    run(60, 100)
    grown = rss_mb() - before
    assert grown < 60, f"RSS grew by {grown:.0f} MB over 60 factorizations"


def test_a_token_in_use_outlives_newer_factorizations():
    """Eviction drops the least recently used factorization: a Newton solve that keeps its
    token for several steps (and, under vmap, a batch element's lagged token) stays valid
    while newer ones come and go; an unused one is dropped."""
    h, nbr, a = _grid_system(3)
    free = np.ones(nbr.shape[0], bool)
    rhs = np.random.default_rng(2).standard_normal((nbr.shape[0], 3))
    want = np.linalg.solve(a.toarray(), rhs.reshape(-1)).reshape(rhs.shape)
    kept = linsolve._on_owner(linsolve._factor_now, h, nbr, free)
    dropped = linsolve._on_owner(linsolve._factor_now, h, nbr, free)
    for _ in range(3 * linsolve._KEEP):
        linsolve._on_owner(linsolve._factor_now, h, nbr, free)
        z = linsolve._on_owner(linsolve._solve_now, kept, rhs)
        np.testing.assert_allclose(z, want, rtol=1e-9, atol=1e-12)
    assert np.all(np.isnan(linsolve._on_owner(linsolve._solve_now, dropped, rhs)))


def test_pair_couplings_join_distant_vertices():
    """`factor(..., couplings=)` adds the blocks w_k w_l core (k != l) between the vertices of
    each pair, outside the mesh's pattern; pinned rows stay the identity; zero cores are
    skipped; the result equals a dense solve of the coupled matrix."""
    h, nbr, a = _grid_system(6)
    n = nbr.shape[0]
    rng = np.random.default_rng(2)
    idx = np.stack([rng.choice(n, 4, replace=False) for _ in range(5)]).astype(np.int32)
    w = rng.uniform(-1.0, 1.0, (5, 4))
    u = rng.standard_normal((5, 3))
    core = 0.5 * u[:, :, None] * u[:, None, :]  # PSD, rank one
    core[4] = 0.0  # a padding row
    free = np.ones(n, bool)
    free[[0, 7]] = False
    dense = a.toarray()
    for p in range(5):
        for k in range(4):
            for m in range(4):
                if k != m:
                    i, j = idx[p, k], idx[p, m]
                    dense[3 * i : 3 * i + 3, 3 * j : 3 * j + 3] += w[p, k] * w[p, m] * core[p]
    fdof = np.repeat(free, 3)
    dense[~fdof, :] = 0.0
    dense[:, ~fdof] = 0.0
    dense[~fdof, ~fdof] = 1.0
    rhs = rng.standard_normal((n, 3))
    tok = linsolve.factor(jnp.asarray(h), jnp.asarray(nbr), jnp.asarray(free),
                          (jnp.asarray(idx), jnp.asarray(w), jnp.asarray(core)))  # fmt: skip
    z = linsolve.solve(tok, jnp.asarray(rhs))
    want = np.linalg.solve(dense, rhs.reshape(-1)).reshape(n, 3)
    np.testing.assert_allclose(np.asarray(z), want, rtol=1e-9, atol=1e-12)
