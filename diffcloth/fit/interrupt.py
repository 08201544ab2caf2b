"""Ctrl-C (SIGINT) and SIGTERM during a fit: finish the step, save, stop cleanly.

    with catch_interrupts() as stop:
        result = dc.fit.fit(scene, targets, ["bend"], stop=stop, checkpoint_path="ck.npz")
    if result.status == "interrupted": ...   # resume later with resume="ck.npz"

The first signal sets the event (the fit loop checks it after every step, writes its checkpoint
and returns with status "interrupted"). A signal that arrives while XLA compiles or runs a compiled
call is handled when the call returns to Python. Inside the command line's
`diffcloth.signals.handle_signals` (every `diffcloth` command) this only marks the block as
cooperative: a second signal there discards the temporary output and exits 130 / 143 at once.
Elsewhere (a script of your own) handlers are installed for the block, and a second signal
raises KeyboardInterrupt.
"""

from __future__ import annotations

import contextlib
import signal
import sys
import threading
from collections.abc import Iterator

__all__ = ["catch_interrupts"]


@contextlib.contextmanager
def catch_interrupts(
    signals=(signal.SIGINT, signal.SIGTERM), *, message: bool = True
) -> Iterator[threading.Event]:
    """Install handlers for `signals` that set the yielded event (the previous handlers are put
    back on exit). Off the main thread (where Python cannot install handlers) the event is
    yielded without handlers. The event's `signum` attribute names the signal received."""
    from diffcloth import signals as shared

    state = shared.current()
    if state is not None and state.installed:
        with state.cooperate(message=message) as event:
            yield event
        return
    event = threading.Event()
    event.signum = None  # type: ignore[attr-defined]
    if threading.current_thread() is not threading.main_thread():
        yield event
        return

    def handler(signum, frame):
        if event.is_set():
            raise KeyboardInterrupt
        event.signum = signum  # type: ignore[attr-defined]
        event.set()
        if message:
            print(
                f"\n{signal.Signals(signum).name}: stopping after the current step and saving a "
                "checkpoint (send it again to stop at once)",
                file=sys.stderr,
                flush=True,
            )

    previous = {s: signal.signal(s, handler) for s in signals}
    try:
        yield event
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
