"""Hardening of the numba cache and of ``python -m auv_follow_env.warm``: a damaged cache file is
repaired (reported in one line, recompiled), and interrupting warm stops its compile jobs.

The cheap tests compile a one-line function in a private NUMBA_CACHE_DIR; the one test that
compiles the env's kernels (twice, like its reproducer) is marked slow."""

from __future__ import annotations

import os
import pickle
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from auv_follow_env import warm as warm_mod
from auv_follow_env.warm import CACHE_MESSAGE, JOBS, main, warm

ROOT = Path(__file__).resolve().parents[1]
#: 200 fixed bytes standing for the reproducer's os.urandom(200) (fixed so the test is deterministic)
JUNK = random.Random(17).randbytes(200)

_MOD = "from numba import njit\n\n\n@njit(cache=True)\ndef f(x):\n    return x + 1\n"
# the env's import path (auv_follow_env.sim installs the guard), then the cached function
_RUN = ("import auv_follow_env.sim, mod\n"
        "print(mod.f(1), sum(mod.f.stats.cache_hits.values()), sum(mod.f.stats.cache_misses.values()))")


def _env(tmp_path: Path) -> dict[str, str]:
    return {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache"),
            "PYTHONPATH": os.pathsep.join([str(tmp_path), str(ROOT)])}


def _run(tmp_path: Path, code: str = _RUN) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=_env(tmp_path), capture_output=True,
                          text=True, timeout=120)


def test_junk_is_not_a_pickle():
    with pytest.raises(Exception):  # noqa: B017 - whatever pickle raises on it
        pickle.loads(JUNK)


@pytest.mark.parametrize("ext", ["nbi", "nbc"])
def test_a_damaged_cache_file_is_reported_removed_and_recompiled(tmp_path, ext):
    """numba_cache_corrupt.sh: every cache index (and here also: every data file) overwritten with
    200 random bytes made each first call raise UnpicklingError. Now: the call returns the right
    value, one stderr line names the file and what to do, and the next process loads from the
    repaired cache without compiling."""
    (tmp_path / "mod.py").write_text(_MOD)
    first = _run(tmp_path)
    assert first.returncode == 0, first.stderr
    assert first.stdout.split() == ["2", "0", "1"]  # compiled (a miss), then saved
    damaged = sorted((tmp_path / "cache").rglob(f"*.{ext}"))
    assert damaged
    for path in damaged:
        path.write_bytes(JUNK)
    second = _run(tmp_path)
    assert second.returncode == 0, second.stderr
    assert "Traceback" not in second.stderr
    assert second.stdout.split()[0] == "2"
    lines = [line for line in second.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"{CACHE_MESSAGE} {damaged[0]} is unreadable (")
    assert "removed it and recompiling" in lines[0] and "auv_follow_env.warm" in lines[0]
    third = _run(tmp_path)
    assert third.returncode == 0 and not third.stderr.strip(), third.stderr
    assert third.stdout.split() == ["2", "1", "0"]  # loaded from the cache: a hit, nothing compiled


def test_warm_passes_the_repair_report_on(tmp_path, monkeypatch, capsys):
    """warm's jobs run in fresh processes whose stderr is kept only on failure: a repair must still
    reach the user (numba_cache_corrupt.sh runs warm on the damaged cache)."""
    (tmp_path / "mod.py").write_text(_MOD)
    assert _run(tmp_path).returncode == 0
    for path in (tmp_path / "cache").rglob("*.nbi"):
        path.write_bytes(JUNK)
    for key, value in _env(tmp_path).items():
        monkeypatch.setenv(key, value)
    monkeypatch.setitem(JOBS, "single", _RUN)
    assert set(warm(("single",), processes=1)) == {"single"}
    out = capsys.readouterr().out
    assert out.count(CACHE_MESSAGE) == 1 and "is unreadable (" in out


def test_a_failed_job_is_one_line_with_a_hint_and_its_log(monkeypatch, capsys):
    """What warm printed on a damaged cache before the guard: a raw traceback. A job that fails
    with an unpickling error gives one line naming the job, the error, the cache to delete and
    where the job's full output was saved; exit 1."""
    monkeypatch.setitem(JOBS, "single", f"import pickle; pickle.loads({JUNK!r})")
    assert main(["single", "--processes", "1"]) == 1
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1
    assert err[0].startswith("warm: job 'single' failed (exit 1): ") and "Error" in err[0]
    assert "numba's cache may be damaged: delete " in err[0]
    log = Path(err[0].rsplit("(its output: ", 1)[1].rstrip(")"))
    try:
        assert "Traceback" in log.read_text()
    finally:
        log.unlink()


def test_a_failing_job_stops_the_others(tmp_path, monkeypatch):
    pids = tmp_path / "pids"
    pids.mkdir()
    monkeypatch.setenv("PIDDIR", str(pids))
    monkeypatch.setitem(JOBS, "vector", "import os, time\nopen(os.path.join(os.environ['PIDDIR'], str(os.getpid())), "
                                        "'w').close()\ntime.sleep(120)")
    monkeypatch.setitem(JOBS, "single", "import os, sys, time\nwhile not os.listdir(os.environ['PIDDIR']):\n"
                                        "    time.sleep(0.05)\nsys.exit('boom')")
    with pytest.raises(warm_mod.WarmJobFailed, match="boom"):
        warm(("vector", "single"), verbose=False)
    for name in os.listdir(pids):
        with pytest.raises(ProcessLookupError):
            os.kill(int(name), 0)


_SLEEPERS = """
import signal, sys
signal.signal(signal.SIGINT, signal.default_int_handler)  # as from a terminal (see below)
import auv_follow_env.warm as w
job = "import os, time\\nopen(os.path.join(os.environ['PIDDIR'], str(os.getpid())), 'w').close()\\ntime.sleep(120)"
w.JOBS["single"] = w.JOBS["vector"] = job
sys.exit(w.main(["single", "vector"]))
"""


@pytest.mark.parametrize("sig, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_a_signal_to_warm_stops_its_jobs(tmp_path, sig, code):
    """warm_orphans.sh: SIGINT to the warm command alone (not its process group) printed a
    KeyboardInterrupt traceback and left both compile jobs running. Now both are gone when it
    exits, with one line and the signal's exit status; SIGTERM likewise."""
    pids = tmp_path / "pids"
    pids.mkdir()
    env = {**os.environ, "PIDDIR": str(pids), "PYTHONPATH": str(ROOT)}
    # as from a terminal: a test run started in the background (nohup, `&`) inherits SIGINT ignored,
    # and a Python started so never turns SIGINT into KeyboardInterrupt: _SLEEPERS installs Python's
    # default handler first (not a preexec_fn: that may deadlock a child forked from threads)
    parent = subprocess.Popen([sys.executable, "-c", _SLEEPERS], cwd=ROOT, env=env, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while len(os.listdir(pids)) < 2 and time.monotonic() < deadline and parent.poll() is None:
            time.sleep(0.05)
        kids = [int(name) for name in os.listdir(pids)]
        assert len(kids) == 2, parent.stderr.read() if parent.poll() is not None else "jobs did not start"
        parent.send_signal(sig)
        out, err = parent.communicate(timeout=30)
    finally:
        if parent.poll() is None:
            parent.kill()
    assert parent.returncode == code
    assert "Traceback" not in err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"warm: stopped by {signal.Signals(sig).name}")
    for pid in kids:
        with pytest.raises(ProcessLookupError):
            os.kill(pid, 0)


@pytest.mark.slow
def test_warm_and_the_env_recover_from_a_damaged_env_cache(tmp_path):
    """numba_cache_corrupt.sh end to end (compiles the single env twice: tens of seconds): warm
    into an empty cache, overwrite every index with random bytes, warm again (it must succeed and
    say what it repaired), then a Hard-v1 step in a new process loads without a message."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache"), "PYTHONPATH": str(ROOT)}
    cmd = [sys.executable, "-m", "auv_follow_env.warm", "single", "--processes", "1"]
    subprocess.run(cmd, cwd=ROOT, env=env, check=True, capture_output=True)
    for path in (tmp_path / "cache").rglob("*.nbi"):
        path.write_bytes(JUNK)
    res = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    assert "UnpicklingError" not in res.stderr + res.stdout and CACHE_MESSAGE in res.stdout
    step = ("import numpy as np, gymnasium as gym, auv_follow_env\n"
            "e = gym.make('AUVFollow-Hard-v1'); e.reset(seed=0); e.step(np.zeros(3))")
    res = subprocess.run([sys.executable, "-c", step], cwd=ROOT, env=env, capture_output=True, text=True)
    assert res.returncode == 0 and CACHE_MESSAGE not in res.stderr, res.stderr


def test_stopping_never_waits_for_ever_on_a_held_wait_lock():
    """The CI failure of test_a_signal_to_warm_stops_its_jobs[SIGINT]: Ctrl-C raised inside
    Popen.poll between its wait lock's acquisition and release left the lock held, and stopping
    the jobs then waited for ever on it. Now signals are acted on between polls only, and _stop
    bounds every wait: with the lock held it returns within its bounds (2 s + 5 s) and the job
    has been killed (a zombie until reaped, since the lock also keeps it from being reaped)."""
    proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"])
    assert proc._waitpid_lock.acquire(False)  # what the interrupted poll left behind
    try:
        t0 = time.monotonic()
        warm_mod._stop({"job": (proc, t0, open(os.devnull))})
        assert time.monotonic() - t0 < 60  # bounded (about 7 s: 2 s, then 5 s after the kill)
        state = Path(f"/proc/{proc.pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        assert state == "Z"  # killed, not yet reaped
    finally:
        proc._waitpid_lock.release()
        proc.kill()
        proc.wait(10)
    assert proc.returncode == -signal.SIGTERM  # stopped by _stop's terminate
