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
