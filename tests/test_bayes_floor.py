"""The Leader tiers' oracle-parameter floor (agents/benchmark/bayes_floor.py): a particle filter under
the true generator. Expectations worked out independently: the truncated Erlang law in closed
form, geometric medians of configurations whose median is known, and on a one-mode leader (a
target whose speed and turn rate are Ornstein-Uhlenbeck processes) the v1 tiers' Kalman floor."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from agents.benchmark import bayes_floor as bf
from agents.benchmark import floors
from agents.benchmark.floors import _episode_floor, extract_packets, record_episodes
from auv_follow_env import dynamics as dyn


def test_threshold_redraw_is_the_truncated_erlang():
    """The Gibbs move re-draws a wander mode's threshold from Gamma(4, mean / 4) truncated to
    more than the progress made: its conditional survival function is S(x) / S(t)."""
    k, mean, elapsed = int(dyn.LD_K), 8.0, 11.0
    lam = k / mean
    rs = np.array([12345], dtype=np.uint64)
    proc = np.zeros((1, dyn.NR))
    draws = np.array([bf._erlang_remaining(k, lam, elapsed, rs, proc, 0) for _ in range(20000)])
    assert draws.min() > elapsed
    law = stats.gamma(a=k, scale=1.0 / lam)
    cdf = lambda x: (law.cdf(x) - law.cdf(elapsed)) / law.sf(elapsed)  # noqa: E731
    assert stats.kstest(draws, cdf).pvalue > 1e-3
    # E[T | T > t] = (k / lam) S_{k+1}(t) / S_k(t) for an Erlang(k, lam)
    expect = k / lam * stats.gamma(a=k + 1, scale=1.0 / lam).sf(elapsed) / law.sf(elapsed)
    assert draws.mean() == pytest.approx(expect, rel=0.02)


def test_first_mode_age_is_the_truncated_equilibrium_age():
    """An episode's first wander mode starts with a length-biased Gamma(k + 1) duration and a
    uniform position in it: its age is the equilibrium age, density S_k(a) / mean. Given no
    switch for ``elapsed`` seconds, the Gibbs move draws it from that law truncated to a >= elapsed."""
    k, mean, elapsed = int(dyn.LD_K), 6.0, 4.0
    lam = k / mean
    rs = np.array([777], dtype=np.uint64)
    proc = np.zeros((1, dyn.NR))
    draws = np.array([bf._erlang_age(k, lam, elapsed, rs, proc, 0) for _ in range(20000)])
    assert draws.min() >= elapsed
    grid = np.linspace(elapsed, elapsed + 20 * mean, 20001)
    dens = stats.gamma(a=k, scale=1.0 / lam).sf(grid)
    cum = np.concatenate([[0.0], np.cumsum(0.5 * (dens[1:] + dens[:-1]) * np.diff(grid))])
    cum /= cum[-1]
    assert stats.kstest(draws, lambda x: np.interp(x, grid, cum)).pvalue > 1e-3


def test_straight_start_odds_match_the_generators_start():
    """A leader that has gone straight since it started is a survey leg or a wander cruise. With
    nothing travelled the odds are leader_init's shares; after d metres a leg survives with
    P(progress + d < thr), thr ~ U[lo, hi], progress ~ U[0, thr] (here by simulation), and a
    cruise after t seconds with the equilibrium Erlang's survival (1 / k) sum_j S_(j+1)(lam t)."""
    p = np.zeros((1, dyn.NP))
    p[0, [dyn.P_LD_MODES, dyn.P_LD_SURVEY, dyn.P_LD_UC, dyn.P_LD_LEG, dyn.P_LD_RS]] = [2.0, 0.5, 0.5, 10.0, 0.25]
    p[0, [dyn.P_LD_MC, dyn.P_LD_MT, dyn.P_LD_ML, dyn.P_LD_MS]] = [8.0, 5.0, 6.0, 4.0]
    leg0, cruise0 = bf._straight_start_odds(p, 0, 0.0, 0.0)
    t_leg, t_turn = 10.0 / 0.5, math.pi / 0.25
    assert leg0 == pytest.approx(0.5 * t_leg / (t_leg + t_turn))
    assert cruise0 == pytest.approx(0.5 * 0.5 * 8.0 / (0.5 * 8.0 + 2 * 0.15 * 5.0 + 0.1 * 6.0 + 0.1 * 4.0))
    rng = np.random.default_rng(0)
    thr = rng.uniform(9.5, 10.5, 400000)
    prog = rng.uniform(0.0, thr)
    for d in (3.0, 9.7):
        leg, _ = bf._straight_start_odds(p, 0, d, 0.0)
        assert leg / leg0 == pytest.approx(np.mean(prog + d < thr), abs=3e-3)
    _, cruise = bf._straight_start_odds(p, 0, 0.0, 5.0)
    x = 4 / 8.0 * 5.0
    expect = np.mean([stats.gamma(a=j + 1).sf(x) for j in range(4)])
    assert cruise / cruise0 == pytest.approx(expect, rel=1e-9)


def _median(points: np.ndarray) -> np.ndarray:
    """The spatial median and the mean distance to it of points used as reference points
    (offset zero: the reference point is the target's position)."""
    pose = np.column_stack([points, np.zeros(len(points))])
    p = np.zeros((len(points), dyn.NP))
    out = np.full(3, np.nan)
    bf._medians(np.ascontiguousarray(pose), p, 0.0, 0.0, out)
    return out


def test_spatial_median_of_known_configurations():
    # an equilateral triangle: the Fermat point is the centre, every vertex at the circumradius
    ang = np.deg2rad([90.0, 210.0, 330.0])
    tri = np.column_stack([2.0 * np.cos(ang) + 1.0, 2.0 * np.sin(ang) - 3.0])
    mx, my, e = _median(tri)
    assert (mx, my) == pytest.approx((1.0, -3.0), abs=1e-6)
    assert e == pytest.approx(2.0, abs=1e-6)
    # a point holding more than half the mass is the median (the mean would be pulled away)
    # (the iteration stops at a step below 1e-3 of the mean distance: the mean distance, which is
    # flat at the median, is then exact to far better than the position)
    pts = np.array([[0.0, 0.0]] * 3 + [[10.0, 0.0]])
    mx, my, e = _median(pts)
    assert (mx, my) == pytest.approx((0.0, 0.0), abs=0.01 * 2.5)
    assert e == pytest.approx(10.0 / 4, rel=1e-3)


def test_spatial_median_does_not_depend_on_the_thread_count():
    """The floor per step is a median of 1,000s of particles: its bits must not depend on how many
    threads numba has (a host's core count), or cached floors would not reproduce elsewhere."""
    import numba

    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("numba has one thread here")
    rng = np.random.default_rng(3)
    points = rng.standard_normal((4000, 2)) * [3.0, 0.5] + [1e3, -2e3]  # (large coordinates: rounding shows)
    before = numba.get_num_threads()
    try:
        got = {}
        for k in (1, 2):
            numba.set_num_threads(k)
            got[k] = _median(points)
    finally:
        numba.set_num_threads(before)
    assert got[1].tolist() == got[2].tolist()  # exact: one process, one host


def test_one_mode_leader_matches_the_kalman_floor():
    """A leader that only cruises (mean cruise 1e4 s: no switch in an episode) has speed
    = command + an OU wobble and turn rate = an OU wobble: the v1 target model, whose floor the
    Kalman filter gives. The particle floor agrees within its Monte Carlo error and the Kalman
    floor's linearisation (measured on four episodes at 2048 particles: -1.2 % to +0.3 %; allowed 3 %)."""
    ov = {"leader_modes": 1.0, "leader_survey_share": 0.0, "leader_cruise_mean_s": 1e4, "outlier_share": 0.0}
    seeds = [300, 301]
    rec = record_episodes("Leader-Easy", seeds, "PROPOSED_IMM_DOB", overrides=ov)
    params = bf.episode_params("AUVFollow-Leader-Easy-v1", seeds, **ov)
    spec = rec["spec"]
    times = spec.dt * np.arange(1, spec.n_steps + 1)
    steady = times >= spec.steady_start_s - 1e-9
    ratios = []
    for j in range(len(seeds)):
        cond = {k: v[j] for k, v in rec["conditions"].items()}
        L = int(rec["length"][j])
        assert L == spec.n_steps
        linear = dict(cond, target_speed=cond["leader_cruise_speed"], target_speed_std=cond["leader_wobble_speed"],
                      target_yaw_rate_std=cond["leader_wobble_rate"], target_speed_corr_s=cond["leader_wobble_corr_s"],
                      target_yaw_rate_corr_s=cond["leader_wobble_corr_s"])
        kf = _episode_floor(rec["target"][:, j], rec["pose"][:, j], rec["ref"][:, j], rec["obs"][:, j], L, linear,
                            spec.dt, spec.p_d, spec.steady_start_s)
        pk = extract_packets(rec["obs"][:L + 1, j], rec["pose"][:L + 1, j], spec.dt)
        sig = bf.packet_sigmas(rec, j, pk["meas"], nominal=True)  # the Kalman floor's sigma convention
        res = bf.particle_floor_episode(params[j], pk["meas"], pk["arr"], pk["z"], sig, rec["ref"][:, j, :2],
                                        spec.p_d, L, bf.warmup_start(rec, j), particles=2048, seed=j)
        pf = float(np.mean(res["expected"][1:][steady]))
        ratios.append(pf / kf["expected_steady_mean"])
        # the filter's median is an estimator as good as the EKF's (realised errors within 10 %)
        assert np.mean(res["realised"][1:][steady]) == pytest.approx(kf["realised_steady_mean"], rel=0.1)
        assert res["dropped"] == 0
    assert np.mean(ratios) == pytest.approx(1.0, abs=0.03), ratios


def test_floor_rows_and_errors():
    with pytest.raises(ValueError, match="tier='Hard'.*Leader"):
        floors.leader_floor("Hard")
    z = np.zeros((1, 5))
    one = np.zeros(1, dtype=np.int64)
    with pytest.raises(ValueError, match="particles=1"):
        bf.particle_floor_episode(np.zeros(dyn.NP), one, one, z, np.ones(1), np.zeros((2, 2)), (0.0, 0.0), 1, 0,
                                  particles=1)
    with pytest.raises(ValueError, match="children=0"):
        bf.particle_floor_episode(np.zeros(dyn.NP), one, one, z, np.ones(1), np.zeros((2, 2)), (0.0, 0.0), 1, 0,
                                  children=0)


def test_leader_floor_is_cached_and_reused(tmp_path):
    """Two calls with a cache directory: the second reads the stored rows (same numbers, no
    filter run), and the rows have the documented columns with an expected error > 0."""
    kw = {"particles": 256, "children": 2, "cache_dir": str(tmp_path)}
    a = floors.leader_floor("Leader-Hard", [210], **kw)
    files = list(tmp_path.glob("leader-floor-Leader-Hard-*.parquet"))
    assert len(files) == 1
    mtime = files[0].stat().st_mtime_ns
    b = floors.leader_floor("Leader-Hard", [210], **kw)
    assert files[0].stat().st_mtime_ns == mtime
    assert a.equals(b)
    assert {"expected_steady_mean", "realised_steady_mean", "min_ess_share", "dropped"} <= set(a.columns)
    assert a["expected_steady_mean"].iloc[0] > 0 and math.isfinite(a["realised_steady_mean"].iloc[0])
