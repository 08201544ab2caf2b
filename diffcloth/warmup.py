"""`diffcloth warmup`: compile a fit config's programs into the persistent compilation cache.

A fit's first run on a machine spends most of its time compiling (the main job,
`configs/drape_fit.toml`: about 40 of its 45 s on a 2-core CPU). Its programs depend on the
config's shapes and settings, not on the fitted values or the number of steps, so a one-step fit
of the same config compiles every one of them. `warmup` runs that fit into a temporary folder
(deleted afterwards) with the compilation cache on; a later `diffcloth fit` of the config with the
same cache folder, JAX version and flags (--x64) then loads them instead of compiling.

The work is not skipped, only moved: the warm-up itself takes as long as the cold first fit.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

__all__ = ["warmup"]


def warmup(configs, *, smoke: bool = False, log=print) -> list[dict]:
    """One-step fit of each config into a temporary folder, for the compilation cache.

    Args:
      configs: paths of fit configs (TOML with a [fit] section).
      smoke: warm up the `--smoke` variant (tiny sizes) instead.
      log: called with one line per config.
    Returns:
      One dict per config: config, seconds, status of the one-step fit.
    Raises:
      ConfigError, UsageError (ValueErrors) as `diffcloth fit` does, for any of the configs,
      before the first is compiled (`cli_commands.check_config` runs on all of them first).
    """
    import shutil

    from diffcloth import signals
    from diffcloth.cli_commands import check_config
    from diffcloth.experiment import run_fit_config

    for path in configs:  # every config's checks before any compilation
        check_config(path, "fit", smoke=smoke)
    rows = []
    for path in configs:
        t = time.perf_counter()
        with tempfile.TemporaryDirectory(prefix="diffcloth-warmup-") as tmp:
            # a signal ends the process with os._exit (diffcloth.signals): remove it then too
            hook = signals.at_abort(lambda tmp=tmp: shutil.rmtree(tmp, ignore_errors=True))
            try:
                summary = run_fit_config(
                    path, Path(tmp) / "fit", smoke=smoke, steps=1, progress=False,
                    checkpoint_every=0,
                )  # fmt: skip
            finally:
                signals.forget(hook)
        row = {"config": str(path), "seconds": time.perf_counter() - t, "status": summary["status"]}
        log(f"  {path}: compiled in {row['seconds']:.1f} s")
        rows.append(row)
    return rows
