"""Fit reports: result.json format, report.md, pictures, results README rows."""

import json

import numpy as np
import pytest

from diffcloth.fit.identifiability import identifiability
from diffcloth.fit.loop import FitResult, History
from diffcloth.report import (
    append_results_row,
    fit_summary,
    relative_error,
    results_row,
    write_fit_report,
)


def _result():
    n = 6
    hist = History(
        loss=np.geomspace(1.0, 1e-6, n),
        params={"stretch": np.linspace(500.0, 801.0, n), "color": np.full((n, 3), 0.5)},
        grad_norm={"stretch": np.ones(n), "color": np.ones(n)},
        wall_s=np.linspace(0.0, 1.0, n),
    )
    return FitResult(
        params={"stretch": np.array(801.0), "color": np.array([0.5, 0.5, 0.5])},
        raw={"stretch": np.log(801.0), "color": np.zeros(3)},
        loss=1e-6,
        initial={"stretch": np.array(500.0), "color": np.array([0.4, 0.5, 0.6])},
        history=hist,
        iterations=5,
        wall_s=1.25,
        status="max_steps",
        message="reached steps=5",
        best_step=5,
        last_finite={"stretch": np.array(801.0), "color": np.array([0.5, 0.5, 0.5])},
    )


def test_relative_error():
    assert relative_error(101.0, 100.0) == pytest.approx(0.01)
    assert relative_error(0.5, 0.0) == pytest.approx(0.5)
    assert relative_error([3.0, 4.0], [0.0, 0.0]) == pytest.approx(5.0)
    with pytest.raises(ValueError, match="shape"):
        relative_error([1.0, 2.0], 1.0)


def test_result_json_exact_format(tmp_path):
    res = _result()
    paths = write_fit_report(
        tmp_path,
        res,
        truth={"stretch": 800.0},
        target=np.zeros((3, 8, 8, 3)),
        fitted=np.full((3, 8, 8, 3), 0.1),
    )
    data = json.loads((tmp_path / "result.json").read_text())
    assert list(data) == ["status", "message", "params", "loss", "iterations", "wall_s"]
    assert data["status"] == res.status
    assert data["params"]["stretch"] == {
        "true": 800.0,
        "initial": 500.0,
        "fitted": 801.0,
        "relative_error": pytest.approx(1 / 800),
    }
    assert list(data["params"]["stretch"]) == ["true", "initial", "fitted", "relative_error"]
    # no truth -> no "true" / "relative_error"
    assert data["params"]["color"] == {"initial": [0.4, 0.5, 0.6], "fitted": [0.5, 0.5, 0.5]}
    assert data["iterations"] == 5 and data["wall_s"] == 1.25 and data["loss"] == 1e-6
    for key in ("loss", "params", "compare", "report"):
        assert paths[key].exists(), key
    assert paths["compare"].name == "compare.gif"
    md = (tmp_path / "report.md").read_text()
    assert "| stretch | 800 | 500 | 801 | 0.125 % |" in md
    assert "![loss](loss.png)" in md and "![compare](compare.gif)" in md
    # metrics.jsonl: one line per evaluation, the history exactly; environment.json: versions
    rows = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == list(range(6))
    assert rows[-1]["loss"] == pytest.approx(1e-6) and rows[-1]["params"]["stretch"] == 801.0
    assert rows[2]["params"]["color"] == [0.5, 0.5, 0.5] and rows[0]["grad_norm"]["stretch"] == 1.0
    env = json.loads((tmp_path / "environment.json").read_text())
    import jax

    assert env["jax"] == jax.__version__ and env["backend"] == jax.default_backend()
    assert env["x64"] is True  # the test suite runs in float64


def test_report_with_identifiability_and_sections(tmp_path):
    res = _result()
    x = np.linspace(0, 1, 10)
    rep = identifiability(lambda p: p["a"] * p["b"] * x - x, {"a": 1.0, "b": 1.0})
    write_fit_report(
        tmp_path,
        res,
        identifiability=rep,
        plots=False,
        extra_sections={"Notes": "noiseless targets"},
    )
    md = (tmp_path / "report.md").read_text()
    assert "## Identifiability" in md and "confounded" in md
    assert "## Notes\n\nnoiseless targets" in md
    assert not (tmp_path / "loss.png").exists()
    assert json.loads((tmp_path / "identifiability.json").read_text())["confounded"][0][:2] == [
        "a",
        "b",
    ]
    with pytest.raises(ValueError, match="unknown parameters"):
        fit_summary(res, truth={"bend": 1.0})


def test_results_readme_rows(tmp_path):
    readme = tmp_path / "results" / "README.md"
    summary = fit_summary(_result(), truth={"stretch": 800.0})
    append_results_row(readme, results_row("drape", summary, "drape/report.md"), intro="All runs.")
    append_results_row(readme, results_row("flag", summary))
    append_results_row(readme, dict(results_row("drape", summary), iterations="99"))
    text = readme.read_text()
    lines = [line for line in text.splitlines() if line.startswith("|")]
    assert len(lines) == 4  # header, separator, drape (replaced), flag
    assert lines[2].startswith("| drape | stretch, color | 0.125 % |") and "| 99 |" in lines[2]
    assert lines[3].startswith("| flag |")
    assert text.startswith("# Results\n\nAll runs.\n")
    with pytest.raises(ValueError, match="not columns"):
        append_results_row(readme, {"experiment": "x", "speed": 1})
