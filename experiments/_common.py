"""Shared glue of the experiment scripts: run a fit config, write results/<name>/ and a README row.

Holds no physics: it calls `diffcloth.experiment.run_fit_config` and `diffcloth.report`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from diffcloth import report
from diffcloth.experiment import run_fit_config

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "results"
README = RESULTS / "README.md"
INTRO = (
    "One row per experiment (scripts in `experiments/`, configs in `configs/experiments/`). "
    "Synthetic targets rendered from the true values; relative error |fitted - true| / |true| "
    "(Euclidean norm for vectors). Wall time is the fit loop only; see each report for the total "
    "including compilation and the Gauss-Newton identifiability table. Smoke runs write to "
    "`results/smoke/` and add no row here."
)


def _num(v) -> str:
    a = np.asarray(v, float)
    if a.ndim == 0:
        return f"{float(a):.4g}"
    return "[" + ", ".join(f"{x:.3g}" for x in a.ravel()) + "]"


def table_row(name: str, summary: dict, link: str | None) -> dict:
    """A README row with true, initial and fitted values and the relative error per parameter
    (its columns include `diffcloth.report.RESULTS_COLUMNS`)."""
    p = summary["params"]

    def col(key, fmt=_num):
        return "; ".join(f"{k} {fmt(e[key])}" for k, e in p.items() if e.get(key) is not None)

    row = report.results_row(name, summary, link)
    row.update(
        {
            "true": col("true"),
            "initial": col("initial"),
            "fitted": col("fitted"),
            "relative error": col("relative_error", lambda e: f"{100 * e:.2g} %"),
            "total (s)": f"{summary.get('total_s', float('nan')):.0f}",
        }
    )
    return row


def out_dir(name: str, smoke: bool) -> Path:
    return RESULTS / "smoke" / name if smoke else RESULTS / name


def add_row(name: str, summary: dict, smoke: bool) -> None:
    if not smoke:
        link = f"{name.split(' ')[0]}/report.md"
        try:
            report.append_results_row(
                README, table_row(name, summary, link), title="Experiment results", intro=INTRO
            )
        except ValueError:  # a table with only the standard columns: add the standard row
            report.append_results_row(README, report.results_row(name, summary, link))


def run_experiment(
    name: str, config_path, *, smoke: bool = False, title: str | None = None, extra_sections=None
) -> dict:
    """Fit one config into results/<name>/ (results/smoke/<name>/ for smoke) and add its row."""
    summary = run_fit_config(
        config_path,
        out_dir(name, smoke),
        smoke=smoke,
        progress=not smoke,
        title=title,
        extra_sections=extra_sections,
        overwrite=True,
    )
    add_row(name, summary, smoke)
    return summary


def cli(main, default_config: str, doc: str | None = None) -> None:
    """argparse front end: [config] [--smoke]."""
    ap = argparse.ArgumentParser(description=doc)
    ap.add_argument("config", nargs="?", default=str(ROOT / default_config))
    ap.add_argument("--smoke", action="store_true", help="tiny images, 4 frames, 2 steps")
    args = ap.parse_args()
    from diffcloth.signals import handle_signals

    with handle_signals():  # Ctrl-C / SIGTERM: the results folder is complete or untouched
        main(args.config, smoke=args.smoke)
