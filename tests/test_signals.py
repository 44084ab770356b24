"""auv_follow_env._signals.deferred_signals: a real signal sent inside the block is acted on at the
block's safe points (``deliver()``) or when it ends, never in between - also with other threads
alive, where masking the main thread (what the benchmark's writer did before) let the kernel hand
the signal to another thread and Python still raised in the middle of the block."""

from __future__ import annotations

import os
import signal
import threading
import time
from pathlib import Path

import pytest

from agents.benchmark.outputs import replace_set
from auv_follow_env._signals import deferred_signals


@pytest.fixture(autouse=True)
def python_sigint():
    """Python's own Ctrl-C handler (libraries imported by earlier tests, e.g. ray, install theirs)."""
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, old)


@pytest.fixture
def other_thread():
    """A second live thread, as numba's and pyarrow's pools are in a real run."""
    stop = threading.Event()
    t = threading.Thread(target=stop.wait, daemon=True)
    t.start()
    yield t
    stop.set()
    t.join()


def _ctrl_c_and_wait():
    os.kill(os.getpid(), signal.SIGINT)
    time.sleep(0.2)  # many bytecodes and a blocking call: an undeferred handler would have run here


def test_sigint_waits_for_the_end_of_the_block(other_thread):
    reached = []
    with pytest.raises(KeyboardInterrupt):
        with deferred_signals((signal.SIGINT,)):
            _ctrl_c_and_wait()
            reached.append("after the signal")
    assert reached == ["after the signal"]
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # restored


def test_deliver_acts_at_the_safe_point_and_only_once(other_thread):
    steps = []
    with deferred_signals((signal.SIGINT,)) as deliver:
        deliver()  # nothing recorded: nothing happens
        _ctrl_c_and_wait()
        steps.append("recorded")
        with pytest.raises(KeyboardInterrupt):
            deliver()
        steps.append("delivered")
    assert steps == ["recorded", "delivered"]  # and leaving the block raised nothing more


def test_the_callers_own_handler_is_what_runs(other_thread):
    got = []
    old = signal.signal(signal.SIGTERM, lambda signum, frame: got.append(signum))
    try:
        with deferred_signals((signal.SIGTERM,)):
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.2)
            assert got == []
        assert got == [signal.SIGTERM]
    finally:
        signal.signal(signal.SIGTERM, old)


def test_ignored_signals_stay_ignored():
    old = signal.signal(signal.SIGHUP, signal.SIG_IGN)
    try:
        with deferred_signals((signal.SIGHUP,)):
            assert signal.getsignal(signal.SIGHUP) == signal.SIG_IGN
            os.kill(os.getpid(), signal.SIGHUP)
    finally:
        signal.signal(signal.SIGHUP, old)


def test_a_real_ctrl_c_during_the_moves_lands_after_the_whole_new_set(tmp_path, monkeypatch, other_thread):
    """replace_set: SIGINT sent at the second of five moves; every move still happens (the folder
    holds the whole new set), then KeyboardInterrupt."""
    out, stage = tmp_path / "out", tmp_path / "out" / ".stage"
    stage.mkdir(parents=True)
    for f in ("a.txt", "b.txt"):
        (out / f).write_text("old " + f)
    for f in ("a.txt", "b.txt", "c.txt"):
        (stage / f).write_text("new " + f)
    real, n = os.replace, {"c": 0}

    def patched(src, dst, *a, **k):
        n["c"] += 1
        if n["c"] == 2:
            _ctrl_c_and_wait()
        return real(src, dst, *a, **k)

    monkeypatch.setattr(os, "replace", patched)
    with pytest.raises(KeyboardInterrupt):
        replace_set(stage, out, ["a.txt", "b.txt", "c.txt"])
    assert n["c"] == 5
    assert {f: (out / f).read_text() for f in ("a.txt", "b.txt", "c.txt")} == {
        f: "new " + f for f in ("a.txt", "b.txt", "c.txt")}
    assert not [p for p in Path(out).iterdir() if p.name.startswith(".benchmark-previous-")]
