"""Paired statistics of the leaderboard: per-seed differences against the best
classical baseline on the same test seeds, worked out by hand."""

from __future__ import annotations

import pandas as pd
import pytest

from agents.benchmark.leaderboard import leaderboard, paired_difference


def _episodes(pairs, runs=("r",)):
    rows = []
    for s, (a, b) in enumerate(pairs):
        for k, run in enumerate(runs):
            rows.append(dict(tier="Hard", policy="A", kind="learned", run=run, seed=s, terminated=False,
                             true_steady_mean=a + 0.01 * k, true_full_mean=a))
        rows.append(dict(tier="Hard", policy="B", kind="classical", run="", seed=s, terminated=False,
                         true_steady_mean=b, true_full_mean=b))
    return pd.DataFrame(rows)


def test_paired_difference_by_hand():
    # differences -0.1, -0.1, -0.1, -0.15: mean -0.1125; every bootstrap mean lies in [-0.15, -0.1]
    ep = _episodes([(0.5, 0.6), (0.4, 0.5), (0.3, 0.4), (0.2, 0.35)])
    d, lo, hi = paired_difference(ep, "Hard", "A", "B", n_resamples=2000)
    assert d == pytest.approx(-0.1125)
    assert -0.15 - 1e-12 <= lo <= d <= hi <= -0.1 + 1e-12
    board = leaderboard(ep, n_resamples=200).set_index("policy")
    assert board.loc["A", "paired_diff"] == pytest.approx(-0.1125)
    assert board.loc["B", "paired_diff"] == 0.0  # the best classical against itself


def test_runs_are_averaged_per_seed_before_differencing():
    # two runs of A at a and a + 0.01: per-seed mean a + 0.005, so every difference is -0.095
    ep = _episodes([(0.5, 0.6), (0.4, 0.5), (0.3, 0.4)], runs=("r0", "r1"))
    d, lo, hi = paired_difference(ep, "Hard", "A", "B")
    assert d == pytest.approx(-0.095) and lo == pytest.approx(-0.095) and hi == pytest.approx(-0.095)


def test_terminated_episode_scores_the_loss_threshold():
    ep = _episodes([(0.5, 0.6), (0.4, 0.5)]).assign(fail_error_m=20.0)
    ep.loc[(ep["policy"] == "A") & (ep["seed"] == 1), "terminated"] = True
    d, _, _ = paired_difference(ep, "Hard", "A", "B")
    assert d == pytest.approx(((0.5 - 0.6) + (20.0 - 0.5)) / 2)


def test_unknown_policy_is_refused():
    with pytest.raises(ValueError, match="policy='C'"):
        paired_difference(_episodes([(0.5, 0.6)]), "Hard", "C", "B")


def test_a_residual_is_paired_with_its_own_base(tmp_path):
    """B best classical, C a weaker classical that is A's base: A - C per seed is
    0.5 - 0.9, 0.4 - 0.8, 0.3 - 0.7 = -0.4 each (by hand); the markdown names the base."""
    from agents.benchmark.leaderboard import leaderboard_markdown
    from agents.benchmark.policies import PolicySpec, residual_bases

    ep = _episodes([(0.5, 0.6), (0.4, 0.5), (0.3, 0.4)])
    ep = pd.concat([ep, pd.DataFrame([dict(tier="Hard", policy="C", kind="classical", run="", seed=s,
                                           terminated=False, true_steady_mean=0.9 - 0.1 * s,
                                           true_full_mean=0.9 - 0.1 * s) for s in range(3)])],
                   ignore_index=True)
    board = leaderboard(ep, n_resamples=200, bases={"A": "C"}).set_index("policy")
    assert board.loc["A", "base"] == "C"
    assert board.loc["A", ["paired_diff_base", "paired_diff_base_lo", "paired_diff_base_hi"]].tolist() == \
        pytest.approx([-0.4, -0.4, -0.4])
    assert board.loc["A", "paired_diff"] == pytest.approx(-0.1)  # against the best classical B
    assert pd.isna(board.loc["B", "paired_diff_base"])
    # no seed lost a target, so the robust statistics equal the paired mean: -0.4 on all 3 seeds
    ci = "-0.4000 [-0.4000, -0.4000]"
    assert f"{ci} (base C; robust: neither lost {ci} (3 seeds); median {ci})" in \
        leaderboard_markdown(board.reset_index())
    # the base is read from the runs' config.yaml; a method mixing bases (or not residual) has none
    for name, mode, ctrl in (("r0", "residual", "PROPOSED"), ("r1", "residual", "PROPOSED"),
                             ("r2", "residual", "PID"), ("r3", "scratch", None)):
        (tmp_path / name).mkdir()
        (tmp_path / name / "config.yaml").write_text(f"run:\n  mode: {mode}\n  controller: {ctrl}\n")
    specs = [PolicySpec("one", "learned", runs=(str(tmp_path / "r0"), str(tmp_path / "r1"))),
             PolicySpec("mixed", "learned", runs=(str(tmp_path / "r0"), str(tmp_path / "r2"))),
             PolicySpec("scratch", "learned", runs=(str(tmp_path / "r3"),)),
             PolicySpec("PID", "classical", controller="PID")]
    assert residual_bases(specs) == {"one": "PROPOSED"}


def _write_run(path, controller, observation):
    import yaml

    path.mkdir(parents=True)
    (path / "config.yaml").write_text(yaml.safe_dump({"run": {"mode": "residual", "controller": controller},
                                                      "observation": {"observation": observation}}))
    return str(path)


def test_a_residual_carrying_a_filter_is_also_paired_with_the_law_on_that_filter(tmp_path):
    """A residual on PROPOSED whose observation carries the estimator block is compared with
    PROPOSED (its base) and with PROPOSED_KF (the same law on that filter); one on raw
    observations, or on a base with its own filter, only with its base. Per-seed differences
    by hand: R - PROPOSED = -0.2, -0.2, -0.2 (mean -0.2); R - PROPOSED_KF = -0.05, +0.05, 0.0 (mean 0)."""
    from agents.benchmark.leaderboard import leaderboard_markdown
    from agents.benchmark.policies import PolicySpec, filtered_laws, residual_bases, residual_observations

    est = PolicySpec("R", "learned", runs=(_write_run(tmp_path / "a", "PROPOSED", "estimator"),))
    raw = PolicySpec("Q", "learned", runs=(_write_run(tmp_path / "b", "PROPOSED", "raw"),))
    own = PolicySpec("K", "learned", runs=(_write_run(tmp_path / "c", "PROPOSED_KF_DOB", "estimator"),))
    specs = [est, raw, own]
    assert residual_bases(specs) == {"R": "PROPOSED", "Q": "PROPOSED", "K": "PROPOSED_KF_DOB"}
    assert residual_observations(specs) == {"R": "estimator", "Q": "raw", "K": "estimator"}
    assert filtered_laws(specs) == {"R": "PROPOSED_KF"}

    rows = []
    for s, (r, p, kf) in enumerate([(0.3, 0.5, 0.35), (0.4, 0.6, 0.35), (0.5, 0.7, 0.5)]):
        for pol, kind, v in (("R", "learned", r), ("PROPOSED", "classical", p), ("PROPOSED_KF", "classical", kf)):
            rows.append(dict(tier="Medium", policy=pol, kind=kind, run="x" if kind == "learned" else "", seed=s,
                             terminated=False, true_steady_mean=v, true_full_mean=v))
    board = leaderboard(pd.DataFrame(rows), n_resamples=200, bases={"R": "PROPOSED"},
                        observations={"R": "estimator"}, filtered={"R": "PROPOSED_KF"}).set_index("policy")
    assert board.loc["R", "paired_diff_base"] == pytest.approx(-0.2)
    assert board.loc["R", "paired_diff_filtered"] == pytest.approx(0.0, abs=1e-12)
    assert board.loc["R", "filtered_law"] == "PROPOSED_KF" and board.loc["R", "observation"] == "estimator"
    md = leaderboard_markdown(board.reset_index())
    ci = "-0.2000 [-0.2000, -0.2000]"
    assert f"(base PROPOSED; obs estimator; robust: neither lost {ci} (3 seeds); median {ci})" in md
    assert "(PROPOSED_KF)" in md
