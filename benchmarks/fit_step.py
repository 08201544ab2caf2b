"""Fit step time of two commits, side by side: compile, forward, backward, per config.

    python benchmarks/fit_step.py --base d26acf4              # that commit vs this working tree
    python benchmarks/fit_step.py --base d26acf4 --new perf --configs configs/drape_fit.toml
    python benchmarks/fit_step.py --single                    # this tree only (e.g. on a GPU)

`--base` (a commit) is checked out with `git worktree add --detach` into a temporary folder;
`--new` is a commit too, or "WORKTREE" (default: this working tree as it is). Each (tree,
config) runs in a fresh Python process with the persistent compilation cache off, alternating
base and new for every repeat round, so both see the same machine load.

The step is the fit's loss and gradient: `value_and_grad` of `video_loss(simulate_and_render(
scene, params), targets, kind)` over the config's [fit] free parameters at their [fit.initial]
values, targets rendered at [truth] (as `diffcloth fit` does). One JSON line per (config, tree):
  bench "fit_step", config, tree ("base"/"new"), commit,
  compile_s  first value_and_grad call (trace + compile + run), s
  forward_ms loss value only (jitted), median
  step_ms    value and gradient (jitted), median;  backward_ms = step_ms - forward_ms
  xla_flags  XLA_FLAGS in that process after its imports (`import diffcloth` adds its CPU loop
             option since 0d0b6fd, 2026-11-27; older trees do not),
and one line per config with bench "fit_step_ratio": step_ratio, forward_ratio, backward_ratio,
compile_ratio (new / base, below 1: faster). With --single: the "new" lines only (tree "this",
commit from git where there is one), no base and no ratio.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from _timing import emit, meta

ROOT = Path(__file__).resolve().parent.parent
CONFIGS = ("configs/drape_fit.toml", "configs/experiments/drape_material.toml")

CHILD = r"""
import json, os, sys, time, tomllib
from pathlib import Path
sys.path.insert(0, sys.argv[4])
import jax, jax.numpy as jnp
from _timing import timed, compile_and_run
from diffcloth import pipeline
from diffcloth.fit.scene_fit import make_targets, video_loss
from diffcloth.scene import load_scene

path, repeats, tree = Path(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
raw = tomllib.loads(path.read_text())
fit = raw.get("fit", {})
kind = fit.get("loss", "l2")
scene = load_scene(path)
targets = jnp.asarray(make_targets(scene, raw.get("truth", {})), scene.material.stretch.dtype)
init = fit.get("initial", {})
params = {
    n: jnp.asarray(init[n] if n in init else pipeline.param_value(scene, n),
                   scene.material.stretch.dtype)
    for n in fit["free"]
}

def loss(p):
    return video_loss(pipeline.simulate_and_render(scene, p), targets, kind)

step = jax.jit(jax.value_and_grad(loss))
fwd = jax.jit(loss)
compile_s = compile_and_run(step, params)
t_step = timed(step, params, repeats=repeats)
t_fwd = timed(fwd, params, repeats=repeats)
back = round(t_step.median_ms - t_fwd.median_ms, 3)
print(json.dumps(dict(compile_s=round(compile_s, 3), forward_ms=t_fwd.median_ms,
                      step_ms=t_step.median_ms, backward_ms=back,
                      xla_flags=os.environ.get("XLA_FLAGS", ""))))
"""


def _run_child(tree: Path, config: str, repeats: int) -> dict:
    env = dict(os.environ, PYTHONPATH=str(tree), DIFFCLOTH_CACHE="off")
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    res = subprocess.run(
        [
            sys.executable,
            "-c",
            CHILD,
            str(tree / config),
            str(repeats),
            str(tree),
            str(ROOT / "benchmarks"),
        ],
        env=env,
        cwd=tree,
        capture_output=True,
        text=True,
        check=False,
    )
    if res.returncode != 0:
        raise RuntimeError(f"{tree} {config}: {res.stderr[-2000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def _commit(tree: Path) -> str | None:
    res = subprocess.run(
        ["git", "-C", str(tree), "rev-parse", "--short", "HEAD"],
        capture_output=True,
        text=True,
        check=False,
    )
    return res.stdout.strip() or None


def _single(args, out) -> None:
    """This tree alone: one line per config (no base, no ratio)."""
    for config in args.configs:
        rs = [_run_child(ROOT, config, args.repeats) for _ in range(args.rounds)]
        keys = ("compile_s", "forward_ms", "step_ms", "backward_ms")
        best = {k: min(r[k] for r in rs) for k in keys}
        row = dict(bench="fit_step", config=config, tree="this", commit=_commit(ROOT))
        emit(dict(row, rounds=args.rounds, **best, xla_flags=rs[-1]["xla_flags"]), out)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--base", help="the reference commit (required unless --single)")
    parser.add_argument("--single", action="store_true", help="time this tree only")
    parser.add_argument("--new", default="WORKTREE", help='a commit, or "WORKTREE"')
    parser.add_argument("--configs", nargs="+", default=list(CONFIGS))
    parser.add_argument("--repeats", type=int, default=5, help="timed calls per process")
    parser.add_argument("--rounds", type=int, default=1, help="fresh processes per tree")
    parser.add_argument("--out", help="also write the JSON lines to this file")
    args = parser.parse_args()
    if args.base is None and not args.single:
        parser.error("--base COMMIT is required (or --single for this tree alone)")
    out = open(args.out, "w") if args.out else None  # noqa: SIM115
    emit(meta("fit_step", base=args.base, new=args.new), out)
    if args.single:
        _single(args, out)
        if out is not None:
            out.close()
        return
    with tempfile.TemporaryDirectory(prefix="diffcloth_fit_step_") as tmp:
        trees = {}
        for name, ref in (("base", args.base), ("new", args.new)):
            if ref == "WORKTREE":
                trees[name] = ROOT
                continue
            path = Path(tmp) / name
            subprocess.run(
                ["git", "-C", str(ROOT), "worktree", "add", "--detach", str(path), ref],
                check=True,
                capture_output=True,
            )
            trees[name] = path
        try:
            commits = {name: _commit(path) for name, path in trees.items()}
            for config in args.configs:
                runs = {"base": [], "new": []}
                for _ in range(args.rounds):
                    for name in ("base", "new"):
                        runs[name].append(_run_child(trees[name], config, args.repeats))
                best = {}
                for name, rs in runs.items():
                    keys = ("compile_s", "forward_ms", "step_ms", "backward_ms")
                    best[name] = {k: min(r[k] for r in rs) for k in keys}
                    emit(
                        dict(
                            bench="fit_step",
                            config=config,
                            tree=name,
                            commit=commits[name],
                            rounds=args.rounds,
                            **best[name],
                            xla_flags=rs[-1]["xla_flags"],
                        ),
                        out,
                    )
                ratio = {
                    f"{k.rsplit('_', 1)[0]}_ratio": round(best["new"][k] / best["base"][k], 3)
                    for k in ("compile_s", "forward_ms", "step_ms", "backward_ms")
                }
                emit(dict(bench="fit_step_ratio", config=config, **ratio), out)
        finally:
            for path in trees.values():
                if path != ROOT:
                    subprocess.run(
                        ["git", "-C", str(ROOT), "worktree", "remove", "--force", str(path)],
                        check=False,
                        capture_output=True,
                    )
    if out is not None:
        out.close()


if __name__ == "__main__":
    main()
