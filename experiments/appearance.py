"""Experiment 4: Minnaert exponent, bump strength and diffuse colour from still images of a known
shape.

    python experiments/appearance.py [config] [--smoke]

Writes results/appearance/ (report.md, result.json, loss.png, params.png, compare.gif,
identifiability.json) and a row in results/README.md. Default config:
configs/experiments/appearance.toml.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import cli, run_experiment  # noqa: E402

CONFIG = "configs/experiments/appearance.toml"


def main(config_path=None, *, smoke: bool = False) -> dict:
    """Run the fit of config_path (default CONFIG); returns the result.json summary."""
    config_path = Path(config_path or Path(__file__).resolve().parents[1] / CONFIG)
    name = config_path.stem
    return run_experiment(
        name, config_path, smoke=smoke, title="Appearance: minnaert_k, bump_strength, diffuse"
    )


if __name__ == "__main__":
    cli(main, CONFIG, __doc__)
