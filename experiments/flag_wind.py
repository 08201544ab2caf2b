"""Experiment 2: normal and tangential drag coefficients and the wind velocity of a flag pinned on
its left edge.

    python experiments/flag_wind.py [config] [--smoke]

Writes results/flag_wind/ (report.md, result.json, loss.png, params.png, compare.gif,
identifiability.json) and a row in results/README.md. Default config:
configs/experiments/flag_wind.toml.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import cli, run_experiment  # noqa: E402

CONFIG = "configs/experiments/flag_wind.toml"


def main(config_path=None, *, smoke: bool = False) -> dict:
    """Run the fit of config_path (default CONFIG); returns the result.json summary."""
    config_path = Path(config_path or Path(__file__).resolve().parents[1] / CONFIG)
    name = config_path.stem
    return run_experiment(
        name, config_path, smoke=smoke, title="Flag in wind: drag_normal, drag_tangent, wind"
    )


if __name__ == "__main__":
    cli(main, CONFIG, __doc__)
