"""The structured target filter ``OU0``: no sway, OU speed and turn rate, in numba.

Expected values are worked out by hand: a constant-turn target is a circular arc; a straight
OU run has its speed's closed-form integral; the Jacobian is checked against central
differences of the independent numpy propagation.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from auv_follow_env.layout import OBS_DIM_V1, OBS_INDEX_V1
from auv_follow_env.params import TaskSpec
from controllers import _ou0
from controllers.estimator import EstimatorConfig, TargetEstimator, propagate_mean

DT = 0.05


def _spec(layout: str = "v1") -> TaskSpec:
    import gymnasium as gym

    import auv_follow_env  # noqa: F401

    spec = gym.make("AUVFollow-Hard-v1").unwrapped.task_spec
    assert spec.layout == layout and math.isclose(spec.dt, DT)
    return spec


def _arc(t: np.ndarray, u: float, r: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A target starting at the origin heading +x with constant u and r: a circular arc."""
    return u / r * np.sin(r * t), u / r * (1.0 - np.cos(r * t)), r * t


def _link_obs(n_steps: int, u: float, r: float, period_s: float, latency_s: float, sway: float = 0.0):
    """v1 observations of a follower at rest at the origin (heading 0: body = world) hearing the
    arc target: a fix measured every ``period_s``, arriving ``latency_s`` later."""
    obs = np.zeros((n_steps, OBS_DIM_V1))
    obs[:, OBS_INDEX_V1["cos_psi"]] = 1.0
    held = None
    for k in range(n_steps):
        t = k * DT
        # newest packet that has arrived by t (measurement times j * period_s)
        j = math.floor((t - latency_s) / period_s + 1e-9)
        new = 0.0
        if j >= 0:
            if held != j:
                new, held = 1.0, j
            tm = j * period_s
            x, y, psi = _arc(np.array(tm), u, r)
            o = obs[k]
            o[OBS_INDEX_V1["target_dx"]], o[OBS_INDEX_V1["target_dy"]] = x, y
            o[OBS_INDEX_V1["target_cos_dpsi"]], o[OBS_INDEX_V1["target_sin_dpsi"]] = math.cos(psi), math.sin(psi)
            o[OBS_INDEX_V1["target_u"]], o[OBS_INDEX_V1["target_v"]], o[OBS_INDEX_V1["target_r"]] = u, sway, r
            o[OBS_INDEX_V1["packet_age"]] = t - tm
            o[OBS_INDEX_V1["since_arrival"]] = 0.0 if new else obs[k - 1, OBS_INDEX_V1["since_arrival"]] + DT
            o[OBS_INDEX_V1["new_packet"]], o[OBS_INDEX_V1["has_packet"]] = new, 1.0
    return obs


def _exact_cfg(**kw) -> EstimatorConfig:
    base = dict(model="OU0", sigma_pos=1e-6, sigma_psi=1e-6, sigma_vel=1e-6, sigma_r=1e-6, q_acc=1e-12,
                q_yaw=1e-12, tau_u=math.inf, tau_r=math.inf, sigma_ubar0=1e-6)
    base.update(kw)
    return EstimatorConfig(**base)


def test_noiseless_constant_turn_target_is_predicted_exactly():
    """tau = inf is the constant-turn limit: from noiseless fixes 1 s apart, each 0.7 s old on
    arrival, the present pose equals the arc's at every step (hand-computed closed form)."""
    u, r = 0.5, 0.05
    obs = _link_obs(400, u, r, period_s=1.0, latency_s=0.7)
    est = TargetEstimator(_spec(), _exact_cfg())
    worst = 0.0
    for k in range(obs.shape[0]):
        e = est.step(obs[k:k + 1], np.array([k == 0]))
        if obs[k, OBS_INDEX_V1["has_packet"]] == 0:
            assert not e.valid[0]
            continue
        x, y, psi = _arc(np.array(k * DT), u, r)
        worst = max(worst, abs(e.rel_x[0] - x), abs(e.rel_y[0] - y), abs(e.rel_psi[0] - psi))
        assert e.valid[0] and abs(e.u[0] - u) < 1e-9 and abs(e.r[0] - r) < 1e-9 and e.v[0] == 0.0
    assert worst < 1e-7, worst


def test_reported_sway_is_ignored():
    """The target never slips sideways: a fix's reported sway (noise) changes nothing."""
    a = _link_obs(120, 0.45, 0.03, 0.8, 0.6, sway=0.0)
    b = _link_obs(120, 0.45, 0.03, 0.8, 0.6, sway=0.3)
    ea, eb = TargetEstimator(_spec()), TargetEstimator(_spec())
    for k in range(a.shape[0]):
        xa = ea.step(a[k:k + 1], np.array([k == 0]))
        xb = eb.step(b[k:k + 1], np.array([k == 0]))
        np.testing.assert_array_equal(xa.state, xb.state)
        np.testing.assert_array_equal(xa.cov, xb.cov)


def test_straight_ou_run_matches_closed_form():
    """r = 0: u(s) = ub + (u0 - ub) e^{-s/tu}, so x(T) = ub T + (u0 - ub) tu (1 - e^{-T/tu});
    both the numpy propagation and the numba kernel's."""
    tu, tr, T = 12.0, 8.0, 3.7
    x0 = np.array([0.2, -0.1, 0.0, 0.6, 0.0, 0.45])
    expect_x = 0.2 + 0.45 * T + (0.6 - 0.45) * tu * (1 - math.exp(-T / tu))
    expect_u = 0.45 + (0.6 - 0.45) * math.exp(-T / tu)
    xn = propagate_mean("OU0", x0[None], np.array([T]), (tu, tr))[0]
    out, F = np.empty(6), np.empty((6, 6))
    _ou0._propagate(x0, T, tu, tr, _ou0._GL16_X, _ou0._GL16_W, out, F)
    for got in (xn, out):
        assert got[0] == pytest.approx(expect_x, abs=1e-12)
        assert got[1] == pytest.approx(-0.1, abs=1e-15)
        assert got[3] == pytest.approx(expect_u, abs=1e-15)


def test_kernel_jacobian_matches_central_differences_of_numpy_propagation():
    tu, tr, T = 10.0, 6.0, 2.9
    x0 = np.array([1.0, 2.0, 0.7, 0.5, 0.08, 0.47])
    out, F = np.empty(6), np.empty((6, 6))
    _ou0._propagate(x0, T, tu, tr, _ou0._GL16_X, _ou0._GL16_W, out, F)
    h = 1e-6
    num = np.empty((6, 6))
    for j in range(6):
        e = np.zeros(6)
        e[j] = h
        fp = propagate_mean("OU0", (x0 + e)[None], np.array([T]), (tu, tr))[0]
        fm = propagate_mean("OU0", (x0 - e)[None], np.array([T]), (tu, tr))[0]
        num[:, j] = (fp - fm) / (2 * h)
    np.testing.assert_allclose(F, num, atol=1e-8)


def test_smoothing_keeps_the_pose_continuous_and_decays_at_its_time_constant():
    """With smooth_s = T_s the returned pose does not step at a fix, and the offset to the
    unsmoothed estimate shrinks by exactly e^{-dt/T_s} per step between fixes."""
    u, r, ts = 0.5, 0.05, 0.8
    obs = _link_obs(200, u, r, period_s=2.0, latency_s=0.5)
    obs[:, OBS_INDEX_V1["target_dx"]] += np.where(np.arange(200) % 80 < 40, 0.0, 0.3)  # jumps in the fixes
    cfg = EstimatorConfig.for_spec(_spec())
    import dataclasses

    raw = TargetEstimator(_spec(), cfg)
    smo = TargetEstimator(_spec(), dataclasses.replace(cfg, smooth_s=ts))
    prev_gap, prev_x = None, None
    for k in range(200):
        a = raw.step(obs[k:k + 1], np.array([k == 0]))
        b = smo.step(obs[k:k + 1], np.array([k == 0]))
        if not a.valid[0]:
            continue
        gap = b.x[0] - a.x[0]
        if prev_x is not None:
            assert abs(b.x[0] - prev_x) < 2 * u * DT + 1e-3  # no jump larger than the motion of a step
            if obs[k, OBS_INDEX_V1["new_packet"]] == 0 and abs(prev_gap) > 1e-6:
                assert gap / prev_gap == pytest.approx(math.exp(-DT / ts), rel=1e-6)
        prev_gap, prev_x = gap, b.x[0]


def test_adaptive_noise_is_the_shrunk_sample_variance():
    """n fixes with reported speeds s_i and turn rates r_i: var_u = (n0 V0 + (n-1) max(S2 -
    sigma_vel^2, 0)) / (n0 + n - 1), var_r = (n0 W0 + n max(mean r^2 - sigma_r^2, 0)) / (n0 + n),
    q = 2 var / tau (hand-computed)."""
    cfg = np.zeros(_ou0.NC)
    cfg[_ou0.C_ADAPT], cfg[_ou0.C_N0] = 1.0, 4.0
    cfg[_ou0.C_TU], cfg[_ou0.C_TR], cfg[_ou0.C_SVEL], cfg[_ou0.C_SR] = 10.0, 5.0, 0.02, 0.01
    speeds, rates = np.array([0.40, 0.55, 0.50, 0.62, 0.47]), np.array([0.02, -0.05, 0.04, 0.0, -0.03])
    stats = np.zeros((1, _ou0.NS))
    stats[0, _ou0.S_N] = 5
    stats[0, _ou0.S_MU] = speeds.mean()
    stats[0, _ou0.S_M2] = ((speeds - speeds.mean()) ** 2).sum()
    stats[0, _ou0.S_R2] = (rates ** 2).sum()
    qu0, qr0 = 2 * 0.05 ** 2 / 10.0, 2 * 0.04 ** 2 / 5.0
    qu, qr = _ou0._noise(cfg, stats, 0, qu0, qr0)
    vu = (4 * 0.05 ** 2 + 4 * (speeds.var(ddof=1) - 0.02 ** 2)) / (4 + 4)
    vr = (4 * 0.04 ** 2 + 5 * ((rates ** 2).mean() - 0.01 ** 2)) / (4 + 5)
    assert qu == pytest.approx(2 * vu / 10.0, rel=1e-12)
    assert qr == pytest.approx(2 * vr / 5.0, rel=1e-12)


def test_ou0_refuses_bad_settings():
    with pytest.raises(ValueError, match="smooth_s"):
        EstimatorConfig(model="OU", smooth_s=1.0)
    with pytest.raises(ValueError, match="adapt"):
        EstimatorConfig(model="OU0", adapt="yes")
    with pytest.raises(ValueError, match="tau_u"):
        EstimatorConfig(model="OU", tau_u=math.inf)


def test_observer_with_thruster_model_sees_the_lagged_force():
    """A constant command c from rest through a first-order lag (alpha = 1 - e^{-dt/T}) and a rate
    limit: f_k = f_{k-1} + alpha (c - f_{k-1}) clipped to +- rate * limit * dt per step, acting
    over step k. A vehicle held at rest by a disturbance d = -f_k: at the next step the observer
    measures d_meas = -f_k (with the thruster model; without it, -c) and low-pass filters it with
    gain dt / (T_d + dt)."""
    from auv_follow_env.params import VehicleParams
    from controllers import DisturbanceObserver

    nom = VehicleParams()
    lim = (100.0, 100.0, 20.0)
    alpha, step, g = 1 - math.exp(-DT / 0.3), 1.5 * DT * np.array(lim), DT / (0.5 + DT)
    c = np.array([[60.0, -30.0, 5.0]])
    nu, cur = np.zeros((1, 3)), np.zeros((1, 2))
    for model in (True, False):
        kw = {"thruster_tc_s": 0.3, "thruster_rate": 1.5} if model else {}
        dob = DisturbanceObserver(nom, DT, lim, 0.5, **kw)
        dob.update(nu, cur, np.array([True]))
        f, d_hat = np.zeros(3), np.zeros(3)
        for k in range(40):
            dob.applied(c)
            f = np.clip(f + alpha * (c[0] - f), f - step, f + step)  # what acts over this step
            meas = -f if model else -c[0]
            if k == 0:  # by hand: the rate limit (1.5 * 0.05 * 100 = 7.5 N) binds before the lag (9.21 N)
                assert f[0] == pytest.approx(7.5) and alpha * 60.0 > 9.2
            got = dob.update(nu, cur, np.array([False]))[0]
            d_hat = np.clip(d_hat + g * (meas - d_hat), -np.array(lim), np.array(lim))
            np.testing.assert_allclose(got, d_hat, rtol=1e-12, atol=1e-12)


def test_threaded_ou0_step_equals_the_serial_step_bit_for_bit(monkeypatch, count_calls):
    """From THREADED_MIN_ENVS envs on, ou0_step splits the batch over numba's threads; every env
    runs the same operations as in the serial loop: the same estimates, covariances and filter
    states, bit for bit (one process), along real Hard-v1 episodes with restarts."""
    import gymnasium as gym

    import auv_follow_env  # noqa: F401
    from controllers import _ou0, make_controller
    from controllers.estimator import TargetEstimator

    n = _ou0.THREADED_MIN_ENVS + 7
    venv = gym.make_vec("AUVFollow-Hard-v1", num_envs=n, vectorization_mode="vector_entry_point",
                        episode_s=8.0, steady_start_s=4.0)
    spec = venv.unwrapped.task_spec
    driver = make_controller("PROPOSED_KF_DOB", spec)
    threaded, serial = TargetEstimator(spec), TargetEstimator(spec)
    assert threaded.model == "OU0"
    obs, _ = venv.reset(seed=list(range(300, 300 + n)))
    start = np.ones(n, dtype=bool)
    calls = count_calls(_ou0, "_ou0_threads")
    mine = 0  # the threaded estimator's calls (the driver's own filter calls the kernel too)
    restarts = 0
    for k in range(200):
        o = np.asarray(obs, dtype=np.float64)
        before = calls["calls"]
        a = threaded.step(o, start, with_cov=k % 3 != 0)
        mine += calls["calls"] - before
        monkeypatch.setattr(_ou0, "THREADED_MIN_ENVS", 10**9)  # the serial loop
        b = serial.step(o, start, with_cov=k % 3 != 0)
        monkeypatch.setattr(_ou0, "THREADED_MIN_ENVS", n - 7)
        for f in ("valid", "rel_x", "rel_y", "rel_psi", "u", "r", "age", "state"):
            assert np.array_equal(getattr(a, f), getattr(b, f)), (f, k)
        if k % 3 != 0:
            assert np.array_equal(a.cov, b.cov)
        act, _ = driver.predict(o, episode_start=start)
        obs, _, term, trunc, _ = venv.step(act)
        start = term | trunc
        restarts += int(start.sum())
    assert restarts >= n  # (8 s episodes: 160 steps, so every env restarted within the 200)
    for f in ("x", "P", "xp", "t_fix", "odom", "stats"):
        assert np.array_equal(getattr(threaded._s, f), getattr(serial._s, f)), f
    import numba

    assert mine == (200 if numba.get_num_threads() > 1 else 0)
