"""The plant, the target, the disturbances and the delay line: one implementation.

Every kernel here works on a leading batch axis ``i`` and is compiled with numba (cached on
disk, so only the first run in a fresh checkout pays the compile). The single env calls it
with a batch of one; the vector env with a batch of N. There is no second copy.

Equations (Zhang et al. 2026, signs restored per NOTES.md):

* kinematics (3): x' = u cos psi - v sin psi, y' = u sin psi + v cos psi, psi' = r;
* current (5): [u_c, v_c] = R(psi)^T v_c^I;  (9): u_r = u - u_c, v_r = v - v_c;
* dynamics (6)-(8): m u' = F_u - X_u u_r + m v r + d_u,
  m v' = F_v - Y_v v_r - m u r + d_v,  I_z r' = F_r - N_r r + d_r;
* target (10): x_t' = u_t cos psi_t - v_t sin psi_t, y_t' = u_t sin psi_t + v_t cos psi_t,
  psi_t' = r_t, with u_t, r_t given functions of time and v_t = 0.

Integration: classical RK4 with ``physics_substeps`` substeps per control step; the force
is held constant over the control step (zero-order hold); current, disturbances and the
target's velocity are evaluated at each RK4 stage time (each distinct time once).

Array conventions (documented column maps below):

* ``state``  (N, 9) float64: x, y, psi, u, v, r (follower), x_t, y_t, psi_t (target);
* ``k``      (N,)  int64: control steps taken this episode; time t = k * dt;
* ``buf``    (N, L, 6) float64: delay line of target states (x, y, psi, u, v, r), L = D + 1,
  slot ``j mod L`` holds the state at step j (j may be negative: the target is simulated
  from t = -tau so the line is full at t = 0);
* ``params`` (N, NP) float64: per-episode plant/target/current/disturbance parameters;
* ``cfg``    (NC,) float64: static configuration shared by the batch.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

# --- parameter columns (per env) ---------------------------------------------------------
P_M, P_IZ, P_XU, P_YV, P_NR = 0, 1, 2, 3, 4  # true plant [kg, kg m^2, N s/m, N s/m, N m s]
P_TV, P_TAU, P_TWU, P_TPU, P_TAR, P_TWR, P_TPR = 5, 6, 7, 8, 9, 10, 11  # target
P_CX, P_CY = 12, 16  # current x/y: mean [m/s], amplitude [m/s], omega [rad/s], phase [rad]
P_D = 20  # disturbance u/v/r: 4 columns each: amp1 [N or N m], phase1, amp2, phase2
NP = 32
#: disturbance tone frequencies [rad/s] (ours, NOTES.md) and weights (sum to 1)
DIST_OMEGA = (0.35, 0.9)
DIST_WEIGHT = (0.6, 0.4)

# --- cfg entries (shared) ----------------------------------------------------------------
C_DT, C_NSUB, C_D, C_L, C_PDX, C_PDY, C_PSID = 0, 1, 2, 3, 4, 5, 6
C_FU, C_FV, C_FR, C_MAXD, C_NSTEPS, C_EFFORT, C_INIT = 7, 8, 9, 10, 11, 12, 13
NC = 14

# --- truth columns (per env, for evaluation only) ----------------------------------------
T_FOLLOWER = slice(0, 3)  # x, y, psi
T_TARGET = slice(3, 9)  # x_t, y_t, psi_t, u_t, v_t, r_t (present, undelayed)
T_REF = slice(9, 12)  # true reference x, y, psi (eq. (21) with the present target)
T_ERR = 12  # ||p - p_ref_true|| [m]
NT = 13

_W1, _W2 = DIST_OMEGA


@njit(cache=True, inline="always")
def target_velocity(p, i, t):
    """(u_t, r_t) of the target at time t [m/s, rad/s]; v_t = 0."""
    ut = p[i, P_TV] * (1.0 + p[i, P_TAU] * math.sin(p[i, P_TWU] * t + p[i, P_TPU]))
    rt = p[i, P_TAR] * math.sin(p[i, P_TWR] * t + p[i, P_TPR])
    return ut, rt


@njit(cache=True, inline="always")
def current_inertial(p, i, t):
    """Inertial current (v_cx, v_cy) at time t [m/s]."""
    cx = p[i, P_CX] + p[i, P_CX + 1] * math.sin(p[i, P_CX + 2] * t + p[i, P_CX + 3])
    cy = p[i, P_CY] + p[i, P_CY + 1] * math.sin(p[i, P_CY + 2] * t + p[i, P_CY + 3])
    return cx, cy


@njit(cache=True, inline="always")
def cos_sin_small(d):
    """(cos d, sin d): Taylor polynomials (exact to double precision for |d| <= 0.25), libm beyond.

    Used for the small angle increments inside one RK4 step (stage headings, tone phasors),
    where it replaces libm calls that dominate the kernel's cost.
    """
    if abs(d) > 0.25:
        return math.cos(d), math.sin(d)
    d2 = d * d
    c = 1.0 - d2 / 2.0 * (1.0 - d2 / 12.0 * (1.0 - d2 / 30.0 * (1.0 - d2 / 56.0 * (
        1.0 - d2 / 90.0 * (1.0 - d2 / 132.0)))))
    s = d * (1.0 - d2 / 6.0 * (1.0 - d2 / 20.0 * (1.0 - d2 / 42.0 * (1.0 - d2 / 72.0 * (
        1.0 - d2 / 110.0 * (1.0 - d2 / 156.0))))))
    return c, s


@njit(cache=True, inline="always")
def _turn(c0, s0, d):
    """(cos, sin) of (angle + d) from (cos, sin) of the angle."""
    cd, sd = cos_sin_small(d)
    return c0 * cd - s0 * sd, s0 * cd + c0 * sd


@njit(cache=True, inline="always")
def follower_rhs(p, i, f, c, s, u, v, r, fu, fv, fr):
    """Right-hand side of eqs. (3)-(9) for the follower at heading (cos, sin) = (c, s),
    given the forcing tuple f = (v_cx, v_cy, d_u, d_v, d_r, u_t, r_t)."""
    ur = u - (c * f[0] + s * f[1])  # eq. (9) with eq. (5)
    vr = v - (-s * f[0] + c * f[1])
    m = p[i, P_M]
    return (c * u - s * v, s * u + c * v, r,
            (fu - p[i, P_XU] * ur + m * v * r + f[2]) / m,
            (fv - p[i, P_YV] * vr - m * u * r + f[3]) / m,
            (fr - p[i, P_NR] * r + f[4]) / p[i, P_IZ])


@njit(cache=True)
def rk4_substep(state, i, p, h, fu, fv, fr, f0, fm, f1):
    """One classical RK4 step of length h for follower and target of env i (in place).

    f0, fm, f1: the forcing at the step's start, midpoint and end (the stage times). The
    stage headings psi + dpsi use cos/sin of psi and of the small increment dpsi.
    """
    x, y, ps, u, v, r = state[i, 0], state[i, 1], state[i, 2], state[i, 3], state[i, 4], state[i, 5]
    hh = 0.5 * h
    c0 = math.cos(ps)
    s0 = math.sin(ps)
    a0, a1, a2, a3, a4, a5 = follower_rhs(p, i, f0, c0, s0, u, v, r, fu, fv, fr)
    c, s = _turn(c0, s0, hh * a2)
    b0, b1, b2, b3, b4, b5 = follower_rhs(p, i, fm, c, s, u + hh * a3, v + hh * a4, r + hh * a5, fu, fv, fr)
    c, s = _turn(c0, s0, hh * b2)
    c0_, c1, c2, c3, c4, c5 = follower_rhs(p, i, fm, c, s, u + hh * b3, v + hh * b4, r + hh * b5, fu, fv, fr)
    c, s = _turn(c0, s0, h * c2)
    d0, d1, d2, d3, d4, d5 = follower_rhs(p, i, f1, c, s, u + h * c3, v + h * c4, r + h * c5, fu, fv, fr)
    w = h / 6.0
    state[i, 0] = x + w * (a0 + 2.0 * (b0 + c0_) + d0)
    state[i, 1] = y + w * (a1 + 2.0 * (b1 + c1) + d1)
    state[i, 2] = ps + w * (a2 + 2.0 * (b2 + c2) + d2)
    state[i, 3] = u + w * (a3 + 2.0 * (b3 + c3) + d3)
    state[i, 4] = v + w * (a4 + 2.0 * (b4 + c4) + d4)
    state[i, 5] = r + w * (a5 + 2.0 * (b5 + c5) + d5)
    # target, eq. (10) with v_t = 0: x' = u_t cos, y' = u_t sin, psi' = r_t
    pt = state[i, 8]
    c0 = math.cos(pt)
    s0 = math.sin(pt)
    cb, sb = _turn(c0, s0, hh * f0[6])
    cc, sc = _turn(c0, s0, hh * fm[6])
    cd, sd = _turn(c0, s0, h * fm[6])
    state[i, 6] += w * (f0[5] * c0 + 2.0 * fm[5] * (cb + cc) + f1[5] * cd)
    state[i, 7] += w * (f0[5] * s0 + 2.0 * fm[5] * (sb + sc) + f1[5] * sd)
    state[i, 8] = pt + w * (f0[6] + 4.0 * fm[6] + f1[6])


#: the ten tones of the forcing: (omega column or -1 for DIST_OMEGA[k], phase column)
_TONE_OMEGA = np.array([P_TWU, P_TWR, P_CX + 2, P_CY + 2, -1, -2, -1, -2, -1, -2], dtype=np.int64)
_TONE_PHASE = np.array([P_TPU, P_TPR, P_CX + 3, P_CY + 3, P_D + 1, P_D + 3, P_D + 5, P_D + 7, P_D + 9,
                        P_D + 11], dtype=np.int64)


@njit(cache=True, inline="always")
def _forcing_from(p, i, S):
    """Forcing tuple (v_cx, v_cy, d_u [N], d_v [N], d_r [N m], u_t, r_t) from the ten tone sines S."""
    return (p[i, P_CX] + p[i, P_CX + 1] * S[2], p[i, P_CY] + p[i, P_CY + 1] * S[3],
            p[i, P_D] * S[4] + p[i, P_D + 2] * S[5], p[i, P_D + 4] * S[6] + p[i, P_D + 6] * S[7],
            p[i, P_D + 8] * S[8] + p[i, P_D + 10] * S[9],
            p[i, P_TV] * (1.0 + p[i, P_TAU] * S[0]), p[i, P_TAR] * S[1])


@njit(cache=True)
def advance(state, i, p, t0, dt, nsub, fu, fv, fr, scratch):
    """Advance env i by dt from time t0 in nsub RK4 substeps, force held constant.

    The ten time-dependent tones are evaluated once at t0 and then rotated by half substeps
    (angle addition with small-angle cos/sin), so each stage time is exact to rounding.
    ``scratch`` is a (4, 10) float64 work array.
    """
    h = dt / nsub
    hh = 0.5 * h
    S, C, RC, RS = scratch[0], scratch[1], scratch[2], scratch[3]
    for j in range(10):
        oc = _TONE_OMEGA[j]
        w = p[i, oc] if oc >= 0 else (_W1 if oc == -1 else _W2)
        a = w * t0 + p[i, _TONE_PHASE[j]]
        S[j] = math.sin(a)
        C[j] = math.cos(a)
        RC[j], RS[j] = cos_sin_small(w * hh)
    f0 = _forcing_from(p, i, S)
    for _ in range(nsub):
        for j in range(10):
            s, c = S[j], C[j]
            S[j] = s * RC[j] + c * RS[j]
            C[j] = c * RC[j] - s * RS[j]
        fm = _forcing_from(p, i, S)
        for j in range(10):
            s, c = S[j], C[j]
            S[j] = s * RC[j] + c * RS[j]
            C[j] = c * RC[j] - s * RS[j]
        f1 = _forcing_from(p, i, S)
        rk4_substep(state, i, p, h, fu, fv, fr, f0, fm, f1)
        f0 = f1


@njit(cache=True)
def integrate(state, p, cfg, t0, forces):
    """Advance every env one control step from time t0[i] under forces (N, 3) [N, N, N m].

    The bare physics kernel (follower and target), without delay line, observation or
    reward: what the speed benchmark compares the env against.
    """
    nsub = int(cfg[C_NSUB])
    scratch = np.empty((4, 10))
    for i in range(state.shape[0]):
        advance(state, i, p, t0[i], cfg[C_DT], nsub, forces[i, 0], forces[i, 1], forces[i, 2], scratch)


@njit(cache=True)
def _store_target(state, buf, p, cfg, i, step):
    """Write the target's state at control step ``step`` into the delay line."""
    L = int(cfg[C_L])
    slot = step % L
    ut, rt = target_velocity(p, i, step * cfg[C_DT])
    buf[i, slot, 0] = state[i, 6]
    buf[i, slot, 1] = state[i, 7]
    buf[i, slot, 2] = state[i, 8]
    buf[i, slot, 3] = ut
    buf[i, slot, 4] = 0.0
    buf[i, slot, 5] = rt


@njit(cache=True)
def _observe(state, k, buf, p, cfg, i, obs, truth):
    """Fill obs[i] (what the follower has) and truth[i] (evaluation only); return error."""
    dt = cfg[C_DT]
    t = k[i] * dt
    L = int(cfg[C_L])
    D = int(cfg[C_D])
    pdx = cfg[C_PDX]
    pdy = cfg[C_PDY]
    x, y, ps = state[i, 0], state[i, 1], state[i, 2]
    c = math.cos(ps)
    s = math.sin(ps)
    # delayed target, eq. (12)
    slot = (k[i] - D) % L
    xd, yd, psd = buf[i, slot, 0], buf[i, slot, 1], buf[i, slot, 2]
    cd = math.cos(psd)
    sd = math.sin(psd)
    ex = xd - x
    ey = yd - y
    rx = xd + cd * pdx - sd * pdy - x  # delayed reference, eq. (21) without prediction
    ry = yd + sd * pdx + cd * pdy - y
    cx, cy = current_inertial(p, i, t)
    obs[i, 0] = state[i, 3]
    obs[i, 1] = state[i, 4]
    obs[i, 2] = state[i, 5]
    obs[i, 3] = c
    obs[i, 4] = s
    obs[i, 5] = c * ex + s * ey
    obs[i, 6] = -s * ex + c * ey
    obs[i, 7] = math.cos(psd - ps)
    obs[i, 8] = math.sin(psd - ps)
    obs[i, 9] = buf[i, slot, 3]
    obs[i, 10] = buf[i, slot, 4]
    obs[i, 11] = buf[i, slot, 5]
    obs[i, 12] = c * rx + s * ry
    obs[i, 13] = -s * rx + c * ry
    obs[i, 14] = c * cx + s * cy
    obs[i, 15] = -s * cx + c * cy
    # truth: present target and the true reference (eq. (21) with eta_t(t))
    xt, yt, pst = state[i, 6], state[i, 7], state[i, 8]
    ut, rt = target_velocity(p, i, t)
    ct = math.cos(pst)
    st = math.sin(pst)
    xr = xt + ct * pdx - st * pdy
    yr = yt + st * pdx + ct * pdy
    err = math.sqrt((x - xr) ** 2 + (y - yr) ** 2)
    truth[i, 0] = x
    truth[i, 1] = y
    truth[i, 2] = ps
    truth[i, 3] = xt
    truth[i, 4] = yt
    truth[i, 5] = pst
    truth[i, 6] = ut
    truth[i, 7] = 0.0
    truth[i, 8] = rt
    truth[i, 9] = xr
    truth[i, 10] = yr
    truth[i, 11] = pst + cfg[C_PSID]
    truth[i, 12] = err
    return err


@njit(cache=True)
def reset_kernel(state, k, buf, p, cfg, idx, obs, truth):
    """Start episodes for the envs in ``idx`` (their params rows must be set).

    The target starts at the origin heading along +x at t = -tau and is simulated up to
    t = 0, filling the delay line: from the first step the follower receives genuine
    tau-old measurements (nothing is zero-filled). The follower starts at rest with the
    delayed target's heading, ``init_offset`` metres behind the delayed reference point.
    """
    D = int(cfg[C_D])
    dt = cfg[C_DT]
    nsub = int(cfg[C_NSUB])
    scratch = np.empty((4, 10))
    for n in range(idx.shape[0]):
        i = idx[n]
        for c in range(6):
            state[i, c] = 0.0
        state[i, 6] = 0.0
        state[i, 7] = 0.0
        state[i, 8] = 0.0
        _store_target(state, buf, p, cfg, i, -D)
        for step in range(-D, 0):
            advance(state, i, p, step * dt, dt, nsub, 0.0, 0.0, 0.0, scratch)  # follower rewritten below
            _store_target(state, buf, p, cfg, i, step + 1)
        L = int(cfg[C_L])
        slot = (-D) % L
        xd, yd, psd = buf[i, slot, 0], buf[i, slot, 1], buf[i, slot, 2]
        cd = math.cos(psd)
        sd = math.sin(psd)
        bx = cfg[C_PDX] - cfg[C_INIT]  # behind the delayed reference, target body frame
        by = cfg[C_PDY]
        state[i, 0] = xd + cd * bx - sd * by
        state[i, 1] = yd + sd * bx + cd * by
        state[i, 2] = psd
        state[i, 3] = 0.0
        state[i, 4] = 0.0
        state[i, 5] = 0.0
        k[i] = 0
        _observe(state, k, buf, p, cfg, i, obs, truth)


@njit(cache=True)
def step_kernel(state, k, buf, p, cfg, obs, truth, err_hist, rew, term, action):
    """One control step for every env of the batch.

    ``action`` is flat, length 3N, in [-1, 1] (clipped here) and scaled by the force
    limits. Returns -1, or the index of the first env whose action is not finite, in which
    case nothing at all was changed. Writes obs, truth, reward and termination flags, and
    the error sample into err_hist[i, k - 1].
    """
    n = state.shape[0]
    for j in range(3 * n):
        if not math.isfinite(action[j]):
            return j // 3
    dt = cfg[C_DT]
    nsub = int(cfg[C_NSUB])
    maxd = cfg[C_MAXD]
    scratch = np.empty((4, 10))
    nsteps = int(cfg[C_NSTEPS])
    effort = cfg[C_EFFORT]
    for i in range(n):
        a0 = min(1.0, max(-1.0, float(action[3 * i])))
        a1 = min(1.0, max(-1.0, float(action[3 * i + 1])))
        a2 = min(1.0, max(-1.0, float(action[3 * i + 2])))
        fu = a0 * cfg[C_FU]
        fv = a1 * cfg[C_FV]
        fr = a2 * cfg[C_FR]
        advance(state, i, p, k[i] * dt, dt, nsub, fu, fv, fr, scratch)
        k[i] += 1
        _store_target(state, buf, p, cfg, i, k[i])
        err = _observe(state, k, buf, p, cfg, i, obs, truth)
        if k[i] - 1 < err_hist.shape[1]:
            err_hist[i, k[i] - 1] = err
        finite = True
        for c in range(9):
            if not math.isfinite(state[i, c]):
                finite = False
        if not finite:
            for c in range(obs.shape[1]):
                obs[i, c] = 0.0
            err = maxd
        r = -err - effort * (a0 * a0 + a1 * a1 + a2 * a2) / 3.0
        done = (not finite) or err > maxd
        if done:
            r -= maxd * max(0, nsteps - k[i])  # terminating never pays
        rew[i] = r
        term[i] = done
    return -1
