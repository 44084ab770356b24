"""Disturbance observer: a constant force disturbance is removed to zero steady velocity error
(analytic: without it the error is d / (K + rho / phi) in the boundary layer), its estimate
does not wind up while the actuators saturate, and it rejects bad input.

The plant is a tiny closed-loop simulation of eqs. (6)-(8) on the nominal model with a
constant force added (RK4, force held over the control step), written here.
"""

from __future__ import annotations

import numpy as np
import pytest

from auv_follow_env.params import NOMINAL_VEHICLE as NOM
from controllers.disturbance import DisturbanceObserver
from controllers.hierarchical import Gains, inner_loop

DT = 0.05
G = Gains()


def plant_rhs(nu, F, d):
    u, v, r = nu
    return np.array([(F[0] - NOM.X_u * u + NOM.m * v * r + d[0]) / NOM.m,
                     (F[1] - NOM.Y_v * v - NOM.m * u * r + d[1]) / NOM.m,
                     (F[2] - NOM.N_r * r + d[2]) / NOM.I_z])


def plant_step(nu, F, d, sub=5):
    h = DT / sub
    for _ in range(sub):
        k1 = plant_rhs(nu, F, d)
        k2 = plant_rhs(nu + h / 2 * k1, F, d)
        k3 = plant_rhs(nu + h / 2 * k2, F, d)
        k4 = plant_rhs(nu + h * k3, F, d)
        nu = nu + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return nu


def closed_loop(d, desired, dob: DisturbanceObserver | None, steps: int, limits=(150.0, 150.0, 30.0),
                schedule=None):
    """Inner loop (32)-(34) (robust terms on) tracking constant desired velocities."""
    nu = np.zeros(3)
    lim = np.asarray(limits)
    log = []
    for k in range(steps):
        des = schedule(k) if schedule else desired
        o = {"u": np.array([nu[0]]), "v": np.array([nu[1]]), "r": np.array([nu[2]]),
             "current_u": np.zeros(1), "current_v": np.zeros(1)}
        F = np.stack(inner_loop(o, tuple(np.array([x]) for x in des), (np.zeros(1),) * 3, NOM, G, True), axis=-1)
        if dob is not None:
            d_hat = dob.update(nu[None], np.zeros((1, 2)), np.array([k == 0]))
            F = F - d_hat
            dob.applied(F)
        F = np.clip(F[0], -lim, lim)
        nu = plant_step(nu, F, d)
        log.append((nu.copy(), dob.d_hat[0].copy() if dob is not None else None, F))
    return nu, log


D = np.array([3.0, -2.0, 0.2])  # N, N, N m
DESIRED = (0.5, 0.1, 0.05)


def test_without_observer_the_steady_error_is_d_over_k_plus_rho_over_phi():
    nu, _ = closed_loop(D, DESIRED, None, 1200)
    K = np.array([G.K_u, G.K_v, G.K_r]) + np.array(G.rho) / np.array(G.phi)
    expected = np.array(DESIRED) + D / K  # m e' = -K e - rho e / phi + d = 0 inside the boundary layer
    assert np.all(np.abs(D / K) < np.array(G.phi))  # (the analytic value assumes the boundary layer)
    np.testing.assert_allclose(nu, expected, atol=1e-9)


def test_observer_removes_a_constant_force_disturbance_to_zero_steady_error():
    dob = DisturbanceObserver(NOM, DT, (150.0, 150.0, 30.0), time_constant=0.5)
    nu, log = closed_loop(D, DESIRED, dob, 1200)
    np.testing.assert_allclose(nu, DESIRED, atol=1e-9)
    np.testing.assert_allclose(log[-1][1], D, atol=1e-8)


def test_observer_does_not_wind_up_while_the_actuators_saturate():
    """Surge limit 20 N, d_u = 10 N, u_d = 3 m/s needs 35 N: saturated, u settles at
    (20 + 10) / X_u = 2 m/s, and d_hat still converges to the true 10 N (not beyond); back to
    u_d = 0.5 m/s, the error returns to zero."""
    lim = (20.0, 150.0, 30.0)
    d = np.array([10.0, 0.0, 0.0])
    dob = DisturbanceObserver(NOM, DT, lim, time_constant=0.5)
    nu, log = closed_loop(d, None, dob, 2400, limits=lim, schedule=lambda k: (3.0, 0.0, 0.0) if k < 1200
                          else (0.5, 0.0, 0.0))
    sat_nu, sat_dhat, sat_F = log[1199]
    assert sat_F[0] == pytest.approx(20.0)
    assert sat_nu[0] == pytest.approx((20.0 + 10.0) / NOM.X_u, abs=1e-6)
    assert sat_dhat[0] == pytest.approx(10.0, abs=1e-6)
    assert max(abs(entry[1][0]) for entry in log) <= 20.0
    assert nu[0] == pytest.approx(0.5, abs=1e-9)


@pytest.mark.parametrize("kwargs, name", [
    ({"nominal": "S4"}, "nominal"), ({"dt": 0.0}, "dt"), ({"time_constant": -1.0}, "time_constant"),
    ({"force_limits": (1.0, 2.0)}, "force_limits"), ({"force_limits": (1.0, 0.0, 1.0)}, "force_limits")])
def test_observer_rejects_bad_arguments(kwargs, name):
    args = {"nominal": NOM, "dt": DT, "force_limits": (150.0, 150.0, 30.0), "time_constant": 0.5, **kwargs}
    with pytest.raises(ValueError, match=name):
        DisturbanceObserver(**args)
