"""Target estimator (ours, not the paper's): a batched Kalman filter over the target's state,
fed by the timestamped fixes in the observation and propagated to the *present* every step.

It replaces the paper's memoryless extrapolation (13)-(17) for the controllers that want it
(``PROPOSED_KF``, ``PROPOSED_KF_DOB``, ``MPC``; :mod:`controllers.__init__`).

**Frames.** The observation has no absolute follower position, so the estimator builds a
local *odometry frame*: compass-aligned axes, origin at the follower's position at the
episode's first observation, position integrated from the follower's exact ground velocity
R(psi) [u, v] with the trapezoid rule between samples. A fix is ``p_odom + R(psi) [dx, dy]``
with heading ``psi + dpsi``; the present estimate is returned both in that frame and relative
to the follower in its body frame (what the hierarchical law and the MPC use).

**Timing.** v0 (16 fields): every observation carries a new fix exactly ``tau`` old. v1
(20 fields): a fix is new on steps with ``new_packet`` = 1 (and the packet held when the
episode starts, or when the filter has none yet), measured at ``now - packet_age``; nothing
is known while ``has_packet`` = 0. The filter state is held at the measurement time
``t_fix`` of the newest fix used. On a step with a newer fix the state is predicted from
``t_fix`` to the fix's time and updated; the first fix initialises it; a fix not newer than
``t_fix`` (stale or out of order) is ignored; a step without a fix only predicts. Then, every
step, the state is predicted from ``t_fix`` to now *without* changing the filter: holding
the state at the last fix (instead of at now) is what makes a late fix an ordinary update,
with no retrodiction.

**Models** (continuous time, exact mean propagation; ``q_*`` are white-noise intensities):

| model | state | motion | noise on |
|---|---|---|---|
| ``CV`` | x, y, psi, vx, vy, r | constant inertial velocity and yaw rate | vx, vy (q_acc), r (q_yaw) |
| ``CT`` | x, y, psi, u, v, r | constant body velocity and turn rate (coordinated turn) | u, v (q_acc), r (q_yaw) |
| ``CTA`` | CT + a, alpha | CT, constant accelerations a = u', alpha = r' | as CT; a (q_jerk), alpha (q_yaw_acc) |
| ``OU`` | CT + u_bar | u reverts to u_bar (time constant tau_u), r to 0 (tau_r) | u, v (q_acc), r (q_yaw) |
| ``OU0`` | x, y, psi, u, r, u_bar | OU with no sway (v = 0: the target does not slip sideways) | u (q_acc), r (q_yaw) |

OU is the v1 tiers' own target model (Ornstein-Uhlenbeck surge speed about an unknown mean
u_bar and turn rate about 0): over a long gap between fixes its prediction relaxes to a
straight line at the mean speed instead of extrapolating a turn for ever. ``OU0`` (the tiers'
default since 0.2.0) adds the target's structure: its sway velocity is zero (eq. (10) with
v_t = 0 for every target simulated here), so sway is not a state and the fix's reported sway,
pure noise, is not used; the measurement is (x, y, psi, u, r). It runs in numba
(:mod:`controllers._ou0`: closed-form Jacobian, the present advanced one control step at a time,
the present covariance only when asked for) and has two options, both off on the tiers because
they did not help on the training seeds (results/estimator_study.md): ``adapt`` (the OU
variances per episode from the received fixes) and ``smooth_s`` (a fix's jump of the returned
pose decays instead of stepping). On the training seeds 500-599, OU0 lowers the estimate's
error of the present reference point (IQM) by 19 % (Easy), 18 % (Medium) and 10 % (Hard)
against OU.

CV is a linear KF. CT, CTA, OU and OU0 are EKFs: the mean is propagated exactly (the position is
the integral of the body velocity along the heading, psi0 + r s + alpha s^2 / 2 or
psi0 + r0 tau_r (1 - exp(-s / tau_r)),
evaluated by 16-point Gauss-Legendre quadrature: exact to rounding for the spans met here);
the Jacobian is taken by complex-step differentiation of that same propagation (exact to
rounding, no hand-written derivative to get wrong); the discrete process noise is
int_0^T Phi(s) Q_c Phi(s)^T ds by Simpson's rule with Phi at the mean (exact for CV).

The measurement is the full target state the link reports (position, heading, body
velocity; CV converts the body velocity to inertial with the measured heading), so H = [I 0].
Its noise: sigma_pos + sigma_pos_per_m * range on x and y, sigma_psi, sigma_vel, sigma_r.

**Why our own filter and not filterpy:** filterpy's ``KalmanFilter``/``ExtendedKalmanFilter``
hold one filter each, in Python objects; the controllers here run hundreds of envs per call
(``evaluate_batched``, the vector env), and a loop of filterpy objects per step would cost
more than the physics. This filter is plain numpy over a leading batch axis (batched
``solve``), about a hundred lines of arithmetic.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

from auv_follow_env.layout import OBS_DIM, OBS_DIM_V1, decode
from auv_follow_env.params import TaskSpec
from controllers import _imm, _leader_imm, _leader_pf, _ou0
from controllers.base import ObservationHold, as_batch, as_mask

__all__ = ["EstimatorConfig", "TargetEstimate", "TargetEstimator", "MODELS", "propagate_mean"]

#: model name -> state dimension
MODELS: dict[str, int] = {"CV": 6, "CT": 6, "CTA": 8, "OU": 7, "OU0": 6, "IMM": 5, "LEADER_PF": 5, "LEADER_IMM": 5}

#: the model used on the v1 tiers: their target's own (OU speed and turn rate) with its structure
#: (no sway), in numba (:mod:`controllers._ou0`)
TIER_MODEL = "OU0"

_GL_X, _GL_W = np.polynomial.legendre.leggauss(16)
_CSTEP = 1e-30  # complex-step size (any tiny number: no subtractive cancellation)



def _leader_moments(mid) -> tuple[float, float, float, float]:
    """An OU target with the second moments of a Leader tier's target (its ranges' midpoints):
    the speed's and the turn rate's stationary std (time-share-weighted over the modes, wobbles
    included) and correlation times of the order of a mode's mean duration. What a linear filter
    can be told of the leader without fitting it; the generic and model-aware estimators of the
    Leader tiers are separate."""
    share = mid("leader_survey_share", 0.0)
    speed = mid("leader_modes", 1.0) >= 2
    vc, w = mid("leader_cruise_speed", 0.5), mid("leader_turn_rate", 0.15)
    mc, mt = mid("leader_cruise_mean_s", 10.0), mid("leader_turn_mean_s", 6.0)
    # wander: time shares of the modes (visit shares times mean durations)
    vis = [(0.5, mc, vc, 0.0), (0.15 if speed else 0.25, mt, vc, w), (0.15 if speed else 0.25, mt, vc, -w)]
    if speed:
        vis += [(0.1, mid("leader_loiter_mean_s", 8.0), mid("leader_loiter_speed", 0.1), 0.0),
                (0.1, mid("leader_sprint_mean_s", 5.0), mid("leader_sprint_speed", 0.9), 0.0)]
    tot = sum(v * m for v, m, _, _ in vis)
    shares = [(v * m / tot, u, r) for v, m, u, r in vis]
    eu = sum(q * u for q, u, _ in shares)
    var_u = sum(q * (u - eu) ** 2 for q, u, _ in shares)
    var_r = sum(q * r * r for q, _, r in shares)
    # survey: legs and U-turns (time shares by length / speed and pi / rate)
    ws, leg = mid("leader_uturn_rate", 0.25), mid("leader_leg_m", 10.0)
    t_leg, t_turn = leg / vc, math.pi / ws
    var_r_s = t_turn / (t_leg + t_turn) * ws * ws
    var_u = (1 - share) * var_u + share * (1 - share) * (eu - vc) ** 2 + mid("leader_wobble_speed", 0.02) ** 2
    var_r = (1 - share) * var_r + share * var_r_s + mid("leader_wobble_rate", 0.01) ** 2
    tau_u = (1 - share) * mc + share * t_leg
    tau_r = (1 - share) * mt + share * t_turn
    return math.sqrt(var_u), tau_u, math.sqrt(var_r), tau_r


#: EstimatorConfig's real settings: (low, high, low end open, unit). The upper ends are far beyond any
#: sensible setting (a sigma of 100 m, a correlation time of 11 days) and keep every filter's
#: arithmetic finite: at 1e308 a process noise overflowed to NaN actions (tests/test_hardening4.py
#: runs each model with every setting at its ends)
_REAL_BOUNDS: dict[str, tuple[float, float, bool, str]] = {
    "sigma_pos": (0.0, 100.0, True, "m"), "sigma_pos_per_m": (0.0, 1.0, False, "m/m"),
    "sigma_psi": (0.0, math.pi, True, "rad"), "sigma_vel": (0.0, 10.0, True, "m/s"),
    "sigma_r": (0.0, 10.0, True, "rad/s"),
    "q_acc": (0.0, 100.0, False, "m^2/s^3"), "q_yaw": (0.0, 10.0, False, "rad^2/s^3"),
    "q_jerk": (0.0, 100.0, False, "m^2/s^5"), "q_yaw_acc": (0.0, 10.0, False, "rad^2/s^5"),
    "sigma_acc0": (0.0, 100.0, False, "m/s^2"), "sigma_yaw_acc0": (0.0, 10.0, False, "rad/s^2"),
    "tau_u": (0.0, 1e6, True, "s"), "tau_r": (0.0, 1e6, True, "s"), "sigma_ubar0": (0.0, 10.0, False, "m/s"),
    "adapt_n0": (0.0, 1e6, False, "fixes"), "smooth_s": (0.0, 1e4, False, "s"),
    "imm_q_u": (0.0, 100.0, False, "m^2/s^3"), "imm_q_r": (0.0, 10.0, False, "rad^2/s^3"),
    "imm_q_h": (0.0, 10.0, False, "rad^2/s"), "imm_tau_s": (0.0, 1e6, True, "s"),
    "limm_q_u": (0.0, 100.0, False, "m^2/s^3"), "limm_q_h": (0.0, 10.0, False, "rad^2/s"),
    "limm_q_r": (0.0, 10.0, False, "rad^2/s^3"), "limm_sojourn": (0.0, 100.0, True, "-"),
    "pf_temper": (0.0, 1e3, True, "-"), "pf_drift": (0.0, 1e3, False, "m^2/s"),
}
#: EstimatorConfig's whole-number settings: (low, high)
_WHOLE_BOUNDS: dict[str, tuple[int, int]] = {"limm_shape": (1, 4), "pf_particles": (1, 100_000),
                                              "imm_q_panels": (1, 64)}


@dataclass(frozen=True, kw_only=True)
class EstimatorConfig:
    """Settings of :class:`TargetEstimator` (all ours). The defaults are for v0's exact, every-step
    fixes: the q's were picked from a grid (CT and CTA, q_acc 1e-5..1e-2, q_yaw 1e-6..1e-3,
    q_jerk 1e-5..1e-1, q_yaw_acc 1e-6..1e-2) by the steady-state true-reference RMSE of
    PROPOSED_KF_DOB on seeds 100-119 of S1-S4 (never the scored seeds 0-19); the result is
    flat in q_acc and q_yaw, and prefers large q_jerk / q_yaw_acc (trust the newest fixes'
    accelerations: the fixes are exact). The v1 tiers use :meth:`for_spec`."""

    model: str = "CTA"  #: one of :data:`MODELS`
    sigma_pos: float = 0.01  #: fix position noise at zero range [m]
    sigma_pos_per_m: float = 0.0  #: growth of the position noise with range [m/m]
    sigma_psi: float = 0.01  #: fix heading noise [rad]
    sigma_vel: float = 0.01  #: fix velocity noise [m/s]
    sigma_r: float = 0.005  #: fix yaw-rate noise [rad/s]
    q_acc: float = 1e-5  #: white-noise intensity on the velocities u, v (vx, vy) [m^2/s^3]
    q_yaw: float = 1e-6  #: white-noise intensity on the yaw rate [rad^2/s^3]
    q_jerk: float = 0.1  #: CTA: white-noise intensity on the surge acceleration [m^2/s^5]
    q_yaw_acc: float = 0.01  #: CTA: white-noise intensity on the yaw acceleration [rad^2/s^5]
    sigma_acc0: float = 0.05  #: CTA: prior std of the surge acceleration at the first fix [m/s^2]
    sigma_yaw_acc0: float = 0.02  #: CTA: prior std of the yaw acceleration at the first fix [rad/s^2]
    tau_u: float = 20.0  #: OU: correlation time of the surge speed [s] (> 0)
    tau_r: float = 10.0  #: OU: correlation time of the turn rate [s] (> 0)
    sigma_ubar0: float = 0.05  #: OU: prior std of the mean speed about the first fix's speed [m/s]
    adapt: bool = False  #: OU0: estimate the OU variances of speed and turn rate per episode from the fixes
    adapt_n0: float = 5.0  #: OU0: weight of the prior variance in that estimate, in fixes [-]
    smooth_s: float = 0.0  #: OU0: a fix's jump of the returned pose decays with this time constant [s] (0: off)
    imm_q_u: float = 0.01  #: IMM: white-noise intensity on the speed (both models) [m^2/s^3]
    imm_q_r: float = 0.001  #: IMM: white-noise intensity on the turn rate (CT) [rad^2/s^3]
    imm_q_h: float = 0.001  #: IMM: white-noise intensity on the heading (CV) [rad^2/s]
    imm_tau_s: float = 15.0  #: IMM: mean time between switches of the CV / CT models [s] (> 0)
    imm_gate: bool = True  #: IMM: a fix's position outside the 99.9 % chi-square gate of both models is not used
    #: IMM: panels of the composite Simpson rule for the process noise, 1-64 (1: the plain rule, nodes 0, T/2, T;
    #: experiments/quadrature_study.py measured what 16 change on the Leader tiers)
    imm_q_panels: int = 1
    limm_q_u: float = 0.001  #: LEADER_IMM: white-noise intensity on the speed [m^2/s^3]
    limm_q_h: float = 0.01  #: LEADER_IMM: white-noise intensity on the heading [rad^2/s]
    limm_q_r: float = 0.0001  #: LEADER_IMM: white-noise intensity on the turn rate [rad^2/s^3]
    limm_sojourn: float = 1.0  #: LEADER_IMM: the modes' leaving rates (1 / mean duration) times this (> 0) [-]
    limm_shape: int = 4  #: LEADER_IMM: the sojourns' Gamma shape, 1-4 (the generator's: 4; 1: a Markov chain)
    pf_particles: int = 1000  #: LEADER_PF: particles per env (the model-aware filter of a Leader tier)
    pf_temper: float = 4.0  #: LEADER_PF: the heading, speed and turn-rate likelihoods' variances times this
    pf_drift: float = 0.03  #: LEADER_PF: position likelihood variance added per second between fixes [m^2/s]

    def __post_init__(self) -> None:
        if not isinstance(self.model, str) or self.model not in MODELS:
            raise ValueError(f"model={self.model!r} is invalid: must be one of {list(MODELS)}")
        for b in ("adapt", "imm_gate"):
            v = getattr(self, b)
            if not isinstance(v, (bool, np.bool_)):
                raise ValueError(f"{b}={v!r} is invalid: must be True or False")
            object.__setattr__(self, b, bool(v))  # a numpy bool is stored as Python's
        for name, (lo, hi) in _WHOLE_BOUNDS.items():
            v = getattr(self, name)
            if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)) or not lo <= v <= hi:
                raise ValueError(f"{name}={v!r} is invalid: must be a whole number in [{lo}, {hi}] (int or numpy "
                                 f"integer)")
            object.__setattr__(self, name, int(v))
        for f in fields(self):
            if f.name not in _REAL_BOUNDS:
                continue
            lo, hi, lo_open, unit = _REAL_BOUNDS[f.name]
            v = getattr(self, f.name)
            inf_ok = f.name in ("tau_u", "tau_r") and self.model == "OU0"
            allowed = (f"a number in {'(' if lo_open else '['}{lo:g}, {hi:g}] [{unit}]"
                       + (" (or inf with model='OU0')" if f.name in ("tau_u", "tau_r") else ""))
            if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, float, np.integer, np.floating)):
                raise ValueError(f"{f.name}={v!r} is invalid: must be {allowed}, got a {type(v).__name__}")
            x = float(v)
            ok = (x > lo if lo_open else x >= lo) and (x <= hi or (inf_ok and x == math.inf))
            if not ok:  # NaN fails both comparisons
                raise ValueError(f"{f.name}={v!r} is invalid: must be {allowed}")
            object.__setattr__(self, f.name, x)  # a numpy scalar is stored as a Python float
        if (self.adapt or self.smooth_s) and self.model != "OU0":
            raise ValueError(f"adapt={self.adapt!r} / smooth_s={self.smooth_s!r} need model='OU0' "
                             f"(got model={self.model!r})")

    @property
    def dim(self) -> int:
        return MODELS[self.model]

    @classmethod
    def for_spec(cls, spec: TaskSpec) -> EstimatorConfig:
        """The settings for a task: v0 and custom v1 tasks get the defaults; a v1 tier gets
        noise levels from its *published* table (:mod:`auv_follow_env.tiers`: what a follower
        knows of its modem / USBL and of the target class, the middle of each drawn range):
        fix noise as the link's, and the OU0 model (OU without sway) with the target's correlation times and
        process noise q = 2 std^2 / correlation time (the white-noise intensity of an OU
        process). Nothing here is fitted to test seeds.

        Raises:
            ValueError: if ``spec`` is not a TaskSpec.
        """
        if not isinstance(spec, TaskSpec):
            raise ValueError(f"spec={spec!r} is invalid: must be an auv_follow_env TaskSpec")
        tier = getattr(spec, "tier", None)
        if tier is None:
            return cls()
        from auv_follow_env.tiers import ALL_TIERS

        t = ALL_TIERS[tier]

        def mid(name: str, default: float) -> float:
            if name in t.ranges:
                lo, hi = t.ranges[name]
                return 0.5 * (lo + hi)
            return float(t.fixed.get(name, default))

        def pos(x: float, floor: float) -> float:
            return max(x, floor)

        if mid("leader_modes", 0.0) > 0:
            std_u, tau_u, std_r, tau_r = _leader_moments(mid)
            fx = dict(target_speed_std=std_u, target_speed_corr_s=tau_u, target_yaw_rate_std=std_r,
                      target_yaw_rate_corr_s=tau_r)
            base = mid

            def mid(name: str, default: float) -> float:  # noqa: F811  (the OU fields from the leader's moments)
                return fx[name] if name in fx else base(name, default)

        return cls(model=TIER_MODEL, sigma_pos=pos(mid("fix_sigma_m", 0.0), 1e-3),
                   sigma_pos_per_m=mid("fix_sigma_per_m", 0.0), sigma_psi=pos(mid("heading_sigma_rad", 0.0), 1e-3),
                   sigma_vel=pos(mid("velocity_sigma_mps", 0.0), 1e-3),
                   sigma_r=pos(mid("yaw_rate_sigma_radps", 0.0), 1e-4),
                   q_acc=2 * mid("target_speed_std", 0.0) ** 2 / mid("target_speed_corr_s", 20.0) + 1e-6,
                   q_yaw=2 * mid("target_yaw_rate_std", 0.0) ** 2 / mid("target_yaw_rate_corr_s", 10.0) + 1e-7,
                   tau_u=mid("target_speed_corr_s", 20.0), tau_r=mid("target_yaw_rate_corr_s", 10.0),
                   sigma_ubar0=pos(mid("target_speed_std", 0.05), 1e-3))

    def process_intensity(self) -> np.ndarray:
        """Diagonal of the continuous white-noise intensity Q_c over the state."""
        q = [0.0, 0.0, 0.0, self.q_acc, self.q_acc, self.q_yaw]
        if self.model == "CTA":
            q += [self.q_jerk, self.q_yaw_acc]
        if self.model == "OU":
            q += [1e-9]  # the mean speed: a constant, kept barely adaptable
        return np.asarray(q)

    def prior_std(self) -> list[float]:
        """Prior std of the states beyond the measured six, at the first fix."""
        return {"CTA": [self.sigma_acc0, self.sigma_yaw_acc0], "OU": [self.sigma_ubar0]}.get(self.model, [])


def propagate_mean(model: str, x: np.ndarray, T: np.ndarray, taus: tuple[float, float] = (20.0, 10.0)) -> np.ndarray:
    """Exact noise-free motion of the state ``x`` (..., n) over ``T`` (...,) seconds.

    ``taus`` = (tau_u, tau_r) of the OU model. Works on complex arrays (used for the
    complex-step Jacobian).
    """
    if model == "OU0":
        tu, tr = taus
        s = 0.5 * T[..., None] * (1.0 + _GL_X)
        w = 0.5 * T[..., None] * _GL_W
        eu = np.exp(-s / tu) if math.isfinite(tu) else np.ones_like(s)
        gr = -tr * np.expm1(-s / tr) if math.isfinite(tr) else s
        psi = x[..., 2, None] + x[..., 4, None] * gr
        u = x[..., 5, None] + (x[..., 3, None] - x[..., 5, None]) * eu
        out = x.copy()
        out[..., 0] = x[..., 0] + np.sum(w * u * np.cos(psi), axis=-1)
        out[..., 1] = x[..., 1] + np.sum(w * u * np.sin(psi), axis=-1)
        euT = np.exp(-T / tu) if math.isfinite(tu) else np.ones_like(T)
        grT = -tr * np.expm1(-T / tr) if math.isfinite(tr) else T
        erT = np.exp(-T / tr) if math.isfinite(tr) else np.ones_like(T)
        out[..., 2] = x[..., 2] + x[..., 4] * grT
        out[..., 3] = x[..., 5] + (x[..., 3] - x[..., 5]) * euT
        out[..., 4] = x[..., 4] * erT
        return out
    if model == "OU":
        tu, tr = taus
        s = 0.5 * T[..., None] * (1.0 + _GL_X)
        w = 0.5 * T[..., None] * _GL_W
        ub = x[..., 6, None]
        psi = x[..., 2, None] + x[..., 5, None] * tr * (1.0 - np.exp(-s / tr))
        u = ub + (x[..., 3, None] - ub) * np.exp(-s / tu)
        v = x[..., 4, None]
        c, sn = np.cos(psi), np.sin(psi)
        out = x.copy()
        out[..., 0] = x[..., 0] + np.sum(w * (u * c - v * sn), axis=-1)
        out[..., 1] = x[..., 1] + np.sum(w * (u * sn + v * c), axis=-1)
        out[..., 2] = x[..., 2] + x[..., 5] * tr * (1.0 - np.exp(-T / tr))
        out[..., 3] = x[..., 6] + (x[..., 3] - x[..., 6]) * np.exp(-T / tu)
        out[..., 5] = x[..., 5] * np.exp(-T / tr)
        return out
    if model == "CV":
        out = x.copy()
        out[..., 0] = x[..., 0] + x[..., 3] * T
        out[..., 1] = x[..., 1] + x[..., 4] * T
        out[..., 2] = x[..., 2] + x[..., 5] * T
        return out
    a = x[..., 6] if model == "CTA" else 0.0
    al = x[..., 7] if model == "CTA" else 0.0
    s = 0.5 * T[..., None] * (1.0 + _GL_X)  # (..., G) quadrature nodes on [0, T]
    w = 0.5 * T[..., None] * _GL_W
    a_ = a[..., None] if model == "CTA" else 0.0
    al_ = al[..., None] if model == "CTA" else 0.0
    psi = x[..., 2, None] + x[..., 5, None] * s + 0.5 * al_ * s * s
    u = x[..., 3, None] + a_ * s
    v = x[..., 4, None]
    c, sn = np.cos(psi), np.sin(psi)
    out = x.copy()
    out[..., 0] = x[..., 0] + np.sum(w * (u * c - v * sn), axis=-1)
    out[..., 1] = x[..., 1] + np.sum(w * (u * sn + v * c), axis=-1)
    out[..., 2] = x[..., 2] + x[..., 5] * T + 0.5 * al * T * T
    out[..., 3] = x[..., 3] + a * T
    out[..., 5] = x[..., 5] + al * T
    return out


def _jacobian(model: str, x: np.ndarray, T: np.ndarray, taus: tuple[float, float]) -> np.ndarray:
    """d propagate_mean / d x, (N, n, n), by complex-step differentiation."""
    n = x.shape[-1]
    X = x[:, None, :] + 1j * _CSTEP * np.eye(n)[None]  # row j perturbs state j
    Y = propagate_mean(model, X, np.repeat(T[:, None], n, axis=1), taus)
    return np.imag(Y).transpose(0, 2, 1) / _CSTEP  # [i, j] = d y_i / d x_j


def _predict(model: str, x: np.ndarray, P: np.ndarray, T: np.ndarray, qc: np.ndarray,
             taus: tuple[float, float], with_cov: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """Mean and covariance after ``T`` (N,) seconds: P' = Phi P Phi^T + Q(T)."""
    xm = propagate_mean(model, x, T, taus)
    if not with_cov:
        return xm, None
    F = _jacobian(model, x, T, taus)
    Fh = _jacobian(model, x, 0.5 * T, taus)
    Qc = np.diag(qc)
    Q = (T / 6.0)[:, None, None] * (Qc[None] + 4.0 * Fh @ Qc @ Fh.transpose(0, 2, 1)
                                    + F @ Qc @ F.transpose(0, 2, 1))
    Pn = F @ P @ F.transpose(0, 2, 1) + Q
    return xm, 0.5 * (Pn + Pn.transpose(0, 2, 1))


@dataclass
class TargetEstimate:
    """The present target estimate of N envs (arrays over the batch).

    ``valid`` is False for envs without any fix yet (everything else is 0 there).
    ``x, y, psi``: odometry frame [m, m, rad]; ``rel_x, rel_y, rel_psi``: relative to the
    follower in its body frame (``rel_psi`` wrapped into (-pi, pi]); ``u, v, r``: target body
    velocity [m/s, m/s, rad/s]; ``state`` and ``cov``: the model's state and covariance at now
    (N, n) and (N, n, n) (CV: inertial velocities); ``age``: now minus the newest fix's
    measurement time [s].
    """

    valid: np.ndarray
    x: np.ndarray
    y: np.ndarray
    psi: np.ndarray
    u: np.ndarray
    v: np.ndarray
    r: np.ndarray
    rel_x: np.ndarray
    rel_y: np.ndarray
    rel_psi: np.ndarray
    state: np.ndarray
    cov: np.ndarray | None
    age: np.ndarray

    def as_prediction(self) -> tuple[np.ndarray, ...]:
        """(x_hat, y_hat, psi_hat, u_hat, v_hat, r_hat) relative to the follower: the tuple
        :func:`controllers.hierarchical.predict_target` returns."""
        return self.rel_x, self.rel_y, self.rel_psi, self.u, self.v, self.r


@dataclass
class _FilterState:
    t_now: np.ndarray  # (N,) time since the episode's first observation [s]
    odom: np.ndarray  # (N, 2) follower position in the odometry frame [m]
    vel: np.ndarray  # (N, 2) follower inertial velocity at the last sample [m/s]
    psi_f: np.ndarray  # (N,) follower heading at the last sample [rad]
    init: np.ndarray  # (N,) a fix has been used
    t_fix: np.ndarray  # (N,) measurement time of the filter state [s]
    x: np.ndarray  # (N, n)
    P: np.ndarray  # (N, n, n)

    def copy(self) -> _FilterState:
        return _FilterState(*(getattr(self, f.name).copy() for f in fields(self)))


@dataclass
class _OU0State:
    """The OU0 kernel's per-env arrays (:func:`controllers._ou0.ou0_step`)."""

    t_now: np.ndarray  # (N,) [s]
    odom: np.ndarray  # (N, 2) [m]
    vel: np.ndarray  # (N, 2) [m/s]
    psi_f: np.ndarray  # (N,) [rad]
    init: np.ndarray  # (N,) bool
    t_fix: np.ndarray  # (N,) [s]
    x: np.ndarray  # (N, 6) filter state at t_fix
    P: np.ndarray  # (N, 6, 6)
    xp: np.ndarray  # (N, 6) present state
    Pp: np.ndarray  # (N, 6, 6)
    stale: np.ndarray  # (N,) bool: Pp is to be recomputed when next wanted
    dlt: np.ndarray  # (N, 3) smoothing offset of the returned pose (odometry frame)
    stats: np.ndarray  # (N, NS) fix statistics for the adaptive noise

    @classmethod
    def fresh(cls, n: int) -> _OU0State:
        eye = np.tile(np.eye(6), (n, 1, 1))
        return cls(np.zeros(n), np.zeros((n, 2)), np.zeros((n, 2)), np.zeros(n), np.zeros(n, dtype=bool),
                   np.zeros(n), np.zeros((n, 6)), eye, np.zeros((n, 6)), eye.copy(), np.ones(n, dtype=bool),
                   np.zeros((n, 3)), np.zeros((n, _ou0.NS)))

    def copy(self) -> _OU0State:
        return _OU0State(*(getattr(self, f.name).copy() for f in fields(self)))


@dataclass
class _IMMState:
    """The IMM kernel's per-env arrays (:func:`controllers._imm.imm_step`)."""

    t_now: np.ndarray  # (N,) [s]
    odom: np.ndarray  # (N, 2) [m]
    vel: np.ndarray  # (N, 2) [m/s]
    psi_f: np.ndarray  # (N,) [rad]
    init: np.ndarray  # (N,) bool
    t_fix: np.ndarray  # (N,) [s]
    m: np.ndarray  # (N, 2, 5) the models' means at t_fix
    P: np.ndarray  # (N, 2, 5, 5)
    mu: np.ndarray  # (N, 2) mode probabilities (CV, CT)
    ng: np.ndarray  # (N, 1) int64: gated fixes in a row
    gap: np.ndarray  # (N,) [rad] the models' heading difference, wrapped (kept from fix to fix)

    @classmethod
    def fresh(cls, n: int) -> _IMMState:
        return cls(np.zeros(n), np.zeros((n, 2)), np.zeros((n, 2)), np.zeros(n), np.zeros(n, dtype=bool),
                   np.zeros(n), np.zeros((n, 2, 5)), np.tile(np.eye(5), (n, 2, 1, 1)), np.full((n, 2), 0.5),
                   np.zeros((n, 1), dtype=np.int64), np.zeros(n))

    @property
    def x(self) -> np.ndarray:  # (the batch size, as the other states' x)
        return self.m[:, 0]

    def copy(self) -> _IMMState:
        return _IMMState(*(getattr(self, f.name).copy() for f in fields(self)))


@dataclass
class _LIMMState:
    """The model-aware IMM kernel's per-env arrays (:func:`controllers._leader_imm.limm_step`)."""

    t_now: np.ndarray  # (N,) [s]
    odom: np.ndarray  # (N, 2) [m]
    vel: np.ndarray  # (N, 2) [m/s]
    psi_f: np.ndarray  # (N,) [rad]
    init: np.ndarray  # (N,) bool
    t_fix: np.ndarray  # (N,) [s]
    m: np.ndarray  # (N, K, 5) the models' means at t_fix
    P: np.ndarray  # (N, K, 5, 5)
    mu: np.ndarray  # (N, K) mode probabilities at t_fix
    ag: np.ndarray  # (N, K) [s] the modes' ages at t_fix
    ng: np.ndarray  # (N, 1) int64: gated fixes in a row
    om: np.ndarray  # (N, 2) [rad/s] the env's turn and U-turn rates
    pm: np.ndarray  # (N, K, 4) the models' means now
    pcs: np.ndarray  # (N, K, 2) cos, sin of their headings now
    pc: np.ndarray  # (N, K) mode probabilities now
    sq: np.ndarray  # (N, K) exp(-k lam T) of each mode (T: since the fix)
    sp0: np.ndarray  # (N, K) 1 / each mode's survival polynomial at its age at the fix
    fx: np.ndarray  # (N,) bool: the state at the last fix changed in the step that made this state
    gen: np.ndarray  # (1,) int64: the steps this state has taken (a peek's copy uses it)

    @classmethod
    def fresh(cls, n: int) -> _LIMMState:
        k, nx = _leader_imm.K, _leader_imm.NX
        return cls(np.zeros(n), np.zeros((n, 2)), np.zeros((n, 2)), np.zeros(n), np.zeros(n, dtype=bool),
                   np.zeros(n), np.zeros((n, k, nx)), np.tile(np.eye(nx), (n, k, 1, 1)), np.zeros((n, k)),
                   np.zeros((n, k)), np.zeros((n, 1), dtype=np.int64), np.zeros((n, 2)), np.zeros((n, k, nx)),
                   np.zeros((n, k, 2)), np.zeros((n, k)), np.ones((n, k)), np.ones((n, k)), np.ones(n, dtype=bool),
                   np.zeros(1, dtype=np.int64))

    @property
    def x(self) -> np.ndarray:  # (the batch size, as the other states' x)
        return self.odom

    def copy(self) -> _LIMMState:
        return _LIMMState(*(getattr(self, f.name).copy() for f in fields(self)))


@dataclass
class _PFState:
    """The particle filter's per-env arrays (:func:`controllers._leader_pf.pf_step`)."""

    t_now: np.ndarray
    odom: np.ndarray
    vel: np.ndarray
    init: np.ndarray
    t_fix: np.ndarray
    P: np.ndarray  # (N, n, NPC) particles at the newest fix's time
    Pn: np.ndarray  # (N, n, NPC) advanced to now
    logw: np.ndarray  # (N, n)
    rs: np.ndarray  # (N, 1) uint64: each env's generator
    psi_f: np.ndarray  # (N,) the follower's heading at the last step

    @classmethod
    def fresh(cls, n: int, particles: int) -> _PFState:
        st = _leader_pf.new_state(n, particles)
        return cls(st["t_now"], st["odom"], st["vel"], st["init"], st["t_fix"], st["P"], st["Pn"], st["logw"],
                   st["rs"], np.zeros(n))

    @property
    def x(self) -> np.ndarray:  # (the batch size, as the other states' x)
        return self.odom

    def copy(self) -> _PFState:
        return _PFState(*(getattr(self, f.name).copy() for f in fields(self)))


@dataclass
class _Peek:
    """A peek (``step(commit=False)``) kept for the commit that follows it on the same input."""

    base: _FilterState  # the filter state the peek started from (identity; any commit drops the peek)
    obs: np.ndarray  # (N, W) float64, a private copy of the bits
    mask: np.ndarray  # (N,) the reset mask it applied
    with_cov: bool
    state: _FilterState  # the advanced copy
    estimate: TargetEstimate


def _blank_like(st, spare):
    """``spare`` if it is a state of the same kind, shapes and dtypes as ``st`` (to be
    overwritten), else a new uninitialised one."""
    if spare is not None and type(spare) is type(st) and spare is not st and all(
            (a := getattr(spare, f.name)).shape == (b := getattr(st, f.name)).shape and a.dtype == b.dtype
            for f in fields(st)):
        return spare
    return type(st)(*(np.empty_like(getattr(st, f.name)) for f in fields(st)))


def _copy_state(st, spare):
    """A copy of the filter state ``st``, written into ``spare`` (a state the estimator no longer
    uses) when it fits (:func:`_blank_like`), which spares the allocation (and, for the large
    arrays, the fresh pages' faults) of every peek."""
    out = _blank_like(st, spare)
    for f in fields(st):
        np.copyto(getattr(out, f.name), getattr(st, f.name))
    return out


def _state_arrays(st) -> tuple[np.ndarray, ...]:
    """The state's arrays in field order."""
    return tuple(getattr(st, f.name) for f in fields(st))


def _copy_estimate(e: TargetEstimate) -> TargetEstimate:
    return TargetEstimate(**{f.name: (v.copy() if isinstance(v := getattr(e, f.name), np.ndarray) else v)
                             for f in fields(e)})


def _kernel_estimate(out: np.ndarray, state: np.ndarray, cov: np.ndarray | None,
                     zeroed: bool = False) -> TargetEstimate:
    """A :class:`TargetEstimate` from a numba filter's output rows (the OU0 kernel's columns E_*;
    the IMM writes the same) and its present state (N, n) (``zeroed``: already 0 for envs
    without a fix, and not the filter's own array); no sway (v = 0)."""
    k = _ou0
    valid = out[:, k.E_VALID] > 0.5
    return TargetEstimate(valid=valid, x=out[:, k.E_X], y=out[:, k.E_Y], psi=out[:, k.E_PSI], u=out[:, k.E_U],
                          v=np.zeros(out.shape[0]), r=out[:, k.E_R], rel_x=out[:, k.E_RX], rel_y=out[:, k.E_RY],
                          rel_psi=out[:, k.E_RPSI], state=state if zeroed else np.where(valid[:, None], state, 0.0),
                          cov=cov, age=out[:, k.E_AGE])


#: the filters in numba (their state a dataclass of arrays, their input the raw observation rows)
_NUMBA_MODELS = ("OU0", "IMM", "LEADER_PF", "LEADER_IMM")
#: the IMM's present state (x, y, psi, u, r) among the kernel's output columns (a view: E_X .. E_R)
_IMM_STATE_COLUMNS = slice(_ou0.E_X, _ou0.E_R + 1)
assert [_ou0.E_X, _ou0.E_Y, _ou0.E_PSI, _ou0.E_U, _ou0.E_R] == list(range(_ou0.E_X, _ou0.E_R + 1))


class TargetEstimator:
    """Batched target Kalman filter over N envs; see the module docstring.

    Args:
        spec: the env's TaskSpec (dt, and the delay tau that v0 fixes carry).
        config: :class:`EstimatorConfig` (default: :meth:`EstimatorConfig.for_spec`).

    Call :meth:`step` once per control step with the observation batch and the per-env
    episode-start mask; it returns the present :class:`TargetEstimate`.
    """

    def __init__(self, spec: TaskSpec, config: EstimatorConfig | None = None) -> None:
        if not isinstance(spec, TaskSpec):
            raise ValueError(f"spec={spec!r} is invalid: must be an auv_follow_env TaskSpec")
        if config is not None and not isinstance(config, EstimatorConfig):
            raise ValueError(f"config={config!r} is invalid: must be an EstimatorConfig or None")
        self.spec = spec
        self.config = config if config is not None else EstimatorConfig.for_spec(spec)
        self.model = self.config.model
        self._qc = self.config.process_intensity()
        self._taus = (self.config.tau_u, self.config.tau_r)
        self._cfg = (self._kernel_config() if self.model == "OU0" else
                     self._imm_config() if self.model == "IMM" else None)
        self._prior = None
        if self.model in ("LEADER_PF", "LEADER_IMM"):
            tier = getattr(spec, "tier", None)
            from auv_follow_env.tiers import LEADER_TIERS

            if tier not in LEADER_TIERS or spec.layout != "v1":
                raise ValueError(f"model={self.model!r} needs a Leader tier's task (it knows the tier's modes); got "
                                 f"tier={tier!r}: valid tiers are {list(LEADER_TIERS)}")
        if self.model == "LEADER_IMM":
            c = self.config
            self._cfg = _leader_imm.limm_config(spec, tier, q_u=c.limm_q_u, q_h=c.limm_q_h, q_r=c.limm_q_r,
                                                sojourn_scale=c.limm_sojourn, shape=c.limm_shape,
                                                gate=c.imm_gate)
        if self.model == "LEADER_PF":
            self._cfg, self._prior = _leader_pf.pf_config(spec, tier)
            self._cfg[_leader_pf.C_TEMPER] = self.config.pf_temper
            self._cfg[_leader_pf.C_DRIFT] = self.config.pf_drift
        self._kstep = (_ou0.step_constants(spec.dt, self.config.tau_u, self.config.tau_r)
                       if self.model == "OU0" else None)
        self._s: _FilterState | None = None
        #: a state no longer in use (the one a commit replaced by its peek's), refilled by the next peek;
        #: only for the numba filters, whose estimates never share the state's arrays
        self._spare = None
        #: reuse a peek's result for the commit that follows it on bit-identical input (False: always
        #: recompute, e.g. to check that reuse changes nothing)
        self.reuse_peek = True
        self._peek: _Peek | None = None  # the last peek, dropped by the next commit
        #: the recovery rule for non-finite observation fields (controllers.base.ObservationHold)
        self.hold = ObservationHold(spec.dt)

    def reset(self) -> None:
        """Forget all envs: the next :meth:`step` starts every env fresh."""
        self.hold.reset()
        self._s = None
        self._peek = None
        self._spare = None

    # ------------------------------------------------------------------------------------
    def _kernel_config(self) -> np.ndarray:
        c, k = self.config, _ou0
        cfg = np.zeros(k.NC)
        cfg[k.C_DT], cfg[k.C_TAU] = self.spec.dt, self.spec.delay_s
        cfg[k.C_V1] = 1.0 if self.spec.layout == "v1" else 0.0
        cfg[k.C_TU], cfg[k.C_TR] = c.tau_u, c.tau_r
        cfg[k.C_SPOS], cfg[k.C_SPM], cfg[k.C_SPSI] = c.sigma_pos, c.sigma_pos_per_m, c.sigma_psi
        cfg[k.C_SVEL], cfg[k.C_SR], cfg[k.C_SUB0] = c.sigma_vel, c.sigma_r, c.sigma_ubar0
        cfg[k.C_QU], cfg[k.C_QR], cfg[k.C_QUB] = c.q_acc, c.q_yaw, 1e-9
        cfg[k.C_ADAPT], cfg[k.C_N0], cfg[k.C_SMOOTH] = float(c.adapt), c.adapt_n0, c.smooth_s
        return cfg

    def _imm_config(self) -> np.ndarray:
        c, k = self.config, _imm
        cfg = np.zeros(k.NC)
        cfg[k.C_DT], cfg[k.C_TAU] = self.spec.dt, self.spec.delay_s
        cfg[k.C_V1] = 1.0 if self.spec.layout == "v1" else 0.0
        cfg[k.C_SPOS], cfg[k.C_SPM], cfg[k.C_SPSI] = c.sigma_pos, c.sigma_pos_per_m, c.sigma_psi
        cfg[k.C_SVEL], cfg[k.C_SR] = c.sigma_vel, c.sigma_r
        cfg[k.C_QU], cfg[k.C_QR], cfg[k.C_QH] = c.imm_q_u, c.imm_q_r, c.imm_q_h
        cfg[k.C_TS], cfg[k.C_GATE], cfg[k.C_QN] = c.imm_tau_s, float(c.imm_gate), float(c.imm_q_panels)
        return cfg

    def _run_imm(self, st: _IMMState, obs: np.ndarray, mask: np.ndarray, with_cov: bool,
                 src: _IMMState | None = None) -> TargetEstimate:
        """The IMM kernel on ``st`` (in place; from the state ``src`` instead if given: st is
        then overwritten, the copy made env by env inside the kernel)."""
        n = obs.shape[0]
        out = np.empty((n, _ou0.NE))
        cov = np.empty((n if with_cov else 0, 5, 5))
        _imm.imm_step(obs, mask, self._cfg, st.t_now, st.odom, st.vel, st.psi_f, st.init, st.t_fix, st.m, st.P,
                      st.mu, st.ng, st.gap, out, cov, None if src is None else _state_arrays(src))
        # (x, y, psi, u, r): the kernel's columns E_X .. E_R in this order, zero where no fix yet
        state = out[:, _IMM_STATE_COLUMNS]
        return _kernel_estimate(out, state, cov if with_cov else None, zeroed=True)

    def _run_limm(self, st: _LIMMState, obs: np.ndarray, mask: np.ndarray, src: _LIMMState | None = None,
                  reused: bool = False) -> TargetEstimate:
        """The model-aware IMM's kernel on ``st`` (in place; from the state ``src`` instead if given,
        as :meth:`_run_imm`). ``reused``: st is the spare state a commit left (not a new one)."""
        out = np.empty((obs.shape[0], _ou0.NE))
        # a peek into the very state src was stepped from (the spare a commit left, one step behind)
        # copies only what changed since
        partial = src is not None and reused and int(st.gen[0]) == int(src.gen[0]) - 1
        _leader_imm.limm_step(obs, mask, self._cfg, *_state_arrays(st)[:-1], out,
                              None if src is None else _state_arrays(src)[:-1], partial)
        st.gen[0] = (st if src is None else src).gen[0] + 1
        return _kernel_estimate(out, out[:, _IMM_STATE_COLUMNS], None, zeroed=True)

    def _run_pf(self, st: _PFState, obs: np.ndarray, mask: np.ndarray) -> TargetEstimate:
        n = obs.shape[0]
        out = np.empty((n, _leader_pf.NF))
        _leader_pf.pf_step(obs, mask, self._cfg, self._prior, st.t_now, st.odom, st.vel, st.init, st.t_fix, st.P,
                           st.Pn, st.logw, st.rs, out)
        k = _leader_pf
        valid = out[:, k.F_VALID] > 0.5
        pf = np.arctan2(obs[:, 4], obs[:, 3])  # the follower's heading (cos_psi, sin_psi)
        st.psi_f = pf
        c, s = np.cos(pf), np.sin(pf)
        ex, ey = out[:, k.F_X] - st.odom[:, 0], out[:, k.F_Y] - st.odom[:, 1]
        rel_psi = np.arctan2(np.sin(out[:, k.F_PSI] - pf), np.cos(out[:, k.F_PSI] - pf))
        z = np.zeros(n)
        state = np.stack([out[:, k.F_X], out[:, k.F_Y], out[:, k.F_PSI], out[:, k.F_U], out[:, k.F_R]], axis=-1)
        return TargetEstimate(valid=valid, x=np.where(valid, out[:, k.F_X], z), y=np.where(valid, out[:, k.F_Y], z),
                              psi=np.where(valid, out[:, k.F_PSI], z), u=np.where(valid, out[:, k.F_U], z), v=z.copy(),
                              r=np.where(valid, out[:, k.F_R], z), rel_x=np.where(valid, c * ex + s * ey, z),
                              rel_y=np.where(valid, -s * ex + c * ey, z), rel_psi=np.where(valid, rel_psi, z),
                              state=np.where(valid[:, None], state, 0.0), cov=None,
                              age=np.where(valid, out[:, k.F_AGE], z))

    def _run_ou0(self, st: _OU0State, obs: np.ndarray, mask: np.ndarray, with_cov: bool) -> TargetEstimate:
        n = obs.shape[0]
        out = np.empty((n, _ou0.NE))
        cov = np.empty((n if with_cov else 0, 6, 6))
        _ou0.ou0_step(obs, mask, self._cfg, self._kstep, st.t_now, st.odom, st.vel, st.psi_f, st.init, st.t_fix,
                      st.x, st.P, st.xp, st.Pp, st.stale, st.dlt, st.stats, out, cov)
        return _kernel_estimate(out, st.xp, cov if with_cov else None)

    def _fresh(self, n: int):
        if self.model == "OU0":
            return _OU0State.fresh(n)
        if self.model == "IMM":
            return _IMMState.fresh(n)
        if self.model == "LEADER_PF":
            return _PFState.fresh(n, self.config.pf_particles)
        if self.model == "LEADER_IMM":
            return _LIMMState.fresh(n)
        d = self.config.dim
        return _FilterState(np.zeros(n), np.zeros((n, 2)), np.zeros((n, 2)), np.zeros(n), np.zeros(n, dtype=bool),
                            np.zeros(n), np.zeros((n, d)), np.tile(np.eye(d), (n, 1, 1)))

    def _measurement(self, o: dict[str, np.ndarray], odom: np.ndarray, psi_f: np.ndarray):
        """Fix z (N, 6) in the model's coordinates and its noise variances (N, 6)."""
        c, s = np.cos(psi_f), np.sin(psi_f)
        dx, dy = o["target_dx"], o["target_dy"]
        psi_t = psi_f + np.arctan2(o["target_sin_dpsi"], o["target_cos_dpsi"])
        u, v, r = o["target_u"], o["target_v"], o["target_r"]
        if self.model == "CV":
            ct, st = np.cos(psi_t), np.sin(psi_t)
            u, v = ct * u - st * v, st * u + ct * v
        z = np.stack([odom[:, 0] + c * dx - s * dy, odom[:, 1] + s * dx + c * dy, psi_t, u, v, r], axis=-1)
        cfg = self.config
        sp = cfg.sigma_pos + cfg.sigma_pos_per_m * np.hypot(dx, dy)
        var = np.stack([sp * sp, sp * sp, np.full_like(sp, cfg.sigma_psi ** 2),
                        np.full_like(sp, cfg.sigma_vel ** 2), np.full_like(sp, cfg.sigma_vel ** 2),
                        np.full_like(sp, cfg.sigma_r ** 2)], axis=-1)
        return z, var

    def _advance(self, st: _FilterState, o: dict[str, np.ndarray], reset: np.ndarray) -> None:
        """Odometry, then the measurement update of the envs with a newer fix (in place)."""
        n = reset.shape[0]
        psi_f = np.arctan2(o["sin_psi"], o["cos_psi"])
        c, s = np.cos(psi_f), np.sin(psi_f)
        vel = np.stack([c * o["u"] - s * o["v"], s * o["u"] + c * o["v"]], axis=-1)
        go = ~reset
        st.odom[go] += 0.5 * self.spec.dt * (st.vel[go] + vel[go])
        st.t_now[go] += self.spec.dt
        st.odom[reset] = 0.0
        st.t_now[reset] = 0.0
        st.init[reset] = False
        st.vel = vel
        st.psi_f = psi_f
        if "packet_age" in o:
            # a packet already held at the episode's start (received during the warm-up) is used too
            fresh = (o["has_packet"] > 0.5) & ((o["new_packet"] > 0.5) | ~st.init)
            t_meas = st.t_now - o["packet_age"]
        else:
            fresh = np.ones(n, dtype=bool)
            t_meas = st.t_now - self.spec.delay_s
        fresh &= ~st.init | (t_meas > st.t_fix + 1e-6)  # stale / out-of-order fixes are ignored
        if not fresh.any():
            return
        z, var = self._measurement(o, st.odom, psi_f)
        d = self.config.dim
        first = fresh & ~st.init
        if first.any():
            x0 = np.zeros((int(first.sum()), d))
            x0[:, :6] = z[first]
            if self.model == "OU":
                x0[:, 6] = z[first][:, 3]  # mean speed: the first fix's speed
            p0 = np.zeros((x0.shape[0], d))
            p0[:, :6] = var[first]
            p0[:, 6:] = np.square(self.config.prior_std())
            st.x[first] = x0
            st.P[first] = p0[:, :, None] * np.eye(d)[None]
            st.t_fix[first] = t_meas[first]
            st.init[first] = True
        upd = fresh & ~first
        if upd.any():
            xp, Pp = _predict(self.model, st.x[upd], st.P[upd], t_meas[upd] - st.t_fix[upd], self._qc, self._taus)
            zi = z[upd]
            innov = zi - xp[:, :6]
            innov[:, 2] = np.arctan2(np.sin(innov[:, 2]), np.cos(innov[:, 2]))
            S = Pp[:, :6, :6] + var[upd][:, :, None] * np.eye(6)[None]
            K = np.linalg.solve(S, Pp[:, :6, :]).transpose(0, 2, 1)  # P H^T S^-1, (m, d, 6)
            xn = xp + np.einsum("nij,nj->ni", K, innov)
            IKH = np.eye(d)[None] - np.concatenate([K, np.zeros((K.shape[0], d, d - 6))], axis=2)
            Pn = IKH @ Pp @ IKH.transpose(0, 2, 1) + (K * var[upd][:, None, :]) @ K.transpose(0, 2, 1)  # Joseph
            st.x[upd] = xn
            st.P[upd] = 0.5 * (Pn + Pn.transpose(0, 2, 1))
            st.t_fix[upd] = t_meas[upd]

    def _present(self, st: _FilterState, o: dict[str, np.ndarray], with_cov: bool) -> TargetEstimate:
        T = np.where(st.init, st.t_now - st.t_fix, 0.0)
        x, P = _predict(self.model, st.x, st.P, T, self._qc, self._taus, with_cov)
        valid = st.init.copy()
        x = np.where(valid[:, None], x, 0.0)
        psi_t = x[:, 2]
        if self.model == "CV":
            ct, s_t = np.cos(psi_t), np.sin(psi_t)
            u, v = ct * x[:, 3] + s_t * x[:, 4], -s_t * x[:, 3] + ct * x[:, 4]
        else:
            u, v = x[:, 3], x[:, 4]
        psi_f = np.arctan2(o["sin_psi"], o["cos_psi"])
        c, s = np.cos(psi_f), np.sin(psi_f)
        ex, ey = x[:, 0] - st.odom[:, 0], x[:, 1] - st.odom[:, 1]
        dpsi = psi_t - psi_f
        z = np.zeros_like(T)
        return TargetEstimate(
            valid=valid, x=x[:, 0], y=x[:, 1], psi=psi_t, u=u, v=v, r=x[:, 5],
            rel_x=np.where(valid, c * ex + s * ey, z), rel_y=np.where(valid, -s * ex + c * ey, z),
            rel_psi=np.where(valid, np.arctan2(np.sin(dpsi), np.cos(dpsi)), z), state=x, cov=P, age=T)

    def _checked(self, observation, reset_mask, commit: bool = True):
        obs, _ = as_batch(observation, (OBS_DIM, OBS_DIM_V1))
        n = obs.shape[0]
        mask = as_mask(reset_mask, n, "reset_mask")
        if self._s is None or self._s.x.shape[0] != n:
            mask = np.ones(n, dtype=bool)
            self._s = self._fresh(n)
            self.hold.reset()
        obs = self.hold(obs, mask, commit)
        return obs, (None if self.model in _NUMBA_MODELS else decode(obs)), mask

    def step(self, observation: np.ndarray, reset_mask: np.ndarray | None = None, *, commit: bool = True,
             with_cov: bool = True, copy: bool = True) -> TargetEstimate:
        """Take one control step's observations (N, 16 or 20) and return the present estimate.

        Args:
            observation: the batch (or one observation) of either layout.
            reset_mask: (N,) envs whose episode starts at this observation (None: none).
                The first call, or a change of batch size, starts every env fresh.
            commit: False computes the estimate without changing the filter (a peek, e.g.
                for a controller's ``reference`` method).
            with_cov: also propagate the covariance to now (``cov`` is None otherwise).
            copy: False lets a commit that adopts a peek return the peek's own arrays (for a
                caller that only reads them; True: a private copy).

        A commit on the same observation bits, reset mask and ``with_cov`` as the peek just
        before it (no other commit in between) adopts the peek's filter state and returns a copy
        of its estimate instead of computing both again: the same operations on the same inputs,
        so the result is bit-identical (``evaluate_batched`` peeks through a controller's
        ``reference`` at the observation the next ``predict`` commits). ``reuse_peek = False``
        turns this off.

        Raises:
            ValueError: observation of a wrong shape, or a reset_mask of the wrong length.
        """
        obs, o, mask = self._checked(observation, reset_mask, commit)
        if self.model in _NUMBA_MODELS:
            obs = np.ascontiguousarray(obs, dtype=np.float64)
        if not commit:
            if self.model in ("IMM", "LEADER_IMM"):  # the peek's copy of the state is made inside the kernel
                spare = self._spare
                st = _blank_like(self._s, spare)
                self._spare = None
                est = (self._run_imm(st, obs, mask, with_cov, src=self._s) if self.model == "IMM" else
                       self._run_limm(st, obs, mask, src=self._s, reused=st is spare))
            else:
                st = _copy_state(self._s, self._spare) if self.model in _NUMBA_MODELS else self._s.copy()
                self._spare = None
                est = self._run(st, obs, o, mask, with_cov)
            self._peek = None
            if self.reuse_peek:
                key = obs.copy() if np.may_share_memory(obs, observation) else obs
                self._peek = _Peek(self._s, key, mask.copy(), with_cov, st, est)
            return est
        pk, self._peek = self._peek, None
        if (self.reuse_peek and pk is not None and pk.base is self._s and pk.with_cov == with_cov
                and np.array_equal(pk.mask, mask) and np.array_equal(pk.obs.view(np.int64), obs.view(np.int64))):
            self._spare, self._s = self._s, pk.state
            return _copy_estimate(pk.estimate) if copy else pk.estimate
        return self._run(self._s, obs, o, mask, with_cov)

    def _run(self, st, obs: np.ndarray, o: dict[str, np.ndarray], mask: np.ndarray, with_cov: bool) -> TargetEstimate:
        if self.model == "OU0":
            return self._run_ou0(st, obs, mask, with_cov)
        if self.model == "IMM":
            return self._run_imm(st, obs, mask, with_cov)
        if self.model == "LEADER_PF":
            return self._run_pf(st, obs, mask)
        if self.model == "LEADER_IMM":
            return self._run_limm(st, obs, mask)
        self._advance(st, o, mask)
        return self._present(st, o, with_cov)

    def follower_odometry(self) -> tuple[np.ndarray, np.ndarray]:
        """The follower's position (N, 2) in the odometry frame [m] and heading (N,) [rad] at the
        last :meth:`step`.

        Raises:
            ValueError: if :meth:`step` has not been called.
        """
        if self._s is None:
            raise ValueError("follower_odometry() needs a step() first: no filter state yet")
        return self._s.odom.copy(), self._s.psi_f.copy()

    def trajectory(self, times: np.ndarray, frame: str = "body") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The predicted target pose at ``times`` (K,) seconds after the last :meth:`step`.

        Args:
            times: offsets from now [s], 1-D, finite, >= 0.
            frame: "body": relative to the follower's pose at that step, in its body frame,
                psi continuous along the horizon starting from the wrapped relative heading;
                "odometry": in the odometry frame (psi as the filter carries it, unwrapped).

        Returns:
            (x, y, psi), each (N, K); envs without a fix give zeros.

        Raises:
            ValueError: if :meth:`step` has not been called, or a bad ``times`` or ``frame``.
        """
        if self._s is None:
            raise ValueError("trajectory() needs a step() first: no filter state yet")
        if frame not in ("body", "odometry"):
            raise ValueError(f"frame={frame!r} is invalid: must be 'body' or 'odometry'")
        tk = np.asarray(times, dtype=np.float64)
        if tk.ndim != 1 or not np.all(np.isfinite(tk)) or np.any(tk < 0):
            raise ValueError(f"times={times!r} is invalid: must be a 1-D array of finite numbers >= 0 [s]")
        st = self._s
        n, K = st.x.shape[0], tk.shape[0]
        if self.model == "OU0":  # from the present state (the filter's, without the smoothing offset)
            T = np.broadcast_to(tk[None, :], (n, K))
            X = propagate_mean(self.model, np.repeat(st.xp[:, None, :], K, axis=1), T, self._taus)
        elif self.model == "LEADER_PF":
            raise ValueError("trajectory() is not available for model='LEADER_PF' (the particle filter predicts the "
                             "present only): use it with the hierarchical law (PROPOSED_PF_DOB), not the MPC")
        elif self.model == "IMM":  # the mixture's prediction from the last fix
            T = np.where(st.init, st.t_now - st.t_fix, 0.0)[:, None] + tk[None, :]
            X = _imm.imm_trajectory(st.m, st.P, st.mu, st.init, np.ascontiguousarray(T), self._cfg)
        elif self.model == "LEADER_IMM":  # the models' mixture from the last fix
            T = np.where(st.init, st.t_now - st.t_fix, 0.0)[:, None] + tk[None, :]
            X = _leader_imm.limm_trajectory(st.m, st.mu, st.ag, st.om, st.init, np.ascontiguousarray(T), self._cfg)
        else:
            T = np.where(st.init, st.t_now - st.t_fix, 0.0)[:, None] + tk[None, :]
            X = propagate_mean(self.model, np.repeat(st.x[:, None, :], K, axis=1), T, self._taus)  # (N, K, n)
        ok = st.init[:, None]
        z = np.zeros((n, K))
        if frame == "odometry":
            return np.where(ok, X[..., 0], z), np.where(ok, X[..., 1], z), np.where(ok, X[..., 2], z)
        psi_f = st.psi_f
        c, s = np.cos(psi_f)[:, None], np.sin(psi_f)[:, None]
        ex, ey = X[..., 0] - st.odom[:, 0, None], X[..., 1] - st.odom[:, 1, None]
        d0 = X[:, :1, 2] - psi_f[:, None]
        wrap0 = np.arctan2(np.sin(d0), np.cos(d0)) - d0
        return (np.where(ok, c * ex + s * ey, z), np.where(ok, -s * ex + c * ey, z),
                np.where(ok, X[..., 2] - psi_f[:, None] + wrap0, z))
