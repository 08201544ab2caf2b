"""Fit reports: result.json, report.md, plots and the side-by-side video; results/README.md rows.

    write_fit_report("results/drape", result, truth={"stretch": 800.0},
                     target=target_video, fitted=fitted_video)

writes to the folder:
  result.json  {"status": converged | stalled | max_steps | nonfinite | interrupted | stopped,
                "message": .., "params": {NAME: {"true": .., "initial": .., "fitted": ..,
                "relative_error": ..}}, "loss": .. (null if not finite), "iterations": ..,
                "wall_s": ..}   ("true" and "relative_error" only
                when the truth is known; array parameters are lists)
  loss.png     loss per step (log scale)
  params.png   every parameter against step, with the true value
  compare.gif  target | fit | |difference| per frame (when both videos are given), sRGB-encoded
  report.md    the table, the pictures and any extra sections
  metrics.jsonl  one JSON line per step: step, loss, params, grad_norm, wall_s
  environment.json  versions, backend, devices, x64 (`diffcloth.runtime.environment`)
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from diffcloth.io.media import save_json, save_png, save_video, side_by_side, to_jsonable

__all__ = [
    "RESULTS_COLUMNS",
    "append_results_row",
    "fit_summary",
    "relative_error",
    "results_row",
    "write_fit_report",
]


def relative_error(fitted, true) -> float:
    """|fitted - true| / |true| (Euclidean norms for arrays); the absolute error where true is 0."""
    f = np.asarray(fitted, float).ravel()
    t = np.asarray(true, float).ravel()
    if f.shape != t.shape:
        raise ValueError(f"relative_error: fitted shape {f.shape} != true shape {t.shape}")
    num = float(np.linalg.norm(f - t))
    den = float(np.linalg.norm(t))
    return num / den if den > 0 else num


def _value(v):
    a = np.asarray(v)
    return float(a) if a.ndim == 0 else a.tolist()


def fit_summary(result, truth: Mapping | None = None, initial: Mapping | None = None) -> dict:
    """The result.json dictionary (see the module docstring) for a FitResult."""
    truth = dict(truth or {})
    initial = dict(result.initial if initial is None else initial)
    unknown = sorted(set(truth) - set(result.params))
    if unknown:
        raise ValueError(
            f"truth names unknown parameters {unknown}; fitted are {sorted(result.params)}"
        )
    params: dict[str, dict[str, Any]] = {}
    for name, fitted in result.params.items():
        entry: dict[str, Any] = {}
        if name in truth:
            entry["true"] = _value(truth[name])
        entry["initial"] = _value(initial[name]) if name in initial else None
        entry["fitted"] = _value(fitted)
        if name in truth:
            entry["relative_error"] = relative_error(fitted, truth[name])
        params[name] = entry
    loss = float(result.loss)
    return {
        "status": str(getattr(result, "status", "unknown")),
        "message": str(getattr(result, "message", "")),
        "params": params,
        "loss": loss if np.isfinite(loss) else None,
        "iterations": int(result.iterations),
        "wall_s": float(result.wall_s),
    }


def _fmt(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, list):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    if isinstance(v, float):
        return f"{v:.5g}"
    return str(v)


def _table(summary: dict) -> str:
    has_truth = any("true" in e for e in summary["params"].values())
    head = ["parameter"] + (["true"] if has_truth else []) + ["initial", "fitted"]
    head += ["relative error"] if has_truth else []
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, e in summary["params"].items():
        row = [name] + ([_fmt(e.get("true"))] if has_truth else [])
        row += [_fmt(e.get("initial")), _fmt(e.get("fitted"))]
        if has_truth:
            re = e.get("relative_error")
            row.append("-" if re is None else f"{100 * re:.3g} %")
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines)


def write_metrics(path, history) -> Path:
    """The fit history as JSON lines, one per evaluation: step, loss, params, grad_norm, wall_s
    (strict JSON: non-finite numbers are null)."""
    import json

    lines = []
    for k in range(len(history.loss)):
        row = {
            "step": k,
            "loss": float(history.loss[k]),
            "params": {n: np.asarray(v[k]) for n, v in history.params.items()},
            "grad_norm": {n: float(v[k]) for n, v in history.grad_norm.items()},
            "wall_s": float(history.wall_s[k]),
        }
        # strict JSON: a non-finite loss or gradient norm is written as null, never NaN
        lines.append(json.dumps(to_jsonable(row), allow_nan=False))
    path = Path(path)
    path.write_text("\n".join(lines) + ("\n" if lines else ""))
    return path


def write_fit_report(
    out_dir,
    result,
    truth: Mapping | None = None,
    initial: Mapping | None = None,
    *,
    target=None,
    fitted=None,
    fps: float = 10.0,
    gain: float = 1.0,
    identifiability=None,
    extra_sections: Mapping[str, str] | Sequence[str] | None = None,
    title: str = "Fit report",
    plots: bool = True,
    colorspace: str = "srgb",
) -> dict[str, Path]:
    """Write result.json, loss.png, params.png, compare.gif and report.md into `out_dir`.

    Args:
      out_dir: folder (created).
      result: a FitResult (`diffcloth.fit.FitResult`).
      truth: name -> true value, when known (synthetic targets).
      initial: name -> initial value (default `result.initial`).
      target, fitted: target and fitted images or videos ((T,) H, W, C) for compare.gif.
      fps: frame rate of compare.gif.  gain: brightening of the difference panel.
      identifiability: an `Identifiability` (its table is added to report.md, its numbers to
        identifiability.json).
      extra_sections: {heading: markdown} or a list of markdown blocks appended to report.md.
      plots: draw loss.png and params.png (needs matplotlib).
      colorspace: "srgb" (default): target and fitted are linear RGB (as rendered) and compare.gif
        is sRGB-encoded for viewing; "linear": they are written as given (already encoded).
    Returns:
      {"result", "metrics", "environment", "report", "loss", "params", "compare",
      "identifiability"}: the paths written.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    summary = fit_summary(result, truth, initial)
    paths: dict[str, Path] = {"result": save_json(out / "result.json", summary)}
    paths["metrics"] = write_metrics(out / "metrics.jsonl", result.history)
    from diffcloth.runtime import environment

    paths["environment"] = save_json(out / "environment.json", environment())
    if plots:
        from diffcloth.plots import plot_loss, plot_params

        paths["loss"] = plot_loss(result.history, out / "loss.png")
        paths["params"] = plot_params(result.history, out / "params.png", truth=truth)
    if target is not None and fitted is not None:
        frames = side_by_side(target, fitted, gain=gain)
        if frames.ndim == 3:
            paths["compare"] = save_png(out / "compare.png", frames, colorspace=colorspace)
        else:
            paths["compare"] = save_video(
                out / "compare.gif", frames, fps=fps, colorspace=colorspace
            )
    if identifiability is not None:
        from diffcloth.fit.identifiability import format_identifiability

        paths["identifiability"] = save_json(
            out / "identifiability.json", identifiability.to_dict()
        )

    md = [f"# {title}", ""]
    md.append(
        f"Status: **{getattr(result, 'status', '?')}** ({getattr(result, 'message', '')}). "
        f"Loss {_fmt(summary['loss'])} after {summary['iterations']} iterations in "
        f"{summary['wall_s']:.1f} s."
    )
    md += ["", _table(summary), ""]
    if "loss" in paths:
        md += ["## Convergence", "", "![loss](loss.png)", "", "![parameters](params.png)", ""]
    if "compare" in paths:
        name = paths["compare"].name
        enc = "sRGB-encoded for display" if colorspace == "srgb" else "values as given"
        md += [
            "## Target | fit | difference",
            "",
            f"![compare]({name})",
            "",
            f"Images are {enc}; the fit itself compares linear RGB.",
            "",
        ]
    md += [
        "3D viewer: [viewer.html](viewer.html), a recording that opens offline; DIR being this "
        "folder, write it with `diffcloth view DIR --export DIR/viewer.html`, or browse live with "
        "`diffcloth view DIR` (needs the `view` extra).",
        "",
    ]
    if identifiability is not None:
        md += ["## Identifiability", "", format_identifiability(identifiability), ""]
    if extra_sections:
        items = (
            extra_sections.items()
            if isinstance(extra_sections, Mapping)
            else [(None, s) for s in extra_sections]
        )
        for heading, body in items:
            if heading:
                md += [f"## {heading}", ""]
            md += [str(body).rstrip(), ""]
    paths["report"] = out / "report.md"
    paths["report"].write_text("\n".join(md).rstrip() + "\n")
    return paths


RESULTS_COLUMNS = (
    "experiment",
    "parameters",
    "max relative error",
    "loss",
    "iterations",
    "wall (s)",
    "report",
)


def results_row(experiment: str, summary: Mapping, report_link: str | None = None) -> dict:
    """A results/README.md row (RESULTS_COLUMNS) from a result.json dictionary."""
    errors = [e["relative_error"] for e in summary["params"].values() if "relative_error" in e]
    return {
        "experiment": experiment,
        "parameters": ", ".join(summary["params"]),
        "max relative error": f"{100 * max(errors):.3g} %" if errors else "-",
        "loss": "-" if summary["loss"] is None else f"{summary['loss']:.3g}",
        "iterations": str(summary["iterations"]),
        "wall (s)": f"{summary['wall_s']:.1f}",
        "report": f"[report]({report_link})" if report_link else "-",
    }


def _cell(v) -> str:
    v = to_jsonable(v) if not isinstance(v, str) else v
    if isinstance(v, float):
        v = f"{v:.4g}"
    return str(v).replace("|", "\\|").replace("\n", " ")


def append_results_row(
    readme_path, row: Mapping[str, Any], *, title: str = "Results", intro: str = ""
) -> Path:
    """Add (or replace, matched on the first column) one row of the table in a results README.

    The file is created with `# title`, `intro` and a table whose columns are the row's keys. An
    existing table keeps its columns; a row with keys it lacks raises ValueError; missing cells
    are "-".
    """
    path = Path(readme_path)
    lines = path.read_text().splitlines() if path.exists() else []
    idx = [i for i, line in enumerate(lines) if line.lstrip().startswith("|")]
    if not idx:
        columns = list(row)
        if not path.exists() or not lines:
            lines = [f"# {title}", ""] + ([intro, ""] if intro else [])
        else:
            lines = lines + [""]
        start = len(lines)
        lines += ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
        end = len(lines)
    else:
        start = idx[0]
        end = start
        while end < len(lines) and lines[end].lstrip().startswith("|"):
            end += 1
        columns = [c.strip() for c in lines[start].strip().strip("|").split("|")]
    extra = [k for k in row if k not in columns]
    if extra:
        raise ValueError(f"row keys {extra} are not columns of the table in {path}: {columns}")
    new = "| " + " | ".join(_cell(row.get(c, "-")) for c in columns) + " |"
    key = _cell(row.get(columns[0], ""))
    body = lines[start + 2 : end]
    replaced = False
    for j, line in enumerate(body):
        if line.strip().strip("|").split("|")[0].strip() == key:
            body[j] = new
            replaced = True
    if not replaced:
        body.append(new)
    lines = lines[: start + 2] + body + lines[end:]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")
    return path
