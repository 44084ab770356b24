"""Scripted controllers: predictor (13)-(17), reference (21), the hierarchical law (25)-(35),
Table 1's ablations, the PID baseline and the SB3 ``predict`` protocol.

Expected values are worked out by hand or in closed form (target kinematics integrated
exactly), never taken from the code under test.
"""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest

import auv_follow_env  # noqa: F401  (registers the ids)
from auv_follow_env.layout import OBS_DIM, OBS_INDEX, decode
from auv_follow_env.params import make_task_spec
from controllers import CONTROLLERS, HierarchicalController, PIDController, make_controller
from controllers.base import FilteredDerivative, sat
from controllers.hierarchical import Gains, outer_loop, predict_target, reference_point

# --------------------------------------------------------------------------------------------
# helpers


def make_obs(**fields: float) -> np.ndarray:
    """One observation built by field name; ``target_dpsi`` sets the cos/sin pair."""
    o = np.zeros(OBS_DIM)
    dpsi = fields.pop("target_dpsi", 0.0)
    o[OBS_INDEX["target_cos_dpsi"]] = math.cos(dpsi)
    o[OBS_INDEX["target_sin_dpsi"]] = math.sin(dpsi)
    o[OBS_INDEX["cos_psi"]] = 1.0
    psi = fields.pop("psi", None)
    if psi is not None:
        o[OBS_INDEX["cos_psi"]] = math.cos(psi)
        o[OBS_INDEX["sin_psi"]] = math.sin(psi)
    for k, v in fields.items():
        o[OBS_INDEX[k]] = v
    return o


def obs_from_inertial(follower: tuple[float, float, float], target: tuple[float, float, float],
                      target_vel: tuple[float, float, float]) -> np.ndarray:
    """Observation of a (delayed) target pose/velocity seen from a follower pose (inertial)."""
    xf, yf, pf = follower
    xt, yt, pt = target
    dx, dy = xt - xf, yt - yf
    c, s = math.cos(pf), math.sin(pf)
    return make_obs(psi=pf, target_dx=c * dx + s * dy, target_dy=-s * dx + c * dy,
                    target_dpsi=pt - pf, target_u=target_vel[0], target_v=target_vel[1],
                    target_r=target_vel[2])


def to_inertial(follower: tuple[float, float, float], bx: float, by: float) -> tuple[float, float]:
    xf, yf, pf = follower
    c, s = math.cos(pf), math.sin(pf)
    return xf + c * bx - s * by, yf + s * bx + c * by


def random_obs(rng: np.random.Generator, n: int | None = None) -> np.ndarray:
    """Plausible observations: unit cos/sin pairs, O(0.1-1) positions and velocities."""
    shape = (OBS_DIM,) if n is None else (n, OBS_DIM)
    o = rng.uniform(-0.5, 0.5, shape)
    psi = rng.uniform(-math.pi, math.pi, shape[:-1])
    dpsi = rng.uniform(-1.0, 1.0, shape[:-1])
    o[..., OBS_INDEX["cos_psi"]], o[..., OBS_INDEX["sin_psi"]] = np.cos(psi), np.sin(psi)
    o[..., OBS_INDEX["target_cos_dpsi"]], o[..., OBS_INDEX["target_sin_dpsi"]] = np.cos(dpsi), np.sin(dpsi)
    o[..., OBS_INDEX["target_dx"]] += 1.0
    o[..., OBS_INDEX["target_u"]] = rng.uniform(0.3, 0.6, shape[:-1])
    o[..., OBS_INDEX["target_r"]] = rng.uniform(-0.1, 0.1, shape[:-1])
    return o


S4 = make_task_spec("S4")
PD = S4.p_d
TAU = S4.delay_s


# --------------------------------------------------------------------------------------------
# predictor, eqs. (13)-(17)


@pytest.mark.parametrize("tau", [0.0, 0.5, 1.0, 2.0, 3.7])
def test_predictor_exact_for_straight_line(tau):
    # target moving straight at constant body velocity (u, v), r = 0: present pose in closed form
    follower = (1.3, -0.4, 0.9)
    p0, psi_t = (3.0, 2.0), -0.6
    u, v = 0.5, 0.1
    obs = obs_from_inertial(follower, (*p0, psi_t), (u, v, 0.0))
    x, y, psi, uh, vh, rh = predict_target(decode(obs), tau)
    true_x = p0[0] + (math.cos(psi_t) * u - math.sin(psi_t) * v) * tau
    true_y = p0[1] + (math.sin(psi_t) * u + math.cos(psi_t) * v) * tau
    gx, gy = to_inertial(follower, float(x), float(y))
    assert gx == pytest.approx(true_x, abs=1e-12)
    assert gy == pytest.approx(true_y, abs=1e-12)
    assert float(psi) + follower[2] == pytest.approx(psi_t, abs=1e-12)
    # eq. (13): the predicted velocity is the delayed one
    assert (float(uh), float(vh), float(rh)) == pytest.approx((u, v, 0.0), abs=1e-15)


@pytest.mark.parametrize("tau", [0.5, 2.0, 5.0])
def test_predictor_exact_for_turning_on_the_spot(tau):
    # u = v = 0, constant r: the position stays, the heading advances by r tau exactly
    follower = (0.0, 0.0, 0.3)
    obs = obs_from_inertial(follower, (1.0, -2.0, 0.4), (0.0, 0.0, 0.15))
    x, y, psi, *_ = predict_target(decode(obs), tau)
    gx, gy = to_inertial(follower, float(x), float(y))
    assert (gx, gy) == pytest.approx((1.0, -2.0), abs=1e-12)
    assert float(psi) + 0.3 == pytest.approx(0.4 + 0.15 * tau, abs=1e-12)


@pytest.mark.parametrize("tau", [0.25, 0.5, 1.0, 2.0])
def test_predictor_error_on_a_circular_arc(tau):
    # constant u, r (v = 0): exact arc p(tau) = p0 + (u / r) [sin(psi0 + r tau) - sin psi0,
    # cos psi0 - cos(psi0 + r tau)]; the first-order prediction misses it by
    # u * || (sin(r tau) / r - tau, (1 - cos(r tau)) / r) || (chord vs tangent).
    u, r, psi0 = 0.5, 0.07, 1.1
    p0 = (-0.5, 0.8)
    obs = obs_from_inertial((0.0, 0.0, 0.0), (*p0, psi0), (u, 0.0, r))
    x, y, psi, *_ = predict_target(decode(obs), tau)
    true_x = p0[0] + u / r * (math.sin(psi0 + r * tau) - math.sin(psi0))
    true_y = p0[1] + u / r * (math.cos(psi0) - math.cos(psi0 + r * tau))
    err = math.hypot(float(x) - true_x, float(y) - true_y)
    expected = u * math.hypot(math.sin(r * tau) / r - tau, (1 - math.cos(r * tau)) / r)
    assert err == pytest.approx(expected, rel=1e-9)
    # small r tau: about 0.5 * (centripetal acceleration u r) * tau^2
    assert err == pytest.approx(0.5 * u * r * tau**2, rel=0.1)
    assert float(psi) == pytest.approx(psi0 + r * tau, abs=1e-12)  # heading is exact


def test_predictor_error_under_constant_acceleration_scales_with_tau_squared():
    # straight line with surge acceleration a: true advance u0 tau + a tau^2 / 2, prediction u0 tau
    a, u0, psi0, p0 = 0.03, 0.4, -2.0, (0.7, 0.2)
    ratios = []
    for tau in (0.5, 1.0, 1.5, 2.0, 3.0):
        obs = obs_from_inertial((0.0, 0.0, 0.0), (*p0, psi0), (u0, 0.0, 0.0))
        x, y, *_ = predict_target(decode(obs), tau)
        s = u0 * tau + 0.5 * a * tau**2
        true_x, true_y = p0[0] + s * math.cos(psi0), p0[1] + s * math.sin(psi0)
        err = math.hypot(float(x) - true_x, float(y) - true_y)
        assert err == pytest.approx(0.5 * a * tau**2, rel=1e-9)
        ratios.append(err / tau**2)
    assert np.allclose(ratios, 0.5 * a, rtol=1e-9)


def test_predictor_disabled_returns_the_delayed_pose():
    obs = make_obs(target_dx=1.2, target_dy=-0.3, target_dpsi=0.4, target_u=0.5, target_v=0.02,
                   target_r=0.05)
    out = predict_target(decode(obs), 2.0, enabled=False)
    assert tuple(float(z) for z in out) == pytest.approx((1.2, -0.3, 0.4, 0.5, 0.02, 0.05), abs=1e-15)


def test_predictor_is_batched():
    obs = np.stack([make_obs(target_dx=1.0, target_u=0.5), make_obs(target_dy=2.0, target_dpsi=math.pi / 2,
                                                                     target_u=0.25)])
    x, y, psi, *_ = predict_target(decode(obs), 2.0)
    np.testing.assert_allclose(x, [2.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(y, [0.0, 2.5], atol=1e-12)
    np.testing.assert_allclose(psi, [0.0, math.pi / 2], atol=1e-12)


# --------------------------------------------------------------------------------------------
# reference generation, eq. (21)


@pytest.mark.parametrize("psi_hat, expected_xy", [
    (math.pi / 2, (2 - 0.12, 1 - 0.65)),  # R(pi/2) (-0.65, 0.12) = (-0.12, -0.65)
    (0.0, (2 - 0.65, 1 + 0.12)),
    (math.pi, (2 + 0.65, 1 - 0.12)),
    (-math.pi / 2, (2 + 0.12, 1 + 0.65)),
])
def test_reference_point_by_hand(psi_hat, expected_xy):
    x, y, psi = reference_point(2.0, 1.0, psi_hat, (-0.65, 0.12), 0.25)
    assert (x, y) == pytest.approx(expected_xy, abs=1e-12)
    assert psi == pytest.approx(psi_hat + 0.25, abs=1e-15)


def test_reference_lies_065_behind_and_012_to_port_of_the_target():
    # distance target -> reference is |p_d| whatever the heading
    for psi_hat in np.linspace(-3, 3, 7):
        x, y, _ = reference_point(0.0, 0.0, psi_hat, PD, 0.0)
        assert math.hypot(x, y) == pytest.approx(math.hypot(0.65, 0.12), abs=1e-12)
        # along-track component -0.65, cross-track +0.12
        c, s = math.cos(psi_hat), math.sin(psi_hat)
        assert c * x + s * y == pytest.approx(-0.65, abs=1e-12)
        assert -s * x + c * y == pytest.approx(0.12, abs=1e-12)


def test_controller_reference_uses_prediction_per_table_1():
    obs = make_obs(target_dx=2.0, target_dy=1.0, target_dpsi=math.pi / 2, target_u=0.5)
    # ROBUST_ONLY / PID: reference of the delayed target
    delayed = (2 - 0.12, 1 - 0.65, math.pi / 2)
    # predicted target: (2, 1) + R(pi/2) (0.5, 0) * 2 s = (2, 2)
    predicted = (2 - 0.12, 2 - 0.65, math.pi / 2)
    for name, exp in (("PID", delayed), ("ROBUST_ONLY", delayed), ("PRED_ONLY", predicted),
                      ("PROPOSED", predicted)):
        ref = make_controller(name, S4).reference(obs)
        assert ref.shape == (1, 3)
        np.testing.assert_allclose(ref[0], exp, atol=1e-12, err_msg=name)


# --------------------------------------------------------------------------------------------
# the hierarchical law with zero tracking error: only model compensation is left


@pytest.mark.parametrize("psi_d", [0.0, 0.3])
@pytest.mark.parametrize("name", ["PROPOSED", "PRED_ONLY"])
def test_zero_tracking_error_leaves_only_model_compensation(name, psi_d):
    spec = make_task_spec("S4", psi_d=psi_d)
    tau, (pdx, pdy) = spec.delay_s, spec.p_d
    u_t, v_t, r_t = 0.4, 0.05, 0.1
    # place the delayed target so that the predicted reference is the follower's pose:
    # psi_hat + psi_d = 0 and p_hat + R(psi_hat) p_d = 0
    psi_hat = -psi_d
    alpha = psi_hat - r_t * tau  # delayed heading
    ch, sh = math.cos(psi_hat), math.sin(psi_hat)
    p_hat = (-(ch * pdx - sh * pdy), -(sh * pdx + ch * pdy))
    ca, sa = math.cos(alpha), math.sin(alpha)
    delayed = (p_hat[0] - (ca * u_t - sa * v_t) * tau, p_hat[1] - (sa * u_t + ca * v_t) * tau)
    # desired velocity = velocity of the reference point (rigid body: nu + r x p_d), rotated
    bx, by = u_t - r_t * pdy, v_t + r_t * pdx
    u_d, v_d, r_d = ch * bx - sh * by, sh * bx + ch * by, r_t
    obs = make_obs(u=u_d, v=v_d, r=r_d, target_dx=delayed[0], target_dy=delayed[1], target_dpsi=alpha,
                   target_u=u_t, target_v=v_t, target_r=r_t)
    ctrl = make_controller(name, spec)
    ref = ctrl.reference(obs)[0]
    np.testing.assert_allclose(ref, [0.0, 0.0, 0.0], atol=1e-12)
    action, _ = ctrl.predict(obs)
    nm = spec.nominal
    # eqs. (32)-(34) with e = 0, derivative 0 at the first sample, no current
    expected = np.array([nm.X_u * u_d - nm.m * v_d * r_d,
                         nm.Y_v * v_d + nm.m * u_d * r_d,
                         nm.N_r * r_d])
    np.testing.assert_allclose(ctrl.last_forces[0], expected, atol=1e-10)
    np.testing.assert_allclose(action, expected / np.asarray(spec.force_limits), atol=1e-6)


def test_zero_error_by_hand_numbers():
    # the same case with psi_d = 0 in plain numbers (m 25, X_u 15, Y_v 20, N_r 3 nominal):
    # u_d = 0.4 - 0.1 * 0.12 = 0.388, v_d = 0.05 + 0.1 * (-0.65) = -0.015, r_d = 0.1
    # F_u = 15 * 0.388 - 25 * (-0.015) * 0.1 = 5.8575; F_v = 20 * (-0.015) + 25 * 0.388 * 0.1 = 0.67
    # F_r = 3 * 0.1 = 0.3
    nm = S4.nominal
    assert (nm.m, nm.X_u, nm.Y_v, nm.N_r) == (25.0, 15.0, 20.0, 3.0)
    delayed = (0.65 - 0.4 * 2.0 * math.cos(-0.2) + 0.05 * 2.0 * math.sin(-0.2),
               -0.12 - 0.4 * 2.0 * math.sin(-0.2) - 0.05 * 2.0 * math.cos(-0.2))
    obs = make_obs(u=0.388, v=-0.015, r=0.1, target_dx=delayed[0], target_dy=delayed[1], target_dpsi=-0.2,
                   target_u=0.4, target_v=0.05, target_r=0.1)
    ctrl = make_controller("PROPOSED", S4)
    ctrl.predict(obs)
    np.testing.assert_allclose(ctrl.last_forces[0], [5.8575, 0.67, 0.3], atol=1e-10)


def test_outer_loop_proportional_term_by_hand():
    # reference 1 m ahead and 0.5 m to port, heading +0.2, static target: v_ref = -K_p e_p
    o = decode(make_obs(target_dx=1.0 + 0.65, target_dy=0.5 - 0.12, target_dpsi=0.0))
    pred = predict_target(o, 0.0)
    ref = reference_point(*pred[:3], PD, 0.2)
    u_d, v_d, r_d = outer_loop(ref, pred, PD, Gains(K_p=2.0, K_psi=3.0))
    assert (float(u_d), float(v_d), float(r_d)) == pytest.approx((2.0, 1.0, 0.6), abs=1e-12)


# --------------------------------------------------------------------------------------------
# ablations differ from PROPOSED only in their switched mechanism


def _run(ctrl, obs_seq):
    out = []
    for k, o in enumerate(obs_seq):
        ctrl.predict(o, episode_start=np.array([k == 0]))
        out.append(ctrl.last_forces[0].copy())
    return np.array(out)


def _moving_sequence(n=6):
    rng = np.random.default_rng(7)
    base = random_obs(rng)
    seq = []
    for k in range(n):
        o = base.copy()
        o[OBS_INDEX["target_dx"]] += 0.02 * k
        o[OBS_INDEX["u"]] += 0.01 * k
        o[OBS_INDEX["r"]] -= 0.005 * k
        seq.append(o)
    return seq


def test_robust_only_equals_proposed_without_delay():
    spec0 = make_task_spec("S4", delay_s=0.0)
    seq = _moving_sequence()
    f_prop = _run(make_controller("PROPOSED", spec0), seq)
    f_rob = _run(make_controller("ROBUST_ONLY", spec0), seq)
    np.testing.assert_array_equal(f_rob, f_prop)
    # with tau = 2 s and a moving target they differ
    g_prop = _run(make_controller("PROPOSED", S4), seq)
    g_rob = _run(make_controller("ROBUST_ONLY", S4), seq)
    assert np.abs(g_prop - g_rob).max() > 1.0


def test_pred_only_is_proposed_minus_the_robust_term():
    gains = Gains()
    seq = _moving_sequence()
    f_prop = _run(make_controller("PROPOSED", S4), seq)
    f_pred = _run(make_controller("PRED_ONLY", S4), seq)
    for k, o in enumerate(seq):
        d = decode(o)
        pred = predict_target(d, S4.delay_s)
        ref = reference_point(*pred[:3], S4.p_d, S4.psi_d)
        desired = outer_loop(ref, pred, S4.p_d, gains)
        e = np.array([d["u"] - desired[0], d["v"] - desired[1], d["r"] - desired[2]], dtype=float)
        # eqs. (32)-(34): F = ... - rho sat(e / phi), so PROPOSED = PRED_ONLY - rho sat(e / phi)
        robust = np.array([rho * min(1.0, max(-1.0, ek / phi))
                           for rho, phi, ek in zip(gains.rho, gains.phi, e, strict=True)])
        assert np.any(robust != 0.0)
        np.testing.assert_allclose(f_prop[k], f_pred[k] - robust, atol=1e-10, err_msg=f"step {k}")


def test_pred_only_equals_proposed_when_velocity_errors_vanish():
    # the zero-error observation of test_zero_tracking_error_leaves_only_model_compensation
    delayed = (0.65 - 0.8 * math.cos(-0.2) + 0.1 * math.sin(-0.2),
               -0.12 - 0.8 * math.sin(-0.2) - 0.1 * math.cos(-0.2))
    obs = make_obs(u=0.388, v=-0.015, r=0.1, target_dx=delayed[0], target_dy=delayed[1], target_dpsi=-0.2,
                   target_u=0.4, target_v=0.05, target_r=0.1)
    a = make_controller("PROPOSED", S4)
    b = make_controller("PRED_ONLY", S4)
    a.predict(obs)
    b.predict(obs)
    np.testing.assert_allclose(a.last_forces, b.last_forces, atol=1e-12)


def test_make_controller_flags_per_table_1():
    table = {"ROBUST_ONLY": (False, True), "PRED_ONLY": (True, False), "PROPOSED": (True, True)}
    for name, (prediction, robust) in table.items():
        c = make_controller(name, S4)
        assert isinstance(c, HierarchicalController)
        assert (c.prediction, c.robust) == (prediction, robust)
        assert c.name == name
    pid = make_controller("PID", S4)
    assert isinstance(pid, PIDController) and not isinstance(pid, HierarchicalController)
    assert pid.name == "PID"
    assert set(CONTROLLERS) == {"PID", "ROBUST_ONLY", "PRED_ONLY", "PROPOSED"}


def test_make_controller_unknown_name_lists_valid_names():
    with pytest.raises(ValueError) as exc:
        make_controller("LQR", S4)
    for n in ("PID", "ROBUST_ONLY", "PRED_ONLY", "PROPOSED"):
        assert n in str(exc.value)


# --------------------------------------------------------------------------------------------
# saturation and the robust term


def test_sat_inside_outside_and_at_the_boundary():
    z = np.array([-3.0, -1.0, -0.5, 0.0, 0.25, 1.0, 7.0])
    np.testing.assert_array_equal(sat(z), [-1.0, -1.0, -0.5, 0.0, 0.25, 1.0, 1.0])
    phi = 0.04
    for sign in (1.0, -1.0):
        lo = sat(np.array(sign * phi * (1 - 1e-9)) / phi)
        hi = sat(np.array(sign * phi * (1 + 1e-9)) / phi)
        assert abs(float(hi) - float(lo)) <= 1.1e-9
        assert float(hi) == sign


def test_robust_term_is_continuous_in_e():
    rho, phi = 4.0, 0.04
    e = np.linspace(-0.2, 0.2, 400_001)  # step 1e-6, crossing +-phi
    f = rho * sat(e / phi)
    h = e[1] - e[0]
    assert np.abs(np.diff(f)).max() <= rho / phi * h * (1 + 1e-6)
    assert f[0] == -rho and f[-1] == rho


# --------------------------------------------------------------------------------------------
# filtered derivative


def test_filtered_derivative_on_a_ramp_converges_to_the_slope():
    dt, c = 0.05, np.array([0.7, -2.0])
    d = FilteredDerivative(dt, 0.05)
    x0 = np.zeros((1, 2))
    d.reset(np.ones(1, dtype=bool), x0)
    out = d(x0)
    np.testing.assert_array_equal(out, 0.0)  # the first sample after a reset
    # first step of D(s) = s / (T s + 1), Tustin: d_1 = 2 dx / (2 T + dt) = 2 c dt / 0.15
    out = d(c * dt)
    np.testing.assert_allclose(out[0], 2 * c * dt / (2 * 0.05 + dt), rtol=1e-12)
    for k in range(2, 200):
        out = d(c * k * dt)
    np.testing.assert_allclose(out[0], c, rtol=1e-9)


def test_filtered_derivative_of_a_constant_is_zero_and_reset_is_per_env():
    d = FilteredDerivative(0.05, 0.05)
    x = np.array([[1.5, -2.0, 0.3], [4.0, 0.0, 1.0]])
    d.reset(np.ones(2, dtype=bool), x)
    for _ in range(10):
        np.testing.assert_array_equal(d(x), 0.0)
    # step env 1 only, then restart env 0 at a new value: env 0 reads 0, env 1 keeps its memory
    x2 = x.copy()
    x2[1] += 1.0
    d1 = d(x2)[1].copy()
    assert np.all(d1 > 0)
    x3 = x2.copy()
    x3[0] += 5.0
    d.reset(np.array([True, False]), x3)
    out = d(x3)
    np.testing.assert_array_equal(out[0], 0.0)
    np.testing.assert_allclose(out[1], d.b * d1)  # constant input: geometric decay by b
    assert 0 < d.b < 1


def test_filtered_derivative_rejects_bad_time_constant():
    for tc in (-0.1, float("nan"), float("inf")):
        with pytest.raises(ValueError):
            FilteredDerivative(0.05, tc)


# --------------------------------------------------------------------------------------------
# memory and episode_start


def _sequences(rng, steps=5):
    return [random_obs(rng, 2) for _ in range(steps)]


@pytest.mark.parametrize("name", CONTROLLERS)
def test_episode_start_resets_memory_per_env(name):
    rng = np.random.default_rng(11)
    seq = _sequences(rng)
    batch = make_controller(name, S4)
    singles = [make_controller(name, S4), make_controller(name, S4)]
    never_reset = make_controller(name, S4)
    for k, o in enumerate(seq):
        start = np.array([k == 0, k == 0])
        a, _ = batch.predict(o, episode_start=start)
        for i in range(2):
            ai, _ = singles[i].predict(o[i], episode_start=start[i:i + 1])
            np.testing.assert_allclose(a[i], ai, atol=1e-6)
        never_reset.predict(o[0], episode_start=np.array([k == 0]))
    last = random_obs(rng, 2)
    a, _ = batch.predict(last, episode_start=np.array([True, False]))
    f_batch = batch.last_forces.copy()
    fresh = make_controller(name, S4)
    a0, _ = fresh.predict(last[0])
    a1, _ = singles[1].predict(last[1], episode_start=np.array([False]))
    np.testing.assert_allclose(f_batch[0], fresh.last_forces[0], atol=1e-10)
    np.testing.assert_allclose(f_batch[1], singles[1].last_forces[0], atol=1e-10)
    np.testing.assert_allclose(a[0], a0, atol=1e-6)
    np.testing.assert_allclose(a[1], a1, atol=1e-6)
    # the reset mattered: without it env 0 would have continued differently
    never_reset.predict(last[0], episode_start=np.array([False]))
    assert np.abs(never_reset.last_forces[0] - f_batch[0]).max() > 1e-3


def test_pid_integral_accumulates_and_resets():
    # follower heading 0 at the origin, static delayed target 1 m ahead: e = p_ref - p
    obs = make_obs(target_dx=1.0, target_dy=0.0)
    e = np.array([1.0 - 0.65, 0.12, 0.0])
    pid = make_controller("PID", S4)
    g = pid.gains
    forces = []
    for k in range(6):
        pid.predict(obs, episode_start=np.array([k == 0]))
        forces.append(pid.last_forces[0].copy())
    forces = np.array(forces)
    kp = np.array([g.K_P, g.K_P, g.K_P_psi])
    ki = np.array([g.K_I, g.K_I, g.K_I_psi])
    # constant error: derivative 0; each step adds K_I e dt
    np.testing.assert_allclose(np.diff(forces, axis=0), np.tile(ki * e * S4.dt, (5, 1)), atol=1e-12)
    # the proportional part: F_1 = K_P e + (at most one step of) integral
    assert np.all(np.abs(forces[0] - kp * e) <= np.abs(ki * e) * S4.dt + 1e-12)
    pid.predict(obs, episode_start=np.array([True]))
    np.testing.assert_allclose(pid.last_forces[0], forces[0], atol=1e-12)


def test_first_call_always_starts_fresh_and_reset_forgets():
    rng = np.random.default_rng(3)
    o1, o2 = random_obs(rng), random_obs(rng)
    c = make_controller("PROPOSED", S4)
    c.predict(o1)
    c.predict(o2)  # episode_start None: continues
    f_cont = c.last_forces.copy()
    c.reset()
    c.predict(o2)
    f_reset = c.last_forces.copy()
    fresh = make_controller("PROPOSED", S4)
    fresh.predict(o2)
    np.testing.assert_allclose(f_reset, fresh.last_forces, atol=1e-12)
    assert np.abs(f_cont - f_reset).max() > 1e-3


# --------------------------------------------------------------------------------------------
# batching and the predict protocol


@pytest.mark.parametrize("name", CONTROLLERS)
def test_batched_predict_equals_stacked_single_predicts(name):
    rng = np.random.default_rng(5)
    seq = [random_obs(rng, 3) for _ in range(4)]
    batch = make_controller(name, S4)
    singles = [make_controller(name, S4) for _ in range(3)]
    for k, o in enumerate(seq):
        a, _ = batch.predict(o, episode_start=np.full(3, k == 0))
        f = batch.last_forces.copy()
        for i in range(3):
            ai, _ = singles[i].predict(o[i], episode_start=np.array([k == 0]))
            np.testing.assert_allclose(f[i], singles[i].last_forces[0], rtol=1e-12, atol=1e-12)
            np.testing.assert_array_equal(a[i], ai)


@pytest.mark.parametrize("name", CONTROLLERS)
def test_predict_shapes_dtype_and_range(name):
    rng = np.random.default_rng(9)
    c = make_controller(name, S4)
    a, state = c.predict(random_obs(rng))
    assert a.shape == (3,) and a.dtype == np.float32 and state is None
    big = random_obs(rng, 4)
    big[:, OBS_INDEX["target_dx"]] *= 100.0  # far away: the forces saturate
    c2 = make_controller(name, S4)
    a, _ = c2.predict(big.astype(np.float32))
    assert a.shape == (4, 3) and a.dtype == np.float32
    assert np.all(np.abs(a) <= 1.0) and np.any(np.abs(a) == 1.0)
    assert c2(big[0]).shape == (3,)


@pytest.mark.parametrize("shape", [(OBS_DIM - 1,), (2, OBS_DIM + 1), (2, 2, OBS_DIM), ()])
def test_predict_rejects_wrong_obs_shape(shape):
    with pytest.raises(ValueError):
        make_controller("PROPOSED", S4).predict(np.zeros(shape))
    with pytest.raises(ValueError):
        make_controller("PID", S4).predict(np.zeros(shape))


def test_predict_rejects_wrong_episode_start_shape():
    c = make_controller("PROPOSED", S4)
    obs = np.tile(make_obs(), (2, 1))
    c.predict(obs)
    with pytest.raises(ValueError):
        c.predict(obs, episode_start=np.array([True, False, True]))


@pytest.mark.parametrize("bad", [None, {"delay_s": 2.0}, "S4"])
def test_non_taskspec_spec_raises_type_error(bad):
    with pytest.raises(TypeError):
        HierarchicalController(bad)
    with pytest.raises(TypeError):
        PIDController(bad)
    with pytest.raises(TypeError):
        make_controller("PROPOSED", bad)


# --------------------------------------------------------------------------------------------
# SB3 evaluate_policy on a vectorised env


class _ZeroPolicy:
    def predict(self, observation, state=None, episode_start=None, deterministic=True):
        obs = np.asarray(observation)
        return np.zeros(obs.shape[:-1] + (3,), dtype=np.float32), state


def test_sb3_evaluate_policy_runs_each_controller():
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.evaluation import evaluate_policy

    def make():
        return gym.make("AUVFollow-S1-v0", episode_s=5.0, steady_start_s=2.0, max_episode_steps=100)

    spec = make_task_spec("S1", episode_s=5.0, steady_start_s=2.0)
    means = {}
    for name in (*CONTROLLERS, "zero"):
        venv = make_vec_env(make, n_envs=2, seed=0)
        policy = _ZeroPolicy() if name == "zero" else make_controller(name, spec)
        mean, std = evaluate_policy(policy, venv, n_eval_episodes=2)
        venv.close()
        assert math.isfinite(mean) and math.isfinite(std)
        means[name] = mean
    assert means["PROPOSED"] > means["zero"]
