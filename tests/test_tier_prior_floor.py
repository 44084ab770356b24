"""The tier-prior particle floor (agents/benchmark/bayes_floor.py with per-particle parameter
rows drawn from the tier's law): a follower who knows the tier but not the episode's draws.
Expectations worked out independently: the tier's published ranges, the kernel move's mean and
variance in closed form, ranges of hand-made fixes, and the oracle-parameter floor when the prior
is a point (every draw is the episode's own row)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from agents.benchmark import bayes_floor as bf
from agents.benchmark import floors
from auv_follow_env import dynamics as dyn
from auv_follow_env.tiers import LEADER_TIERS

#: published range name -> kernel column (docs/tiers.md, "Leader tiers")
COLUMNS = {"leader_cruise_speed": dyn.P_LD_UC, "leader_turn_rate": dyn.P_LD_RT, "leader_leg_m": dyn.P_LD_LEG,
           "leader_uturn_rate": dyn.P_LD_RS, "fix_sigma_m": dyn.P_NS0, "outlier_share": dyn.P_OUT_P,
           "leader_sprint_speed": dyn.P_LD_US}


def test_tier_prior_draws_fill_the_published_ranges():
    """Each prior row is a draw of the tier's law: every published range is respected and,
    with 400 draws of a uniform, covered to within 3 % of its width at both ends."""
    rows = bf.tier_prior("AUVFollow-Leader-Hard-v1", 400)
    assert rows.shape == (400, dyn.NP)
    ranges = LEADER_TIERS["Leader-Hard"].ranges
    for name, col in COLUMNS.items():
        lo, hi = ranges[name]
        x = rows[:, col]
        assert lo - 1e-12 <= x.min() and x.max() <= hi + 1e-12, name
        assert x.min() < lo + 0.03 * (hi - lo) and x.max() > hi - 0.03 * (hi - lo), name
    # no draw shares an episode's stream: the first prior row is not any test seed's row
    test = bf.episode_params("AUVFollow-Leader-Hard-v1", LEADER_TIERS["Leader-Hard"].test_seeds[:5])
    assert not any(np.array_equal(rows[0], t) for t in test)
    with pytest.raises(ValueError, match="draws=0"):
        bf.tier_prior("AUVFollow-Leader-Hard-v1", 0)


def test_liu_west_move_keeps_the_clouds_mean_and_variance():
    """a x + (1 - a) m + sqrt(1 - a^2) sd eps has mean m and variance a^2 v + (1 - a^2) v = v;
    columns not moved are untouched; draws outside the prior's range are clipped to it."""
    rng = np.random.default_rng(0)
    p = np.zeros((200_000, dyn.NP))
    p[:, dyn.P_LD_UC] = rng.uniform(0.4, 0.6, len(p))
    p[:, dyn.P_XU] = 7.0
    cols = np.array([dyn.P_LD_UC])
    out = bf._liu_west(p, cols, np.array([0.0]), np.array([10.0]), 0.9, np.random.default_rng(1))
    x = out[:, dyn.P_LD_UC]
    assert x.mean() == pytest.approx(0.5, abs=4 * np.sqrt(0.2 ** 2 / 12 / len(p)))
    assert x.var() == pytest.approx(0.2 ** 2 / 12, rel=0.02)
    assert np.all(out[:, dyn.P_XU] == 7.0)
    assert np.corrcoef(x, p[:, dyn.P_LD_UC])[0, 1] == pytest.approx(0.9, abs=0.01)  # corr = a
    tight = bf._liu_west(p, cols, np.array([0.45]), np.array([0.55]), 0.5, np.random.default_rng(2))
    assert tight[:, dyn.P_LD_UC].min() == 0.45 and tight[:, dyn.P_LD_UC].max() == 0.55


def test_fix_ranges_are_the_distance_the_fix_shows():
    rec = {"pose": np.zeros((5, 1, 3))}
    rec["pose"][:, 0, 0] = np.arange(5.0)  # the follower moves 1 m per step along x
    z = np.array([[3.0, 4.0, 0.0, 0.0, 0.0], [4.0, -1.0, 0.0, 0.0, 0.0]])
    got = bf.fix_ranges(rec, 0, np.array([0, 3]), z)
    np.testing.assert_allclose(got, [5.0, np.hypot(1.0, 1.0)])
    # a packet measured before the episode's first step uses the first pose
    np.testing.assert_allclose(bf.fix_ranges(rec, 0, np.array([-2]), z[:1]), [5.0])


def test_prior_arguments_are_checked():
    z = np.zeros((1, 5))
    one = np.zeros(1, dtype=np.int64)
    args = (one, one, z, np.ones(1), np.zeros((2, 2)), (0.0, 0.0), 1, 0)
    with pytest.raises(ValueError, match=r"params has shape \(3,\)"):
        bf.particle_floor_episode(np.zeros(3), *args)
    with pytest.raises(ValueError, match="fix_range is None"):
        bf.particle_floor_episode(np.zeros((4, dyn.NP)), *args)
    with pytest.raises(ValueError, match=r"fix_range has shape \(2,\)"):
        bf.particle_floor_episode(np.zeros((4, dyn.NP)), *args, fix_range=np.ones(2))
    with pytest.raises(ValueError, match="shrink=0"):
        bf.particle_floor_episode(np.zeros((4, dyn.NP)), *args, fix_range=np.ones(1), shrink=0)


def test_a_point_prior_gives_the_oracle_parameter_floor():
    """When every prior draw is the episode's own row (every range of the tier a point), the
    tier-prior floor is the oracle-parameter floor up to Monte Carlo error: the fix noise then
    differs only by the shown range against the true one (fix_sigma_per_m x the fix's own
    error, under 1e-3 m here). Leader-Easy training seeds 300-301, 1024 particles; the
    allowance is three times the oracle floor's own spread between two filter seeds, at least 5 %."""
    kw = {"particles": 1024, "children": 2}
    for seed in (300, 301):
        rec = floors.record_episodes("Leader-Easy", [seed], floors.LEADER_FOLLOWER)
        params = bf.episode_params("AUVFollow-Leader-Easy-v1", [seed])
        b0 = floors.leader_bayes_floor(rec, params, seed=0, **kw)
        b1 = floors.leader_bayes_floor(rec, params, seed=50, **kw)
        a = floors.leader_bayes_floor(rec, None, prior=np.repeat(params, 64, axis=0), seed=100, **kw)
        for col in ("expected_steady_mean", "realised_steady_mean"):
            ref, other = b0[col].iloc[0], b1[col].iloc[0]
            tol = max(3 * abs(ref - other), 0.05 * ref)
            assert a[col].iloc[0] == pytest.approx(ref, abs=tol), (seed, col, a[col].iloc[0], ref, other)


def _board(tier_prior_iqm: float | None) -> pd.DataFrame:

    policies = ["PROPOSED_PF_DOB", "PROPOSED_IMM_DOB", "L", floors.INFORMATION_FLOOR]
    kinds = ["classical", "classical", "learned", "reference"]
    iqm = [0.45, 0.50, 0.40, 0.10]
    if tier_prior_iqm is not None:
        policies.append(floors.TIER_PRIOR_FLOOR)
        kinds.append("reference")
        iqm.append(tier_prior_iqm)
    return pd.DataFrame({"tier": "Leader-Hard", "policy": policies, "kind": kinds, "true_steady_mean_iqm": iqm,
                         "best_classical": "PROPOSED_PF_DOB"})


def test_gap_closed_is_measured_against_the_tier_prior_floor_where_there_is_one():
    """Best generic classical 0.50 m (the model-aware 0.45 does not count), tier-prior floor
    0.30 m, oracle-parameter floor 0.10 m: a learned row at 0.40 m closes (0.50 - 0.40) /
    (0.50 - 0.30) = 0.5 of the reachable gap and 0.10 / 0.40 = 0.25 of the oracle one."""
    out = floors.add_gap_closed(_board(0.30)).set_index("policy")
    assert out.loc["L", "gap_closed"] == pytest.approx(0.5)
    assert out.loc["L", "gap_closed_oracle"] == pytest.approx(0.25)
    assert out.loc["PROPOSED_PF_DOB", "gap_closed"] == pytest.approx(0.25)  # 0.05 / 0.20
    assert out.loc["PROPOSED_IMM_DOB", "gap_closed"] == 0.0
    assert (out["gap_floor"] == floors.TIER_PRIOR_FLOOR).all()
    assert np.isnan(out.loc[floors.TIER_PRIOR_FLOOR, "gap_closed"])  # reference rows get none
    # without a tier-prior row, or with one no lower than the best generic classical (then it
    # is no floor to close a gap to), the oracle-parameter floor is the one
    for board in (_board(None), _board(0.55)):
        out = floors.add_gap_closed(board).set_index("policy")
        assert out.loc["L", "gap_closed"] == pytest.approx(0.25)
        assert (out["gap_floor"] == floors.INFORMATION_FLOOR).all()


def test_the_tier_prior_floor_is_added_to_a_benchmark_folder(tmp_path, monkeypatch):
    """`auv-follow leaderboard --tier-prior-floor` adds the floor's rows (the same numbers as
    leader_floor(knows='tier')'s realised error on those seeds), keeps every other episode row, and names the
    floor in the leaderboard's gap-closed column; a tier the folder lacks is refused by name."""
    from agents.benchmark.run import benchmark, rebuild_leaderboard

    monkeypatch.setattr(floors, "TIER_PRIOR_PARTICLES", 256)  # a quick floor: the mechanics, not the value
    seeds = [1, 2]
    out = tmp_path / "bench"
    res = benchmark(["PROPOSED_KF_DOB", "PROPOSED_IMM_DOB"], tiers=["Leader-Easy"], seeds=seeds, out_dir=out,
                    n_resamples=200, progress=False)
    before = res.episodes
    with pytest.raises(ValueError, match="'Leader-Hard' is not one of the folder's Leader tiers"):
        rebuild_leaderboard(out, tier_prior_floor=["Leader-Hard"], progress=False)
    new = rebuild_leaderboard(out, tier_prior_floor=["Leader-Easy"], cache_dir=tmp_path / "cache", progress=False)
    rows = new.episodes[new.episodes["policy"] == floors.TIER_PRIOR_FLOOR].sort_values("seed")
    direct = floors.leader_floor("Leader-Easy", seeds, knows="tier", cache_dir=tmp_path / "cache")
    # the tier-prior floor's rows hold its realised error (its expected error can collapse with its posterior)
    np.testing.assert_array_equal(rows["true_steady_mean"].to_numpy(), direct["realised_steady_mean"].to_numpy())
    assert (rows["kind"] == floors.REFERENCE_KIND).all() and rows["cond_fix_sigma_m"].notna().all()
    kept = new.episodes[new.episodes["policy"] != floors.TIER_PRIOR_FLOOR].reset_index(drop=True)
    assert kept.equals(before.reset_index(drop=True)[kept.columns])
    # again: the rows are replaced, not doubled
    again = rebuild_leaderboard(out, tier_prior_floor=["Leader-Easy"], cache_dir=tmp_path / "cache", progress=False)
    assert (again.episodes["policy"] == floors.TIER_PRIOR_FLOOR).sum() == len(seeds)
    assert floors.TIER_PRIOR_FLOOR in set(again.leaderboard["policy"])
    assert "Leader-Easy" in again.provenance["rebuilt"]["added_rows"]
