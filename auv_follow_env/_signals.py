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


#: the signals a scheduler, `timeout` or a closed terminal sends to stop a command
STOP_SIGNALS: tuple[int, ...] = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


_received: list[int] = []  #: the stop signals received by this process, oldest first


def record_stop(signum: int) -> None:
    """Note that ``signum`` asked this process to stop (read by :func:`last_stop`)."""
    _received.append(int(signum))


def last_stop() -> int:
    """The newest stop signal received (SIGINT if none was recorded: a KeyboardInterrupt)."""
    return _received[-1] if _received else int(signal.SIGINT)


class SignalStop(KeyboardInterrupt):
    """SIGTERM or SIGHUP, raised like KeyboardInterrupt for SIGINT, so that every command's
    Ctrl-C path (save the model, keep the previous result set, resume later) serves them too."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = int(signum)


def exit_code(exc: BaseException | None = None) -> int:
    """The shell's exit status for a command stopped by ``exc`` (or by the newest recorded stop
    signal): 128 + the signal's number (143 for SIGTERM, 129 for SIGHUP, 130 for Ctrl-C)."""
    return 128 + _signum(exc)


def _signum(exc: BaseException | None) -> int:
    if isinstance(exc, SignalStop):
        return exc.signum
    return last_stop() if exc is None else int(signal.SIGINT)


def stop_name(exc: BaseException | None = None) -> str:
    """" by SIGTERM" / " by SIGHUP" for a stop by those signals, "" for Ctrl-C."""
    signum = _signum(exc)
    return "" if signum == signal.SIGINT else f" by {signal.Signals(signum).name}"


@contextlib.contextmanager
def stop_on_signals() -> Iterator[None]:
    """Within the block SIGTERM and SIGHUP raise :class:`SignalStop` in the main thread (where
    they are left to the system, SIG_DFL; a SIGHUP ignored by ``nohup`` stays ignored)."""
    def stop(signum, frame) -> None:  # noqa: ARG001 - a signal handler's signature
        record_stop(signum)
        raise SignalStop(signum)

    previous: dict[int, object] = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGTERM, signal.SIGHUP):
            if signal.getsignal(sig) is signal.SIG_DFL:
                previous[sig] = signal.signal(sig, stop)
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
