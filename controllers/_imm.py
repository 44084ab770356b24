"""Numba kernel of the ``IMM`` target filter (:mod:`controllers.estimator`): the *generic*
estimator of the Leader tiers, built as tracking practice builds one without knowing the
target's generator: an interacting multiple model (Blom and Bar-Shalom, 1988) over a
constant-velocity (CV) and a coordinated-turn (CT) model, with a chi-square gate on the fix's
position, for a batch of envs in one call.

State (5): ``x, y, psi`` (odometry frame [m, m, rad]), ``u`` (surge [m/s]), ``r`` (turn rate
[rad/s]; held at 0 in CV). Motion over a span T: CV straight at speed u along psi; CT the exact
arc at constant u and r. Jacobians in closed form; the discrete process noise
int_0^T Phi Q_c Phi^T ds by Simpson's rule along the mean (composite, over ``C_QN`` panels; 0 or
1: the plain rule, nodes 0, T/2, T; experiments/quadrature_study.py measures what more panels
change). Process noise intensities: ``q_u``
[m^2/s^3] on the speed (both models), ``q_r`` [rad^2/s^3] on the turn rate (CT), ``q_h``
[rad^2/s] on the heading (CV: a slow drift of a straight course). The models switch as a
two-state Markov chain with mean sojourn ``tau_s`` [s] (probability of a switch over T:
(1 - e^{-2 T / tau_s}) / 2).

A fix whose position is outside the 99.9 % chi-square gate of every model (d^2 > 13.82, two
degrees of freedom) is taken without its position (heading, speed and turn rate still update);
after two gated fixes in a row the filter restarts at the newest fix (the target has moved far
from the prediction, or the filter has lost it).

Out-of-order fixes: in the envs the receiver keeps the newest packet, so a fix older than the
filter's is never observed (the link counts it as discarded). :func:`imm_filter_fixes` takes fixes
in *arrival* order and handles an out-of-order fix by retrodiction: it inserts the fix in the
buffer sorted by measurement time and re-runs the filter from the snapshot before it, so the
result equals that of the same fixes in measurement order.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import njit, prange

from auv_follow_env.dynamics import recompiled
from controllers._ou0 import (
    NE,
    fix_measurement,
    fix_timing,
    fix_variances,
    odometry_step,
    write_estimate,
)

# config vector (float64) indices
C_DT, C_TAU, C_V1 = 0, 1, 2
C_SPOS, C_SPM, C_SPSI, C_SVEL, C_SR = 3, 4, 5, 6, 7
C_QU, C_QR, C_QH, C_TS, C_GATE, C_QN = 8, 9, 10, 11, 12, 13
NC = 14
GATE_POS = 13.815510557964274  #: chi-square(2) 99.9 % quantile
NX = 5


@njit(cache=True, inline="always")
def _wrap(a):
    return math.atan2(math.sin(a), math.cos(a))


@njit(cache=True, inline="always")
def _arc(psi, r, T):
    """(rs, sin psi, cos psi, sin p1, cos p1) of a turn at rate r over T: rs is r kept off zero
    (+-1e-5 rad/s: the arc's formulas divide by it), p1 = psi + rs T."""
    s0, c0 = math.sin(psi), math.cos(psi)
    rs = r
    if abs(r) < 1e-5:
        rs = 1e-5 if r >= 0 else -1e-5
    p1 = psi + rs * T
    return rs, s0, c0, math.sin(p1), math.cos(p1)


@njit(cache=True, inline="always")
def _prop(x, T, turn, out, J):
    """The mean (5,) of state x after T seconds under CV (turn False) or CT, into ``out``, and
    its Jacobian into J (5, 5). Returns (cos, sin) of the new heading out[2] (the values the
    arc needed anyway: bit for bit those of math.cos, math.sin of out[2])."""
    px, py, psi, u, r = x[0], x[1], x[2], x[3], x[4]
    for a in range(NX):
        for b in range(NX):
            J[a, b] = 0.0
        J[a, a] = 1.0
    if turn:
        rs, s0, c0, s1, c1 = _arc(psi, r, T)
        ds, dc = s1 - s0, c0 - c1
        out[0] = px + u * ds / rs
        out[1] = py + u * dc / rs
        out[2] = psi + r * T
        out[3] = u
        out[4] = r
        J[0, 2] = u * (c1 - c0) / rs
        J[0, 3] = ds / rs
        J[0, 4] = -u * ds / (rs * rs) + u * T * c1 / rs
        J[1, 2] = u * (s1 - s0) / rs
        J[1, 3] = dc / rs
        J[1, 4] = -u * dc / (rs * rs) + u * T * s1 / rs
        J[2, 4] = T
        if rs != r:  # (a turn rate below 1e-5 rad/s: the arc used rs; the heading moved by r)
            return math.cos(out[2]), math.sin(out[2])
        return c1, s1
    else:
        s0, c0 = math.sin(psi), math.cos(psi)
        out[0] = px + u * T * c0
        out[1] = py + u * T * s0
        out[2] = psi
        out[3] = u
        out[4] = 0.0
        J[0, 2] = -u * T * s0
        J[0, 3] = T * c0
        J[1, 2] = u * T * c0
        J[1, 3] = T * s0
        J[4, 4] = 0.0
        return c0, s0


@njit(cache=True)
def _predict(x0, P0, T, turn, qc, m, P, tmp5, J, Jh, tmpm, panels):
    """Mean m and covariance P of one model after T from (x0, P0): J P0 J^T plus the discrete
    process noise by composite Simpson's rule over ``panels`` panels (weights 1, 4, 2, ..., 4, 1 at
    k T / (2 panels); one panel: 1, 4, 1 at 0, T/2, T, the same operations as the plain rule).
    Returns (cos, sin) of m[2]."""
    ce, se = _prop(x0, T, turn, m, J)
    for a in range(NX):
        for b in range(NX):
            acc = 0.0
            for k in range(NX):
                acc += J[a, k] * P0[k, b]
            tmpm[a, b] = acc
    for a in range(NX):
        for b in range(NX):
            acc = 0.0
            for k in range(NX):
                acc += tmpm[a, k] * J[b, k]
            P[a, b] = acc
    if T <= 0.0:
        return ce, se
    nodes = 2 * panels
    for node in range(nodes + 1):
        f = node / nodes
        coef = 1.0 if node == 0 or node == nodes else (4.0 if node % 2 == 1 else 2.0)
        w = coef * T / (6.0 * panels)
        _prop(x0, f * T, turn, tmp5, Jh)  # the mean at f T ...
        _prop(tmp5, (1.0 - f) * T, turn, tmp5, Jh)  # ... and Phi(T, f T) there (tmp5 is overwritten, unused)
        for a in range(NX):
            for b in range(NX):
                acc = 0.0
                for k in range(NX):
                    acc += Jh[a, k] * qc[k] * Jh[b, k]
                P[a, b] += w * acc
    return ce, se


@njit(cache=True)
def _solve_sym(S, n, Sinv):
    """Inverse of the symmetric positive-definite S (n, n) by Gauss-Jordan; returns log det S."""
    A = np.empty((n, 2 * n))
    for a in range(n):
        for b in range(n):
            A[a, b] = S[a, b]
            A[a, n + b] = 1.0 if a == b else 0.0
    logdet = 0.0
    for c in range(n):
        piv = c
        for a in range(c + 1, n):
            if abs(A[a, c]) > abs(A[piv, c]):
                piv = a
        if piv != c:
            for b in range(2 * n):
                A[c, b], A[piv, b] = A[piv, b], A[c, b]
        d = A[c, c]
        logdet += math.log(abs(d))
        for b in range(2 * n):
            A[c, b] /= d
        for a in range(n):
            if a != c:
                f = A[a, c]
                for b in range(2 * n):
                    A[a, b] -= f * A[c, b]
    for a in range(n):
        for b in range(n):
            Sinv[a, b] = A[a, n + b]
    return logdet


@njit(cache=True)
def work():
    """Scratch arrays of one filter call (:func:`_interact_predict`), allocated once per batch
    chunk and reused env after env: qc (2, 5), c (2,), x0 (2, 5), P0 (2, 5, 5), mp (2, 5),
    Pp (2, 5, 5), tmp5 (5,), J, Jh, tmpm (5, 5), d (5,), cs (2, 2) (cos, sin of each model's
    predicted heading)."""
    return (np.zeros((2, NX)), np.empty(2), np.empty((2, NX)), np.empty((2, NX, NX)), np.empty((2, NX)),
            np.empty((2, NX, NX)), np.empty(NX), np.empty((NX, NX)), np.empty((NX, NX)), np.empty((NX, NX)),
            np.empty(NX), np.empty((2, 2)))


@njit(cache=True, inline="always")
def heading_gap(m):
    """The models' heading difference m_1 - m_0 wrapped to [-pi, pi] (:func:`_mix`'s ``dpsi``; it
    changes only with m, at a fix, so :func:`imm_step` keeps it per env between fixes)."""
    return _wrap(m[1, 2] - m[0, 2])


@njit(cache=True, inline="always")
def _interact_predict(m, P, mu, T, cfg, with_cov, w, dpsi):
    """The IMM's interaction over T and both models' predictions: the predicted mode probabilities
    c (2,), means mp (2, 5) and (if ``with_cov``) covariances Pp (2, 5, 5), in the scratch ``w``
    (:func:`work`); the cos, sin of the predicted headings into w's cs. ``dpsi``:
    :func:`heading_gap` of m."""
    qc, c, x0, P0, mp, Pp, tmp5, J, Jh, tmpm, d, cs = w
    for j in range(2):
        for a in range(NX):
            qc[j, a] = 0.0
    qc[0, 2] = cfg[C_QH]
    qc[0, 3] = cfg[C_QU]
    qc[1, 3] = cfg[C_QU]
    qc[1, 4] = cfg[C_QR]
    _mix(m, P, mu, T, cfg[C_TS], c, x0, P0, with_cov, d, dpsi)
    panels = max(1, int(cfg[C_QN]))
    for j in range(2):
        if with_cov:
            cs[j, 0], cs[j, 1] = _predict(x0[j], P0[j], T, j == 1, qc[j], mp[j], Pp[j], tmp5, J, Jh, tmpm, panels)
        else:
            cs[j, 0], cs[j, 1] = _prop(x0[j], T, j == 1, mp[j], J)
    return c, mp, Pp


@njit(cache=True)
def imm_init(m, P, mu, z, var):
    """Start both models at the fix z (5,) with variances var (5,); CV's turn rate at 0."""
    for j in range(2):
        for a in range(NX):
            m[j, a] = z[a]
            for b in range(NX):
                P[j, a, b] = 0.0
            P[j, a, a] = var[a]
    m[0, 4] = 0.0
    P[0, 4, 4] = 1e-10
    mu[0] = 0.5
    mu[1] = 0.5


@njit(cache=True, inline="always")
def _mix(m, P, mu, T, ts, c, x0, P0, with_cov, d, dpsi):
    """The IMM's interaction over a span T: predicted mode probabilities c (2,), mixed initial
    means x0 (2, 5) and covariances P0 (2, 5, 5) (if ``with_cov``); d (5,) is scratch; dpsi:
    :func:`heading_gap` of m."""
    p = 0.5 * (1.0 - math.exp(-2.0 * T / ts))
    for j in range(2):
        c[j] = mu[0] * (1.0 - p if j == 0 else p) + mu[1] * (p if j == 0 else 1.0 - p)
    # the heading difference wrapped once (dpsi): m_0 - m_1 is exactly -(m_1 - m_0), and the wrap
    # atan2(sin, cos) is odd (glibc's sin and atan2 are odd bit for bit; a libm that is not would
    # move the other model's mixed heading by an ulp)
    for j in range(2):
        cj = max(c[j], 1e-300)
        w0 = mu[0] * (1.0 - p if j == 0 else p) / cj
        w1 = mu[1] * (p if j == 0 else 1.0 - p) / cj
        # x0_j = m_j + sum_i w_ij (m_i - m_j), the heading difference wrapped
        for a in range(NX):
            d[a] = m[1 - j, a] - m[j, a]
        d[2] = dpsi if j == 0 else -dpsi
        wo = w1 if j == 0 else w0  # the weight of the other model
        for a in range(NX):
            x0[j, a] = m[j, a] + wo * d[a]
        if with_cov:
            # P0_j = sum_i w_ij (P_i + e_ij e_ij^T), e_ij = m_i - x0_j
            ws = w0 if j == 0 else w1  # own weight
            for a in range(NX):
                for b in range(NX):
                    ea_own, eb_own = -wo * d[a], -wo * d[b]
                    ea_oth, eb_oth = (1.0 - wo) * d[a], (1.0 - wo) * d[b]
                    P0[j, a, b] = (ws * (P[j, a, b] + ea_own * eb_own)
                                   + wo * (P[1 - j, a, b] + ea_oth * eb_oth))
    x0[0, 4] = 0.0
    if with_cov:
        for a in range(NX):
            P0[0, 4, a] = 0.0
            P0[0, a, 4] = 0.0
        P0[0, 4, 4] = 1e-10


@njit(cache=True)
def gate_distance(Pp, nu, var, j, S2, S2i):
    """Model j's squared Mahalanobis distance of the fix's position: the innovation nu[j, :2] under
    the predicted position covariance Pp[j, :2, :2] plus the fix's variances var[:2] (S2, S2i: 2 x 2
    scratch). Shared by the IMMs (and the model-aware one, :mod:`controllers._leader_imm`)."""
    for a in range(2):
        for b in range(2):
            S2[a, b] = Pp[j, a, b] + (var[a] if a == b else 0.0)
    _solve_sym(S2, 2, S2i)
    d2 = 0.0
    for a in range(2):
        for b in range(2):
            d2 += nu[j, a] * S2i[a, b] * nu[j, b]
    return d2


@njit(cache=True)
def model_update(Pp, mp, nu, R, m, P, j, S, Si, Kg):
    """Model j's Kalman update in place: prediction (mp[j], Pp[j]), innovation nu[j] of a fix with
    the noise variances R (the state is measured directly), into m[j], P[j] (symmetrised); S, Si,
    Kg: (n, n) scratch. Returns the fix's log-likelihood under the model (up to a constant)."""
    n = S.shape[0]
    for a in range(n):
        for b in range(n):
            S[a, b] = Pp[j, a, b] + (R[a] if a == b else 0.0)
    logdet = _solve_sym(S, n, Si)
    q = 0.0
    for a in range(n):
        for b in range(n):
            q += nu[j, a] * Si[a, b] * nu[j, b]
    for a in range(n):
        for b in range(n):
            acc = 0.0
            for k in range(n):
                acc += Pp[j, a, k] * Si[k, b]
            Kg[a, b] = acc
    for a in range(n):
        acc = 0.0
        for k in range(n):
            acc += Kg[a, k] * nu[j, k]
        m[j, a] = mp[j, a] + acc
    for a in range(n):
        for b in range(n):
            acc = 0.0
            for k in range(n):
                acc += Kg[a, k] * Pp[j, k, b]
            P[j, a, b] = Pp[j, a, b] - acc
    for a in range(n):
        for b in range(a + 1, n):
            v = 0.5 * (P[j, a, b] + P[j, b, a])
            P[j, a, b] = v
            P[j, b, a] = v
    return -0.5 * (q + logdet)


@njit(cache=True)
def imm_update(m, P, mu, ng, T, z, var, cfg):
    """One fix z (5,) with variances var (5,), T seconds after the filter's last: interaction,
    prediction of both models, gating, update and the new mode probabilities (all in place).
    Returns True if the fix's position was gated out."""
    c, mp, Pp = _interact_predict(m, P, mu, T, cfg, True, work(), heading_gap(m))
    nu = np.empty((2, NX))
    for j in range(2):
        for a in range(NX):
            nu[j, a] = z[a] - mp[j, a]
        nu[j, 2] = _wrap(nu[j, 2])
    # the position gate: outside it for every model -> the position is not used
    S2, S2i = np.empty((2, 2)), np.empty((2, 2))
    dmin = math.inf
    for j in range(2):
        dmin = min(dmin, gate_distance(Pp, nu, var, j, S2, S2i))
    gated = cfg[C_GATE] > 0.0 and dmin > GATE_POS
    R = var.copy()
    if gated:
        R[0] = 1e8
        R[1] = 1e8
    S, Si = np.empty((NX, NX)), np.empty((NX, NX))
    ll = np.empty(2)
    K = np.empty((NX, NX))
    for j in range(2):
        ll[j] = model_update(Pp, mp, nu, R, m, P, j, S, Si, K)
    m[0, 4] = 0.0
    top = max(ll[0], ll[1])
    w0 = c[0] * math.exp(ll[0] - top)
    w1 = c[1] * math.exp(ll[1] - top)
    mu[0] = w0 / (w0 + w1)
    mu[1] = w1 / (w0 + w1)
    ng[0] = ng[0] + 1 if gated else 0
    if ng[0] >= 2:
        imm_init(m, P, mu, z, var)
        ng[0] = 0
    return gated


@njit(cache=True, inline="always")
def imm_present(m, P, mu, T, cfg, out_x, with_cov, out_P, w, dpsi):
    """The present state T seconds after the last fix: the models' predictions weighted by the
    predicted mode probabilities; the heading as the weighted circular mean. out_x (5,); the
    mixture covariance into out_P (5, 5) if ``with_cov``; w: scratch (:func:`work`); dpsi:
    :func:`heading_gap` of m."""
    c, mp, Pp = _interact_predict(m, P, mu, T, cfg, with_cov, w, dpsi)
    sx, sy = 0.0, 0.0
    for a in range(NX):
        out_x[a] = 0.0
    for j in range(2):
        for a in (0, 1, 3, 4):
            out_x[a] += c[j] * mp[j, a]
        sx += c[j] * w[11][j, 0]  # cos, sin of mp[j, 2]
        sy += c[j] * w[11][j, 1]
    # the heading: the weighted circular mean, kept on the branch of the most likely model
    ref = mp[0, 2] if c[0] >= c[1] else mp[1, 2]
    out_x[2] = ref + _wrap(math.atan2(sy, sx) - ref)
    if with_cov:
        for a in range(NX):
            for b in range(NX):
                acc = 0.0
                for j in range(2):
                    da = mp[j, a] - out_x[a]
                    db = mp[j, b] - out_x[b]
                    if a == 2:
                        da = _wrap(da)
                    if b == 2:
                        db = _wrap(db)
                    acc += c[j] * (Pp[j, a, b] + da * db)
                out_P[a, b] = acc


@njit(cache=True, inline="always")
def _prop_mean(px, py, psi, u, r, T, turn):
    """:func:`_prop`'s mean in scalars (the same operations: the same bits), without the Jacobian:
    (x, y, psi, u, r, cos psi, sin psi) after T. Scalars only, as :func:`_present_mean`."""
    if turn:
        rs, s0, c0, s1, c1 = _arc(psi, r, T)
        ds, dc = s1 - s0, c0 - c1
        p2 = psi + r * T
        if rs != r:
            return px + u * ds / rs, py + u * dc / rs, p2, u, r, math.cos(p2), math.sin(p2)
        return px + u * ds / rs, py + u * dc / rs, p2, u, r, c1, s1
    s0, c0 = math.sin(psi), math.cos(psi)
    return px + u * T * c0, py + u * T * s0, psi, u, 0.0, c0, s0


@njit(cache=True, inline="always")
def _present_mean(m, mu, i, T, ts, dpsi):
    """:func:`imm_present` without the covariance for env i of the batch state (m (N, 2, 5), mu
    (N, 2); dpsi: :func:`heading_gap` of m[i]): the same operations as the array functions
    (:func:`_mix`, :func:`_prop`), in scalars. (Array views made per env cost numba an atomic
    reference count each, which took most of this path's time.) Returns (x, y, psi, u, r)."""
    p = 0.5 * (1.0 - math.exp(-2.0 * T / ts))
    mu0, mu1 = mu[i, 0], mu[i, 1]
    c0 = mu0 * (1.0 - p) + mu1 * p
    c1 = mu0 * p + mu1 * (1.0 - p)
    # the mixed initial means (as _mix): x0_j = m_j + w_oj (m_o - m_j), the heading gap wrapped
    cj = max(c0, 1e-300)
    wo = mu1 * p / cj
    a0 = m[i, 0, 0] + wo * (m[i, 1, 0] - m[i, 0, 0])
    a1 = m[i, 0, 1] + wo * (m[i, 1, 1] - m[i, 0, 1])
    a2 = m[i, 0, 2] + wo * dpsi
    a3 = m[i, 0, 3] + wo * (m[i, 1, 3] - m[i, 0, 3])
    cj = max(c1, 1e-300)
    wo = mu0 * p / cj
    b0 = m[i, 1, 0] + wo * (m[i, 0, 0] - m[i, 1, 0])
    b1 = m[i, 1, 1] + wo * (m[i, 0, 1] - m[i, 1, 1])
    b2 = m[i, 1, 2] + wo * -dpsi
    b3 = m[i, 1, 3] + wo * (m[i, 0, 3] - m[i, 1, 3])
    b4 = m[i, 1, 4] + wo * (m[i, 0, 4] - m[i, 1, 4])
    x0, y0, h0, u0, r0, k0, s0 = _prop_mean(a0, a1, a2, a3, 0.0, T, False)
    x1, y1, h1, u1, r1, k1, s1 = _prop_mean(b0, b1, b2, b3, b4, T, True)
    # the weighted mean (as imm_present: 0 + c_0 (.) + c_1 (.)) and the circular mean heading
    x = 0.0 + c0 * x0 + c1 * x1
    y = 0.0 + c0 * y0 + c1 * y1
    u = 0.0 + c0 * u0 + c1 * u1
    r = 0.0 + c0 * r0 + c1 * r1
    sx = 0.0 + c0 * k0 + c1 * k1
    sy = 0.0 + c0 * s0 + c1 * s1
    ref = h0 if c0 >= c1 else h1
    return x, y, ref + _wrap(math.atan2(sy, sx) - ref), u, r


def _imm_chunks(chunks, obs, reset, cfg, t_now, odom, vel, psi_f, init, t_fix, m, P, mu, ng, gap, out, cov_out, src,
                copy_rows):
    """:func:`imm_step` over ``chunks`` contiguous blocks of envs (a parallel loop in the threaded
    build), each block with its own scratch; with ``copy_rows`` each env's state is first copied
    from ``src``.

    The per-env body is written out here, with scalars and whole-array indexing: an inlined helper
    taking the ~20 state arrays (or a tuple of them) costs numba an atomic reference count per
    array and env, which took two thirds of this kernel's time (the same operations either way)."""
    n = obs.shape[0]
    s_t_now, s_odom, s_vel, s_psi_f, s_init, s_t_fix, s_m, s_P, s_mu, s_ng, s_gap = src
    want_cov = cov_out.shape[0] > 0
    dt, tau, ts = cfg[C_DT], cfg[C_TAU], cfg[C_TS]
    v1 = cfg[C_V1] != 0.0
    for ch in prange(chunks):
        z = np.empty(NX)
        var = np.empty(NX)
        xo = np.empty(NX)
        Po = np.empty((NX, NX))
        w = work()
        for i in range(ch * n // chunks, (ch + 1) * n // chunks):
            if copy_rows:  # env i's row of every state array from src
                t_now[i] = s_t_now[i]
                psi_f[i] = s_psi_f[i]
                init[i] = s_init[i]
                t_fix[i] = s_t_fix[i]
                ng[i, 0] = s_ng[i, 0]
                gap[i] = s_gap[i]
                for a in range(2):
                    odom[i, a] = s_odom[i, a]
                    vel[i, a] = s_vel[i, a]
                    mu[i, a] = s_mu[i, a]
                    for b in range(NX):
                        m[i, a, b] = s_m[i, a, b]
                        for c in range(NX):
                            P[i, a, b, c] = s_P[i, a, b, c]
            pf, c, s = odometry_step(obs, reset, i, odom, vel, t_now, init, dt)
            if reset[i]:
                ng[i, 0] = 0
            psi_f[i] = pf
            fresh, t_meas = fix_timing(obs, i, t_now[i], init[i], t_fix[i], v1, tau)
            if fresh:
                dx, dy = fix_measurement(obs, i, odom, pf, c, s, z)
                fix_variances(cfg[C_SPOS], cfg[C_SPM], cfg[C_SPSI], cfg[C_SVEL], cfg[C_SR], dx, dy, var)
                if init[i]:
                    z[2] = m[i, 0, 2] + _wrap(z[2] - m[i, 0, 2])  # the heading on the filter's branch
                    imm_update(m[i], P[i], mu[i], ng[i], t_meas - t_fix[i], z, var, cfg)
                else:
                    imm_init(m[i], P[i], mu[i], z, var)
                    init[i] = True
                    ng[i, 0] = 0
                t_fix[i] = t_meas
                gap[i] = heading_gap(m[i])  # (m changes only here)
            if init[i]:
                T = t_now[i] - t_fix[i]
                if want_cov:
                    imm_present(m[i], P[i], mu[i], T, cfg, xo, True, Po, w, gap[i])
                    x, y, h, u, r = xo[0], xo[1], xo[2], xo[3], xo[4]
                    for a in range(NX):
                        for b in range(NX):
                            cov_out[i, a, b] = Po[a, b]
                else:
                    x, y, h, u, r = _present_mean(m, mu, i, T, ts, gap[i])
                write_estimate(out, i, x, y, h, u, r, odom[i, 0], odom[i, 1], c, s, _wrap(h - pf), T)
            else:
                for j in range(NE):
                    out[i, j] = 0.0
                if want_cov:
                    for a in range(NX):
                        for b in range(NX):
                            cov_out[i, a, b] = 0.0


#: the step, serial and on numba's threads (per env the same operations: the same bits)
_imm_serial = njit(cache=True)(_imm_chunks)
_imm_threads = recompiled(_imm_chunks, "_imm_chunks_par", cache=True, parallel=True)
#: batches from this many envs are filtered on numba's threads (as the vector env steps them)
THREADED_MIN_ENVS = 256


def imm_step(obs, reset, cfg, t_now, odom, vel, psi_f, init, t_fix, m, P, mu, ng, gap, out, cov_out, src=None):
    """One control step of the IMM filter for every env (all arrays updated in place).

    obs (N, W) observations (W = 16: v0, a fix ``tau`` old every step; 20: v1); reset (N,) bool;
    cfg: the config vector (C_*). State: t_now, psi_f (N,), odom, vel (N, 2), init (N,) bool,
    t_fix (N,), m (N, 2, 5), P (N, 2, 5, 5), mu (N, 2), ng (N, 1) (gated fixes in a row), gap (N,)
    (:func:`heading_gap` of m, set at each fix).
    out (N, NE): the present estimate (the OU0 kernel's columns E_*); cov_out (N, 5, 5) or
    (0, 5, 5): the present mixture covariance (or not wanted). The odometry frame and the timing
    of fixes are the OU0 kernel's: a fix not newer than the filter's is ignored (never observed
    in the envs: the receiver keeps the newest packet). From :data:`THREADED_MIN_ENVS` envs on,
    the envs are split over numba's threads (the same result). ``src``: None (the state arrays are
    updated in place) or a tuple of state arrays of the same shapes (t_now .. gap) to start from
    (the state arrays given are then overwritten: a peek's copy made inside the kernel).
    """
    n = obs.shape[0]
    threads = numba.get_num_threads() if n >= THREADED_MIN_ENVS else 1
    dst = (t_now, odom, vel, psi_f, init, t_fix, m, P, mu, ng, gap)
    step = _imm_threads if threads > 1 else _imm_serial
    step(threads, obs, reset, cfg, *dst, out, cov_out, dst if src is None else tuple(src), src is not None)


@njit(cache=True)
def insert_by_time(order, nbuf, t_meas, f):
    """Insert fix f into the buffer order[:nbuf] of fix indices sorted by measurement time t_meas
    (after any of equal time); returns its position (the filter re-runs from there)."""
    pos = nbuf
    while pos > 0 and t_meas[order[pos - 1]] > t_meas[f]:
        pos -= 1
    for k in range(nbuf, pos, -1):
        order[k] = order[k - 1]
    order[pos] = f
    return pos


@njit(cache=True)
def imm_filter_fixes(t_meas, z, var, cfg, t_query):
    """Run the filter over fixes given in *arrival* order (times of measurement t_meas (F,),
    values z (F, 5), variances var (F, 5)): a fix older than one already used is inserted where
    its measurement time belongs and the filter is re-run from the state before it
    (retrodiction), so the result is that of the fixes in measurement order. Returns, after each
    arrival, the present state (F, 5) at t_query (F,) [s, the same clock as t_meas] and the mode
    probabilities (F, 2)."""
    F = t_meas.shape[0]
    order = np.empty(F, dtype=np.int64)  # fix indices in measurement order (the buffer)
    snap_m = np.empty((F, 2, NX))
    snap_P = np.empty((F, 2, NX, NX))
    snap_mu = np.empty((F, 2))
    snap_ng = np.empty((F, 1), dtype=np.int64)
    m = np.empty((2, NX))
    P = np.empty((2, NX, NX))
    mu = np.empty(2)
    ng = np.zeros(1, dtype=np.int64)
    out = np.empty((F, NX))
    mus = np.empty((F, 2))
    Po = np.empty((NX, NX))
    xo = np.empty(NX)
    w = work()
    nbuf = 0
    for f in range(F):
        pos = insert_by_time(order, nbuf, t_meas, f)
        nbuf += 1
        for k in range(pos, nbuf):  # re-run from the snapshot before the inserted fix
            j = order[k]
            if k == 0:
                imm_init(m, P, mu, z[j], var[j])
                ng[0] = 0
            else:
                m[:, :] = snap_m[k - 1]
                P[:, :, :] = snap_P[k - 1]
                mu[:] = snap_mu[k - 1]
                ng[0] = snap_ng[k - 1, 0]
                zz = z[j].copy()
                zz[2] = m[0, 2] + _wrap(zz[2] - m[0, 2])
                imm_update(m, P, mu, ng, t_meas[j] - t_meas[order[k - 1]], zz, var[j], cfg)
            snap_m[k] = m
            snap_P[k] = P
            snap_mu[k] = mu
            snap_ng[k, 0] = ng[0]
        last = order[nbuf - 1]
        m[:, :] = snap_m[nbuf - 1]
        P[:, :, :] = snap_P[nbuf - 1]
        mu[:] = snap_mu[nbuf - 1]
        imm_present(m, P, mu, t_query[f] - t_meas[last], cfg, xo, False, Po, w, heading_gap(m))
        out[f] = xo
        mus[f] = mu
    return out, mus


@njit(cache=True)
def imm_trajectory(m, P, mu, init, T, cfg):
    """The present-state prediction of every env at the spans T (N, K) after its last fix
    (:func:`imm_present` without covariance), (N, K, 5); zeros where ``init`` is False."""
    n, K = T.shape
    out = np.zeros((n, K, NX))
    xo = np.empty(NX)
    Po = np.empty((NX, NX))
    w = work()
    for i in range(n):
        if not init[i]:
            continue
        gap = heading_gap(m[i])
        for k in range(K):
            imm_present(m[i], P[i], mu[i], T[i, k], cfg, xo, False, Po, w, gap)
            for a in range(NX):
                out[i, k, a] = xo[a]
    return out
