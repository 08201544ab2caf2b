"""Results folders that are never half-written and never destroy an input: check first, lock, write
to a temporary folder, then move it into place.

    out = OutputDir(args.out, overwrite=args.overwrite, inputs=config_inputs(args.config))
    ...                                                    # compute
    out.tmp / "result.json" ...                            # write into the temporary folder
    out.commit()                                           # replace `--out` in one rename

What holds, for every command that writes a folder:
- Every check runs before any work. Refused (UsageError): "", an existing file, the current
  folder, one of its parents or the home folder, a non-empty folder without `overwrite`/`resume`,
  and a folder that holds or contains an input of the run (the config, the files it names such
  as targets or meshes, a checkpoint the run starts from), or lies inside an input folder --
  `overwrite` included, since results replace `--out` as a whole.
- One run at a time per folder: a lock file `.NAME.lock` next to it (flock; released by the
  kernel if the process dies) is taken before the checks of the folder's contents and held until
  the commit. A second run into the same `--out` is refused at once, naming the running one.
- Results go to a temporary folder `.NAME.tmp-*` next to the target (same file system, so the
  final rename is atomic), which is removed on any error or signal (`discard_all`, also run by
  `diffcloth.signals`). An older result is replaced as a whole only when complete, so a failed
  run leaves it untouched and no stale file of it survives.
- A symlinked `--out` is written through: the folder it points to is replaced, the link stays.
"""

from __future__ import annotations

import errno
import os
import shutil
import tempfile
import tomllib
from collections.abc import Iterable
from pathlib import Path

from diffcloth import signals

try:
    import fcntl
except ImportError:  # pragma: no cover  (Windows: no lock, the other guarantees hold)
    fcntl = None

__all__ = ["OutputDir", "UsageError", "config_inputs", "discard_all"]

_LIVE: list = []  # OutputDirs not yet committed or discarded (the CLI drops them on any error)


def discard_all() -> None:
    """Discard every temporary folder not yet moved into place (after an error or Ctrl-C)."""
    for d in list(_LIVE):
        d.discard()


signals.at_abort(discard_all)


class UsageError(ValueError):
    """A command-line argument is not allowed; the message says which and what is allowed."""


def _first_existing(path: Path) -> Path:
    p = path
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def config_inputs(config_path) -> list[tuple[str, Path]]:
    """The files a config run reads: ("config", path) and, for every string value of the TOML
    that names an existing file or folder (relative to the config's folder, as the config reads
    it: [fit] targets, meshes, textures), ("[section] key", path)."""
    path = Path(config_path)
    found: list[tuple[str, Path]] = [("config", path)]
    try:
        with path.open("rb") as fh:
            data = tomllib.load(fh)
    except (OSError, ValueError):  # load_config reports it
        return found
    base = path.parent
    home = base.resolve()

    def walk(value, where):
        if isinstance(value, dict):
            for k, v in value.items():
                walk(v, f"{where}.{k}" if where else str(k))
        elif isinstance(value, list):
            for v in value:
                walk(v, where)
        elif isinstance(value, str) and value.strip() and len(value) < 4096 and "\n" not in value:
            p = Path(value).expanduser()
            p = p if p.is_absolute() else base / p
            try:
                full = p.resolve()
                # "." and ".." name the config's own folders, not an input of their own (the
                # config file is one already): they would refuse every --out beside the config
                if p.exists() and full != home and full not in home.parents:
                    section, _, key = where.rpartition(".")
                    found.append((f"[{section}] {key}" if section else key, p))
            except (OSError, RuntimeError):
                pass

    walk(data, "")
    return found


def _as_inputs(inputs) -> list[tuple[str, Path]]:
    out = []
    for item in inputs or ():
        label, p = item if isinstance(item, tuple) else ("input", item)
        if p is not None:
            out.append((label, Path(p).expanduser()))
    return out


class OutputDir:
    """A results folder `path` that is written as a whole (see the module docstring).

    Args:
      path: the folder (created with its parents; a symlink is written through).
      overwrite: replace a non-empty folder as a whole.
      resume: allow a non-empty folder (a fit continuing from its checkpoint there).
      option: the option's name, for the messages.
      inputs: the run's inputs, (label, path) pairs or paths (see `config_inputs`): `path` may
        neither be, hold nor lie inside any of them.
    Raises UsageError (naming the option, the path and what is allowed) when `path` is refused.
    """

    def __init__(
        self,
        path,
        *,
        overwrite: bool = False,
        resume: bool = False,
        option="--out",
        inputs: Iterable = (),
    ):
        if path is None or str(path).strip() == "":
            raise UsageError(f"{option} must name a folder, got an empty string")
        self.path = Path(path).expanduser()
        self.option = option
        self._tmp: Path | None = None
        self._lock: int | None = None
        self._created: list[Path] = []
        self._replace = overwrite or resume
        p = self.path
        try:  # a symlinked --out: write into the folder it names
            real = self.real = p.resolve()
        except (OSError, RuntimeError) as err:  # a symlink loop
            raise UsageError(f"{option} {str(path)!r} cannot be resolved ({err})") from None
        here = Path.cwd().resolve()
        if real == here or real in here.parents or real == Path.home().resolve():
            raise UsageError(
                f"{option} {str(path)!r} is the current folder, one of its parents or the home "
                "folder; give a folder of its own for the results"
            )
        self._check_inputs(_as_inputs(inputs))
        if real.exists() and not real.is_dir():
            raise UsageError(f"{option} {str(p)!r} is an existing file; give a folder")
        parent = _first_existing(real.parent)
        if not parent.is_dir():
            raise UsageError(f"{option} {str(p)!r}: {str(parent)!r} is a file, not a folder")
        if real.is_dir() and not os.access(real, os.W_OK | os.X_OK):
            raise UsageError(f"{option} {str(p)!r} is not writable")
        with signals.deferred():  # a signal here must not leave a lock or a temporary folder
            try:  # the real test of writability (permissions, read-only file systems, root or not)
                self._make_parents(real.parent)
                self._take_lock()
                _LIVE.append(self)
                self._check_contents()
                self._tmp = Path(tempfile.mkdtemp(prefix=f".{real.name}.tmp-", dir=real.parent))
                os.chmod(self._tmp, 0o777 & ~_umask())  # a results folder, not a private one
            except OSError as err:
                self.discard()
                raise UsageError(
                    f"{option} {str(p)!r}: cannot write next to it in {str(real.parent)!r} "
                    f"({err.strerror or err})"
                ) from None
            except BaseException:
                self.discard()
                raise

    def _check_inputs(self, inputs: list[tuple[str, Path]]) -> None:
        real, option = self.real, self.option
        for label, p in inputs:
            try:
                full = p.resolve()
            except OSError:
                continue
            if full == real or real in full.parents:
                what = "is" if full == real else "holds"
                raise UsageError(
                    f"{option} {str(self.path)!r} {what} an input of this run ({label} "
                    f"{str(p)!r}); the results replace {option} as a whole, so the input would be "
                    f"lost (--overwrite too): choose a folder that holds no input"
                )
            if full.is_dir() and full in real.parents:
                raise UsageError(
                    f"{option} {str(self.path)!r} lies inside an input folder of this run "
                    f"({label} {str(p)!r}); choose a folder outside it"
                )

    def _make_parents(self, parent: Path) -> None:
        missing = []
        p = parent
        while not p.exists() and p != p.parent:
            missing.append(p)
            p = p.parent
        for d in reversed(missing):
            d.mkdir()
            self._created.append(d)

    def _take_lock(self) -> None:
        if fcntl is None:
            return
        lock = self.real.parent / f".{self.real.name}.lock"
        for _ in range(5):
            fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as err:
                if err.errno not in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
                    os.close(fd)
                    raise
                try:
                    who = os.read(fd, 64).decode(errors="replace").strip()
                finally:
                    os.close(fd)
                raise UsageError(
                    f"{self.option} {str(self.path)!r} is being written by another diffcloth run"
                    f"{f' (process {who})' if who else ''}; wait for it to finish, or choose "
                    "another folder"
                ) from None
            try:
                same = os.path.samestat(os.fstat(fd), os.stat(lock))
            except FileNotFoundError:
                same = False
            if same:  # not a lock file that its last holder removed meanwhile
                os.ftruncate(fd, 0)
                os.write(fd, f"{os.getpid()}\n".encode())
                self._lock = fd
                self._remove_stale()
                return
            os.close(fd)
        raise UsageError(f"{self.option} {str(self.path)!r}: could not lock it; try again")

    def _remove_stale(self) -> None:
        """Temporary folders of killed runs (only the lock holder writes them)."""
        for d in self.real.parent.glob(f".{self.real.name}.tmp-*"):
            shutil.rmtree(d, ignore_errors=True)

    def _release_lock(self) -> None:
        if self._lock is not None:
            try:
                os.unlink(self.real.parent / f".{self.real.name}.lock")
            except OSError:
                pass
            os.close(self._lock)
            self._lock = None

    def _check_contents(self) -> None:
        p, option = self.real, self.option
        if p.is_dir():
            entries = sorted(e.name for e in p.iterdir())
            if entries and not self._replace:
                shown = ", ".join(entries[:5]) + (", ..." if len(entries) > 5 else "")
                raise UsageError(
                    f"{option} {str(self.path)!r} is not empty ({len(entries)} entries: {shown}); "
                    "pass --overwrite to replace it, or choose a new folder"
                )

    @property
    def tmp(self) -> Path:
        """The temporary folder to write into (created on first use, next to `path`)."""
        if self._tmp is None:
            raise RuntimeError("OutputDir: already committed or discarded")
        return self._tmp

    def commit(self) -> Path:
        """Move the temporary folder into place, replacing an older `path` as a whole (only with
        overwrite/resume, or when it is empty). Returns `path` as given."""
        tmp, real = self.tmp, self.real
        with signals.deferred(f"the results in {str(self.path)!r} are complete"):
            try:
                os.rename(tmp, real)  # new or empty: one atomic step, refused if it was filled
            except OSError as err:
                if err.errno not in (errno.ENOTEMPTY, errno.EEXIST):
                    raise
                if not self._replace:
                    self.discard()
                    raise UsageError(
                        f"{self.option} {str(self.path)!r} was filled by another program while "
                        "this run worked; nothing of this run was written"
                    ) from None
                old = Path(tempfile.mkdtemp(prefix=f".{real.name}.old-", dir=real.parent))
                old.rmdir()
                os.rename(real, old)
                os.rename(tmp, real)
                shutil.rmtree(old, ignore_errors=True)
            self._tmp = None
            self._created = []
            self._release_lock()
            if self in _LIVE:
                _LIVE.remove(self)
        return self.path

    def discard(self) -> None:
        """Remove the temporary folder (nothing of this run is kept) and the parents it made."""
        if self._tmp is not None:
            shutil.rmtree(self._tmp, ignore_errors=True)
            self._tmp = None
        self._release_lock()
        for d in reversed(self._created):
            try:
                d.rmdir()
            except OSError:
                break
        self._created = []
        if self in _LIVE:
            _LIVE.remove(self)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask
