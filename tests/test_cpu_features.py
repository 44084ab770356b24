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
AVX512 = "AVX512F AVX512CD AVX512_SKX AVX512_CLX AVX512_CNL AVX512_ICL AVX512_SPR"


def test_fused_law_tests_pass_with_numpy_avx512_disabled():
    env = dict(os.environ, NPY_DISABLE_CPU_FEATURES=AVX512)
    probe = subprocess.run([sys.executable, "-c", "import numpy; numpy.show_runtime()"], env=env,
                           capture_output=True, text=True, timeout=120)
    assert probe.returncode == 0, probe.stderr  # numpy accepts the variable on this host
    run = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                          str(ROOT / "tests" / "test_fused_law.py")],
                         env=env, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-2000:]
    assert " passed" in run.stdout
