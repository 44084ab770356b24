"""The paper's PID baseline (Sec. 4, Table 1): a conventional PID on the reference-tracking
error, with no prediction, no model compensation and no robust terms.

The paper gives no structure or gains; ours (docs/paper_notes.md suggested values): the position
error to the *delayed* reference e_I = p_ref - p, in the inertial frame, drives a PID per
axis whose output force is rotated into the body axes; heading has its own PID on
wrapToPi(psi_ref - psi). Derivatives are filtered (time constant 0.05 s); the integral is
a forward sum. On a v1 observation without a packet yet (``has_packet`` = 0) the reference
is the follower's own pose (hold position).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from auv_follow_env.layout import decode
from auv_follow_env.params import TaskSpec
from controllers.base import FilteredDerivative, ScriptedPolicy, check_real, wrap_to_pi
from controllers.hierarchical import no_packet_mask, predict_target, reference_point, zero_where

__all__ = ["PIDGains", "PIDController"]


@dataclass(frozen=True, kw_only=True)
class PIDGains:
    K_P: float = 14.0  #: position proportional gain [N/m]
    K_I: float = 3.6  #: position integral gain [N/(m s)]
    K_D: float = 12.0  #: position derivative gain [N s/m]
    K_P_psi: float = 1.15  #: heading proportional gain [N m/rad]
    K_I_psi: float = 0.29  #: heading integral gain [N m/(rad s)]
    K_D_psi: float = 0.53  #: heading derivative gain [N m s/rad]
    derivative_tc: float = 0.05  #: derivative filter time constant [s]

    def __post_init__(self) -> None:
        for n in ("K_P", "K_I", "K_D", "K_P_psi", "K_I_psi", "K_D_psi", "derivative_tc"):
            check_real(n, getattr(self, n), 0.0, False)


class PIDController(ScriptedPolicy):
    """Conventional PID baseline; see the module docstring for its structure."""

    name = "PID"

    def __init__(self, spec: TaskSpec, gains: PIDGains | None = None, name: str = "PID") -> None:
        super().__init__(spec)
        self.gains = gains if gains is not None else PIDGains()
        self.name = name
        self._diff = FilteredDerivative(spec.dt, self.gains.derivative_tc)
        self._integral: np.ndarray | None = None

    def reference(self, observation) -> np.ndarray:
        o = decode(np.atleast_2d(observation))
        pred = predict_target(o, self.spec.delay_s, enabled=False)
        ref = reference_point(pred[0], pred[1], pred[2], self.spec.p_d, self.spec.psi_d)
        return np.stack(zero_where(ref, no_packet_mask(o)), axis=-1)

    def forces(self, obs: np.ndarray, reset_mask: np.ndarray) -> np.ndarray:
        o = decode(obs)
        ref = self.reference(obs)
        c, s = o["cos_psi"], o["sin_psi"]
        ex = c * ref[:, 0] - s * ref[:, 1]  # inertial error p_ref - p
        ey = s * ref[:, 0] + c * ref[:, 1]
        e = np.stack([ex, ey, wrap_to_pi(ref[:, 2])], axis=-1)
        if self._integral is None or self._integral.shape != e.shape:
            self._integral = np.zeros_like(e)
        self._integral[reset_mask] = 0.0
        if reset_mask.any() or self._diff.prev is None:
            self._diff.reset(reset_mask, e)
        de = self._diff(e)
        self._integral += e * self.dt
        g = self.gains
        kp = np.array([g.K_P, g.K_P, g.K_P_psi])
        ki = np.array([g.K_I, g.K_I, g.K_I_psi])
        kd = np.array([g.K_D, g.K_D, g.K_D_psi])
        F = kp * e + ki * self._integral + kd * de
        fu = c * F[:, 0] + s * F[:, 1]  # rotate the inertial force into the body axes
        fv = -s * F[:, 0] + c * F[:, 1]
        return np.stack([fu, fv, F[:, 2]], axis=-1)
