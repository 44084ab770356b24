"""The tests whose results depend on numpy's run-time SIMD dispatch also pass with numpy's
AVX-512 loops switched off (``NPY_DISABLE_CPU_FEATURES``), so one run of the suite shows both
of numpy's paths on a host that has AVX-512, and the default path elsewhere (there the variable
changes nothing). The fused-law tests compare compiled code with numpy's sin/cos/arctan2 loops,
the loops that differ between AVX2 and AVX-512."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: numpy's names of the AVX-512 dispatch targets: before numpy 2.4 the AVX512_* features, from 2.4 on the
#: X86_V4 level groups them (disabling AVX512F alone then leaves X86_V4, and so every AVX-512 loop, on)
AVX512 = ("X86_V4", "AVX512F", "AVX512CD", "AVX512_SKX", "AVX512_CLX", "AVX512_CNL", "AVX512_ICL", "AVX512_SPR")
_FEATURES = ("from numpy._core._multiarray_umath import __cpu_features__ as f; "
             "print(' '.join(k for k, v in f.items() if v))")


def _features(env: dict[str, str]) -> set[str]:
    probe = subprocess.run([sys.executable, "-c", _FEATURES], env=env, capture_output=True, text=True, timeout=120)
    assert probe.returncode == 0, probe.stderr  # numpy accepts the variable on this host
    return set(probe.stdout.split())


def test_fused_law_tests_pass_with_numpy_avx512_disabled():
    host = {k: v for k, v in os.environ.items() if k != "NPY_DISABLE_CPU_FEATURES"}  # what the CPU has
    on = _features(host)
    known = subprocess.run([sys.executable, "-c", _FEATURES.replace("if v", "")], env=host, capture_output=True,
                           text=True, timeout=120).stdout.split()
    env = dict(os.environ, NPY_DISABLE_CPU_FEATURES=" ".join(k for k in AVX512 if k in known and k in on))
    off = _features(env)
    # what numpy dispatches on: X86_V4 (numpy >= 2.4) or AVX512_SKX (older) is off in the child
    assert not ({"X86_V4", "AVX512_SKX"} & off), sorted(off)
    run = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                          str(ROOT / "tests" / "test_fused_law.py")],
                         env=env, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-2000:]
    assert " passed" in run.stdout
