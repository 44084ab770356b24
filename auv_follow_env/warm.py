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
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from typing import Any

__all__ = ["JOBS", "warm", "main"]

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
    ``processes`` below 1, ``RuntimeError`` (with the job's stderr) if a job fails."""
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
    while pending or running:
        while pending and len(running) < processes:
            job = pending.pop(0)
            log = tempfile.TemporaryFile(mode="w+")  # (a pipe could fill up and block the job)
            proc = subprocess.Popen([sys.executable, "-c", JOBS[job], env_id], stdout=subprocess.DEVNULL,
                                    stderr=log, text=True)
            running[job] = (proc, time.perf_counter(), log)
        for job, (proc, t0, log) in list(running.items()):
            if proc.poll() is None:
                continue
            del running[job]
            log.seek(0)
            err = log.read()
            log.close()
            if proc.returncode != 0:
                for other, _, other_log in running.values():
                    other.kill()
                    other_log.close()
                raise RuntimeError(f"warm job {job!r} failed (exit {proc.returncode}):\n{err}")
            out[job] = time.perf_counter() - t0
            if verbose:
                print(f"  {job:<8} {out[job]:6.1f} s", flush=True)
        time.sleep(0.05)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("jobs", nargs="*", default=list(JOBS), help=f"jobs to run (default: all of {list(JOBS)})")
    p.add_argument("--env-id", default="AUVFollow-Hard-v1", help="id whose kernels are compiled (default %(default)s)")
    p.add_argument("--processes", type=int, default=2, help="jobs at once (default %(default)s)")
    a = p.parse_args(argv)
    print("compiling the env's numba kernels into the cache (about a minute the first time, seconds after)",
          flush=True)
    t0 = time.perf_counter()
    try:
        warm(tuple(a.jobs), a.env_id, a.processes)
    except ValueError as e:
        p.error(str(e))
    print(f"done in {time.perf_counter() - t0:.1f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
