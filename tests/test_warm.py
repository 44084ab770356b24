"""auv_follow_env.warm: the set-up's compile step fills the numba cache that later processes load."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from auv_follow_env.warm import JOBS, warm

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("kwargs, match", [
    ({"jobs": ("single", "nope")}, r"jobs=\['nope'\] are unknown"),
    ({"processes": 0}, r"processes=0 is invalid"),
    ({"processes": 1.5}, r"processes=1.5 is invalid"),
    ({"env_id": "AUVFollow-Nope-v0"}, r"env_id='AUVFollow-Nope-v0' is not an auv-follow id"),
])
def test_bad_arguments_are_value_errors(kwargs, match):
    with pytest.raises(ValueError, match=match):
        warm(**kwargs, verbose=False)


def test_a_failing_job_raises_with_its_stderr(monkeypatch):
    monkeypatch.setitem(JOBS, "single", "import sys; sys.exit('boom: the kernel did not compile')")
    with pytest.raises(RuntimeError, match=r"(?s)warm job 'single' failed \(exit 1\).*boom: the kernel"):
        warm(("single",), verbose=False)


def test_the_command_line_refuses_an_unknown_job():
    res = subprocess.run([sys.executable, "-m", "auv_follow_env.warm", "nope"], cwd=ROOT, capture_output=True,
                         text=True)
    assert res.returncode == 2
    assert "unknown" in res.stderr and "single" in res.stderr


@pytest.mark.slow
def test_after_warming_a_new_process_compiles_nothing(tmp_path):
    """Warm the single env into an empty cache; a new process's first reset + step of another id
    (same kernels) then loads every jitted function from it: numba compiles nothing."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path), "PYTHONPATH": str(ROOT)}
    subprocess.run([sys.executable, "-m", "auv_follow_env.warm", "single", "--processes", "1"], cwd=ROOT, env=env,
                   check=True, capture_output=True)
    assert list(tmp_path.rglob("*.nbi")), "the warm wrote no cache index"
    probe = ("from numba.core import event as ev\n" + JOBS["single"].replace("e = gym.make", "with ev.install_recorder("
             "'numba:compile') as rec:\n    e = gym.make") + "\nprint(sum(1 for _, x in rec.buffer if x.is_start))")
    out = subprocess.run([sys.executable, "-c", probe, "AUVFollow-S2-v0"], cwd=ROOT, env=env, check=True,
                         capture_output=True, text=True)
    assert out.stdout.split()[-1] == "0"
