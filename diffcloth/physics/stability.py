"""Explicit stability estimates for the symplectic integrator, for both force models (eager).

Symplectic Euler on one damped mode x'' = -lam x - g x' (lam: eigenvalue of M^-1 K, g: its damping
rate) is stable for h^2 lam + 2 h g <= 4, i.e. h <= (sqrt(g^2 + 4 lam) - g) / lam.

- `modal_substep` finds lam for the stiffest mode of the forces linearised at rest (Lanczos on
  M^-1/2 K M^-1/2 over the free nodes, K = -df/dx by forward-mode AD, so it holds for any force
  model) and g as that mode's Rayleigh quotient of M^-1/2 C M^-1/2 (C = -df/dv); likewise for the
  most damped mode; the smaller limit wins. Tight: within a few % of where the runs blow up.
- `node_substeps` is the cheap per-node Gershgorin bound: node mass against the springs actually
  attached to it (off-diagonal terms to pinned nodes dropped) plus its damping terms.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from diffcloth.physics.forces import _total_forces, autodiff_forces, node_mass
from diffcloth.physics.material import Material
from diffcloth.physics.net import Net


def _continuum_rows(net: Net, material: Material) -> tuple[np.ndarray, np.ndarray]:
    """Per-node Gershgorin row sums of the continuum model's stiffness (N/m) at rest and of its
    non-Rayleigh damping (N s/m, normal drag of the node's area); pinned neighbours eliminated."""
    R, C = net.rows, net.cols
    free = (~np.asarray(net.pinned)).astype(np.float64)
    kh = np.asarray(material.stretch * net.weight_h, np.float64)
    kv = np.asarray(material.stretch * net.weight_v, np.float64)
    kd = np.asarray(material.shear * net.weight_d, np.float64)
    row = np.zeros((R, C))
    # (per-spring stiffness, slices of end a, slices of end b, pads back onto a, pads back onto b)
    sets = (
        (kh, np.s_[:, :-1], np.s_[:, 1:], ((0, 0), (0, 1)), ((0, 0), (1, 0))),
        (kv, np.s_[:-1, :], np.s_[1:, :], ((0, 1), (0, 0)), ((1, 0), (0, 0))),
        (kd, np.s_[:-1, :-1], np.s_[1:, 1:], ((0, 1), (0, 1)), ((1, 0), (1, 0))),
        (kd, np.s_[:-1, 1:], np.s_[1:, :-1], ((0, 1), (1, 0)), ((1, 0), (0, 1))),
    )
    for k, sa, sb, pa, pb in sets:
        row += np.pad(k * (1.0 + free[sb]), pa) + np.pad(k * (1.0 + free[sa]), pb)
    # bend triplet (a, b, c) of weight w: w [1, -2, 1]^T [1, -2, 1]
    bh = np.asarray(material.bend * net.weight_bh, np.float64)
    bv = np.asarray(material.bend * net.weight_bv, np.float64)
    for b, axis in ((bh, 1), (bv, 0)):
        n = free.shape[axis]
        f = [np.take(free, range(s, s + n - 2), axis=axis) for s in range(3)]
        terms = (1.0 + 2.0 * f[1] + f[2], 4.0 + 2.0 * f[0] + 2.0 * f[2], 1.0 + 2.0 * f[1] + f[0])
        for shift, t in enumerate(terms):
            pad = [(0, 0), (0, 0)]
            pad[axis] = (shift, 2 - shift)
            row += np.pad(b * t, pad)
    drag = float(np.asarray(material.drag_normal)) * np.asarray(net.area, np.float64)
    return row, drag


def node_substeps(net: Net, material) -> np.ndarray:
    """Per-node explicit stability limit (rows, cols), s (inf at pinned nodes), eager.

    Node i has Gershgorin bound lam_i = K_i / m_i on the eigenvalues of M^-1 K (K_i: the row sum
    of the stiffness matrix at rest over the springs actually attached to node i, off-diagonal
    terms to pinned nodes dropped) and a damping rate g_i = D_i / m_i. Symplectic Euler on
    x'' = -lam x - g x' is stable for h^2 lam + 2 h g <= 4, so h_i = (sqrt(g^2 + 4 lam) - g) / lam.
    Continuum model: g_i = damping * lam_i (Rayleigh) + normal drag of the node's area / m_i.
    Mass-spring model: D_i = Gershgorin row of the dashpots + air damping.
    """
    from diffcloth.physics.massspring import MassSpring, node_rows

    mass = np.asarray(node_mass(net, material), np.float64)
    free = ~np.asarray(net.pinned)
    if isinstance(material, MassSpring):
        krow, drow = node_rows(net, material)
        lam = krow / mass
        g = drow / mass
    else:
        krow, drag = _continuum_rows(net, material)
        lam = krow / mass
        g = float(np.asarray(material.damping)) * lam + drag / mass
    with np.errstate(divide="ignore", invalid="ignore"):
        h = np.where(lam > 0, (np.sqrt(g * g + 4.0 * lam) - g) / np.where(lam > 0, lam, 1.0), 0.0)
        h = np.where(lam > 0, h, np.where(g > 0, 2.0 / np.where(g > 0, g, 1.0), np.inf))
    return np.where(free, h, np.inf)


def _limit(lam, g):
    """Stable substep (s) of one mode with stiffness rate lam (1/s^2) and damping rate g (1/s)."""
    if lam <= 0:
        return 2.0 / g if g > 0 else np.inf
    return float((np.sqrt(g * g + 4.0 * lam) - g) / lam)


def _lanczos_top(matvec, n: int, steps: int, seed: int = 0):
    """Largest eigenvalue and its Ritz vector of a symmetric operator on R^n (full reorthogonalised
    Lanczos, numpy float64)."""
    rng = np.random.default_rng(seed)
    q = rng.standard_normal(n)
    q /= np.linalg.norm(q)
    steps = max(1, min(steps, n))
    Q = np.zeros((steps, n))
    alpha, beta = np.zeros(steps), np.zeros(steps)
    m = steps
    for j in range(steps):
        Q[j] = q
        w = matvec(q)
        alpha[j] = q @ w
        for _ in range(2):  # einsum without BLAS: BLAS threads thrash on a loaded machine
            qj = Q[: j + 1]
            w = w - np.einsum("ji,j->i", qj, np.einsum("ji,i->j", qj, w, optimize=False),
                              optimize=False)  # fmt: skip
        b = np.linalg.norm(w)
        if j + 1 == steps or b < 1e-12 * max(abs(alpha[: j + 1]).max(), 1e-300):
            m = j + 1
            break
        beta[j] = b
        q = w / b
    T = np.diag(alpha[:m]) + np.diag(beta[: m - 1], 1) + np.diag(beta[: m - 1], -1)
    vals, vecs = np.linalg.eigh(T)
    return float(vals[-1]), np.einsum("ji,j->i", Q[:m], vecs[:, -1], optimize=False)


@jax.jit
def _force_jvps(net, material, gravity, wind, dx, dv):
    """(-df/dx dx, -df/dv dv) at rest (planar (3, rows, cols)); one compile per net shape/model."""
    x0 = jnp.moveaxis(net.rest, -1, 0)
    zero = jnp.zeros_like(x0)
    f = lambda x, v: _total_forces(net, material, x, v, gravity, wind)
    _, kx = jax.jvp(lambda x: f(x, zero), (x0,), (dx,))
    _, cv = jax.jvp(lambda v: f(x0, v), (zero,), (dv,))
    return -kx, -cv


def modal_substep(net: Net, sim, material, *, steps: int = 50) -> float:
    """Stable substep (s) from the stiffest and the most damped mode at rest (see module doc).

    Shapes: net (rows, cols, 3) m -> a Python float () s.
    """
    dtype = jnp.float64 if jax.config.jax_enable_x64 else jnp.float32
    free = ~np.asarray(net.pinned)
    mass = np.asarray(node_mass(net, material), np.float64)
    inv_sqrt = np.where(free, 1.0 / np.sqrt(np.where(free, mass, 1.0)), 0.0)
    x0 = jnp.moveaxis(jnp.asarray(net.rest, dtype), -1, 0)
    zero = jnp.zeros_like(x0)
    g = jnp.asarray(sim.gravity, dtype)
    wind = jnp.asarray(sim.wind, dtype)
    mat = jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype), material)
    netc = jax.tree_util.tree_map(
        lambda a: jnp.asarray(a, dtype) if jnp.issubdtype(a.dtype, jnp.floating) else a, net
    )

    jvps = lambda dx, dv: _force_jvps(netc, mat, g, wind, dx, dv)

    scale = np.broadcast_to(inv_sqrt[None], (3,) + inv_sqrt.shape).ravel()
    shape = x0.shape

    def op(which):
        def mv(u):
            d = jnp.asarray((scale * u).reshape(shape), dtype)
            kx, cv = jvps(d, zero) if which == 0 else jvps(zero, d)
            out = np.asarray(kx if which == 0 else cv, np.float64).ravel()
            return scale * out

        return mv

    n = scale.size
    k_op, c_op = op(0), op(1)
    with autodiff_forces():  # forward mode through the stencil forces (no hand-written VJP)
        lam, u = _lanczos_top(k_op, n, steps)
        gam, w = _lanczos_top(c_op, n, steps)
        g_u = float(u @ c_op(u))
        l_w = float(w @ k_op(w))
    return min(_limit(lam, g_u), _limit(l_w, gam))
