"""The paper's hierarchical law, written once: predictor (13)-(17), reference (21),
outer loop (25)-(30) and inner robust loop (31)-(35).

PROPOSED, ROBUST_ONLY and PRED_ONLY are this one law with Table 1's switches.

Everything is computed in the follower's body frame with the follower at the origin and
heading 0: the laws are equivariant under rotations and translations (K_p is a scalar
gain), so this equals the paper's inertial-frame computation followed by R(psi)^T, eq. (27).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from auv_follow_env.layout import decode
from auv_follow_env.params import TaskSpec
from controllers.base import FilteredDerivative, ScriptedPolicy, sat, wrap_to_pi

__all__ = ["Gains", "HierarchicalController", "predict_target", "reference_point", "outer_loop",
           "inner_loop"]


@dataclass(frozen=True, kw_only=True)
class Gains:
    """Gains of the hierarchical law: one set for the whole study (NOTES.md suggested values;
    the paper gives none). Shared by PROPOSED, ROBUST_ONLY and PRED_ONLY."""

    K_p: float = 1.0  #: outer-loop position gain, eq. (25) [1/s]
    K_psi: float = 1.0  #: heading gain, eq. (29) [1/s]
    K_u: float = 50.0  #: surge velocity gain, eq. (32) [N s/m]
    K_v: float = 50.0  #: sway velocity gain, eq. (33) [N s/m]
    K_r: float = 4.0  #: yaw-rate gain, eq. (34) [N m s]
    rho: tuple[float, float, float] = (4.0, 4.0, 0.3)  #: robust gains [N, N, N m]
    phi: tuple[float, float, float] = (0.04, 0.04, 0.04)  #: boundary layers [m/s, m/s, rad/s]
    derivative_tc: float = 0.05  #: filter time constant for u_d, v_d, r_d derivatives [s]

    def __post_init__(self) -> None:
        for n in ("K_p", "K_psi", "K_u", "K_v", "K_r"):
            v = getattr(self, n)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"{n}={v!r} is invalid: must be a finite number > 0")
        if len(self.rho) != 3 or any(not (np.isfinite(r) and r >= 0) for r in self.rho):
            raise ValueError(f"rho={self.rho!r} is invalid: must be three finite numbers >= 0")
        if len(self.phi) != 3 or any(not (np.isfinite(p) and p > 0) for p in self.phi):
            raise ValueError(f"phi={self.phi!r} is invalid: must be three finite numbers > 0")


def _rot(psi: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    c, s = np.cos(psi), np.sin(psi)
    return c * x - s * y, s * x + c * y


def predict_target(o: dict[str, np.ndarray], tau: float, enabled: bool = True):
    """Eqs. (13)-(17): first-order extrapolation of the delayed target over tau.

    Args:
        o: decoded observation (body frame).
        tau: delay [s].
        enabled: False gives eta_hat = eta_t(t - tau) (ROBUST_ONLY, Table 1).

    Returns:
        (x_hat, y_hat, psi_hat, u_hat, v_hat, r_hat), positions/heading relative to the follower.
    """
    psi_d = np.arctan2(o["target_sin_dpsi"], o["target_cos_dpsi"])
    u, v, r = o["target_u"], o["target_v"], o["target_r"]  # eq. (13)
    x, y = o["target_dx"], o["target_dy"]
    if enabled:
        vx, vy = _rot(psi_d, u, v)  # eq. (17)
        x, y, psi_d = x + vx * tau, y + vy * tau, psi_d + r * tau  # eqs. (14)-(16)
    return x, y, psi_d, u, v, r


def reference_point(x_hat, y_hat, psi_hat, p_d: tuple[float, float], psi_d: float):
    """Eq. (21): p_ref = p_hat + R(psi_hat) p_d, psi_ref = psi_hat + psi_d."""
    ox, oy = _rot(psi_hat, p_d[0], p_d[1])
    return x_hat + ox, y_hat + oy, psi_hat + psi_d


def outer_loop(ref, pred, p_d: tuple[float, float], gains: Gains):
    """Eqs. (22)-(30) in the follower frame: returns (u_d, v_d, r_d)."""
    x_ref, y_ref, psi_ref = ref
    _, _, psi_hat, u_hat, v_hat, r_hat = pred
    e_x, e_y = -x_ref, -y_ref  # eq. (22): e_p = p - p_ref with p = 0
    e_psi = wrap_to_pi(-psi_ref)  # eq. (24)
    fx, fy = _rot(psi_hat, u_hat, v_hat)
    ox, oy = _rot(psi_hat, p_d[0], p_d[1])
    vffx = fx - r_hat * oy  # eq. (26): J = [[0, -1], [1, 0]]
    vffy = fy + r_hat * ox
    u_d = -gains.K_p * e_x + vffx  # eqs. (25), (27)-(28)
    v_d = -gains.K_p * e_y + vffy
    r_d = -gains.K_psi * e_psi + r_hat  # eq. (29)
    return u_d, v_d, r_d


def inner_loop(o: dict[str, np.ndarray], desired, desired_dot, nominal, gains: Gains, robust: bool):
    """Eqs. (31)-(35): (F_u, F_v, F_r) [N, N, N m]. ``robust=False`` sets rho = 0 (PRED_ONLY)."""
    u, v, r = o["u"], o["v"], o["r"]
    u_d, v_d, r_d = desired
    ud_dot, vd_dot, rd_dot = desired_dot
    e_u, e_v, e_r = u - u_d, v - v_d, r - r_d  # eq. (31)
    u_r = u - o["current_u"]  # eq. (9), with the measured current
    v_r = v - o["current_v"]
    m, I_z = nominal.m, nominal.I_z
    rho = gains.rho if robust else (0.0, 0.0, 0.0)
    phi = gains.phi
    F_u = m * ud_dot + nominal.X_u * u_r - m * v * r - gains.K_u * e_u - rho[0] * sat(e_u / phi[0])  # (32)
    F_v = m * vd_dot + nominal.Y_v * v_r + m * u * r - gains.K_v * e_v - rho[1] * sat(e_v / phi[1])  # (33)
    F_r = I_z * rd_dot + nominal.N_r * r - gains.K_r * e_r - rho[2] * sat(e_r / phi[2])  # (34)
    return F_u, F_v, F_r


class HierarchicalController(ScriptedPolicy):
    """The predictive robust tracking controller and its ablations (Table 1).

    Args:
        spec: the env's TaskSpec (tau, p_d, psi_d, nominal model, dt, force limits).
        prediction: delay prediction (Sec. 3.3) on/off.
        robust: robust terms rho sat(e/phi) in (32)-(34) on/off.
        gains: :class:`Gains`; defaults shared by all variants.
        name: label used in tables.
    """

    def __init__(self, spec: TaskSpec, *, prediction: bool = True, robust: bool = True,
                 gains: Gains | None = None, name: str | None = None) -> None:
        super().__init__(spec)
        self.prediction = bool(prediction)
        self.robust = bool(robust)
        self.gains = gains if gains is not None else Gains()
        self.name = name or f"hierarchical(prediction={self.prediction}, robust={self.robust})"
        self._diff = FilteredDerivative(spec.dt, self.gains.derivative_tc)

    def _generate(self, o: dict[str, np.ndarray]):
        pred = predict_target(o, self.spec.delay_s, self.prediction)
        ref = reference_point(pred[0], pred[1], pred[2], self.spec.p_d, self.spec.psi_d)
        return pred, ref

    def reference(self, observation) -> np.ndarray:
        o = decode(np.atleast_2d(observation))
        _, ref = self._generate(o)
        return np.stack(ref, axis=-1)

    def forces(self, obs: np.ndarray, reset_mask: np.ndarray) -> np.ndarray:
        o = decode(obs)
        pred, ref = self._generate(o)
        desired = outer_loop(ref, pred, self.spec.p_d, self.gains)
        d = np.stack(desired, axis=-1)
        if reset_mask.any() or self._diff.prev is None:
            self._diff.reset(reset_mask, d)
        d_dot = self._diff(d)
        F = inner_loop(o, desired, (d_dot[:, 0], d_dot[:, 1], d_dot[:, 2]), self.spec.nominal,
                       self.gains, self.robust)
        return np.stack(F, axis=-1)
