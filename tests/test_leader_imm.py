"""The model-aware IMM of the Leader tiers (controllers/_leader_imm.py): expectations worked out
from the chain's and the models' definitions, not from the filter's output."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest
from test_imm import SIG, _arc  # (the exact piecewise-constant-rate arc and the tiers' fix noise)

import auv_follow_env  # noqa: F401
from controllers import _leader_imm as L
from controllers import make_controller
from controllers.estimator import EstimatorConfig, TargetEstimator


@pytest.fixture(scope="module")
def spec():
    return gym.make("AUVFollow-Leader-Hard-v1").unwrapped.task_spec


def _cfg(spec, **kw):
    return L.limm_config(spec, "Leader-Hard", **kw)


def test_the_modes_switch_with_the_tiers_shares_and_gamma_sojourns(spec):
    """The transition over T: rows that sum to 1; a mode entered now stays with the survival
    function of a Gamma(k) duration of the tier's mean (scipy's); with k = 1 the stay is exp(-T /
    mean) whatever the age (memoryless: a Markov chain); with k = 4 an older mode is likelier to
    end (the hazard grows); the shares of time solve pi_j lam_j = pi_0 lam_0 split_j (each mode
    returns to cruise); on Hard all seven models are in, and cruise's exits follow the generator's
    shares (left, right 0.3, loiter, sprint 0.2 of wandering; U-turns 0.5 each of surveying)."""
    from scipy.stats import gamma

    c = _cfg(spec)
    K = L.K
    lam, pi, split = c[L.C_LAM:L.C_LAM + K], c[L.C_PI:L.C_PI + K], c[L.C_SPLIT:L.C_SPLIT + K]
    assert c[L.C_SHAPE] == 4
    for T in (0.05, 1.0, 7.0, 60.0):
        for ag in (np.zeros(K), np.full(K, 3.0)):
            np.testing.assert_allclose(L._transition_matrix(c, T, ag).sum(axis=1), 1.0, atol=1e-12)
        np.testing.assert_allclose(np.diag(L._transition_matrix(c, T)), gamma.sf(T, a=4, scale=0.25 / lam), rtol=1e-10)
    old = np.diag(L._transition_matrix(c, 2.0, np.full(K, 6.0)))
    assert np.all(old < np.diag(L._transition_matrix(c, 2.0)))
    c1 = _cfg(spec, shape=1)
    for ag in (np.zeros(K), np.full(K, 6.0)):
        np.testing.assert_allclose(np.diag(L._transition_matrix(c1, 2.0, ag)), np.exp(-2.0 * lam), rtol=1e-12)
    assert np.all(pi > 0) and math.isclose(pi.sum(), 1.0)
    np.testing.assert_allclose(pi[1:] * lam[1:], pi[0] * lam[0] * split[1:], rtol=1e-12)
    share = 0.5  # the survey share of Leader-Hard (docs/tiers.md)
    wander = (1 - share) / 8.5  # 1 / mean cruise duration (the middle of U[5, 12] s)
    survey = share / (8.5 / 0.5)  # 1 / a leg's duration (8.5 m at 0.5 m/s)
    np.testing.assert_allclose(split[1:], np.array([0.3 * wander, 0.3 * wander, 0.5 * survey, 0.5 * survey,
                                                    0.2 * wander, 0.2 * wander]) / (wander + survey))


def test_the_modes_missing_from_a_tier_keep_probability_zero():
    """Leader-Easy has one mode set (no loiter, no sprint): those models never get probability."""
    spec = gym.make("AUVFollow-Leader-Easy-v1").unwrapped.task_spec
    c = L.limm_config(spec, "Leader-Easy")
    assert c[L.C_PI + L.LOITER] == c[L.C_PI + L.SPRINT] == 0.0
    P = L._transition_matrix(c, 10.0, np.full(L.K, 4.0))
    assert np.all(P[:, [L.LOITER, L.SPRINT]][[L.CRUISE, L.TURN_L, L.UTURN_L]] == 0.0)
    t = np.arange(0.0, 30.0, 1.0)
    z = _arc(t, lambda s: 0.1 if s > 10 else 0.0) + np.random.default_rng(0).standard_normal((len(t), 5)) * SIG
    _, mus = L.limm_filter_fixes(t, z, np.tile(SIG ** 2, (len(t), 1)), c, t)
    assert np.all(mus[:, [L.LOITER, L.SPRINT]] == 0.0)


def test_a_noiseless_turn_is_predicted_exactly_once_the_rate_is_learned(spec):
    """Exact fixes every 2 s of a constant 0.2 rad/s turn at 0.5 m/s (within Leader-Hard's turn
    rates U[0.15, 0.3]), switches practically off (sojourn_scale 1e-9): the turn model takes the
    probability, its rate adapts to 0.2, and the prediction 3 s past the last fix is the arc's pose
    (the 8-point quadrature of a constant-rate arc is exact to rounding)."""
    t = np.arange(0.0, 80.0, 2.0)
    z = _arc(t, lambda s: 0.2)
    var = np.tile(np.full(5, 1e-10), (len(t), 1))
    truth = _arc(t + 3.0, lambda s: 0.2)
    out, mus = L.limm_filter_fixes(t, z, var, _cfg(spec, sojourn_scale=1e-9), t + 3.0)
    assert mus[-1, L.TURN_L] > 0.999
    np.testing.assert_allclose(out[-1, :2], truth[-1, :2], atol=1e-4)
    assert abs(out[-1, 2] - truth[-1, 2]) < 1e-4
    assert abs(out[-1, 4] - 0.2) < 1e-4


def test_mode_probabilities_switch_within_two_fixes_of_a_turn(spec):
    """A straight run (30 s), then a 0.2 rad/s right turn, fixes every 2 s with the tiers' noise:
    before the turn the cruise model holds most of the probability; from the second fix after
    the turn's start (4 s) a right-turn model (wandering turn or U-turn) holds more than 90 %."""
    rng = np.random.default_rng(0)
    t = np.arange(0.0, 60.0, 2.0)
    z = _arc(t, lambda s: 0.0 if s < 30.0 else -0.2) + rng.standard_normal((len(t), 5)) * SIG
    _, mus = L.limm_filter_fixes(t, z, np.tile(SIG ** 2, (len(t), 1)), _cfg(spec), t)
    before = (t >= 10.0) & (t < 30.0)
    assert mus[before, L.CRUISE].mean() > 0.7
    right = mus[:, L.TURN_R] + mus[:, L.UTURN_R]
    assert np.all(right[t >= 34.0] > 0.9), right


def test_a_sprint_is_recognised_by_its_speed(spec):
    """Straight at 0.5 m/s, then an 8 s sprint toward Leader-Hard's sprint speed (1.05 m/s, the middle
    of U[0.9, 1.2]; the speed lags in with the generator's 2 s), then cruise again; fixes every 2 s
    with the tiers' noise: cruise holds the probability before, and the sprint model (whose speed
    lags toward 1.05) holds more than half of it at every fix from 2 s to 6 s into the sprint."""
    rng = np.random.default_rng(3)
    t = np.arange(0.0, 40.0, 2.0)
    fast, end = 20.0, 28.0
    u = np.where(t < fast, 0.5, np.where(t < end, 1.05 + (0.5 - 1.05) * np.exp(-(t - fast) / 2.0), 0.5))
    z = np.zeros((len(t), 5))
    z[:, 0] = np.concatenate([[0.0], np.cumsum(0.5 * (u[1:] + u[:-1]) * 2.0)])  # (the trapezoid: fine at 2 s)
    z[:, 3] = u
    z += rng.standard_normal((len(t), 5)) * SIG
    _, mus = L.limm_filter_fixes(t, z, np.tile(SIG ** 2, (len(t), 1)), _cfg(spec), t)
    assert mus[(t > 8) & (t < fast), L.CRUISE].mean() > 0.7
    assert np.all(mus[(t >= fast + 2.0) & (t <= fast + 6.0), L.SPRINT] > 0.5), mus[:, L.SPRINT]


def test_an_out_of_order_fix_gives_the_estimate_of_the_same_fixes_in_order(spec):
    """Fixes arriving 3 <-> 4 and 7 <-> 9 swapped: after the late ones have arrived, every output
    equals that of the fixes in measurement order (retrodiction: the same updates re-run, bit for bit)."""
    rng = np.random.default_rng(1)
    t = np.arange(0.0, 30.0, 2.5)
    z = _arc(t, lambda s: 0.2 if 8.0 < s < 20.0 else 0.0) + rng.standard_normal((len(t), 5)) * SIG
    var = np.tile(SIG ** 2, (len(t), 1))
    tq = np.full(len(t), 35.0)
    ref, ref_mu = L.limm_filter_fixes(t, z, var, _cfg(spec), tq)
    order = np.arange(len(t))
    order[[3, 4]] = [4, 3]
    order[[7, 8, 9]] = [8, 9, 7]
    out, mu = L.limm_filter_fixes(t[order], z[order], var[order], _cfg(spec), tq)
    for k in (4, 9, len(t) - 1):
        np.testing.assert_array_equal(out[k], ref[k])
        np.testing.assert_array_equal(mu[k], ref_mu[k])
    assert not np.array_equal(out[3], ref[3])


def test_gating_rejects_multipath_outliers_and_keeps_inliers_at_the_gates_rate(spec):
    """A straight target, fixes every second with the tiers' noise; 1 in 10 fixes moved by 3 m
    (60 position sigmas): every moved fix is gated out; of the inliers no more than about the
    gate's 0.1 % are (allow 0.5 %)."""
    rng = np.random.default_rng(2)
    cfg = _cfg(spec)
    n_out = n_out_gated = n_in = n_in_gated = 0
    for _ in range(30):
        t = np.arange(0.0, 100.0, 1.0)
        z = _arc(t, lambda s: 0.0) + rng.standard_normal((len(t), 5)) * SIG
        m, P, mu, ag = np.zeros((L.K, L.NX)), np.zeros((L.K, L.NX, L.NX)), np.zeros(L.K), np.zeros(L.K)
        om, ng = np.zeros(2), np.zeros(1, dtype=np.int64)
        L.limm_init(m, P, mu, ag, om, z[0], SIG ** 2, cfg, True)
        for k in range(1, len(t)):
            zz = z[k].copy()
            outlier = k % 10 == 5
            if outlier:
                a = rng.uniform(0, 2 * math.pi)
                zz[:2] += 3.0 * np.array([math.cos(a), math.sin(a)])
            gated = L.limm_update(m, P, mu, ag, om, ng, 1.0, zz, SIG ** 2, cfg, L.work())
            if k < 10:
                continue
            if outlier:
                n_out, n_out_gated = n_out + 1, n_out_gated + gated
            else:
                n_in, n_in_gated = n_in + 1, n_in_gated + gated
    assert n_out_gated == n_out
    assert n_in_gated <= 0.005 * n_in


def _episodes(n: int, steps: int, seed: int = 700):
    venv = gym.make_vec("AUVFollow-Leader-Hard-v1", num_envs=n, vectorization_mode="vector_entry_point",
                        episode_s=steps * 0.05, steady_start_s=0.5 * steps * 0.05)
    spec = venv.unwrapped.task_spec
    driver = make_controller("PROPOSED_IMM_DOB", spec)
    obs, _ = venv.reset(seed=list(range(seed, seed + n)))
    start = np.ones(n, dtype=bool)
    out = []
    for _ in range(steps):
        o = np.asarray(obs, dtype=np.float64)
        out.append((o, start.copy()))
        act, _ = driver.predict(o, episode_start=start)
        obs, _, term, trunc, _ = venv.step(act)
        start = term | trunc
    return spec, out


def test_the_per_step_advance_equals_the_prediction_from_the_fix():
    """Between fixes the kernel advances every model by one control step (a constant-rate arc per
    step); the direct prediction from the last fix (trajectory at 0 s: the closed form and the
    quadrature, 6 nodes) agrees within 1 mm and 1e-4 rad along real Leader-Hard episodes (against errors of
    tenths of a metre)."""
    spec, steps = _episodes(6, 400)
    est = TargetEstimator(spec, EstimatorConfig(model="LEADER_IMM"))
    worst = 0.0
    for o, start in steps:
        e = est.step(o, start, with_cov=False)
        x, y, psi = est.trajectory(np.array([0.0]), frame="odometry")
        ok = e.valid
        worst = max(worst, np.max(np.abs(x[ok, 0] - e.x[ok]), initial=0), np.max(np.abs(y[ok, 0] - e.y[ok]), initial=0))
        assert np.all(np.abs(np.angle(np.exp(1j * (psi[ok, 0] - e.psi[ok])))) < 1e-4)
    assert worst < 1e-3


def test_threaded_step_equals_the_serial_step_bit_for_bit(monkeypatch, count_calls):
    """From THREADED_MIN_ENVS envs on, the batch is split over numba's threads: the same operations
    per env, so the same bits (one process), along real Leader-Hard episodes."""
    import numba

    n = L.THREADED_MIN_ENVS + 5
    spec, steps = _episodes(n, 80)
    cfg = EstimatorConfig(model="LEADER_IMM")
    threaded, serial = TargetEstimator(spec, cfg), TargetEstimator(spec, cfg)
    calls = count_calls(L, "_limm_threads")
    for o, start in steps:
        a = threaded.step(o, start, with_cov=False)
        monkeypatch.setattr(L, "THREADED_MIN_ENVS", 10**9)
        b = serial.step(o, start, with_cov=False)
        monkeypatch.setattr(L, "THREADED_MIN_ENVS", n - 5)
        for f in ("rel_x", "rel_y", "rel_psi", "u", "r", "age", "valid"):
            assert np.array_equal(getattr(a, f), getattr(b, f)), f
    for f in ("m", "P", "mu", "ag", "om", "pm", "pc", "sq", "sp0"):
        assert np.array_equal(getattr(threaded._s, f), getattr(serial._s, f)), f
    assert calls["calls"] == (80 if numba.get_num_threads() > 1 else 0)


def test_the_model_aware_imm_controller_runs_on_leader_tiers_only():
    """PROPOSED_LIMM_DOB refuses a task that is not a Leader tier's (it needs the tier's modes);
    on Leader-Hard it keeps a bounded error along short episodes, and peeks (commit=False) leave the
    filter as it was: peeking and committing gives the bits of committing alone, whether the peek's
    copy is whole or only what changed."""
    with pytest.raises(ValueError, match="needs a Leader tier"):
        make_controller("PROPOSED_LIMM_DOB", gym.make("AUVFollow-Hard-v1").unwrapped.task_spec)
    spec, steps = _episodes(4, 200, seed=900)
    est = TargetEstimator(spec, EstimatorConfig(model="LEADER_IMM"))
    twin = TargetEstimator(spec, EstimatorConfig(model="LEADER_IMM"))
    twin.reuse_peek = False
    for k, (o, start) in enumerate(steps):
        # a peek, then the commit on the same input (it adopts the peek's state: the next peek copies
        # only what changed into the state left spare); every 7th step a plain commit breaks that chain
        if k % 7 != 3:
            est.step(o, start, commit=False, with_cov=False)
        a = est.step(o, start, with_cov=False)
        b = twin.step(o, start, with_cov=False)
        np.testing.assert_array_equal(a.rel_x, b.rel_x)
        assert np.all(np.isfinite(a.rel_x)) and np.all(np.abs(a.rel_x[a.valid]) < 100.0)


def test_the_model_aware_imm_settings_are_the_fitted_ones_in_the_committed_table():
    """controllers.LEADER_LIMM is the table written by experiments/leader_limm_fit.py (the best of its
    grid on training seeds), and PROPOSED_LIMM_DOB's estimator runs with them."""
    import json
    import re
    from pathlib import Path

    from controllers import LEADER_LIMM

    text = (Path(__file__).resolve().parents[1] / "results" / "leader_limm_fit.md").read_text()
    assert json.loads(re.search(r"```json\n(.*?)```", text, re.S).group(1)) == LEADER_LIMM
    spec = gym.make("AUVFollow-Leader-Hard-v1").unwrapped.task_spec
    cfg = make_controller("PROPOSED_LIMM_DOB", spec).estimator.config
    assert {k: getattr(cfg, k) for k in LEADER_LIMM["Leader-Hard"]} == LEADER_LIMM["Leader-Hard"]


def test_bad_model_aware_imm_settings_are_refused_by_name():
    with pytest.raises(ValueError, match="limm_sojourn=0"):
        EstimatorConfig(model="LEADER_IMM", limm_sojourn=0.0)
    with pytest.raises(ValueError, match="limm_q_h=-1"):
        EstimatorConfig(model="LEADER_IMM", limm_q_h=-1.0)
