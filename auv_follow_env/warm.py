"""Compile the env's numba kernels ahead of their first use: ``python -m auv_follow_env.warm``.

numba compiles the kernels at their first call and keeps the machine code in its on-disk
cache (``__pycache__`` beside the sources, or ``NUMBA_CACHE_DIR``); later processes load it in
well under a second. On a fresh clone the first ``reset(); step(a)`` therefore pays the
compilation: about 20 s of CPU for the single env on this project's 2-core machines, 15-30 s
more for each of the vector env's serial and threaded kernels (results/bench_vector.md).
``scripts/setup.sh`` runs this module once after installing, so the first step a newcomer
takes loads from the cache instead; with the cache in place the module takes a second or two.

Each job runs in a fresh process (the first reset and step of what it names), at most
``--processes`` at once (numba compiles on one thread; the jobs share no compiled code that
they could not also write to the cache themselves, and the cache's writes are atomic):

========== ==================================================================================
job        what it compiles
========== ==================================================================================
single     the single env's reset and step for float32 and float64 actions (``gym.make(id)``)
vector     the native vector env's serial step and reset kernels (``parallel=False``)
parallel   the vector env's threaded step kernel (``parallel=True``; skipped with one thread)
========== ==================================================================================

Every id shares these kernels (v0 and v1: the same array types), so one id compiles them for
all. The vector env hands its kernels float64 actions whatever the caller's dtype (float32 to
float64 is exact), so one specialisation serves both; the single env's step (kernel_one) is
compiled for each dtype instead (a conversion costs about 0.4 us, a tenth of its step). What
the controllers and the metrics compile on their first use is not included.

Interrupting the command (Ctrl-C, SIGINT or SIGTERM to it alone) stops its running jobs too and
prints one line; what they had finished stays in the cache.

**A damaged cache repairs itself.** numba reads each function's cache index (``*.nbi``) and
data (``*.nbc``) with pickle; a file that cannot be read back (truncated by a full disk, or
overwritten) made every env raise ``UnpicklingError`` from deep inside numba. Importing the env
(:mod:`auv_follow_env.sim`) installs :func:`guard_numba_cache`: such a file is reported in one
line on stderr (its path and what to do), removed, and the function recompiled and cached again.
"""

from __future__ import annotations

import argparse
import glob
import os
import signal
import subprocess
import sys
import tempfile
import time
from typing import Any

from auv_follow_env._signals import deferred_signals

__all__ = ["JOBS", "warm", "main", "guard_numba_cache", "CACHE_MESSAGE", "WarmJobFailed"]

#: how the cache guard's line on stderr starts (warm passes such lines of its jobs on)
CACHE_MESSAGE = "auv_follow_env: numba cache file"
_GUARD_MARK = "_auv_follow_env_guard"
_reported: set[str] = set()  # cache folders already reported by this process


def _cache_folder_hint() -> str:
    d = os.environ.get("NUMBA_CACHE_DIR")
    return d if d else os.path.join(os.path.dirname(os.path.abspath(__file__)), "__pycache__")


def _repair(paths: list[str], exc: BaseException) -> None:
    """Remove the unreadable cache files ``paths`` (the first is the one that failed); report it
    once per cache folder and process, in one line on stderr."""
    failed = []
    for path in paths:
        try:
            os.remove(path)
        except FileNotFoundError:
            pass
        except OSError as e:
            failed.append(f"{path}: {e.strerror or e}")
    folder = os.path.dirname(paths[0])
    if folder in _reported and not failed:
        return
    _reported.add(folder)
    # (the exception's message, not its class: an "UnpicklingError" in the output reads as the crash it replaces)
    why = (str(exc).splitlines() or [""])[0][:120] or type(exc).__name__
    if failed:
        what = (f"could not remove it ({'; '.join(failed)}): delete the folder {folder} by hand and run "
                f"`python -m auv_follow_env.warm`")
    else:
        what = (f"removed it and recompiling (further unreadable files in {folder} are replaced without a "
                f"message); if this repeats, delete that folder and run `python -m auv_follow_env.warm`")
    print(f"{CACHE_MESSAGE} {paths[0]} is unreadable (damaged: {why}): {what}", file=sys.stderr,
          flush=True)


def guard_numba_cache() -> bool:
    """Make numba's on-disk cache recover from a file it cannot read back, in this process.

    numba unpickles a function's index (``*.nbi``) and data files (``*.nbc``) at its first call;
    a damaged file raises ``UnpicklingError`` (or ``EOFError``, ``ValueError``, ...) there, every
    time. With the guard, such a file is removed and reported in one line on stderr (path, what to
    do), the function is compiled as if it had never been cached and saved again: one recompile,
    then the cache is whole. Errors reading the files (``OSError``, e.g. permissions) still raise.
    Idempotent; returns False (and changes nothing) if this numba has not the internals it wraps.
    """
    try:
        from numba.core import caching
    except ImportError:  # pragma: no cover - numba is a dependency
        return False
    files, cache = getattr(caching, "IndexDataCacheFile", None), getattr(caching, "Cache", None)
    if files is None or cache is None or not all(callable(getattr(files, n, None)) for n in
                                                 ("_load_index", "_load_data", "_data_path")) \
            or not callable(getattr(cache, "_load_overload", None)):
        return False
    if getattr(files._load_index, _GUARD_MARK, False):
        return True
    load_index, load_data, load_overload = files._load_index, files._load_data, cache._load_overload

    def _load_index(self):
        try:
            return load_index(self)
        except OSError:
            raise
        except Exception as exc:  # noqa: BLE001 - whatever unpickling a damaged file raises
            _repair([self._index_path], exc)
            return {}  # (as for a missing index: the function compiles and a new index is saved)

    def _load_data(self, name):
        try:
            return load_data(self, name)
        except OSError:
            raise
        except Exception as exc:  # noqa: BLE001
            _repair([self._data_path(name)], exc)
            return None  # (as for an entry that is not cached: the function compiles)

    def _load_overload(self, sig, target_context):
        try:
            return load_overload(self, sig, target_context)
        except OSError:
            raise
        except Exception as exc:  # noqa: BLE001 - a data file that unpickles but cannot be rebuilt
            cf = self._cache_file
            base = cf._index_path[:-len(".nbi")]
            _repair([cf._index_path] + sorted(glob.glob(glob.escape(base) + ".*.nbc")), exc)
            return None

    for f in (_load_index, _load_data, _load_overload):
        setattr(f, _GUARD_MARK, True)
    files._load_index, files._load_data, cache._load_overload = _load_index, _load_data, _load_overload
    return True


class WarmJobFailed(RuntimeError):
    """A warm job exited non-zero; ``job``, ``returncode`` and its ``stderr`` are attributes."""

    def __init__(self, job: str, returncode: int, stderr: str) -> None:
        super().__init__(f"warm job {job!r} failed (exit {returncode}):\n{stderr}")
        self.job, self.returncode, self.stderr = job, returncode, stderr


class _Stopped(BaseException):
    """SIGTERM or SIGHUP to the command (raised by its handler, like KeyboardInterrupt for SIGINT;
    :func:`warm` runs the handlers only between its polls of the jobs)."""


def _stop(running: dict) -> None:
    """Terminate the running jobs, wait briefly, kill those left; close their logs. Never waits
    without a bound: an exception raised asynchronously inside ``Popen.poll`` (a signal handler's)
    can leave the Popen's internal wait lock held, and an unbounded ``wait`` would then block for
    ever (the killed job is reaped when this process exits)."""
    for proc, _, _ in running.values():
        if proc.poll() is None:
            proc.terminate()
    deadline = time.monotonic() + 2.0
    for proc, _, log in running.values():
        try:
            proc.wait(max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            proc.kill()
            try:
                proc.wait(5.0)
            except subprocess.TimeoutExpired:
                pass
        log.close()
    running.clear()


#: job name -> Python code run in a fresh process (argv[1] the env id)
JOBS: dict[str, str] = {
    "single": ("import sys, numpy as np, gymnasium as gym, auv_follow_env\n"
               "e = gym.make(sys.argv[1]); e.reset(seed=0); e.step(np.zeros(3, np.float32)); e.step(np.zeros(3))"),
    "vector": ("import sys, numpy as np, gymnasium as gym, auv_follow_env\n"
               "v = gym.make_vec(sys.argv[1], num_envs=2, vectorization_mode='vector_entry_point', parallel=False)\n"
               "v.reset(seed=0); v.step(np.zeros((2, 3), np.float32))"),
    "parallel": ("import sys, numpy as np, gymnasium as gym, auv_follow_env\n"
                 "from auv_follow_env.vector_env import _num_threads\n"
                 "if _num_threads() > 1:\n"
                 "    v = gym.make_vec(sys.argv[1], num_envs=128, vectorization_mode='vector_entry_point',"
                 " parallel=True)\n"
                 "    v.reset(seed=0); v.step(np.zeros((128, 3), np.float32))"),
}


def warm(jobs: tuple[str, ...] = tuple(JOBS), env_id: str = "AUVFollow-Hard-v1", processes: int = 2,
         verbose: bool = True) -> dict[str, float]:
    """Run ``jobs`` (names of :data:`JOBS`) in fresh processes, at most ``processes`` at once;
    return each job's wall seconds. Raises ``ValueError`` on an unknown job or id or a
    ``processes`` below 1, :class:`WarmJobFailed` (a ``RuntimeError``, with the job's stderr) if a
    job fails. However the call ends (a failure, KeyboardInterrupt, any exception), it stops the
    jobs still running before it returns or raises. With ``verbose``, each job's seconds and the
    cache guard's reports of files it repaired (:func:`guard_numba_cache`) are printed."""
    unknown = [j for j in jobs if j not in JOBS]
    if unknown:
        raise ValueError(f"jobs={unknown!r} are unknown: choose from {sorted(JOBS)}")
    import auv_follow_env

    ids = auv_follow_env.ENV_IDS + auv_follow_env.ENV_IDS_V1
    if env_id not in ids:
        raise ValueError(f"env_id={env_id!r} is not an auv-follow id: choose from {list(ids)}")
    if isinstance(processes, bool) or not isinstance(processes, int) or processes < 1:
        raise ValueError(f"processes={processes!r} is invalid: pass an int >= 1")
    pending = list(dict.fromkeys(jobs))
    running: dict[str, tuple[subprocess.Popen, float, Any]] = {}
    out: dict[str, float] = {}
    # (a handler that raises, run inside subprocess's internals, can leave a Popen's wait lock held:
    # the signals are acted on between polls, see auv_follow_env._signals)
    with deferred_signals((signal.SIGINT, signal.SIGTERM, signal.SIGHUP)) as deliver:
        try:
            _run_jobs(pending, running, out, env_id, processes, verbose, deliver)
        finally:  # an error, Ctrl-C or a signal: no job outlives the call
            _stop(running)
    return out


def _run_jobs(pending: list[str], running: dict, out: dict[str, float], env_id: str, processes: int,
              verbose: bool, deliver: Any) -> None:
    seen: set[str] = set()
    while pending or running:
        deliver()
        while pending and len(running) < processes:
            job = pending.pop(0)
            log = tempfile.TemporaryFile(mode="w+")  # (a pipe could fill up and block the job)
            running[job] = (subprocess.Popen([sys.executable, "-c", JOBS[job], env_id],
                                             stdout=subprocess.DEVNULL, stderr=log, text=True),
                            time.perf_counter(), log)
        for job, (proc, t0, log) in list(running.items()):
            if proc.poll() is None:
                continue
            del running[job]
            log.seek(0)
            err = log.read()
            log.close()
            if proc.returncode != 0:
                raise WarmJobFailed(job, proc.returncode, err)
            out[job] = time.perf_counter() - t0
            if verbose:
                for line in err.splitlines():  # the cache guard's reports (repaired files)
                    if line.startswith(CACHE_MESSAGE) and line not in seen:
                        seen.add(line)
                        print(f"  {line}", flush=True)
                print(f"  {job:<8} {out[job]:6.1f} s", flush=True)
        time.sleep(0.05)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("jobs", nargs="*", default=list(JOBS), help=f"jobs to run (default: all of {list(JOBS)})")
    p.add_argument("--env-id", default="AUVFollow-Hard-v1", help="id whose kernels are compiled (default %(default)s)")
    p.add_argument("--processes", type=int, default=2, help="jobs at once (default %(default)s)")
    a = p.parse_args(argv)
    print("compiling the env's numba kernels into the cache (about a minute the first time, seconds after)",
          flush=True)
    t0 = time.perf_counter()

    def stopped(signum, frame):
        raise _Stopped(signal.Signals(signum).name)

    previous = {sig: signal.signal(sig, stopped) for sig in (signal.SIGTERM, signal.SIGHUP)}
    try:
        warm(tuple(a.jobs), a.env_id, a.processes)
    except ValueError as e:
        p.error(str(e))
    except (KeyboardInterrupt, _Stopped) as e:
        name = str(e) if isinstance(e, _Stopped) else "SIGINT"
        print(f"warm: stopped by {name}: its compile jobs were stopped too (what they had finished is cached; "
              f"run it again to finish)", file=sys.stderr, flush=True)
        return 143 if name == "SIGTERM" else 129 if name == "SIGHUP" else 130
    except WarmJobFailed as e:
        fd, path = tempfile.mkstemp(prefix=f"auv-follow-warm-{e.job}-", suffix=".log")
        with os.fdopen(fd, "w") as f:
            f.write(e.stderr)
        last = next((line for line in reversed(e.stderr.splitlines()) if line.strip()), "(no output)")
        hint = ""
        if "pickl" in e.stderr.lower() or ".nbi" in e.stderr or ".nbc" in e.stderr:
            hint = f"; numba's cache may be damaged: delete {_cache_folder_hint()} and run warm again"
        print(f"warm: job {e.job!r} failed (exit {e.returncode}): {last.strip()}{hint} (its output: {path})",
              file=sys.stderr, flush=True)
        return 1
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    print(f"done in {time.perf_counter() - t0:.1f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
