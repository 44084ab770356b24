"""The generic estimator of the Leader tiers (controllers/_imm.py: IMM over constant-velocity and
coordinated-turn models, gated): expectations worked out from the models' definitions."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest

from controllers import _imm

ROOT = Path(__file__).resolve().parents[1]
SIG = np.array([0.05, 0.05, 0.02, 0.02, 0.01])


def _cfg(gate: bool = True, q_u: float = 0.01, q_r: float = 0.001, q_h: float = 0.001, ts: float = 15.0):
    c = np.zeros(_imm.NC)
    c[_imm.C_DT] = 0.05
    c[_imm.C_QU], c[_imm.C_QR], c[_imm.C_QH], c[_imm.C_TS] = q_u, q_r, q_h, ts
    c[_imm.C_GATE] = float(gate)
    return c


def _arc(t: np.ndarray, r_of_t, u: float = 0.5) -> np.ndarray:
    """Exact poses (x, y, psi, u, r) of a target at speed u whose turn rate is piecewise constant
    (r_of_t(t)), integrated in closed form segment by segment at 1 ms."""
    out = np.zeros((len(t), 5))
    x = y = psi = 0.0
    h = 1e-3
    tt = 0.0
    for k, tk in enumerate(t):
        while tt < tk - 1e-12:
            r = r_of_t(tt)
            step = min(h, tk - tt)
            if abs(r) > 0:
                x += u * (math.sin(psi + r * step) - math.sin(psi)) / r
                y += u * (math.cos(psi) - math.cos(psi + r * step)) / r
            else:
                x += u * step * math.cos(psi)
                y += u * step * math.sin(psi)
            psi += r * step
            tt += step
        out[k] = (x, y, psi, u, r_of_t(tk))
    return out


def test_a_noiseless_arc_is_predicted_exactly_by_the_turn_model():
    """Exact fixes every 2 s of a constant turn (0.2 rad/s at 0.5 m/s), models that practically
    never switch (tau_s = 1e9 s): once the coordinated-turn model carries the probability, the
    prediction 3 s past the last fix is the arc's pose (with switches, the IMM would hedge toward
    the straight model's prediction by the switch probability over those 3 s)."""
    t = np.arange(0.0, 40.0, 2.0)
    z = _arc(t, lambda s: 0.2)
    var = np.tile(np.full(5, 1e-8), (len(t), 1))
    truth = _arc(t + 3.0, lambda s: 0.2)
    out, mus = _imm.imm_filter_fixes(t, z, var, _cfg(ts=1e9), t + 3.0)
    assert mus[-1, 1] > 0.999
    np.testing.assert_allclose(out[-1, :2], truth[-1, :2], atol=1e-4)
    assert abs(out[-1, 2] - truth[-1, 2]) < 1e-4


def test_mode_probabilities_switch_within_two_fixes_of_a_turn():
    """A straight run (30 s), then a 0.2 rad/s turn, fixes every 2 s with the tiers' noise
    (0.05 m, 0.02 rad, 0.02 m/s, 0.01 rad/s): before the turn the constant-velocity model holds
    most of the probability on average (a turn model with a rate near 0 explains a straight run
    almost as well, so not at every fix); within two fixes (4 s) of the turn's start the turn model
    holds more than 90 % and its rate is the turn's within 0.02 rad/s."""
    rng = np.random.default_rng(0)
    t = np.arange(0.0, 60.0, 2.0)
    z = _arc(t, lambda s: 0.0 if s < 30.0 else 0.2) + rng.standard_normal((len(t), 5)) * SIG
    var = np.tile(SIG ** 2, (len(t), 1))
    out, mus = _imm.imm_filter_fixes(t, z, var, _cfg(), t)
    before = (t >= 10.0) & (t < 30.0)
    assert mus[before, 0].mean() > 0.7
    after = t >= 34.0
    assert np.all(mus[after, 1] > 0.9), mus[:, 1]
    assert np.all(np.abs(out[after, 4] - 0.2) < 0.02)


def test_an_out_of_order_fix_gives_the_estimate_of_the_same_fixes_in_order():
    """Fixes arriving 3 <-> 4 and 7 <-> 9 swapped: after the late ones have arrived, every output
    equals that of the fixes in measurement order (retrodiction: the same updates re-run, bit for bit)."""
    rng = np.random.default_rng(1)
    t = np.arange(0.0, 30.0, 2.5)
    z = _arc(t, lambda s: 0.1 if 8.0 < s < 20.0 else 0.0) + rng.standard_normal((len(t), 5)) * SIG
    var = np.tile(SIG ** 2, (len(t), 1))
    tq = np.full(len(t), 35.0)
    ref, ref_mu = _imm.imm_filter_fixes(t, z, var, _cfg(), tq)
    order = np.arange(len(t))
    order[[3, 4]] = [4, 3]
    order[[7, 8, 9]] = [8, 9, 7]
    out, mu = _imm.imm_filter_fixes(t[order], z[order], var[order], _cfg(), tq)
    for k in (4, 9, len(t) - 1):  # after both of a swapped pair (and at the end)
        np.testing.assert_array_equal(out[k], ref[k])
        np.testing.assert_array_equal(mu[k], ref_mu[k])
    assert not np.array_equal(out[3], ref[3])  # before the late fix came, the filter had less


def test_gating_rejects_multipath_outliers_and_keeps_inliers_at_the_gates_rate():
    """A straight target, fixes every second with the tiers' noise; 1 in 10 fixes moved by 3 m
    (60 position sigmas): every moved fix is gated out, and of the inliers no more than about the
    gate's 0.1 % are (both models' gates must reject; allow 0.5 %)."""
    rng = np.random.default_rng(2)
    cfg = _cfg()
    n_out = n_out_gated = n_in = n_in_gated = 0
    for _ in range(40):
        t = np.arange(0.0, 100.0, 1.0)
        z = _arc(t, lambda s: 0.0) + rng.standard_normal((len(t), 5)) * SIG
        m, P, mu, ng = np.zeros((2, 5)), np.zeros((2, 5, 5)), np.zeros(2), np.zeros(1, dtype=np.int64)
        _imm.imm_init(m, P, mu, z[0], SIG ** 2)
        for k in range(1, len(t)):
            zz = z[k].copy()
            outlier = k % 10 == 5
            if outlier:
                a = rng.uniform(0, 2 * math.pi)
                zz[:2] += 3.0 * np.array([math.cos(a), math.sin(a)])
            gated = _imm.imm_update(m, P, mu, ng, 1.0, zz, SIG ** 2, cfg)
            if k < 10:
                continue  # the filter settles
            if outlier:
                n_out += 1
                n_out_gated += gated
            else:
                n_in += 1
                n_in_gated += gated
    assert n_out_gated == n_out
    assert n_in_gated <= 0.005 * n_in


def test_two_gated_fixes_in_a_row_restart_the_filter_at_the_newest():
    """The target jumps 20 m (the filter lost it): the first fix there is gated, the second
    restarts both models at that fix."""
    m, P, mu, ng = np.zeros((2, 5)), np.zeros((2, 5, 5)), np.zeros(2), np.zeros(1, dtype=np.int64)
    _imm.imm_init(m, P, mu, np.array([0.0, 0.0, 0.0, 0.5, 0.0]), SIG ** 2)
    _imm.imm_update(m, P, mu, ng, 1.0, np.array([0.5, 0.0, 0.0, 0.5, 0.0]), SIG ** 2, _cfg())
    far = np.array([21.0, 0.0, 0.0, 0.5, 0.0])
    assert _imm.imm_update(m, P, mu, ng, 1.0, far, SIG ** 2, _cfg()) and ng[0] == 1
    far2 = np.array([21.5, 0.0, 0.0, 0.5, 0.0])
    _imm.imm_update(m, P, mu, ng, 1.0, far2, SIG ** 2, _cfg())
    assert ng[0] == 0
    np.testing.assert_array_equal(m[1], far2)
    assert mu[0] == mu[1] == 0.5


def test_leader_imm_settings_are_the_fitted_ones_in_the_committed_table():
    from controllers import LEADER_IMM

    text = (ROOT / "results" / "leader_estimators.md").read_text()
    fitted = json.loads(re.search(r"```json\n(.*?)```", text, re.S).group(1))
    assert fitted == LEADER_IMM


@pytest.mark.parametrize("tier", ["Leader-Medium", "Hard"])
def test_the_imm_controller_follows_a_leader(tier):
    """PROPOSED_IMM_DOB (the IMM in the hierarchical law) keeps a finite, bounded error on a Leader
    tier and on an OU tier for a whole episode (a smoke test of the integration)."""
    import gymnasium as gym

    import auv_follow_env  # noqa: F401
    from controllers import make_controller

    env = gym.make(f"AUVFollow-{tier}-v1")
    ctrl = make_controller("PROPOSED_IMM_DOB", env.unwrapped.task_spec)
    obs, _ = env.reset(seed=11)
    errs = []
    for k in range(1200):
        a, _ = ctrl.predict(obs, episode_start=np.array([k == 0]))
        obs, _, term, trunc, info = env.step(a)
        errs.append(info["tracking_error"])
        assert not term
        if trunc:
            break
    assert np.isfinite(errs).all() and np.mean(errs[200:]) < 1.0


def test_the_model_aware_filter_tracks_a_leader_it_knows_and_rejects_outliers():
    """The particle filter (controllers/_leader_pf.py) on a leader whose law it is given exactly
    (a straight cruise: turn rate 0, modes that never end, no wobble), fixes every 2 s about 3 s
    old with 5 % of them 1 m-scale outliers: its estimate of the present reference point stays
    within 0.1 m of the truth on average (the straight-line prediction is exact, the fixes are
    0.05 m noisy, an outlier is kept off by the mixture likelihood)."""
    import gymnasium as gym

    import auv_follow_env  # noqa: F401
    from controllers import _leader_pf

    kw = dict(leader_modes=1, leader_turn_rate=0.0, leader_cruise_mean_s=1e4, leader_turn_mean_s=1e4,
              leader_wobble_speed=0.0, leader_wobble_rate=0.0, update_period_s=2.0, latency_s=3.0,
              fix_sigma_m=0.05, outlier_share=0.05)
    env = gym.make("AUVFollow-v1", **kw)
    spec = env.unwrapped.task_spec
    cfg, prior = _leader_pf.pf_config(spec, fields={**kw, "leader_cruise_speed": 0.5, "leader_speed_lag_s": 2.0,
                                                     "leader_rate_lag_s": 1.0, "leader_wobble_corr_s": 5.0,
                                                     "leader_leg_m": 10.0, "leader_uturn_rate": 0.25})
    errs = []
    for seed in (1, 2):
        obs, info = env.reset(seed=seed)
        O, ref = [], []
        for _ in range(800):
            fol, tr = info["follower_pose"], info["true_reference"]
            c, s = math.cos(fol[2]), math.sin(fol[2])
            O.append(obs.astype(np.float64))
            ref.append((c * (tr[0] - fol[0]) + s * (tr[1] - fol[1]), -s * (tr[0] - fol[0]) + c * (tr[1] - fol[1])))
            obs, _, term, trunc, info = env.step(np.zeros(3))
            if term or trunc:
                break
        est, _ = _leader_pf.pf_episode(np.asarray(O), cfg, prior, 300)
        ref = np.asarray(ref)
        e = np.hypot(est[200:, 0] - ref[200:, 0], est[200:, 1] - ref[200:, 1])
        errs.append(np.nanmean(e))
    assert max(errs) < 0.1, errs


def test_the_model_aware_controller_runs_on_leader_tiers_only_and_batches_do_not_mix():
    """PROPOSED_PF_DOB refuses a task that is not a Leader tier's (it needs the tier's generator);
    on one, an env's estimate is the same alone as in a batch (each env's particles draw from their
    own generator, seeded by its episode's first observation)."""
    import gymnasium as gym

    import auv_follow_env  # noqa: F401
    from controllers import make_controller

    with pytest.raises(ValueError, match="needs a Leader tier"):
        make_controller("PROPOSED_PF_DOB", gym.make("AUVFollow-Hard-v1").unwrapped.task_spec)
    venv = gym.make_vec("AUVFollow-Leader-Hard-v1", num_envs=3, vectorization_mode="vector_entry_point")
    spec = venv.unwrapped.task_spec
    both = make_controller("PROPOSED_PF_DOB", spec)
    alone = make_controller("PROPOSED_PF_DOB", spec)
    obs, _ = venv.reset(seed=5)
    start = np.ones(3, dtype=bool)
    for _ in range(120):
        a, _ = both.predict(obs, episode_start=start)
        b, _ = alone.predict(obs[1:2], episode_start=start[1:2])
        np.testing.assert_array_equal(a[1], b[0])
        start[:] = False
        obs, *_ = venv.step(a)


def test_threaded_step_equals_the_serial_step_bit_for_bit(monkeypatch, count_calls):
    """From THREADED_MIN_ENVS envs on, imm_step splits the batch over numba's threads; every env
    runs the same operations as in the serial loop, so estimates and filter states are the same
    bits (one process), along real Leader-Hard episodes with fixes, gating and restarts."""
    import gymnasium as gym

    import auv_follow_env  # noqa: F401
    from controllers.estimator import TargetEstimator

    n = _imm.THREADED_MIN_ENVS + 5
    venv = gym.make_vec("AUVFollow-Leader-Hard-v1", num_envs=n, vectorization_mode="vector_entry_point",
                        episode_s=10.0, steady_start_s=5.0)
    spec = venv.unwrapped.task_spec
    from controllers import make_controller

    driver = make_controller("PROPOSED_IMM_DOB", spec)
    threaded, serial = TargetEstimator(spec, driver.estimator.config), TargetEstimator(spec, driver.estimator.config)
    obs, _ = venv.reset(seed=list(range(700, 700 + n)))
    start = np.ones(n, dtype=bool)
    calls = count_calls(_imm, "_imm_threads")
    mine = 0  # the threaded estimator's calls (the driver's own filter calls the kernel too)
    for k in range(80):
        o = np.asarray(obs, dtype=np.float64)
        before = calls["calls"]
        a = threaded.step(o, start, with_cov=k % 2 == 0)
        mine += calls["calls"] - before
        monkeypatch.setattr(_imm, "THREADED_MIN_ENVS", 10**9)  # the serial loop
        b = serial.step(o, start, with_cov=k % 2 == 0)
        monkeypatch.setattr(_imm, "THREADED_MIN_ENVS", n - 5)
        for f in ("rel_x", "rel_y", "rel_psi", "u", "r", "age", "valid"):
            assert np.array_equal(getattr(a, f), getattr(b, f)), (f, k)
        if k % 2 == 0:
            assert np.array_equal(a.cov, b.cov)
        act, _ = driver.predict(o, episode_start=start)
        obs, _, term, trunc, _ = venv.step(act)
        start = term | trunc
    for f in ("m", "P", "mu", "ng", "t_fix", "odom"):
        assert np.array_equal(getattr(threaded._s, f), getattr(serial._s, f)), f
    import numba

    assert mine == (80 if numba.get_num_threads() > 1 else 0)


def test_present_estimate_without_covariance_equals_the_covariance_path_bit_for_bit():
    """The kernel computes the present mean in scalars when no covariance is wanted (the array
    functions _mix, _prop and imm_present otherwise): the same operations, so the estimates are the
    same bits, along real Leader-Hard episodes (fixes, gating, restarts), serial and threaded."""
    import gymnasium as gym

    import auv_follow_env  # noqa: F401
    from controllers import make_controller
    from controllers.estimator import TargetEstimator

    for n in (7, _imm.THREADED_MIN_ENVS + 3):
        venv = gym.make_vec("AUVFollow-Leader-Hard-v1", num_envs=n, vectorization_mode="vector_entry_point",
                            episode_s=12.0, steady_start_s=5.0)
        spec = venv.unwrapped.task_spec
        driver = make_controller("PROPOSED_IMM_DOB", spec)
        cfg = driver.estimator.config
        with_cov, without = TargetEstimator(spec, cfg), TargetEstimator(spec, cfg)
        obs, _ = venv.reset(seed=list(range(900, 900 + n)))
        start = np.ones(n, dtype=bool)
        fixes = 0
        for k in range(240):
            o = np.asarray(obs, dtype=np.float64)
            before = None if with_cov._s is None else with_cov._s.t_fix.copy()
            a = with_cov.step(o, start, with_cov=True)
            b = without.step(o, start, with_cov=False)
            if before is not None:
                fixes += int(np.sum(with_cov._s.t_fix != before))
            assert b.cov is None and a.cov.shape == (n, 5, 5)
            for f in ("rel_x", "rel_y", "rel_psi", "u", "v", "r", "age", "valid"):
                assert np.array_equal(getattr(a, f), getattr(b, f)), (f, k, n)
            act, _ = driver.predict(o, episode_start=start)
            obs, _, term, trunc, _ = venv.step(act)
            start = term | trunc
        assert fixes > 2 * n  # fixes after each env's first (the update path ran)
        for f in ("m", "P", "mu", "ng", "gap", "t_fix"):
            assert np.array_equal(getattr(with_cov._s, f), getattr(without._s, f)), f
        venv.close()


def test_particle_filter_threaded_step_equals_the_serial_step_bit_for_bit(monkeypatch, count_calls):
    """The model-aware particle filter splits a batch of envs over numba's threads; each env draws
    from its own generator, so the estimates and the particles are the same bits as the serial
    loop's, along real Leader-Hard episodes (fixes, resampling)."""
    import gymnasium as gym

    import auv_follow_env  # noqa: F401
    from controllers import _leader_pf, make_controller

    n = 3
    venv = gym.make_vec("AUVFollow-Leader-Hard-v1", num_envs=n, vectorization_mode="vector_entry_point",
                        episode_s=12.0, steady_start_s=5.0)
    spec = venv.unwrapped.task_spec
    driver = make_controller("PROPOSED_IMM_DOB", spec)
    pf = make_controller("PROPOSED_PF_DOB", spec).estimator  # its configuration (the tier's generator)
    cfg, prior = pf._cfg, pf._prior
    threaded, serial = _leader_pf.new_state(n, 64), _leader_pf.new_state(n, 64)
    out_t, out_s = np.zeros((n, _leader_pf.NF)), np.zeros((n, _leader_pf.NF))
    obs, _ = venv.reset(seed=[31, 32, 33])
    start = np.ones(n, dtype=bool)
    keys = ("t_now", "odom", "vel", "init", "t_fix", "P", "Pn", "logw", "rs")
    calls = count_calls(_leader_pf, "_pf_threads")
    for _ in range(240):
        o = np.ascontiguousarray(obs, dtype=np.float64)
        _leader_pf.pf_step(o, start, cfg, prior, *(threaded[k] for k in keys), out_t)
        monkeypatch.setattr(_leader_pf, "THREADED_MIN_ENVS", 10**9)  # the serial loop
        _leader_pf.pf_step(o, start, cfg, prior, *(serial[k] for k in keys), out_s)
        monkeypatch.setattr(_leader_pf, "THREADED_MIN_ENVS", 2)
        assert np.array_equal(out_t, out_s, equal_nan=True)
        act, _ = driver.predict(o, episode_start=start)
        obs, _, term, trunc, _ = venv.step(act)
        start = term | trunc
    for k in keys:
        assert np.array_equal(threaded[k], serial[k]), k
    assert out_t[:, _leader_pf.F_VALID].all()  # every env had fixes
    import numba

    assert calls["calls"] == (240 if numba.get_num_threads() > 1 else 0)
