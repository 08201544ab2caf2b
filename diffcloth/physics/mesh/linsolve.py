"""Sparse direct solves of the mesh cloth's Newton systems, on the host through SciPy's SuperLU
(`jax.pure_callback`): a drape's Hessian has a stiff membrane and a soft bending part (condition
numbers of 1e4-1e6), where conjugate gradients need hundreds of iterations per Newton step and a
sparse LU factorization of the same system takes tens of milliseconds. SciPy is imported on first
use only. The callback runs on the host on every backend (on a GPU the blocks travel to the host).

Threads: SciPy's SuperLU records each factorization's memory with the thread that made it and
frees it only from that thread; XLA runs host callbacks on varying threads, so factors created
on one and dropped (evicted) on another leaked (5-7 MB per Newton step of a 687-vertex drape,
GBs per solve at 2,846 vertices). Every factorization, solve and eviction therefore runs on one
dedicated host thread.

The system is the block-row Hessian (n, K, 3, 3) of `hessian.assemble`, with the rows and
columns of pinned vertices replaced by the identity.
"""

from __future__ import annotations

import concurrent.futures
import functools
import os
import threading

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["direct_solve", "factor", "pin_rows", "solve"]


@functools.lru_cache(maxsize=16)
def _structure(nbr_bytes: bytes, n: int, k: int):
    """CSR pattern of the block-row matrix, and for each ELL entry its CSR data index."""
    nbr = np.frombuffer(nbr_bytes, np.int32).reshape(n, k)
    rows = np.arange(n)[:, None, None, None] * 3 + np.arange(3)[None, None, :, None]
    cols = nbr[:, :, None, None] * 3 + np.arange(3)[None, None, None, :]
    rows = np.broadcast_to(rows, (n, k, 3, 3)).ravel()
    cols = np.broadcast_to(cols, (n, k, 3, 3)).ravel()
    key = rows.astype(np.int64) * (3 * n) + cols
    uniq, inverse = np.unique(key, return_inverse=True)
    r, c = uniq // (3 * n), uniq % (3 * n)
    indptr = np.concatenate([[0], np.cumsum(np.bincount(r, minlength=3 * n))])
    return inverse.astype(np.int64), c.astype(np.int32), indptr.astype(np.int32), len(uniq)


#: host-side factorizations by token: `factor` stores one and returns its token, `solve` uses it
#: (the preconditioned Krylov iterations of a Newton step factor their matrix once)
_FACTORS: dict[int, object] = {}
_NEXT = [1]
_KEEP = 16

_OWNER: list = [None, None]  # [executor, pid]
_OWNER_LOCK = threading.Lock()
_OWNER_NAME = "diffcloth-linsolve"
_ORPHANS: list = []  # a forked child's copy of its parent's factors (never freed there)


def _on_owner(fn, *args):
    """fn(*args) on the one thread that creates, uses and frees every SuperLU object."""
    if threading.current_thread().name.startswith(_OWNER_NAME):
        return fn(*args)
    with _OWNER_LOCK:
        if _OWNER[0] is None or _OWNER[1] != os.getpid():  # none yet, or a forked child's
            if _OWNER[0] is not None:
                _ORPHANS.append(dict(_FACTORS))
                _FACTORS.clear()
            _OWNER[0] = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix=_OWNER_NAME)
            _OWNER[1] = os.getpid()
        executor = _OWNER[0]
    return executor.submit(fn, *args).result()


def _host_factor(h, nbr):
    h = np.asarray(h)
    nbr = np.ascontiguousarray(np.asarray(nbr, np.int32))
    return np.asarray(_on_owner(_factor_now, h, nbr), np.int32)


def _factor_now(h, nbr):
    import scipy.sparse as sp
    import scipy.sparse.linalg as spl

    n, k = nbr.shape
    inverse, indices, indptr, nnz = _structure(nbr.tobytes(), n, k)
    data = np.bincount(inverse, weights=h.reshape(-1).astype(np.float64), minlength=nnz)
    a = sp.csc_matrix((data, indices, indptr), shape=(3 * n, 3 * n))  # symmetric: CSR^T = CSC
    try:
        lu = spl.splu(a, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                      options={"SymmetricMode": True})  # fmt: skip
    except RuntimeError:  # singular
        lu = None
    token = _NEXT[0]
    _NEXT[0] += 1
    _FACTORS[token] = lu
    while len(_FACTORS) > _KEEP:
        _FACTORS.pop(next(iter(_FACTORS)))
    return token


def _host_solve(token, rhs):
    return _on_owner(_solve_now, int(np.asarray(token)), np.asarray(rhs))


def _solve_now(token, rhs):
    lu = _FACTORS.get(token)
    if lu is None:
        return np.full(rhs.shape, np.nan, rhs.dtype)
    z = lu.solve(rhs.astype(np.float64).reshape(-1))
    return z.reshape(rhs.shape).astype(rhs.dtype)


def factor(h, neighbors):
    """Factor the block-row matrix h (n, K, 3, 3) on the host; returns a token (int32 scalar)
    for `solve`. Tokens stay valid for the next 16 factorizations."""
    out = jax.ShapeDtypeStruct((), jnp.int32)
    return jax.pure_callback(_host_factor, out, h, neighbors, vmap_method="sequential")


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


def direct_solve(h, neighbors, rhs):
    """Solve H z = rhs once (H: (n, K, 3, 3) block rows with `neighbors`; rhs (n, 3))."""
    return solve(factor(h, neighbors), rhs)


def _cg(apply_a, b, precond, iters: int, rtol: float):
    """Preconditioned conjugate gradients for A z = b (A symmetric), stopping at a relative
    residual rtol, after `iters`, or at a direction of non-positive curvature (then ok is
    False unless some progress was made). Returns (z, ok, iterations)."""
    bnorm = jnp.sqrt(jnp.vdot(b, b))

    def cond(c):
        z, r, p, rz, k, ok, done = c
        return (~done) & (k < iters)

    def body(c):
        z, r, p, rz, k, ok, done = c
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
        return z_new, r_new, p_new, rz_new, k + 1, ok_new, done | neg | conv

    s0 = precond(b)
    init = (jnp.zeros_like(b), b, s0, jnp.vdot(b, s0), 0, jnp.array(True), bnorm == 0)
    z, _, _, _, k, ok, _ = jax.lax.while_loop(cond, body, init)
    return z, ok, k


def _block_jacobi(diag_blocks, free):
    """Preconditioner r -> D^-1 r from (n, 3, 3) diagonal blocks (identity where singular)."""
    eye = jnp.eye(3, dtype=diag_blocks.dtype)
    scale = jnp.maximum(jnp.trace(diag_blocks, axis1=1, axis2=2), 1e-30)[:, None, None]
    inv = jnp.linalg.inv(diag_blocks / scale + 1e-10 * eye[None]) / scale
    inv = jnp.where(free[:, None, None], inv, 0.0)
    return lambda r: jnp.einsum("nab,nb->na", inv, r)
