"""The plant, the target, the disturbances and the delay line: one implementation.

Every kernel here works on a leading batch axis ``i`` and is compiled with numba (cached on
disk, so only the first run in a fresh checkout pays the compile). The single env calls it
with a batch of one; the vector env with a batch of N. There is no second copy.

Equations (Zhang et al. 2026, signs restored per docs/paper_notes.md):

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
* ``queue``  (N, Q, NQ) float64: packets in flight, a FIFO ring in send order: measurement
  step, arrival step, measured (x, y, psi, u, v, r) of the target, cos/sin of that psi;
* ``rs``     (N,) uint64: each env's SplitMix64 generator state (seeded from the env's numpy
  generator at reset; v0 settings draw nothing from it);
* ``params`` (N, NP) float64: per-episode plant/target/current/disturbance/link parameters;
* ``err_hist`` (N, S) float64: each env's tracking-error samples of its episode (row i, sample
  k - 1 after step k), written 8 at a time (one cache line) from ``err_stage``, and at once
  when the episode ends (termination or k = n_steps): :func:`error_samples` reads them at
  any time;
* ``err_stage`` (N, 8) float64: each env's latest samples, sample k - 1 in column (k - 1) % 8
  (dense, so the per-step write streams; a per-step write into err_hist itself was a cache
  miss per env-step once autoresets had desynchronised the envs' steps);
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
import types as pytypes

import numpy as np
from llvmlite import ir as llir
from numba import njit, prange, types
from numba.extending import intrinsic

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
# leader targets (zero in v0 and the v1 tiers: P_LD_MODES = 0 switches the leader off, nothing drawn)
P_LD_MODES, P_LD_SURVEY = 64, 65  # 1: cruise / turn modes, 2: also loiter / sprint; share of survey episodes
P_LD_UC, P_LD_RT, P_LD_MC, P_LD_MT = 66, 67, 68, 69  # cruise speed [m/s], turn rate [rad/s], mean cruise
#   and turn durations [s]
P_LD_UL, P_LD_ML, P_LD_US, P_LD_MS = 70, 71, 72, 73  # loiter speed, mean duration; sprint speed, mean duration
P_LD_LEG, P_LD_RS = 74, 75  # survey leg length [m], U-turn rate [rad/s]
P_LD_AU, P_LD_AR = 76, 77  # per-step decay of the speed and turn-rate lags exp(-dt / T) [-]
P_LD_WU, P_LD_WR, P_LD_WA = 78, 79, 80  # wobble std of speed [m/s] and turn rate [rad/s], per-step decay
P_LD_TR = 81  # the turn-rate lag's time constant [s] (a U-turn's command ends pi - omega T_r early)
P_OUT_P, P_OUT_S = 82, 83  # share of fixes that are multipath outliers, scale of their Student-t error [m]
P_LD_DT = 84  # the control step [s] (the leader's progress in time)
NP = 85
#: latency models (P_LAT_KIND)
LAT_CONSTANT, LAT_UNIFORM, LAT_GAUSS_MARKOV = 0, 1, 2
#: disturbance tone frequencies [rad/s] (ours, docs/paper_notes.md) and weights (sum to 1)
DIST_OMEGA = (0.35, 0.9)
DIST_WEIGHT = (0.6, 0.4)

# --- cfg entries (shared) ----------------------------------------------------------------
C_DT, C_NSUB, C_D, C_L, C_PDX, C_PDY, C_PSID = 0, 1, 2, 3, 4, 5, 6
C_FU, C_FV, C_FR, C_MAXD, C_NSTEPS, C_EFFORT, C_INIT = 7, 8, 9, 10, 11, 12, 13
C_WARM, C_Q, C_OBSV1 = 14, 15, 16  # warm-up steps before t = 0, queue capacity, 1 = v1 layout
C_FAST = 17  # 1 = sincos="simd" (default): the step's sin/cos by :func:`fast_sincos` (SIMD, <= 1 ULP), 0 = libm
NC = 18

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
# libm values computed once and reused (each is a pure function of its key, so reusing it
# changes no result): the ten tones at step R_TK (sines, cosines), and cos/sin of the
# follower's and the target's heading with the heading they belong to (NaN keys: none)
R_TK = 35  # step of the cached tone values
R_TS, R_TC = 36, 46  # tone sines (36-45) and cosines (46-55) at t = R_TK * dt
R_PSK, R_PSC, R_PSS = 56, 57, 58  # follower heading, its cos, its sin
R_PTK, R_PTC, R_PTS = 59, 60, 61  # target heading, its cos, its sin
R_HC, R_HS = 62, 63  # cos/sin of the held packet's heading
# leader targets: the hidden mode (LD_* below), the U-turn side (+-1), the progress in the mode (s,
# m or rad) and the threshold at which it ends, the lagged speed and turn-rate commands and the wobbles
R_LD_MODE, R_LD_SIDE, R_LD_PROG, R_LD_THR = 64, 65, 66, 67
R_LD_UB, R_LD_RB, R_LD_WU, R_LD_WR = 68, 69, 70, 71
NR = 72
#: the leader's modes
LD_CRUISE, LD_TURN_L, LD_TURN_R, LD_LOITER, LD_SPRINT, LD_LEG, LD_UTURN = 0, 1, 2, 3, 4, 5, 6
LD_K = 4.0  #: Gamma shape of the wander modes' durations (coefficient of variation 1 / sqrt(4) = 0.5)
LD_LEG_JITTER = 0.05  #: a survey leg's length is the episode's leg length times 1 + U(-0.05, 0.05)
OUTLIER_DOF = 3.0  #: degrees of freedom of the outlier fixes' 2-D Student-t position error
Q_MEAS, Q_ARR, Q_X = 0, 1, 2  # queue entry: measurement step, arrival step, state at 2-7
Q_C, Q_S = 8, 9  # cos/sin of the measured heading
NQ = 10

# --- truth columns (per env, for evaluation only) ----------------------------------------
T_FOLLOWER = slice(0, 3)  # x, y, psi
T_TARGET = slice(3, 9)  # x_t, y_t, psi_t, u_t, v_t, r_t (present, undelayed)
T_REF = slice(9, 12)  # true reference x, y, psi (eq. (21) with the present target)
T_ERR = 12  # ||p - p_ref_true|| [m]
NT = 13

_W1, _W2 = DIST_OMEGA
INF = math.inf

#: numba options of a kernel function that only compiled code calls and that allocates nothing:
#: no reference counting (numba took a reference, two atomic operations, on every array argument
#: of every call and inlined helper: more than the arithmetic of some helpers; DEVELOPERS.md) and
#: no Python or C entry point (less to compile: cold start). Such a function cannot allocate
#: (numba refuses to compile it) and cannot be called from Python.
INTERNAL = {"_nrt": False, "no_cpython_wrapper": True, "no_cfunc_wrapper": True}


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


@njit(cache=True, **INTERNAL)
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
    """min(hi, max(lo, x)) with Python's (and numba's builtin) semantics, written as selects so
    that loops over envs vectorise (a NaN x gives lo, as max(lo, nan) does)."""
    y = x if x > lo else lo
    return y if y < hi else hi


# --- sincos="simd" (formerly fast_math): a vectorisable sin/cos ------------------------------
# fdlibm's method (Sun Microsystems, 1993; freely distributable), written branch-free so that
# a loop over envs compiles to SIMD code: x - n pi/2 in double-double by the two-round
# Cody-Waite reduction of e_rem_pio2.c (pi/2 in 33-bit pieces, so each n * piece is exact
# for n < 2^20), then the minimax polynomials of __kernel_sin / __kernel_cos with the tail.
# Within 1 ULP of the exact value for |x| <= FAST_TRIG_MAX (tests/test_fast_math.py);
# glibc's sin/cos are within 0.52 ULP (measured), and the two differ in the last bit for about 3 % of
# arguments. The envs' default (``sincos="simd"``) since 0.2.0; ``sincos="libm"`` keeps glibc's
# scalar calls (the v0 golden arrays were recorded with them; the contract is a 1e-9 tolerance).
_INVPIO2 = 6.36619772367581382433e-01
_PIO2_1 = 1.57079632673412561417e+00  # first 33 bits of pi/2
_PIO2_2 = 6.07710050630396597660e-11  # next 33 bits
_PIO2_2T = 2.02226624879595063154e-21  # pi/2 - _PIO2_1 - _PIO2_2
_S1, _S2, _S3 = -1.66666666666666324348e-01, 8.33333333332248946124e-03, -1.98412698298579493134e-04
_S4, _S5, _S6 = 2.75573137070700676789e-06, -2.50507602534068634195e-08, 1.58969099521155010221e-10
_C1, _C2, _C3 = 4.16666666666666019037e-02, -1.38888888888741095749e-03, 2.48015872894767294178e-05
_C4, _C5, _C6 = -2.75573143513906633035e-07, 2.08757232129817482790e-09, -1.13596475577881948265e-11
#: |x| beyond which fast_sincos is not used (the callers fall back to libm for that lane)
FAST_TRIG_MAX = 1.0e5


@njit(cache=True, inline="always")
def fast_sincos(x):
    """(sin x, cos x) within 1 ULP for |x| <= FAST_TRIG_MAX, branch-free (vectorises)."""
    n = math.floor(x * _INVPIO2 + 0.5)
    t = x - n * _PIO2_1  # exact
    w = n * _PIO2_2  # exact
    r = t - w
    w = n * _PIO2_2T - ((t - r) - w)
    y0 = r - w  # x - n pi/2 = y0 + y1, |y0| <= pi/4
    y1 = (r - y0) - w
    z = y0 * y0
    v = z * y0
    ps = _S2 + z * (_S3 + z * (_S4 + z * (_S5 + z * _S6)))
    s = y0 - ((z * (0.5 * y1 - v * ps) - y1) - v * _S1)
    pc = z * (_C1 + z * (_C2 + z * (_C3 + z * (_C4 + z * (_C5 + z * _C6)))))
    hz = 0.5 * z
    w = 1.0 - hz
    c = w + (((1.0 - w) - hz) + (z * pc - y0 * y1))
    q = n - 4.0 * math.floor(n * 0.25)  # quadrant 0..3
    odd = (q == 1.0) | (q == 3.0)
    sb = c if odd else s
    cb = s if odd else c
    return (-sb if q >= 2.0 else sb), (-cb if (q == 1.0) | (q == 2.0) else cb)


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
def _target_velocity_cached(p, proc, i):
    """target_velocity_now at the step of env i's cached tones (same operations, sines cached)."""
    ut = p[i, P_TV] * (1.0 + p[i, P_TAU] * proc[i, R_TS])
    rt = p[i, P_TAR] * proc[i, R_TS + 1]
    return (_clip(ut + proc[i, R_OUU], p[i, P_ULO], p[i, P_UHI]),
            _clip(rt + proc[i, R_OUR], -p[i, P_RMAX], p[i, P_RMAX]))


@njit(cache=True, inline="always")
def current_inertial(p, i, t):
    """Inertial current of the tones (v_cx, v_cy) at time t [m/s]."""
    cx = p[i, P_CX] + p[i, P_CX + 1] * math.sin(p[i, P_CX + 2] * t + p[i, P_CX + 3])
    cy = p[i, P_CY] + p[i, P_CY + 1] * math.sin(p[i, P_CY + 2] * t + p[i, P_CY + 3])
    return cx, cy


@njit(cache=True, inline="always")
def _taylor_cos_sin(d):
    """(cos d, sin d) by their Taylor polynomials (exact to double precision for |d| <= 0.25)."""
    d2 = d * d
    c = 1.0 - d2 / 2.0 * (1.0 - d2 / 12.0 * (1.0 - d2 / 30.0 * (1.0 - d2 / 56.0 * (
        1.0 - d2 / 90.0 * (1.0 - d2 / 132.0)))))
    s = d * (1.0 - d2 / 6.0 * (1.0 - d2 / 20.0 * (1.0 - d2 / 42.0 * (1.0 - d2 / 72.0 * (
        1.0 - d2 / 110.0 * (1.0 - d2 / 156.0))))))
    return c, s


#: |d| above which cos_sin_small calls libm
SMALL_ANGLE = 0.25


@njit(cache=True, inline="always")
def cos_sin_small(d, exact=True):
    """(cos d, sin d): Taylor polynomials (exact to double precision for |d| <= 0.25), libm beyond.

    Used for the small angle increments inside one RK4 step (stage headings, tone phasors),
    where it replaces libm calls that dominate the kernel's cost. ``exact=False`` (a
    compile-time constant in the block kernels) drops the libm branch so a loop over envs
    vectorises; those callers flag the lanes with |d| > 0.25 and redo them with ``exact=True``.
    """
    if exact:
        return _cos_sin_exact(d)
    return _taylor_cos_sin(d)


@njit(cache=True, error_model="numpy")
def _cos_sin_exact(d):
    """:func:`cos_sin_small` with libm beyond SMALL_ANGLE; called, not inlined (compiled once for
    the RK4 lane's seven increments, cold start)."""
    if abs(d) > SMALL_ANGLE:
        return math.cos(d), math.sin(d)
    return _taylor_cos_sin(d)


@njit(cache=True, inline="always")
def _turn(c0, s0, d, exact):
    """(cos, sin) of (angle + d) from (cos, sin) of the angle."""
    cd, sd = cos_sin_small(d, exact)
    return c0 * cd - s0 * sd, s0 * cd + c0 * sd


@njit(cache=True, inline="always")
def follower_rhs(m, iz, xu, yv, nr, f, c, s, u, v, r, fu, fv, fr):
    """Right-hand side of eqs. (3)-(9) for the follower at heading (cos, sin) = (c, s), with
    true mass m, inertia iz and damping xu, yv, nr, given the forcing tuple
    f = (v_cx, v_cy, d_u, d_v, d_r, u_t, r_t)."""
    ur = u - (c * f[0] + s * f[1])  # eq. (9) with eq. (5)
    vr = v - (-s * f[0] + c * f[1])
    return (c * u - s * v, s * u + c * v, r,
            (fu - xu * ur + m * v * r + f[2]) / m,
            (fv - yv * vr - m * u * r + f[3]) / m,
            (fr - nr * r + f[4]) / iz)


@njit(cache=True, inline="always")
def rk4_lane(x, y, ps, u, v, r, xt, yt, pt, c0, s0, ct, st, h, fu, fv, fr, m, iz, xu, yv, nr, f0, fm, f1,
             exact):
    """One classical RK4 step of length h for follower and target of one env.

    (c0, s0) and (ct, st): cos/sin of the follower's and the target's heading at the step's
    start; f0, fm, f1: the forcing at the step's start, midpoint and end (the stage times).
    The stage headings psi + dpsi use cos/sin of psi and of the small increment dpsi.
    Returns the nine new state values and whether an increment exceeded SMALL_ANGLE (only
    meaningful with ``exact=False``: then the lane must be redone with ``exact=True``).
    """
    hh = 0.5 * h
    a0, a1, a2, a3, a4, a5 = follower_rhs(m, iz, xu, yv, nr, f0, c0, s0, u, v, r, fu, fv, fr)
    e1 = hh * a2
    c, s = _turn(c0, s0, e1, exact)
    b0, b1, b2, b3, b4, b5 = follower_rhs(m, iz, xu, yv, nr, fm, c, s, u + hh * a3, v + hh * a4, r + hh * a5,
                                          fu, fv, fr)
    e2 = hh * b2
    c, s = _turn(c0, s0, e2, exact)
    k0, k1, k2, k3, k4, k5 = follower_rhs(m, iz, xu, yv, nr, fm, c, s, u + hh * b3, v + hh * b4, r + hh * b5,
                                          fu, fv, fr)
    e3 = h * k2
    c, s = _turn(c0, s0, e3, exact)
    d0, d1, d2, d3, d4, d5 = follower_rhs(m, iz, xu, yv, nr, f1, c, s, u + h * k3, v + h * k4, r + h * k5,
                                          fu, fv, fr)
    w = h / 6.0
    # target, eq. (10) with v_t = 0: x' = u_t cos, y' = u_t sin, psi' = r_t
    e4 = hh * f0[6]
    e5 = hh * fm[6]
    e6 = h * fm[6]
    cb, sb = _turn(ct, st, e4, exact)
    cc, sc = _turn(ct, st, e5, exact)
    cd, sd = _turn(ct, st, e6, exact)
    big = ((abs(e1) > SMALL_ANGLE) | (abs(e2) > SMALL_ANGLE) | (abs(e3) > SMALL_ANGLE)
           | (abs(e4) > SMALL_ANGLE) | (abs(e5) > SMALL_ANGLE) | (abs(e6) > SMALL_ANGLE))
    return (x + w * (a0 + 2.0 * (b0 + k0) + d0),
            y + w * (a1 + 2.0 * (b1 + k1) + d1),
            ps + w * (a2 + 2.0 * (b2 + k2) + d2),
            u + w * (a3 + 2.0 * (b3 + k3) + d3),
            v + w * (a4 + 2.0 * (b4 + k4) + d4),
            r + w * (a5 + 2.0 * (b5 + k5) + d5),
            xt + w * (f0[5] * ct + 2.0 * fm[5] * (cb + cc) + f1[5] * cd),
            yt + w * (f0[5] * st + 2.0 * fm[5] * (sb + sc) + f1[5] * sd),
            pt + w * (f0[6] + 4.0 * fm[6] + f1[6])), big


# --- structure-of-arrays blocks -------------------------------------------------------------
# The batched kernels work on blocks of up to BLOCK envs at a time: the state, the parameters
# the integrator reads and every intermediate are copied into rows of one flat work buffer
# (row r of a block is ``wk[r * BLOCK : (r + 1) * BLOCK]``: one contiguous row per variable,
# the env as the innermost index), so each loop over the envs of a block is branch-free and
# vectorises (SIMD over envs; the rows of one buffer sit at compile-time distances, so the
# compiler needs no aliasing checks). libm calls (which numba cannot vectorise without
# changing their results) sit in loops of their own. Every env still goes through exactly
# the same floating-point operations in the same order as a scalar per-env loop would, so
# the results do not depend on the block size or on the lane.
BLOCK = 32  #: envs per block (the work buffer: NK rows of BLOCK doubles, 37 KB, in L1/L2; 16 measured no faster)

#: parameter columns gathered into a block (rows K_PP.. of the buffer), in this order
_PP_COLS = np.array([P_M, P_IZ, P_XU, P_YV, P_NR,
                     P_CX, P_CX + 1, P_CY, P_CY + 1, P_D, P_D + 2, P_D + 4, P_D + 6, P_D + 8, P_D + 10,
                     P_TV, P_TAU, P_TAR, P_ULO, P_UHI, P_RMAX], dtype=np.int64)
#: the ten tones of the forcing: (omega column or -1 / -2 for DIST_OMEGA[0] / [1], phase column);
#: order: target surge, target yaw rate, current x, current y, then d_u, d_v, d_r (two tones each)
_TONE_OMEGA = np.array([P_TWU, P_TWR, P_CX + 2, P_CY + 2, -1, -2, -1, -2, -1, -2], dtype=np.int64)
_TONE_PHASE = np.array([P_TPU, P_TPR, P_CX + 3, P_CY + 3, P_D + 1, P_D + 3, P_D + 5, P_D + 7, P_D + 9,
                        P_D + 11], dtype=np.int64)
# rows of a block's work buffer
K_ST = 0  # state x, y, psi, u, v, r, x_t, y_t, psi_t (rows 0-8)
K_PP = 9  # gathered parameters, in _PP_COLS order (rows 9-29):
K_M, K_IZ, K_XU, K_YV, K_NR = 9, 10, 11, 12, 13
K_CX0, K_CX1, K_CY0, K_CY1, K_D = 14, 15, 16, 17, 18  # K_D..K_D + 5: disturbance amplitudes
K_TV, K_TAU, K_TAR, K_ULO, K_UHI, K_RMAX = 24, 25, 26, 27, 28, 29
K_OM, K_PH = 30, 40  # the ten tone frequencies [rad/s] and phases [rad]
K_G = 50  # step-constant random forcing (v_cx, v_cy, d_u, d_v, d_r, u_t, r_t), rows 50-56
K_F = 57  # applied forces, rows 57-59
K_T0 = 60  # time at the step's start
K_S, K_C, K_RC, K_RS = 61, 71, 81, 91  # tone sines, cosines and their half-substep rotation
K_F0, K_FM, K_F1 = 101, 108, 115  # forcing at the substep's start, midpoint, end
K_C0, K_S0, K_CT, K_STT = 122, 123, 124, 125  # cos/sin of the follower's and the target's heading
K_OUT = 126  # new state, rows 126-134
K_BIG = 135  # lane flag: an increment exceeded SMALL_ANGLE
K_DK = 136  # the ten tones' half-substep angles omega * h / 2 whose cos/sin rows K_RC.., K_RS..
#   hold (NaN: none yet), rows 136-145: the rotation factors are recomputed only where it changed
NK = 146


#: lanes of a SIMD vector of doubles (AVX2): a reset's warm-up pads a small block to whole vectors
#: (a SIMD loop runs lanes beyond the last whole vector one at a time, each costing about a vector)
PAD = 4

#: the slots [lo, hi) of a work buffer that hold the rotation-factor keys (rows K_DK..): NaN in a new one
WK_KEYS = (K_DK * BLOCK, (K_DK + 10) * BLOCK)


@njit(cache=True, inline="always")
def work_buffer(zeroed):
    """A block's work buffer (NK rows of BLOCK doubles): uninitialised (every row a lane reads is
    written first) or zeroed, with the rotation-factor keys (rows K_DK..) NaN."""
    wk = np.zeros(NK * BLOCK) if zeroed else np.empty(NK * BLOCK)
    wk[WK_KEYS[0]:WK_KEYS[1]] = np.nan
    return wk


@njit(cache=True)
def new_work_buffer(zeroed):
    """:func:`work_buffer` for callers outside numba (tests, benchmarks), which pass it to a
    kernel compiled without reference counting (``_nrt=False``: such a kernel cannot allocate)."""
    return work_buffer(zeroed)


_ZERO7 = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


@intrinsic
def _ix(typingctx, row, b):
    """Index of lane b of row ``row``, ``row * BLOCK + b`` as uint64 (unsigned: no negative-index
    wrap-around to check). An intrinsic: two LLVM instructions at each use, where an
    ``inline="always"`` function made numba re-run its front end at each of the kernels' hundreds
    of uses (cold start)."""
    if not isinstance(row, types.Integer) or not isinstance(b, types.Integer):
        return None
    sig = types.uint64(row, b)

    def codegen(context, builder, sig, args):
        r = context.cast(builder, args[0], sig.args[0], types.uint64)
        lane = context.cast(builder, args[1], sig.args[1], types.uint64)
        return builder.add(builder.mul(r, llir.Constant(llir.IntType(64), BLOCK)), lane)

    return sig, codegen


@njit(cache=True, inline="always")
def _sincos_rows(wk, src, sin_row, cos_row, m, fast):
    """sin/cos of lanes 0..m-1 of row ``src`` into rows ``sin_row`` and ``cos_row`` (all three
    distinct): :func:`_sincos_rows_r`, called with runtime ints (numba compiles a called function
    once per literal argument: one compiled copy for every use, cold start)."""
    _sincos_rows_r(wk, np.int64(src), np.int64(sin_row), np.int64(cos_row), np.int64(m), fast)


@njit(cache=True, error_model="numpy", **INTERNAL)
def _sincos_rows_r(wk, src, sin_row, cos_row, m, fast):
    """sin/cos of lanes 0..m-1 of row ``src`` into rows ``sin_row`` and ``cos_row`` (all three
    distinct): libm (scalar calls), or fast_sincos in a SIMD loop with libm for the lanes whose
    argument exceeds FAST_TRIG_MAX."""
    if m == 1:  # (the single env's blocks) no loop
        x = wk[_ix(src, 0)]
        if fast and abs(x) <= FAST_TRIG_MAX:
            sv, cv = fast_sincos(x)
        else:
            sv, cv = math.sin(x), math.cos(x)
        wk[_ix(sin_row, 0)] = sv
        wk[_ix(cos_row, 0)] = cv
        return
    if fast:
        nbig = 0
        for b in range(m):
            x = wk[_ix(src, b)]
            nbig += abs(x) > FAST_TRIG_MAX
            sv, cv = fast_sincos(x)
            wk[_ix(sin_row, b)] = sv
            wk[_ix(cos_row, b)] = cv
        if nbig:
            for b in range(m):
                x = wk[_ix(src, b)]
                if abs(x) > FAST_TRIG_MAX:
                    wk[_ix(sin_row, b)] = math.sin(x)
                    wk[_ix(cos_row, b)] = math.cos(x)
    else:
        for b in range(m):
            x = wk[_ix(src, b)]
            wk[_ix(sin_row, b)] = math.sin(x)
            wk[_ix(cos_row, b)] = math.cos(x)


@njit(cache=True, inline="always", error_model="numpy")
def _tone_values(wk, m, fast):
    """sin/cos of the ten tones at each lane's time (row K_T0) into rows K_S.., K_C.. (row K_OUT,
    free outside the RK4 step, holds each tone's arguments meanwhile)."""
    for j in range(10):
        for b in range(m):
            wk[_ix(K_OUT, b)] = wk[_ix(K_OM + j, b)] * wk[_ix(K_T0, b)] + wk[_ix(K_PH + j, b)]
        _sincos_rows(wk, K_OUT, K_S + j, K_C + j, m, fast)


@njit(cache=True, error_model="numpy", **INTERNAL)
def _heading_values(wk, m, fast):
    """cos/sin of both headings (state rows K_ST + 2, K_ST + 8) into rows K_C0, K_S0, K_CT, K_STT."""
    _sincos_rows(wk, K_ST + 2, K_S0, K_C0, m, fast)
    _sincos_rows(wk, K_ST + 8, K_STT, K_CT, m, fast)


@njit(cache=True, error_model="numpy", **INTERNAL)
def _trig_values(wk, m, fast):
    """:func:`_tone_values` and :func:`_heading_values`: the sin/cos at a step's start, for a block.
    Not inlined (called once per block): one compiled copy for the step's refresh, the reset's
    warm-up and the single env (cold start)."""
    _tone_values(wk, m, fast)
    _heading_values(wk, m, fast)


@njit(cache=True, inline="always")
def _gather_lane(state, p, i, wk, b):
    """Copy env i of state (N, 9) and params (N, NP) into lane b of the block's rows."""
    for c in range(9):
        wk[_ix(K_ST + c, b)] = state[i, c]
    for c in range(_PP_COLS.shape[0]):
        wk[_ix(K_PP + c, b)] = p[i, _PP_COLS[c]]
    for j in range(10):
        oc = _TONE_OMEGA[j]
        wk[_ix(K_OM + j, b)] = p[i, oc] if oc >= 0 else (_W1 if oc == -1 else _W2)
        wk[_ix(K_PH + j, b)] = p[i, _TONE_PHASE[j]]


@njit(cache=True, error_model="numpy", **INTERNAL)
def gather_block(state, p, a, m, wk):
    """Copy envs a..a+m-1 of state (N, 9) and params (N, NP) into the block's rows."""
    for b in range(m):
        _gather_lane(state, p, a + b, wk, b)


@njit(cache=True, inline="always")
def _forcing_lane(wk, row, out, b):
    """Forcing (v_cx, v_cy, d_u [N], d_v [N], d_r [N m], u_t, r_t) of lane b into rows
    ``out``.., from the ten tone sines in rows ``row``.. and the step-constant random parts
    (zeros in v0); u_t and r_t are bounded (by +-inf in v0). (Stored element by element:
    a returned tuple would not vectorise.)"""
    wk[_ix(out, b)] = wk[_ix(K_CX0, b)] + wk[_ix(K_CX1, b)] * wk[_ix(row + 2, b)] + wk[_ix(K_G, b)]
    wk[_ix(out + 1, b)] = wk[_ix(K_CY0, b)] + wk[_ix(K_CY1, b)] * wk[_ix(row + 3, b)] + wk[_ix(K_G + 1, b)]
    wk[_ix(out + 2, b)] = (wk[_ix(K_D, b)] * wk[_ix(row + 4, b)] + wk[_ix(K_D + 1, b)] * wk[_ix(row + 5, b)]
                           + wk[_ix(K_G + 2, b)])
    wk[_ix(out + 3, b)] = (wk[_ix(K_D + 2, b)] * wk[_ix(row + 6, b)] + wk[_ix(K_D + 3, b)] * wk[_ix(row + 7, b)]
                           + wk[_ix(K_G + 3, b)])
    wk[_ix(out + 4, b)] = (wk[_ix(K_D + 4, b)] * wk[_ix(row + 8, b)] + wk[_ix(K_D + 5, b)] * wk[_ix(row + 9, b)]
                           + wk[_ix(K_G + 4, b)])
    wk[_ix(out + 5, b)] = _clip(wk[_ix(K_TV, b)] * (1.0 + wk[_ix(K_TAU, b)] * wk[_ix(row, b)]) + wk[_ix(K_G + 5, b)],
                                wk[_ix(K_ULO, b)], wk[_ix(K_UHI, b)])
    wk[_ix(out + 6, b)] = _clip(wk[_ix(K_TAR, b)] * wk[_ix(row + 1, b)] + wk[_ix(K_G + 6, b)], -wk[_ix(K_RMAX, b)],
                                wk[_ix(K_RMAX, b)])


@njit(cache=True, inline="always")
def _store7(wk, row, b, f):
    # written out (a loop over a tuple index would not vectorise)
    wk[_ix(row, b)] = f[0]
    wk[_ix(row + 1, b)] = f[1]
    wk[_ix(row + 2, b)] = f[2]
    wk[_ix(row + 3, b)] = f[3]
    wk[_ix(row + 4, b)] = f[4]
    wk[_ix(row + 5, b)] = f[5]
    wk[_ix(row + 6, b)] = f[6]


@njit(cache=True, inline="always")
def _store9(wk, row, b, x):
    _store7(wk, row, b, x)
    wk[_ix(row + 7, b)] = x[7]
    wk[_ix(row + 8, b)] = x[8]


@njit(cache=True, inline="always")
def _load7(wk, row, b):
    return (wk[_ix(row, b)], wk[_ix(row + 1, b)], wk[_ix(row + 2, b)], wk[_ix(row + 3, b)],
            wk[_ix(row + 4, b)], wk[_ix(row + 5, b)], wk[_ix(row + 6, b)])


@njit(cache=True, inline="always")
def _rk4_block_lane(wk, h, b, exact):
    return rk4_lane(wk[_ix(K_ST, b)], wk[_ix(K_ST + 1, b)], wk[_ix(K_ST + 2, b)], wk[_ix(K_ST + 3, b)],
                    wk[_ix(K_ST + 4, b)], wk[_ix(K_ST + 5, b)], wk[_ix(K_ST + 6, b)], wk[_ix(K_ST + 7, b)],
                    wk[_ix(K_ST + 8, b)], wk[_ix(K_C0, b)], wk[_ix(K_S0, b)], wk[_ix(K_CT, b)],
                    wk[_ix(K_STT, b)], h, wk[_ix(K_F, b)], wk[_ix(K_F + 1, b)], wk[_ix(K_F + 2, b)],
                    wk[_ix(K_M, b)], wk[_ix(K_IZ, b)], wk[_ix(K_XU, b)], wk[_ix(K_YV, b)], wk[_ix(K_NR, b)],
                    _load7(wk, K_F0, b), _load7(wk, K_FM, b), _load7(wk, K_F1, b), exact)


@njit(cache=True, error_model="numpy", **INTERNAL)
def _rotation_factors(wk, hh, m):
    """cos/sin of each tone's half-substep angle omega * hh into rows K_RC.., K_RS..: small-angle
    polynomials, libm for the lanes beyond SMALL_ANGLE. A tone's row is recomputed only if some
    lane's angle differs from the one its rows hold (keys in rows K_DK..; the same angle with
    the same sign gives the same values, so reuse changes no result). The tone frequencies
    that are constants of the config (the disturbance tones, in v0 the target's) then cost a
    compare per step instead of a polynomial with eleven divisions."""
    for j in range(10):
        ndiff = 0
        for b in range(m):
            d = wk[_ix(K_OM + j, b)] * hh
            key = wk[_ix(K_DK + j, b)]
            ndiff += (d != key) | (math.copysign(1.0, d) != math.copysign(1.0, key))  # (NaN: differs)
        if ndiff:
            nbig = 0
            for b in range(m):
                d = wk[_ix(K_OM + j, b)] * hh
                rc, rsn = cos_sin_small(d, False)
                wk[_ix(K_RC + j, b)] = rc
                wk[_ix(K_RS + j, b)] = rsn
                wk[_ix(K_DK + j, b)] = d
                nbig += abs(d) > SMALL_ANGLE
            if nbig:
                for b in range(m):
                    d = wk[_ix(K_OM + j, b)] * hh
                    if abs(d) > SMALL_ANGLE:
                        rc, rsn = cos_sin_small(d, True)
                        wk[_ix(K_RC + j, b)] = rc
                        wk[_ix(K_RS + j, b)] = rsn


@njit(cache=True, error_model="numpy", **INTERNAL)
def _redo_lane(wk, h, b):
    """Lane b's RK4 step again with libm cos/sin for its heading increments (the rare lanes
    with an increment beyond SMALL_ANGLE); a function of its own, compiled once, so that the
    block kernels hold one inlined copy of the RK4 lane, not two (cold start)."""
    out, _big = _rk4_block_lane(wk, h, b, True)
    _store9(wk, K_OUT, b, out)


#: True only in kernel_one's recompiled copy of :func:`advance_block` (blocks of one env)
_ONE_LANE = False


@njit(cache=True, error_model="numpy", **INTERNAL)
def advance_block(wk, dt, nsub, m, fast):
    """Advance the m lanes of a block by dt from their times (row K_T0) in nsub RK4
    substeps, the forces (rows K_F..) held constant; the state rows change in place.

    The caller fills the tones' sines and cosines at t0 (rows K_S.., K_C..) and cos/sin of
    both headings (rows K_C0, K_S0, K_CT, K_STT), from a cache or by :func:`_tone_values` and
    :func:`_heading_values`. The ten time-dependent tones are then rotated by half
    substeps (angle addition with small-angle cos/sin), so each stage time is exact to
    rounding. ``fast``: the headings of later substeps by :func:`fast_sincos` instead of
    libm. (Call it with runtime values, not literals, for ``m`` and ``fast``: numba compiles
    a specialisation per literal argument.)
    """
    h = dt / nsub
    hh = 0.5 * h
    _rotation_factors(wk, hh, m)
    for b in range(m):
        _forcing_lane(wk, K_S, K_F1, b)
    for sub in range(nsub):
        for c in range(7):
            for b in range(m):
                wk[_ix(K_F0 + c, b)] = wk[_ix(K_F1 + c, b)]
        for half in range(2):
            for j in range(10):
                for b in range(m):
                    sj = wk[_ix(K_S + j, b)]
                    cj = wk[_ix(K_C + j, b)]
                    wk[_ix(K_S + j, b)] = sj * wk[_ix(K_RC + j, b)] + cj * wk[_ix(K_RS + j, b)]
                    wk[_ix(K_C + j, b)] = cj * wk[_ix(K_RC + j, b)] - sj * wk[_ix(K_RS + j, b)]
            row = K_FM if half == 0 else K_F1
            for b in range(m):
                _forcing_lane(wk, K_S, row, b)
        if sub > 0:  # cos/sin of both headings at the substep's start
            _heading_values(wk, m, fast)
        if _ONE_LANE:
            # (kernel_one's copy, for a block of one env) the lane's step with libm beyond
            # SMALL_ANGLE at once, which is what the block path below gives (the same
            # polynomials up to SMALL_ANGLE); numba prunes the other path before compiling it
            _redo_lane(wk, h, 0)
        else:
            nbig = 0
            for b in range(m):
                out, big = _rk4_block_lane(wk, h, b, False)
                _store9(wk, K_OUT, b, out)
                wk[_ix(K_BIG, b)] = 1.0 if big else 0.0
                nbig += big
            if nbig:  # lanes with a large heading increment: redo them with libm cos/sin
                for b in range(m):
                    if wk[_ix(K_BIG, b)] != 0.0:
                        _redo_lane(wk, h, b)
        for c in range(9):
            for b in range(m):
                wk[_ix(K_ST + c, b)] = wk[_ix(K_OUT + c, b)]


@njit(cache=True, error_model="numpy")
def integrate(state, p, cfg, t0, forces, fast=False):
    """Advance every env one control step from time t0[i] under forces (N, 3) [N, N, N m].

    The bare physics kernel (follower and target, the tones only), without link,
    observation or reward: what the speed benchmark compares the env against. ``fast``:
    the sin/cos by :func:`fast_sincos` (the envs' ``sincos="simd"``) instead of libm.
    """
    n = state.shape[0]
    nsub = int(cfg[C_NSUB])
    dt = cfg[C_DT]
    wk = work_buffer(False)
    for a in range(0, n, BLOCK):
        m = min(BLOCK, n - a)
        gather_block(state, p, a, m, wk)
        for b in range(m):
            _store7(wk, K_G, b, _ZERO7)  # the tones only
            wk[_ix(K_F, b)] = forces[a + b, 0]
            wk[_ix(K_F + 1, b)] = forces[a + b, 1]
            wk[_ix(K_F + 2, b)] = forces[a + b, 2]
            wk[_ix(K_T0, b)] = t0[a + b]
        _tone_values(wk, m, fast)
        _heading_values(wk, m, fast)
        advance_block(wk, dt, nsub, m, fast)
        for b in range(m):
            for c in range(9):
                state[a + b, c] = wk[_ix(K_ST + c, b)]


@njit(cache=True, inline="always")
def _load_random_forcing(proc, i, wk, b):
    """Env i's step-constant random forcing (v_cx, v_cy, d_u, d_v, d_r, u_t, r_t deviations)
    into lane b of a block (rows K_G..)."""
    _store7(wk, K_G, b, (proc[i, R_CGX], proc[i, R_CGY], proc[i, R_DN], proc[i, R_DN + 1], proc[i, R_DN + 2],
                         proc[i, R_OUU], proc[i, R_OUR]))


@njit(cache=True, inline="always")
def _gm_z(x, a, std, z):
    """One exact step of a stationary Gauss-Markov (OU) process with per-step decay a, given the
    standard normal ``z``."""
    return a * x + math.sqrt(1.0 - a * a) * std * z


@njit(cache=True, **INTERNAL)
def _gm(x, a, std, rs, proc, i):
    """One exact step of a stationary Gauss-Markov (OU) process with per-step decay a."""
    return _gm_z(x, a, std, normal01(rs, proc, i))


@njit(cache=True, inline="always")
def update_processes(proc, rs, p, i):
    """Advance env i's random processes by one control step (draws only where a std > 0)."""
    if p[i, P_LD_MODES] > 0.0:
        leader_step(proc, rs, p, i, p[i, P_LD_DT])
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


# --- leader targets: hidden semi-Markov modes (docs/tiers.md, "Leader tiers") ----------------------
# A wandering leader cruises, turns left or right, (modes 2) loiters or sprints; a surveying one
# runs legs of similar length joined by U-turns, alternately left and right. Each mode's command
# (speed, turn rate) is followed through first-order lags, plus small OU wobbles; the results are
# the target's surge speed and turn rate held over the next step (rows R_OUU, R_OUR, which the
# target's velocity adds to its tones: zero on a leader tier). A mode ends when its progress
# (time; distance along a leg; heading turned in a U-turn) reaches a threshold drawn when it
# began: a Gamma(LD_K) duration about the mode's mean, a leg's length, or pi minus the heading
# the rate lag still adds after the command drops.

@njit(cache=True, **INTERNAL)
def _ld_uniform_pos(rs, i):
    """A uniform in (0, 1] (for logarithms)."""
    return 1.0 - uniform01(rs, i)


@njit(cache=True, **INTERNAL)
def _ld_gamma(rs, i, k):
    """A standard Gamma(k) deviate for a whole k (the sum of k standard exponentials)."""
    prod = 1.0
    for _ in range(int(k)):
        prod *= _ld_uniform_pos(rs, i)
    return -math.log(prod)


@njit(cache=True, inline="always")
def _ld_mean(p, i, mode):
    """Mean duration [s] of wander mode ``mode``."""
    if mode == LD_CRUISE:
        return p[i, P_LD_MC]
    if mode == LD_LOITER:
        return p[i, P_LD_ML]
    if mode == LD_SPRINT:
        return p[i, P_LD_MS]
    return p[i, P_LD_MT]


@njit(cache=True, **INTERNAL)
def _ld_threshold(rs, p, i, mode, shape):
    """The progress at which a new mode ``mode`` ends (``shape``: the Gamma shape of a wander
    duration, LD_K for a new mode, LD_K + 1 for the length-biased mode at an episode's start)."""
    if mode == LD_LEG:
        return p[i, P_LD_LEG] * (1.0 + LD_LEG_JITTER * (2.0 * uniform01(rs, i) - 1.0))
    if mode == LD_UTURN:
        return math.pi - p[i, P_LD_RS] * p[i, P_LD_TR]
    return _ld_gamma(rs, i, shape) * _ld_mean(p, i, mode) / LD_K


@njit(cache=True, inline="always")
def _ld_commands(proc, p, i):
    """The (speed [m/s], turn rate [rad/s]) command of env i's present mode."""
    mode = proc[i, R_LD_MODE]
    u = p[i, P_LD_UC]
    if mode == LD_LOITER:
        u = p[i, P_LD_UL]
    elif mode == LD_SPRINT:
        u = p[i, P_LD_US]
    r = 0.0
    if mode == LD_TURN_L:
        r = p[i, P_LD_RT]
    elif mode == LD_TURN_R:
        r = -p[i, P_LD_RT]
    elif mode == LD_UTURN:
        r = p[i, P_LD_RS] * proc[i, R_LD_SIDE]
    return u, r


@njit(cache=True, **INTERNAL)
def _ld_next_mode(rs, p, i, mode):
    """The mode after ``mode`` (the semi-Markov chain's jump; one uniform drawn in wander modes)."""
    if mode == LD_LEG:
        return LD_UTURN
    if mode == LD_UTURN:
        return LD_LEG
    if mode != LD_CRUISE:
        return LD_CRUISE
    u = uniform01(rs, i)
    if p[i, P_LD_MODES] >= 2.0:  # left 0.3, right 0.3, loiter 0.2, sprint 0.2
        if u < 0.3:
            return LD_TURN_L
        if u < 0.6:
            return LD_TURN_R
        return LD_LOITER if u < 0.8 else LD_SPRINT
    return LD_TURN_L if u < 0.5 else LD_TURN_R


@njit(cache=True, **INTERNAL)
def leader_init(proc, rs, p, i):
    """A stationary start of env i's leader (draws: survey or wander, the mode by its share of
    time, the length-biased first threshold and the progress made in it, the U-turn side, the
    wobbles); the lags start at the mode's command."""
    survey = uniform01(rs, i) < p[i, P_LD_SURVEY]
    if survey:
        t_leg = p[i, P_LD_LEG] / p[i, P_LD_UC]
        t_turn = math.pi / p[i, P_LD_RS]
        mode = LD_LEG if uniform01(rs, i) < t_leg / (t_leg + t_turn) else LD_UTURN
    else:
        # visits: cruise half of them, the rest split as the chain leaves cruise; weighted by mean duration
        speed = p[i, P_LD_MODES] >= 2.0
        w_turn = (0.15 if speed else 0.25) * p[i, P_LD_MT]
        w_l = (0.1 * p[i, P_LD_ML]) if speed else 0.0
        w_s = (0.1 * p[i, P_LD_MS]) if speed else 0.0
        w_c = 0.5 * p[i, P_LD_MC]
        u = uniform01(rs, i) * (w_c + 2.0 * w_turn + w_l + w_s)
        if u < w_c:
            mode = LD_CRUISE
        elif u < w_c + w_turn:
            mode = LD_TURN_L
        elif u < w_c + 2.0 * w_turn:
            mode = LD_TURN_R
        elif u < w_c + 2.0 * w_turn + w_l:
            mode = LD_LOITER
        else:
            mode = LD_SPRINT
    proc[i, R_LD_MODE] = mode
    thr = _ld_threshold(rs, p, i, mode, LD_K + 1.0)
    proc[i, R_LD_THR] = thr
    proc[i, R_LD_PROG] = uniform01(rs, i) * thr
    proc[i, R_LD_SIDE] = -1.0 if uniform01(rs, i) < 0.5 else 1.0
    ub, rb = _ld_commands(proc, p, i)
    proc[i, R_LD_UB] = ub
    proc[i, R_LD_RB] = rb
    proc[i, R_LD_WU] = p[i, P_LD_WU] * normal01(rs, proc, i)
    proc[i, R_LD_WR] = p[i, P_LD_WR] * normal01(rs, proc, i)
    proc[i, R_OUU] = max(ub + proc[i, R_LD_WU], 0.0)
    proc[i, R_OUR] = rb + proc[i, R_LD_WR]


@njit(cache=True, **INTERNAL)
def leader_step(proc, rs, p, i, dt):
    """Advance env i's leader by one control step: the progress made over the step just simulated
    (with the speed and turn rate it held), a mode switch if the threshold is reached, then the
    lags and wobbles, whose result is held over the next step."""
    mode = proc[i, R_LD_MODE]
    if mode == LD_LEG:
        proc[i, R_LD_PROG] += dt * proc[i, R_OUU]
    elif mode == LD_UTURN:
        proc[i, R_LD_PROG] += dt * abs(proc[i, R_OUR])
    else:
        proc[i, R_LD_PROG] += dt
    if proc[i, R_LD_PROG] >= proc[i, R_LD_THR]:
        new = _ld_next_mode(rs, p, i, mode)
        if mode == LD_UTURN:
            proc[i, R_LD_SIDE] = -proc[i, R_LD_SIDE]
        proc[i, R_LD_MODE] = new
        proc[i, R_LD_PROG] = 0.0
        proc[i, R_LD_THR] = _ld_threshold(rs, p, i, new, LD_K)
    uc, rc = _ld_commands(proc, p, i)
    proc[i, R_LD_UB] += (uc - proc[i, R_LD_UB]) * (1.0 - p[i, P_LD_AU])
    proc[i, R_LD_RB] += (rc - proc[i, R_LD_RB]) * (1.0 - p[i, P_LD_AR])
    a = p[i, P_LD_WA]
    proc[i, R_LD_WU] = _gm(proc[i, R_LD_WU], a, p[i, P_LD_WU], rs, proc, i)
    proc[i, R_LD_WR] = _gm(proc[i, R_LD_WR], a, p[i, P_LD_WR], rs, proc, i)
    proc[i, R_OUU] = max(proc[i, R_LD_UB] + proc[i, R_LD_WU], 0.0)
    proc[i, R_OUR] = proc[i, R_LD_RB] + proc[i, R_LD_WR]


@njit(cache=True)
def leader_trace(p, seeds, steps):
    """The leader process alone (no physics, no link), for the tests and the docs: env i's
    generator seeded with ``seeds[i]``, :func:`leader_init`, then ``steps`` control steps of
    :func:`update_processes`. Returns (steps + 1, N, 4): mode, progress, speed held [m/s], turn
    rate held [rad/s] after the start and after each step."""
    n = p.shape[0]
    proc = np.zeros((n, NR))
    rs = np.empty(n, dtype=np.uint64)
    out = np.empty((steps + 1, n, 4))
    for i in range(n):
        rs[i] = np.uint64(seeds[i])
        leader_init(proc, rs, p, i)
        out[0, i, 0] = proc[i, R_LD_MODE]
        out[0, i, 1] = proc[i, R_LD_PROG]
        out[0, i, 2] = proc[i, R_OUU]
        out[0, i, 3] = proc[i, R_OUR]
        for k in range(steps):
            update_processes(proc, rs, p, i)
            out[k + 1, i, 0] = proc[i, R_LD_MODE]
            out[k + 1, i, 1] = proc[i, R_LD_PROG]
            out[k + 1, i, 2] = proc[i, R_OUU]
            out[k + 1, i, 3] = proc[i, R_OUR]
    return out


# --- the random processes of a block of envs at once -------------------------------------------
# update_processes_block draws the same normals as update_processes, env by env, from the same
# uniforms in the same order (env i's Box-Muller pairs, its cached second value first), but the
# transcendental functions of a block's pairs run in SIMD loops: with ``fast`` the logarithm by
# :func:`fast_log` and the sine/cosine by :func:`fast_sincos` (each within 1 ULP of the exact value,
# so a draw differs from libm's in its last bits at most), without it libm's calls as in normal01
# (the same bits). Rows of the work buffer used meanwhile: the RK4 forcing rows (K_F0..), free
# between steps.
K_U1 = K_F0  # rows K_U1..K_U1 + 3: pair j's u1 in (0, 1], then sqrt(-2 log u1)
K_U2 = K_F0 + 4  # pair j's angle 2 pi u2
K_ZS, K_ZC = K_F0 + 8, K_F0 + 12  # sin and cos of pair j's angle
K_CD, K_CDS, K_CDC = K_F0 + 16, K_F0 + 17, K_F0 + 18  # the current's direction, its sin and cos
K_ENV = K_F0 + 19  # the lane's env index (set by the caller)
K_NN = K_F0 + 20  # the number of normals the lane's env draws per step
K_DP, K_DPS, K_DPC = K_F0, K_F0 + 1, K_F0 + 2  # after the processes: the observation's relative
#   heading (held packet's minus the follower's), its sin and cos
_NPAIR = 4  # at most seven normals per env and step: four pairs

# fdlibm's e_log.c (Sun Microsystems, 1993; freely distributable): x = 2^k (1 + f) with 1 + f in
# [sqrt(2)/2, sqrt(2)), log(1 + f) = f - f^2/2 + s (f^2/2 + R(s^2)), s = f / (2 + f), R minimax
_LN2_HI, _LN2_LO = 6.93147180369123816490e-01, 1.90821492927058770002e-10
_LG1, _LG2, _LG3 = 6.666666666666735130e-01, 3.999999999940941908e-01, 2.857142874366239149e-01
_LG4, _LG5, _LG6 = 2.222219843214978396e-01, 1.818357216161805012e-01, 1.531383769920937332e-01
_LG7 = 1.479819860511658591e-01


def _bitcast(name: str, frm, to, ll_to, doc: str):
    """An intrinsic that reinterprets the bits of a ``frm`` value as a ``to`` value (same width)."""
    def cast(typingctx, x):
        if x != frm:
            return None

        def codegen(context, builder, sig, args):
            return builder.bitcast(args[0], ll_to)

        return to(frm), codegen

    cast.__name__ = cast.__qualname__ = name
    cast.__doc__ = doc
    return intrinsic(cast)


_bits = _bitcast("_bits", types.float64, types.uint64, llir.IntType(64),
                 "The IEEE-754 bits of the float64 ``x`` as a uint64 (a bit cast).")
_from_bits = _bitcast("_from_bits", types.uint64, types.float64, llir.DoubleType(),
                      "The float64 whose IEEE-754 bits are the uint64 ``x`` (a bit cast).")
_U32, _U20 = np.uint64(32), np.uint64(20)
_U_MANT, _U_SQRT2, _U_CARRY = np.uint64(0x000FFFFF), np.uint64(0x95F64), np.uint64(0x100000)
_U_ONE, _U_LOW = np.uint64(0x3FF00000), np.uint64(0xFFFFFFFF)
_U_TWO52, _TWO52_BIAS = np.uint64(0x4330000000000000), 4503599627370496.0 + 1023.0  # 2^52 as bits; 2^52 + 1023
_U_NEAR_LO, _U_NEAR_HI = np.uint64(0x6147A), np.uint64(0x6B851)


@njit(cache=True, inline="always", error_model="numpy")
def fast_log(x):
    """log x within 1 ULP for positive normal x (fdlibm's method, branch-free: vectorises).
    Not for 0, subnormals, infinities or NaN (the callers pass uniforms in (0, 1]).

    Unsigned 64-bit integer operations only, and the exponent converted to a double by the
    2^52 trick: AVX2 has no 64-bit arithmetic shift or int64-to-double conversion, without
    which a loop of it would not vectorise."""
    ix = _bits(x)
    hx = ix >> _U32
    m = hx & _U_MANT  # the high 20 bits of the mantissa
    i = (m + _U_SQRT2) & _U_CARRY  # whether the mantissa is >= sqrt(2): then halve it
    xm = _from_bits(((m | (i ^ _U_ONE)) << _U32) | (ix & _U_LOW))
    e = (hx >> _U20) + (i >> _U20)  # the biased exponent (x > 0: no sign bit), + 1 where halved
    dk = _from_bits(_U_TWO52 | e) - _TWO52_BIAS  # e - 1023 exactly
    f = xm - 1.0
    s = f / (2.0 + f)
    z = s * s
    w = z * z
    t1 = w * (_LG2 + w * (_LG4 + w * _LG6))
    t2 = z * (_LG1 + w * (_LG3 + w * (_LG5 + w * _LG7)))
    r = t2 + t1
    hfsq = 0.5 * f * f
    near = (m >= _U_NEAR_LO) & (m <= _U_NEAR_HI)  # 1 + f in [1.38, 1.42]: the f^2/2 form
    a = dk * _LN2_HI - ((hfsq - (s * (hfsq + r) + dk * _LN2_LO)) - f)
    b = dk * _LN2_HI - ((s * (f - r) - dk * _LN2_LO) - f)
    return a if near else b


#: the processes in update_processes' order of draws: the column of their std (the current
#: direction's step for c = 3), of their per-step decay, and their row in proc
_PROC_STD = np.array([P_OUU_STD, P_OUR_STD, P_CS_STD, P_CD_STEP, P_DN, P_DN + 1, P_DN + 2], dtype=np.int64)
_PROC_A = np.array([P_OUU_A, P_OUR_A, P_CS_A, P_CD_STEP, P_DN_A, P_DN_A, P_DN_A], dtype=np.int64)
_PROC_ROW = np.array([R_OUU, R_OUR, R_CSX, R_CDIR, R_DN, R_DN + 1, R_DN + 2], dtype=np.int64)


@njit(cache=True, inline="always")
def _n_normals(p, i):
    """How many normals env i's processes draw per control step."""
    n = 0
    for c in range(7):
        n += p[i, _PROC_STD[c]] > 0.0
    return n


@njit(cache=True, inline="always")
def _normal_at(wk, b, j):
    """The j-th new normal of lane b this step: pair j // 2's cosine value, then its sine value."""
    q = j >> 1
    return wk[_ix(K_U1 + q, b)] * wk[_ix((K_ZS if j & 1 else K_ZC) + q, b)]


@njit(cache=True, inline="always", error_model="numpy")
def update_processes_block(proc, rs, p, m, wk, fast):
    """:func:`update_processes` for the envs of lanes 0..m-1 (env indices in row K_ENV; the same
    draws and updates per env; see the comment above K_U1): per env its uniforms, then the
    block's logarithms and sines/cosines in SIMD loops, then per env its updates. A leader
    target (P_LD_MODES > 0) advances first (:func:`leader_step`, its own draws)."""
    for b in range(m):
        i = int(wk[_ix(K_ENV, b)])
        if p[i, P_LD_MODES] > 0.0:
            leader_step(proc, rs, p, i, p[i, P_LD_DT])
    npair_max = 0
    for b in range(m):
        i = int(wk[_ix(K_ENV, b)])
        n = _n_normals(p, i)
        wk[_ix(K_NN, b)] = n
        has = int(proc[i, R_GAUSS_HAS] != 0.0)
        npair = max(0, n - has + 1) // 2
        npair_max = max(npair_max, npair)
        for j in range(_NPAIR):
            if j < npair:
                wk[_ix(K_U1 + j, b)] = 1.0 - uniform01(rs, i)
                wk[_ix(K_U2 + j, b)] = 2.0 * math.pi * uniform01(rs, i)
            else:
                wk[_ix(K_U1 + j, b)] = 1.0
                wk[_ix(K_U2 + j, b)] = 0.0
    if npair_max == 0:
        return
    for j in range(npair_max):
        if fast:
            for b in range(m):
                wk[_ix(K_U1 + j, b)] = math.sqrt(-2.0 * fast_log(wk[_ix(K_U1 + j, b)]))
        else:
            for b in range(m):
                wk[_ix(K_U1 + j, b)] = math.sqrt(-2.0 * math.log(wk[_ix(K_U1 + j, b)]))
        _sincos_rows(wk, K_U2 + j, K_ZS + j, K_ZC + j, m, fast)
    moved_any = False
    for b in range(m):
        i = int(wk[_ix(K_ENV, b)])
        n = int(wk[_ix(K_NN, b)])
        j = -1 if proc[i, R_GAUSS_HAS] != 0.0 and n > 0 else 0  # -1: the cached normal first
        for c in range(7):
            col = _PROC_STD[c]
            if p[i, col] > 0.0:
                z = proc[i, R_GAUSS] if j < 0 else _normal_at(wk, b, j)
                j += 1
                if c == 3:
                    proc[i, R_CDIR] += p[i, P_CD_STEP] * z
                else:
                    row = _PROC_ROW[c]
                    proc[i, row] = _gm_z(proc[i, row], p[i, _PROC_A[c]], p[i, col], z)
        if n > 0:
            if j > 0:  # new pairs were drawn: the last one's sine value, cached if unused
                proc[i, R_GAUSS] = _normal_at(wk, b, 2 * ((j - 1) >> 1) + 1)
            proc[i, R_GAUSS_HAS] = 1.0 if j & 1 else 0.0
        moved = p[i, P_CS_STD] > 0.0 or p[i, P_CD_STEP] > 0.0
        moved_any |= moved
        wk[_ix(K_CD, b)] = proc[i, R_CDIR]
    if not moved_any:
        return
    _sincos_rows(wk, K_CD, K_CDS, K_CDC, m, fast)
    for b in range(m):
        i = int(wk[_ix(K_ENV, b)])
        if p[i, P_CS_STD] > 0.0 or p[i, P_CD_STEP] > 0.0:
            sp = max(0.0, p[i, P_CS_MEAN] + proc[i, R_CSX])
            proc[i, R_CGX] = sp * wk[_ix(K_CDC, b)]
            proc[i, R_CGY] = sp * wk[_ix(K_CDS, b)]


@njit(cache=True, error_model="numpy")
def update_processes_all(proc, rs, p, steps, fast):
    """:func:`update_processes_block` over every env, block by block as the step runs it, for
    ``steps`` control steps (for the tests and the speed benchmark)."""
    _update_processes_steps(proc, rs, p, steps, fast, work_buffer(True))


@njit(cache=True, error_model="numpy", **INTERNAL)
def _update_processes_steps(proc, rs, p, steps, fast, wk):
    """:func:`update_processes_all` in the work buffer ``wk`` (without reference counting, as the step)."""
    n = proc.shape[0]
    for _ in range(steps):
        for a in range(0, n, BLOCK):
            m = min(BLOCK, n - a)
            for b in range(m):
                wk[_ix(K_ENV, b)] = a + b
            update_processes_block(proc, rs, p, m, wk, fast)


@njit(cache=True, **INTERNAL)
def _current_vector(proc, p, i):
    sp = max(0.0, p[i, P_CS_MEAN] + proc[i, R_CSX])
    proc[i, R_CGX] = sp * math.cos(proc[i, R_CDIR])
    proc[i, R_CGY] = sp * math.sin(proc[i, R_CDIR])


@njit(cache=True, inline="always")
def _heading_trig(proc, i, key, col, x):
    """(cos x, sin x), from env i's cache (columns ``key``, ``col``, ``col + 1`` of ``proc``) if it
    holds them for x, else libm (cached)."""
    if proc[i, key] != x or math.copysign(1.0, proc[i, key]) != math.copysign(1.0, x):  # (-0.0: sin differs)
        proc[i, key] = x
        proc[i, col] = math.cos(x)
        proc[i, col + 1] = math.sin(x)
    return proc[i, col], proc[i, col + 1]


@njit(cache=True, inline="always")
def refresh_trig(state, k, proc, p, cfg, i):
    """Make env i's cached libm values those of its present state and time (computed only
    where the keys differ): the ten tones at t = k dt and cos/sin of both headings."""
    if proc[i, R_TK] != k[i]:
        t = k[i] * cfg[C_DT]
        for j in range(10):
            oc = _TONE_OMEGA[j]
            w = p[i, oc] if oc >= 0 else (_W1 if oc == -1 else _W2)
            a = w * t + p[i, _TONE_PHASE[j]]
            proc[i, R_TS + j] = math.sin(a)
            proc[i, R_TC + j] = math.cos(a)
        proc[i, R_TK] = k[i]
    _heading_trig(proc, i, R_PSK, R_PSC, state[i, 2])
    _heading_trig(proc, i, R_PTK, R_PTC, state[i, 8])


@njit(cache=True, inline="always")
def refresh_trig_block(k, proc, cfg, a, m, wk, fast):
    """:func:`refresh_trig` for envs a..a+m-1 at once, after :func:`advance_block` (the new
    state in rows K_ST.., the tone frequencies and phases in rows K_OM.., K_PH..): the libm
    values (libm, or fast_sincos with ``fast``) in SIMD loops, then into each env's cache.
    With libm the values equal refresh_trig's (the same calls on the same arguments)."""
    dt = cfg[C_DT]
    for b in range(m):
        wk[_ix(K_T0, b)] = k[a + b] * dt
    _trig_values(wk, m, fast)  # (the rotation rows are free after advance_block)
    for b in range(m):
        i = a + b
        for j in range(10):
            proc[i, R_TS + j] = wk[_ix(K_S + j, b)]
            proc[i, R_TC + j] = wk[_ix(K_C + j, b)]
        proc[i, R_TK] = k[i]
        proc[i, R_PSK] = wk[_ix(K_ST + 2, b)]
        proc[i, R_PSC] = wk[_ix(K_C0, b)]
        proc[i, R_PSS] = wk[_ix(K_S0, b)]
        proc[i, R_PTK] = wk[_ix(K_ST + 8, b)]
        proc[i, R_PTC] = wk[_ix(K_CT, b)]
        proc[i, R_PTS] = wk[_ix(K_STT, b)]


@njit(cache=True, **INTERNAL)
def _init_processes(proc, rs, p, i, direction):
    """Stationary start of env i's processes; link and thrusters empty."""
    for c in range(NR):
        proc[i, c] = 0.0
    proc[i, R_TK] = math.nan
    proc[i, R_PSK] = math.nan
    proc[i, R_PTK] = math.nan
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
    if p[i, P_LD_MODES] > 0.0:
        leader_init(proc, rs, p, i)


@njit(cache=True, inline="always")
def _ring(s, q):
    """s mod q for 0 <= s < 2q: the ring index of the packet queue (a compare instead of an
    integer division, which costs tens of cycles and was several of them per env-step)."""
    return s - q if s >= q else s


@njit(cache=True, **INTERNAL)
def _send(state, proc, queue, rs, p, cfg, i, step):
    """Measure the target at control step ``step`` and put the packet in flight (or lose it)."""
    dt = cfg[C_DT]
    xt, yt, pt = state[i, 6], state[i, 7], state[i, 8]
    if proc[i, R_TK] == step:  # the tones at this step are cached
        ut, rt = _target_velocity_cached(p, proc, i)
    else:
        ut, rt = target_velocity_now(p, proc, i, step * dt)
    vt = 0.0
    # fix noise: position sigma grows with range (as a USBL's), heading, velocity, yaw rate
    s0 = p[i, P_NS0]
    sk = p[i, P_NSK]
    if s0 > 0.0 or sk > 0.0:
        sig = s0 + sk * math.sqrt((xt - state[i, 0]) ** 2 + (yt - state[i, 1]) ** 2)
        xt += sig * normal01(rs, proc, i)
        yt += sig * normal01(rs, proc, i)
    if p[i, P_OUT_P] > 0.0 and uniform01(rs, i) < p[i, P_OUT_P]:
        # a multipath outlier: a 2-D Student-t position error (OUTLIER_DOF dof, scale P_OUT_S) on top
        z1 = normal01(rs, proc, i)
        z2 = normal01(rs, proc, i)
        chi2 = 0.0
        for _ in range(int(OUTLIER_DOF)):
            z = normal01(rs, proc, i)
            chi2 += z * z
        sc = p[i, P_OUT_S] * math.sqrt(OUTLIER_DOF / max(chi2, 1e-300))
        xt += sc * z1
        yt += sc * z2
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
        head = _ring(head + 1, Q)
        n -= 1
    slot = _ring(head + n, Q)
    queue[i, slot, Q_MEAS] = step
    queue[i, slot, Q_ARR] = step + math.ceil(lat - 1e-6)
    queue[i, slot, Q_X] = xt
    queue[i, slot, Q_X + 1] = yt
    queue[i, slot, Q_X + 2] = pt
    queue[i, slot, Q_X + 3] = ut
    queue[i, slot, Q_X + 4] = vt
    queue[i, slot, Q_X + 5] = rt
    if pt == proc[i, R_PTK] and math.copysign(1.0, pt) == math.copysign(1.0, proc[i, R_PTK]):
        queue[i, slot, Q_C] = proc[i, R_PTC]  # unchanged by fix noise: cached
        queue[i, slot, Q_S] = proc[i, R_PTS]
    else:
        queue[i, slot, Q_C] = math.cos(pt)
        queue[i, slot, Q_S] = math.sin(pt)
    proc[i, R_QHEAD] = head
    proc[i, R_QLEN] = n + 1


@njit(cache=True, inline="always")
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
        if queue[i, _ring(head + m, Q), Q_ARR] <= step:
            newest = m
        elif fifo:
            break
    if newest < 0:
        return
    slot = _ring(head + newest, Q)
    for c in range(6):
        proc[i, R_HX + c] = queue[i, slot, Q_X + c]
    proc[i, R_HMEAS] = queue[i, slot, Q_MEAS]
    proc[i, R_HC] = queue[i, slot, Q_C]
    proc[i, R_HS] = queue[i, slot, Q_S]
    proc[i, R_HARR] = step
    proc[i, R_HAS] = 1.0
    proc[i, R_NEW] = 1.0
    # counters cover the packets sent from t = 0 on: sent = lost + arrived + discarded + overflow
    # + still in flight
    if queue[i, slot, Q_MEAS] >= 0:
        proc[i, R_ARRIVED] += 1.0
    for m in range(newest):  # older packets still in flight: they would arrive out of order
        if queue[i, _ring(head + m, Q), Q_MEAS] >= 0:
            proc[i, R_DISCARDED] += 1.0
    proc[i, R_QHEAD] = _ring(head + newest + 1, Q)
    proc[i, R_QLEN] = n - newest - 1


@njit(cache=True, inline="always")
def _lag(prev, cmd, alpha, lim):
    new = prev + alpha * (cmd - prev)
    if lim != INF:
        new = _clip(new, prev - lim, prev + lim)
    return new


@njit(cache=True, inline="always")
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


@njit(cache=True, error_model="numpy", **INTERNAL)
def _observe(state, k, proc, p, cfg, i, obs, truth):
    """Fill obs[i] (what the follower has) and truth[i] (evaluation only); return error.

    The tones and heading cos/sin come from env i's cache (:func:`refresh_trig`). For the reset
    (once per episode; the step computes the relative heading's sin/cos a block at a time and
    calls :func:`_observe_dp` itself), so it calls the compiled ``_refresh_trig_r`` and
    ``_observe_dp_r`` shared with the single env's step instead of inlining them (cold start)."""
    _refresh_trig_r(state, k, proc, p, cfg, i)
    dpsi = proc[i, R_HX + 2] - state[i, 2]
    if cfg[C_FAST] != 0.0 and abs(dpsi) <= FAST_TRIG_MAX:
        sdp, cdp = fast_sincos(dpsi)
    else:
        cdp = math.cos(dpsi)
        sdp = math.sin(dpsi)
    return _observe_dp_r(state, k, proc, p, cfg, i, obs, truth, cdp, sdp)


@njit(cache=True, inline="always", error_model="numpy")
def _observe_dp(state, k, proc, p, cfg, i, obs, truth, cdp, sdp):
    """:func:`_observe` given (cos, sin) of the held packet's heading minus the follower's,
    ``proc[i, R_HX + 2] - state[i, 2]`` (computed for a block at once by the step), with env i's
    cached values current."""
    dt = cfg[C_DT]
    pdx = cfg[C_PDX]
    pdy = cfg[C_PDY]
    x, y, ps = state[i, 0], state[i, 1], state[i, 2]
    c = proc[i, R_PSC]
    s = proc[i, R_PSS]
    cx = p[i, P_CX] + p[i, P_CX + 1] * proc[i, R_TS + 2]  # current_inertial at t = k dt
    cy = p[i, P_CY] + p[i, P_CY + 1] * proc[i, R_TS + 3]
    cx += proc[i, R_CGX]
    cy += proc[i, R_CGY]
    obs[i, 0] = state[i, 3]
    obs[i, 1] = state[i, 4]
    obs[i, 2] = state[i, 5]
    obs[i, 3] = c
    obs[i, 4] = s
    if proc[i, R_HAS] != 0.0:
        # the newest received packet (v0: the target tau ago, eq. (12))
        xd, yd = proc[i, R_HX], proc[i, R_HX + 1]
        cd = proc[i, R_HC]  # cos/sin of its heading, computed when the packet was sent
        sd = proc[i, R_HS]
        ex = xd - x
        ey = yd - y
        rx = xd + cd * pdx - sd * pdy - x  # delayed reference, eq. (21) without prediction
        ry = yd + sd * pdx + cd * pdy - y
        obs[i, 5] = c * ex + s * ey
        obs[i, 6] = -s * ex + c * ey
        obs[i, 7] = cdp
        obs[i, 8] = sdp
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
    ut, rt = _target_velocity_cached(p, proc, i)
    ct = proc[i, R_PTC]
    st = proc[i, R_PTS]
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


def _called(disp):
    """A second dispatcher of the jitted function ``disp`` that its callers call instead of
    inlining (no ``inline="always"``): for the reset, which runs once per episode, and the single
    env's step (kernel_one, one env per call: nothing to vectorise), so that the link, processes,
    thrusters, sin/cos caches and observation compile once as functions instead of as an
    inlined copy in each kernel (cold start); with the options :data:`INTERNAL`. Same code, same
    results."""
    opts = {k: v for k, v in disp.targetoptions.items() if k not in ("nopython", "inline")}
    return njit(cache=True, **{**opts, **INTERNAL})(disp.py_func)


def recompiled(f, name: str, subs: dict | None = None, **opts):
    """A new dispatcher compiled from the Python function ``f`` (the same code object) under the
    name ``name`` (so that its on-disk cache is its own), with the module globals ``subs``
    replaced, and numba's options ``opts`` (e.g. ``parallel=True``)."""
    fn = pytypes.FunctionType(f.__code__, {**f.__globals__, **(subs or {})}, name, f.__defaults__, f.__closure__)
    fn.__qualname__ = name
    fn.__doc__ = f.__doc__
    return njit(**opts)(fn)


_link_tick_r = _called(link_tick)
_update_processes_block_r = _called(update_processes_block)
_load_random_forcing_r = _called(_load_random_forcing)
_observe_dp_r = _called(_observe_dp)
_thrusters_r = _called(thrusters)
_refresh_trig_r = _called(refresh_trig)
_refresh_trig_block_r = _called(refresh_trig_block)


@njit(cache=True)
def reset_kernel(state, k, proc, queue, rs, p, cfg, idx, seeds, directions, obs, truth):
    """Start episodes for the envs in ``idx`` (their params rows must be set).

    ``seeds[n]`` seeds env idx[n]'s generator; ``directions[n]`` is the Gauss-Markov
    current's initial direction [rad]. The target starts at the origin heading along +x at
    t = -warm-up (v0: -tau) and is simulated up to t = 0 with the link running, so at t = 0
    the link is in its steady state: in v0 the follower receives genuine tau-old
    measurements from the first step (nothing is zero-filled). The follower starts at rest
    with the held packet's heading, ``init_offset`` metres behind the reference point of
    the held packet (of the present target if no packet has arrived yet). The warm-up computes its
    sin/cos and the processes' draws as the step does (``cfg[C_FAST]``: SIMD or libm), a block of
    envs at once.
    """
    reset_range(state, k, proc, queue, rs, p, cfg, idx, seeds, directions, obs, truth, work_buffer(True))


@njit(cache=True, **INTERNAL)
def reset_range(state, k, proc, queue, rs, p, cfg, idx, seeds, directions, obs, truth, wk):
    """:func:`reset_kernel` in the zeroed work buffer ``wk`` (:func:`work_buffer`): allocates nothing,
    so it is compiled without reference counting (as :func:`step_range`). The warm-up's forces
    stay 0 (the follower is placed afterwards)."""
    W = int(cfg[C_WARM])
    dt = cfg[C_DT]
    nsub = int(cfg[C_NSUB])
    fast = cfg[C_FAST] != 0.0
    for n0 in range(0, idx.shape[0], BLOCK):  # the warm-up of up to BLOCK envs at once
        m = min(BLOCK, idx.shape[0] - n0)
        # the pure arithmetic of the block (sin/cos, RK4: lane by lane, nothing leaves the buffer)
        # runs over mp lanes, whole SIMD vectors: the padding lanes compute on whatever the
        # buffer holds (zeros, or an earlier block's lanes: NaN at worst, no traps) and are
        # never read back; every lane's result is its own, so the envs' are unchanged
        # (tests/test_kernel_one.py). A reset of 2 v0 envs: 103 -> 62 us.
        mp = m if m == 1 else min(BLOCK, (m + PAD - 1) // PAD * PAD)
        for b in range(m):
            i = idx[n0 + b]
            rs[i] = np.uint64(seeds[n0 + b])
            for c in range(9):
                state[i, c] = 0.0
            _init_processes(proc, rs, p, i, directions[n0 + b])
            proc[i, R_NEXT] = -W
            proc[i, R_LAST_SEND] = -W
            _link_tick_r(state, proc, queue, rs, p, cfg, i, -W)
            _gather_lane(state, p, i, wk, b)
        for step in range(-W, 0):
            for b in range(m):
                _load_random_forcing_r(proc, idx[n0 + b], wk, b)
                wk[_ix(K_T0, b)] = step * dt
            _trig_values(wk, mp, fast)
            advance_block(wk, dt, nsub, mp, fast)
            for b in range(m):
                i = idx[n0 + b]
                for c in range(9):
                    state[i, c] = wk[_ix(K_ST + c, b)]
                wk[_ix(K_ENV, b)] = i
            _update_processes_block_r(proc, rs, p, m, wk, fast)
            for b in range(m):
                _link_tick_r(state, proc, queue, rs, p, cfg, idx[n0 + b], step + 1)
        for b in range(m):
            _place_follower(state, k, proc, p, cfg, idx[n0 + b], obs, truth)


@njit(cache=True, parallel=True)
def reset_kernel_parallel(state, k, proc, queue, rs, p, cfg, idx, seeds, directions, obs, truth, chunks):
    """:func:`reset_kernel` on numba's threads: ``chunks`` contiguous slices of ``idx`` (whole
    blocks of BLOCK envs) in a ``prange`` loop. Each env's reset is its own arithmetic and
    draws, so the results equal the serial kernel's bit for bit."""
    n = idx.shape[0]
    nblk = (n + BLOCK - 1) // BLOCK
    chunks = max(1, min(chunks, nblk))
    for c in prange(chunks):
        lo = min(n, (c * nblk // chunks) * BLOCK)
        hi = min(n, ((c + 1) * nblk // chunks) * BLOCK)
        if hi > lo:
            reset_kernel(state, k, proc, queue, rs, p, cfg, idx[lo:hi], seeds[lo:hi], directions[lo:hi], obs,
                         truth)


@njit(cache=True, **INTERNAL)
def _place_follower(state, k, proc, p, cfg, i, obs, truth):
    """After the warm-up: the follower at rest behind the held packet's reference point."""
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


def error_samples(err_hist, err_stage, i, n):
    """Env i's first n error samples (a copy): err_hist[i] up to the last multiple of 8,
    the rest from err_stage[i] (see step_range)."""
    n8 = n - n % 8
    return np.concatenate((err_hist[i, :n8], err_stage[i, :n - n8]))


@njit(cache=True, **INTERNAL)
def first_bad_action(action):
    """-1, or the env index of the first non-finite entry of the flat (3N,) action."""
    for j in range(action.shape[0]):
        if not math.isfinite(action[j]):
            return j // 3
    return -1


@njit(cache=True, error_model="numpy", **INTERNAL)
def step_range(state, k, proc, queue, rs, p, cfg, obs, truth, err_hist, err_stage, rew, term, action, lo, hi, wk):
    """One control step for envs lo..hi-1 (actions assumed finite; see :func:`step_kernel`), in
    the work buffer ``wk`` (:func:`work_buffer`; the caller's, so that this function allocates
    nothing and is compiled without reference counting: see :data:`INTERNAL`).

    Block by block: actions and thrusters per env, the RK4 step for the block's envs at
    once (:func:`advance_block`), the block's random processes (:func:`update_processes_block`),
    the new step's libm values for the block at once (:func:`refresh_trig_block`), then per env the link, the
    observation, the reward and termination. ``cfg[C_FAST]`` = 1 (``sincos="simd"``, the
    envs' default) computes the step's sin/cos by :func:`fast_sincos`, 0 by libm.
    """
    dt = cfg[C_DT]
    nsub = int(cfg[C_NSUB])
    maxd = cfg[C_MAXD]
    nsteps = int(cfg[C_NSTEPS])
    effort = cfg[C_EFFORT]
    fast = cfg[C_FAST] != 0.0
    for a in range(lo, hi, BLOCK):
        m = min(BLOCK, hi - a)
        gather_block(state, p, a, m, wk)
        for b in range(m):
            i = a + b
            a0 = min(1.0, max(-1.0, float(action[3 * i])))
            a1 = min(1.0, max(-1.0, float(action[3 * i + 1])))
            a2 = min(1.0, max(-1.0, float(action[3 * i + 2])))
            fu, fv, fr = thrusters(proc, p, cfg, i, a0 * cfg[C_FU], a1 * cfg[C_FV], a2 * cfg[C_FR])
            wk[_ix(K_F, b)] = fu
            wk[_ix(K_F + 1, b)] = fv
            wk[_ix(K_F + 2, b)] = fr
            _load_random_forcing(proc, i, wk, b)
            wk[_ix(K_T0, b)] = k[i] * dt
            refresh_trig(state, k, proc, p, cfg, i)  # (already current unless the state was changed)
            for j in range(10):
                wk[_ix(K_S + j, b)] = proc[i, R_TS + j]
                wk[_ix(K_C + j, b)] = proc[i, R_TC + j]
            wk[_ix(K_C0, b)] = proc[i, R_PSC]
            wk[_ix(K_S0, b)] = proc[i, R_PSS]
            wk[_ix(K_CT, b)] = proc[i, R_PTC]
            wk[_ix(K_STT, b)] = proc[i, R_PTS]
        advance_block(wk, dt, nsub, m, fast)
        for b in range(m):
            i = a + b
            for c in range(9):
                state[i, c] = wk[_ix(K_ST + c, b)]
            k[i] += 1
            wk[_ix(K_ENV, b)] = i
        update_processes_block(proc, rs, p, m, wk, fast)
        refresh_trig_block(k, proc, cfg, a, m, wk, fast)  # the new step's libm values, used from here on
        for b in range(m):
            link_tick(state, proc, queue, rs, p, cfg, a + b, k[a + b])
        for b in range(m):  # the observation's relative heading, the block's sin/cos at once
            wk[_ix(K_DP, b)] = proc[a + b, R_HX + 2] - state[a + b, 2]
        _sincos_rows(wk, K_DP, K_DPS, K_DPC, m, fast)
        for b in range(m):
            i = a + b
            a0 = min(1.0, max(-1.0, float(action[3 * i])))
            a1 = min(1.0, max(-1.0, float(action[3 * i + 1])))
            a2 = min(1.0, max(-1.0, float(action[3 * i + 2])))
            err = _observe_dp(state, k, proc, p, cfg, i, obs, truth, wk[_ix(K_DPC, b)], wk[_ix(K_DPS, b)])
            ks = k[i] - 1  # this sample's index, and its column in err_stage
            slot = ks & 7
            if ks < err_hist.shape[1]:
                err_stage[i, slot] = err
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
            if ks < err_hist.shape[1] and (slot == 7 or done or k[i] >= nsteps):
                for c in range(slot + 1):
                    err_hist[i, ks - slot + c] = err_stage[i, c]


@njit(cache=True)
def step_kernel(state, k, proc, queue, rs, p, cfg, obs, truth, err_hist, err_stage, rew, term, action):
    """One control step for every env of the batch.

    ``action`` is flat, length 3N, in [-1, 1] (clipped here) and scaled by the force
    limits. Returns -1, or the index of the first env whose action is not finite, in which
    case nothing at all was changed. Writes obs, truth, reward and termination flags, and
    the error sample k - 1 of env i into err_hist[i] (through err_stage: complete up to a
    multiple of 8 samples, and entirely once the episode has ended).
    """
    bad = first_bad_action(action)
    if bad >= 0:
        return bad
    step_range(state, k, proc, queue, rs, p, cfg, obs, truth, err_hist, err_stage, rew, term, action, 0, state.shape[0],
               work_buffer(False))
    return -1


@njit(cache=True, parallel=True)
def step_kernel_parallel(state, k, proc, queue, rs, p, cfg, obs, truth, err_hist, err_stage, rew, term, action, chunks):
    """:func:`step_kernel` on numba's threads: one parallel region per step, ``chunks``
    contiguous slices of the batch (multiples of BLOCK envs) in a ``prange`` loop.

    The same :func:`step_range` as the serial kernel, so the results are bit-identical
    (every env's arithmetic and random draws are its own). Compiled (and cached on disk) on
    first use only; importing the module starts no threads.
    """
    bad = first_bad_action(action)
    if bad >= 0:
        return bad
    n = state.shape[0]
    nblk = (n + BLOCK - 1) // BLOCK
    for c in prange(chunks):
        lo = min(n, (c * nblk // chunks) * BLOCK)
        hi = min(n, ((c + 1) * nblk // chunks) * BLOCK)
        if hi > lo:
            step_range(state, k, proc, queue, rs, p, cfg, obs, truth, err_hist, err_stage, rew, term, action, lo, hi,
                       work_buffer(False))
    return -1
