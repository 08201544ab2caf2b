"""Plots of fits: loss curves, parameter convergence, error vs simulations (matplotlib, Agg).

matplotlib is an optional extra (`pip install "diffcloth[plot]"`), imported only inside these
functions; they draw on an off-screen Agg canvas (no pyplot, no global backend change) and write
PNG files.

A `history` argument may be a `diffcloth.fit.History`, a `FitResult` (its history is used) or a
dict with "loss" and "params" entries (as `History.to_dict()` gives).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

__all__ = ["plot_error_vs_evals", "plot_loss", "plot_params"]


def _figure(nrows: int = 1, ncols: int = 1, size=(6.0, 4.0)):
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError(
            "diffcloth.plots needs matplotlib: pip install 'diffcloth[plot]' (or matplotlib)"
        ) from e
    fig = Figure(figsize=(size[0] * ncols, size[1] * nrows), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(nrows, ncols, squeeze=False)
    return fig, axes


def _save(fig, path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    return path


def _history(h):
    """-> (loss (n,), params {name: (n, ...)})."""
    if hasattr(h, "history") and hasattr(h, "params"):  # a FitResult
        h = h.history
    if hasattr(h, "loss") and hasattr(h, "params"):
        return np.asarray(h.loss, float), {k: np.asarray(v, float) for k, v in h.params.items()}
    if isinstance(h, Mapping) and "loss" in h:
        params = {k: np.asarray(v, float) for k, v in dict(h.get("params", {})).items()}
        return np.asarray(h["loss"], float), params
    raise TypeError(f"expected a History, FitResult or dict with 'loss'; got {type(h).__name__}")


def _is_single(h) -> bool:
    return not isinstance(h, Mapping) or "loss" in h


def plot_loss(history, path, *, title: str = "loss", logy: bool = True) -> Path:
    """Loss against step (log scale). `history` may also be {label: history} for several curves."""
    curves = {"loss": history} if _is_single(history) else dict(history)
    fig, axes = _figure()
    ax = axes[0, 0]
    for label, h in curves.items():
        loss, _ = _history(h)
        steps = np.arange(loss.shape[0])
        if logy:
            ok = np.isfinite(loss) & (loss > 0)
            ax.plot(steps[ok], loss[ok], label=label)
        else:
            ax.plot(steps, loss, label=label)
    if logy:
        ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("loss")
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    if len(curves) > 1:
        ax.legend()
    return _save(fig, path)


def plot_params(history, path, truth: Mapping | None = None, *, title: str | None = None) -> Path:
    """One subplot per parameter: its value against step, with the true value as a dashed line.

    Array parameters draw one line per component (and one true line per component).
    """
    _, params = _history(history)
    if not params:
        raise ValueError("plot_params: the history holds no parameters")
    truth = dict(truth or {})
    names = list(params)
    ncols = min(3, len(names))
    nrows = math.ceil(len(names) / ncols)
    fig, axes = _figure(nrows, ncols, size=(4.0, 3.0))
    for i, name in enumerate(names):
        ax = axes[i // ncols, i % ncols]
        v = params[name].reshape(params[name].shape[0], -1)
        steps = np.arange(v.shape[0])
        for j in range(v.shape[1]):
            label = name if v.shape[1] == 1 else f"{name}[{j}]"
            (line,) = ax.plot(steps, v[:, j], label=label)
            if name in truth:
                tv = np.asarray(truth[name], float).reshape(-1)
                if tv.size in (1, v.shape[1]):
                    ax.axhline(
                        tv[j if tv.size > 1 else 0],
                        ls="--",
                        color=line.get_color(),
                        alpha=0.8,
                        label="true" if j == 0 else None,
                    )
        finite = v[np.isfinite(v)]
        if finite.size and finite.min() > 0 and finite.max() / finite.min() > 100:
            ax.set_yscale("log")
        ax.set_title(name)
        ax.set_xlabel("step")
        ax.grid(True, alpha=0.3)
        if name in truth or v.shape[1] > 1:
            ax.legend(fontsize="small")
    for k in range(len(names), nrows * ncols):
        axes[k // ncols, k % ncols].set_visible(False)
    if title:
        fig.suptitle(title)
    return _save(fig, path)


def plot_error_vs_evals(
    curves: Mapping[str, tuple[Sequence[float], Sequence[float]]],
    path,
    *,
    xlabel: str = "simulations (loss evaluations)",
    ylabel: str = "relative parameter error",
    title: str | None = None,
    logy: bool = True,
) -> Path:
    """Error against number of simulations for several methods (gradient descent vs CMA-ES).

    Args:
      curves: label -> (evals, errors), each a 1-D sequence of equal length.
      path: PNG file to write.
    """
    if not curves:
        raise ValueError("plot_error_vs_evals: no curves given")
    fig, axes = _figure()
    ax = axes[0, 0]
    for label, (evals, errors) in curves.items():
        e, r = np.asarray(evals, float), np.asarray(errors, float)
        if e.shape != r.shape or e.ndim != 1:
            raise ValueError(
                f"curve {label!r}: evals shape {e.shape} and errors shape {r.shape} must be equal "
                "and 1-D"
            )
        ok = np.isfinite(r) & ((r > 0) if logy else True)
        ax.plot(e[ok], r[ok], marker=".", label=label)
    if logy:
        ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    return _save(fig, path)
