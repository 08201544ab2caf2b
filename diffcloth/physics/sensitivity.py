"""Mixed-mode differentiation of the physics: forward sensitivities for few inputs.

A fit has few scalar physics parameters (2-8), while its rollout has hundreds of substeps on a
small net. Reverse mode through the rollout replays it backwards (checkpointed, ~25x a forward on
the main job); forward mode carries P tangent columns along the same scan and costs about
(1 + P * small) forwards. `mixed_mode` wraps a physics function in a `jax.custom_jvp` whose rule,
when the inputs actually differentiated hold P scalars in all (few), computes the primal and the
Jacobian J = d(out)/d(those inputs) (outputs x P) by P forward-mode tangents, and returns the
tangent J @ t. That is linear in t, so reverse mode (`jax.grad`) only transposes a small einsum
(J lands in the forward pass), and forward mode (`jax.jacfwd`) works too. The renderer after it
stays in reverse mode.

The rule ("auto"): forward sensitivities when P <= FORWARD_MAX_PARAMS and J takes at most
FORWARD_MAX_BYTES; otherwise plain `jax.jvp` of the function (today's reverse mode after
linearisation). "forward" always uses the sensitivities; "reverse" does not wrap at all.
"""

from __future__ import annotations

import contextlib
import math

import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import SymbolicZero

from diffcloth.physics.state import GRADIENT_MODES

#: "auto" uses forward sensitivities for at most this many differentiated scalars ... (the P
#: tangents ride in every fused kernel of the substep: on the 2-core CPU, loaded, the main job's
#: physics gradient took 0.84x of reverse mode with P = 2, drape_material's 2.25x with P = 4;
#: benchmarks/fit_step_modes.py)
FORWARD_MAX_PARAMS = 2
#: ... and when the Jacobian (outputs x P) takes at most this many bytes
FORWARD_MAX_BYTES = 256 << 20


@contextlib.contextmanager
def forward_tracing():
    """Context manager: trace the physics for forward mode. The stencil forces are the same
    primal under plain autodiff (their hand-written VJP has no forward mode) and the contact rule
    uses its plain JVP (cheaper per tangent than the per-node Jacobian of `contact_jac`, which
    serves reverse mode)."""
    from diffcloth.physics.collide import _PLAIN_CONTACT
    from diffcloth.physics.stencil_vjp import _PLAIN_STENCIL

    prev = (_PLAIN_CONTACT[0], _PLAIN_STENCIL[0])
    _PLAIN_CONTACT[0] = _PLAIN_STENCIL[0] = True
    try:
        yield
    finally:
        _PLAIN_CONTACT[0], _PLAIN_STENCIL[0] = prev


def _is_float(a) -> bool:
    return jnp.issubdtype(jnp.result_type(a), jnp.inexact)


def _nonzero(t) -> bool:
    return not isinstance(t, SymbolicZero) and jnp.result_type(t) != jax.dtypes.float0


def use_forward(mode: str, num_params: int, out_size: int, itemsize: int) -> bool:
    """Whether forward sensitivities are used for `num_params` differentiated scalars and
    `out_size` output scalars of `itemsize` bytes (the "auto" rule in the module docstring).
    Shapes: none (Python ints in, a Python bool out)."""
    if mode == "forward":
        return True
    if mode == "reverse":
        return False
    return (
        num_params <= FORWARD_MAX_PARAMS and num_params * out_size * itemsize <= FORWARD_MAX_BYTES
    )


def _zero_tangent(a):
    a = jnp.asarray(a)
    if _is_float(a):
        return jnp.zeros_like(a)
    return np.zeros(a.shape, jax.dtypes.float0)


def forward_jacobian(f, args: tuple):
    """(f(*args), J): J has f's output structure with each leaf (P, *leaf_shape), the derivative
    along each of the P scalars of `args` (all leaves float, raveled and concatenated in order).
    The primal is computed once (unbatched); the P tangents ride along it under `vmap`."""
    leaves = jax.tree_util.tree_leaves(args)
    sizes = [int(np.prod(jnp.shape(a))) for a in leaves]
    P = sum(sizes)
    rows, off = [], 0
    for a, n in zip(leaves, sizes, strict=True):
        eye = jnp.eye(P, n, -off, dtype=jnp.result_type(a))
        rows.append(eye.reshape((P,) + jnp.shape(a)))
        off += n
    basis = jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(args), rows)

    def column(t):
        return jax.jvp(f, args, t)

    return jax.vmap(column, out_axes=(None, 0))(basis)


def mixed_mode(fn, mode: str = "auto"):
    """`fn(*args) -> pytree` with the same values and a derivative by forward sensitivities.

    fn must read traced values only through its arguments (no closed-over tracers: their
    derivative would be lost); its float outputs get the tangents, others (ints, bools) none.
    mode: "auto", "forward" or "reverse" (GRADIENT_MODES; the rule is in the module docstring);
    "reverse" returns fn itself.
    """
    if mode not in GRADIENT_MODES:
        raise ValueError(f"gradient: must be one of {GRADIENT_MODES}, got {mode!r}")
    if mode == "reverse":
        return fn

    @jax.custom_jvp
    def wrapped(*args):
        return fn(*args)

    def rule(primals, tangents):
        flat, tree = jax.tree_util.tree_flatten(primals)
        # the tangents at the primal leaves' places (a None child, such as a switched-off
        # `SimSettings.self_contact`, has no leaf in either)
        tflat = tree.flatten_up_to(tangents)
        idx = [i for i, (a, t) in enumerate(zip(flat, tflat, strict=True))
               if _is_float(a) and _nonzero(t)]  # fmt: skip

        def f(*vals):
            ls = list(flat)
            for i, v in zip(idx, vals, strict=True):
                ls[i] = v
            return fn(*jax.tree_util.tree_unflatten(tree, ls))

        nz = tuple(flat[i] for i in idx)
        tnz = tuple(jnp.asarray(tflat[i], jnp.result_type(flat[i])) for i in idx)
        out_shape = jax.eval_shape(f, *nz)
        out_leaves = jax.tree_util.tree_leaves(out_shape)
        P = sum(int(np.prod(a.shape)) for a in nz)
        out_size = sum(math.prod(o.shape) for o in out_leaves if _is_float(o))
        itemsize = max([jnp.dtype(o.dtype).itemsize for o in out_leaves] + [4])
        if not idx:
            out = f()
            return out, jax.tree_util.tree_map(_zero_tangent, out)
        if not use_forward(mode, P, out_size, itemsize):
            return jax.jvp(f, nz, tnz)
        with forward_tracing():
            out, jac = forward_jacobian(f, nz)
        t = jnp.concatenate([jnp.ravel(a) for a in tnz])

        def tangent(o, j):
            if not _is_float(o):
                return _zero_tangent(o)
            return jnp.tensordot(t.astype(j.dtype), j, axes=1)

        return out, jax.tree_util.tree_map(tangent, out, jac)

    wrapped.defjvp(rule, symbolic_zeros=True)
    return wrapped
