"""The cross-engine drape fitted from the command line: `diffcloth fit` of
configs/footage_example.toml per stiffness regime, start and rendering, one fresh process each.

    python -m benchmarks.cross_engine.generate --cases drape:soft drape:stiff   # the footage
    python -m benchmarks.cross_engine.config_fits                 # every run, then the table
    python -m benchmarks.cross_engine.config_fits --runs soft_k0.37_air2.9 soft_k0.37_air2.9_sh
    python -m benchmarks.cross_engine.config_fits --table         # the table of recorded runs

A run is REGIME_GUESS[_sh]: the regime's footage (soft: k_struct 40 N/m, stiff 400; air damping
0.01 N s/m); the guess: "generic" (the config's: k_struct 100, air damping 0.002) or kA_airB
(A and B times the truth: off the 2^k scan grids around the truth); "_sh": the fit's scene
draws the floor, the light's shadows (shadow_quality "fit") and the occluded ambient light (8
sky directions), as the Mitsuba frames show them. Each run's config is written next to its
output (OUT/NAME.toml); one JSON line per run (errors, status, wall time, the machine's load)
is appended to config_fits.jsonl. Runs are sequential: compare times within one invocation.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
CONFIG = ROOT / "configs" / "footage_example.toml"
TRUTH = {"soft": 40.0, "stiff": 400.0}
AIR = 0.01
GUESSES = {"generic": None, "k0.37_air2.9": (0.37, 2.9), "k2.9_air0.37": (2.9, 0.37)}
SHADOWS = 'draw_planes = true\nplane_color = [0.5, 0.5, 0.5]\nambient_occlusion = 8\nshadow_quality = "fit"\n'
RUNS = [f"{r}_{g}{s}" for r in TRUTH for g in GUESSES for s in ("", "_sh")]


def config_text(name: str) -> str:
    """footage_example.toml for the run `name` (absolute target path, regime, guess, shadows)."""
    regime, rest = name.split("_", 1)
    shadows = rest.endswith("_sh")
    guess = GUESSES[rest[:-3] if shadows else rest]
    data = ROOT / "benchmarks" / "cross_engine" / "data" / f"drape_{regime}.npz"
    t = CONFIG.read_text()
    t = t.replace('"../benchmarks/cross_engine/data/drape_soft.npz"', f'"{data}"')
    t = t.replace("--cases drape:soft", f"--cases drape:{regime}")
    t = t.replace(
        "k_struct = 40.0\nair_damping = 0.01", f"k_struct = {TRUTH[regime]}\nair_damping = {AIR}"
    )
    if shadows:
        t = t.replace("[render]\n", "[render]\n" + SHADOWS, 1)
        t = t.replace("intensity = 1.0\n", "intensity = 1.0\nshadows = true\n", 1)
    if guess is not None:
        k, a = guess
        t = t.replace("\n[truth]", f"\n[fit.initial]\nk_struct = {k * TRUTH[regime]:g}\n"
                      f"air_damping = {a * AIR:g}\n\n[truth]")  # fmt: skip
    return t


def load() -> str:
    return " ".join(f"{x:.1f}" for x in os.getloadavg())


def run(name: str, out: Path, log: Path) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    cfg = out / f"{name}.toml"
    cfg.write_text(config_text(name))
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT,
                            capture_output=True, text=True).stdout.strip()  # fmt: skip
    row = {"run": name, "commit": commit, "load_start": load()}
    t0 = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-m", "diffcloth", "fit", str(cfg), "--out", str(out / name), "--overwrite"],
        cwd=ROOT, capture_output=True, text=True,
    )  # fmt: skip
    row.update(wall_s=round(time.perf_counter() - t0, 1), load_end=load(), rc=proc.returncode)
    row.update(collect(out / name, name))
    with log.open("a") as fh:
        fh.write(json.dumps(row) + "\n")
    print(json.dumps(row), flush=True)
    return row


def collect(folder: Path, name: str) -> dict:
    """Errors, status and times of a finished run's result.json."""
    path = folder / "result.json"
    if not path.is_file():
        return {"status": "missing"}
    r = json.loads(path.read_text())
    regime = name.split("_", 1)[0]
    truth = {"k_struct": TRUTH[regime], "air_damping": AIR}
    p = r["params"]
    return {
        "status": r["status"],
        "initial": {k: p[k]["initial"] for k in truth},
        "fitted": {k: p[k]["fitted"] for k in truth},
        "err_pct": {k: round(100 * (p[k]["fitted"] / truth[k] - 1), 2) for k in truth},
        "fit_s": round(r["wall_s"], 1),
        "total_s": round(r["total_s"], 1),
        "stages": [s["name"] for s in r.get("stages", [])],
    }


def table(rows: list[dict]) -> str:
    """Markdown: one row per run (the last record of each), shadows next to its plain run."""
    last = {r["run"]: r for r in rows}
    lines = [
        "| run | start k_struct / air | k_struct err | air damping err | status | s (with "
        "compilation) | load at start | commit |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name in RUNS:
        r = last.get(name)
        if r is None or "err_pct" not in r:
            continue
        e, i = r["err_pct"], r["initial"]
        lines.append(
            f"| {name} | {i['k_struct']:g} / {i['air_damping']:g} | {e['k_struct']:+.2f} % | "
            f"{e['air_damping']:+.2f} % | {r['status']} | {r['total_s']:.0f} | "
            f"{r['load_start']} | {r['commit']} |"
        )
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", nargs="*", default=RUNS, choices=RUNS)
    ap.add_argument("--out", default="/tmp/cross_engine_config_fits", help="configs and results")
    ap.add_argument("--log", default=str(HERE / "config_fits.jsonl"))
    ap.add_argument("--table", action="store_true", help="print the table of --log and stop")
    a = ap.parse_args(argv)
    log = Path(a.log)
    if not a.table:
        for name in a.runs:
            run(name, Path(a.out), log)
    rows = (
        [json.loads(x) for x in log.read_text().splitlines() if x.strip()] if log.is_file() else []
    )
    print(table(rows))


if __name__ == "__main__":
    main(sys.argv[1:])
