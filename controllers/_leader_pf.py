"""A *model-aware* estimator of the Leader tiers' target: a particle filter that knows the tier's
generator (auv_follow_env/dynamics.py, "leader targets": the modes, their Gamma(4) durations, the
survey's legs and U-turns, the lags, the wobbles, the outlier fixes) and the tier's published
ranges as the prior of each episode's parameters. In numba, for one episode's observations at a
time (offline: experiments/leader_estimators.py scores it; its error with many particles
estimates the Bayes floor of the tier from above).

Each particle carries the target's pose (odometry frame), the leader's hidden state (mode, side,
progress, threshold, lagged commands, wobbles) and its own draw of the episode's parameters (speeds,
rates, mean durations, leg length, survey or not). The filter is held at the newest fix's
measurement time: a new fix moves the particles to its time with the generator itself, weights
them by the fix's likelihood (Gaussian noise of the tier's fix sigmas; on position a mixture with
the outliers' Student-t), and resamples (systematic) when the effective sample size drops below
half; resampled particles' continuous parameters get a small Gaussian jitter (Liu and West's
shrinkage toward the mean, so the parameter cloud keeps its spread and mean). The present estimate
is a copy of the particles advanced to now with the generator (a sample of the predictive
distribution), one control step at a time between fixes; its weighted mean reference point is the
estimate.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import njit, prange

from auv_follow_env.dynamics import recompiled
from controllers._ou0 import fix_measurement, fix_timing, odometry_step

# particle columns
X, Y, PSI, MODE, SIDE, PROG, THR, UB, RB, WU, WR, U, R = range(13)
# the episode's parameters (per particle), in the prior's order
Q_SURVEY, Q_VC, Q_RT, Q_MC, Q_MT, Q_VL, Q_ML, Q_VS, Q_MS, Q_LEG, Q_RS = range(13, 24)
NPC = 24
NQ = 11
# prior rows (lo, hi) for Q_VC .. Q_RS, and scalars in the config vector
C_DT, C_MODES, C_SURVEY, C_AU, C_AR, C_TR, C_WU, C_WR, C_WA = range(9)
C_SPOS, C_SPM, C_SPSI, C_SVEL, C_SR, C_OUTP, C_OUTS = range(9, 16)
C_PDX, C_PDY = 16, 17
C_DRIFT = 18  # tempering of the position likelihood: variance added per second of the span [m^2/s]
C_TEMPER = 19  # tempering of the heading, speed and turn-rate likelihoods: their variances times this
NC = 20
CRUISE, TURN_L, TURN_R, LOITER, SPRINT, LEG, UTURN = range(7)
K_DUR = 4.0
LEG_JITTER = 0.05
LW_A = 0.98  #: Liu-West shrinkage (the jitter's variance is 1 - a^2 of the cloud's)
_GAMMA, _M1, _M2 = np.uint64(0x9E3779B97F4A7C15), np.uint64(0xBF58476D1CE4E5B9), np.uint64(0x94D049BB133111EB)
_S30, _S27, _S31, _S11 = np.uint64(30), np.uint64(27), np.uint64(31), np.uint64(11)


@njit(cache=True, inline="always")
def _rand(rs):
    """A uniform in [0, 1) from the env's own SplitMix64 generator rs (1,) uint64 (its draws do
    not depend on the other envs of a batch)."""
    z = rs[0] + _GAMMA
    rs[0] = z
    z = (z ^ (z >> _S30)) * _M1
    z = (z ^ (z >> _S27)) * _M2
    z = z ^ (z >> _S31)
    return float(z >> _S11) * (1.0 / 9007199254740992.0)


@njit(cache=True, inline="always")
def _randn(rs):
    """A standard normal (Box-Muller, one value per pair)."""
    u1 = 1.0 - _rand(rs)
    return math.sqrt(-2.0 * math.log(u1)) * math.cos(2.0 * math.pi * _rand(rs))


@njit(cache=True)
def _gamma4(shape, rs):
    prod = 1.0
    for _ in range(int(shape)):
        prod *= 1.0 - _rand(rs)
    return -math.log(prod)


@njit(cache=True)
def _mean_dur(p, mode):
    if mode == CRUISE:
        return p[Q_MC]
    if mode == LOITER:
        return p[Q_ML]
    if mode == SPRINT:
        return p[Q_MS]
    return p[Q_MT]


@njit(cache=True)
def _threshold(p, mode, shape, cfg, rs):
    if mode == LEG:
        return p[Q_LEG] * (1.0 + LEG_JITTER * (2.0 * _rand(rs) - 1.0))
    if mode == UTURN:
        return math.pi - p[Q_RS] * cfg[C_TR]
    return _gamma4(shape, rs) * _mean_dur(p, mode) / K_DUR


@njit(cache=True)
def _commands(p):
    mode = p[MODE]
    u = p[Q_VC]
    if mode == LOITER:
        u = p[Q_VL]
    elif mode == SPRINT:
        u = p[Q_VS]
    r = 0.0
    if mode == TURN_L:
        r = p[Q_RT]
    elif mode == TURN_R:
        r = -p[Q_RT]
    elif mode == UTURN:
        r = p[Q_RS] * p[SIDE]
    return u, r


@njit(cache=True)
def _next_mode(p, cfg, rs):
    mode = p[MODE]
    if mode == LEG:
        return UTURN
    if mode == UTURN:
        return LEG
    if mode != CRUISE:
        return CRUISE
    u = _rand(rs)
    if cfg[C_MODES] >= 2.0:
        if u < 0.3:
            return TURN_L
        if u < 0.6:
            return TURN_R
        return LOITER if u < 0.8 else SPRINT
    return TURN_L if u < 0.5 else TURN_R


@njit(cache=True)
def _init_particle(p, prior, cfg, z, rs):
    """A draw from the prior (parameters, stationary mode) at the pose of fix z."""
    for q in range(NQ - 1):
        lo, hi = prior[q, 0], prior[q, 1]
        p[Q_VC + q] = lo + (hi - lo) * _rand(rs)
    p[Q_SURVEY] = 1.0 if _rand(rs) < cfg[C_SURVEY] else 0.0
    if p[Q_SURVEY] > 0.5:
        t_leg = p[Q_LEG] / p[Q_VC]
        t_turn = math.pi / p[Q_RS]
        p[MODE] = LEG if _rand(rs) < t_leg / (t_leg + t_turn) else UTURN
    else:
        speed = cfg[C_MODES] >= 2.0
        w_turn = (0.15 if speed else 0.25) * p[Q_MT]
        w_l = 0.1 * p[Q_ML] if speed else 0.0
        w_s = 0.1 * p[Q_MS] if speed else 0.0
        w_c = 0.5 * p[Q_MC]
        u = _rand(rs) * (w_c + 2.0 * w_turn + w_l + w_s)
        if u < w_c:
            p[MODE] = CRUISE
        elif u < w_c + w_turn:
            p[MODE] = TURN_L
        elif u < w_c + 2.0 * w_turn:
            p[MODE] = TURN_R
        elif u < w_c + 2.0 * w_turn + w_l:
            p[MODE] = LOITER
        else:
            p[MODE] = SPRINT
    p[SIDE] = -1.0 if _rand(rs) < 0.5 else 1.0
    p[THR] = _threshold(p, p[MODE], K_DUR + 1.0, cfg, rs)
    p[PROG] = _rand(rs) * p[THR]
    ub, rb = _commands(p)
    p[UB] = ub
    p[RB] = rb
    p[WU] = cfg[C_WU] * _randn(rs)
    p[WR] = cfg[C_WR] * _randn(rs)
    p[U] = max(ub + p[WU], 0.0)
    p[R] = rb + p[WR]
    sp = cfg[C_SPOS]
    p[X] = z[0] + sp * _randn(rs)
    p[Y] = z[1] + sp * _randn(rs)
    p[PSI] = z[2] + cfg[C_SPSI] * _randn(rs)


@njit(cache=True)
def _step(p, cfg, rs):
    """One control step of the generator for a particle: the pose over the step with the held
    speed and turn rate (the exact arc), then the leader's step (as dynamics.leader_step)."""
    dt = cfg[C_DT]
    u, r = p[U], p[R]
    psi = p[PSI]
    if abs(r) > 1e-9:
        p[X] += u * (math.sin(psi + r * dt) - math.sin(psi)) / r
        p[Y] += u * (math.cos(psi) - math.cos(psi + r * dt)) / r
    else:
        p[X] += u * dt * math.cos(psi)
        p[Y] += u * dt * math.sin(psi)
    p[PSI] = psi + r * dt
    mode = p[MODE]
    if mode == LEG:
        p[PROG] += dt * u
    elif mode == UTURN:
        p[PROG] += dt * abs(r)
    else:
        p[PROG] += dt
    if p[PROG] >= p[THR]:
        new = _next_mode(p, cfg, rs)
        if mode == UTURN:
            p[SIDE] = -p[SIDE]
        p[MODE] = new
        p[PROG] = 0.0
        p[THR] = _threshold(p, new, K_DUR, cfg, rs)
    uc, rc = _commands(p)
    p[UB] += (uc - p[UB]) * (1.0 - cfg[C_AU])
    p[RB] += (rc - p[RB]) * (1.0 - cfg[C_AR])
    a = cfg[C_WA]
    b = math.sqrt(1.0 - a * a)
    p[WU] = a * p[WU] + b * cfg[C_WU] * _randn(rs)
    p[WR] = a * p[WR] + b * cfg[C_WR] * _randn(rs)
    p[U] = max(p[UB] + p[WU], 0.0)
    p[R] = p[RB] + p[WR]


@njit(cache=True)
def _loglik(p, z, sig_pos, cfg):
    """log-likelihood of fix z (x, y, psi, u, r) for a particle (position: a mixture of the fix
    noise and the outliers' Student-t with 3 dof)."""
    dx, dy = z[0] - p[X], z[1] - p[Y]
    d2 = (dx * dx + dy * dy) / (sig_pos * sig_pos)
    lg = -0.5 * d2 - 2.0 * math.log(sig_pos)
    eps = cfg[C_OUTP]
    if eps > 0.0:
        s2 = cfg[C_OUTS] * cfg[C_OUTS] + sig_pos * sig_pos
        # 2-D Student-t (nu = 3): density (1 + r^2 / (nu s^2))^(-(nu + 2) / 2) / (s^2) up to constants
        lt = -2.5 * math.log(1.0 + (dx * dx + dy * dy) / (3.0 * s2)) - math.log(s2)
        top = max(lg, lt)
        lg = top + math.log((1.0 - eps) * math.exp(lg - top) + eps * math.exp(lt - top))
    dpsi = math.atan2(math.sin(z[2] - p[PSI]), math.cos(z[2] - p[PSI]))
    # speed and turn rate: the fix noise plus the wobble's spread (tempered: the lags' state at a
    # particle's birth is a guess)
    su2 = cfg[C_SVEL] ** 2 + cfg[C_WU] ** 2
    sr2 = cfg[C_SR] ** 2 + cfg[C_WR] ** 2
    tmp = cfg[C_TEMPER]
    return (lg - 0.5 * dpsi * dpsi / (tmp * cfg[C_SPSI] ** 2) - 0.5 * (z[3] - p[U]) ** 2 / (tmp * su2)
            - 0.5 * (z[4] - p[R]) ** 2 / (tmp * sr2))


@njit(cache=True)
def _anchor(P, z, sig, cfg, rs):
    """Move each particle's observed states to a draw from the fix's noise about the fix (the fix
    pins them far more tightly than the prediction does), unless the fix is more likely an
    outlier for that particle (then its predicted position stays); the hidden states (mode,
    progress, threshold, parameters) are what the particles carry across fixes."""
    n = P.shape[0]
    eps = cfg[C_OUTP]
    for i in range(n):
        keep_pos = False
        if eps > 0.0:
            dx, dy = z[0] - P[i, X], z[1] - P[i, Y]
            s2 = sig * sig + cfg[C_DRIFT] * 5.0
            lg = math.log(1.0 - eps) - 0.5 * (dx * dx + dy * dy) / s2 - math.log(s2)
            so = cfg[C_OUTS] * cfg[C_OUTS] + s2
            lt = math.log(eps) - 2.5 * math.log(1.0 + (dx * dx + dy * dy) / (3.0 * so)) - math.log(so)
            keep_pos = _rand(rs) < 1.0 / (1.0 + math.exp(min(lg - lt, 700.0)))
        if not keep_pos:
            P[i, X] = z[0] + sig * _randn(rs)
            P[i, Y] = z[1] + sig * _randn(rs)
        P[i, PSI] = P[i, PSI] + math.atan2(math.sin(z[2] - P[i, PSI]), math.cos(z[2] - P[i, PSI])) \
            + cfg[C_SPSI] * _randn(rs)
        u = max(z[3] + cfg[C_SVEL] * _randn(rs), 0.0)
        r = z[4] + cfg[C_SR] * _randn(rs)
        P[i, UB] += u - P[i, U]
        P[i, RB] += r - P[i, R]
        P[i, U] = u
        P[i, R] = r


@njit(cache=True)
def _resample(P, logw, prior, rs):
    """Systematic resampling (weights reset to equal), then Liu-West jitter of the continuous
    parameters within the prior's bounds."""
    n = P.shape[0]
    top = logw.max()
    w = np.exp(logw - top)
    w /= w.sum()
    cum = np.cumsum(w)
    u0 = _rand(rs) / n
    idx = np.empty(n, dtype=np.int64)
    j = 0
    for i in range(n):
        u = u0 + i / n
        while j < n - 1 and cum[j] < u:
            j += 1
        idx[i] = j
    Q = P[idx].copy()
    for q in range(NQ - 1):
        c = Q_VC + q
        mean = Q[:, c].mean()
        sd = Q[:, c].std()
        lo, hi = prior[q, 0], prior[q, 1]
        for i in range(n):
            jit = math.sqrt(1.0 - LW_A ** 2) * sd * _randn(rs)
            v = LW_A * Q[i, c] + (1.0 - LW_A) * mean + jit
            Q[i, c] = min(max(v, lo), hi)
    P[:, :] = Q
    logw[:] = 0.0


# estimate columns of pf_step (beside the OU0 kernel's pose columns, reused by the estimator)
F_VALID, F_X, F_Y, F_PSI, F_U, F_R, F_RX, F_RY, F_AGE, F_ESS = range(10)
NF = 10


@njit(cache=True)
def _seed_from(obs_row):
    """An env's generator seed from its episode's first observation (bits of its fields): the
    filter's draws are then a function of the episode alone, whatever the batch."""
    h = np.uint64(0x243F6A8885A308D3)
    for j in range(obs_row.shape[0]):
        b = np.uint64(int(obs_row[j] * 1e9) & 0xFFFFFFFFFFFF)
        h = (h ^ b) * np.uint64(0x100000001B3)
    return h


def pf_step(obs, reset, cfg, prior, t_now, odom, vel, init, t_fix, P, Pn, logw, rs, out):
    """One control step of the particle filter for every env (all arrays updated in place).

    obs (N, 20) v1 observations; reset (N,) bool. State per env: t_now, t_fix (N,), odom, vel
    (N, 2), init (N,) bool, particles at the newest fix's time P (N, n, NPC) and advanced to now Pn,
    log-weights logw (N, n), the generator rs (N, 1) uint64 (seeded from the episode's first
    observation). out (N, NF): validity, the weighted mean pose (odometry frame; heading the
    weighted circular mean), speed and turn rate, the weighted mean reference point relative to
    the follower in its body frame, the newest fix's age and the effective sample share after the
    last fix's weighting. From :data:`THREADED_MIN_ENVS` envs on, the envs are split over numba's
    threads (each env draws from its own generator: the same result)."""
    threads = numba.get_num_threads() if obs.shape[0] >= THREADED_MIN_ENVS else 1
    step = _pf_threads if threads > 1 else _pf_serial
    step(threads, obs, reset, cfg, prior, t_now, odom, vel, init, t_fix, P, Pn, logw, rs, out)


def _pf_chunks(chunks, obs, reset, cfg, prior, t_now, odom, vel, init, t_fix, P, Pn, logw, rs, out):
    """:func:`pf_step` over ``chunks`` contiguous blocks of envs (a parallel loop in the threaded
    build)."""
    N = P.shape[0]
    for ch in prange(chunks):
        z = np.empty(5)
        for e in range(ch * N // chunks, (ch + 1) * N // chunks):
            _pf_env(e, obs, reset, cfg, prior, t_now, odom, vel, init, t_fix, P, Pn, logw, rs, out, z)


@njit(cache=True)
def _pf_env(e, obs, reset, cfg, prior, t_now, odom, vel, init, t_fix, P, Pn, logw, rs, out, z):
    """:func:`pf_step` for env e (z (5,): scratch)."""
    n = P.shape[1]
    dt = cfg[C_DT]
    r_ = rs[e]
    pf, c, s = odometry_step(obs, reset, e, odom, vel, t_now, init, dt)
    if reset[e]:
        r_[0] = _seed_from(obs[e])
    elif init[e]:
        for i in range(n):
            _step(Pn[e, i], cfg, r_)
    fresh, t_meas = fix_timing(obs, e, t_now[e], init[e], t_fix[e], True, 0.0)
    if fresh:
        dx, dy = fix_measurement(obs, e, odom, pf, c, s, z)
        sig = cfg[C_SPOS] + cfg[C_SPM] * math.sqrt(dx * dx + dy * dy)
        span = 0.0
        if not init[e]:
            for i in range(n):
                _init_particle(P[e, i], prior, cfg, z, r_)
                logw[e, i] = 0.0
            init[e] = True
        else:
            span = max(t_meas - t_fix[e], 0.0)
            m = int(round(span / dt))
            for i in range(n):
                for _ in range(m):
                    _step(P[e, i], cfg, r_)
        # the weight: the fix's likelihood, its position tempered by the prediction's spread over
        # the span (a particle's path is one sample of many that end near the fix)
        sig_w = math.sqrt(sig * sig + cfg[C_DRIFT] * span)
        for i in range(n):
            logw[e, i] += _loglik(P[e, i], z, sig_w, cfg)
        top = logw[e].max()
        w = np.exp(logw[e] - top)
        ess = w.sum() ** 2 / (w * w).sum()
        out[e, F_ESS] = ess / n
        if ess < 0.5 * n:
            _resample(P[e], logw[e], prior, r_)
        else:
            for i in range(n):
                logw[e, i] -= top
        _anchor(P[e], z, sig, cfg, r_)
        t_fix[e] = t_meas
        Pn[e, :, :] = P[e]
        m = int(round((t_now[e] - t_fix[e]) / dt))
        for i in range(n):
            for _ in range(m):
                _step(Pn[e, i], cfg, r_)
    if init[e]:
        top = logw[e].max()
        w = np.exp(logw[e] - top)
        w /= w.sum()
        mx = my = sx = sy = mu = mr = rx = ry = 0.0
        for i in range(n):
            q = Pn[e, i]
            cp, sp = math.cos(q[PSI]), math.sin(q[PSI])
            mx += w[i] * q[X]
            my += w[i] * q[Y]
            sx += w[i] * cp
            sy += w[i] * sp
            mu += w[i] * q[U]
            mr += w[i] * q[R]
            rx += w[i] * (q[X] + cp * cfg[C_PDX] - sp * cfg[C_PDY])
            ry += w[i] * (q[Y] + sp * cfg[C_PDX] + cp * cfg[C_PDY])
        out[e, F_VALID] = 1.0
        out[e, F_X], out[e, F_Y] = mx, my
        best = Pn[e, np.argmax(w), PSI]  # the heading on the branch of the likeliest particle
        out[e, F_PSI] = best + math.atan2(math.sin(math.atan2(sy, sx) - best), math.cos(math.atan2(sy, sx) - best))
        out[e, F_U], out[e, F_R] = mu, mr
        ex, ey = rx - odom[e, 0], ry - odom[e, 1]
        out[e, F_RX] = c * ex + s * ey
        out[e, F_RY] = -s * ex + c * ey
        out[e, F_AGE] = t_now[e] - t_fix[e]
    else:
        for j in range(NF):
            out[e, j] = 0.0



#: the step, serial and on numba's threads (each env draws from its own generator: the same bits)
_pf_serial = njit(cache=True)(_pf_chunks)
_pf_threads = recompiled(_pf_chunks, "_pf_chunks_par", cache=True, parallel=True)
#: batches from this many envs are filtered on numba's threads (an env's step is ~0.2 ms of work)
THREADED_MIN_ENVS = 2

def new_state(N: int, n: int) -> dict[str, np.ndarray]:
    """Fresh per-env arrays of :func:`pf_step` for N envs of n particles."""
    return {"t_now": np.zeros(N), "odom": np.zeros((N, 2)), "vel": np.zeros((N, 2)), "init": np.zeros(N, dtype=bool),
            "t_fix": np.zeros(N), "P": np.zeros((N, n, NPC)), "Pn": np.zeros((N, n, NPC)), "logw": np.zeros((N, n)),
            "rs": np.zeros((N, 1), dtype=np.uint64)}


def pf_episode(obs: np.ndarray, cfg: np.ndarray, prior: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """The filter over one episode's observations obs (T, 20): the estimated present reference
    point relative to the follower in its body frame (T, 2) (NaN before the first fix) and the
    effective sample share after the weighting of each fix (T,) (NaN on other steps)."""
    T = obs.shape[0]
    st = new_state(1, n)
    out = np.zeros((1, NF))
    est = np.full((T, 2), np.nan)
    ess = np.full(T, np.nan)
    obs = np.ascontiguousarray(obs, dtype=np.float64)
    for k in range(T):
        out[0, F_ESS] = np.nan
        pf_step(obs[k:k + 1], np.array([k == 0]), cfg, prior, st["t_now"], st["odom"], st["vel"], st["init"],
                st["t_fix"], st["P"], st["Pn"], st["logw"], st["rs"], out)
        if out[0, F_VALID] > 0.5:
            est[k] = out[0, F_RX], out[0, F_RY]
        ess[k] = out[0, F_ESS]
    return est, ess


def pf_config(spec, tier: str | None = None, fields: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(cfg, prior) of a Leader tier from its published table (or of ``fields``: name -> a value or
    a (lo, hi) range, for a custom task): the generator's fixed settings, the fix noise at the
    ranges' midpoints, and the uniform priors of the drawn parameters."""
    if tier is not None:
        from auv_follow_env.tiers import LEADER_TIERS

        t = LEADER_TIERS[tier]
        fields = {**t.fixed, **t.ranges}
    fields = dict(fields or {})

    def rng(name: str, default: float) -> tuple[float, float]:
        v = fields.get(name, default)
        if isinstance(v, (tuple, list)):
            return (float(v[0]), float(v[1]))
        return (float(v), float(v))

    def mid(name: str, default: float) -> float:
        lo, hi = rng(name, default)
        return 0.5 * (lo + hi)

    dt = spec.dt
    cfg = np.zeros(NC)
    cfg[C_DT] = dt
    cfg[C_MODES] = mid("leader_modes", 1.0)
    cfg[C_SURVEY] = mid("leader_survey_share", 0.0)
    cfg[C_AU] = math.exp(-dt / mid("leader_speed_lag_s", 2.0))
    cfg[C_AR] = math.exp(-dt / mid("leader_rate_lag_s", 1.0))
    cfg[C_TR] = mid("leader_rate_lag_s", 1.0)
    cfg[C_WU], cfg[C_WR] = mid("leader_wobble_speed", 0.02), mid("leader_wobble_rate", 0.01)
    cfg[C_WA] = math.exp(-dt / mid("leader_wobble_corr_s", 5.0))
    cfg[C_SPOS] = max(mid("fix_sigma_m", 0.0), 1e-3)
    cfg[C_SPM] = mid("fix_sigma_per_m", 0.0)
    cfg[C_SPSI] = max(mid("heading_sigma_rad", 0.0), 1e-3)
    cfg[C_SVEL] = max(mid("velocity_sigma_mps", 0.0), 1e-3)
    cfg[C_SR] = max(mid("yaw_rate_sigma_radps", 0.0), 1e-4)
    cfg[C_OUTP] = mid("outlier_share", 0.0)
    cfg[C_OUTS] = mid("outlier_scale_m", 1.0)
    cfg[C_PDX], cfg[C_PDY] = spec.p_d
    cfg[C_DRIFT] = 0.01
    cfg[C_TEMPER] = 2.0
    names = [("leader_cruise_speed", 0.5), ("leader_turn_rate", 0.15), ("leader_cruise_mean_s", 10.0),
             ("leader_turn_mean_s", 6.0), ("leader_loiter_speed", 0.1), ("leader_loiter_mean_s", 8.0),
             ("leader_sprint_speed", 0.9), ("leader_sprint_mean_s", 5.0), ("leader_leg_m", 10.0),
             ("leader_uturn_rate", 0.25)]
    prior = np.array([rng(nm, d) for nm, d in names], dtype=np.float64)
    return cfg, prior


@njit(cache=True)
def particle_trace(cfg, prior, n, steps, seed):
    """n particles from the prior at a fix at the origin, advanced ``steps`` control steps by the
    particles' generator (for the test that it is the kernel's): (steps + 1, n, 3) mode, speed and
    turn rate held."""
    rs = np.empty(1, dtype=np.uint64)
    rs[0] = np.uint64(seed)
    z = np.zeros(5)
    p = np.empty(NPC)
    out = np.empty((steps + 1, n, 3))
    for i in range(n):
        _init_particle(p, prior, cfg, z, rs)
        out[0, i, 0], out[0, i, 1], out[0, i, 2] = p[MODE], p[U], p[R]
        for k in range(steps):
            _step(p, cfg, rs)
            out[k + 1, i, 0], out[k + 1, i, 1], out[k + 1, i, 2] = p[MODE], p[U], p[R]
    return out
