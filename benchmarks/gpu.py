"""The GPU column: the stage benchmarks on JAX's default backend, each bounded in time.

    python benchmarks/gpu.py --out DIR [--budget 480] [--only physics,render]

Runs, in this order (most wanted first), each as its own process with the backend JAX picks (a
GPU where jax has one; the code is the same as on the CPU):
  physics      benchmarks/physics.py, symplectic (13x10 .. 128x128; substep, 100-substep gradient)
  fit_step     the fit step (value + gradient) of the main job and drape_material, this tree only
  interactive  benchmarks/interactive.py (one frame of the default scene, per shading mode)
  render       benchmarks/render.py (rasterizer 256^2 and 512^2, forward and forward + backward)
  surface      benchmarks/surface.py (tessellation and gradient per level)
  compile      benchmarks/compile.py --cold-only (the whole main job, cold)
  shading      benchmarks/shading.py --no-grad (every shading mode, forward)
  physics_implicit  benchmarks/physics.py, implicit Euler, force layouts and gradient memory
Every case's JSON lines go, as they come, to one file DIR/gpu.jsonl, followed by a line
{"bench": "gpu_case", name, rc, seconds, lines}; the end of each case's stderr goes to
DIR/gpu_stderr.txt (two files: the device tool brings back at most 8). A case gets at most what
is left of --budget seconds (and at most its own cap): a slow or broken case costs its own lines,
never the others'. Nothing here is a test; the README's GPU column is read from gpu.jsonl.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent

#: (name, argv after the interpreter, cap in seconds)
CASES = (
    ("physics", [str(HERE / "physics.py"), "--integrators", "symplectic", "--no-extras"], 120),
    ("fit_step", [str(HERE / "fit_step.py"), "--single", "--repeats", "7"], 150),
    ("interactive", [str(HERE / "interactive.py"), "--repeats", "20"], 150),
    ("render", [str(HERE / "render.py"), "--repeats", "11"], 90),
    ("surface", [str(HERE / "surface.py"), "--repeats", "30"], 60),
    ("compile", [str(HERE / "compile.py"), "--cold-only"], 120),
    ("shading", [str(HERE / "shading.py"), "--no-grad"], 150),
    ("physics_implicit", [str(HERE / "physics.py"), "--integrators", "implicit"], 150),
)


def run_case(name: str, argv: list[str], limit: float, out: Path) -> dict:
    """Run one benchmark for at most `limit` s; its stdout lines are appended to out/gpu.jsonl,
    the last 4,000 characters of its stderr to out/gpu_stderr.txt."""
    env = dict(os.environ, PYTHONUNBUFFERED="1", PYTHONPATH=str(ROOT))
    jsonl = out / "gpu.jsonl"
    before = jsonl.stat().st_size if jsonl.exists() else 0
    t = time.perf_counter()
    with open(jsonl, "ab") as so, tempfile.TemporaryFile("w+") as se:
        try:
            rc = subprocess.run(
                [sys.executable, *argv], stdout=so, stderr=se, env=env, cwd=ROOT, timeout=limit
            ).returncode
        except subprocess.TimeoutExpired:
            rc = "timeout"
        se.seek(0)
        err = se.read()[-4000:]
    with open(out / "gpu_stderr.txt", "a") as f:
        f.write(f"## {name} (rc {rc})\n{err}\n")
    with open(jsonl, "rb") as f:
        f.seek(before)
        lines = sum(1 for ln in f.read().splitlines() if ln.startswith(b"{"))
    return dict(bench="gpu_case", name=name, rc=rc, seconds=round(time.perf_counter() - t, 1),
                lines=lines)  # fmt: skip


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True, help="folder for gpu.jsonl and gpu_stderr.txt")
    parser.add_argument("--budget", type=float, default=480.0, help="seconds for all cases")
    parser.add_argument("--only", default=None, help="comma-separated case names")
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    names = [c[0] for c in CASES]
    chosen = names if args.only is None else args.only.split(",")
    unknown = sorted(set(chosen) - set(names))
    if unknown:
        sys.exit(f"--only: unknown case(s) {unknown}; allowed: {', '.join(names)}")
    start = time.perf_counter()
    for name, argv, cap in CASES:
        if name not in chosen:
            continue
        left = args.budget - (time.perf_counter() - start)
        if left < 10:
            row = dict(bench="gpu_case", name=name, rc="not run", seconds=0.0, lines=0)
        else:
            row = run_case(name, argv, min(cap, left), out)
        print(json.dumps(row), flush=True)
        with open(out / "gpu.jsonl", "a") as f:
            f.write(json.dumps(row) + "\n")


if __name__ == "__main__":
    main()
