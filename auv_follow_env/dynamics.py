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
* ``proc``   (N, NR) float64: the random processes (target surge/turn OU deviations, current
  speed and direction, coloured disturbances), the thrusters' applied forces and the link's
  state (next send, latency state, Gilbert-Elliott state, the held packet, queue pointers,
  counters); columns ``R_*`` below;
* ``queue``  (N, Q, 8) float64: packets in flight, a FIFO ring in send order: measurement
  step, arrival step, measured (x, y, psi, u, v, r) of the target;
* ``rs``     (N,) uint64: each env's SplitMix64 generator state (seeded from the env's numpy
  generator at reset; v0 settings draw nothing from it);
* ``params`` (N, NP) float64: per-episode plant/target/current/disturbance/link parameters;
* ``cfg``    (NC,) float64: static configuration shared by the batch.

The target link (one code path for v0 and v1). At every send time the target's present
state is *measured* (with fix noise), given a latency and either lost or put in flight; at
every control step the newest packet that has arrived replaces the held one and older
packets still in flight are discarded. Send and arrival times fall on the control grid:
a packet is sent on the first step at or after its scheduled time (the schedule advances by
``period + jitter`` from the previous *scheduled* time, so the mean period is exact) and is
usable from the first step at or after ``send + latency``. v0's constant delay is the
setting period = dt, latency = tau, no loss, no noise: then the held packet at step k is
the target's state at step k - tau / dt exactly, as the delay line of eq. (12).
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
# v1 processes (zero / +-inf / 1 in v0: nothing drawn, nothing added)
P_OUU_STD, P_OUU_A = 32, 33  # target surge OU: std [m/s], per-step decay exp(-dt / T) [-]
P_OUR_STD, P_OUR_A = 34, 35  # target yaw-rate OU: std [rad/s], per-step decay [-]
P_ULO, P_UHI, P_RMAX = 36, 37, 38  # target bounds: surge speed [m/s], |yaw rate| [rad/s]
P_CS_MEAN, P_CS_STD, P_CS_A, P_CD_STEP = 39, 40, 41, 42  # Gauss-Markov current: mean speed,
#   speed std [m/s], per-step decay, direction random-walk std per step [rad]
P_DN = 43  # coloured disturbance std u/v/r [N, N, N m] in columns 43-45
P_DN_A = 46  # its per-step decay [-]
P_TH_ALPHA, P_TH_RATE = 47, 48  # thrusters: lag 1 - exp(-dt / T) (1 = none); max change per
#   step as a fraction of the force limit (inf = none)
P_PER, P_JIT = 49, 50  # send period, jitter half-width [control steps]
P_LAT_KIND, P_LAT_MEAN, P_LAT_SPREAD, P_LAT_CORR = 51, 52, 53, 54  # latency: 0 constant,
#   1 uniform(mean +- spread), 2 Gauss-Markov(mean, std = spread, corr. time) [control steps]
P_LOSS, P_GB, P_BG, P_LOSS_BAD = 55, 56, 57, 58  # i.i.d. loss prob., Gilbert-Elliott
#   p(good->bad), p(bad->good) per packet, loss prob. in the bad state
P_NS0, P_NSK, P_NPSI, P_NVEL, P_NYAW = 59, 60, 61, 62, 63  # fix noise: position sigma =
#   NS0 [m] + NSK [-] * range, heading [rad], velocity [m/s], yaw rate [rad/s]
NP = 64
#: latency models (P_LAT_KIND)
LAT_CONSTANT, LAT_UNIFORM, LAT_GAUSS_MARKOV = 0, 1, 2
#: disturbance tone frequencies [rad/s] (ours, NOTES.md) and weights (sum to 1)
DIST_OMEGA = (0.35, 0.9)
DIST_WEIGHT = (0.6, 0.4)

# --- cfg entries (shared) ----------------------------------------------------------------
C_DT, C_NSUB, C_D, C_L, C_PDX, C_PDY, C_PSID = 0, 1, 2, 3, 4, 5, 6
C_FU, C_FV, C_FR, C_MAXD, C_NSTEPS, C_EFFORT, C_INIT = 7, 8, 9, 10, 11, 12, 13
C_WARM, C_Q, C_OBSV1 = 14, 15, 16  # warm-up steps before t = 0, queue capacity, 1 = v1 layout
NC = 17

# --- proc columns (per env) --------------------------------------------------------------
R_OUU, R_OUR = 0, 1  # target surge / yaw-rate OU deviations [m/s, rad/s]
R_CSX, R_CDIR = 2, 3  # current speed deviation [m/s], direction [rad]
R_CGX, R_CGY = 4, 5  # resulting Gauss-Markov current, inertial x/y [m/s]
R_DN = 6  # coloured disturbances u/v/r [N, N, N m], columns 6-8
R_F = 9  # applied forces after the thruster model, columns 9-11
R_NEXT = 12  # next scheduled send [control steps]
R_LAST_SEND = 13  # step of the last send
R_LATX = 14  # Gauss-Markov latency deviation [steps]
R_GE = 15  # Gilbert-Elliott state: 0 good, 1 bad
R_HAS, R_NEW = 16, 17  # a packet is held / a newer one arrived this step
R_HMEAS, R_HARR = 18, 19  # held packet's measurement and arrival steps
R_HX = 20  # held packet's measured (x, y, psi, u, v, r), columns 20-25
R_QHEAD, R_QLEN = 26, 27  # queue ring head index and length
R_SENT, R_LOST, R_ARRIVED, R_DISCARDED, R_OVERFLOW = 28, 29, 30, 31, 32  # counters (packets sent
#   from t = 0 on)
R_GAUSS_HAS, R_GAUSS = 33, 34  # cached second Box-Muller deviate
NR = 35
Q_MEAS, Q_ARR, Q_X = 0, 1, 2  # queue entry: measurement step, arrival step, state at 2-7

# --- truth columns (per env, for evaluation only) ----------------------------------------
T_FOLLOWER = slice(0, 3)  # x, y, psi
T_TARGET = slice(3, 9)  # x_t, y_t, psi_t, u_t, v_t, r_t (present, undelayed)
T_REF = slice(9, 12)  # true reference x, y, psi (eq. (21) with the present target)
T_ERR = 12  # ||p - p_ref_true|| [m]
NT = 13

_W1, _W2 = DIST_OMEGA
INF = math.inf

# --- per-env random numbers: SplitMix64 (Steele, Lea & Flood 2014) ---------------------------
_SM_GAMMA = np.uint64(0x9E3779B97F4A7C15)
_SM_M1 = np.uint64(0xBF58476D1CE4E5B9)
_SM_M2 = np.uint64(0x94D049BB133111EB)
_S30, _S27, _S31, _S11 = np.uint64(30), np.uint64(27), np.uint64(31), np.uint64(11)


@njit(cache=True, inline="always")
def next_u64(rs, i):
    """The next 64-bit output of env i's SplitMix64 generator (state ``rs[i]`` advances)."""
    z = rs[i] + _SM_GAMMA
    rs[i] = z
    z = (z ^ (z >> _S30)) * _SM_M1
    z = (z ^ (z >> _S27)) * _SM_M2
    return z ^ (z >> _S31)


@njit(cache=True, inline="always")
def uniform01(rs, i):
    """A uniform double in [0, 1) with 53 random bits."""
    return float(next_u64(rs, i) >> _S11) * (1.0 / 9007199254740992.0)


@njit(cache=True)
def normal01(rs, proc, i):
    """A standard normal deviate (Box-Muller; the pair's second value is cached in proc)."""
    if proc[i, R_GAUSS_HAS] != 0.0:
        proc[i, R_GAUSS_HAS] = 0.0
        return proc[i, R_GAUSS]
    u1 = 1.0 - uniform01(rs, i)  # (0, 1]
    u2 = uniform01(rs, i)
    rad = math.sqrt(-2.0 * math.log(u1))
    a = 2.0 * math.pi * u2
    proc[i, R_GAUSS] = rad * math.sin(a)
    proc[i, R_GAUSS_HAS] = 1.0
    return rad * math.cos(a)


@njit(cache=True)
def draw_uniforms(rs, n):
    """``n`` uniforms from env 0's generator (for tests of the generator)."""
    out = np.empty(n)
    for j in range(n):
        out[j] = uniform01(rs, 0)
    return out


@njit(cache=True)
def draw_normals(rs, proc, n):
    """``n`` standard normals from env 0's generator (for tests)."""
    out = np.empty(n)
    for j in range(n):
        out[j] = normal01(rs, proc, 0)
    return out


@njit(cache=True, inline="always")
def _clip(x, lo, hi):
    return min(hi, max(lo, x))


@njit(cache=True, inline="always")
def target_velocity(p, i, t):
    """(u_t, r_t) of the v0 target at time t [m/s, rad/s] (the tones only); v_t = 0."""
    ut = p[i, P_TV] * (1.0 + p[i, P_TAU] * math.sin(p[i, P_TWU] * t + p[i, P_TPU]))
    rt = p[i, P_TAR] * math.sin(p[i, P_TWR] * t + p[i, P_TPR])
    return ut, rt


@njit(cache=True, inline="always")
def target_velocity_now(p, proc, i, t):
    """(u_t, r_t) at time t: tones plus the OU deviations held over the step, bounded."""
    ut, rt = target_velocity(p, i, t)
    return (_clip(ut + proc[i, R_OUU], p[i, P_ULO], p[i, P_UHI]),
            _clip(rt + proc[i, R_OUR], -p[i, P_RMAX], p[i, P_RMAX]))


@njit(cache=True, inline="always")
def current_inertial(p, i, t):
    """Inertial current of the tones (v_cx, v_cy) at time t [m/s]."""
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
def _forcing_from(p, i, S, g):
    """Forcing tuple (v_cx, v_cy, d_u [N], d_v [N], d_r [N m], u_t, r_t) from the ten tone sines S
    and the step-constant random parts g = (v_cx, v_cy, d_u, d_v, d_r, u_t, r_t) (zeros in v0);
    u_t and r_t are bounded (by +-inf in v0)."""
    return (p[i, P_CX] + p[i, P_CX + 1] * S[2] + g[0], p[i, P_CY] + p[i, P_CY + 1] * S[3] + g[1],
            p[i, P_D] * S[4] + p[i, P_D + 2] * S[5] + g[2], p[i, P_D + 4] * S[6] + p[i, P_D + 6] * S[7] + g[3],
            p[i, P_D + 8] * S[8] + p[i, P_D + 10] * S[9] + g[4],
            _clip(p[i, P_TV] * (1.0 + p[i, P_TAU] * S[0]) + g[5], p[i, P_ULO], p[i, P_UHI]),
            _clip(p[i, P_TAR] * S[1] + g[6], -p[i, P_RMAX], p[i, P_RMAX]))


_ZERO7 = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


@njit(cache=True)
def advance(state, i, p, t0, dt, nsub, fu, fv, fr, scratch, g):
    """Advance env i by dt from time t0 in nsub RK4 substeps, force held constant.

    The ten time-dependent tones are evaluated once at t0 and then rotated by half substeps
    (angle addition with small-angle cos/sin), so each stage time is exact to rounding.
    ``scratch`` is a (4, 10) float64 work array; ``g`` the step-constant random forcing.
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
    f0 = _forcing_from(p, i, S, g)
    for _ in range(nsub):
        for j in range(10):
            s, c = S[j], C[j]
            S[j] = s * RC[j] + c * RS[j]
            C[j] = c * RC[j] - s * RS[j]
        fm = _forcing_from(p, i, S, g)
        for j in range(10):
            s, c = S[j], C[j]
            S[j] = s * RC[j] + c * RS[j]
            C[j] = c * RC[j] - s * RS[j]
        f1 = _forcing_from(p, i, S, g)
        rk4_substep(state, i, p, h, fu, fv, fr, f0, fm, f1)
        f0 = f1


@njit(cache=True)
def integrate(state, p, cfg, t0, forces):
    """Advance every env one control step from time t0[i] under forces (N, 3) [N, N, N m].

    The bare physics kernel (follower and target, the tones only), without link,
    observation or reward: what the speed benchmark compares the env against.
    """
    nsub = int(cfg[C_NSUB])
    scratch = np.empty((4, 10))
    for i in range(state.shape[0]):
        advance(state, i, p, t0[i], cfg[C_DT], nsub, forces[i, 0], forces[i, 1], forces[i, 2], scratch,
                _ZERO7)


@njit(cache=True, inline="always")
def _random_forcing(proc, i):
    return (proc[i, R_CGX], proc[i, R_CGY], proc[i, R_DN], proc[i, R_DN + 1], proc[i, R_DN + 2],
            proc[i, R_OUU], proc[i, R_OUR])


@njit(cache=True)
def _gm(x, a, std, rs, proc, i):
    """One exact step of a stationary Gauss-Markov (OU) process with per-step decay a."""
    return a * x + math.sqrt(1.0 - a * a) * std * normal01(rs, proc, i)


@njit(cache=True)
def update_processes(proc, rs, p, i):
    """Advance env i's random processes by one control step (draws only where a std > 0)."""
    if p[i, P_OUU_STD] > 0.0:
        proc[i, R_OUU] = _gm(proc[i, R_OUU], p[i, P_OUU_A], p[i, P_OUU_STD], rs, proc, i)
    if p[i, P_OUR_STD] > 0.0:
        proc[i, R_OUR] = _gm(proc[i, R_OUR], p[i, P_OUR_A], p[i, P_OUR_STD], rs, proc, i)
    moved = False
    if p[i, P_CS_STD] > 0.0:
        proc[i, R_CSX] = _gm(proc[i, R_CSX], p[i, P_CS_A], p[i, P_CS_STD], rs, proc, i)
        moved = True
    if p[i, P_CD_STEP] > 0.0:
        proc[i, R_CDIR] += p[i, P_CD_STEP] * normal01(rs, proc, i)
        moved = True
    if moved:
        _current_vector(proc, p, i)
    for c in range(3):
        if p[i, P_DN + c] > 0.0:
            proc[i, R_DN + c] = _gm(proc[i, R_DN + c], p[i, P_DN_A], p[i, P_DN + c], rs, proc, i)


@njit(cache=True)
def _current_vector(proc, p, i):
    sp = max(0.0, p[i, P_CS_MEAN] + proc[i, R_CSX])
    proc[i, R_CGX] = sp * math.cos(proc[i, R_CDIR])
    proc[i, R_CGY] = sp * math.sin(proc[i, R_CDIR])


@njit(cache=True)
def _init_processes(proc, rs, p, i, direction):
    """Stationary start of env i's processes; link and thrusters empty."""
    for c in range(NR):
        proc[i, c] = 0.0
    if p[i, P_OUU_STD] > 0.0:
        proc[i, R_OUU] = p[i, P_OUU_STD] * normal01(rs, proc, i)
    if p[i, P_OUR_STD] > 0.0:
        proc[i, R_OUR] = p[i, P_OUR_STD] * normal01(rs, proc, i)
    if p[i, P_CS_STD] > 0.0:
        proc[i, R_CSX] = p[i, P_CS_STD] * normal01(rs, proc, i)
    proc[i, R_CDIR] = direction
    if p[i, P_CS_MEAN] != 0.0 or p[i, P_CS_STD] > 0.0:
        _current_vector(proc, p, i)
    for c in range(3):
        if p[i, P_DN + c] > 0.0:
            proc[i, R_DN + c] = p[i, P_DN + c] * normal01(rs, proc, i)


@njit(cache=True)
def _send(state, proc, queue, rs, p, cfg, i, step):
    """Measure the target at control step ``step`` and put the packet in flight (or lose it)."""
    dt = cfg[C_DT]
    xt, yt, pt = state[i, 6], state[i, 7], state[i, 8]
    ut, rt = target_velocity_now(p, proc, i, step * dt)
    vt = 0.0
    # fix noise: position sigma grows with range (as a USBL's), heading, velocity, yaw rate
    s0 = p[i, P_NS0]
    sk = p[i, P_NSK]
    if s0 > 0.0 or sk > 0.0:
        sig = s0 + sk * math.sqrt((xt - state[i, 0]) ** 2 + (yt - state[i, 1]) ** 2)
        xt += sig * normal01(rs, proc, i)
        yt += sig * normal01(rs, proc, i)
    if p[i, P_NPSI] > 0.0:
        pt += p[i, P_NPSI] * normal01(rs, proc, i)
    if p[i, P_NVEL] > 0.0:
        ut += p[i, P_NVEL] * normal01(rs, proc, i)
        vt += p[i, P_NVEL] * normal01(rs, proc, i)
    if p[i, P_NYAW] > 0.0:
        rt += p[i, P_NYAW] * normal01(rs, proc, i)
    # latency [steps]
    kind = p[i, P_LAT_KIND]
    lat = p[i, P_LAT_MEAN]
    if kind == LAT_UNIFORM:
        lat += p[i, P_LAT_SPREAD] * (2.0 * uniform01(rs, i) - 1.0)
    elif kind == LAT_GAUSS_MARKOV:
        a = math.exp(-(step - proc[i, R_LAST_SEND]) / p[i, P_LAT_CORR])
        proc[i, R_LATX] = _gm(proc[i, R_LATX], a, p[i, P_LAT_SPREAD], rs, proc, i)
        lat += proc[i, R_LATX]
    lat = max(0.0, lat)
    proc[i, R_LAST_SEND] = step
    counting = step >= 0
    if counting:
        proc[i, R_SENT] += 1.0
    # loss: i.i.d. with probability P_LOSS, and in the Gilbert-Elliott bad state with P_LOSS_BAD;
    # the channel state then moves (good -> bad with P_GB, bad -> good with P_BG)
    lost = False
    if p[i, P_LOSS] > 0.0 and uniform01(rs, i) < p[i, P_LOSS]:
        lost = True
    if p[i, P_GB] > 0.0:
        if proc[i, R_GE] != 0.0:
            if uniform01(rs, i) < p[i, P_LOSS_BAD]:
                lost = True
            if uniform01(rs, i) < p[i, P_BG]:
                proc[i, R_GE] = 0.0
        elif uniform01(rs, i) < p[i, P_GB]:
            proc[i, R_GE] = 1.0
    if lost:
        if counting:
            proc[i, R_LOST] += 1.0
        return
    Q = queue.shape[1]
    n = int(proc[i, R_QLEN])
    head = int(proc[i, R_QHEAD])
    if n == Q:  # full: the oldest packet in flight is dropped
        if queue[i, head, Q_MEAS] >= 0:
            proc[i, R_OVERFLOW] += 1.0
        head = (head + 1) % Q
        n -= 1
    slot = (head + n) % Q
    queue[i, slot, Q_MEAS] = step
    queue[i, slot, Q_ARR] = step + math.ceil(lat - 1e-6)
    queue[i, slot, Q_X] = xt
    queue[i, slot, Q_X + 1] = yt
    queue[i, slot, Q_X + 2] = pt
    queue[i, slot, Q_X + 3] = ut
    queue[i, slot, Q_X + 4] = vt
    queue[i, slot, Q_X + 5] = rt
    proc[i, R_QHEAD] = head
    proc[i, R_QLEN] = n + 1


@njit(cache=True)
def link_tick(state, proc, queue, rs, p, cfg, i, step):
    """The link at control step ``step``: send if due, then take the newest arrived packet."""
    if step >= proc[i, R_NEXT] - 1e-9:
        _send(state, proc, queue, rs, p, cfg, i, step)
        nxt = proc[i, R_NEXT] + p[i, P_PER]
        if p[i, P_JIT] > 0.0:
            nxt += p[i, P_JIT] * (2.0 * uniform01(rs, i) - 1.0)
        proc[i, R_NEXT] = nxt
    proc[i, R_NEW] = 0.0
    n = int(proc[i, R_QLEN])
    if n == 0:
        return
    Q = queue.shape[1]
    head = int(proc[i, R_QHEAD])
    newest = -1
    fifo = p[i, P_LAT_KIND] == LAT_CONSTANT  # constant latency: packets arrive in send order
    for m in range(n):
        if queue[i, (head + m) % Q, Q_ARR] <= step:
            newest = m
        elif fifo:
            break
    if newest < 0:
        return
    slot = (head + newest) % Q
    for c in range(6):
        proc[i, R_HX + c] = queue[i, slot, Q_X + c]
    proc[i, R_HMEAS] = queue[i, slot, Q_MEAS]
    proc[i, R_HARR] = step
    proc[i, R_HAS] = 1.0
    proc[i, R_NEW] = 1.0
    # counters cover the packets sent from t = 0 on: sent = lost + arrived + discarded + overflow
    # + still in flight
    if queue[i, slot, Q_MEAS] >= 0:
        proc[i, R_ARRIVED] += 1.0
    for m in range(newest):  # older packets still in flight: they would arrive out of order
        if queue[i, (head + m) % Q, Q_MEAS] >= 0:
            proc[i, R_DISCARDED] += 1.0
    proc[i, R_QHEAD] = (head + newest + 1) % Q
    proc[i, R_QLEN] = n - newest - 1


@njit(cache=True, inline="always")
def _lag(prev, cmd, alpha, lim):
    new = prev + alpha * (cmd - prev)
    if lim != INF:
        new = _clip(new, prev - lim, prev + lim)
    return new


@njit(cache=True)
def thrusters(proc, p, cfg, i, fu, fv, fr):
    """Applied forces from the commanded ones: first-order lag and rate limit (none in v0)."""
    alpha = p[i, P_TH_ALPHA]
    rate = p[i, P_TH_RATE]
    if alpha >= 1.0 and rate == INF:
        return fu, fv, fr
    fu = _lag(proc[i, R_F], fu, alpha, rate * cfg[C_FU])
    fv = _lag(proc[i, R_F + 1], fv, alpha, rate * cfg[C_FV])
    fr = _lag(proc[i, R_F + 2], fr, alpha, rate * cfg[C_FR])
    proc[i, R_F] = fu
    proc[i, R_F + 1] = fv
    proc[i, R_F + 2] = fr
    return fu, fv, fr


@njit(cache=True)
def _observe(state, k, proc, p, cfg, i, obs, truth):
    """Fill obs[i] (what the follower has) and truth[i] (evaluation only); return error."""
    dt = cfg[C_DT]
    t = k[i] * dt
    pdx = cfg[C_PDX]
    pdy = cfg[C_PDY]
    x, y, ps = state[i, 0], state[i, 1], state[i, 2]
    c = math.cos(ps)
    s = math.sin(ps)
    cx, cy = current_inertial(p, i, t)
    cx += proc[i, R_CGX]
    cy += proc[i, R_CGY]
    obs[i, 0] = state[i, 3]
    obs[i, 1] = state[i, 4]
    obs[i, 2] = state[i, 5]
    obs[i, 3] = c
    obs[i, 4] = s
    if proc[i, R_HAS] != 0.0:
        # the newest received packet (v0: the target tau ago, eq. (12))
        xd, yd, psd = proc[i, R_HX], proc[i, R_HX + 1], proc[i, R_HX + 2]
        cd = math.cos(psd)
        sd = math.sin(psd)
        ex = xd - x
        ey = yd - y
        rx = xd + cd * pdx - sd * pdy - x  # delayed reference, eq. (21) without prediction
        ry = yd + sd * pdx + cd * pdy - y
        obs[i, 5] = c * ex + s * ey
        obs[i, 6] = -s * ex + c * ey
        obs[i, 7] = math.cos(psd - ps)
        obs[i, 8] = math.sin(psd - ps)
        obs[i, 9] = proc[i, R_HX + 3]
        obs[i, 10] = proc[i, R_HX + 4]
        obs[i, 11] = proc[i, R_HX + 5]
        obs[i, 12] = c * rx + s * ry
        obs[i, 13] = -s * rx + c * ry
    else:
        for j in range(5, 14):
            obs[i, j] = 0.0
    obs[i, 14] = c * cx + s * cy
    obs[i, 15] = -s * cx + c * cy
    if cfg[C_OBSV1] != 0.0:
        if proc[i, R_HAS] != 0.0:
            obs[i, 16] = (k[i] - proc[i, R_HMEAS]) * dt
            obs[i, 17] = (k[i] - proc[i, R_HARR]) * dt
            obs[i, 19] = 1.0
        else:
            obs[i, 16] = 0.0
            obs[i, 17] = 0.0
            obs[i, 19] = 0.0
        obs[i, 18] = proc[i, R_NEW]
    # truth: present target and the true reference (eq. (21) with eta_t(t))
    xt, yt, pst = state[i, 6], state[i, 7], state[i, 8]
    ut, rt = target_velocity_now(p, proc, i, t)
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
def reset_kernel(state, k, proc, queue, rs, p, cfg, idx, seeds, directions, obs, truth):
    """Start episodes for the envs in ``idx`` (their params rows must be set).

    ``seeds[n]`` seeds env idx[n]'s generator; ``directions[n]`` is the Gauss-Markov
    current's initial direction [rad]. The target starts at the origin heading along +x at
    t = -warm-up (v0: -tau) and is simulated up to t = 0 with the link running, so at t = 0
    the link is in its steady state: in v0 the follower receives genuine tau-old
    measurements from the first step (nothing is zero-filled). The follower starts at rest
    with the held packet's heading, ``init_offset`` metres behind the reference point of
    the held packet (of the present target if no packet has arrived yet).
    """
    W = int(cfg[C_WARM])
    dt = cfg[C_DT]
    nsub = int(cfg[C_NSUB])
    scratch = np.empty((4, 10))
    for n in range(idx.shape[0]):
        i = idx[n]
        rs[i] = np.uint64(seeds[n])
        for c in range(9):
            state[i, c] = 0.0
        _init_processes(proc, rs, p, i, directions[n])
        proc[i, R_NEXT] = -W
        proc[i, R_LAST_SEND] = -W
        link_tick(state, proc, queue, rs, p, cfg, i, -W)
        for step in range(-W, 0):
            advance(state, i, p, step * dt, dt, nsub, 0.0, 0.0, 0.0, scratch,
                    _random_forcing(proc, i))  # follower rewritten below
            update_processes(proc, rs, p, i)
            link_tick(state, proc, queue, rs, p, cfg, i, step + 1)
        if proc[i, R_HAS] != 0.0:
            xd, yd, psd = proc[i, R_HX], proc[i, R_HX + 1], proc[i, R_HX + 2]
        else:
            xd, yd, psd = state[i, 6], state[i, 7], state[i, 8]
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
        _observe(state, k, proc, p, cfg, i, obs, truth)


@njit(cache=True)
def step_kernel(state, k, proc, queue, rs, p, cfg, obs, truth, err_hist, rew, term, action):
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
        fu, fv, fr = thrusters(proc, p, cfg, i, a0 * cfg[C_FU], a1 * cfg[C_FV], a2 * cfg[C_FR])
        advance(state, i, p, k[i] * dt, dt, nsub, fu, fv, fr, scratch, _random_forcing(proc, i))
        k[i] += 1
        update_processes(proc, rs, p, i)
        link_tick(state, proc, queue, rs, p, cfg, i, k[i])
        err = _observe(state, k, proc, p, cfg, i, obs, truth)
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
