"""Numba kernel of the ``LEADER_IMM`` target filter (:mod:`controllers.estimator`): a *model-aware*
estimator of the Leader tiers that is cheap enough for the control loop. An interacting multiple
model filter (Blom and Bar-Shalom, 1988) over the tier's own mode set (docs/tiers.md, "Leader
tiers"), with the tier's published ranges, mean durations and shares and the generator's lags;
the particle filter (:mod:`controllers._leader_pf`) is the model-aware reference that knows the
whole generator (durations' shapes, the survey's legs).

Models (index: mode, turn-rate command, speed):

====  ===============  ==============  =====================================================
0     cruise / leg     0               held (a random walk)
1, 2  turn left/right  +-w_t           held
3, 4  U-turn l/r       +-w_u           held  (only if the tier has surveys)
5     loiter           0               lags toward the tier's loiter speed
6     sprint           0               lags toward the tier's sprint speed (both: 2 mode sets)
====  ===============  ==============  =====================================================

State per model (5): ``x, y, psi`` (odometry frame [m, m, rad]), ``u`` (surge [m/s]) and ``r``
(turn rate [rad/s]). As in the generator, the turn rate lags toward the model's command (time
constant ``leader_rate_lag_s``) and the loiter and sprint speeds toward theirs
(``leader_speed_lag_s``); heading, speed and rate move in closed form, the position by
Gauss-Legendre quadrature. The commands w_t, w_u start at the middle of the tier's ranges and
adapt per env to the fixes' measured turn rate while a turn model holds the probability (clipped
to the range: each episode draws its rates from it). Process noise: white noise on the speed
(``q_u``), the turn rate (``q_r``) and the heading (``q_h``), in closed form along the course.

Switches: the semi-Markov modes with sojourn-time-dependent switching (Campo, Mookerjee and
Bar-Shalom, 1991). Each mode keeps its expected age (the time since it was entered, given that it
holds); over a span it stays with the survival ratio S(age + T) / S(age) of a Gamma(k) duration
with the tier's mean (times 1 / ``sojourn_scale``; the generator's shape is 4, k = 1 makes the
modes a Markov chain). Leaving cruise goes to the other modes in the generator's shares (surveys
and wandering weighted by the survey share), leaving any other mode goes back to cruise; a second
switch within one span is neglected. At a fix the mass that stayed ages by the span and the mass
that entered counts half of it. The position is gated as in the generic IMM
(:mod:`controllers._imm`: 99.9 % chi-square for every model; two gated fixes in a row restart the
filter).

The present estimate: at a fix the models' means are predicted to now and the mode probabilities
carried over the same span; between fixes both advance by one control step (each model by a
constant-rate arc over the step, the survival ratios by a running exponential and a cubic, a few
multiplications per model), so the control loop pays little per step. Out-of-order fixes: the envs
never deliver one (the receiver keeps the newest packet); :func:`limm_filter_fixes` takes fixes in
arrival order and handles them by retrodiction (re-running from the snapshot before the fix), as
the generic IMM.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import njit, prange

from auv_follow_env.dynamics import recompiled
from controllers._imm import GATE_POS, _wrap, gate_distance, insert_by_time, model_update
from controllers._ou0 import (
    NE,
    fix_measurement,
    fix_timing,
    fix_variances,
    odometry_step,
    write_estimate,
)

K = 7  #: models
NX = 5  #: state per model (x, y, psi, u, r)
# config vector (float64) indices: scalars, then per model its exit rate [1/s], its stationary
# share (0: the model is not in this tier's mode set) and cruise's share of switches into it
C_DT, C_TAU, C_V1 = 0, 1, 2
C_SPOS, C_SPM, C_SPSI, C_SVEL, C_SR = 3, 4, 5, 6, 7
C_QU, C_QH, C_GATE, C_TU, C_SRATE = 8, 9, 10, 11, 12
C_VL, C_VS, C_WT_LO, C_WT_HI, C_WU_LO, C_WU_HI, C_ADAPT, C_TR = 13, 14, 15, 16, 17, 18, 19, 20
C_QR = 21
C_LAM, C_PI, C_SPLIT = 22, 22 + K, 22 + 2 * K
C_SHAPE = 22 + 3 * K  #: the sojourns' Gamma shape (a whole number 1-4; 1: exponential, a Markov chain)
NC = 23 + 3 * K
NQ = 6  #: quadrature nodes of a model's motion over a span
_GL_X, _GL_W = np.polynomial.legendre.leggauss(NQ)  #: Gauss-Legendre nodes, weights on [-1, 1]
CRUISE, TURN_L, TURN_R, UTURN_L, UTURN_R, LOITER, SPRINT = range(K)


def limm_config(spec, tier: str, *, q_u: float = 0.001, q_h: float = 0.01, q_r: float = 0.0001, s_rate: float = 0.03,
                adapt: float = 0.3, sojourn_scale: float = 1.0, shape: int = 4, gate: bool = True) -> np.ndarray:
    """The config vector of a Leader tier from its published table (:data:`auv_follow_env.tiers.LEADER_TIERS`):
    the mode set, the ranges' midpoints (speeds, rates, mean durations, leg length), the survey
    share, the speed lag, and the fix noise; ``q_u``, ``q_h``, ``s_rate`` (std of a mode's turn
    rate about its model's [rad/s]), ``adapt`` (gain of the rates' adaptation) and
    ``sojourn_scale`` (the modes' leaving rates, 1 / mean duration, times this) and ``shape`` (the
    sojourns' Gamma shape: the generator's is 4; 1 makes the modes a Markov chain) are ours."""
    from auv_follow_env.tiers import LEADER_TIERS

    t = LEADER_TIERS[tier]
    fields = {**t.fixed, **t.ranges}

    def rng(name: str, default: float) -> tuple[float, float]:
        v = fields.get(name, default)
        return (float(v[0]), float(v[1])) if isinstance(v, (tuple, list)) else (float(v), float(v))

    def mid(name: str, default: float) -> float:
        lo, hi = rng(name, default)
        return 0.5 * (lo + hi)

    c = np.zeros(NC)
    c[C_DT], c[C_TAU], c[C_V1] = spec.dt, spec.delay_s, 1.0
    c[C_SPOS] = max(mid("fix_sigma_m", 0.0), 1e-3)
    c[C_SPM] = mid("fix_sigma_per_m", 0.0)
    c[C_SPSI] = max(mid("heading_sigma_rad", 0.0), 1e-3)
    c[C_SVEL] = max(mid("velocity_sigma_mps", 0.0), 1e-3)
    c[C_SR] = max(mid("yaw_rate_sigma_radps", 0.0), 1e-4)
    c[C_QU], c[C_QH], c[C_QR], c[C_GATE], c[C_SRATE], c[C_ADAPT] = q_u, q_h, q_r, float(gate), s_rate, adapt
    c[C_TU], c[C_TR] = mid("leader_speed_lag_s", 2.0), mid("leader_rate_lag_s", 1.0)
    c[C_VL], c[C_VS] = mid("leader_loiter_speed", 0.1), mid("leader_sprint_speed", 0.9)
    c[C_WT_LO], c[C_WT_HI] = rng("leader_turn_rate", 0.15)
    c[C_WU_LO], c[C_WU_HI] = rng("leader_uturn_rate", 0.25)
    share = mid("leader_survey_share", 0.0)
    speed_modes = mid("leader_modes", 1.0) >= 2
    mc, mt = mid("leader_cruise_mean_s", 10.0), mid("leader_turn_mean_s", 6.0)
    ml, ms = mid("leader_loiter_mean_s", 8.0), mid("leader_sprint_mean_s", 5.0)
    t_leg = mid("leader_leg_m", 10.0) / mid("leader_cruise_speed", 0.5)
    t_u = math.pi / mid("leader_uturn_rate", 0.25)
    # wander: cruise's exits (the generator's shares) and each mode's mean duration
    p_turn = 0.3 if speed_modes else 0.5
    wander = {TURN_L: (p_turn, mt), TURN_R: (p_turn, mt)}
    if speed_modes:
        wander.update({LOITER: (0.2, ml), SPRINT: (0.2, ms)})
    survey = {UTURN_L: (0.5, t_u), UTURN_R: (0.5, t_u)} if share > 0 else {}
    # exits from cruise per second: (1 - share) / mc to the wander modes, share / t_leg to the U-turns
    out_w, out_s = (1.0 - share) / mc, share / t_leg
    c[C_LAM + CRUISE] = (out_w + out_s) * sojourn_scale
    for group, out in ((wander, out_w), (survey, out_s)):
        for j, (p, dur) in group.items():
            c[C_LAM + j] = sojourn_scale / dur
            c[C_SPLIT + j] = out * p / (out_w + out_s)
    # the modes' shares of time: a visit's share times its mean duration (every mode returns to cruise)
    act = [CRUISE] + [j for j in range(1, K) if c[C_SPLIT + j] > 0]
    pi = np.array([1.0] + [c[C_LAM + CRUISE] * c[C_SPLIT + j] / c[C_LAM + j] for j in act[1:]])
    c[[C_PI + j for j in act]] = pi / pi.sum()
    c[C_SHAPE] = float(shape)
    return c


@njit(cache=True, inline="always")
def _wrap_d(a):
    """The angle a wrapped to [-pi, pi): returned as it is when already there (the headings'
    differences between models and fixes nearly always are), else shifted by whole turns."""
    if -math.pi <= a < math.pi:
        return a
    return a - 2.0 * math.pi * math.floor((a + math.pi) / (2.0 * math.pi))


@njit(cache=True, inline="always")
def _rate(j, wt, wu):
    """Model j's turn rate [rad/s] given the env's turn and U-turn rates."""
    if j == TURN_L:
        return wt
    if j == TURN_R:
        return -wt
    if j == UTURN_L:
        return wu
    if j == UTURN_R:
        return -wu
    return 0.0


@njit(cache=True, inline="always")
def _ucmd(j, cfg):
    """Model j's speed command [m/s] (-1: the speed is held)."""
    if j == LOITER:
        return cfg[C_VL]
    if j == SPRINT:
        return cfg[C_VS]
    return -1.0


@njit(cache=True, inline="always")
def _surv_poly(x, k):
    """sum_{n < k} x^n / n! (k = 1-4, Horner): the Gamma(k) survival function is exp(-x) times this
    (x = k t / mean)."""
    if k == 4.0:
        return 1.0 + x * (1.0 + x * (0.5 + x * (1.0 / 6.0)))
    if k == 3.0:
        return 1.0 + x * (1.0 + x * 0.5)
    if k == 2.0:
        return 1.0 + x
    return 1.0


@njit(cache=True, inline="always")
def _stay(a, T, lam, k):
    """The probability that a mode entered ``a`` seconds ago lasts T more seconds, its duration
    Gamma(k) with mean 1 / lam: S(a + T) / S(a)."""
    if lam == 0.0:
        return 1.0
    x0, x1 = k * lam * a, k * lam * (a + T)
    return math.exp(-k * lam * T) * _surv_poly(x1, k) / _surv_poly(x0, k)


@njit(cache=True)
def _transition(T, ag, cfg, Pi):
    """The modes' transition matrix over T into Pi (K, K), Pi[i, k] = P(mode k at T | i at 0), for
    modes entered ag (K,) seconds before: a mode stays with its sojourn's survival ratio; leaving
    cruise goes to the others by their shares, leaving another mode goes to cruise (a second switch
    within T neglected: a Gamma(4) sojourn rarely ends that soon)."""
    k = cfg[C_SHAPE]
    for i in range(K):
        for j in range(K):
            Pi[i, j] = 0.0
        if cfg[C_PI + i] == 0.0:
            continue
        p = _stay(ag[i], T, cfg[C_LAM + i], k)
        Pi[i, i] = p
        if i == CRUISE:
            for j in range(1, K):
                Pi[i, j] = (1.0 - p) * cfg[C_SPLIT + j]
        else:
            Pi[i, CRUISE] = 1.0 - p


def _transition_matrix(cfg, T, ag=None):
    Pi = np.empty((K, K))
    _transition(T, np.zeros(K) if ag is None else np.asarray(ag, dtype=np.float64), cfg, Pi)
    return Pi


@njit(cache=True, inline="always")
def _stationary_age(cfg, j):
    """A mode's expected age at a random time in it (length-biased): mean (1 + 1 / k) / 2."""
    lam = cfg[C_LAM + j]
    return 0.0 if lam == 0.0 else 0.5 * (1.0 + 1.0 / cfg[C_SHAPE]) / lam


@njit(cache=True)
def _nodes(T, cfg, tab):
    """The quadrature table of a span T, shared by the models, into tab (NQ + 1, 4): per node its
    time, weight, heading lag g(t) = tr (1 - exp(-t / tr)) and speed decay exp(-t / tu); the last
    row exp(-T / tr), g(T), exp(-T / tu)."""
    tr, tu = cfg[C_TR], cfg[C_TU]
    for q in range(NQ):
        t = 0.5 * T * (1.0 + _GL_X[q])
        tab[q, 0] = t
        tab[q, 1] = 0.5 * T * _GL_W[q]
        tab[q, 2] = tr * (1.0 - math.exp(-t / tr))
        tab[q, 3] = math.exp(-t / tu)
    er = math.exp(-T / tr)
    tab[NQ, 0] = er
    tab[NQ, 1] = tr * (1.0 - er)
    tab[NQ, 2] = math.exp(-T / tu)


@njit(cache=True)
def _prop(x, T, rc, uc, tab, out, J, want_J):
    """Mean (5,) of model state x after T (:func:`_nodes`' table ``tab`` of T), the turn rate
    lagging toward the model's rc, the speed held (uc < 0) or lagging toward uc, into ``out``;
    with ``want_J`` its Jacobian into J (5, 5). Heading, speed and rate in closed form, the
    position by Gauss-Legendre quadrature (NQ nodes) of u(t) (cos, sin) psi(t)."""
    px, py, psi, u, r = x[0], x[1], x[2], x[3], x[4]
    sx = sy = dxp = dyp = dxu = dyu = dxr = dyr = 0.0
    for q in range(NQ):
        t, w, g = tab[q, 0], tab[q, 1], tab[q, 2]
        ph = psi + rc * t + (r - rc) * g
        if uc >= 0.0:
            h = tab[q, 3]
            ut = uc + (u - uc) * h
        else:
            h = 1.0
            ut = u
        cq, sq = math.cos(ph), math.sin(ph)
        sx += w * ut * cq
        sy += w * ut * sq
        if want_J:
            dxp -= w * ut * sq
            dyp += w * ut * cq
            dxu += w * h * cq
            dyu += w * h * sq
            dxr -= w * ut * sq * g
            dyr += w * ut * cq * g
    er, gT, eu = tab[NQ, 0], tab[NQ, 1], tab[NQ, 2]
    out[0] = px + sx
    out[1] = py + sy
    out[2] = psi + rc * T + (r - rc) * gT
    out[3] = uc + (u - uc) * eu if uc >= 0.0 else u
    out[4] = rc + (r - rc) * er
    if want_J:
        for a in range(NX):
            for b in range(NX):
                J[a, b] = 0.0
            J[a, a] = 1.0
        J[0, 2], J[0, 3], J[0, 4] = dxp, dxu, dxr
        J[1, 2], J[1, 3], J[1, 4] = dyp, dyu, dyr
        J[2, 4] = gT
        J[4, 4] = er
        if uc >= 0.0:
            J[3, 3] = eu


@njit(cache=True)
def _add_noise(P, T, heading, u, qu, qh, qr):
    """P += the discrete process noise over T: white noise of intensity qu on the speed, qr on the
    turn rate and qh on the heading, integrated along a straight course at ``heading`` and speed u
    (closed form; the lags' damping of the noise neglected)."""
    A, Au = qu * T ** 3 / 3.0, qu * T * T / 2.0
    L = u * u * (qh * T ** 3 / 3.0 + qr * T ** 5 / 20.0)
    Lp = u * (qh * T * T / 2.0 + qr * T ** 4 / 8.0)
    Lr = u * qr * T ** 3 / 6.0
    ca, sa = math.cos(heading), math.sin(heading)
    P[0, 0] += A * ca * ca + L * sa * sa
    P[1, 1] += A * sa * sa + L * ca * ca
    P[0, 1] += (A - L) * ca * sa
    P[1, 0] += (A - L) * ca * sa
    for a, e in ((0, -sa), (1, ca)):  # the lateral direction's share of x and y
        P[a, 2] += Lp * e
        P[2, a] += Lp * e
        P[a, 4] += Lr * e
        P[4, a] += Lr * e
    P[0, 3] += Au * ca
    P[3, 0] += Au * ca
    P[1, 3] += Au * sa
    P[3, 1] += Au * sa
    P[2, 2] += qh * T + qr * T ** 3 / 3.0
    P[2, 4] += qr * T * T / 2.0
    P[4, 2] += qr * T * T / 2.0
    P[3, 3] += qu * T
    P[4, 4] += qr * T


@njit(cache=True)
def limm_init(m, P, mu, ag, om, z, var, cfg, fresh_rates):
    """Start every model at the fix z (5,: x, y, psi, u, r) with variances var (5,); the mode
    probabilities from the modes' shares of time and the fix's turn rate, their ages ag (K,) the
    stationary ones; with ``fresh_rates`` the env's rates om (2,) at the middle of the tier's ranges."""
    if fresh_rates:
        om[0] = 0.5 * (cfg[C_WT_LO] + cfg[C_WT_HI])
        om[1] = 0.5 * (cfg[C_WU_LO] + cfg[C_WU_HI])
    vr = var[4] + cfg[C_SRATE] ** 2
    tot = 0.0
    for j in range(K):
        for a in range(NX):
            m[j, a] = z[a]
            for b in range(NX):
                P[j, a, b] = 0.0
            P[j, a, a] = var[a]
        e = z[4] - _rate(j, om[0], om[1])
        mu[j] = cfg[C_PI + j] * math.exp(-0.5 * e * e / vr)
        tot += mu[j]
        ag[j] = _stationary_age(cfg, j)
    for j in range(K):
        mu[j] = mu[j] / tot if tot > 0.0 else cfg[C_PI + j]


@njit(cache=True)
def work():
    """Scratch arrays of :func:`limm_update` and :func:`limm_predict`, allocated once per batch
    chunk and reused: Pi (K, K), c (K,), x0, mp, nu (K, 5), P0, Pp (K, 5, 5), d (5,), J, tmp, S,
    Si, Kg (5, 5), tab (NQ + 1, 4), S2, S2i (2, 2), R (5,), ll (K,)."""
    return (np.empty((K, K)), np.empty(K), np.empty((K, NX)), np.empty((K, NX)), np.empty((K, NX)),
            np.empty((K, NX, NX)), np.empty((K, NX, NX)), np.empty(NX), np.empty((NX, NX)), np.empty((NX, NX)),
            np.empty((NX, NX)), np.empty((NX, NX)), np.empty((NX, NX)), np.empty((NQ + 1, 4)), np.empty((2, 2)),
            np.empty((2, 2)), np.empty(NX), np.empty(K))


@njit(cache=True)
def _jpjt(J, A, tmp, out):
    """out = J A J^T for a model's Jacobian J (:func:`_prop`: the identity but for J[0|1, 2:5],
    J[2, 4], J[3, 3], J[4, 4]), its zeros skipped."""
    for b in range(NX):
        tmp[0, b] = A[0, b] + J[0, 2] * A[2, b] + J[0, 3] * A[3, b] + J[0, 4] * A[4, b]
        tmp[1, b] = A[1, b] + J[1, 2] * A[2, b] + J[1, 3] * A[3, b] + J[1, 4] * A[4, b]
        tmp[2, b] = A[2, b] + J[2, 4] * A[4, b]
        tmp[3, b] = J[3, 3] * A[3, b]
        tmp[4, b] = J[4, 4] * A[4, b]
    for a in range(NX):
        out[a, 0] = tmp[a, 0] + J[0, 2] * tmp[a, 2] + J[0, 3] * tmp[a, 3] + J[0, 4] * tmp[a, 4]
        out[a, 1] = tmp[a, 1] + J[1, 2] * tmp[a, 2] + J[1, 3] * tmp[a, 3] + J[1, 4] * tmp[a, 4]
        out[a, 2] = tmp[a, 2] + J[2, 4] * tmp[a, 4]
        out[a, 3] = J[3, 3] * tmp[a, 3]
        out[a, 4] = J[4, 4] * tmp[a, 4]


@njit(cache=True)
def limm_update(m, P, mu, ag, om, ng, T, z, var, cfg, w):
    """One fix z (5,) with variances var (5,), T seconds after the filter's last: interaction
    (mixing), prediction of every model, gating, update, the new mode probabilities and the rates'
    adaptation; the modes' ages ag (K,): the mass that stayed aged by T, the mass that entered
    T / 2 old (all in place); w: :func:`work`. Returns True if the fix's position was gated out."""
    Pi, c, x0, mp, nu, P0, Pp, d, J, tmp, S, Si, Kg, tab, S2, S2i, R, ll = w
    _transition(T, ag, cfg, Pi)
    for k in range(K):
        c[k] = 0.0
    for i in range(K):
        for k in range(K):
            c[k] += mu[i] * Pi[i, k]
    for j in range(K):
        if c[j] > 0.0:
            stay = mu[j] * Pi[j, j]
            ag[j] = (stay * (ag[j] + T) + (c[j] - stay) * 0.5 * T) / c[j]
    for j in range(K):
        if cfg[C_PI + j] == 0.0:
            continue
        cj = max(c[j], 1e-300)
        for a in range(NX):
            x0[j, a] = m[j, a]
        for i in range(K):  # x0_j = m_j + sum_i w_ij (m_i - m_j), the heading difference wrapped
            wi = mu[i] * Pi[i, j] / cj
            if i == j or wi == 0.0:
                continue
            for a in range(NX):
                d[a] = m[i, a] - m[j, a]
            d[2] = _wrap_d(d[2])
            for a in range(NX):
                x0[j, a] += wi * d[a]
        for a in range(NX):
            for b in range(NX):
                P0[j, a, b] = 0.0
        for i in range(K):  # P0_j = sum_i w_ij (P_i + e e^T), e = m_i - x0_j
            wi = mu[i] * Pi[i, j] / cj
            if wi == 0.0:
                continue
            for a in range(NX):
                d[a] = m[i, a] - x0[j, a]
            d[2] = _wrap_d(d[2])
            for a in range(NX):
                for b in range(NX):
                    P0[j, a, b] += wi * (P[i, a, b] + d[a] * d[b])
    _nodes(T, cfg, tab)
    for j in range(K):
        if cfg[C_PI + j] == 0.0:
            continue
        r = _rate(j, om[0], om[1])
        _prop(x0[j], T, r, _ucmd(j, cfg), tab, mp[j], J, True)
        _jpjt(J, P0[j], tmp, Pp[j])
        _add_noise(Pp[j], T, 0.5 * (x0[j, 2] + mp[j, 2]), x0[j, 3], cfg[C_QU], cfg[C_QH], cfg[C_QR])
    # the position gate: outside it for every model -> the position is not used
    dmin = math.inf
    for j in range(K):
        if cfg[C_PI + j] == 0.0:
            continue
        for a in range(NX):
            nu[j, a] = z[a] - mp[j, a]
        nu[j, 2] = _wrap_d(nu[j, 2])
        dmin = min(dmin, gate_distance(Pp, nu, var, j, S2, S2i))
    gated = cfg[C_GATE] > 0.0 and dmin > GATE_POS
    for a in range(NX):
        R[a] = var[a]
    if gated:
        R[0] = 1e8
        R[1] = 1e8
    for j in range(K):
        ll[j] = -math.inf
    for j in range(K):
        if cfg[C_PI + j] == 0.0:
            continue
        ll[j] = model_update(Pp, mp, nu, R, m, P, j, S, Si, Kg)
    top = -math.inf
    for j in range(K):
        top = max(top, ll[j])
    tot = 0.0
    for j in range(K):
        mu[j] = c[j] * math.exp(ll[j] - top) if cfg[C_PI + j] > 0.0 else 0.0
        tot += mu[j]
    for j in range(K):
        mu[j] /= tot
    # the rates' adaptation to the measured turn rate while a turn model holds the probability
    g, ar = cfg[C_ADAPT], abs(z[4])
    if mu[TURN_L] + mu[TURN_R] > 0.8 and ar > 0.5 * om[0]:
        om[0] = min(max(om[0] + g * (ar - om[0]), cfg[C_WT_LO]), cfg[C_WT_HI])
    if mu[UTURN_L] + mu[UTURN_R] > 0.8 and ar > 0.5 * om[1]:
        om[1] = min(max(om[1] + g * (ar - om[1]), cfg[C_WU_LO]), cfg[C_WU_HI])
    ng[0] = ng[0] + 1 if gated else 0
    if ng[0] >= 2:
        limm_init(m, P, mu, ag, om, z, var, cfg, False)
        ng[0] = 0
    return gated


@njit(cache=True)
def limm_predict(m, mu, ag, om, T, cfg, pm, pcs, pc, sq, sp0, w):
    """The present of every model T seconds after the fix: means pm (K, 5), (cos, sin) of their
    headings pcs (K, 2) and the mode probabilities pc (K,); for the steps that follow, each mode's
    exp(-k lam T) into sq (K,) and 1 / its survival polynomial at its age into sp0 (K,); w: :func:`work`."""
    Pi, J, tab = w[0], w[8], w[13]
    _transition(T, ag, cfg, Pi)
    _nodes(T, cfg, tab)
    k = cfg[C_SHAPE]
    for j in range(K):
        pc[j] = 0.0
        lam = cfg[C_LAM + j]
        sq[j] = math.exp(-k * lam * T)
        sp0[j] = 1.0 / _surv_poly(k * lam * ag[j], k)
    for i in range(K):
        for j in range(K):
            pc[j] += mu[i] * Pi[i, j]
    for j in range(K):
        r = _rate(j, om[0], om[1])
        _prop(m[j], T, r, _ucmd(j, cfg), tab, pm[j], J, False)
        pcs[j, 0] = math.cos(pm[j, 2])
        pcs[j, 1] = math.sin(pm[j, 2])


@njit(cache=True, inline="always")
def _present_out(pm, pcs, pc, om, i, out, odom, pf, c, s, T):
    """Env i's present estimate (the models' means weighted by their probabilities, the heading
    as the weighted circular mean on the likeliest model's branch) into its output row."""
    x = y = u = r = sx = sy = 0.0
    best, jb = -1.0, 0
    for j in range(K):
        w = pc[i, j]
        x += w * pm[i, j, 0]
        y += w * pm[i, j, 1]
        u += w * pm[i, j, 3]
        r += w * pm[i, j, 4]
        sx += w * pcs[i, j, 0]
        sy += w * pcs[i, j, 1]
        if w > best:
            best, jb = w, j
    ref = pm[i, jb, 2]
    h = ref + _wrap_d(math.atan2(sy, sx) - ref)
    write_estimate(out, i, x, y, h, u, r, odom[i, 0], odom[i, 1], c, s, _wrap_d(h - pf), T)


def _limm_chunks(chunks, obs, reset, cfg, t_now, odom, vel, psi_f, init, t_fix, m, P, mu, ag, ng, om, pm, pcs, pc, sq,
                 sp0, fx, out, src, copy_rows, partial):
    """:func:`limm_step` over ``chunks`` contiguous blocks of envs (a parallel loop in the threaded
    build); with ``copy_rows`` each env's state is first copied from ``src`` (with ``partial`` the
    state at the last fix only where src's ``fx`` says it changed). The per-step advance is written
    out with whole-array indexing (no per-env views: numba counts references of each)."""
    n = obs.shape[0]
    (s_t_now, s_odom, s_vel, s_psi_f, s_init, s_t_fix, s_m, s_P, s_mu, s_ag, s_ng, s_om, s_pm, s_pcs, s_pc, s_sq,
     s_sp0, s_fx) = src
    dt, tau = cfg[C_DT], cfg[C_TAU]
    au, ar = math.exp(-dt / cfg[C_TU]), math.exp(-dt / cfg[C_TR])  # the lags over one step
    gu, gr = cfg[C_TU] * (1.0 - au), cfg[C_TR] * (1.0 - ar)
    v1 = cfg[C_V1] != 0.0
    kk = cfg[C_SHAPE]
    edt = np.empty(K)  # each mode's exp(-k lam dt)
    klam = np.empty(K)
    for j in range(K):
        klam[j] = kk * cfg[C_LAM + j]
        edt[j] = math.exp(-klam[j] * dt)
    for ch in prange(chunks):
        stay = np.empty(K)
        w = work()
        z = np.empty(5)
        var = np.empty(5)
        for i in range(ch * n // chunks, (ch + 1) * n // chunks):
            if copy_rows:  # env i's row of every state array from src
                t_now[i] = s_t_now[i]
                psi_f[i] = s_psi_f[i]
                for a in range(2):
                    odom[i, a] = s_odom[i, a]
                    vel[i, a] = s_vel[i, a]
                for j in range(K):
                    pc[i, j] = s_pc[i, j]
                    sq[i, j] = s_sq[i, j]
                    sp0[i, j] = s_sp0[i, j]
                    pcs[i, j, 0] = s_pcs[i, j, 0]
                    pcs[i, j, 1] = s_pcs[i, j, 1]
                    for a in range(NX):
                        pm[i, j, a] = s_pm[i, j, a]
                if s_fx[i] or not partial:  # the state at the last fix (else this row holds it already)
                    init[i] = s_init[i]
                    t_fix[i] = s_t_fix[i]
                    ng[i, 0] = s_ng[i, 0]
                    om[i, 0] = s_om[i, 0]
                    om[i, 1] = s_om[i, 1]
                    for j in range(K):
                        mu[i, j] = s_mu[i, j]
                        ag[i, j] = s_ag[i, j]
                        for a in range(NX):
                            m[i, j, a] = s_m[i, j, a]
                            for b in range(NX):
                                P[i, j, a, b] = s_P[i, j, a, b]
            pf, c, s = odometry_step(obs, reset, i, odom, vel, t_now, init, dt)
            if reset[i]:
                ng[i, 0] = 0
            psi_f[i] = pf
            fresh, t_meas = fix_timing(obs, i, t_now[i], init[i], t_fix[i], v1, tau)
            fx[i] = fresh or reset[i]  # (the state at the last fix changes in this step)
            if fresh:
                dx, dy = fix_measurement(obs, i, odom, pf, c, s, z)
                fix_variances(cfg[C_SPOS], cfg[C_SPM], cfg[C_SPSI], cfg[C_SVEL], cfg[C_SR], dx, dy, var)
                if init[i]:
                    z[2] = m[i, 0, 2] + _wrap(z[2] - m[i, 0, 2])  # the heading on the filter's branch
                    limm_update(m[i], P[i], mu[i], ag[i], om[i], ng[i], t_meas - t_fix[i], z, var, cfg, w)
                else:
                    limm_init(m[i], P[i], mu[i], ag[i], om[i], z, var, cfg, True)
                    init[i] = True
                    ng[i, 0] = 0
                t_fix[i] = t_meas
                limm_predict(m[i], mu[i], ag[i], om[i], t_now[i] - t_meas, cfg, pm[i], pcs[i], pc[i], sq[i], sp0[i], w)
            elif init[i]:  # one control step of every model and of the mode probabilities
                for j in range(K):
                    # the turn rate lags toward the model's; over the step the heading turns by th
                    # at a constant rate (the quadrature's motion within 1e-6 m per step)
                    rc = _rate(j, om[i, 0], om[i, 1])
                    rj = pm[i, j, 4]
                    th = rc * dt + (rj - rc) * gr
                    pm[i, j, 4] = rc + (rj - rc) * ar
                    uj = pm[i, j, 3]
                    if j == LOITER or j == SPRINT:
                        uc = cfg[C_VL] if j == LOITER else cfg[C_VS]
                        dd = uc * dt + (uj - uc) * gu
                        pm[i, j, 3] = uc + (uj - uc) * au
                    else:
                        dd = uj * dt
                    hh = 0.5 * th
                    h2 = hh * hh
                    ch = 1.0 - h2 / 2.0 + h2 * h2 / 24.0  # cos, sin of hh (|hh| < 0.02: to 1e-13)
                    sh = hh * (1.0 - h2 / 6.0 + h2 * h2 / 120.0)
                    sc = 1.0 - h2 / 6.0 + h2 * h2 / 120.0  # the chord's length / the arc's
                    ck, sk = pcs[i, j, 0], pcs[i, j, 1]
                    cm = ck * ch - sk * sh
                    sm = sk * ch + ck * sh
                    pm[i, j, 0] += dd * sc * cm
                    pm[i, j, 1] += dd * sc * sm
                    pm[i, j, 2] += th
                    pcs[i, j, 0] = cm * ch - sm * sh
                    pcs[i, j, 1] = sm * ch + cm * sh
                # the mode probabilities now (as _transition over T from the fix, in steps)
                T = t_now[i] - t_fix[i]
                for j in range(K):
                    sq[i, j] *= edt[j]
                    stay[j] = sq[i, j] * _surv_poly(klam[j] * (ag[i, j] + T), kk) * sp0[i, j]
                back = 0.0
                for j in range(1, K):
                    if cfg[C_PI + j] > 0.0:
                        pc[i, j] = mu[i, j] * stay[j] + mu[i, CRUISE] * (1.0 - stay[CRUISE]) * cfg[C_SPLIT + j]
                        back += mu[i, j] * (1.0 - stay[j])
                pc[i, CRUISE] = mu[i, CRUISE] * stay[CRUISE] + back
            if init[i]:
                _present_out(pm, pcs, pc, om, i, out, odom, pf, c, s, t_now[i] - t_fix[i])
            else:
                for j in range(NE):
                    out[i, j] = 0.0


#: the step, serial and on numba's threads (per env the same operations: the same bits)
_limm_serial = njit(cache=True)(_limm_chunks)
_limm_threads = recompiled(_limm_chunks, "_limm_chunks_par", cache=True, parallel=True)
#: batches from this many envs are filtered on numba's threads (as the vector env steps them)
THREADED_MIN_ENVS = 256


def limm_step(obs, reset, cfg, t_now, odom, vel, psi_f, init, t_fix, m, P, mu, ag, ng, om, pm, pcs, pc, sq, sp0, fx,
              out, src=None, partial=False):
    """One control step of the model-aware IMM for every env (all arrays updated in place).

    obs (N, 20) v1 observations; reset (N,) bool; cfg: :func:`limm_config`. State: t_now, psi_f,
    t_fix (N,), odom, vel (N, 2), init (N,) bool, m (N, K, 5), P (N, K, 5, 5), mu (N, K), ag (N, K)
    (the modes' ages) at the last fix, ng (N, 1) int64 (gated fixes in a row), om (N, 2) the env's
    turn and U-turn rates; the present: pm (N, K, 5), pcs (N, K, 2), pc (N, K), sq, sp0 (N, K)
    (:func:`limm_predict`); fx (N,) bool: the env's state at the last fix changed in this step (a
    fix, or the episode's start). ``src``: None (the state arrays are updated in place) or a tuple
    of state arrays of the same shapes (t_now .. fx) to start from (the state arrays given are then
    overwritten: a peek's copy made inside the kernel); with ``partial`` the arrays given are the
    state src was stepped from, so the state at the last fix is copied only where src's fx is set
    (the rest of it is already equal: two thirds of the state's bytes). out (N, NE): the present
    estimate (the OU0 kernel's columns E_*). From :data:`THREADED_MIN_ENVS` envs on, the envs are
    split over numba's threads (the same result)."""
    n = obs.shape[0]
    threads = numba.get_num_threads() if n >= THREADED_MIN_ENVS else 1
    step = _limm_threads if threads > 1 else _limm_serial
    dst = (t_now, odom, vel, psi_f, init, t_fix, m, P, mu, ag, ng, om, pm, pcs, pc, sq, sp0, fx)
    step(threads, obs, reset, cfg, *dst, out, dst if src is None else tuple(src), src is not None,
         bool(partial) and src is not None)


@njit(cache=True)
def limm_filter_fixes(t_meas, z, var, cfg, t_query):
    """Run the filter over fixes given in *arrival* order (times of measurement t_meas (F,),
    values z (F, 5), variances var (F, 5)): a fix older than one already used is inserted where
    its measurement time belongs and the filter is re-run from the state before it
    (retrodiction), so the result is that of the fixes in measurement order. Returns, after each
    arrival, the present (x, y, psi, u, r) (F, 5) at t_query (F,) [s, the clock of t_meas] and the
    mode probabilities at the newest fix (F, K)."""
    F = t_meas.shape[0]
    order = np.empty(F, dtype=np.int64)
    snap_m, snap_P = np.empty((F, K, NX)), np.empty((F, K, NX, NX))
    snap_mu, snap_om, snap_ng = np.empty((F, K)), np.empty((F, 2)), np.empty((F, 1), dtype=np.int64)
    snap_ag = np.empty((F, K))
    m, P, mu, om, ag = np.empty((K, NX)), np.empty((K, NX, NX)), np.empty(K), np.empty(2), np.empty(K)
    sq, sp0 = np.empty(K), np.empty(K)
    ng = np.zeros(1, dtype=np.int64)
    pm, pcs, pc = np.empty((K, NX)), np.empty((K, 2)), np.empty(K)
    out = np.empty((F, 5))
    x = np.empty(5)
    mus = np.empty((F, K))
    w = work()
    nbuf = 0
    for f in range(F):
        pos = insert_by_time(order, nbuf, t_meas, f)
        nbuf += 1
        for k in range(pos, nbuf):  # re-run from the snapshot before the inserted fix
            j = order[k]
            if k == 0:
                limm_init(m, P, mu, ag, om, z[j], var[j], cfg, True)
                ng[0] = 0
            else:
                m[:, :] = snap_m[k - 1]
                P[:, :, :] = snap_P[k - 1]
                mu[:] = snap_mu[k - 1]
                om[:] = snap_om[k - 1]
                ag[:] = snap_ag[k - 1]
                ng[0] = snap_ng[k - 1, 0]
                zz = z[j].copy()
                zz[2] = m[0, 2] + _wrap(zz[2] - m[0, 2])
                limm_update(m, P, mu, ag, om, ng, t_meas[j] - t_meas[order[k - 1]], zz, var[j], cfg, w)
            snap_m[k] = m
            snap_P[k] = P
            snap_mu[k] = mu
            snap_om[k] = om
            snap_ag[k] = ag
            snap_ng[k, 0] = ng[0]
        last = nbuf - 1
        m[:, :] = snap_m[last]
        mu[:] = snap_mu[last]
        om[:] = snap_om[last]
        ag[:] = snap_ag[last]
        limm_predict(m, mu, ag, om, t_query[f] - t_meas[order[last]], cfg, pm, pcs, pc, sq, sp0, w)
        _mixture(pm, pcs, pc, om, x)
        out[f] = x
        mus[f] = mu
    return out, mus


@njit(cache=True, inline="always")
def _mixture(pm, pcs, pc, om, out):
    """The mixture's (x, y, psi, u, r) from the models' present means into out (5,): the weighted
    means, the heading as the weighted circular mean on the likeliest model's branch."""
    sx = sy = 0.0
    best, jb = -1.0, 0
    for a in range(5):
        out[a] = 0.0
    for j in range(K):
        w = pc[j]
        out[0] += w * pm[j, 0]
        out[1] += w * pm[j, 1]
        out[3] += w * pm[j, 3]
        out[4] += w * pm[j, 4]
        sx += w * pcs[j, 0]
        sy += w * pcs[j, 1]
        if w > best:
            best, jb = w, j
    out[2] = pm[jb, 2] + _wrap_d(math.atan2(sy, sx) - pm[jb, 2])


@njit(cache=True)
def limm_trajectory(m, mu, ag, om, init, T, cfg):
    """The present-state prediction of every env at the spans T (N, S) after its last fix (the
    mixture of :func:`limm_predict`), (N, S, 5); zeros where ``init`` is False."""
    n, S = T.shape
    out = np.zeros((n, S, 5))
    pm, pcs, pc, sq, sp0 = np.empty((K, NX)), np.empty((K, 2)), np.empty(K), np.empty(K), np.empty(K)
    x = np.empty(5)
    w = work()
    for i in range(n):
        if not init[i]:
            continue
        for k in range(S):
            limm_predict(m[i], mu[i], ag[i], om[i], T[i, k], cfg, pm, pcs, pc, sq, sp0, w)
            _mixture(pm, pcs, pc, om[i], x)
            for a in range(5):
                out[i, k, a] = x[a]
    return out
