"""Physics of the numba kernels against hand-worked (closed-form) values.

Every expected value below is derived by hand from eqs. (3)-(10) of the paper (signs as
restored in docs/paper_notes.md), never printed by the code under test:

* linear surge/sway/yaw damping from rest under a constant force: first-order lag
  u(t) = F / X (1 - exp(-X t / m)), position = its integral;
* a constant inertial current with no force: the body velocity relaxes to the current
  seen in the body frame, so the inertial velocity tends to the current vector;
* coupled steady turn: 0 = F_u - X u + m v r, 0 = -Y v - m u r, 0 = F_r - N r;
* target: u_t constant, r_t = a sin(w t + ph) -> psi_t = psi0 + a / w (cos ph - cos(w t + ph)).
"""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest

import auv_follow_env  # noqa: F401  (registers the ids)
from auv_follow_env import dynamics as dyn
from auv_follow_env.layout import OBS_INDEX
from auv_follow_env.params import VehicleParams, make_config
from auv_follow_env.sim import config_vector, param_row

VEH = VehicleParams(m=25.0, I_z=2.0, X_u=15.0, Y_v=20.0, N_r=3.0)


def _cfg(dt: float = 0.05, substeps: int = 2) -> np.ndarray:
    return config_vector(make_config("S1", dt=dt, physics_substeps=substeps, delay_s=0.0))


def _run(state0, p_row, forces, n_steps, dt=0.05, substeps=2):
    """Integrate a batch from t = 0; returns the state history (n_steps + 1, N, 9) and times."""
    state = np.array(state0, dtype=np.float64, ndmin=2).copy()
    p = np.array(p_row, dtype=np.float64, ndmin=2)
    if p.shape[0] != state.shape[0]:
        p = np.repeat(p, state.shape[0], axis=0)
    f = np.array(forces, dtype=np.float64, ndmin=2)
    if f.shape[0] != state.shape[0]:
        f = np.repeat(f, state.shape[0], axis=0)
    cfg = _cfg(dt, substeps)
    hist = [state.copy()]
    for k in range(n_steps):
        t0 = np.full(state.shape[0], k * dt)
        dyn.integrate(state, p, cfg, t0, f)
        hist.append(state.copy())
    return np.array(hist), dt * np.arange(n_steps + 1)


def _inertial_velocity(s):
    psi, u, v = s[..., 2], s[..., 3], s[..., 4]
    return u * np.cos(psi) - v * np.sin(psi), u * np.sin(psi) + v * np.cos(psi)


# --- follower ---------------------------------------------------------------------------

@pytest.mark.parametrize("psi0", [0.0, 0.9, -2.5])
def test_zero_force_constant_current_drifts_with_the_current(psi0):
    cx, cy = 0.07, -0.04
    p = param_row(vehicle=VEH, current_x=(cx, 0.0, 0.0, 0.0), current_y=(cy, 0.0, 0.0, 0.0))
    s0 = np.zeros(9)
    s0[2] = psi0
    hist, t = _run(s0, p, [0.0, 0.0, 0.0], 1200)  # 60 s = 36 surge time constants
    xd, yd = _inertial_velocity(hist[-1, 0])
    assert xd == pytest.approx(cx, abs=1e-10)
    assert yd == pytest.approx(cy, abs=1e-10)
    # no moment, no disturbance: the heading never changes
    np.testing.assert_array_equal(hist[:, 0, 2], psi0)
    np.testing.assert_array_equal(hist[:, 0, 5], 0.0)
    # transient: body velocity is a first-order lag towards the body-frame current
    uc = math.cos(psi0) * cx + math.sin(psi0) * cy
    vc = -math.sin(psi0) * cx + math.cos(psi0) * cy
    np.testing.assert_allclose(hist[:, 0, 3], uc * (1 - np.exp(-VEH.X_u * t / VEH.m)), rtol=0, atol=1e-10)
    np.testing.assert_allclose(hist[:, 0, 4], vc * (1 - np.exp(-VEH.Y_v * t / VEH.m)), rtol=0, atol=1e-10)


@pytest.mark.parametrize("psi0", [0.0, 0.3])
def test_constant_surge_force_first_order_lag(psi0):
    F = 12.0
    p = param_row(vehicle=VEH)
    s0 = np.zeros(9)
    s0[2] = psi0
    hist, t = _run(s0, p, [F, 0.0, 0.0], 1200)
    a = VEH.X_u / VEH.m
    u_exact = F / VEH.X_u * (1 - np.exp(-a * t))
    np.testing.assert_allclose(hist[:, 0, 3], u_exact, rtol=0, atol=1e-9)
    assert hist[-1, 0, 3] == pytest.approx(F / VEH.X_u, abs=1e-12)
    # no sway, no yaw: v = r = 0 and the heading is held
    np.testing.assert_array_equal(hist[:, 0, 4], 0.0)
    np.testing.assert_array_equal(hist[:, 0, 5], 0.0)
    # path length s(t) = F/X (t - (1 - exp(-a t)) / a), along the heading
    s = F / VEH.X_u * (t - (1 - np.exp(-a * t)) / a)
    np.testing.assert_allclose(hist[:, 0, 0], math.cos(psi0) * s, rtol=0, atol=1e-8)
    np.testing.assert_allclose(hist[:, 0, 1], math.sin(psi0) * s, rtol=0, atol=1e-8)


# Yaw is the fastest mode (N_r / I_z = 1.5 /s): with h = 0.025 s, RK4's global error is
# about (h b)^4 / 120 * |F / N_r| ~ 1e-8; with 8 substeps it is 256 times smaller.
@pytest.mark.parametrize("substeps,tol", [(2, 2e-8), (8, 1e-10)])
@pytest.mark.parametrize("F", [2.0, -5.0])
def test_constant_moment_from_rest_turns_on_the_spot(F, substeps, tol):
    p = param_row(vehicle=VEH)
    hist, t = _run(np.zeros(9), p, [0.0, 0.0, F], 600, substeps=substeps)
    b = VEH.N_r / VEH.I_z
    r_exact = F / VEH.N_r * (1 - np.exp(-b * t))
    psi_exact = F / VEH.N_r * (t - (1 - np.exp(-b * t)) / b)
    np.testing.assert_allclose(hist[:, 0, 5], r_exact, rtol=0, atol=tol)
    np.testing.assert_allclose(hist[:, 0, 2], psi_exact, rtol=0, atol=10 * tol)
    assert hist[-1, 0, 5] == pytest.approx(F / VEH.N_r, abs=1e-12)
    # u = v = 0 stays u = v = 0 (the Coriolis terms are products with u, v)
    np.testing.assert_array_equal(hist[:, 0, 3:5], 0.0)
    np.testing.assert_array_equal(hist[:, 0, 0:2], 0.0)


def test_sway_force_first_order_lag():
    F = -8.0
    hist, t = _run(np.zeros(9), param_row(vehicle=VEH), [0.0, F, 0.0], 400)
    np.testing.assert_allclose(hist[:, 0, 4], F / VEH.Y_v * (1 - np.exp(-VEH.Y_v * t / VEH.m)),
                               rtol=0, atol=1e-9)
    np.testing.assert_array_equal(hist[:, 0, 3], 0.0)


def test_coupled_steady_turn():
    # 0 = F_r - N r  ->  r = F_r / N ;  0 = -Y v - m u r  ->  v = -m u r / Y ;
    # 0 = F_u - X u + m v r  ->  u = F_u / (X + m^2 r^2 / Y)
    Fu, Fr = 10.0, 0.6
    r = Fr / VEH.N_r
    u = Fu / (VEH.X_u + VEH.m ** 2 * r ** 2 / VEH.Y_v)
    v = -VEH.m * u * r / VEH.Y_v
    hist, _ = _run(np.zeros(9), param_row(vehicle=VEH), [Fu, 0.0, Fr], 1200)
    assert hist[-1, 0, 3] == pytest.approx(u, abs=1e-9)
    assert hist[-1, 0, 4] == pytest.approx(v, abs=1e-9)
    assert hist[-1, 0, 5] == pytest.approx(r, abs=1e-12)


def test_batch_rows_are_independent():
    p = np.stack([param_row(vehicle=VEH), param_row(vehicle=VEH.with_mismatch(1.0))])
    forces = np.array([[12.0, 0.0, 0.0], [0.0, 0.0, 2.0]])
    hist, t = _run(np.zeros((2, 9)), p, forces, 200, substeps=8)
    np.testing.assert_allclose(hist[:, 0, 3], 12.0 / 15.0 * (1 - np.exp(-15.0 * t / 25.0)), rtol=0, atol=1e-9)
    np.testing.assert_allclose(hist[:, 1, 5], 2.0 / 6.0 * (1 - np.exp(-6.0 * t / 2.0)), rtol=0, atol=1e-9)
    np.testing.assert_array_equal(hist[:, 0, 5], 0.0)
    np.testing.assert_array_equal(hist[:, 1, 3], 0.0)


def test_substeps_converge():
    # halving the RK4 step changes a disturbed, current-driven run by far less than 1e-6
    p = param_row(vehicle=VEH, target_speed=0.5, surge_amp=0.1, surge_period=15.0, yaw_rate_amp=0.07,
                  yaw_period=24.0, current_x=(0.06, 0.04, 0.1, 0.3), current_y=(-0.03, 0.03, 0.12, 1.0),
                  disturbance=((2.0, 0.1, 1.0, 0.2), (1.5, 0.3, 1.0, 0.4), (0.05, 0.5, 0.03, 0.6)))
    a, _ = _run(np.zeros(9), p, [20.0, -10.0, 1.0], 400, substeps=2)
    b, _ = _run(np.zeros(9), p, [20.0, -10.0, 1.0], 400, substeps=8)
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-6)


def _rot(a, x, y):
    return math.cos(a) * x - math.sin(a) * y, math.sin(a) * x + math.cos(a) * y


@pytest.mark.parametrize("alpha", [0.7, -2.2, math.pi])
def test_rotation_equivariance(alpha):
    # A current whose two components share frequency and phase is a vector
    # m + A sin(w t + ph); rotating the scene rotates m and A.
    mx, my, ax, ay, w, ph = 0.05, -0.03, 0.03, 0.02, 0.11, 0.4
    dist = ((2.0, 0.1, 1.0, 0.2), (1.5, 0.3, 1.0, 0.4), (0.05, 0.5, 0.03, 0.6))  # body frame
    common = dict(vehicle=VEH, target_speed=0.5, surge_amp=0.1, surge_period=15.0, surge_phase=0.3,
                  yaw_rate_amp=0.07, yaw_period=24.0, yaw_phase=1.1, disturbance=dist)
    p0 = param_row(current_x=(mx, ax, w, ph), current_y=(my, ay, w, ph), **common)
    rmx, rmy = _rot(alpha, mx, my)
    rax, ray = _rot(alpha, ax, ay)
    p1 = param_row(current_x=(rmx, rax, w, ph), current_y=(rmy, ray, w, ph), **common)
    s0 = np.array([1.0, -2.0, 0.4, 0.2, -0.1, 0.05, 3.0, 1.5, -0.6])
    s1 = s0.copy()
    s1[0], s1[1] = _rot(alpha, s0[0], s0[1])
    s1[6], s1[7] = _rot(alpha, s0[6], s0[7])
    s1[2] += alpha
    s1[8] += alpha
    forces = [18.0, -7.0, 1.5]  # body-frame forces are unchanged by a rotation of the scene
    h0, _ = _run(s0, p0, forces, 400)
    h1, _ = _run(s1, p1, forces, 400)
    e0, e1 = h0[:, 0], h1[:, 0]
    for cx, cy in ((0, 1), (6, 7)):
        xr, yr = _rot(alpha, e0[:, cx], e0[:, cy])
        np.testing.assert_allclose(e1[:, cx], xr, rtol=0, atol=1e-9)
        np.testing.assert_allclose(e1[:, cy], yr, rtol=0, atol=1e-9)
    np.testing.assert_allclose(e1[:, 2], e0[:, 2] + alpha, rtol=0, atol=1e-9)
    np.testing.assert_allclose(e1[:, 8], e0[:, 8] + alpha, rtol=0, atol=1e-9)
    np.testing.assert_allclose(e1[:, 3:6], e0[:, 3:6], rtol=0, atol=1e-10)


# --- target -----------------------------------------------------------------------------

@pytest.mark.parametrize("psi_t0", [0.0, 0.7, -2.0])
def test_target_straight_line(psi_t0):
    vbar = 0.52
    p = param_row(vehicle=VEH, target_speed=vbar, surge_amp=0.0, yaw_rate_amp=0.0, surge_phase=1.0)
    s0 = np.zeros(9)
    s0[6], s0[7], s0[8] = 2.0, -1.0, psi_t0
    hist, t = _run(s0, p, [0.0, 0.0, 0.0], 1200)
    np.testing.assert_allclose(hist[:, 0, 6], 2.0 + vbar * t * math.cos(psi_t0), rtol=0, atol=1e-10)
    np.testing.assert_allclose(hist[:, 0, 7], -1.0 + vbar * t * math.sin(psi_t0), rtol=0, atol=1e-10)
    np.testing.assert_array_equal(hist[:, 0, 8], psi_t0)
    # speed from successive positions
    step = np.hypot(np.diff(hist[:, 0, 6]), np.diff(hist[:, 0, 7]))
    np.testing.assert_allclose(step, vbar * 0.05, rtol=1e-9)


def test_target_heading_closed_form():
    a, P, ph = 0.07, 24.0, 0.8
    w = 2 * math.pi / P
    p = param_row(vehicle=VEH, target_speed=0.5, surge_amp=0.1, surge_period=15.0, yaw_rate_amp=a,
                  yaw_period=P, yaw_phase=ph)
    s0 = np.zeros(9)
    s0[8] = 0.3
    hist, t = _run(s0, p, [0.0, 0.0, 0.0], 1200)
    np.testing.assert_allclose(hist[:, 0, 8], 0.3 + a / w * (math.cos(ph) - np.cos(w * t + ph)),
                               rtol=0, atol=1e-10)


def test_target_surge_modulation_distance():
    # straight line (a_r = 0), u_t = v (1 + a sin(w t + ph)): distance = v t + v a/w (cos ph - cos(w t + ph))
    v, a, P, ph = 0.49, 0.075, 20.0, 2.0
    w = 2 * math.pi / P
    p = param_row(vehicle=VEH, target_speed=v, surge_amp=a, surge_period=P, surge_phase=ph)
    hist, t = _run(np.zeros(9), p, [0.0, 0.0, 0.0], 800)
    np.testing.assert_allclose(hist[:, 0, 6], v * t + v * a / w * (math.cos(ph) - np.cos(w * t + ph)),
                               rtol=0, atol=1e-10)
    np.testing.assert_array_equal(hist[:, 0, 7], 0.0)


# --- the delay line, through the env ----------------------------------------------------

def _body(psi, dx, dy):
    c, s = np.cos(psi), np.sin(psi)
    return c * dx + s * dy, -s * dx + c * dy


def _expected_obs_from_truth(tgt, pose, p_d):
    """Observation fields 5-13 from a target state (x, y, psi, u, v, r) and a follower pose."""
    xt, yt, pst = tgt[0], tgt[1], tgt[2]
    x, y, psi = pose
    dx, dy = _body(psi, xt - x, yt - y)
    rx = xt + math.cos(pst) * p_d[0] - math.sin(pst) * p_d[1] - x
    ry = yt + math.sin(pst) * p_d[0] + math.cos(pst) * p_d[1] - y
    rdx, rdy = _body(psi, rx, ry)
    return np.array([dx, dy, math.cos(pst - psi), math.sin(pst - psi), tgt[3], tgt[4], tgt[5], rdx, rdy])


@pytest.mark.parametrize("env_id,seed", [("AUVFollow-S4-v0", 3), ("AUVFollow-S1-v0", 11)])
def test_delay_line_obs_equals_truth_tau_earlier(env_id, seed):
    env = gym.make(env_id)
    spec = env.unwrapped.task_spec
    D = int(round(spec.delay_s / spec.dt))
    assert D == spec.delay_steps
    rng = np.random.default_rng(seed)
    obs, info = env.reset(seed=seed)
    obs_h, tgt_h, pose_h = [obs], [info["true_target"].copy()], [info["follower_pose"].copy()]
    for _ in range(3 * D + 20):
        obs, _, _, _, info = env.step(rng.uniform(-1, 1, 3).astype(np.float32))
        obs_h.append(obs)
        tgt_h.append(info["true_target"].copy())
        pose_h.append(info["follower_pose"].copy())
    sl = slice(OBS_INDEX["target_dx"], OBS_INDEX["ref_dy"] + 1)
    for k in range(D, len(obs_h)):
        exp = _expected_obs_from_truth(tgt_h[k - D], pose_h[k], spec.p_d)
        np.testing.assert_allclose(obs_h[k][sl], exp, rtol=1e-6, atol=2e-6, err_msg=f"step {k}")
        # and it does NOT match the present target (the target moves ~v dt per step)
        present = _expected_obs_from_truth(tgt_h[k], pose_h[k], spec.p_d)
        assert abs(obs_h[k][sl][0] - present[0]) + abs(obs_h[k][sl][1] - present[1]) > 0.1
    # before t = tau: the target was simulated from t = -tau, starting at the origin heading +x.
    p = env.unwrapped._sim.params[0]
    vbar, au, wu, phu = p[dyn.P_TV], p[dyn.P_TAU], p[dyn.P_TWU], p[dyn.P_TPU]
    ar, wr, phr = p[dyn.P_TAR], p[dyn.P_TWR], p[dyn.P_TPR]
    tp = env.unwrapped.config.scenario.target
    assert vbar == tp.speed and au == tp.surge_amp and ar == tp.yaw_rate_amp
    assert wu == pytest.approx(2 * math.pi / tp.surge_period)
    tau = spec.delay_s
    for k in range(0, D + 1):
        s = k * spec.dt - tau  # the time of the state the follower receives
        d = obs_h[k]
        assert d[OBS_INDEX["target_u"]] == pytest.approx(vbar * (1 + au * math.sin(wu * s + phu)), abs=1e-6)
        assert d[OBS_INDEX["target_r"]] == pytest.approx(ar * math.sin(wr * s + phr), abs=1e-7)
        assert d[OBS_INDEX["target_v"]] == 0.0
        # delayed heading: psi_t(s) = a_r / w_r (cos(w_r (-tau) + ph) - cos(w_r s + ph))
        psi_t = ar / wr * (math.cos(-wr * tau + phr) - math.cos(wr * s + phr))
        psi_f = pose_h[k][2]
        assert d[OBS_INDEX["target_cos_dpsi"]] == pytest.approx(math.cos(psi_t - psi_f), abs=1e-6)
        assert d[OBS_INDEX["target_sin_dpsi"]] == pytest.approx(math.sin(psi_t - psi_f), abs=1e-6)
    # at k = 0 the delayed target is exactly at the origin
    dx, dy = _body(pose_h[0][2], -pose_h[0][0], -pose_h[0][1])
    assert obs_h[0][OBS_INDEX["target_dx"]] == pytest.approx(dx, abs=1e-6)
    assert obs_h[0][OBS_INDEX["target_dy"]] == pytest.approx(dy, abs=1e-6)
    # the present target at t = 0 (reset info) is the target at t = -tau advanced by tau
    psi0 = ar / wr * (math.cos(-wr * tau + phr) - math.cos(phr))
    assert tgt_h[0][2] == pytest.approx(psi0, abs=1e-10)
    env.close()


def test_follower_starts_behind_the_delayed_reference():
    env = gym.make("AUVFollow-S4-v0")
    obs, info = env.reset(seed=5)
    cfg = env.unwrapped.config
    # the follower has the delayed target's heading and sits init_offset_m behind the delayed
    # reference along that heading: ref_d in body frame = (init_offset, 0)
    assert obs[OBS_INDEX["target_cos_dpsi"]] == pytest.approx(1.0, abs=1e-7)
    assert obs[OBS_INDEX["ref_dx"]] == pytest.approx(cfg.init_offset_m, abs=1e-6)
    assert obs[OBS_INDEX["ref_dy"]] == pytest.approx(0.0, abs=1e-6)
    np.testing.assert_array_equal(obs[0:3], 0.0)
    env.close()
