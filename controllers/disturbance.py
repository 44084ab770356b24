"""Disturbance observer on the inner loop (ours, not the paper's), with anti-windup.

The inner loop (32)-(34) compensates the *nominal* model; what the nominal model misses (the
damping mismatch -dX u_r, the disturbances d, the current's error) acts as a lumped force
``d`` in eqs. (6)-(8):

    m u' = F_u - X_u u_r + m v r + d_u,   m v' = F_v - Y_v v_r - m u r + d_v,   I_z r' = F_r - N_r r + d_r.

Each step the observer solves the nominal model for ``d`` over the last control step, with
the force that was *applied* (the command clipped to the force limits) and the trapezoid rule
for the state-dependent terms,

    d_meas = M (nu_k - nu_{k-1}) / dt - F_applied,{k-1} - (n(nu_k) + n(nu_{k-1})) / 2,

and low-pass filters it, ``d_hat += dt / (T_d + dt) (d_meas - d_hat)``. The law then adds
``-d_hat`` to (32)-(34). A constant ``d`` is removed exactly (zero steady velocity error):
at rest ``d_meas`` equals ``d``.

**Thrusters.** On the v1 tiers the thrusters lag the command (first order, time constant
T_th) and are rate limited; the force that acts over a step is then not the command. Given
``thruster_tc_s`` and ``thruster_rate`` (the follower knows its own thrusters; the task spec
carries them), the observer runs the same thruster model on the commands it is told and
uses its output as the applied force, as the plant does:
``f_k = f_{k-1} + (1 - e^{-dt/T_th}) (c_k - f_{k-1})``, clipped to ``f_{k-1} +- rate * limit * dt``,
``c_k`` the command clipped to the limits, ``f = 0`` at an episode's start.

**Anti-windup.** The observer never sees the unclipped command, only the applied force, so it
keeps estimating the true ``d`` while the actuators saturate (no integrator state runs away);
``d_hat`` itself is clamped to the force limits.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import njit, prange

from auv_follow_env.dynamics import recompiled
from auv_follow_env.layout import OBS_INDEX
from auv_follow_env.params import VehicleParams
from controllers.base import check_real

__all__ = ["DisturbanceObserver"]


class DisturbanceObserver:
    """Batched lumped-force observer for N envs (see the module docstring).

    Args:
        nominal: the nominal vehicle model the controller is given.
        dt: control step [s].
        force_limits: (F_u [N], F_v [N], F_r [N m]) of the actuators.
        time_constant: T_d of the low-pass filter [s] (> 0).
        thruster_tc_s: the thrusters' first-order lag [s] (0: none).
        thruster_rate: their rate limit, fraction of the force limit per second (inf: none).
    """

    def __init__(self, nominal: VehicleParams, dt: float, force_limits: tuple[float, float, float],
                 time_constant: float = 0.5, thruster_tc_s: float = 0.0, thruster_rate: float = math.inf) -> None:
        if not isinstance(nominal, VehicleParams):
            raise ValueError(f"nominal={nominal!r} is invalid: must be an auv_follow_env VehicleParams")
        check_real("dt", dt, 0.0, True)
        check_real("time_constant", time_constant, 0.0, True)
        lim = np.asarray(force_limits, dtype=np.float64)
        if lim.shape != (3,) or not np.all(np.isfinite(lim) & (lim > 0)):
            raise ValueError(f"force_limits={force_limits!r} is invalid: must be three finite numbers > 0")
        check_real("thruster_tc_s", thruster_tc_s, 0.0, False)
        if not (isinstance(thruster_rate, (int, float, np.integer, np.floating)) and not isinstance(thruster_rate, bool)
                and not math.isnan(thruster_rate) and thruster_rate > 0):
            raise ValueError(f"thruster_rate={thruster_rate!r} is invalid: must be a number > 0 (inf: no limit) [1/s]")
        dt, time_constant, thruster_tc_s = float(dt), float(time_constant), float(thruster_tc_s)
        self.alpha = 1.0 - math.exp(-dt / thruster_tc_s) if thruster_tc_s > 0 else 1.0
        self.rate_step = float(thruster_rate) * dt * lim  # max change of the applied force per step
        self.nominal = nominal
        self.dt = float(dt)
        self.limits = lim
        self.time_constant = float(time_constant)
        self.gain = self.dt / (self.time_constant + self.dt)
        self.d_hat: np.ndarray | None = None
        self._nu: np.ndarray | None = None
        self._n: np.ndarray | None = None
        self._f: np.ndarray | None = None

    def _model_terms(self, nu: np.ndarray, current: np.ndarray) -> np.ndarray:
        """n(nu): the nominal model's non-force terms M nu' - F (N, 3)."""
        m = self.nominal.m
        u, v, r = nu[:, 0], nu[:, 1], nu[:, 2]
        return np.stack([-self.nominal.X_u * (u - current[:, 0]) + m * v * r,
                         -self.nominal.Y_v * (v - current[:, 1]) - m * u * r,
                         -self.nominal.N_r * r], axis=-1)

    def update(self, nu: np.ndarray, current: np.ndarray, reset_mask: np.ndarray) -> np.ndarray:
        """Take the body velocity ``nu`` (N, 3) and body current (N, 2) at this step; return d_hat (N, 3).

        Envs in ``reset_mask`` (and all on the first call or a change of batch size) restart
        from d_hat = 0. Call :meth:`applied` after computing the command of this step.
        """
        nu = np.asarray(nu, dtype=np.float64)
        n = nu.shape[0]
        nm = self._model_terms(nu, np.asarray(current, dtype=np.float64))
        if self.d_hat is None or self.d_hat.shape[0] != n:
            self.d_hat = np.zeros((n, 3))
            self._nu, self._n, self._f = nu.copy(), nm.copy(), np.zeros((n, 3))
            return self.d_hat.copy()
        M = np.array([self.nominal.m, self.nominal.m, self.nominal.I_z])
        d_meas = M * (nu - self._nu) / self.dt - self._f - 0.5 * (nm + self._n)
        self.d_hat = np.clip(self.d_hat + self.gain * (d_meas - self.d_hat), -self.limits, self.limits)
        r = np.asarray(reset_mask, dtype=bool)
        self.d_hat[r] = 0.0
        self._f[r] = 0.0  # the thrusters start an episode at rest
        self._nu, self._n = nu.copy(), nm
        return self.d_hat.copy()

    @property
    def fusable(self) -> bool:
        """Whether :meth:`correct` applies (no thruster model: the applied force is the clipped
        command)."""
        return not self.models_thrusters

    def correct(self, obs: np.ndarray, reset_mask: np.ndarray, F: np.ndarray) -> None:
        """:meth:`update` on a float64 observation batch (N, W) (its body velocity and current),
        then ``F -= d_hat`` and :meth:`applied` (F), in one compiled pass: the same operations as
        ``F = F - update(nu, current, reset_mask); applied(F)``. Needs :attr:`fusable`."""
        if not self.fusable:
            raise ValueError("correct() needs an observer without a thruster model (fusable is False); "
                             "call update() and applied()")
        n = obs.shape[0]
        first = self.d_hat is None or self.d_hat.shape[0] != n
        if first:
            self.d_hat, self._nu, self._n, self._f = (np.zeros((n, 3)), np.empty((n, 3)), np.empty((n, 3)),
                                                      np.zeros((n, 3)))
        nom = self.nominal
        model = np.array([nom.m, nom.I_z, nom.X_u, nom.Y_v, nom.N_r], dtype=np.float64)
        pas = _correct_threads if n >= _THREADED_MIN_ENVS and numba.get_num_threads() > 1 else _correct_serial
        pas(obs, reset_mask, first, model, self.dt, self.gain, self.limits, self.d_hat, self._nu, self._n, self._f, F)

    @property
    def models_thrusters(self) -> bool:
        return self.alpha < 1.0 or all(map(math.isfinite, self.rate_step.tolist()))  # (per step: no numpy temporaries)

    def applied(self, command: np.ndarray) -> None:
        """Record this step's command (N, 3) [N, N, N m]: the observer keeps it clipped to the limits
        and, with a thruster model, passes it through the thrusters' lag and rate limit."""
        c = np.clip(np.asarray(command, dtype=np.float64), -self.limits, self.limits)
        if not self.models_thrusters or self._f is None or self._f.shape != c.shape:
            self._f = c
            return
        new = self._f + self.alpha * (c - self._f)
        self._f = np.clip(new, self._f - self.rate_step, self._f + self.rate_step)


_U, _V, _R = OBS_INDEX["u"], OBS_INDEX["v"], OBS_INDEX["r"]
_CU, _CV = OBS_INDEX["current_u"], OBS_INDEX["current_v"]
_THREADED_MIN_ENVS = 256  #: as the controllers' compiled passes (controllers.hierarchical.THREADED_MIN_ENVS)


@njit(cache=True, inline="always")
def _clip(x, lim):
    """np.clip(x, -lim, lim) (NaN stays NaN)."""
    if x < -lim:
        return -lim
    if x > lim:
        return lim
    return x


def _correct_all(a, reset, first, model, dt, gain, limits, d_hat, nu_prev, n_prev, f_prev, F):
    """:meth:`DisturbanceObserver.correct` env by env (``first``: the observer's first call on
    this batch, d_hat = 0)."""
    m, i_z, x_u, y_v, n_r = model[0], model[1], model[2], model[3], model[4]
    for i in prange(a.shape[0]):
        u, v, r = a[i, _U], a[i, _V], a[i, _R]
        n0 = -x_u * (u - a[i, _CU]) + m * v * r
        n1 = -y_v * (v - a[i, _CV]) - m * u * r
        n2 = -n_r * r
        if not first:
            for j, mj, nuj, nj in ((0, m, u, n0), (1, m, v, n1), (2, i_z, r, n2)):
                d_meas = mj * (nuj - nu_prev[i, j]) / dt - f_prev[i, j] - 0.5 * (nj + n_prev[i, j])
                d_hat[i, j] = _clip(d_hat[i, j] + gain * (d_meas - d_hat[i, j]), limits[j])
            if reset[i]:
                for j in range(3):
                    d_hat[i, j] = 0.0
        nu_prev[i, 0], nu_prev[i, 1], nu_prev[i, 2] = u, v, r
        n_prev[i, 0], n_prev[i, 1], n_prev[i, 2] = n0, n1, n2
        for j in range(3):
            F[i, j] = F[i, j] - d_hat[i, j]
            f_prev[i, j] = _clip(F[i, j], limits[j])


_correct_serial = njit(cache=True)(_correct_all)
_correct_threads = recompiled(_correct_all, "_correct_par", cache=True, parallel=True)
