"""A fit result's data for the viewer (its summary, fitted values, loss curve) and the small
conversions the model shares (camera poses, sRGB colours)."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any

import numpy as np


def camera_pose(camera) -> dict[str, Any]:
    """eye, look-at point, up (3,) and vertical field of view (rad) of a `render.Camera`,
    recovered from its view and projection matrices (y up, OpenGL conventions)."""
    view = np.asarray(camera.view, np.float64)
    R, t = view[:3, :3], view[:3, 3]
    eye = -R.T @ t
    forward = -R[2]
    up = R[1]
    proj = np.asarray(camera.projection, np.float64)
    if camera.kind == "perspective" and proj[1, 1] > 0:
        fov = 2.0 * math.atan(1.0 / proj[1, 1])
    else:
        fov = math.radians(45.0)
    return {"eye": eye, "look_at": eye + forward, "up": up, "fov": fov}


def _srgb(rgb) -> tuple[int, int, int]:
    c = np.clip(np.asarray(rgb, np.float64), 0.0, 1.0) ** (1.0 / 2.2)
    return tuple(int(round(255 * v)) for v in c)


@dataclasses.dataclass
class FitData:
    """A fit result folder: fitted and target parameters, loss history, the result table."""

    folder: Path
    fitted: dict[str, np.ndarray]
    truth: dict[str, np.ndarray]
    summary: dict
    loss: np.ndarray  # (steps,)

    def table_markdown(self) -> str:
        """The parameter table of result.json as markdown."""
        rows = ["| parameter | true | initial | fitted | rel. error |", "|---|---|---|---|---|"]

        def fmt(v):
            if v is None:
                return "-"
            if isinstance(v, list):
                return "[" + ", ".join(fmt(a) for a in v) + "]"
            return f"{v:.4g}"

        for name, e in self.summary.get("params", {}).items():
            err = e.get("relative_error")
            rows.append(
                f"| {name} | {fmt(e.get('true'))} | {fmt(e.get('initial'))} | "
                f"{fmt(e.get('fitted'))} | {'-' if err is None else f'{100 * err:.3g} %'} |"
            )
        return "\n".join(rows)


def _read_fit(folder: Path) -> tuple[dict, dict, np.ndarray]:
    summary = json.loads((folder / "result.json").read_text())
    fitted = {n: np.asarray(e["fitted"], np.float64) for n, e in summary["params"].items()}
    loss = []
    metrics = folder / "metrics.jsonl"
    if metrics.exists():
        for line in metrics.read_text().splitlines():
            if line.strip():
                loss.append(float(json.loads(line)["loss"]))
    return summary, fitted, np.asarray(loss)
