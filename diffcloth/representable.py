"""Values checked in the dtype the run uses, not only in Python's float64.

A config or a parameter is validated as a Python float (float64), but the run holds it in its own
float dtype (float32 unless x64 is on). A value that is fine in float64 can overflow to inf in
float32 (`width = 1e39`) or underflow to 0 or to a subnormal number (`density = 1e-46`,
`dt = 1e-46`; XLA on CPU flushes subnormals to 0), and the run then "blows up" or never moves.
Every number that enters a run passes `check_representable` (or `unrepresentable`) against the run's
dtype: it must be finite there, and a non-zero value must keep a normal magnitude,
[finfo.tiny, finfo.max] (float32: [1.175e-38, 3.403e+38]). `check_physics` applies the same
rule to the quantities the physics derives from several values (node masses, rest lengths, spring
weights, the substep dt / num_substeps), which can leave the range when each value is inside it.

    >>> import numpy as np
    >>> unrepresentable(1e39, np.float32)
    'overflows to inf in float32'
    >>> unrepresentable(1e-46, np.float32)
    'underflows to 0 or a subnormal number in float32'
    >>> unrepresentable(1e-46, np.float64) is None
    True
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "check_physics",
    "check_quantities",
    "check_representable",
    "net_quantities",
    "range_text",
    "run_dtype",
    "unrepresentable",
]


def run_dtype(dtype=None) -> np.dtype:
    """The float dtype of a run: `dtype`, else JAX's default float (float64 when x64 is on)."""
    if dtype is not None:
        return np.dtype(dtype)
    import jax.numpy as jnp

    return np.dtype(jnp.zeros(()).dtype)


def range_text(dtype) -> str:
    """The magnitudes a value may have in `dtype`, as text."""
    info = np.finfo(run_dtype(dtype))
    return f"0 or a magnitude in [{float(info.tiny):.4g}, {float(info.max):.4g}] in {info.dtype}"


def unrepresentable(value, dtype) -> str | None:
    """Why `value` (a number or array) does not survive conversion to `dtype`, or None when every
    element is finite and either 0 or of a normal magnitude in that dtype."""
    info = np.finfo(run_dtype(dtype))
    a = np.abs(np.asarray(value, np.float64))
    if not np.all(np.isfinite(a)):
        return "is not finite"
    if np.any(a > float(info.max)):
        return f"overflows to inf in {info.dtype}"
    if np.any((a > 0) & (a < float(info.tiny))):
        return f"underflows to 0 or a subnormal number in {info.dtype}"
    return None


def _hint(dtype) -> str:
    if run_dtype(dtype) == np.float64:
        return ""
    return " (float64, e.g. --x64, allows [2.225e-308, 1.798e+308])"


def check_representable(what: str, value, dtype, error=ValueError) -> None:
    """Raise `error` naming `what`, the value and the allowed magnitudes when `value` does not
    survive conversion to `dtype` (see `unrepresentable`)."""
    why = unrepresentable(value, dtype)
    if why is not None:
        shown = np.asarray(value, np.float64)
        shown = shown.item() if shown.ndim == 0 else shown.tolist()
        raise error(
            f"{what} = {shown!r} {why} (the run's dtype); allowed: {range_text(dtype)}"
            f"{_hint(dtype)}"
        )


def _positive_normal(a, dtype) -> bool:
    info = np.finfo(run_dtype(dtype))
    a = np.asarray(a, np.float64)
    return bool(np.all(np.isfinite(a) & (np.abs(a) >= float(info.tiny)) & (a <= float(info.max))))


def check_quantities(source: str, items, dtype, error=ValueError) -> None:
    """Refuse derived quantities that leave the normal range of `dtype`.

    Args:
      source: text naming the inputs that make the quantities (config keys or argument names).
      items: (what, float64 array, positive) triples: every element finite in `dtype`, and when
        `positive`, also of a normal magnitude (a positive mass, length or substep must not
        become 0 or subnormal).
      dtype: the run's float dtype.
    """
    info = np.finfo(run_dtype(dtype))
    for what, a, positive in items:
        a = np.asarray(a, np.float64)
        if a.size == 0:
            continue
        bad = not _positive_normal(a, dtype) if positive else unrepresentable(a, dtype) is not None
        if bad:
            mags = np.abs(a[np.isfinite(a)]) if np.isfinite(a).any() else np.array([np.inf])
            raise error(
                f"{source} make {what} that do not fit {info.dtype} (the run's dtype): "
                f"magnitudes {float(mags.min()):.3g} .. {float(mags.max()):.3g}, allowed "
                f"[{float(info.tiny):.4g}, {float(info.max):.4g}]{_hint(dtype)}; choose values "
                "of a physical scale"
            )


def net_quantities(arrays) -> list:
    """The (what, array, positive) items of a control net's arrays (`check_quantities`)."""
    items = [("rest positions (m)", arrays["rest"], False)]
    items.append(("lumped node areas (m^2)", arrays["area"], True))
    for field in ("rest_h", "rest_v", "rest_d1", "rest_d2"):
        items.append(("spring rest lengths (m)", arrays[field], True))
    for field in ("weight_h", "weight_v", "weight_d", "weight_bh", "weight_bv"):
        items.append(("spring weights (1/m^2 for bending)", arrays[field], True))
    return items


def check_physics(net, sim, material, *, names, error=ValueError) -> None:
    """Refuse derived physics quantities that leave the run's normal range.

    Computed in float64 from the built (dtype) leaves: the net's arrays, node masses (density x
    lumped area), and the substep dt / num_substeps must be finite and of normal magnitude.

    Args:
      net, sim, material: the built physics pytrees (concrete arrays).
      names: {"net", "mass", "substep"} -> text naming the inputs that make the quantity (config
        keys or parameter names), used in the message.
      error: the exception class raised.
    """
    dtype = run_dtype(net.rest.dtype)
    f64 = lambda a: np.asarray(a, np.float64)  # noqa: E731
    arrays = {f: f64(getattr(net, f)) for f in ("rest", "area", "rest_h", "rest_v", "rest_d1",
                                                 "rest_d2", "weight_h", "weight_v", "weight_d",
                                                 "weight_bh", "weight_bv")}  # fmt: skip
    check_quantities(names["net"], net_quantities(arrays), dtype, error)
    density = f64(material.density)
    if getattr(material, "lumping", "area") == "uniform":
        mass = density * arrays["area"].sum() / max(1, net.rows * net.cols)
    else:
        mass = density * arrays["area"]
    check_quantities(names["mass"], [("node masses (kg)", mass, True)], dtype, error)
    substep = f64(sim.dt) / sim.num_substeps
    check_quantities(
        names["substep"], [("a substep dt / num_substeps (s)", substep, True)], dtype, error
    )
