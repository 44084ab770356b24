"""Floors per tier (agents/benchmark/floors.py): the oracle-parameter floor against closed forms and Monte
Carlo, the packets recovered from the observations, the perfect link, the leaderboard rows."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pandas as pd
import pytest
import scipy.linalg

import auv_follow_env  # noqa: F401
from agents.benchmark import floors
from agents.benchmark.leaderboard import leaderboard
from auv_follow_env import perfect_link


def _periodic(period: int, latency: int, T: int, first: int = 0) -> tuple[np.ndarray, np.ndarray]:
    meas = np.arange(first, T, period)
    return meas, meas + latency


def _lag_of(t: int, period: int, latency: int) -> int:
    """Steps since the measurement of the newest packet with arrival <= t - 1 (fixes at 0, period, ...)."""
    m = period * ((t - 1 - latency) // period)
    return t - m


# --- mean norm of a 2-D Gaussian -------------------------------------------------------------

def test_mean_norm_2d_closed_forms():
    s = 0.3
    # isotropic: Rayleigh mean s sqrt(pi / 2); one zero axis: half-normal mean s sqrt(2 / pi)
    assert floors.mean_norm_2d(np.diag([s * s, s * s])) == pytest.approx(s * math.sqrt(math.pi / 2), rel=1e-12)
    assert floors.mean_norm_2d(np.diag([0.0, s * s])) == pytest.approx(s * math.sqrt(2 / math.pi), rel=1e-12)
    assert floors.mean_norm_2d(np.zeros((2, 2))) == 0.0
    # a rotated anisotropic covariance against Monte Carlo (1e6 samples: SE ~ 2e-4 of the mean)
    rot = np.array([[math.cos(0.7), -math.sin(0.7)], [math.sin(0.7), math.cos(0.7)]])
    cov = rot @ np.diag([0.04, 0.0025]) @ rot.T
    e = np.random.default_rng(1).multivariate_normal([0, 0], cov, size=1_000_000)
    norms = np.hypot(e[:, 0], e[:, 1])
    assert abs(floors.mean_norm_2d(cov) - norms.mean()) < 4 * norms.std() / 1000


# --- the delayed Kalman filter: closed forms ---------------------------------------------------

def test_information_floor_random_walk_closed_form():
    """2-D random-walk target (x' = white noise, intensity q per axis), a fix of both coordinates
    every n steps with noise variance rv, latency L steps. Worked by hand: the steady filtered
    variance per axis solves P = (P + a) rv / (P + a + rv), a = q n dt, i.e. P^2 + a P - a rv = 0,
    P = (-a + sqrt(a^2 + 4 a rv)) / 2; at step t the estimate is that of the newest packet with
    arrival <= t - 1, d steps old, variance P + q dt d on each axis, so E||e|| = sqrt(pi/2 (P + q dt d))."""
    dt, q, rv, n, L, T = 0.05, 0.02, 0.01, 40, 30, 4000
    a = q * n * dt
    P = (-a + math.sqrt(a * a + 4 * a * rv)) / 2
    meas, arr = _periodic(n, L, T)
    M = len(meas)
    F = np.tile(np.eye(2), (T, 1, 1))
    Q = np.tile(q * dt * np.eye(2), (T, 1, 1))
    H = np.tile(np.eye(2), (M, 1, 1))
    R = np.tile(rv * np.eye(2), (M, 1, 1))
    J = np.tile(np.eye(2), (T + 1, 1, 1))
    _, cov = floors.delayed_kalman(F, Q, 0, T, meas, arr, np.zeros((M, 2)), H, R, np.zeros(2), 100 * np.eye(2), J)
    t = np.arange(T - 4 * n, T + 1)  # converged: whole periods at the end
    expected = [math.sqrt(math.pi / 2 * (P + q * dt * _lag_of(k, n, L))) for k in t]
    np.testing.assert_allclose(floors.mean_norm_2d(cov[t]), expected, rtol=1e-9)
    assert np.isnan(cov[: L + 1]).all()  # nothing has arrived before step L: no estimate


def _cwna(q: float, h: float) -> np.ndarray:
    """Continuous white-noise acceleration over h, one axis (p, v)."""
    return q * np.array([[h ** 3 / 3, h ** 2 / 2], [h ** 2 / 2, h]])


def _blockdiag2(a: np.ndarray) -> np.ndarray:
    return scipy.linalg.block_diag(a, a)


def test_information_floor_constant_velocity_riccati():
    """2-D constant-velocity target with white acceleration noise (intensity q per axis), position
    fixes every n steps (noise variance rv), latency L steps. Independently: the period-T model
    F_T = [[1, T], [0, 1]], Q_T = q [[T^3/3, T^2/2], [T^2/2, T]] (the exact discretisation, which the
    per-step model composes to), steady a-priori covariance from scipy's discrete Riccati solver,
    the measurement update, then the prediction d steps ahead: F_d P F_d' + Q_d."""
    dt, q, rv, n, L, T = 0.05, 0.05, 0.004, 30, 25, 3000
    Tp = n * dt
    FT = np.array([[1.0, Tp], [0.0, 1.0]])
    h = np.array([[1.0, 0.0]])
    Pm = scipy.linalg.solve_discrete_are(FT.T, h.T, _cwna(q, Tp), np.array([[rv]]))
    Pf = Pm - Pm @ h.T @ np.linalg.inv(h @ Pm @ h.T + rv) @ h @ Pm

    def pos_var(d: int) -> float:
        Fd = np.array([[1.0, d * dt], [0.0, 1.0]])
        return float((Fd @ Pf @ Fd.T + _cwna(q, d * dt))[0, 0])

    meas, arr = _periodic(n, L, T)
    M = len(meas)
    f1 = np.array([[1.0, dt], [0.0, 1.0]])
    F = np.tile(_blockdiag2(f1), (T, 1, 1))  # state (x, vx, y, vy)
    Q = np.tile(_blockdiag2(_cwna(q, dt)), (T, 1, 1))
    Hm = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]])
    J = np.tile(Hm, (T + 1, 1, 1))
    _, cov = floors.delayed_kalman(F, Q, 0, T, meas, arr, np.zeros((M, 2)), np.tile(Hm, (M, 1, 1)),
                                   np.tile(rv * np.eye(2), (M, 1, 1)), np.zeros(4), np.diag([100.0, 1, 100, 1]), J)
    t = np.arange(T - 3 * n, T + 1)
    expected = [math.sqrt(math.pi / 2 * pos_var(_lag_of(k, n, L))) for k in t]
    np.testing.assert_allclose(floors.mean_norm_2d(cov[t]), expected, rtol=1e-7)


def test_information_floor_matches_monte_carlo():
    """Per episode: with irregular packet timing and losses (one fixed draw), the floor (mean over
    the window of E||e|| from the posterior covariance) equals the average over many simulated
    target paths and noise draws of the same filter's realised error, within 4 standard errors."""
    rng = np.random.default_rng(7)
    dt, q, rv, T = 0.05, 0.08, 0.003, 400
    sends = np.cumsum(rng.integers(15, 45, size=40))
    sends = sends[sends < T - 5]
    lat = rng.integers(10, 40, size=len(sends))
    keep = rng.random(len(sends)) > 0.2  # lost packets
    meas, arr = sends[keep], sends[keep] + lat[keep]
    arr = np.maximum.accumulate(arr)  # the follower keeps only packets arriving in order
    ok = np.r_[True, np.diff(arr) > 0]
    meas, arr = meas[ok], arr[ok]
    M = len(meas)
    f1 = np.array([[1.0, dt], [0.0, 1.0]])
    Fs = _blockdiag2(f1)
    Qs = _blockdiag2(_cwna(q, dt))
    F, Q = np.tile(Fs, (T, 1, 1)), np.tile(Qs, (T, 1, 1))
    Hm = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]])
    J = np.tile(Hm, (T + 1, 1, 1))
    x0, P0 = np.array([0.0, 0.4, 0.0, 0.1]), np.diag([0.5, 0.04, 0.5, 0.04])
    H, R = np.tile(Hm, (M, 1, 1)), np.tile(rv * np.eye(2), (M, 1, 1))
    window = np.arange(T + 1) * dt >= 10.0
    k0 = int(meas[0])  # the prior (x0, P0) is at the first packet's measurement step
    _, cov = floors.delayed_kalman(F[k0:], Q[k0:], k0, T, meas, arr, np.zeros((M, 2)), H, R, x0, P0, J)
    floor = floors.mean_norm_2d(cov[window]).mean()
    L = np.linalg.cholesky(Qs + 1e-15 * np.eye(4))
    draws = []
    for _ in range(600):
        x = np.empty((T + 1, 4))
        x[k0] = rng.multivariate_normal(x0, P0)
        for k in range(k0, T):
            x[k + 1] = Fs @ x[k] + L @ rng.standard_normal(4)
        z = x[meas][:, [0, 2]] + math.sqrt(rv) * rng.standard_normal((M, 2))
        est, _ = floors.delayed_kalman(F[k0:], Q[k0:], k0, T, meas, arr, z, H, R, x0, P0, J)
        err = np.hypot(est[window, 0] - x[window, 0], est[window, 1] - x[window, 2])
        draws.append(err.mean())
    draws = np.asarray(draws)
    se = draws.std(ddof=1) / math.sqrt(len(draws))
    assert abs(draws.mean() - floor) < 4 * se, (draws.mean(), floor, se)
    assert se < 0.05 * floor  # the check has power: the sampling error is small against the floor


def test_delayed_kalman_rejects_bad_timing():
    F = np.tile(np.eye(2), (10, 1, 1))
    with pytest.raises(ValueError, match="increasing"):
        floors.delayed_kalman(F, F, 0, 10, [3, 2], [4, 5], np.zeros((2, 2)), np.tile(np.eye(2), (2, 1, 1)),
                              np.tile(np.eye(2), (2, 1, 1)), np.zeros(2), np.eye(2), np.zeros((11, 2, 2)))
    with pytest.raises(ValueError, match="shape"):
        floors.delayed_kalman(F[:5], F[:5], 0, 10, [3], [4], np.zeros((1, 2)), np.eye(2)[None], np.eye(2)[None],
                              np.zeros(2), np.eye(2), np.zeros((11, 2, 2)))


# --- what the follower received --------------------------------------------------------------

def test_extract_packets_recovers_the_true_fixes():
    """With no fix noise, every recovered packet equals the true target at its measurement step
    (x, y, psi, u, r), its arrival step is the step it showed up, and the steps between a send and
    its arrival equal the configured constant latency."""
    env = gym.make("AUVFollow-v1", scenario="S4", update_period_s=1.0, latency_model="constant", latency_s=1.5,
                   target_speed_std=0.05, target_yaw_rate_std=0.05, target_surge_amp=0.0, target_yaw_rate_amp=0.0,
                   thruster_tc_s=0.2)
    obs, info = env.reset(seed=11)
    rec_obs, tgt, pose = [obs], [info["true_target"].copy()], [info["follower_pose"].copy()]
    rng = np.random.default_rng(0)
    for _ in range(400):
        obs, _, _, _, info = env.step(rng.uniform(-0.3, 0.3, 3).astype(np.float32))
        rec_obs.append(obs)
        tgt.append(info["true_target"].copy())
        pose.append(info["follower_pose"].copy())
    env.close()
    pk = floors.extract_packets(np.array(rec_obs), np.array(pose), 0.05)
    tgt = np.array(tgt)
    late = pk["meas"] >= 0
    assert late.sum() >= 18  # a packet per second over 20 s
    np.testing.assert_array_equal(pk["arr"][late] - pk["meas"][late], 30)  # 1.5 s
    np.testing.assert_array_equal(np.diff(pk["meas"][late]), 20)  # 1 s
    m = pk["meas"][late]
    truth = tgt[m][:, [0, 1, 2, 3, 5]]
    np.testing.assert_allclose(pk["z"][late][:, :2], truth[:, :2], atol=2e-5)
    np.testing.assert_allclose(np.angle(np.exp(1j * (pk["z"][late][:, 2] - truth[:, 2]))), 0.0, atol=2e-6)
    np.testing.assert_allclose(pk["z"][late][:, 3:], truth[:, 3:], atol=1e-6)


# --- the perfect link ----------------------------------------------------------------------------

def _substitution_gap(env_kwargs: dict, seeds: list[int]) -> float:
    """Largest difference between the env's observation and :func:`perfect_link_observation`
    of it over 300 steps of PROPOSED_KF_DOB (which sees the env's own observation)."""
    from controllers import make_controller

    venv = gym.make_vec("AUVFollow-v1", num_envs=len(seeds), vectorization_mode="vector_entry_point", **env_kwargs)
    spec = venv.unwrapped.task_spec if hasattr(venv, "unwrapped") else venv.task_spec
    pol = make_controller("PROPOSED_KF_DOB", spec)
    obs, info = venv.reset(seed=seeds)
    gap = 0.0
    start = np.ones(len(seeds), dtype=bool)
    for _ in range(300):
        seen = perfect_link.perfect_link_observation(obs, info["true_target"], info["follower_pose"], spec.p_d)
        gap = max(gap, float(np.abs(seen.astype(np.float64) - obs).max()))
        act, _ = pol.predict(obs, episode_start=start)
        start[:] = False
        obs, _, _, _, info = venv.step(act)
    venv.close()
    return gap


def test_perfect_link_observation_equals_the_perfect_link_overrides():
    """On an env made with :func:`perfect_link_overrides` (a fix every step, no latency, loss or
    noise) the env's own observation must be the substituted one (to float32 rounding), on every
    step of a moving follower; on a real link it is not."""
    base = {"scenario": "S4", "target_speed_std": 0.05, "target_yaw_rate_std": 0.06, "target_surge_amp": 0.0,
            "target_yaw_rate_amp": 0.0, "thruster_tc_s": 0.3, "thruster_rate": 1.5, "current_speed": 0.1,
            "current_speed_std": 0.03, "warmup_s": 4.0}
    assert _substitution_gap({**base, **perfect_link.perfect_link_overrides(0.05)}, [5, 6, 7]) < 2e-6
    real = {**base, "update_period_s": 2.0, "latency_s": 1.5, "fix_sigma_m": 0.05}
    assert _substitution_gap(real, [5, 6, 7]) > 0.1


def test_control_floor_and_rows_on_a_few_episodes():
    seeds = [1000000, 1000001, 1000002, 1000003]
    cf = floors.control_floor("Easy", seeds, controllers=["PROPOSED", "PROPOSED_KF_DOB"])
    assert set(cf.iqm) == {"PROPOSED", "PROPOSED_KF_DOB"}
    assert cf.best == min(cf.iqm, key=cf.iqm.get)
    assert list(cf.scores["seed"]) == seeds and (cf.scores["policy"] == cf.best).all()
    rows = floors.floor_episodes("Easy", seeds, controllers=["PROPOSED", "PROPOSED_KF_DOB"])
    assert set(rows["policy"]) == {floors.CONTROL_FLOOR, floors.INFORMATION_FLOOR}
    assert (rows["kind"] == floors.REFERENCE_KIND).all() and len(rows) == 2 * len(seeds)
    assert {"tier", "env_id", "run", "terminated", "true_steady_mean", "fail_error_m", "cond_latency_s"} <= set(rows)
    ctrl = rows[rows["policy"] == floors.CONTROL_FLOOR]
    np.testing.assert_allclose(ctrl["true_steady_mean"], cf.scores["true_steady_mean"])
    assert (rows["true_steady_mean"] > 0).all()
    # a leaderboard with the floors: they are not the best classical, and the gap column exists
    comp = rows[rows["policy"] == floors.CONTROL_FLOOR].assign(policy="X", kind="classical", run="X",
                                                              true_steady_mean=1.0, true_full_mean=1.0)
    board = leaderboard(pd.concat([rows, comp], ignore_index=True), n_resamples=50)
    assert (board["best_classical"] == "X").all()
    assert "gap_closed" in board and board.loc[board["policy"] == "X", "gap_closed"].item() == 0.0


def test_add_gap_closed_by_hand():
    board = pd.DataFrame({
        "tier": ["Hard"] * 5 + ["Easy"],
        "policy": ["A", "B", "C", floors.INFORMATION_FLOOR, floors.CONTROL_FLOOR, "A"],
        "kind": ["classical", "classical", "learned", "reference", "reference", "classical"],
        "true_steady_mean_iqm": [0.40, 0.50, 0.35, 0.30, 0.01, 0.02],
        "best_classical": ["A"] * 5 + ["A"]})
    out = floors.add_gap_closed(board)
    g = dict(zip(out["tier"] + "/" + out["policy"], out["gap_closed"], strict=True))
    assert g["Hard/A"] == 0.0
    assert g["Hard/B"] == pytest.approx(-1.0)  # (0.40 - 0.50) / (0.40 - 0.30)
    assert g["Hard/C"] == pytest.approx(0.5)  # (0.40 - 0.35) / 0.10
    assert math.isnan(g[f"Hard/{floors.INFORMATION_FLOOR}"]) and math.isnan(g[f"Hard/{floors.CONTROL_FLOOR}"])
    assert math.isnan(g["Easy/A"])  # no oracle-parameter floor on that tier


def test_gap_closed_is_measured_from_the_best_generic_classical():
    """On a Leader tier the model-aware PROPOSED_PF_DOB may be the best classical row; the gap is
    the best *generic* classical's to the floor (issue: the share of the generic-to-floor gap)."""
    board = pd.DataFrame({
        "tier": ["Leader-Hard"] * 5,
        "policy": ["PROPOSED_PF_DOB", "PROPOSED_IMM_DOB", "PROPOSED_KF_DOB", "L", floors.INFORMATION_FLOOR],
        "kind": ["classical", "classical", "classical", "learned", "reference"],
        "true_steady_mean_iqm": [0.50, 0.60, 0.65, 0.55, 0.20],
        "best_classical": ["PROPOSED_PF_DOB"] * 5})
    g = dict(zip(floors.add_gap_closed(board)["policy"], floors.add_gap_closed(board)["gap_closed"], strict=True))
    assert g["PROPOSED_IMM_DOB"] == 0.0
    assert g["PROPOSED_PF_DOB"] == pytest.approx(0.25)  # (0.60 - 0.50) / (0.60 - 0.20)
    assert g["L"] == pytest.approx(0.125)  # (0.60 - 0.55) / 0.40
    assert g["PROPOSED_KF_DOB"] == pytest.approx(-0.125)


def test_bad_arguments():
    with pytest.raises(ValueError, match="tier='S4'"):
        floors.control_floor("S4", [1])
    with pytest.raises(ValueError, match="seeds contains -1"):
        floors.information_floor("Easy", [-1])
    with pytest.raises(ValueError, match="controllers=\\['NOPE'\\]"):
        floors.perfect_link_episodes("Easy", [1], ["NOPE"])
    with pytest.raises(ValueError, match="follower='NOPE'"):
        floors.record_episodes("Easy", [1], "NOPE")
    with pytest.raises(ValueError, match="obs has shape"):
        perfect_link.perfect_link_observation(np.zeros((2, 16)), np.zeros((2, 6)), np.zeros((2, 3)), (0, 0))
    with pytest.raises(ValueError, match="oracle-parameter floor exists for the v1 tiers"):
        floors.information_floor("Leader-Hard", [1])


def test_a_leader_tier_has_both_floors_its_information_floor_a_particle_filter():
    """The control floor (a perfect link) does not depend on the target's model; a Leader tier's
    oracle-parameter floor is the particle filter under the true generator (a linear filter's
    posterior would be wrong there), and lies above the control floor."""
    df = floors.floor_episodes("Leader-Hard", [1], controllers=["PROPOSED_KF_DOB"], tier_prior=False)
    assert set(df["policy"]) == {floors.CONTROL_FLOOR, floors.INFORMATION_FLOOR}
    assert (df["tier"] == "Leader-Hard").all() and (df["kind"] == floors.REFERENCE_KIND).all()
    ctrl = df.loc[df["policy"] == floors.CONTROL_FLOOR].iloc[0]
    info = df.loc[df["policy"] == floors.INFORMATION_FLOOR].iloc[0]
    assert ctrl["true_steady_mean"] < 0.05
    assert info["run"].startswith("particle filter") and info["true_steady_mean"] > ctrl["true_steady_mean"]


def test_benchmark_with_floors_and_report(tmp_path):
    """benchmark(floors=True): the floors are reference rows (never the best classical), the
    leaderboard gets gap_closed (0 for the best classical), the Markdown its column, and the HTML
    report marks them and replays a competitor, not a floor."""
    from agents.benchmark.report import write_report
    from agents.benchmark.run import benchmark

    seeds = [1000000, 1000001, 1000002]
    res = benchmark(["PROPOSED", "PROPOSED_KF"], tiers=["Easy"], seeds=seeds, floors=True, out_dir=tmp_path,
                    n_resamples=50, progress=False)
    b = res.leaderboard.set_index("policy")
    assert b.loc[floors.CONTROL_FLOOR, "kind"] == b.loc[floors.INFORMATION_FLOOR, "kind"] == floors.REFERENCE_KIND
    best = b["best_classical"].iloc[0]
    assert best in ("PROPOSED", "PROPOSED_KF") and b.loc[best, "gap_closed"] == 0.0
    other = ({"PROPOSED", "PROPOSED_KF"} - {best}).pop()
    f, x, o = (b.loc[p, "true_steady_mean_iqm"] for p in (floors.INFORMATION_FLOOR, best, other))
    assert b.loc[other, "gap_closed"] == pytest.approx((x - o) / (x - f))
    assert "gap closed" in (tmp_path / "leaderboard.md").read_text()
    page = write_report(tmp_path).read_text()
    assert "leaderboard-row reference" in page and "gap closed" in page


def test_floors_script_smoke(tmp_path, capsys):
    from experiments.floors import main

    main(["--tiers", "Easy", "--seeds", "2", "--out", str(tmp_path), "--no-progress"])
    table = pd.read_csv(tmp_path / "floors.csv")
    assert list(table["seed"]) == [1000000, 1000001] and (table["tier"] == "Easy").all()
    assert (table["expected_steady_mean"] > table["control_floor_steady_mean"]).all()
    text = (tmp_path / "floors.md").read_text()
    assert "python -m experiments.floors --tiers Easy --seeds 2 --out" in text and "| Easy |" in text
    with pytest.raises(SystemExit):
        main(["--seeds", "1"])
    assert "--seeds must be in [2, 100]" in capsys.readouterr().err
