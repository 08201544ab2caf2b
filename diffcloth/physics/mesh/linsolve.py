"""Sparse direct solves of the mesh cloth's Newton systems on the host (`jax.pure_callback`): a
drape's Hessian has a stiff membrane and a soft bending part (condition numbers of 1e4-1e6),
where conjugate gradients need hundreds of iterations per Newton step and a sparse
factorization of the same system takes milliseconds. SciPy is imported on first use only. The
callback runs on the host on every backend (on a GPU the blocks travel to the host).

The system is the block-row Hessian (n, K, 3, 3) of `hessian.assemble` over the free vertices
(rows and columns of pinned vertices are the identity: `pin_rows`, or `factor(..., free=)`).

Host side, per sparsity pattern (the neighbor table and the free vertices, fixed for a mesh):
the pattern of the free-vertex system and a fill-reducing ordering of its vertices are computed
once and cached; each factorization then gathers the blocks into that permuted, symmetrised
CSC matrix and factors it with MKL's PARDISO where the `mkl` wheel is installed (the `fast`
extra; `pardiso.py`: the pattern analysed once, ~4x faster numeric factorizations and ~2x
faster solves on drape systems), else with SciPy's SuperLU in symmetric mode (no pivoting, the
ordering as given). $DIFFCLOTH_SPARSE_SOLVER = auto (the default) | pardiso | superlu picks
one. The ordering is the approximate minimum degree of `qdldl` (an optional dependency)
where it is installed, else a nested dissection of the vertex graph by breadth-first level
sets (about 1.2x the factorization time of AMD on drape meshes). On a 2,846-vertex drape
Hessian this factorization takes ~30 ms where SuperLU's own MMD_AT_PLUS_A ordering of the full
system, pinned rows included, took ~290 ms.

Threads (SuperLU; PARDISO is driven the same way): SciPy's SuperLU records each
factorization's memory with the thread that made it and frees it only from that thread; XLA
runs host callbacks on varying threads, so factors created on one and dropped on another
leaked (5-7 MB per Newton step of a 687-vertex drape, GBs per solve at 2,846 vertices). Every
factorization and eviction therefore runs on one dedicated host thread; solves run on the
calling thread, under a lock that keeps an eviction (the factors' release) from happening
during one.
"""

from __future__ import annotations

import concurrent.futures
import functools
import os
import threading

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["backend", "direct_solve", "factor", "pin_rows", "solve"]


# ------------------------------------------------------------------------------- host side

#: host-side factorizations by token: `factor` stores one and returns its token, `solve` uses it
#: (the preconditioned Krylov iterations of a Newton step factor their matrix once; a Newton
#: solve keeps one for several steps). Least recently used first: under `vmap` a lagged token
#: stays alive while its batch element solves with it (up to _KEEP / 2 elements)
_FACTORS: dict[int, object] = {}
_NEXT = [1]
_KEEP = 16
_FACTORS_LOCK = threading.Lock()  # held while a factorization is stored, used or evicted

_OWNER: list = [None, None]  # [executor, pid]
_OWNER_LOCK = threading.Lock()
_OWNER_NAME = "diffcloth-linsolve"


def _on_owner(fn, *args):
    """fn(*args) on the one thread that creates, uses and frees every SuperLU object."""
    if threading.current_thread().name.startswith(_OWNER_NAME):
        return fn(*args)
    with _OWNER_LOCK:
        if _OWNER[0] is None or _OWNER[1] != os.getpid():  # none yet, or a forked child's
            if _OWNER[0] is not None:  # the parent's factors: never freed here (other thread)
                _ORPHANS.append(dict(_FACTORS))
                _FACTORS.clear()
            _OWNER[0] = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix=_OWNER_NAME)
            _OWNER[1] = os.getpid()
        executor = _OWNER[0]
    return executor.submit(fn, *args).result()


_ORPHANS: list = []


def _level_sets(graph, start):
    from scipy.sparse.csgraph import shortest_path

    d = shortest_path(graph, unweighted=True, indices=start)
    return np.where(np.isfinite(d), d, -1).astype(np.int64)


def _nested_dissection(graph, leaf: int = 16) -> np.ndarray:
    """Fill-reducing vertex ordering of a symmetric CSR graph: nested dissection by
    breadth-first level sets (from a pseudo-peripheral vertex, the level that halves the
    vertices is the separator, ordered last). Returns perm: new position -> vertex."""
    from scipy.sparse.csgraph import connected_components

    order: list[np.ndarray] = []
    stack = [(np.arange(graph.shape[0]), False)]
    while stack:  # depth first; a (separator, True) entry is emitted after both halves
        idx, emit = stack.pop()
        if emit or len(idx) <= leaf:
            order.append(idx)
            continue
        sub = graph[idx][:, idx]
        ncomp, label = connected_components(sub, directed=False)
        if ncomp > 1:
            stack.extend((idx[label == c], False) for c in range(ncomp - 1, -1, -1))
            continue
        lv = _level_sets(sub, 0)
        lv = _level_sets(sub, int(np.argmax(lv)))  # from a pseudo-peripheral vertex
        if lv.max() < 2:
            order.append(idx)
            continue
        mid = int(np.searchsorted(np.cumsum(np.bincount(lv)), len(idx) / 2))
        mid = min(max(mid, 1), int(lv.max()) - 1)
        stack += [(idx[lv == mid], True), (idx[lv > mid], False), (idx[lv < mid], False)]
    return np.concatenate(order)


def _vertex_ordering(graph) -> np.ndarray:
    """A fill-reducing ordering (new position -> vertex) of a symmetric CSR vertex graph:
    qdldl's AMD where qdldl is installed, else `_nested_dissection`."""
    try:
        import qdldl
    except ImportError:
        return _nested_dissection(graph)
    import scipy.sparse as sp

    n = graph.shape[0]
    a = sp.triu(graph, k=1, format="csc").astype(np.float64)
    a.data[:] = 1.0
    a = (a + sp.diags(np.full(n, n + 1.0))).tocsc()  # diagonally dominant: PD, any ordering
    return np.asarray(qdldl.Solver(a, upper=True).factors()[2], np.int64)


class _Pattern:
    """The free-vertex system's permuted CSC pattern for one (neighbors, free) pair: `slot`
    maps each kept ELL entry (`ell`, flat (n K 3 3) indices) to its CSC data index, `mirror`
    each CSC entry to its transpose's, `dofs` each permuted unknown to its (n 3) index."""

    def __init__(self, nbr: np.ndarray, free: np.ndarray):
        import scipy.sparse as sp

        n, k = nbr.shape
        fv = np.flatnonzero(free)
        nf = len(fv)
        loc = np.full(n, -1, np.int64)
        loc[fv] = np.arange(nf)
        ri = np.broadcast_to(loc[:, None], (n, k))
        ci = loc[nbr]
        keep = ((ri >= 0) & (ci >= 0)).ravel()
        bi, bj = ri.ravel()[keep], ci.ravel()[keep]
        graph = sp.csr_matrix((np.ones(len(bi)), (bi, bj)), shape=(nf, nf))
        graph = (graph + graph.T).tocsr()
        graph.setdiag(0)
        graph.eliminate_zeros()
        vperm = _vertex_ordering(graph) if nf else np.zeros(0, np.int64)
        vinv = np.empty(nf, np.int64)
        vinv[vperm] = np.arange(nf)
        e3 = np.arange(3)
        rows = (vinv[bi][:, None, None] * 3 + e3[None, :, None] + 0 * e3[None, None, :]).ravel()
        cols = (vinv[bj][:, None, None] * 3 + 0 * e3[None, :, None] + e3[None, None, :]).ravel()
        self.ell = (np.flatnonzero(keep)[:, None] * 9 + np.arange(9)[None, :]).ravel()
        m = 3 * nf
        # the union of the pattern and its transpose, column-major (CSC) key order
        key = np.unique(np.concatenate([cols * m + rows, rows * m + cols]))
        self.slot = np.searchsorted(key, cols * m + rows)
        c, r = key // m, key % m
        self.mirror = np.searchsorted(key, r * m + c)
        self.indices = r.astype(np.int32)
        self.indptr = np.concatenate([[0], np.cumsum(np.bincount(c, minlength=m))]).astype(np.int32)
        self.nnz, self.size = len(key), m
        self.dofs = (fv[vperm][:, None] * 3 + e3[None, :]).ravel()
        self.pos = np.full(n, -1, np.int64)  # vertex -> its permuted position (-1: pinned)
        self.pos[fv] = vinv
        self.graph = graph[vperm][:, vperm].tocsr()  # the vertex graph, permuted
        # the upper triangle as CSR (the CSC of a symmetric matrix read as CSR), for PARDISO
        self.upper = np.flatnonzero(r >= c)
        self.upper_indptr = np.concatenate([[0], np.cumsum(np.bincount(c[self.upper],
                                                                       minlength=m))])  # fmt: skip
        self.upper_indices = r[self.upper]
        self.analyses: dict = {}  # dtype -> pardiso.Analysis of this pattern, made on first use


class _PardisoFactor:
    """One PARDISO factorization in a slot of an analysis; the slot is released with it."""

    def __init__(self, analysis, slot: int):
        self.analysis, self.slot = analysis, slot

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        return self.analysis.solve(self.slot, rhs)

    def __del__(self):
        self.analysis.release(self.slot)


def _pardiso_factor(pat: _Pattern | None, a, dtype):
    """PARDISO's factorization of the symmetric CSC matrix a: in a slot of the pattern's own
    analysis (pat given: a has its pattern), else of a one-off analysis; None if it fails."""
    from . import pardiso

    single = dtype == np.float32
    if pat is not None:
        analysis = pat.analyses.get(single)
        if analysis is None:
            analysis = pardiso.Analysis(pat.upper_indptr, pat.upper_indices, pat.size, single,
                                        slots=_KEEP + 1)  # fmt: skip
            pat.analyses[single] = analysis
        data = a.data[pat.upper]
    else:
        import scipy.sparse as sp

        up = sp.triu(a, format="csr")
        up.sort_indices()
        analysis = pardiso.Analysis(up.indptr, up.indices, a.shape[0], single)
        data = up.data
    slot = analysis.factor(data)
    return None if slot is None else _PardisoFactor(analysis, slot)


def backend() -> str:
    """The host factorization the next `factor` uses: "pardiso" or "superlu".
    Shapes: none (reads the environment and whether MKL loads)."""
    return "pardiso" if _use_pardiso() else "superlu"


def _use_pardiso() -> bool:
    """PARDISO where MKL loads and $DIFFCLOTH_SPARSE_SOLVER is not "superlu" ("auto",
    the default, or "pardiso": then a missing MKL is an error)."""
    from . import pardiso

    choice = os.environ.get("DIFFCLOTH_SPARSE_SOLVER", "auto").lower()
    if choice not in ("auto", "pardiso", "superlu"):
        raise ValueError(f"DIFFCLOTH_SPARSE_SOLVER={choice!r}: use auto, pardiso or superlu")
    if choice == "pardiso" and not pardiso.available():
        raise RuntimeError("DIFFCLOTH_SPARSE_SOLVER=pardiso, but MKL's PARDISO does not load in "
                           "this process: pip install 'diffcloth[fast]' (x86_64)")  # fmt: skip
    return choice != "superlu" and pardiso.available()


@functools.lru_cache(maxsize=8)
def _pattern(nbr_bytes: bytes, free_bytes: bytes, n: int, k: int) -> _Pattern:
    nbr = np.frombuffer(nbr_bytes, np.int32).reshape(n, k)
    return _Pattern(nbr, np.frombuffer(free_bytes, np.bool_))


def _coupled(pat: _Pattern, a, idx, w, core):
    """The system a (permuted CSC) plus the pair couplings w_k w_l core between vertices idx_k
    and idx_l (k != l; the diagonal blocks are in a already), reordered for the new pattern:
    (matrix, dofs)."""
    import scipy.sparse as sp

    live = np.any(core != 0, axis=(1, 2))
    idx, w, core = idx[live], w[live].astype(np.float64), core[live].astype(np.float64)
    k, l = np.nonzero(~np.eye(4, dtype=bool))  # the 12 off-diagonal slots
    bi, bj = pat.pos[idx[:, k]].ravel(), pat.pos[idx[:, l]].ravel()
    blk = ((w[:, k] * w[:, l])[:, :, None, None] * core[:, None]).reshape(-1, 3, 3)
    ok = (bi >= 0) & (bj >= 0)  # pinned rows and columns stay the identity
    bi, bj, blk = bi[ok], bj[ok], blk[ok]
    e3 = np.arange(3)
    rows = (bi[:, None, None] * 3 + e3[None, :, None] + 0 * e3[None, None, :]).ravel()
    cols = (bj[:, None, None] * 3 + 0 * e3[None, :, None] + e3[None, None, :]).ravel()
    m, nv = pat.size, pat.size // 3
    a = (a + sp.csc_matrix((blk.ravel(), (rows, cols)), shape=(m, m))).tocsc()
    g = sp.csr_matrix((np.ones(len(bi)), (bi, bj)), shape=(nv, nv))
    g = (pat.graph + g + g.T).tocsr()
    g.setdiag(0)
    g.eliminate_zeros()
    vperm = _vertex_ordering(g)  # the contacts join distant vertices: order again
    perm = (vperm[:, None] * 3 + e3[None, :]).ravel()
    return a[perm][:, perm].tocsc(), pat.dofs[perm]


def _factor_now(h: np.ndarray, nbr: np.ndarray, free: np.ndarray, *couplings) -> int:
    import scipy.sparse as sp
    import scipy.sparse.linalg as spl

    n, k = nbr.shape
    pat = _pattern(nbr.tobytes(), free.tobytes(), n, k)
    vals = h.reshape(-1)[pat.ell].astype(np.float64)
    data = np.bincount(pat.slot, weights=vals, minlength=pat.nnz)
    data = 0.5 * (data + data[pat.mirror])  # symmetric part (float32 assembly is not exact)
    # factored in the system's own precision: float32 halves the factor's memory traffic (a
    # 2,846-vertex drape: ~0.7x the float64 time); the Krylov iterations it preconditions, on
    # the exact Hessian, make up for its rounding
    dtype = np.float32 if h.dtype == np.float32 else np.float64
    data = data.astype(dtype)
    dofs = pat.dofs
    lu = None
    if pat.size and np.all(np.isfinite(data)):
        a = sp.csc_matrix((data, pat.indices, pat.indptr), shape=(pat.size, pat.size))
        # (no pair in contact: the plain pattern, its analysis kept)
        coupled = bool(couplings) and np.all(np.isfinite(couplings[2])) and np.any(couplings[2])
        if coupled:
            a, dofs = _coupled(pat, a, *couplings)
        a = a.astype(dtype)
        if _use_pardiso():
            lu = _pardiso_factor(None if coupled else pat, a, dtype)
        else:
            try:
                lu = spl.splu(a, permc_spec="NATURAL", diag_pivot_thresh=0.0,
                              options={"SymmetricMode": True})  # fmt: skip
            except RuntimeError:  # singular
                lu = None
    elif not pat.size:
        lu = "identity"
    with _FACTORS_LOCK:
        token = _NEXT[0]
        _NEXT[0] += 1
        _FACTORS[token] = (lu, pat.size, dofs, dtype)
        while len(_FACTORS) > _KEEP:
            _FACTORS.pop(next(iter(_FACTORS)))
    return token


def _solve_now(token: int, rhs: np.ndarray) -> np.ndarray:
    # on the calling thread (a solve allocates nothing that outlives it; the hop to the owner
    # thread cost 0.35-0.7 ms per call, 15-30 % of a 2,846-vertex drape's solve), under the
    # lock that eviction takes: the factorization is never dropped, so never freed, here
    with _FACTORS_LOCK:
        entry = _FACTORS.pop(token, None)
        if entry is None:
            return np.full(rhs.shape, np.nan, rhs.dtype)
        _FACTORS[token] = entry  # most recently used last: eviction drops the least recent
        lu, size, dofs, dtype = entry
        del entry
        if lu is None:
            return np.full(rhs.shape, np.nan, rhs.dtype)
        z = rhs.astype(dtype).reshape(-1)  # pinned rows: the identity
        if size:
            z[dofs] = lu.solve(z[dofs])
        del lu
    return z.reshape(rhs.shape).astype(rhs.dtype)


def _host_factor(h, nbr, free, *couplings):
    h = np.asarray(h)
    nbr = np.ascontiguousarray(np.asarray(nbr, np.int32))
    free = np.ascontiguousarray(np.asarray(free, np.bool_))
    couplings = tuple(np.asarray(c) for c in couplings)
    return np.asarray(_on_owner(_factor_now, h, nbr, free, *couplings), np.int32)


def _host_solve(token, rhs):
    return _solve_now(int(np.asarray(token)), np.asarray(rhs))


# ------------------------------------------------------------------------------- JAX side


def factor(h, neighbors, free=None, couplings=None):
    """Factor the block-row matrix h (n, K, 3, 3) on the host; returns a token (int32 scalar)
    for `solve`. free (n,) bool: the system is over these vertices only (the others' rows and
    columns are the identity; default all). couplings: None, or (idx (P, 4) int, w (P, 4),
    core (P, 3, 3)) adding the block w_k w_l core between vertices idx_k and idx_l for k != l
    (self-contact pairs, which join vertices that are not mesh neighbours; rows with a zero
    core are skipped): such a system is ordered again on each factorization. Tokens stay valid
    while used (the 16 most recently made or used are kept)."""
    if free is None:
        free = jnp.ones(h.shape[0], bool)
    out = jax.ShapeDtypeStruct((), jnp.int32)
    extra = () if couplings is None else tuple(couplings)
    return jax.pure_callback(_host_factor, out, h, neighbors, free, *extra,
                             vmap_method="sequential")  # fmt: skip


def solve(token, rhs):
    """Solve with a factorization from `factor`: rhs (n, 3) -> (n, 3) (NaN if it was singular)."""
    out = jax.ShapeDtypeStruct(rhs.shape, rhs.dtype)
    return jax.pure_callback(_host_solve, out, token, rhs, vmap_method="sequential")


def pin_rows(h, neighbors, free):
    """Replace the rows and columns of pinned vertices by the identity. h: (n, K, 3, 3)."""
    keep = free[:, None] & free[neighbors]  # (n, K)
    h = jnp.where(keep[:, :, None, None], h, 0.0)
    eye = jnp.eye(3, dtype=h.dtype)
    return h.at[:, 0].add(jnp.where(free[:, None, None], 0.0, eye))


def direct_solve(h, neighbors, rhs, free=None):
    """Solve H z = rhs once (H: (n, K, 3, 3) block rows with `neighbors`; rhs (n, 3))."""
    return solve(factor(h, neighbors, free), rhs)


def _cg(apply_a, b, precond, iters: int, rtol: float, fall_back=None):
    """Preconditioned conjugate gradients for A z = b (A symmetric), stopping at a relative
    residual rtol, after `iters`, or at a direction of non-positive curvature (then ok is
    False unless some progress was made). fall_back: None, or a () bool: where True, at
    non-positive curvature the preconditioner's own step M^-1 b is returned (ok True) instead
    of the partial iterate. Returns (z, ok, iterations)."""
    bnorm = jnp.sqrt(jnp.vdot(b, b))

    def cond(c):
        z, r, p, rz, k, ok, done, _ = c
        return (~done) & (k < iters)

    def body(c):
        z, r, p, rz, k, ok, done, neg_seen = c
        ap = apply_a(p)
        pap = jnp.vdot(p, ap)
        neg = pap <= 0
        alpha = rz / jnp.where(neg, 1.0, pap)
        z_new = jnp.where(neg, z, z + alpha * p)
        r_new = jnp.where(neg, r, r - alpha * ap)
        s = precond(r_new)
        rz_new = jnp.vdot(r_new, s)
        beta = rz_new / jnp.where(rz == 0, 1.0, rz)
        p_new = s + beta * p
        conv = jnp.sqrt(jnp.vdot(r_new, r_new)) <= rtol * bnorm
        ok_new = jnp.where(neg, k > 0, ok)
        return z_new, r_new, p_new, rz_new, k + 1, ok_new, done | neg | conv, neg_seen | neg

    s0 = precond(b)
    init = (jnp.zeros_like(b), b, s0, jnp.vdot(b, s0), 0, jnp.array(True), bnorm == 0,
            jnp.array(False))  # fmt: skip
    z, _, _, _, k, ok, _, neg = jax.lax.while_loop(cond, body, init)
    if fall_back is not None:
        swap = neg & fall_back
        z, ok = jnp.where(swap, s0, z), ok | swap
    return z, ok, k


def _block_jacobi(diag_blocks, free):
    """Preconditioner r -> D^-1 r from (n, 3, 3) diagonal blocks (identity where singular)."""
    eye = jnp.eye(3, dtype=diag_blocks.dtype)
    scale = jnp.maximum(jnp.trace(diag_blocks, axis1=1, axis2=2), 1e-30)[:, None, None]
    inv = jnp.linalg.inv(diag_blocks / scale + 1e-10 * eye[None]) / scale
    inv = jnp.where(free[:, None, None], inv, 0.0)
    return lambda r: jnp.einsum("nab,nb->na", inv, r)
