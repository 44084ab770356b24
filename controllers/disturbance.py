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

import numpy as np

from auv_follow_env.params import VehicleParams

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
        if not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt > 0):
            raise ValueError(f"dt={dt!r} is invalid: must be a finite number > 0 [s]")
        if not (isinstance(time_constant, (int, float)) and math.isfinite(time_constant) and time_constant > 0):
            raise ValueError(f"time_constant={time_constant!r} is invalid: must be a finite number > 0 [s]")
        lim = np.asarray(force_limits, dtype=np.float64)
        if lim.shape != (3,) or not np.all(np.isfinite(lim) & (lim > 0)):
            raise ValueError(f"force_limits={force_limits!r} is invalid: must be three finite numbers > 0")
        if not (isinstance(thruster_tc_s, (int, float)) and math.isfinite(thruster_tc_s) and thruster_tc_s >= 0):
            raise ValueError(f"thruster_tc_s={thruster_tc_s!r} is invalid: must be a finite number >= 0 [s]")
        if not (isinstance(thruster_rate, (int, float)) and not math.isnan(thruster_rate) and thruster_rate > 0):
            raise ValueError(f"thruster_rate={thruster_rate!r} is invalid: must be a number > 0 (inf: no limit) [1/s]")
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
    def models_thrusters(self) -> bool:
        return self.alpha < 1.0 or bool(np.all(np.isfinite(self.rate_step)))

    def applied(self, command: np.ndarray) -> None:
        """Record this step's command (N, 3) [N, N, N m]: the observer keeps it clipped to the limits
        and, with a thruster model, passes it through the thrusters' lag and rate limit."""
        c = np.clip(np.asarray(command, dtype=np.float64), -self.limits, self.limits)
        if not self.models_thrusters or self._f is None or self._f.shape != c.shape:
            self._f = c
            return
        new = self._f + self.alpha * (c - self._f)
        self._f = np.clip(new, self._f - self.rate_step, self._f + self.rate_step)
