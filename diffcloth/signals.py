"""Ctrl-C (SIGINT) and SIGTERM for every command: a complete result or nothing, exit 130 / 143.

    with handle_signals() as sig:      # cli.main, around the whole command
        ...                            # any work: a signal discards the temporary output, exits
        with sig.cooperate() as stop:  # a fit: the first signal only sets `stop`
            ...
        with deferred():               # moving a finished result into place: a signal waits
            ...

Python runs a signal handler in the main thread between two bytecodes, never inside a compiled
XLA call or a compilation: a signal that arrives during one is handled when it returns. The
handler installed here never raises (a KeyboardInterrupt raised there can land in a
garbage-collector callback, where Python prints it and drops it, or unwind through JAX's
internals). Instead it
- sets the cooperative event, the first time, while a command checks it (`cooperate`: a fit
  finishes its step, writes the checkpoint and a partial report, and exits 130 / 143);
- records the signal while a `deferred` block runs (creating or committing an output folder),
  and acts on it when the block ends;
- otherwise aborts: runs the abort hooks (`at_abort`: every temporary output folder is removed,
  child processes are stopped), prints one line and ends the process with os._exit(128 + signum),
  skipping the interpreter's teardown, where XLA's threads can crash a process that was
  interrupted mid-call (exit 139).
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator

__all__ = [
    "SignalState",
    "abort",
    "at_abort",
    "current",
    "deferred",
    "handle_signals",
    "signal_name",
]

_ABORT_HOOKS: list[Callable[[], None]] = []
_STATE: SignalState | None = None
_DEFER = {"depth": 0, "pending": None}
_exit = os._exit  # tests replace it (an in-process test must not end pytest)


def at_abort(fn: Callable[[], None]) -> Callable[[], None]:
    """Run `fn` (no arguments, must not block) when a signal aborts the command; returns `fn`."""
    if fn not in _ABORT_HOOKS:
        _ABORT_HOOKS.append(fn)
    return fn


def forget(fn: Callable[[], None]) -> None:
    """Undo `at_abort(fn)`."""
    if fn in _ABORT_HOOKS:
        _ABORT_HOOKS.remove(fn)


class SignalState:
    """The signals a command received: `signum` (the first one, or None) and `exit_code`."""

    def __init__(self, *, installed: bool = False):
        self.signum: int | None = None
        self.installed = installed
        self.event = threading.Event()
        self.event.signum = None  # type: ignore[attr-defined]
        self.message = True
        self._cooperative = 0

    @property
    def exit_code(self) -> int | None:
        """128 + the signal number (SIGINT 130, SIGTERM 143), or None without a signal."""
        return None if self.signum is None else 128 + self.signum

    @contextlib.contextmanager
    def cooperate(self, *, message: bool = True) -> Iterator[threading.Event]:
        """Inside the block the first signal only sets the yielded event (its `signum` names
        the signal): the command checks it and stops cleanly; a second signal aborts."""
        self._cooperative += 1
        old, self.message = self.message, message
        try:
            yield self.event
        finally:
            self._cooperative -= 1
            self.message = old


def current() -> SignalState | None:
    """The state of the innermost `handle_signals` block, or None outside one."""
    return _STATE


def signal_name(signum: int) -> str:
    """ "SIGINT", "SIGTERM", ... for a signal number."""
    try:
        return signal.Signals(signum).name
    except ValueError:
        return f"signal {signum}"


def abort(signum: int, note: str = "nothing written") -> None:
    """Run the abort hooks, print one line and end the process with exit code 128 + signum."""
    for fn in list(_ABORT_HOOKS):
        try:
            fn()
        except BaseException:  # noqa: BLE001  (the remaining hooks must still run)
            pass
    try:
        sys.stdout.flush()
        print(f"\ninterrupted by {signal_name(signum)} ({note})", file=sys.stderr, flush=True)
    except BaseException:  # noqa: BLE001  (a closed stream must not keep the process alive)
        pass
    _exit(128 + signum)


def _handler(signum, frame) -> None:
    state = _STATE
    if state is None:  # a handler left behind: behave like Python's default
        signal.default_int_handler(signum, frame)
        return
    if state.signum is None:
        state.signum = signum
    if state._cooperative and not state.event.is_set():
        state.event.signum = signum  # type: ignore[attr-defined]
        state.event.set()
        if state.message:
            print(
                f"\n{signal_name(signum)}: stopping after the current step and saving a checkpoint "
                "(send it again to stop at once, keeping nothing)",
                file=sys.stderr,
                flush=True,
            )
        return
    if _DEFER["depth"]:
        _DEFER["pending"] = _DEFER["pending"] or signum
        return
    abort(signum)


@contextlib.contextmanager
def deferred(note: str = "nothing written") -> Iterator[None]:
    """A block that a signal does not cut short: the signal is acted on when the block ends
    (`note` says what the process leaves then)."""
    _DEFER["depth"] += 1
    failed = False
    try:
        yield
    except BaseException:
        failed = True  # the block did not finish: it leaves nothing
        raise
    finally:
        _DEFER["depth"] -= 1
        pending = _DEFER["pending"]
        if not _DEFER["depth"] and pending is not None:
            _DEFER["pending"] = None
            state = _STATE
            if state is not None and not (state._cooperative and not state.event.is_set()):
                abort(pending, "nothing written" if failed else note)


@contextlib.contextmanager
def handle_signals(signals=(signal.SIGINT, signal.SIGTERM)) -> Iterator[SignalState]:
    """Install the handler (see the module docstring) for `signals` for the block; the previous
    handlers come back on exit. Off the main thread, where Python cannot install handlers, the
    state is yielded without handlers."""
    global _STATE
    if threading.current_thread() is not threading.main_thread():
        yield SignalState()
        return
    state = SignalState(installed=True)
    outer = _STATE
    _STATE = state
    previous = {}
    try:
        for s in signals:
            previous[s] = signal.signal(s, _handler)
        yield state
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
        _STATE = outer
