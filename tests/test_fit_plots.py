"""Plots write PNG files (matplotlib Agg, no pyplot state)."""

import numpy as np
import pytest

from diffcloth.fit.loop import History
from diffcloth.plots import plot_error_vs_evals, plot_loss, plot_params

PNG = b"\x89PNG\r\n\x1a\n"


def _history(n=30):
    s = np.arange(n, dtype=float)
    return History(
        loss=np.exp(-0.2 * s) + 1e-12,
        params={
            "stretch": 500.0 + 300.0 * (1 - np.exp(-0.2 * s)),
            "color": np.stack([0.5 + 0.1 * (1 - np.exp(-s / 5))] * 3, axis=1),
        },
        grad_norm={"stretch": np.exp(-s), "color": np.exp(-s)},
        wall_s=s * 0.01,
    )


def _is_png(path):
    return path.exists() and path.read_bytes()[:8] == PNG and path.stat().st_size > 1000


def test_plot_loss(tmp_path):
    h = _history()
    assert _is_png(plot_loss(h, tmp_path / "loss.png"))
    assert _is_png(plot_loss(h.to_dict(), tmp_path / "d" / "loss_dict.png"))
    assert _is_png(plot_loss({"start 0": h, "start 1": h}, tmp_path / "multi.png"))
    with pytest.raises(TypeError, match="History"):
        plot_loss([1.0, 2.0], tmp_path / "bad.png")


def test_plot_params(tmp_path):
    p = plot_params(
        _history(), tmp_path / "params.png", truth={"stretch": 800.0, "color": [0.6, 0.6, 0.6]}
    )
    assert _is_png(p)
    with pytest.raises(ValueError, match="no parameters"):
        plot_params({"loss": [1.0], "params": {}}, tmp_path / "x.png")


def test_plot_error_vs_evals(tmp_path):
    curves = {
        "gradient (Adam)": ([1, 2, 3], [0.5, 0.1, 0.01]),
        "CMA-ES": ([8, 16, 24], [0.6, 0.3, 0.2]),
    }
    assert _is_png(plot_error_vs_evals(curves, tmp_path / "err.png"))
    with pytest.raises(ValueError, match="must be equal"):
        plot_error_vs_evals({"a": ([1, 2], [1.0])}, tmp_path / "bad.png")
