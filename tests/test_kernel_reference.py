"""The numba kernel against an independent, plain-Python RK4 of eqs. (3)-(10).

The reference below evaluates every sinusoid directly with math.sin at each RK4 stage time;
the kernel rotates phasors and uses small-angle heading updates. They must agree to rounding.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from auv_follow_env import dynamics as dyn
from auv_follow_env.params import NOMINAL_VEHICLE, make_config
from auv_follow_env.sim import config_vector, sample_params


def _reference_step(x, p, t0, dt, nsub, F):
    """Classical RK4 of follower + target from the paper's equations, all stage values direct."""
    W1, W2 = dyn.DIST_OMEGA

    def tone(col, t):
        return p[col] * math.sin(W1 * t + p[col + 1]) + p[col + 2] * math.sin(W2 * t + p[col + 3])

    def rhs(t, s):
        X, Y, ps, u, v, r, xt, yt, pt = s
        cx = p[dyn.P_CX] + p[dyn.P_CX + 1] * math.sin(p[dyn.P_CX + 2] * t + p[dyn.P_CX + 3])
        cy = p[dyn.P_CY] + p[dyn.P_CY + 1] * math.sin(p[dyn.P_CY + 2] * t + p[dyn.P_CY + 3])
        uc = math.cos(ps) * cx + math.sin(ps) * cy  # eq. (5)
        vc = -math.sin(ps) * cx + math.cos(ps) * cy
        m, Iz = p[dyn.P_M], p[dyn.P_IZ]
        du, dv, dr = tone(dyn.P_D, t), tone(dyn.P_D + 4, t), tone(dyn.P_D + 8, t)
        ut = p[dyn.P_TV] * (1 + p[dyn.P_TAU] * math.sin(p[dyn.P_TWU] * t + p[dyn.P_TPU]))
        rt = p[dyn.P_TAR] * math.sin(p[dyn.P_TWR] * t + p[dyn.P_TPR])
        return np.array([
            u * math.cos(ps) - v * math.sin(ps), u * math.sin(ps) + v * math.cos(ps), r,   # eq. (3)
            (F[0] - p[dyn.P_XU] * (u - uc) + m * v * r + du) / m,                          # eq. (6)
            (F[1] - p[dyn.P_YV] * (v - vc) - m * u * r + dv) / m,                          # eq. (7)
            (F[2] - p[dyn.P_NR] * r + dr) / Iz,                                            # eq. (8)
            ut * math.cos(pt), ut * math.sin(pt), rt])                                     # eq. (10)

    h = dt / nsub
    s = np.array(x, dtype=float)
    for j in range(nsub):
        t = t0 + j * h
        k1 = rhs(t, s)
        k2 = rhs(t + h / 2, s + h / 2 * k1)
        k3 = rhs(t + h / 2, s + h / 2 * k2)
        k4 = rhs(t + h, s + h * k3)
        s = s + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return s


@pytest.mark.parametrize("nsub", [1, 2, 5])
def test_kernel_equals_plain_rk4_over_many_steps(nsub):
    cfg_obj = make_config("S4", physics_substeps=nsub)
    p = sample_params(cfg_obj, np.random.default_rng(11))
    cfg = config_vector(cfg_obj)
    state = np.array([[0.3, -0.2, 2.5, 0.4, -0.1, 0.3, 1.0, 0.5, 2.2]])
    ref = state[0].copy()
    rng = np.random.default_rng(5)
    for k in range(200):  # 10 s, t0 up to 10 s so the phasor start phases matter
        F = rng.uniform(-60, 60, 3) * np.array([1.0, 1.0, 0.2])
        t0 = 3.0 + k * cfg_obj.dt
        dyn.integrate(state, p[None, :], cfg, np.array([t0]), F[None, :])
        ref = _reference_step(ref, p, t0, cfg_obj.dt, nsub, F)
        np.testing.assert_allclose(state[0], ref, rtol=0, atol=1e-11)


def test_small_angle_cos_sin_is_exact_to_rounding():
    for d in np.concatenate([np.linspace(-0.25, 0.25, 101), [1e-9, -3e-5, 0.3, -2.0]]):
        c, s = dyn.cos_sin_small.py_func(d)
        assert c == pytest.approx(math.cos(d), abs=2e-16) and s == pytest.approx(math.sin(d), abs=2e-16)


def test_reference_uses_the_nominal_vehicle_shape():
    # guard: the parameter row carries the true (mismatched) damping, not the nominal one
    p = sample_params(make_config("S4"), np.random.default_rng(0))
    assert p[dyn.P_XU] == pytest.approx(NOMINAL_VEHICLE.X_u * 2.05)


def test_tone_rotation_factors_reused_only_for_the_same_angle():
    # The block kernel keeps each lane's tone rotation factors (cos/sin of omega * h / 2) and
    # recomputes a tone's row only when some lane's omega changed. Mix, over three blocks of
    # envs: tone frequencies shared by every env, frequencies that change from block to block
    # or lane to lane, a frequency of 0 (and -0), and frequencies fast enough that the angle
    # exceeds SMALL_ANGLE (libm path). Every env stepped in the batch must equal the same env
    # stepped alone (a fresh work buffer: nothing to reuse), bit for bit, step after step.
    cfg_obj = make_config("S4")
    n = 2 * dyn.BLOCK + 7
    p = np.stack([sample_params(cfg_obj, np.random.default_rng(100 + i)) for i in range(n)])
    hh = cfg_obj.dt / cfg_obj.physics_substeps / 2
    fast = 1.2 * dyn.SMALL_ANGLE / hh  # [rad/s]: the angle omega * hh is beyond SMALL_ANGLE
    assert fast * hh > dyn.SMALL_ANGLE
    p[dyn.BLOCK:, dyn.P_TWU] = 0.8  # target surge tone: changes at the second block
    p[5, dyn.P_TWR] = fast  # one lane of the first block on the libm path
    p[dyn.BLOCK + 5, dyn.P_TWR] = fast  # the same lane of the second block too
    p[2 * dyn.BLOCK:, dyn.P_CX + 2] = 0.0  # current x tone: omega 0 in the third block ...
    p[2 * dyn.BLOCK + 1, dyn.P_CX + 2] = -0.0  # ... and -0 in one of its lanes
    p[3, dyn.P_CY + 2] = fast
    cfg = config_vector(cfg_obj)
    rng = np.random.default_rng(7)
    state = np.tile([0.3, -0.2, 2.5, 0.4, -0.1, 0.3, 1.0, 0.5, 2.2], (n, 1)) + rng.normal(0, 0.1, (n, 9))
    alone = state.copy()
    for k in range(30):
        forces = rng.uniform(-60, 60, (n, 3))
        t0 = np.full(n, 2.0 + k * cfg_obj.dt)
        dyn.integrate(state, p, cfg, t0, forces)
        for i in range(n):
            row = alone[i:i + 1]
            dyn.integrate(row, p[i:i + 1], cfg, t0[i:i + 1], forces[i:i + 1])
        np.testing.assert_array_equal(state, alone)
    # and the values are those of an independent RK4 (a lane on the libm path included)
    ref = np.array([0.3, -0.2, 2.5, 0.4, -0.1, 0.3, 1.0, 0.5, 2.2])
    one = ref[None, :].copy()
    for k in range(20):
        F = np.array([10.0, -5.0, 2.0])
        dyn.integrate(one, p[5:6], cfg, np.array([k * cfg_obj.dt]), F[None, :])
        ref = _reference_step(ref, p[5], k * cfg_obj.dt, cfg_obj.dt, cfg_obj.physics_substeps, F)
    np.testing.assert_allclose(one[0], ref, rtol=0, atol=1e-11)
