"""Numba kernel of the ``OU0`` target filter (:mod:`controllers.estimator`): the v1 tiers' own
target model with its structure, for a batch of envs in one call.

State (6): ``x, y, psi`` (odometry frame [m, m, rad]), ``u`` (surge [m/s]), ``r`` (yaw rate
[rad/s]), ``ub`` (the surge speed's mean [m/s]). The target does not slip sideways
(v = 0 in eq. (10) for every target this suite simulates), so sway is not a state and the
reported sway (pure fix noise) is not used. Motion between fixes (the OU means, exactly):

    u(s) = ub + (u0 - ub) e^{-s/tau_u},  r(s) = r0 e^{-s/tau_r},
    psi(s) = psi0 - r0 tau_r expm1(-s/tau_r),  p(s) = p0 + int_0^s u R(psi) [1, 0]^T,

the position integral by Gauss-Legendre quadrature (16 nodes over a gap between fixes, 4 over
one control step: exact to rounding for the spans met here), its Jacobian in closed form, the
discrete process noise by Simpson's rule over the span (as the numpy models). ``tau = inf``
gives the constant-turn limit (u and r constant).

Per env the kernel keeps the filter at the newest fix's measurement time ``t_fix`` (a late fix
is an ordinary update) and, separately, the *present* state and covariance, advanced by one
control step at a time (a fix re-predicts the present from ``t_fix``). Options per call:
adaptive process noise (the OU variances of speed and turn rate estimated per episode from the
received fixes, shrunk to the tier's prior) and a smoothed output (a fix that moves the present
estimate does not step the returned pose: the jump decays with time constant ``smooth_s``).
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import njit, prange

from auv_follow_env.dynamics import recompiled

# config vector (float64) indices
C_DT, C_TAU, C_V1, C_TU, C_TR = 0, 1, 2, 3, 4
C_SPM, C_SPSI, C_SVEL, C_SR, C_SUB0 = 5, 6, 7, 8, 9
C_QU, C_QR, C_QUB = 10, 11, 12  # prior white-noise intensities on u, r, ub
C_ADAPT, C_N0, C_SMOOTH, C_SPOS = 13, 14, 15, 16
NC = 17

# per-env statistics for the adaptive noise (Welford on the reported speed, sum of r^2)
S_N, S_MU, S_M2, S_R2 = 0, 1, 2, 3
NS = 4

# observation columns (either layout)
O_U, O_V, O_R, O_C, O_S, O_DX, O_DY, O_TC, O_TS, O_TU, O_TV, O_TR = range(12)
O_AGE, O_SINCE, O_NEW, O_HAS = 16, 17, 18, 19

# output columns
E_VALID, E_X, E_Y, E_PSI, E_U, E_R, E_RX, E_RY, E_RPSI, E_AGE = range(10)
NE = 10

_GL16_X, _GL16_W = np.polynomial.legendre.leggauss(16)
_GL4_X, _GL4_W = np.polynomial.legendre.leggauss(4)


@njit(cache=True, inline="always")
def _wrap(a):
    return math.atan2(math.sin(a), math.cos(a))


@njit(cache=True, inline="always")
def _decay(s, tau):
    """e^{-s/tau} and tau (1 - e^{-s/tau}) = -tau expm1(-s/tau) (-> s as tau -> inf)."""
    if math.isinf(tau):
        return 1.0, s
    return math.exp(-s / tau), -tau * math.expm1(-s / tau)


@njit(cache=True)
def _propagate(x, T, tu, tr, gx, gw, out, F):
    """Mean of ``x`` after T seconds into ``out``; its Jacobian into ``F`` (6x6)."""
    px = 0.0
    py = 0.0
    dpx_u0 = 0.0
    dpx_ub = 0.0
    dpx_r0 = 0.0
    dpy_u0 = 0.0
    dpy_ub = 0.0
    dpy_r0 = 0.0
    psi0, u0, r0, ub = x[2], x[3], x[4], x[5]
    for k in range(gx.shape[0]):
        s = 0.5 * T * (1.0 + gx[k])
        w = 0.5 * T * gw[k]
        eu, _ = _decay(s, tu)
        _, gr = _decay(s, tr)
        psi = psi0 + r0 * gr
        u = ub + (u0 - ub) * eu
        c = math.cos(psi)
        sn = math.sin(psi)
        px += w * u * c
        py += w * u * sn
        dpx_u0 += w * eu * c
        dpy_u0 += w * eu * sn
        dpx_ub += w * (1.0 - eu) * c
        dpy_ub += w * (1.0 - eu) * sn
        dpx_r0 -= w * u * sn * gr
        dpy_r0 += w * u * c * gr
    euT, _ = _decay(T, tu)
    erT, grT = _decay(T, tr)
    out[0] = x[0] + px
    out[1] = x[1] + py
    out[2] = psi0 + r0 * grT
    out[3] = ub + (u0 - ub) * euT
    out[4] = r0 * erT
    out[5] = ub
    for a in range(6):
        for b in range(6):
            F[a, b] = 0.0
    F[0, 0] = 1.0
    F[0, 2] = -py
    F[0, 3] = dpx_u0
    F[0, 4] = dpx_r0
    F[0, 5] = dpx_ub
    F[1, 1] = 1.0
    F[1, 2] = px
    F[1, 3] = dpy_u0
    F[1, 4] = dpy_r0
    F[1, 5] = dpy_ub
    F[2, 2] = 1.0
    F[2, 4] = grT
    F[3, 3] = euT
    F[3, 5] = 1.0 - euT
    F[4, 4] = erT
    F[5, 5] = 1.0


def step_constants(dt: float, tu: float, tr: float) -> np.ndarray:
    """Per-node constants of the one-control-step mean propagation (3 Gauss-Legendre nodes: exact
    to rounding over 0.05 s): rows (w, e^{-s/tu}, tau_r (1 - e^{-s/tr})) per node, then
    (e^{-dt/tu}, e^{-dt/tr}, tau_r (1 - e^{-dt/tr})) in the last column block."""
    gx, gw = np.polynomial.legendre.leggauss(3)
    s = 0.5 * dt * (1.0 + gx)
    out = np.zeros((3, 4))
    out[0, :3] = 0.5 * dt * gw
    out[1, :3] = np.ones(3) if np.isinf(tu) else np.exp(-s / tu)
    out[2, :3] = s if np.isinf(tr) else -tr * np.expm1(-s / tr)
    out[0, 3] = 1.0 if np.isinf(tu) else np.exp(-dt / tu)
    out[1, 3] = 1.0 if np.isinf(tr) else np.exp(-dt / tr)
    out[2, 3] = dt if np.isinf(tr) else -tr * np.expm1(-dt / tr)
    return out


@njit(cache=True, inline="always")
def _step_mean_row(x, i, k):
    """Advance the mean of row i of x (N, 6) in place by one control step (constants ``k`` of
    :func:`step_constants`); indexing the whole array (a row view per env costs numba a reference
    count)."""
    psi0, u0, r0, ub = x[i, 2], x[i, 3], x[i, 4], x[i, 5]
    px = 0.0
    py = 0.0
    for j in range(3):
        psi = psi0 + r0 * k[2, j]
        u = ub + (u0 - ub) * k[1, j]
        px += k[0, j] * u * math.cos(psi)
        py += k[0, j] * u * math.sin(psi)
    x[i, 0] += px
    x[i, 1] += py
    x[i, 2] = psi0 + r0 * k[2, 3]
    x[i, 3] = ub + (u0 - ub) * k[0, 3]
    x[i, 4] = r0 * k[1, 3]


@njit(cache=True, inline="always")
def _mat6(A, B, out):
    """out = A B for 6x6 arrays (out must not alias A or B)."""
    for a in range(6):
        for b in range(6):
            acc = 0.0
            for k in range(6):
                acc += A[a, k] * B[k, b]
            out[a, b] = acc


@njit(cache=True)
def _predict_cov(P, F, Fh, T, qu, qr, qub, Pout, tmp):
    """Pout = F P F^T + Q(T), Q by Simpson's rule with F at 0 (identity), T/2 and T."""
    _mat6(F, P, tmp)
    q = (qu, qr, qub)
    for a in range(6):
        for b in range(a, 6):
            acc = 0.0
            for k in range(6):
                acc += tmp[a, k] * F[b, k]
            # Simpson: T/6 (Qc + 4 Fh Qc Fh^T + F Qc F^T); Qc diagonal on states 3, 4, 5
            qq = 0.0
            for j in range(3):
                col = 3 + j
                qj = q[j]
                e = qj if (a == col and b == col) else 0.0
                qq += e + 4.0 * qj * Fh[a, col] * Fh[b, col] + qj * F[a, col] * F[b, col]
            v = acc + T / 6.0 * qq
            Pout[a, b] = v
            Pout[b, a] = v


@njit(cache=True)
def _span(x, P, T, tu, tr, gx, gw, qu, qr, qub, xm, F, xh, Fh, Pout, tmp):
    """Mean (into xm) and covariance (into Pout, which may be P) of (x, P) after T seconds."""
    _propagate(x, T, tu, tr, gx, gw, xm, F)
    _propagate(x, 0.5 * T, tu, tr, gx, gw, xh, Fh)
    _predict_cov(P, F, Fh, T, qu, qr, qub, Pout, tmp)


@njit(cache=True)
def _update(x, P, z, var, Kb, S, tmp):
    """Kalman update of (x, P) with the fix z (5: x, y, psi, u, r), noise variances var (5);
    Joseph form. Returns False if S is not positive definite (no update)."""
    # S = P[:5, :5] + diag(var); Cholesky in place (lower) in S
    for a in range(5):
        for b in range(5):
            S[a, b] = P[a, b] + (var[a] if a == b else 0.0)
    for j in range(5):
        d = S[j, j]
        for k in range(j):
            d -= S[j, k] * S[j, k]
        if not d > 0.0:
            return False
        d = math.sqrt(d)
        S[j, j] = d
        for i in range(j + 1, 5):
            acc = S[i, j]
            for k in range(j):
                acc -= S[i, k] * S[j, k]
            S[i, j] = acc / d
    # K = P H^T S^-1: solve S K^T = H P  (rows of H P are P[0:5, :]) for each of the 6 columns
    for c in range(6):
        yv = np.empty(5)
        for i in range(5):
            acc = P[i, c]
            for k in range(i):
                acc -= S[i, k] * yv[k]
            yv[i] = acc / S[i, i]
        for i in range(4, -1, -1):
            acc = yv[i]
            for k in range(i + 1, 5):
                acc -= S[k, i] * yv[k]
            yv[i] = acc / S[i, i]
        for i in range(5):
            Kb[c, i] = yv[i]  # K[c, i]
    innov = np.empty(5)
    for i in range(5):
        innov[i] = z[i] - x[i]
    innov[2] = _wrap(innov[2])
    for c in range(6):
        acc = 0.0
        for i in range(5):
            acc += Kb[c, i] * innov[i]
        x[c] += acc
    # Joseph: (I - K H) P (I - K H)^T + K R K^T
    IKH = np.zeros((6, 6))
    for a in range(6):
        IKH[a, a] = 1.0
        for i in range(5):
            IKH[a, i] -= Kb[a, i]
    _mat6(IKH, P, tmp)
    for a in range(6):
        for b in range(a, 6):
            acc = 0.0
            for k in range(6):
                acc += tmp[a, k] * IKH[b, k]
            for i in range(5):
                acc += Kb[a, i] * var[i] * Kb[b, i]
            P[a, b] = acc
            P[b, a] = acc
    return True


@njit(cache=True)
def _noise(cfg, stats, i, prior_qu, prior_qr):
    """(q_u, q_r) of env i: the prior, or adapted from its fixes (shrunk to the prior)."""
    if cfg[C_ADAPT] == 0.0:
        return prior_qu, prior_qr
    n = stats[i, S_N]
    n0 = cfg[C_N0]
    tu, tr = cfg[C_TU], cfg[C_TR]
    if math.isinf(tu) or math.isinf(tr):
        return prior_qu, prior_qr
    sv2 = cfg[C_SVEL] * cfg[C_SVEL]
    sr2 = cfg[C_SR] * cfg[C_SR]
    prior_vu = prior_qu * tu / 2.0
    prior_vr = prior_qr * tr / 2.0
    vu = prior_vu
    if n > 1.0:
        su = stats[i, S_M2] / (n - 1.0) - sv2
        vu = (n0 * prior_vu + (n - 1.0) * max(su, 0.0)) / (n0 + n - 1.0)
    vr = prior_vr
    if n > 0.0:
        sr = stats[i, S_R2] / n - sr2
        vr = (n0 * prior_vr + n * max(sr, 0.0)) / (n0 + n)
    return 2.0 * vu / tu, 2.0 * vr / tr


@njit(cache=True, inline="always")
def follower_motion(obs, i):
    """(psi_f, cos psi_f, sin psi_f, vx, vy): the follower's heading and inertial ground velocity
    from observation row i (shared by the target filters' odometry frames)."""
    pf = math.atan2(obs[i, O_S], obs[i, O_C])
    c = math.cos(pf)
    s = math.sin(pf)
    return pf, c, s, c * obs[i, O_U] - s * obs[i, O_V], s * obs[i, O_U] + c * obs[i, O_V]


@njit(cache=True, inline="always")
def advance_odometry(odom, vel, t_now, i, vx, vy, dt):
    """One control step of env i's odometry frame: the trapezoid rule on the ground velocity."""
    odom[i, 0] += 0.5 * dt * (vel[i, 0] + vx)
    odom[i, 1] += 0.5 * dt * (vel[i, 1] + vy)
    t_now[i] += dt


@njit(cache=True, inline="always")
def odometry_step(obs, reset, i, odom, vel, t_now, init, dt):
    """Env i's odometry frame at this control step (shared by the target filters): restarted at
    an episode's start (origin, clock 0, no fix yet), else advanced by :func:`advance_odometry`;
    the ground velocity kept for the next step. Returns (psi_f, cos psi_f, sin psi_f)."""
    pf, c, s, vx, vy = follower_motion(obs, i)
    if reset[i]:
        odom[i, 0] = 0.0
        odom[i, 1] = 0.0
        t_now[i] = 0.0
        init[i] = False
    else:
        advance_odometry(odom, vel, t_now, i, vx, vy, dt)
    vel[i, 0] = vx
    vel[i, 1] = vy
    return pf, c, s


@njit(cache=True, inline="always")
def fix_timing(obs, i, t_now, initialised, t_fix, v1, tau):
    """(fresh, t_meas): whether observation row i carries a fix newer than the filter's (v1: a new
    packet, or the held one before the first; v0: a fix ``tau`` old every step; a fix not newer
    than ``t_fix`` is stale or out of order) and its measurement time."""
    if v1:
        fresh = obs[i, O_HAS] > 0.5 and (obs[i, O_NEW] > 0.5 or not initialised)
        t_meas = t_now - obs[i, O_AGE]
    else:
        fresh = True
        t_meas = t_now - tau
    if fresh and initialised and not (t_meas > t_fix + 1e-6):
        fresh = False
    return fresh, t_meas


@njit(cache=True, inline="always")
def fix_variances(s_pos, s_pos_per_m, s_psi, s_vel, s_r, dx, dy, var):
    """The fix's noise variances into var (5,): position (x, y; its sigma grows with the range
    sqrt(dx^2 + dy^2)), heading, surge speed, turn rate (shared by the target filters)."""
    sp = s_pos + s_pos_per_m * math.sqrt(dx * dx + dy * dy)
    var[0] = sp * sp
    var[1] = sp * sp
    var[2] = s_psi * s_psi
    var[3] = s_vel * s_vel
    var[4] = s_r * s_r


@njit(cache=True, inline="always")
def write_estimate(out, i, x, y, h, u, r, ox, oy, c, s, rel_psi, age):
    """Env i's output row (columns E_*, shared by the target filters): the present pose x, y, h,
    speed u and turn rate r in the odometry frame, the same relative to the follower at (ox, oy)
    with heading cos c, sin s (rel_psi: the heading difference, wrapped by the caller), the age."""
    out[i, E_VALID] = 1.0
    out[i, E_X] = x
    out[i, E_Y] = y
    out[i, E_PSI] = h
    out[i, E_U] = u
    out[i, E_R] = r
    rx = x - ox
    ry = y - oy
    out[i, E_RX] = c * rx + s * ry
    out[i, E_RY] = -s * rx + c * ry
    out[i, E_RPSI] = rel_psi
    out[i, E_AGE] = age


@njit(cache=True, inline="always")
def fix_measurement(obs, i, odom, pf, c, s, z):
    """The fix of observation row i in env i's odometry frame into z (5,): x, y, heading, surge
    speed, turn rate; returns its offset (dx, dy) in the follower's body frame."""
    dx, dy = obs[i, O_DX], obs[i, O_DY]
    z[0] = odom[i, 0] + c * dx - s * dy
    z[1] = odom[i, 1] + s * dx + c * dy
    z[2] = pf + math.atan2(obs[i, O_TS], obs[i, O_TC])
    z[3] = obs[i, O_TU]
    z[4] = obs[i, O_TR]
    return dx, dy


def _ou0_chunks(chunks, obs, reset, cfg, kstep, t_now, odom, vel, psi_f, init, t_fix, x, P, xp, Pp, stale, dlt,
                stats, out, cov_out):
    """:func:`ou0_step` over ``chunks`` contiguous blocks of envs (a parallel loop in the threaded
    build), each block with its own scratch.

    The per-env body is written out here, indexing whole arrays (no per-env views on the common
    path): a helper called with ~38 arguments, or a view per env, costs numba an atomic reference
    count per array and env, which took most of this kernel's time (the same operations either
    way)."""
    n = obs.shape[0]
    want_cov = cov_out.shape[0] > 0
    dt = cfg[C_DT]
    tu, tr = cfg[C_TU], cfg[C_TR]
    v1 = cfg[C_V1] != 0.0
    sm = cfg[C_SMOOTH]
    a_sm = math.exp(-dt / sm) if sm > 0.0 else 0.0
    for ch in prange(chunks):
        F = np.empty((6, 6))
        Fh = np.empty((6, 6))
        tmp = np.empty((6, 6))
        Kb = np.empty((6, 5))
        S = np.empty((5, 5))
        xm = np.empty(6)
        xh = np.empty(6)
        z = np.empty(5)
        var = np.empty(5)
        old = np.empty(3)
        for i in range(ch * n // chunks, (ch + 1) * n // chunks):
            pf, c, s = odometry_step(obs, reset, i, odom, vel, t_now, init, dt)
            if reset[i]:
                for j in range(3):
                    dlt[i, j] = 0.0
                for j in range(NS):
                    stats[i, j] = 0.0
            else:
                # the present advances one control step (and the smoothing offset decays)
                if init[i]:
                    if want_cov and not stale[i]:
                        qu, qr = _noise(cfg, stats, i, cfg[C_QU], cfg[C_QR])
                        _span(xp[i], Pp[i], dt, tu, tr, _GL4_X, _GL4_W, qu, qr, cfg[C_QUB], xm, F, xh, Fh, Pp[i], tmp)
                    else:
                        stale[i] = True
                    _step_mean_row(xp, i, kstep)
                    for j in range(3):
                        dlt[i, j] *= a_sm
            psi_f[i] = pf
            # a newer fix?
            fresh, t_meas = fix_timing(obs, i, t_now[i], init[i], t_fix[i], v1, cfg[C_TAU])
            if fresh:
                dx, dy = fix_measurement(obs, i, odom, pf, c, s, z)
                fix_variances(cfg[C_SPOS], cfg[C_SPM], cfg[C_SPSI], cfg[C_SVEL], cfg[C_SR], dx, dy, var)
                # adaptive statistics (Welford on u, second moment of r)
                nn = stats[i, S_N] + 1.0
                d = z[3] - stats[i, S_MU]
                stats[i, S_MU] += d / nn
                stats[i, S_M2] += d * (z[3] - stats[i, S_MU])
                stats[i, S_R2] += z[4] * z[4]
                stats[i, S_N] = nn
                qu, qr = _noise(cfg, stats, i, cfg[C_QU], cfg[C_QR])
                had = init[i]
                if had:
                    old[0] = xp[i, 0] + dlt[i, 0]
                    old[1] = xp[i, 1] + dlt[i, 1]
                    old[2] = xp[i, 2] + dlt[i, 2]
                    T = t_meas - t_fix[i]
                    _span(x[i], P[i], T, tu, tr, _GL16_X, _GL16_W, qu, qr, cfg[C_QUB], xm, F, xh, Fh, P[i], tmp)
                    for j in range(6):
                        x[i, j] = xm[j]
                    _update(x[i], P[i], z, var, Kb, S, tmp)
                else:
                    for j in range(5):
                        x[i, j] = z[j]
                    x[i, 5] = z[3]
                    for a in range(6):
                        for b in range(6):
                            P[i, a, b] = 0.0
                    for j in range(5):
                        P[i, j, j] = var[j]
                    P[i, 5, 5] = cfg[C_SUB0] * cfg[C_SUB0]
                    init[i] = True
                t_fix[i] = t_meas
                # the present from the new filter state
                T = t_now[i] - t_meas
                _propagate(x[i], T, tu, tr, _GL16_X, _GL16_W, xm, F)
                if want_cov:
                    _propagate(x[i], 0.5 * T, tu, tr, _GL16_X, _GL16_W, xh, Fh)
                    _predict_cov(P[i], F, Fh, T, qu, qr, cfg[C_QUB], Pp[i], tmp)
                    stale[i] = False
                else:
                    stale[i] = True
                for j in range(6):
                    xp[i, j] = xm[j]
                if had and sm > 0.0:  # keep the returned pose where it was: the jump decays from here
                    dlt[i, 0] = old[0] - xp[i, 0]
                    dlt[i, 1] = old[1] - xp[i, 1]
                    dlt[i, 2] = _wrap(old[2] - xp[i, 2])
            # the returned estimate
            if init[i]:
                ex = xp[i, 0] + dlt[i, 0]
                ey = xp[i, 1] + dlt[i, 1]
                pt = xp[i, 2] + dlt[i, 2]
                write_estimate(out, i, ex, ey, pt, xp[i, 3], xp[i, 4], odom[i, 0], odom[i, 1], c, s, _wrap(pt - pf),
                               t_now[i] - t_fix[i])
                if want_cov and stale[i]:  # the present covariance from the filter at t_fix
                    T = t_now[i] - t_fix[i]
                    qu, qr = _noise(cfg, stats, i, cfg[C_QU], cfg[C_QR])
                    _span(x[i], P[i], T, tu, tr, _GL16_X, _GL16_W, qu, qr, cfg[C_QUB], xm, F, xh, Fh, Pp[i], tmp)
                    stale[i] = False
                if want_cov:
                    for a in range(6):
                        for b in range(6):
                            cov_out[i, a, b] = Pp[i, a, b]
            else:
                for j in range(NE):
                    out[i, j] = 0.0
                if want_cov:
                    for a in range(6):
                        for b in range(6):
                            cov_out[i, a, b] = 0.0



#: the step, serial and on numba's threads (per env the same operations: the same bits)
_ou0_serial = njit(cache=True)(_ou0_chunks)
_ou0_threads = recompiled(_ou0_chunks, "_ou0_chunks_par", cache=True, parallel=True)
#: batches from this many envs are filtered on numba's threads (as the vector env steps them)
THREADED_MIN_ENVS = 256


def ou0_step(obs, reset, cfg, kstep, t_now, odom, vel, psi_f, init, t_fix, x, P, xp, Pp, stale, dlt, stats, out,
             cov_out):
    """One control step of the OU0 filter for every env (all arrays updated in place).

    obs (N, W): observations (W = 16: v0, a fix ``tau`` old every step; W = 20: v1).
    reset (N,) bool: the episode starts at this observation.
    cfg: the config vector (C_*); kstep: :func:`step_constants`.
    State: t_now, psi_f (N,), odom, vel (N, 2), init (N,) bool, t_fix (N,), x, xp (N, 6),
    P, Pp (N, 6, 6), stale (N,) bool (Pp is not the present covariance: it is recomputed from
    the filter when next wanted), dlt (N, 3) (the smoothing offset of the returned pose), stats (N, NS).
    out (N, NE): the returned estimate (columns E_*); cov_out (N, 6, 6): the present covariance
    (or shape (0, 6, 6): not wanted).
    From :data:`THREADED_MIN_ENVS` envs on, the envs are split over numba's threads (the same
    result).
    """
    threads = numba.get_num_threads() if obs.shape[0] >= THREADED_MIN_ENVS else 1
    step = _ou0_threads if threads > 1 else _ou0_serial
    step(threads, obs, reset, cfg, kstep, t_now, odom, vel, psi_f, init, t_fix, x, P, xp, Pp, stale, dlt, stats, out,
         cov_out)
