"""The grid net's physics figures and the main job's cold start, of two commits, in alternating
fresh processes (the grid path must not regress while other parts change).

    python benchmarks/grid_ab.py --base 667fe49                 # that commit vs HEAD
    python benchmarks/grid_ab.py --base 667fe49 --new WORKTREE --rounds 3 --skip-cold

Each tree is a `git worktree add --detach` checkout in a temporary folder ("WORKTREE": this
working tree as it is). Per round, for base then new (the order flips every round, so both see
the same drift of a shared machine's load): `benchmarks/physics.py --quick --integrators
symplectic --no-extras` of that tree (the explicit substep inside a 2,000-substep call,
step_rollout_us, and the gradient through 100 substeps, grad100_ms, of the 13 x 10 and 32 x 32
nets), and `benchmarks/compile.py --cold-only` (the whole `diffcloth fit configs/drape_fit.toml`
with an empty compilation cache, wall_s).

One JSON line per (round, tree, figure) with bench "grid_ab", then one "grid_ab_ratio" line per
figure: new / base of the medians over rounds (below 1: faster), with the per-round ratios.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from _timing import emit, meta

ROOT = Path(__file__).resolve().parent.parent


def checkout(commit: str, tmp: Path) -> Path:
    if commit == "WORKTREE":
        return ROOT
    path = tmp / commit
    subprocess.run(["git", "worktree", "add", "--detach", str(path), commit], cwd=ROOT,
                   check=True, capture_output=True)  # fmt: skip
    return path


def run_json(tree: Path, args: list[str]) -> list[dict]:
    env = dict(os.environ, PYTHONPATH=str(tree))
    out = subprocess.run([sys.executable, *args], cwd=tree, env=env, text=True,
                         capture_output=True, check=True).stdout  # fmt: skip
    rows = []
    for line in out.splitlines():
        if line.startswith("{"):
            rows.append(json.loads(line))
    return rows


def figures(tree: Path, cold: bool) -> dict[str, float]:
    out = {}
    for r in run_json(tree, ["benchmarks/physics.py", "--quick", "--integrators", "symplectic",
                             "--no-extras"]):  # fmt: skip
        if r.get("bench") == "physics" and "step_rollout_us" in r:  # the symplectic rows
            out[f"step_rollout_us_{r['net']}"] = r["step_rollout_us"]
            out[f"grad100_ms_{r['net']}"] = r["grad100_ms"]
    if cold:
        for r in run_json(tree, ["benchmarks/compile.py", "--cold-only"]):
            if r.get("run") == "cold":
                out["main_job_cold_s"] = r["wall_s"]
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--base", required=True, help="the reference commit")
    ap.add_argument("--new", default="HEAD", help='a commit, or "WORKTREE"')
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--skip-cold", action="store_true", help="physics figures only")
    ap.add_argument("--out", help="also append the JSON lines to this file")
    args = ap.parse_args(argv)
    out = open(args.out, "a") if args.out else None  # noqa: SIM115
    emit(meta("grid_ab", base=args.base, new=args.new), out)
    with tempfile.TemporaryDirectory(prefix="diffcloth_grid_ab_") as tmp:
        trees = {}
        try:
            trees = {"base": checkout(args.base, Path(tmp)), "new": checkout(args.new, Path(tmp))}
            got: dict[str, list[dict]] = {"base": [], "new": []}
            for k in range(args.rounds):
                order = ("base", "new") if k % 2 == 0 else ("new", "base")
                for name in order:
                    fig = figures(trees[name], not args.skip_cold)
                    got[name].append(fig)
                    emit(dict(bench="grid_ab", round=k, tree=name, load_1min=round(
                        os.getloadavg()[0], 2), **fig), out)  # fmt: skip
            for key in got["base"][0]:
                b = [r[key] for r in got["base"] if key in r]
                n = [r[key] for r in got["new"] if key in r]
                emit(dict(bench="grid_ab_ratio", figure=key, base=args.base, new=args.new,
                          base_median=statistics.median(b), new_median=statistics.median(n),
                          ratio=round(statistics.median(n) / statistics.median(b), 3),
                          round_ratios=[round(y / x, 3) for x, y in zip(b, n, strict=False)]),
                     out)  # fmt: skip
        finally:
            for path in trees.values():
                if path != ROOT:
                    subprocess.run(["git", "worktree", "remove", "--force", str(path)], cwd=ROOT,
                                   capture_output=True)  # fmt: skip
    if out:
        out.close()


if __name__ == "__main__":
    main()
