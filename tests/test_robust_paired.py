"""The leaderboard's paired statistics robust to lost targets, on hand-made tables (values by hand)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from agents.benchmark.leaderboard import leaderboard, paired_difference, robust_paired_difference


def _rows(policy, kind, run, errors, lost=()):
    return pd.DataFrame({"tier": "Hard", "policy": policy, "kind": kind, "run": run, "seed": np.arange(1, 6),
                         "terminated": [s in lost for s in range(1, 6)], "true_steady_mean": errors,
                         "true_full_mean": errors, "fail_error_m": 20.0})


def _table():
    # A loses the target on seed 5 (it scores the 20 m threshold there), B never does
    a = _rows("A", "learned", "a0", [0.1, 0.2, 0.3, 0.4, np.nan], lost=(5,))
    b = _rows("B", "classical", "B", [0.25, 0.2, 0.5, 0.1, 0.3])
    return pd.concat([a, b], ignore_index=True)


def test_robust_statistics_by_hand():
    ep = _table()
    # per seed A - B: -0.15, 0, -0.2, +0.3, 20 - 0.3 = 19.7
    assert paired_difference(ep, "Hard", "A", "B")[0] == pytest.approx(19.65 / 5)
    r = robust_paired_difference(ep, "Hard", "A", "B", n_resamples=2000)
    assert r["paired_diff_kept"] == pytest.approx((-0.15 + 0 - 0.2 + 0.3) / 4)  # seed 5 left out
    assert r["paired_diff_kept_seeds"] == 4
    assert r["paired_diff_median"] == pytest.approx(0.0)  # median of (-0.2, -0.15, 0, 0.3, 19.7)
    assert r["paired_diff_kept_lo"] <= r["paired_diff_kept"] <= r["paired_diff_kept_hi"]
    assert -0.2 <= r["paired_diff_median_lo"] <= 0.0 <= r["paired_diff_median_hi"] <= 19.7


def test_a_seed_lost_by_one_run_is_lost_for_the_method():
    ep = _table()
    # a second run of A that loses nothing: seed 5 is still lost by the method (one of its runs lost it)
    ep = pd.concat([ep, _rows("A", "learned", "a1", [0.1, 0.2, 0.3, 0.4, 0.35])], ignore_index=True)
    r = robust_paired_difference(ep, "Hard", "A", "B")
    assert r["paired_diff_kept_seeds"] == 4
    assert r["paired_diff_kept"] == pytest.approx(-0.05 / 4)
    # the paired median averages the runs per seed first: seed 5 is (20 + 0.35) / 2 - 0.3 = 9.875
    assert r["paired_diff_median"] == pytest.approx(0.0)


def test_leaderboard_carries_them_and_the_lost_count():
    board = leaderboard(_table(), n_resamples=500)
    a = board.set_index("policy").loc["A"]
    assert a["lost_targets"] == 1 and a["paired_diff_kept_seeds"] == 4
    assert a["paired_diff_kept"] == pytest.approx(-0.0125)
    assert board.set_index("policy").loc["B", "lost_targets"] == 0
