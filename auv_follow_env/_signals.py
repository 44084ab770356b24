"""Signals acted on at safe points, not wherever the interpreter happens to be.

Python runs a signal's handler between two bytecodes of the main thread; a handler that raises
(KeyboardInterrupt for Ctrl-C) can so land inside library code between a lock's acquisition and
its release (CPython's ``subprocess.Popen.poll``) or between two file moves that must happen
together. Masking the signal (``pthread_sigmask``) does not help: it masks the main thread only,
and the kernel then hands the signal to another thread (numba's, pyarrow's), whose delivery
still raises in the main thread. :func:`deferred_signals` instead swaps the handlers for one that
records the signal; the block calls the yielded ``deliver`` where an exception is safe, and
leaving the block delivers what is left. Used by ``python -m auv_follow_env.warm`` and by the
benchmark's output writer."""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Callable, Iterator


@contextlib.contextmanager
def deferred_signals(signals: tuple[int, ...]) -> Iterator[Callable[[], None]]:
    """Within the block, each of ``signals`` whose handler is a Python callable (Python's
    ``default_int_handler`` for SIGINT, or the caller's own) is only recorded; the yielded
    ``deliver()`` calls the original handlers for the signals recorded so far (so it raises
    what they raise), and leaving the block restores the handlers and delivers the rest, also
    when the block raised. Signals left to the system (SIG_DFL, SIG_IGN) are not touched, nor is
    anything outside the main thread (where no handler runs)."""
    pending: list[int] = []
    previous: dict[int, Callable] = {}

    def record(signum, frame) -> None:  # noqa: ARG001 - a signal handler's signature
        pending.append(signum)

    def deliver() -> None:
        while pending:
            sig = pending.pop(0)
            previous[sig](sig, None)

    if threading.current_thread() is threading.main_thread():
        for sig in dict.fromkeys(signals):
            handler = signal.getsignal(sig)
            if callable(handler):
                previous[sig] = handler
                signal.signal(sig, record)
    try:
        yield deliver
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        deliver()
