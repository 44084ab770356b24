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


def test_a_folder_from_before_the_floor_rename_reads_and_rebuilds_with_the_new_name(tmp_path):
    """A benchmark folder written when the oracle-parameter floor was called "information floor"
    loads with today's name, and `auv-follow leaderboard` rebuilds the same numbers under it."""
    import hashlib
    import json

    import pyarrow as pa
    import pyarrow.parquet as pq

    from agents.benchmark import benchmark
    from agents.benchmark.floors import INFORMATION_FLOOR
    from agents.benchmark.outputs import load_result
    from agents.benchmark.run import rebuild_leaderboard

    out = tmp_path / "bench"
    res = benchmark(["PROPOSED_KF_DOB"], tiers=["Hard"], seeds=[0, 1, 2], floors=True, out_dir=out,
                    n_resamples=200, progress=False)
    assert INFORMATION_FLOOR in set(res.leaderboard["policy"])
    want = res.leaderboard.set_index("policy")["true_steady_mean_iqm"]
    for name in ("episodes.parquet", "traces.parquet"):  # the old label, metadata kept
        t = pq.read_table(out / name)
        df = t.to_pandas()
        df["policy"] = df["policy"].replace({INFORMATION_FLOOR: "information floor"})
        pq.write_table(pa.Table.from_pandas(df, preserve_index=False).replace_schema_metadata(t.schema.metadata),
                       out / name)
    csv = out / "leaderboard.csv"
    csv.write_text(csv.read_text().replace(INFORMATION_FLOOR, "information floor"))
    meta = json.loads((out / "benchmark.json").read_text())
    meta["files"]["leaderboard.csv"]["sha256"] = hashlib.sha256(csv.read_bytes()).hexdigest()
    (out / "benchmark.json").write_text(json.dumps(meta))
    old = load_result(out)
    for frame in (old.episodes, old.leaderboard):
        assert "information floor" not in set(frame["policy"]) and INFORMATION_FLOOR in set(frame["policy"])
    again = rebuild_leaderboard(out, progress=False).leaderboard.set_index("policy")["true_steady_mean_iqm"]
    assert again.to_dict() == pytest.approx(want.to_dict())
