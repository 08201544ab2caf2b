"""Results folders that are never half-written: check first, write to a temporary folder, then
move it into place.

    out = OutputDir(args.out, overwrite=args.overwrite)   # every check, before any work
    ...                                                    # compute
    out.tmp / "result.json" ...                            # write into the temporary folder
    out.commit()                                           # replace `--out` in one rename

The temporary folder sits next to the target (same file system, so the final rename is atomic).
An existing non-empty folder is refused unless `overwrite` (then it is replaced as a whole, so no
stale file of an older run survives) or `resume` (a fit continuing from its checkpoint).
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

__all__ = ["OutputDir", "UsageError", "discard_all"]

_LIVE: list = []  # OutputDirs not yet committed or discarded (the CLI drops them on any error)


def discard_all() -> None:
    """Discard every temporary folder not yet moved into place (after an error or Ctrl-C)."""
    for d in list(_LIVE):
        d.discard()


class UsageError(ValueError):
    """A command-line argument is not allowed; the message says which and what is allowed."""


def _first_existing(path: Path) -> Path:
    p = path
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


class OutputDir:
    """A results folder `path` that is written as a whole (see the module docstring).

    Raises UsageError (naming the option, the path and what is allowed) when `path` is "", an
    existing file, a non-empty folder without `overwrite`/`resume`, or not writable.
    """

    def __init__(self, path, *, overwrite: bool = False, resume: bool = False, option="--out"):
        if path is None or str(path).strip() == "":
            raise UsageError(f"{option} must name a folder, got an empty string")
        self.path = Path(path).expanduser()
        self.option = option
        self._tmp: Path | None = None
        p = self.path
        here = Path.cwd().resolve()
        full = p.resolve()
        if full == here or full in here.parents or full == Path.home().resolve():
            raise UsageError(
                f"{option} {str(path)!r} is the current folder, one of its parents or the home "
                "folder; give a folder of its own for the results"
            )
        if p.exists() and not p.is_dir():
            raise UsageError(f"{option} {str(p)!r} is an existing file; give a folder")
        if p.is_dir():
            entries = sorted(e.name for e in p.iterdir())
            if entries and not (overwrite or resume):
                shown = ", ".join(entries[:5]) + (", ..." if len(entries) > 5 else "")
                raise UsageError(
                    f"{option} {str(p)!r} is not empty ({len(entries)} entries: {shown}); "
                    "pass --overwrite to replace it, or choose a new folder"
                )
        parent = _first_existing(p.parent)
        if not parent.is_dir():
            raise UsageError(f"{option} {str(p)!r}: {str(parent)!r} is a file, not a folder")
        if p.is_dir() and not os.access(p, os.W_OK | os.X_OK):
            raise UsageError(f"{option} {str(p)!r} is not writable")
        try:  # the real test of writability (permissions, read-only file systems, root or not)
            p.parent.mkdir(parents=True, exist_ok=True)
            self._tmp = Path(tempfile.mkdtemp(prefix=f".{p.name}.tmp-", dir=p.parent))
            _LIVE.append(self)
        except OSError as err:
            raise UsageError(
                f"{option} {str(p)!r}: cannot write next to it in {str(p.parent)!r} "
                f"({err.strerror or err})"
            ) from None

    @property
    def tmp(self) -> Path:
        """The temporary folder to write into (created on first use, next to `path`)."""
        if self._tmp is None:
            raise RuntimeError("OutputDir: already committed or discarded")
        return self._tmp

    def commit(self) -> Path:
        """Move the temporary folder into place, replacing an older `path` as a whole."""
        tmp = self.tmp
        old = None
        if self.path.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.old-", dir=self.path.parent))
            old.rmdir()
            os.replace(self.path, old)
        os.replace(tmp, self.path)
        self._tmp = None
        if self in _LIVE:
            _LIVE.remove(self)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
        return self.path

    def discard(self) -> None:
        """Remove the temporary folder (nothing of this run is kept)."""
        if self._tmp is not None:
            shutil.rmtree(self._tmp, ignore_errors=True)
            self._tmp = None
        if self in _LIVE:
            _LIVE.remove(self)
