"""Compile share of the main job: `diffcloth fit configs/drape_fit.toml`, run in a fresh
subprocess with an empty persistent compilation cache (cold), then again with that cache (warm).

One JSON line per run (schema: benchmarks/_timing.py):
  bench "compile", run ("cold" | "warm"), commit (git HEAD), wall_s (the whole CLI call),
  trace_s, lower_s, backend_compile_s (summed jax.monitoring durations: jaxpr tracing, MLIR
  lowering, XLA compilation incl. cache loads), programs (XLA compilations requested),
  cache_saved_s (compile time the persistent cache reported as saved),
  top_programs (the three slowest compilations, name and seconds, from jax_log_compiles),
  all_programs (with --programs: every compilation in order), fit (status, LM iterations and
  each parameter's relative error from result.json: the speed-ups must not change the fit).

    python benchmarks/compile.py [--config configs/drape_fit.toml] [--steps N] [--programs]
                                 [--cold-only]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

from _timing import emit, meta

ROOT = Path(__file__).resolve().parent.parent

_CHILD = r"""
import collections, json, logging, re, sys, time
import jax
from jax import monitoring
acc, cnt = collections.defaultdict(float), collections.Counter()
def on(event, duration, **kw):
    acc[event] += duration
    cnt[event] += 1
monitoring.register_event_duration_secs_listener(on)
progs = []
class H(logging.Handler):
    def emit(self, record):
        m = re.search(r"Finished XLA compilation of (.*) in ([0-9.e-]+) sec", record.getMessage())
        if m:
            progs.append((m.group(1), float(m.group(2))))
logging.getLogger("jax").addHandler(H())
jax.config.update("jax_log_compiles", True)
from diffcloth.cli import main
ALL = sys.argv[1] == "--programs"
if ALL:
    sys.argv.pop(1)
t = time.perf_counter()
rc = main(sys.argv[1:])
wall = time.perf_counter() - t
g = lambda k: round(acc.get(k, 0.0), 2)
print("RESULT " + json.dumps(dict(
    rc=rc, wall_s=round(wall, 1), trace_s=g("/jax/core/compile/jaxpr_trace_duration"),
    lower_s=g("/jax/core/compile/jaxpr_to_mlir_module_duration"),
    backend_compile_s=g("/jax/core/compile/backend_compile_duration"),
    programs=cnt["/jax/core/compile/backend_compile_duration"],
    cache_saved_s=g("/jax/compilation_cache/compile_time_saved_sec"),
    top_programs=[[n, round(s, 2)] for n, s in sorted(progs, key=lambda p: -p[1])[:3]],
    **({"all_programs": [[n, round(s, 3)] for n, s in progs]} if ALL else {}))))
"""


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default=str(ROOT / "configs" / "drape_fit.toml"))
    parser.add_argument("--steps", type=int, default=None, help="override [fit] steps")
    parser.add_argument(
        "--programs", action="store_true", help="add every compiled program (name, seconds)"
    )
    parser.add_argument("--cold-only", action="store_true", help="skip the warm run")
    args = parser.parse_args()
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True, cwd=ROOT, check=False).stdout.strip() or None  # fmt: skip
    emit(meta("compile"))
    with tempfile.TemporaryDirectory() as tmp:
        for run in ("cold",) if args.cold_only else ("cold", "warm"):
            cmd = [sys.executable, "-c", _CHILD] + (["--programs"] if args.programs else [])
            cmd += ["fit", args.config, "--out", f"{tmp}/{run}"]
            cmd += ["--cache", f"{tmp}/cache"]
            if args.steps is not None:
                cmd += ["--steps", str(args.steps)]
            out = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, check=False)
            lines = [ln for ln in out.stdout.splitlines() if ln.startswith("RESULT ")]
            if not lines:
                sys.exit(f"compile benchmark: the {run} run failed:\n{out.stderr[-2000:]}")
            row = json.loads(lines[-1][7:])
            res = json.loads(Path(f"{tmp}/{run}/result.json").read_text())
            row["fit"] = {"status": res["status"], "iterations": res["iterations"]}
            row["fit"].update(
                {f"{k}_rel_err": v.get("relative_error") for k, v in res["params"].items()}
            )
            emit(dict(bench="compile", run=run, commit=commit, **row))


if __name__ == "__main__":
    main()
