"""Which parameters can the images pin down? A Gauss-Newton / Fisher analysis at the optimum.

For residuals r(p) (e.g. rendered - target pixels, flattened) with i.i.d. Gaussian noise of
standard deviation sigma, the Fisher information is F = J^T J / sigma^2 with J = dr/dp. Its inverse
approximates the covariance of the fitted parameters: per-parameter standard deviations and a
correlation matrix. Parameters whose estimates are almost perfectly correlated (|corr| near 1), or
that dominate a direction of F with a near-zero eigenvalue, cannot be told apart by the data
(density vs stiffness under gravity, for example).

The eigen-analysis and condition number use the relative (log-scale) Fisher matrix
D F D with D = diag(|p|) so that parameters in different units compare fairly.

Example:
    >>> import jax.numpy as jnp
    >>> x = jnp.linspace(0.0, 1.0, 20)
    >>> rep = identifiability(lambda p: p["a"] * p["b"] * x - 2.0 * x, {"a": 1.0, "b": 2.0})
    >>> rep.confounded[0][:2]
    ('a', 'b')
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from diffcloth.fit.constraints import make_constraints, to_physical, to_raw
from diffcloth.physics.forces import autodiff_forces

__all__ = ["Identifiability", "format_identifiability", "identifiability"]


@dataclasses.dataclass
class Identifiability:
    """Result of `identifiability`; entries follow `names` (one per scalar: "color[1]").

    values: parameter values (physical). fisher: J^T J / sigma^2 in the chosen space.
    std: standard deviation per parameter (inf where the data leave it undetermined), in the units
    of `space` ("physical": the parameter's units; "raw": the optimiser's raw values).
    relative_std: std / |value| (physical space). correlation: (n, n).
    eigenvalues / eigenvectors: of the relative Fisher matrix (ascending; columns are directions).
    condition_number: largest / smallest eigenvalue of the relative Fisher matrix (inf if singular).
    confounded: (name_i, name_j, correlation) pairs with |correlation| >= corr_threshold.
    sloppy: near-null directions: dicts {"eigenvalue", "relative_eigenvalue", "params": {name:
    weight}} naming the parameters that dominate each direction.
    identifiable: name -> False when it appears in a confounded pair or a sloppy direction.
    """

    names: list[str]
    values: np.ndarray
    space: str
    noise_sigma: float
    fisher: np.ndarray
    std: np.ndarray
    relative_std: np.ndarray
    correlation: np.ndarray
    eigenvalues: np.ndarray
    eigenvectors: np.ndarray
    condition_number: float
    confounded: list[tuple[str, str, float]]
    sloppy: list[dict[str, Any]]
    identifiable: dict[str, bool]

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly summary (inf written as None)."""

        def num(x):
            x = float(x)
            return x if np.isfinite(x) else None

        return {
            "space": self.space,
            "noise_sigma": self.noise_sigma,
            "params": {
                n: {
                    "value": num(v),
                    "std": num(s),
                    "relative_std": num(rs),
                    "identifiable": self.identifiable[n],
                }
                for n, v, s, rs in zip(
                    self.names, self.values, self.std, self.relative_std, strict=True
                )
            },
            "correlation": [[num(c) for c in row] for row in self.correlation],
            "condition_number": num(self.condition_number),
            "confounded": [[a, b, float(c)] for a, b, c in self.confounded],
            "sloppy": [
                {
                    "eigenvalue": float(d["eigenvalue"]),
                    "relative_eigenvalue": float(d["relative_eigenvalue"]),
                    "params": {k: float(w) for k, w in d["params"].items()},
                }
                for d in self.sloppy
            ],
        }


def _flat_names(params: Mapping[str, Any]) -> list[str]:
    names = []
    for k in sorted(params):
        a = np.asarray(params[k])
        if a.ndim == 0:
            names.append(k)
        else:
            names += [f"{k}[{','.join(map(str, idx))}]" for idx in np.ndindex(a.shape)]
    return names


def identifiability(
    residual_fn: Callable[[dict[str, jax.Array]], jax.Array],
    params: Mapping[str, Any],
    constraints: Mapping | None = None,
    *,
    space: str = "physical",
    noise_sigma: float = 1.0,
    corr_threshold: float = 0.95,
    eig_rtol: float = 1e-6,
    weight_threshold: float = 0.3,
) -> Identifiability:
    """Gauss-Newton / Fisher identifiability analysis of `residual_fn` at `params`.

    Args:
      residual_fn: physical params dict -> residuals (any shape; flattened), e.g. rendered - target.
      params: the optimum (physical values, scalars or arrays).
      constraints: used only for space="raw" (derivatives w.r.t. the optimiser's raw values).
      space: "physical" or "raw": the variables of J and of `std`.
      noise_sigma: standard deviation of the residual noise (e.g. pixel noise); F = J^T J / sigma^2.
      corr_threshold: |correlation| at or above which a pair is reported confounded.
      eig_rtol: relative eigenvalues (lambda / lambda_max of the relative Fisher matrix) at or below
        this are near-null ("sloppy") directions.
      weight_threshold: a parameter "dominates" a sloppy direction when |eigenvector entry| >= this.
    Returns:
      Identifiability.
    """
    if space not in ("physical", "raw"):
        raise ValueError(f"space={space!r} is not one of 'physical', 'raw'")
    if not (np.isfinite(noise_sigma) and noise_sigma > 0):
        raise ValueError(f"noise_sigma={noise_sigma!r} must be finite and > 0")
    phys = {k: jnp.asarray(v, dtype=jnp.result_type(float)) for k, v in params.items()}
    names = _flat_names(phys)
    flat_phys, _ = ravel_pytree(phys)
    if space == "raw":
        cons = make_constraints(list(phys), constraints)
        flat, unravel = ravel_pytree(to_raw(phys, cons))

        def fn(z):
            return jnp.ravel(residual_fn(to_physical(unravel(z), cons)))
    else:
        flat, unravel = ravel_pytree(phys)

        def fn(z):
            return jnp.ravel(residual_fn(unravel(z)))

    # forward mode: trace the physics with JAX's own force derivatives (the hand-written VJP of
    # the symplectic step is reverse-mode only)
    with autodiff_forces():
        jac = np.asarray(jax.jit(jax.jacfwd(fn))(flat), dtype=float)  # (m, n), one compile
    if not np.all(np.isfinite(jac)):
        raise ValueError("the Jacobian of residual_fn at params is not finite")
    fisher = jac.T @ jac / noise_sigma**2
    n = fisher.shape[0]
    values = np.asarray(flat_phys, dtype=float)

    # Relative (scale-free) Fisher matrix for the eigen-analysis.
    scale = np.asarray(flat, dtype=float) if space == "physical" else np.ones(n)
    scale = np.where(np.abs(scale) > 0, np.abs(scale), 1.0)
    rel = fisher * scale[:, None] * scale[None, :]
    lam, vec = np.linalg.eigh(rel)
    lam = np.maximum(lam, 0.0)
    lam_max = float(lam.max()) if n else 0.0
    null = lam <= eig_rtol * lam_max if lam_max > 0 else np.ones(n, bool)
    condition = float(lam_max / lam.min()) if n and lam.min() > 0 else float("inf")

    # Covariance through the eigen-decomposition; near-null directions give infinite variance to
    # the parameters that take part in them, and a large finite regularised value for correlations.
    floor = max(eig_rtol * lam_max, np.finfo(float).tiny)
    inv = 1.0 / np.maximum(lam, floor)
    cov_rel = (vec * inv[None, :]) @ vec.T
    cov = cov_rel * scale[:, None] * scale[None, :]  # F^-1 = D (D F D)^-1 D
    d = np.sqrt(np.maximum(np.diag(cov), 0.0))
    correlation = cov / np.maximum(d[:, None] * d[None, :], np.finfo(float).tiny)
    np.fill_diagonal(correlation, 1.0)
    std = d.copy()
    involved = (np.abs(vec[:, null]) >= 1e-6).any(axis=1) if null.any() else np.zeros(n, bool)
    std[involved] = np.inf
    if space == "physical":
        relative_std = np.where(
            values != 0, std / np.where(values != 0, np.abs(values), 1.0), np.inf
        )
    else:  # raw std of a log-space parameter is already relative; report it via the Jacobian map
        dphys = np.asarray(
            jax.jacfwd(
                lambda z: ravel_pytree(
                    to_physical(unravel(z), make_constraints(list(phys), constraints))
                )[0]
            )(flat)
        )
        std_phys = np.abs(np.diag(dphys)) * std
        relative_std = np.where(
            values != 0, std_phys / np.where(values != 0, np.abs(values), 1.0), np.inf
        )

    confounded = []
    for i in range(n):
        for j in range(i + 1, n):
            if abs(correlation[i, j]) >= corr_threshold:
                confounded.append((names[i], names[j], float(correlation[i, j])))
    sloppy = []
    for idx in np.flatnonzero(null):
        v = vec[:, idx]
        order = np.argsort(-np.abs(v))
        dominant = {names[i]: float(v[i]) for i in order if abs(v[i]) >= weight_threshold}
        sloppy.append(
            {
                "eigenvalue": float(lam[idx]),
                "relative_eigenvalue": float(lam[idx] / lam_max) if lam_max > 0 else 0.0,
                "params": dominant,
            }
        )
    flagged = {a for a, _, _ in confounded} | {b for _, b, _ in confounded}
    for s in sloppy:
        flagged |= set(s["params"])
    identifiable = {nm: nm not in flagged for nm in names}
    return Identifiability(
        names=names,
        values=values,
        space=space,
        noise_sigma=float(noise_sigma),
        fisher=fisher,
        std=std,
        relative_std=relative_std,
        correlation=correlation,
        eigenvalues=lam,
        eigenvectors=vec,
        condition_number=condition,
        confounded=confounded,
        sloppy=sloppy,
        identifiable=identifiable,
    )


def _g(x: float) -> str:
    return f"{x:.4g}" if np.isfinite(x) else "inf"


def format_identifiability(rep: Identifiability) -> str:
    """Markdown: a per-parameter table, the correlation matrix and the flags."""
    lines = [
        f"Fisher / Gauss-Newton estimate at the optimum (noise sigma {rep.noise_sigma:g}, "
        f"{rep.space} space); condition number {_g(rep.condition_number)}.",
        "",
        "| parameter | value | std | relative std | identifiable |",
        "|---|---|---|---|---|",
    ]
    for n, v, s, rs in zip(rep.names, rep.values, rep.std, rep.relative_std, strict=True):
        lines.append(
            f"| {n} | {_g(v)} | {_g(s)} | {_g(rs)} | {'yes' if rep.identifiable[n] else '**no**'} |"
        )
    lines += [
        "",
        "Correlation matrix:",
        "",
        "| | " + " | ".join(rep.names) + " |",
        "|---|" + "---|" * len(rep.names),
    ]
    for n, row in zip(rep.names, rep.correlation, strict=True):
        lines.append(f"| {n} | " + " | ".join(f"{c:+.3f}" for c in row) + " |")
    lines.append("")
    if not rep.confounded and not rep.sloppy:
        lines.append("All parameters are identifiable from these residuals.")
    for a, b, c in rep.confounded:
        lines.append(
            f"- **{a}** and **{b}** are confounded (correlation {c:+.3f}): the images "
            "cannot tell them apart."
        )
    for s in rep.sloppy:
        combo = " ".join(f"{w:+.2f}*{n}" for n, w in s["params"].items())
        lines.append(
            f"- near-null direction (relative eigenvalue {s['relative_eigenvalue']:.2e}): "
            f"changing {combo} (relative) leaves the images almost unchanged."
        )
    return "\n".join(lines) + "\n"
