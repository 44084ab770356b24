"""agents.benchmark: the statistics against hand computations, the leaderboard of known
episodes, clear errors, and one tiny end-to-end run through the CLI."""

from __future__ import annotations

import json
from pathlib import Path

import gymnasium as gym
import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest

from agents.benchmark.evaluation import evaluate_tier
from agents.benchmark.leaderboard import goal_check, leaderboard
from agents.benchmark.policies import parse_policy
from agents.benchmark.protocol import resolve_tier, tier_test_seeds
from agents.benchmark.stats import iqm, probability_of_improvement, stratified_bootstrap_ci
from agents.cli import main

V0_AGENT = (Path(__file__).resolve().parent.parent / "results" / "agents" / "runs"
            / "ppo-AUVFollow-S4-v0-scratch-seed1-20261123-114019")

# --- statistics ------------------------------------------------------------------------------


def test_iqm_of_a_known_list():
    # 8 values: 25 % = 2 cut from each end, the middle four are 3, 4, 5, 6
    x = [7.0, 1.0, 100.0, 3.0, 5.0, 2.0, 6.0, 4.0]
    assert iqm(x) == pytest.approx((3 + 4 + 5 + 6) / 4)
    # 10 values: int(2.5) = 2 cut from each end -> mean of the middle six
    assert iqm(np.arange(10.0)) == pytest.approx(np.mean(np.arange(2.0, 8.0)))


def test_bootstrap_ci_covers_the_true_mean_about_95_percent_of_the_time():
    rng = np.random.default_rng(123)
    repeats, hits = 300, 0
    for k in range(repeats):
        x = rng.normal(2.0, 1.0, size=60)
        _, lo, hi = stratified_bootstrap_ci([x], "mean", n_resamples=1000, seed=k)
        hits += lo <= 2.0 <= hi
    cover = hits / repeats
    # binomial sd at p = 0.95, n = 300: 0.0126; percentile intervals undercover slightly at n = 60
    assert 0.90 <= cover <= 0.99, cover


def test_stratified_bootstrap_keeps_stratum_sizes():
    # two constant strata: any stratified resample has the same pool -> zero-width CI at the
    # pooled mean (an unstratified bootstrap would spread around it)
    est, lo, hi = stratified_bootstrap_ci([[0.0] * 5, [1.0] * 15], "mean", n_resamples=500)
    assert est == lo == hi == pytest.approx(15 / 20)


def test_paired_bootstrap_resamples_test_seeds_not_episodes():
    # two runs with identical scores on the same seeds carry the information of one run: the
    # seed-paired CI equals the CI of a single run (an unpaired one would be narrower)
    x = np.random.default_rng(1).normal(size=40)
    one = stratified_bootstrap_ci([x], "mean", n_resamples=3000, seed=3)
    two = stratified_bootstrap_ci([x, x], "mean", n_resamples=3000, seed=3)
    unpaired = stratified_bootstrap_ci([x, x], "mean", n_resamples=3000, seed=3, paired=False)
    assert two == pytest.approx(one)
    assert unpaired[2] - unpaired[1] < 0.85 * (one[2] - one[1])
    with pytest.raises(ValueError, match="paired=True needs strata of equal length"):
        stratified_bootstrap_ci([x, x[:10]], paired=True)


def test_bootstrap_is_reproducible_and_brackets_the_estimate():
    x = np.random.default_rng(0).lognormal(size=50)
    a = stratified_bootstrap_ci([x[:25], x[25:]], "iqm", n_resamples=2000, seed=7)
    b = stratified_bootstrap_ci([x[:25], x[25:]], "iqm", n_resamples=2000, seed=7)
    assert a == b
    assert a[1] <= a[0] <= a[2]


def test_probability_of_improvement_by_hand():
    x, y = [1.0, 2.0], [1.0, 3.0]
    # pairs (x < y): (1, 3), (2, 3) -> 2; ties (1, 1) -> 0.5; of 4 pairs
    est, lo, hi = probability_of_improvement(x, y, n_resamples=300)
    assert est == pytest.approx(2.5 / 4)
    assert lo <= est <= hi


def test_bad_input_names_argument_and_allowed_values():
    with pytest.raises(ValueError, match=r"tier='S9'.*valid tiers"):
        resolve_tier("S9")
    with pytest.raises(ValueError, match=r"policy='NOPE'.*controller name"):
        parse_policy("NOPE")
    with pytest.raises(ValueError, match=r"confidence=1.5.*\(0, 1\)"):
        stratified_bootstrap_ci([[1.0, 2.0]], confidence=1.5)
    with pytest.raises(ValueError, match=r"statistic='median'.*valid statistics"):
        stratified_bootstrap_ci([[1.0, 2.0]], "median")
    with pytest.raises(ValueError, match=r"NaN or inf"):
        stratified_bootstrap_ci([[1.0, np.nan]])


# --- leaderboard of known episodes -----------------------------------------------------------

def _episodes() -> pd.DataFrame:
    a = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 100.0]  # classical "A", one run
    b1, b2 = [0.5, 1.0, 1.5, 2.0], [2.5, 3.0, 3.5, np.nan]  # learned "B", two runs; last episode terminated
    rows = [dict(tier="T", policy="A", kind="classical", run="A", seed=i, terminated=False,
                 true_steady_mean=v, true_full_mean=2 * v, fail_error_m=40.0) for i, v in enumerate(a)]
    rows += [dict(tier="T", policy="B", kind="learned", run=r, seed=i, terminated=bool(np.isnan(v)),
                  true_steady_mean=v, true_full_mean=2 * v, fail_error_m=40.0)
             for r, vals in (("b1", b1), ("b2", b2)) for i, v in enumerate(vals)]
    return pd.DataFrame(rows)


def test_leaderboard_of_two_policies_equals_the_hand_computation():
    board = leaderboard(_episodes(), n_resamples=2000).set_index("policy")
    # A: sorted 1..7, 100 -> IQM = (3 + 4 + 5 + 6) / 4, mean = 128 / 8
    assert board.loc["A", "true_steady_mean_iqm"] == pytest.approx(4.5)
    assert board.loc["A", "true_steady_mean_mean"] == pytest.approx(16.0)
    assert board.loc["A", "true_full_mean_iqm"] == pytest.approx(9.0)
    # B: the terminated episode scores the loss threshold 40 -> pooled sorted
    # 0.5 1 1.5 2 2.5 3 3.5 40 -> IQM = (1.5 + 2 + 2.5 + 3) / 4 = 2.25, mean = 54 / 8
    assert board.loc["B", "true_steady_mean_iqm"] == pytest.approx(2.25)
    assert board.loc["B", "true_steady_mean_mean"] == pytest.approx(6.75)
    assert board.loc["B", "termination_rate"] == pytest.approx(1 / 8)
    assert board.loc["B", "runs"] == 2 and board.loc["B", "episodes"] == 8
    # per-run IQMs: b1 (4 values, 1 cut each end) -> (1 + 1.5) / 2; b2 -> (3 + 3.5) / 2
    assert board.loc["B", "run_iqm_min"] == pytest.approx(1.25)
    assert board.loc["B", "run_iqm_max"] == pytest.approx(3.25)
    assert (board["best_classical"] == "A").all()
    assert board.loc["B", "true_steady_mean_iqm_change_pct"] == pytest.approx(100 * (2.25 / 4.5 - 1))
    # P(B < A): for each b, the a's above it (+ half the ties):
    # 0.5: 8, 1: 7.5, 1.5: 7, 2: 6.5, 2.5: 6, 3: 5.5, 3.5: 5, 40: 1 -> 46.5 of 64 pairs
    assert board.loc["B", "poi"] == pytest.approx(46.5 / 64)
    assert board.loc["A", "poi"] == pytest.approx(0.5)
    for p in ("A", "B"):
        for m in ("true_steady_mean_iqm", "true_steady_mean_mean", "poi"):
            lo, hi = board.loc[p, f"{m}_lo" if m != "poi" else "poi_lo"], board.loc[p, f"{m}_hi" if m != "poi"
                                                                                  else "poi_hi"]
            assert lo <= board.loc[p, m] <= hi
    # same input, same numbers (fixed bootstrap seed)
    pd.testing.assert_frame_equal(leaderboard(_episodes(), n_resamples=2000).set_index("policy"), board)


def test_leaderboard_needs_its_columns():
    with pytest.raises(ValueError, match=r"lacks columns \['run'\]"):
        leaderboard(_episodes().drop(columns="run"))


# --- end to end ------------------------------------------------------------------------------

def test_batched_equals_single_env_evaluation():
    specs = [parse_policy("PID"), parse_policy("PROPOSED")]
    a = evaluate_tier(specs, "S2", [1000, 1001], batched=True, progress=False)
    b = evaluate_tier(specs, "S2", [1000, 1001], batched=False, progress=False)
    cols = ["policy", "kind", "run", "seed", "true_steady_mean", "true_full_mean", "terminated"]
    pd.testing.assert_frame_equal(a[cols], b[cols], rtol=1e-9)


def test_cli_writes_every_result_file_with_its_provenance(tmp_path, capsys):
    out = tmp_path / "bench"
    assert main(["benchmark", "--policies", "PID", "PROPOSED", "--tiers", "S1", "--seeds", "1000-1002",
                 "--out", str(out), "--resamples", "200", "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "1. PROPOSED" in printed and "| **PROPOSED** |" in (out / "leaderboard.md").read_text()
    for name in ("episodes.parquet", "leaderboard.csv", "leaderboard.md", "leaderboard.png", "benchmark.json"):
        assert (out / name).is_file(), name
    prov = json.loads((out / "benchmark.json").read_text())
    assert prov["config"]["seeds"] == {"S1": [1000, 1001, 1002]}
    assert prov["versions"]["git_commit"] and prov["versions"]["numpy"] == np.__version__
    # a plain CSV (no comment lines: pd.read_csv reads it as is), its SHA-256 recorded in benchmark.json
    import hashlib

    assert (out / "leaderboard.csv").read_text().splitlines()[0].startswith("tier,")
    files = prov.pop("files")
    assert files == {"leaderboard.csv": {"sha256": hashlib.sha256((out / "leaderboard.csv").read_bytes()).hexdigest()}}
    meta = pq.read_schema(out / "episodes.parquet").metadata
    assert json.loads(meta[b"auv_follow_provenance"]) == prov
    assert "git_commit" in (out / "leaderboard.md").read_text()
    board = pd.read_csv(out / "leaderboard.csv")
    assert list(board["policy"]) == ["PID", "PROPOSED"] and (board["best_classical"] == "PROPOSED").all()
    episodes = pd.read_parquet(out / "episodes.parquet")
    assert len(episodes) == 6 and set(episodes["seed"]) == {1000, 1001, 1002}


def test_tier_restriction_scores_a_policy_on_its_tiers_only():
    spec = parse_policy("PID@S2")
    assert spec.tiers == ("S2",) and spec.controller == "PID"
    df = evaluate_tier([spec, parse_policy("PROPOSED")], "S1", [1000], progress=False)
    assert list(df["policy"]) == ["PROPOSED"]
    with pytest.raises(ValueError, match="tier='S9'"):
        parse_policy("PID@S9")


def test_cache_reuses_episodes_only_for_committed_code(tmp_path):
    from agents.benchmark.evaluation import _code_fingerprint

    specs = [parse_policy("PID"), parse_policy("PROPOSED")]
    a = evaluate_tier(specs, "S1", [1000], progress=False, cache_dir=tmp_path)
    files = sorted(tmp_path.glob("*.parquet"))
    if _code_fingerprint() is None:  # episode code differs from git HEAD: nothing may be cached
        assert not files
        return
    assert len(files) == 2
    b = evaluate_tier(specs[::-1], "S1", [1000], progress=False, cache_dir=tmp_path)
    assert len(sorted(tmp_path.glob("*.parquet"))) == 2
    pd.testing.assert_frame_equal(a.set_index("policy").sort_index(), b.set_index("policy").sort_index())


def test_cli_rejects_unknown_tier(capsys):
    with pytest.raises(SystemExit):
        main(["benchmark", "--tiers", "S9", "--no-progress"])
    assert "tier='S9'" in capsys.readouterr().err


def test_goal_check_on_the_hand_leaderboard():
    board = leaderboard(_episodes(), n_resamples=500)
    g = goal_check(board.assign(tier="Hard"), "Hard")
    assert g["best_learned"] == "B" and g["best_classical"] == "A"
    assert g["change_pct"] == pytest.approx(-50.0)
    assert g["met"] == (g["learned_ci"][1] < g["classical_ci"][0])


def test_v1_tier_uses_the_published_test_seeds_and_records_the_condition():
    import auv_follow_env

    assert tier_test_seeds("Hard") == list(auv_follow_env.TIERS["Hard"].test_seeds)
    assert resolve_tier("AUVFollow-Extreme-v1") == ("Extreme", "AUVFollow-Extreme-v1")
    # a v0-trained agent runs on a v1 tier through the v0 prefix of the v1 observation
    spec = parse_policy("old=" + str(V0_AGENT))
    df = evaluate_tier([spec], "Hard", [3_000_000], progress=False)
    first = auv_follow_env.TIERS["Hard"].test_seeds[0]
    env = gym.make("AUVFollow-Hard-v1")
    _, info = env.reset(seed=first)
    assert df.loc[0, "cond_latency_s"] == pytest.approx(info["condition"]["latency_s"])
    assert df.loc[0, "cond_loss_prob"] == pytest.approx(info["condition"]["loss_prob"])
    assert df.loc[0, "env_id"] == "AUVFollow-Hard-v1" and np.isfinite(df.loc[0, "true_full_mean"])
