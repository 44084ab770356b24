"""`auv-follow leaderboard --add-policies`: a policy scored into a benchmark folder gives the
rows a benchmark run with it from the start gives (same host: equal), keeps every other row,
and replaces, not doubles, a label scored again."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pandas as pd
import pytest

from agents.benchmark.outputs import load_result
from agents.benchmark.run import benchmark, rebuild_leaderboard

SEEDS = [1, 2, 3]


@pytest.fixture(scope="module")
def folders(tmp_path_factory):
    root = tmp_path_factory.mktemp("add")
    benchmark(["PID"], tiers=["Easy"], seeds=SEEDS, out_dir=root / "grown", n_resamples=200, progress=False)
    both = benchmark(["PID", "PROPOSED"], tiers=["Easy"], seeds=SEEDS, out_dir=root / "both", n_resamples=200,
                     progress=False)
    return root, both


def test_an_added_policy_has_the_rows_of_a_full_run(folders):
    root, both = folders
    before = load_result(root / "grown").episodes
    grown = rebuild_leaderboard(root / "grown", add_policies=["PROPOSED"], progress=False)
    cols = ["policy", "seed", "steps", "terminated", "true_steady_mean", "true_full_rmse"]
    got = grown.episodes.sort_values(["policy", "seed"])[cols].reset_index(drop=True)
    want = both.episodes.sort_values(["policy", "seed"])[cols].reset_index(drop=True)
    pd.testing.assert_frame_equal(got, want)
    kept = grown.episodes[grown.episodes["policy"] == "PID"].reset_index(drop=True)
    pd.testing.assert_frame_equal(kept, before.reset_index(drop=True))
    board = grown.leaderboard.set_index("policy")
    ref = both.leaderboard.set_index("policy")
    for col in ("true_steady_mean_iqm", "true_steady_mean_iqm_lo", "paired_diff"):
        np.testing.assert_allclose(board.loc[["PID", "PROPOSED"], col].to_numpy(dtype=float),
                                   ref.loc[["PID", "PROPOSED"], col].to_numpy(dtype=float), rtol=1e-12)
    assert "PROPOSED" in set(load_result(root / "grown").traces["policy"])
    assert "PROPOSED" in grown.provenance["rebuilt"]["added_policies"]
    again = rebuild_leaderboard(root / "grown", add_policies=["PROPOSED"], progress=False)
    assert (again.episodes["policy"] == "PROPOSED").sum() == len(SEEDS)
    assert "PROPOSED" in again.provenance["rebuilt"]["added_policies"]  # kept across rebuilds


def test_an_added_policy_must_fit_the_folder(folders):
    root, _ = folders
    with pytest.raises(ValueError, match="does not hold"):
        rebuild_leaderboard(root / "both", add_policies=["PROPOSED@Hard"], progress=False)
    out = subprocess.run([sys.executable, "-m", "agents.cli", "leaderboard", "--bench", str(root / "both"),
                          "--add-policies", "PROPOSED@Hard", "--no-progress"], capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 2 and "--add-policies" in out.stderr and "Traceback" not in out.stderr
