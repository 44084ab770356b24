"""The information floor of the Leader tiers: a particle filter under the true generator.

On a Leader tier the target's speed and turn rate follow hidden semi-Markov modes
(docs/tiers.md, "Leader tiers"), so the posterior of the present reference point given the
packets received is not Gaussian and the v1 tiers' Kalman floor (:mod:`agents.benchmark.floors`)
does not apply. This module computes it by Monte Carlo, per episode, offline:

* **The model is the generator itself.** Each particle is one copy of the env's leader process:
  its row of the kernel's process state, advanced by the kernel's own
  :func:`auv_follow_env.dynamics.leader_step` with the episode's true parameters (the env's
  parameter row), and the target pose integrated exactly over each control step with the speed
  and turn rate held over it (the kernel integrates the same arc by Runge-Kutta; the two agree
  to 1e-12 m per step). Only the random draws are the particle's own.
* **The fixes are weighted where they were measured.** The filter keeps an *anchor* cloud: the
  posterior at the measurement step of the newest fix assimilated. When a packet arrives it
  advances the anchor to the packet's measurement step with the prior, weights each particle by
  the fix's likelihood (position: a mixture of the Gaussian fix noise and, with the tier's
  outlier share, the multipath outlier's 2-D Student-t; heading, speed and turn rate:
  Gaussian), resamples (systematic) and advances a copy to the present. The estimate at step k
  uses the packets that arrived by step k - 1 (the information behind the action that moved the
  follower to step k), as the v1 tiers' Kalman floor. A packet that arrives
  out of order (measured before the anchor) is assimilated by re-running the filter from the
  cloud stored after the newest fix measured before it (retrodiction by re-simulation).
* **The start is the generator's.** At the first packet the hidden leader state (mode,
  progress, threshold, lags, wobbles) is the kernel's :func:`auv_follow_env.dynamics.leader_init`
  at the episode's start run on with the generator to the packet's measurement (the warm-up);
  position and heading get a flat prior (the follower does not know where the target started):
  drawn from the fix's own likelihood.
* **Gibbs moves against degeneracy.** Resampling copies particles, and what no fix informs would
  freeze in the copies: a mode's threshold (copies would switch in lockstep), the episode's
  first mode's progress at the start, a first survey leg's U-turn side, and whether a leader
  that has gone straight since the start is a survey leg or a wander cruise. After every
  resampling each particle re-draws them from their exact conditional given its path: the
  threshold from the mode's duration law truncated to more than the progress made (an Erlang(4)
  duration or the leg's uniform jitter); the first mode's start from the generator's start law
  given no switch since (the equilibrium age of the Erlang renewal, or the leg's uniform start);
  the side uniformly; leg against cruise by their prior shares times their chance of no switch
  so far. These moves leave the posterior unchanged; without them a third of the Leader-Easy
  episodes lost the target for good (realised error 100-2000x the expected).
* **The point estimate for our metric.** The leaderboard scores the mean *norm* of the error:
  the estimate that minimises the posterior's expected norm is the spatial (geometric) median
  of the particles' reference points, found by Weiszfeld's iteration from the mean.
  ``expected`` is the posterior's own mean distance to that median (the floor), ``realised``
  the median's distance to the true reference point; the two agree on average when the model
  is right and the particles are enough.

The fix noise of each packet is the one it was drawn with (sigma = fix_sigma_m +
fix_sigma_per_m * the true range at its measurement, from the recording), so the floor is that
of the packets the recording follower received. (The v1 tiers' linear floor takes the range of
a follower on the reference point; :func:`particle_floor_episode` accepts either.)
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from numba import njit, prange

from auv_follow_env import dynamics as dyn

__all__ = ["DEFAULT_PARTICLES", "DEFAULT_CHILDREN", "PRIOR_SEED_BASE", "episode_params", "fix_ranges",
           "packet_sigmas", "particle_floor_episode", "tier_prior", "warmup_start"]
#: particles per episode by default (docs/benchmark.md, "Floors": the floor for N and 2N)
DEFAULT_PARTICLES = 8192
#: continuations of each particle weighted at a fix (:func:`particle_floor_episode`)
DEFAULT_CHILDREN = 4
#: stored clouds for out-of-order fixes (a packet measured before the newest K - 1 assimilated
#: fixes is dropped and counted: none on the published test seeds)
RETRO_DEPTH = 8
#: Weiszfeld iterations (from the particles' mean) at most, and their stop: a step below
#: this share of the mean distance (which is flat at the median: such a step changes it by far less)
WEISZFELD_ITERS, WEISZFELD_REL = 100, 1e-3
_LOG2PI = math.log(2.0 * math.pi)
_NU = dyn.OUTLIER_DOF


# --- one particle ------------------------------------------------------------------------

@njit(cache=True, inline="always")
def _held(p, proc, i):
    """The target's (surge speed, turn rate) held over the next step, clipped as the kernel does."""
    u = min(max(proc[i, dyn.R_OUU], p[i, dyn.P_ULO]), p[i, dyn.P_UHI])
    r = min(max(proc[i, dyn.R_OUR], -p[i, dyn.P_RMAX]), p[i, dyn.P_RMAX])
    return u, r


@njit(cache=True, parallel=True)
def _advance(proc, rs, p, pose, start, steps):
    """Advance every particle by ``steps`` control steps: the exact arc with the held speed and
    turn rate, then the kernel's leader step (mode switch, lags, wobbles). ``start[i]``: the
    first mode's progress at the leader's start (NaN once particle i has left that mode) and the
    distance [m] travelled since the start while in it."""
    n = proc.shape[0]
    for i in prange(n):
        dt = p[i, dyn.P_LD_DT]
        for _ in range(steps):
            u, r = _held(p, proc, i)
            ps0 = pose[i, 2]
            ps1 = ps0 + r * dt
            if abs(r) > 1e-9:
                pose[i, 0] += u * (math.sin(ps1) - math.sin(ps0)) / r
                pose[i, 1] -= u * (math.cos(ps1) - math.cos(ps0)) / r
            else:
                ph = ps0 + 0.5 * r * dt
                pose[i, 0] += u * dt * math.cos(ph)
                pose[i, 1] += u * dt * math.sin(ph)
            pose[i, 2] = ps1
            mode = proc[i, dyn.R_LD_MODE]
            start[i, 1] += u * dt
            dyn.leader_step(proc, rs, p, i, dt)
            if proc[i, dyn.R_LD_MODE] != mode:
                start[i, 0] = np.nan


@njit(cache=True, inline="always")
def _pos_loglik(ex, ey, sig, out_p, out_s):
    """Log-density of a 2-D position error: the Gaussian fix noise, or with probability
    ``out_p`` a multipath outlier (a 2-D Student-t, OUTLIER_DOF dof, whose scale absorbs the
    Gaussian part: sqrt(out_s^2 + sig^2); the exact law is their convolution)."""
    d2 = ex * ex + ey * ey
    lg = -0.5 * d2 / (sig * sig) - _LOG2PI - 2.0 * math.log(sig)
    if out_p <= 0.0:
        return lg
    s2 = out_s * out_s + sig * sig
    # 2-D Student-t: Gamma((nu+2)/2) / (Gamma(nu/2) nu pi s^2) (1 + d2 / (nu s^2))^(-(nu+2)/2) = 1/(2 pi s^2) (...)
    lt = -math.log(2.0 * math.pi * s2) - 0.5 * (_NU + 2.0) * math.log1p(d2 / (_NU * s2))
    m = max(lg, lt)
    return m + math.log((1.0 - out_p) * math.exp(lg - m) + out_p * math.exp(lt - m))


@njit(cache=True, inline="always")
def _fix_sigma(p, i, sig, rng_m):
    """The fix's position sigma for particle i: ``sig`` (known) or, with ``rng_m`` >= 0, the
    particle's own fix_sigma_m + fix_sigma_per_m x ``rng_m`` (the range the fix shows)."""
    return sig if rng_m < 0.0 else p[i, dyn.P_NS0] + p[i, dyn.P_NSK] * rng_m


@njit(cache=True, parallel=True)
def _loglik(proc, p, pose, z, sig, rng_m, logw, pose_too):
    """Log-likelihood of fix ``z`` = (x, y, psi, u, r) for every particle (position sigma
    :func:`_fix_sigma`; heading, speed and turn-rate sigmas from the parameter row); without
    ``pose_too`` of the speed and turn rate only."""
    n = proc.shape[0]
    for i in prange(n):
        u, r = _held(p, proc, i)
        sp = max(p[i, dyn.P_NPSI], 1e-6)
        su = max(p[i, dyn.P_NVEL], 1e-6)
        sr = max(p[i, dyn.P_NYAW], 1e-6)
        lw = -0.5 * (((z[3] - u) / su) ** 2 + ((z[4] - r) / sr) ** 2)
        if pose_too:
            dpsi = z[2] - pose[i, 2]
            dpsi -= 2.0 * math.pi * math.floor((dpsi + math.pi) / (2.0 * math.pi))
            s = _fix_sigma(p, i, sig, rng_m)
            lw += (_pos_loglik(z[0] - pose[i, 0], z[1] - pose[i, 1], s, p[i, dyn.P_OUT_P], p[i, dyn.P_OUT_S])
                   - 0.5 * (dpsi / sp) ** 2)
        logw[i] = lw


@njit(cache=True)
def _erlang_remaining(k, lam, elapsed, rs, proc, i):
    """A draw of an Erlang(k, rate lam) duration given that it exceeds ``elapsed``: the stages
    completed by then (j < k, probability proportional to (lam t)^j / j!), then k - j fresh
    exponential stages."""
    x = lam * elapsed
    w = 1.0
    tot = 1.0
    for j in range(1, k):
        w *= x / j
        tot += w
    u = dyn.uniform01(rs, i) * tot
    w = 1.0
    acc = 1.0
    j = 0
    while acc < u and j < k - 1:
        j += 1
        w *= x / j
        acc += w
    t = elapsed
    for _ in range(k - j):
        t -= math.log(1.0 - dyn.uniform01(rs, i)) / lam
    return t


@njit(cache=True)
def _erlang_sf_sum(k, x):
    """e^x sum_(j < k) S_(j + 1)(x), S_m the survival function of a standard Erlang(m) (rate 1):
    sum_(j < k) sum_(i <= j) x^i / i!."""
    w = 1.0
    cum = 1.0  # e^x S_(j + 1)(x)
    tot = 0.0
    for j in range(k):
        if j > 0:
            w *= x / j
            cum += w
        tot += cum
    return tot


@njit(cache=True)
def _erlang_age(k, lam, elapsed, rs, proc, i):
    """The age of a renewal process with Erlang(k, lam) durations, started in equilibrium, given
    that it has not renewed for ``elapsed``: the equilibrium age law S_k(a) / mean is the uniform
    mixture of Erlang(j + 1, lam), j < k; truncated to a >= elapsed, component j keeps the weight
    S_(j+1)(elapsed) and is drawn by :func:`_erlang_remaining`."""
    x = lam * elapsed
    u = dyn.uniform01(rs, i) * _erlang_sf_sum(k, x)
    w = 1.0
    cum = 1.0
    acc = cum
    j = 0
    while acc < u and j < k - 1:
        j += 1
        w *= x / j
        cum += w
        acc += cum
    return _erlang_remaining(j + 1, lam, elapsed, rs, proc, i)


@njit(cache=True)
def _erlang_sf_mean(k, x):
    """(1 / k) sum_(j < k) S_(j + 1)(x): the probability that an equilibrium Erlang(k) renewal
    process (rate 1, x in its time units) does not renew within x."""
    return math.exp(-x) * _erlang_sf_sum(k, x) / k


@njit(cache=True)
def _straight_start_odds(p, i, dist, t):
    """Prior times no-switch likelihood of a leader that has gone straight at cruise speed since
    it started: (survey leg, wander cruise), after ``dist`` metres and ``t`` seconds. The start's
    mode shares are :func:`auv_follow_env.dynamics.leader_init`'s."""
    t_leg = p[i, dyn.P_LD_LEG] / p[i, dyn.P_LD_UC]
    t_turn = math.pi / p[i, dyn.P_LD_RS]
    pi_leg = p[i, dyn.P_LD_SURVEY] * t_leg / (t_leg + t_turn)
    speed = p[i, dyn.P_LD_MODES] >= 2.0
    w_turn = (0.15 if speed else 0.25) * p[i, dyn.P_LD_MT]
    w_l = (0.1 * p[i, dyn.P_LD_ML]) if speed else 0.0
    w_s = (0.1 * p[i, dyn.P_LD_MS]) if speed else 0.0
    w_c = 0.5 * p[i, dyn.P_LD_MC]
    pi_cruise = (1.0 - p[i, dyn.P_LD_SURVEY]) * w_c / (w_c + 2.0 * w_turn + w_l + w_s)
    # a leg: thr ~ U[lo, hi], progress ~ U[0, thr]; no switch: E[(thr - dist)+ / thr]
    lo = p[i, dyn.P_LD_LEG] * (1.0 - dyn.LD_LEG_JITTER)
    hi = p[i, dyn.P_LD_LEG] * (1.0 + dyn.LD_LEG_JITTER)
    a = max(lo, dist)
    leg = ((hi - a) - dist * math.log(hi / a)) / (hi - lo) if a < hi else 0.0
    k = int(dyn.LD_K)
    cruise = _erlang_sf_mean(k, k / p[i, dyn.P_LD_MC] * t)
    return pi_leg * max(leg, 0.0), pi_cruise * cruise


@njit(cache=True, parallel=True)
def _rejuvenate(proc, rs, p, start, t_start):
    """Re-draw what resampling would freeze, from its exact conditional given each particle's
    path (a Gibbs move that leaves the posterior unchanged; ``t_start``: seconds since the
    leader started):

    * every particle's mode threshold given the progress made;
    * in the episode's first mode (``start[i, 0]`` not NaN) also the progress that mode had when
      the leader started, given the progress made since without a switch;
    * a first mode that has gone straight at cruise speed: whether it is a survey leg or a
      wander cruise (the path so far is the same; only the prior shares and the chance of no
      switch so far tell them apart), and a first leg's U-turn side (nothing observed yet
      depends on it)."""
    n = proc.shape[0]
    k = int(dyn.LD_K)
    for i in prange(n):
        mode = proc[i, dyn.R_LD_MODE]
        first = not math.isnan(start[i, 0])
        if first and (mode == dyn.LD_LEG or mode == dyn.LD_CRUISE):
            o_leg, o_cruise = _straight_start_odds(p, i, start[i, 1], t_start)
            if o_leg + o_cruise > 0.0:
                mode = dyn.LD_LEG if dyn.uniform01(rs, i) * (o_leg + o_cruise) < o_leg else dyn.LD_CRUISE
                proc[i, dyn.R_LD_MODE] = mode
            if mode == dyn.LD_LEG:
                proc[i, dyn.R_LD_SIDE] = -1.0 if dyn.uniform01(rs, i) < 0.5 else 1.0
        prog = proc[i, dyn.R_LD_PROG]
        if mode == dyn.LD_UTURN:
            if first:  # start: progress uniform on [0, thr]; no switch yet: on [0, thr - done)
                done = prog - start[i, 0]
                thr = proc[i, dyn.R_LD_THR]
                p0 = dyn.uniform01(rs, i) * max(thr - done, 0.0)
                start[i, 0] = p0
                proc[i, dyn.R_LD_PROG] = p0 + done
            continue
        if mode == dyn.LD_LEG:
            lo = p[i, dyn.P_LD_LEG] * (1.0 - dyn.LD_LEG_JITTER)
            hi = p[i, dyn.P_LD_LEG] * (1.0 + dyn.LD_LEG_JITTER)
            if first:
                # start: thr ~ U[lo, hi], progress ~ U[0, thr]; no switch after ``done`` metres:
                # density of thr proportional to (thr - done) / thr on [max(lo, done), hi]
                # (rejection from the uniform), the start's progress uniform on [0, thr - done)
                done = start[i, 1]
                a = max(lo, done)
                if a >= hi:
                    continue
                top = (hi - done) / hi
                thr = a
                for _ in range(1000):
                    thr = a + (hi - a) * dyn.uniform01(rs, i)
                    if dyn.uniform01(rs, i) * top <= (thr - done) / thr:
                        break
                p0 = dyn.uniform01(rs, i) * (thr - done)
                start[i, 0] = p0
                proc[i, dyn.R_LD_PROG] = p0 + done
                proc[i, dyn.R_LD_THR] = thr
            else:
                a = max(lo, prog)
                if a < hi:
                    proc[i, dyn.R_LD_THR] = a + (hi - a) * dyn.uniform01(rs, i)
            continue
        if mode == dyn.LD_CRUISE:
            mean = p[i, dyn.P_LD_MC]
        elif mode == dyn.LD_LOITER:
            mean = p[i, dyn.P_LD_ML]
        elif mode == dyn.LD_SPRINT:
            mean = p[i, dyn.P_LD_MS]
        else:
            mean = p[i, dyn.P_LD_MT]
        lam = k / mean
        if first:  # the start's age is the equilibrium age (length-biased Gamma(k + 1) start)
            age = _erlang_age(k, lam, t_start, rs, proc, i)
            start[i, 0] = age - t_start
            proc[i, dyn.R_LD_PROG] = age
            prog = age
        proc[i, dyn.R_LD_THR] = _erlang_remaining(k, lam, prog, rs, proc, i)


@njit(cache=True, parallel=True)
def _medians(pose, p, pdx, pdy, out):
    """The particles' reference points' spatial median and their mean distance to it, by
    Weiszfeld's iteration from their mean: out = (median x, median y, expected error). (A start
    from the previous step's median was slower: resampled copies cluster, and Weiszfeld crawls
    near a cluster.)"""
    n = pose.shape[0]
    rx = np.empty(n)
    ry = np.empty(n)
    for i in prange(n):
        c, s = math.cos(pose[i, 2]), math.sin(pose[i, 2])
        rx[i] = pose[i, 0] + c * pdx - s * pdy
        ry[i] = pose[i, 1] + s * pdx + c * pdy
    mx = 0.0  # (a serial sum: rx.mean() here became a parallel reduction, its bits set by the thread count)
    my = 0.0
    for i in range(n):
        mx += rx[i]
        my += ry[i]
    mx /= n
    my /= n
    for _ in range(WEISZFELD_ITERS):
        sw = 0.0
        sx = 0.0
        sy = 0.0
        tot = 0.0
        for i in range(n):
            d = math.sqrt((rx[i] - mx) ** 2 + (ry[i] - my) ** 2)
            tot += d
            if d > 1e-12:
                w = 1.0 / d
                sw += w
                sx += w * rx[i]
                sy += w * ry[i]
        if sw == 0.0:
            break
        nx, ny = sx / sw, sy / sw
        moved = math.sqrt((nx - mx) ** 2 + (ny - my) ** 2)
        mx, my = nx, ny
        if moved < WEISZFELD_REL * tot / n:
            break
    tot = 0.0
    for i in range(n):
        tot += math.sqrt((rx[i] - mx) ** 2 + (ry[i] - my) ** 2)
    out[0], out[1], out[2] = mx, my, tot / n


@njit(cache=True)
def _systematic_n(logw, u0, n):
    """Systematic resampling of n particles from len(logw) weighted ones: their ancestors, and
    the effective sample size of the weights."""
    m = logw.max()
    w = np.exp(logw - m)
    tot = w.sum()
    ess = tot * tot / (w * w).sum()
    idx = np.empty(n, dtype=np.int64)
    c = w[0] / tot
    j = 0
    last = logw.shape[0] - 1
    for k in range(n):
        t = (u0 + k) / n
        while t > c and j < last:
            j += 1
            c += w[j] / tot
        idx[k] = j
    return idx, ess


@njit(cache=True, parallel=True)
def _init_cloud(proc, rs, p, pose, start, z, sig, rng_m, seed, burn):
    """Particles at the first fix: the leader's hidden state as the generator has it there (the
    kernel's :func:`auv_follow_env.dynamics.leader_init` at the episode's start, then ``burn``
    leader steps: the warm-up before the fix) and the pose drawn from the fix's own likelihood (a
    flat prior on position and heading: the follower does not know where the target started;
    the Gaussian noise or, with the outlier share, the Student-t outlier)."""
    n = proc.shape[0]
    for i in prange(n):
        rs[i] = np.uint64(seed) + np.uint64(i) * np.uint64(0x9E3779B97F4A7C15)
        dyn.next_u64(rs, i)
        for c in range(proc.shape[1]):
            proc[i, c] = 0.0
        dyn.leader_init(proc, rs, p, i)
        start[i, 0] = proc[i, dyn.R_LD_PROG]
        start[i, 1] = 0.0
        for _ in range(burn):
            mode = proc[i, dyn.R_LD_MODE]
            u, _r = _held(p, proc, i)
            start[i, 1] += u * p[i, dyn.P_LD_DT]
            dyn.leader_step(proc, rs, p, i, p[i, dyn.P_LD_DT])
            if proc[i, dyn.R_LD_MODE] != mode:
                start[i, 0] = np.nan
        s = _fix_sigma(p, i, sig, rng_m)
        sg = s
        if p[i, dyn.P_OUT_P] > 0.0 and dyn.uniform01(rs, i) < p[i, dyn.P_OUT_P]:
            chi2 = 0.0
            for _ in range(int(_NU)):
                g = dyn.normal01(rs, proc, i)
                chi2 += g * g
            s = math.sqrt(p[i, dyn.P_OUT_S] ** 2 + sg * sg) * math.sqrt(_NU / max(chi2, 1e-300))
        pose[i, 0] = z[0] + s * dyn.normal01(rs, proc, i)
        pose[i, 1] = z[1] + s * dyn.normal01(rs, proc, i)
        pose[i, 2] = z[2] + max(p[i, dyn.P_NPSI], 1e-6) * dyn.normal01(rs, proc, i)


class _Cloud:
    """The particles' state: kernel process rows, RNG states, target poses, per particle the
    first mode's progress at the leader's start (NaN once it has left that mode) and the distance
    travelled since the start while in it, and the kernel parameter rows (one per particle: the
    episode's own row for the oracle-parameter floor, a prior draw each for the tier-prior floor;
    static, resampled with the particle)."""

    __slots__ = ("proc", "rs", "pose", "start", "p")

    def __init__(self, proc: np.ndarray, rs: np.ndarray, pose: np.ndarray, start: np.ndarray,
                 p: np.ndarray) -> None:
        self.proc, self.rs, self.pose, self.start, self.p = proc, rs, pose, start, p

    def copy(self) -> _Cloud:
        return _Cloud(self.proc.copy(), self.rs.copy(), self.pose.copy(), self.start.copy(), self.p)

    def take(self, idx: np.ndarray) -> _Cloud:
        return _Cloud(self.proc[idx], self.rs[idx], self.pose[idx], self.start[idx], self.p[idx])


#: the parameter columns a tier-prior particle may move in (Liu and West's kernel): the leader's
#: speeds, turn rates, mode durations and leg length, the fix noise level and the outlier share
PRIOR_MOVE_COLUMNS = (*range(dyn.P_LD_UC, dyn.P_LD_RS + 1), dyn.P_NS0, dyn.P_OUT_P)


def _liu_west(p: np.ndarray, cols: np.ndarray, lo: np.ndarray, hi: np.ndarray, a: float,
              rng: np.random.Generator) -> np.ndarray:
    """Liu and West's kernel move of the static parameters after resampling (equal weights):
    each row shrinks toward the cloud's mean by ``a`` and gets Gaussian noise of variance
    (1 - a^2) x the cloud's variance (mean and variance of the cloud kept), clipped to the prior's
    range. It keeps the rows diverse where resampling would leave copies of a few (an
    approximation of the static-parameter posterior; a = 1: no move)."""
    x = p[:, cols]
    m, v = x.mean(axis=0), x.var(axis=0)
    new = a * x + (1.0 - a) * m + np.sqrt((1.0 - a * a) * v) * rng.standard_normal(x.shape)
    out = p.copy()
    out[:, cols] = np.clip(new, lo, hi)
    return out


def _reseed(rs: np.ndarray, rng: np.random.Generator) -> None:
    """Fresh RNG streams for the particles after resampling (copies must not draw alike)."""
    rs[:] = rng.integers(1, 2 ** 63 - 1, size=len(rs), dtype=np.int64).astype(np.uint64)


def particle_floor_episode(params: np.ndarray, meas: np.ndarray, arr: np.ndarray, z: np.ndarray, sig: np.ndarray,
                           ref: np.ndarray, p_d: Sequence[float], L: int, init_step: int, *,
                           particles: int = DEFAULT_PARTICLES, children: int = DEFAULT_CHILDREN,
                           seed: int = 0, fix_range: np.ndarray | None = None,
                           shrink: float = 1.0) -> dict[str, np.ndarray]:
    """The particle floor of one Leader episode.

    Args:
        params: the episode's kernel parameter row (NP,), as the env drew it (the
            oracle-parameter floor), or (K, NP) rows drawn from the tier's own parameter law (the
            tier-prior floor, :func:`tier_prior`): each particle then carries a row of its own,
            drawn at the first fix (without replacement while K allows) and kept for the
            episode (the parameters are static; resampling weights them by every fix's
            likelihood, so the cloud's rows are draws of their posterior).
        meas, arr: (M,) measurement and arrival steps of the packets received
            (:func:`agents.benchmark.floors.extract_packets`).
        z: (M, 5) the received fixes in the world frame: x, y, psi, u, r.
        sig: (M,) each fix's position-noise sigma [m] (unused with ``fix_range``).
        ref: (L + 1, 2) the true reference point at steps 0..L (for the realised error).
        p_d: the desired offset (d, l) in the target's body frame [m].
        L: the last step.
        init_step: the step at which the env started the leader (minus its warm-up steps): the
            hidden state's prior at the first fix is the generator's start run on to it.
        particles: N, the particles kept between fixes.
        children: how many independent continuations of each particle are weighted at a fix (the
            filter weights N x children candidates and resamples N: diversity where the fix is
            sharp, at the cost of the propagation between fixes).
        seed: the filter's own random seed.
        fix_range: (M,) with per-particle parameters: the range [m] each fix shows (its position
            minus the follower's own at its measurement); each particle's fix sigma is then its
            own fix_sigma_m + fix_sigma_per_m x this range (a follower does not know the
            episode's noise level). None: ``sig``.
        shrink: with per-particle parameters, Liu and West's shrinkage a in (0, 1] of the move
            that re-diversifies :data:`PRIOR_MOVE_COLUMNS` after each resampling (1: none).

    Returns:
        per step 0..L: ``median`` (L + 1, 2), ``expected`` and ``realised`` (L + 1,) [m] (the
        estimate at step k from the packets that arrived by step k - 1; NaN until one has),
        ``ess`` (M,) the effective sample size at each fix's weighting (before resampling),
        ``dropped`` the out-of-order packets older than the stored clouds.
    """
    if not isinstance(particles, (int, np.integer)) or isinstance(particles, bool) or particles < 2:
        raise ValueError(f"particles={particles!r} is invalid: must be an integer >= 2")
    if not isinstance(children, (int, np.integer)) or isinstance(children, bool) or children < 1:
        raise ValueError(f"children={children!r} is invalid: must be an integer >= 1")
    n = int(particles)
    children = int(children)
    rows = np.asarray(params, dtype=np.float64)
    if rows.ndim not in (1, 2) or rows.shape[-1] != dyn.NP or rows.size == 0:
        raise ValueError(f"params has shape {rows.shape}: must be (NP,) = ({dyn.NP},) or (K, {dyn.NP})")
    if rows.ndim == 2 and fix_range is None:
        raise ValueError("params holds prior draws (K, NP) but fix_range is None: with per-particle parameters "
                         "each particle's fix sigma needs the range each fix shows")
    rng = np.random.default_rng(seed)
    if rows.ndim == 2:
        k_rows = rows.shape[0]
        pick = rng.permutation(k_rows)[:n * children] if k_rows >= n * children else rng.integers(
            k_rows, size=n * children)
        p_init = np.ascontiguousarray(rows[pick])
        cols = np.array([c for c in PRIOR_MOVE_COLUMNS if rows[:, c].max() > rows[:, c].min()], dtype=np.int64)
        lo, hi = rows[:, cols].min(axis=0), rows[:, cols].max(axis=0)
        rng_m = np.asarray(fix_range, dtype=np.float64)
        if rng_m.shape != (len(meas),):
            raise ValueError(f"fix_range has shape {rng_m.shape}: must be ({len(meas)},), one per packet")
    else:
        p_init = np.ascontiguousarray(np.broadcast_to(rows, (n * children, dyn.NP)))
        rng_m = np.full(len(meas), -1.0)
        cols = np.zeros(0, dtype=np.int64)
    if not isinstance(shrink, (int, float)) or isinstance(shrink, bool) or not 0.0 < float(shrink) <= 1.0:
        raise ValueError(f"shrink={shrink!r} is invalid: must be a number in (0, 1] (1: no move)")
    move = rows.ndim == 2 and float(shrink) < 1.0 and len(cols) > 0
    pdx, pdy = float(p_d[0]), float(p_d[1])
    dt = float(p_init[0, dyn.P_LD_DT])
    median = np.full((L + 1, 2), np.nan)
    expected = np.full(L + 1, np.nan)
    ess = np.full(len(meas), np.nan)
    order = np.argsort(arr, kind="stable")
    history: list[tuple[int, int, _Cloud]] = []  # (meas step, packet index, posterior cloud at it)
    pred: _Cloud | None = None
    dropped = 0
    out = np.full(3, np.nan)
    ptr = 0

    def assimilate(cloud: _Cloud, at: int, j: int) -> _Cloud:
        """Advance ``children`` copies of ``cloud`` from step ``at`` to packet j's measurement
        (each with its own draws), weight them, resample N."""
        cloud = cloud.take(np.tile(np.arange(n), children))
        _reseed(cloud.rs, rng)
        _advance(cloud.proc, cloud.rs, cloud.p, cloud.pose, cloud.start, int(meas[j] - at))
        logw = np.empty(n * children)
        _loglik(cloud.proc, cloud.p, cloud.pose, np.ascontiguousarray(z[j]), float(sig[j]), float(rng_m[j]), logw,
                True)
        idx, e = _systematic_n(logw, float(rng.random()), n)
        ess[j] = e
        new = cloud.take(idx)
        if move:
            new.p = _liu_west(new.p, cols, lo, hi, shrink, rng)
        _reseed(new.rs, rng)
        _rejuvenate(new.proc, new.rs, new.p, new.start, (int(meas[j]) - init_step) * dt)
        return new

    k_start = int(min(0, arr.min())) if len(arr) else 0
    for k in range(k_start, L + 1):
        # the estimate at step k uses the packets that arrived by step k - 1 (the information behind
        # the action that moved the follower to step k), as the v1 tiers' Kalman floor
        if pred is not None:
            _advance(pred.proc, pred.rs, pred.p, pred.pose, pred.start, 1)
            if k >= 0:
                _medians(pred.pose, pred.p, pdx, pdy, out)
                median[k] = out[0], out[1]
                expected[k] = out[2]
        changed = False
        while ptr < len(order) and arr[order[ptr]] <= k:
            j = int(order[ptr])
            ptr += 1
            m = int(meas[j])
            if not history:  # the first packet: the flat-prior start
                nc = n * children
                c = _Cloud(np.zeros((nc, dyn.NR)), np.zeros(nc, dtype=np.uint64), np.zeros((nc, 3)),
                           np.full((nc, 2), np.nan), p_init)
                _init_cloud(c.proc, c.rs, c.p, c.pose, c.start, np.ascontiguousarray(z[j]), float(sig[j]),
                            float(rng_m[j]), int(rng.integers(1, 2 ** 62)), max(0, m - init_step))
                logw = np.empty(nc)
                # the pose was drawn from its likelihood (the proposal): weight by speed and turn rate only
                # (a flat prior: the position likelihood integrates to 1 whatever the particle's sigma)
                _loglik(c.proc, c.p, c.pose, np.ascontiguousarray(z[j]), float(sig[j]), float(rng_m[j]), logw,
                        False)
                idx, ess[j] = _systematic_n(logw, float(rng.random()), n)
                c = c.take(idx)
                if move:
                    c.p = _liu_west(c.p, cols, lo, hi, shrink, rng)
                _reseed(c.rs, rng)
                _rejuvenate(c.proc, c.rs, c.p, c.start, (m - init_step) * dt)
                history.append((m, j, c))
                changed = True
                continue
            later = [h for h in history if h[0] > m]
            base = [h for h in history if h[0] < m]
            if not base:
                dropped += 1
                continue
            b = base[-1]
            cloud = assimilate(b[2].copy(), b[0], j)
            rebuilt = base + [(m, j, cloud)]
            for hm, hj, _ in later:  # retrodiction: re-run the later fixes on the new posterior
                cloud = assimilate(cloud.copy(), rebuilt[-1][0], hj)
                rebuilt.append((hm, hj, cloud))
            history = rebuilt[-RETRO_DEPTH:]
            changed = True
        if changed:  # the newest posterior, predicted to step k
            am = history[-1][0]
            pred = history[-1][2].copy()
            if k > am:
                _advance(pred.proc, pred.rs, pred.p, pred.pose, pred.start, k - am)
    realised = np.hypot(median[:, 0] - ref[:L + 1, 0], median[:, 1] - ref[:L + 1, 1])
    return {"median": median, "expected": expected, "realised": realised, "ess": ess, "dropped": dropped}


# --- per tier ----------------------------------------------------------------------------

def episode_params(env_id: str, seeds: Iterable[int], **overrides: Any) -> np.ndarray:
    """The kernel parameter rows (S, NP) the env draws for ``seeds`` (one single env, reset per seed)."""
    env = gym.make(env_id, **overrides)
    rows = []
    for s in seeds:
        env.reset(seed=int(s))
        rows.append(env.unwrapped._sim.params[0].copy())
    env.close()
    return np.array(rows)


#: the seeds of the tier-prior floor's parameter draws (:func:`tier_prior`): above every published
#: test seed and every training seed, so the draws share no stream with an episode that is scored
PRIOR_SEED_BASE = 500_000_000


def tier_prior(env_id: str, draws: int, **overrides: Any) -> np.ndarray:
    """``draws`` kernel parameter rows (draws, NP) from the tier's own parameter law: the env
    reset at seeds PRIOR_SEED_BASE, PRIOR_SEED_BASE + 1, ... (what a follower who knows the tier,
    its generator and its published ranges, but not the episode's draws, takes as its prior)."""
    if not isinstance(draws, (int, np.integer)) or isinstance(draws, bool) or draws < 1:
        raise ValueError(f"draws={draws!r} is invalid: must be an integer >= 1")
    return episode_params(env_id, range(PRIOR_SEED_BASE, PRIOR_SEED_BASE + int(draws)), **overrides)


def fix_ranges(recording: dict[str, Any], j: int, meas: np.ndarray, z: np.ndarray) -> np.ndarray:
    """The range each received fix shows: its position minus the follower's own at its
    measurement (what a follower knows of the range that set the fix's noise)."""
    mi = np.clip(meas, 0, None)
    ps = recording["pose"][:, j]
    return np.hypot(z[:, 0] - ps[mi, 0], z[:, 1] - ps[mi, 1])


def packet_sigmas(recording: dict[str, Any], j: int, meas: np.ndarray, *, nominal: bool = False) -> np.ndarray:
    """Each packet's position-noise sigma: fix_sigma_m + fix_sigma_per_m * range, the range at its
    measurement (``nominal``: a follower on the reference point, |p_d|, as the linear floor)."""
    cond = {k: v[j] for k, v in recording["conditions"].items()}
    s0, sk = float(cond["fix_sigma_m"]), float(cond["fix_sigma_per_m"])
    if nominal:
        rng = np.full(len(meas), math.hypot(*recording["spec"].p_d))
    else:
        mi = np.clip(meas, 0, None)
        tg, ps = recording["target"][:, j], recording["pose"][:, j]
        rng = np.hypot(tg[mi, 0] - ps[mi, 0], tg[mi, 1] - ps[mi, 1])
    return s0 + sk * rng


def warmup_start(recording: dict[str, Any], j: int) -> int:
    """The step at which episode j's env started its leader: minus the warm-up steps
    (:attr:`auv_follow_env.params.EnvConfig.warmup_steps`: ceil(warmup_s / dt))."""
    w = float(recording["conditions"]["warmup_s"][j])
    return -int(math.ceil(w / recording["spec"].dt - 1e-9))
