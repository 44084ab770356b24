"""Leader study: how much room a target with hidden manoeuvre modes leaves between a
generic tracker and a model-aware Bayes filter, when its state reaches the follower over a
Hard-like acoustic link.

    python -m experiments.leader_study                    # everything (about 20 min), results/leader_study.md
    python -m experiments.leader_study --units mix:turn,mix:survey      # some units now (cached), report later
    python -m experiments.leader_study --fit-seeds 0-9 --report-seeds 100-119 --particles 200  # quick look (tmp)

The work is split in *units* (one per behaviour mix, one per Leader-tier candidate, and the check
of the proposed Leader-Hard), each cached in ``results/tmp/leader_study_cache/`` with its settings;
the report is written once every unit is there, so the study can run in parts of a few minutes.

A numpy study, not integrated in the env (the env's kernel, tiers and leaderboard are untouched).

**Target.** A semi-Markov process over hidden modes: *cruise* (straight at the cruise speed),
*turn left / right* (cruise speed, turn rate +-omega), *loiter* (low speed), *sprint* (high
speed); each mode lasts a Gamma(4)-distributed time around its per-episode mean, then the next
mode follows a fixed transition table. A *survey* episode instead runs a lawnmower: straight
legs of similar length (+-5 %), a 180-degree turn at each leg end, alternately left and right.
Speed and turn rate follow their mode's command through first-order lags (2 s, 1 s) plus small
Ornstein-Uhlenbeck wobbles; no sway. All per-episode parameters (speeds, rates, mean mode
durations, leg length) are drawn uniformly from a behaviour's ranges (:class:`Behaviour`).

**Link.** As the env's v1 link (``auv_follow_env/dynamics.py``), with the ranges of a v1 tier
(:func:`link_of`, Hard by default): sends every period +- jitter, Gauss-Markov (or uniform)
latency, i.i.d. plus Gilbert-Elliott loss, fix = (x, y, psi, u, r) with Gaussian noise, position
sigma = fix_sigma + fix_sigma_per_m * |p_d| (a follower on the reference point, as the
information floor takes it). Optionally a share of fixes are *outliers* (multipath): their
position error is a 2-D Student-t (3 dof, scale 1 m) instead of Gaussian. Unlike today's env,
a fix that arrives after a newer one is delivered (and must be handled).

**Estimators of the present reference point** p + R(psi) p_d, p_d = (-0.65, 0.12) m:

* ``linear``: a linear Kalman filter on (x, y, vx, vy) with an Ornstein-Uhlenbeck velocity
  (tau = inf: constant velocity), heading from the estimated velocity; its q, tau and whether
  it gates position outliers picked from a grid on the fitting seeds.
* ``IMM``: a generic interacting-multiple-model filter (constant velocity + coordinated turn on
  (x, y, psi, u, r), EKF), chi-square gating of the fix position (99.9 %, re-initialised after
  two gated fixes in a row; the fix's heading, speed and turn rate are still used), its process
  noises and mode switching time picked from a grid on the fitting seeds.
* ``PF``: a model-aware particle filter that knows the generator (mode set, transition table,
  duration law, parameter ranges, outlier law), :func:`run_pf`. Particles run the generator's
  own step and carry the hidden modes and the per-episode parameters; the target's pose (where
  the path is placed and how it is turned) is marginalised in closed form; each particle's last
  seconds are kept, so a delayed or out-of-order fix weights the particle at its send time.
  Its estimate is the particle-weighted geometric median (Weiszfeld) of the reference point,
  the minimiser of the expected error norm; shown with N and 2N particles. What a plain
  bootstrap filter needed to keep track at mode switches (all chosen on seeds 0-15): tempered
  speed / turn-rate likelihoods, a small random-walk drift of the pose, Gibbs moves of the
  mode-duration and leg-length parameters, Liu-West moves with a floor on the speeds and rates.

Both generic filters handle out-of-order fixes exactly by re-running from a stored fix buffer.
Scored: the mean over t in [10, 60] s (every 5th 0.05 s step) of the error norm, per episode;
means over episodes with 95 % bootstrap CIs. Generic parameters are fitted on ``--fit-seeds``
(0-99), everything is reported on ``--report-seeds`` (100-299); all far below the test seeds
(>= 1,000,000, refused).
"""

from __future__ import annotations

import argparse
import hashlib
import math
import pickle
import time
import zlib
from bisect import bisect_right
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from itertools import product
from pathlib import Path

import numpy as np
from scipy.special import gammainc, gammaincc, gammaincinv, gammaln
from scipy.stats import trim_mean

from auv_follow_env.params import CONDITION_INDEX
from auv_follow_env.tiers import TIERS, check_training_seeds
from experiments.outputs import output_path, write_report

ROOT = Path(__file__).resolve().parents[1]
COMMITTED = ROOT / "results" / "leader_study.md"

DT = 0.05  # control step [s]
WARMUP_S = 9.0  # target and link run this long before t = 0 (as Hard's warmup_s) [s]
EPISODE_S = 60.0  # episode length [s]
STEADY_S = 10.0  # scoring window starts here [s]
EVAL_EVERY = 5  # score every 5th control step
P_D = (-0.65, 0.12)  # reference offset in the target's body frame [m]
N_STEPS = round((WARMUP_S + EPISODE_S) / DT) + 1  # steps k = 0..N_STEPS-1, t = -WARMUP_S + k DT
EVAL_STEPS = np.arange(round((WARMUP_S + STEADY_S) / DT), N_STEPS, EVAL_EVERY)

# the generator's fixed constants (known to the model-aware filter)
K_DUR = 4.0  # Gamma shape of the wander modes' durations [-] (coefficient of variation 0.5)
LEG_JITTER = 0.05  # survey leg lengths vary by +- this share [-]
TAU_U, TAU_R = 2.0, 1.0  # lags of the surge speed and turn rate behind their mode's command [s]
WOBBLE_U = (0.02, 5.0)  # surge-speed OU wobble: std [m/s], correlation time [s]
WOBBLE_R = (0.01, 5.0)  # turn-rate OU wobble: std [rad/s], correlation time [s]
OUTLIER_SCALE_M, OUTLIER_DOF = 1.0, 3.0  # multipath fix position error: 2-D Student-t scale [m], dof [-]
GATE_POS = 13.815510557964274  # chi-square(2) 99.9 % quantile: position gate of the generic filters
GATE_POSE = 16.26623619623813  # chi-square(3) 99.9 % quantile: the particle filter's lost-track test
#: the particle filter's own settings (chosen on training seeds 0-15 of the turn, turn+speed and survey mixes on
#: the Hard link): the speed and turn-rate noise of its likelihood is inflated by PF_TEMPER, and the particles' pose
#: drifts as a random walk whose intensity is PF_POSE_DRIFT times the fix's position and heading variances per
#: second (on Hard about 0.02 m^2/s and 0.002 rad^2/s); both keep resampled clones from locking onto a wrong path
PF_TEMPER = 2.0
PF_POSE_DRIFT = (2.5, 2.0)
LW_FLOOR = 0.1  # Liu-West moves use at least this share of a parameter's prior range as its spread [-]
HIST_S = 8.0  # the particle filter keeps each particle's last HIST_S seconds [s]

CRUISE, TURN_L, TURN_R, LOITER, SPRINT, LEG, UTURN = range(7)


# --- behaviours and links ---------------------------------------------------------------------

@dataclass(frozen=True)
class Behaviour:
    """A target behaviour: which modes exist and the per-episode parameter ranges (U[lo, hi])."""

    name: str
    p_survey: float = 0.0  #: share of episodes that are surveys (the rest wander) [-]
    speed_modes: bool = False  #: loiter and sprint among the wander modes
    v_cruise: tuple[float, float] = (0.4, 0.6)  #: cruise (and turn, survey) speed [m/s]
    v_loiter: tuple[float, float] = (0.05, 0.15)  #: loiter speed [m/s]
    v_sprint: tuple[float, float] = (0.8, 1.0)  #: sprint speed [m/s]
    turn_rate: tuple[float, float] = (0.10, 0.25)  #: wander turn rate [rad/s]
    survey_rate: tuple[float, float] = (0.20, 0.35)  #: survey end-of-leg turn rate [rad/s]
    m_cruise: tuple[float, float] = (6.0, 15.0)  #: mean cruise duration [s]
    m_turn: tuple[float, float] = (4.0, 10.0)  #: mean turn duration [s]
    m_loiter: tuple[float, float] = (5.0, 12.0)  #: mean loiter duration [s]
    m_sprint: tuple[float, float] = (3.0, 8.0)  #: mean sprint duration [s]
    leg_m: tuple[float, float] = (6.0, 15.0)  #: survey leg length [m]
    outliers: tuple[float, float] = (0.0, 0.0)  #: share of fixes that are multipath outliers [-]


_BASE = Behaviour(name="turn")
MIXES: dict[str, Behaviour] = {
    "turn": _BASE,
    "turn+speed": replace(_BASE, name="turn+speed", speed_modes=True),
    "survey": replace(_BASE, name="survey", p_survey=1.0),
    "turn+outliers": replace(_BASE, name="turn+outliers", outliers=(0.05, 0.15)),
    "turn+speed+outliers": replace(_BASE, name="turn+speed+outliers", speed_modes=True, outliers=(0.05, 0.15)),
    "survey+outliers": replace(_BASE, name="survey+outliers", p_survey=1.0, outliers=(0.05, 0.15)),
}

#: candidate generators of the Leader tiers, (tier, candidate) -> (link tier, behaviour); for Hard the
#: mildest candidate whose generic-to-PF gap on the fitting seeds has its lower 95 % bound >= 25 % is proposed
TIER_CANDIDATES: dict[tuple[str, str], tuple[str, Behaviour]] = {
    ("Easy", "E"): ("Easy", Behaviour(name="Leader-Easy", p_survey=0.5, turn_rate=(0.05, 0.15),
                                      survey_rate=(0.15, 0.25), m_cruise=(10.0, 20.0), m_turn=(5.0, 10.0),
                                      leg_m=(10.0, 20.0))),
    ("Medium", "M"): ("Medium", Behaviour(name="Leader-Medium", p_survey=0.5, speed_modes=True,
                                          turn_rate=(0.08, 0.20), survey_rate=(0.15, 0.30), m_cruise=(8.0, 18.0),
                                          m_turn=(4.0, 10.0), leg_m=(8.0, 18.0), outliers=(0.0, 0.05))),
    ("Hard", "A"): ("Hard", Behaviour(name="Leader-Hard", p_survey=0.5, speed_modes=True, outliers=(0.05, 0.15))),
    ("Hard", "B"): ("Hard", Behaviour(name="Leader-Hard", p_survey=0.5, speed_modes=True, turn_rate=(0.15, 0.30),
                                      survey_rate=(0.25, 0.40), m_cruise=(5.0, 12.0), m_turn=(3.0, 8.0),
                                      v_sprint=(0.9, 1.2), leg_m=(5.0, 12.0), outliers=(0.05, 0.15))),
}


@dataclass(frozen=True)
class Link:
    """The acoustic link of a v1 tier (ranges U[lo, hi] drawn per episode; see docs/tiers.md)."""

    tier: str
    period_s: tuple[float, float]  #: send period [s]
    jitter_s: float  #: each interval +- this [s]
    latency_model: str  #: "uniform" or "gauss_markov"
    latency_s: tuple[float, float]  #: latency mean [s]
    spread_s: tuple[float, float]  #: uniform half-width or Gauss-Markov std [s]
    latency_corr_s: float  #: Gauss-Markov correlation time [s]
    loss: tuple[float, float]  #: i.i.d. loss probability [-]
    p_good_bad: float  #: Gilbert-Elliott good -> bad per packet [-]
    p_bad_good: tuple[float, float]  #: bad -> good per packet [-]
    loss_bad: float  #: loss probability in the bad state [-]
    sigma_m: tuple[float, float]  #: fix position sigma at zero range [m]
    sigma_per_m: float  #: growth of the position sigma with range [m/m]
    sigma_psi: float  #: fix heading sigma [rad]
    sigma_u: float  #: fix speed sigma [m/s]
    sigma_r: float  #: fix turn-rate sigma [rad/s]


def link_of(tier: str) -> Link:
    """The link of the v1 tier ``tier`` with its ranges, read from :mod:`auv_follow_env.tiers`."""
    t = TIERS[tier]
    merged = {**t.fixed, **t.ranges}

    def get(name: str) -> object:
        return merged.get(name, CONDITION_INDEX[name].default if name in CONDITION_INDEX else None)

    def rng(name: str) -> tuple[float, float]:
        v = get(name)
        return (float(v[0]), float(v[1])) if isinstance(v, tuple) else (float(v), float(v))

    return Link(tier=tier, period_s=rng("update_period_s"), jitter_s=float(get("period_jitter_s")),
                latency_model=str(get("latency_model")), latency_s=rng("latency_s"), spread_s=rng("latency_spread_s"),
                latency_corr_s=float(get("latency_corr_s")), loss=rng("loss_prob"),
                p_good_bad=float(get("burst_p_good_bad")), p_bad_good=rng("burst_p_bad_good"),
                loss_bad=float(get("burst_loss_bad")), sigma_m=rng("fix_sigma_m"),
                sigma_per_m=float(get("fix_sigma_per_m")), sigma_psi=float(get("heading_sigma_rad")),
                sigma_u=float(get("velocity_sigma_mps")), sigma_r=float(get("yaw_rate_sigma_radps")))


# --- the target generator (one code path for the truth and the particles) --------------------

def transition_cum(beh: Behaviour) -> np.ndarray:
    """(7, 7) cumulative transition table: row = mode left, column = next mode."""
    P = np.zeros((7, 7))
    if beh.speed_modes:
        P[CRUISE, [TURN_L, TURN_R, LOITER, SPRINT]] = [0.3, 0.3, 0.2, 0.2]
    else:
        P[CRUISE, [TURN_L, TURN_R]] = 0.5
    P[[TURN_L, TURN_R, LOITER, SPRINT], CRUISE] = 1.0
    P[LEG, UTURN] = P[UTURN, LEG] = 1.0
    c = np.cumsum(P, axis=1)
    c[:, -1] = 1.0
    return c


def wander_visits(beh: Behaviour) -> np.ndarray:
    """(5,) stationary share of mode *visits* of the wander chain (cruise, L, R, loiter, sprint)."""
    if beh.speed_modes:
        return np.array([0.5, 0.15, 0.15, 0.1, 0.1])
    return np.array([0.5, 0.25, 0.25, 0.0, 0.0])


def draw_params(beh: Behaviour, rng: np.random.Generator, shape: tuple[int, ...]) -> dict[str, np.ndarray]:
    """Per-episode generator parameters (one set per element of ``shape``) from the behaviour's ranges."""

    def u(r: tuple[float, float]) -> np.ndarray:
        return rng.uniform(r[0], r[1], shape)

    pr = {"survey": rng.random(shape) < beh.p_survey, "v_c": u(beh.v_cruise), "v_l": u(beh.v_loiter),
          "v_s": u(beh.v_sprint), "omega": u(beh.turn_rate), "omega_s": u(beh.survey_rate),
          "m_cruise": u(beh.m_cruise), "m_turn": u(beh.m_turn), "m_loiter": u(beh.m_loiter),
          "m_sprint": u(beh.m_sprint), "leg": u(beh.leg_m)}
    return pr


#: the speed and rate parameters and their range field (Liu-West moves in the particle filter after resampling;
#: the mean durations and the leg length get an exact Gibbs move instead, :func:`gibbs_lengths`)
CONT_PARAMS = {"v_c": "v_cruise", "v_l": "v_loiter", "v_s": "v_sprint", "omega": "turn_rate",
               "omega_s": "survey_rate"}


def _commands(mode: np.ndarray, side: np.ndarray, pr: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The speed [m/s] and turn-rate [rad/s] commands of each element's mode."""
    u_cmd = np.where(mode == LOITER, pr["v_l"], np.where(mode == SPRINT, pr["v_s"], pr["v_c"]))
    r_cmd = (pr["omega"] * ((mode == TURN_L).astype(float) - (mode == TURN_R))
             + pr["omega_s"] * side * (mode == UTURN))
    return u_cmd, r_cmd


def _mean_duration(mode: np.ndarray, pr: dict[str, np.ndarray], sel: tuple) -> np.ndarray:
    """Mean duration [s] of wander mode ``mode`` for the elements ``sel``."""
    return np.select([mode == CRUISE, (mode == TURN_L) | (mode == TURN_R), mode == LOITER],
                     [pr["m_cruise"][sel], pr["m_turn"][sel], pr["m_loiter"][sel]], pr["m_sprint"][sel])


def _threshold(mode: np.ndarray, pr: dict[str, np.ndarray], sel: tuple, g: np.ndarray, u2: np.ndarray) -> np.ndarray:
    """The progress at which the new mode ends: a Gamma duration [s] (wander: ``g`` a standard
    Gamma draw), a leg length [m] (survey leg) or the heading change [rad] of a U-turn (the turn
    rate's lag adds omega * TAU_R after the command drops)."""
    wander = g * _mean_duration(mode, pr, sel) / K_DUR
    leg = pr["leg"][sel] * (1.0 + LEG_JITTER * (2.0 * u2 - 1.0))
    uturn = math.pi - pr["omega_s"][sel] * TAU_R
    return np.where(mode == LEG, leg, np.where(mode == UTURN, uturn, wander))


def redraw_threshold(st: dict[str, np.ndarray], pr: dict[str, np.ndarray], rng: np.random.Generator) -> None:
    """Draw every element's threshold anew from its law given that the mode has not ended yet
    (progress < threshold): what a filter knows of it. Exact at any time (the threshold is
    independent of everything but the survival), and it keeps resampled clones from sharing it."""
    mode, prog = st["mode"], st["prog"]
    allsel = (slice(None),) * mode.ndim
    m = _mean_duration(mode, pr, allsel)
    f0 = gammainc(K_DUR, K_DUR * prog / m)
    u = np.minimum(f0 + (1.0 - f0) * rng.random(mode.shape), 1.0 - 1e-12)
    wander = m * gammaincinv(K_DUR, u) / K_DUR
    lo, hi = pr["leg"] * (1.0 - LEG_JITTER), pr["leg"] * (1.0 + LEG_JITTER)
    leg = np.where(prog < hi, np.maximum(lo, prog) + (hi - np.maximum(lo, prog)) * rng.random(mode.shape), prog)
    uturn = math.pi - pr["omega_s"] * TAU_R
    st["thr"] = np.where(mode <= SPRINT, np.maximum(wander, prog), np.where(mode == LEG, leg, uturn))


def init_state(beh: Behaviour, pr: dict[str, np.ndarray], rng: np.random.Generator) -> dict[str, np.ndarray]:
    """A stationary start: the mode by its share of time, the elapsed share of a length-biased
    duration (Gamma(K+1)), speeds at their command, wobbles stationary; at the origin with a
    uniform heading (position and heading are anchored to the first fix by the filter)."""
    shape = pr["v_c"].shape
    visits = wander_visits(beh)
    means = np.stack([pr["m_cruise"], pr["m_turn"], pr["m_turn"], pr["m_loiter"], pr["m_sprint"]], -1)
    share = visits * means
    cum = np.cumsum(share / share.sum(-1, keepdims=True), -1)
    mode_w = np.minimum((rng.random(shape)[..., None] >= cum).sum(-1), 4)
    t_leg = pr["leg"] / pr["v_c"]
    t_turn = math.pi / pr["omega_s"]
    mode_s = np.where(rng.random(shape) < t_leg / (t_leg + t_turn), LEG, UTURN)
    mode = np.where(pr["survey"], mode_s, mode_w).astype(np.int64)
    allsel = (slice(None),) * len(shape)
    thr = _threshold(mode, pr, allsel, rng.standard_gamma(K_DUR + 1.0, shape), rng.random(shape))
    side = np.where(rng.random(shape) < 0.5, -1.0, 1.0)
    ub, rb = _commands(mode, side, pr)
    return {"x": np.zeros(shape), "y": np.zeros(shape), "psi": rng.uniform(-math.pi, math.pi, shape),
            "ub": ub, "rb": rb, "wu": WOBBLE_U[0] * rng.standard_normal(shape),
            "wr": WOBBLE_R[0] * rng.standard_normal(shape), "u": ub.copy(), "r": rb.copy(),
            "mode": mode, "prog": rng.random(shape) * thr, "thr": thr, "side": side}


#: mode -> the kind whose mean length it informs (cruise, turn, loiter, sprint, survey leg; -1: none)
_KIND = np.array([0, 1, 1, 2, 3, 4, -1])
_MEAN_KEYS = ("m_cruise", "m_turn", "m_loiter", "m_sprint")


def add_stats(st: dict[str, np.ndarray], beh: Behaviour) -> None:
    """Sufficient statistics of each element's completed mode lengths (the particle filter's
    Gibbs move of the duration and leg parameters): count and sum per kind, the interval the leg
    length is confined to, and whether the element is still in its first mode (whose length law
    is length-biased and not counted)."""
    shape = st["mode"].shape
    st["n_dur"], st["s_dur"] = np.zeros(shape + (5,)), np.zeros(shape + (5,))
    st["leg_lo"], st["leg_hi"] = np.full(shape, beh.leg_m[0]), np.full(shape, beh.leg_m[1])
    st["first"] = np.ones(shape, bool)


def _grid_draw(ll: np.ndarray, grid: np.ndarray, old: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """One draw per row from the density exp(ll) (n, G) on the grid's cells (uniform within a
    cell); rows with no support keep ``old``."""
    top = ll.max(1, keepdims=True)
    ok = np.isfinite(top[:, 0])
    p = np.exp(ll - np.where(np.isfinite(top), top, 0.0))
    c = np.cumsum(p, 1)
    u = rng.random(len(ll))[:, None] * c[:, -1:]
    i = np.minimum((u > c).sum(1), len(grid) - 1)
    cell = grid[1] - grid[0]
    return np.where(ok, grid[i] + (rng.random(len(ll)) - 0.5) * cell, old)


def gibbs_lengths(st: dict[str, np.ndarray], pr: dict[str, np.ndarray], beh: Behaviour,
                  rng: np.random.Generator, n_grid: int = 64) -> None:
    """Draw each particle's mean mode durations and leg length (1-D arrays) from their exact
    conditional given its own path: a uniform prior times the Gamma(K_DUR) likelihood of its
    completed durations (or the leg-length window of its completed legs) times the survival of
    its current mode; on a grid. (A resample-move step: it keeps resampled clones from sharing
    a parameter that only later mode ends would have corrected.)"""
    cur_kind = np.where(st["first"], -1, _KIND[st["mode"]])
    for kind, key in enumerate(_MEAN_KEYS):
        lo, hi = getattr(beh, key)
        if hi <= lo:
            continue
        grid = lo + (hi - lo) * (np.arange(n_grid) + 0.5) / n_grid
        ll = -K_DUR * (st["n_dur"][:, kind, None] * np.log(grid) + st["s_dur"][:, kind, None] / grid)
        cur = cur_kind == kind
        if cur.any():
            ll[cur] += np.log(np.maximum(gammaincc(K_DUR, K_DUR * st["prog"][cur, None] / grid), 1e-300))
        pr[key] = np.clip(_grid_draw(ll, grid, pr[key], rng), lo, hi)
    lo, hi = beh.leg_m
    if hi > lo:
        grid = lo + (hi - lo) * (np.arange(n_grid) + 0.5) / n_grid
        ll = -st["n_dur"][:, 4, None] * np.log(grid)
        ll[(grid < st["leg_lo"][:, None]) | (grid > st["leg_hi"][:, None])] = -np.inf
        cur = cur_kind == 4
        if cur.any():
            surv = np.clip(((1 + LEG_JITTER) * grid - st["prog"][cur, None]) / (2 * LEG_JITTER * grid), 0.0, 1.0)
            ll[cur] += np.log(np.maximum(surv, 1e-300))
        pr["leg"] = np.clip(_grid_draw(ll, grid, pr["leg"], rng), np.maximum(lo, st["leg_lo"]),
                            np.minimum(hi, st["leg_hi"]))


_A_U, _A_R = math.exp(-DT / TAU_U), math.exp(-DT / TAU_R)
_A_WU, _A_WR = math.exp(-DT / WOBBLE_U[1]), math.exp(-DT / WOBBLE_R[1])
_B_WU, _B_WR = WOBBLE_U[0] * math.sqrt(1 - _A_WU ** 2), WOBBLE_R[0] * math.sqrt(1 - _A_WR ** 2)


def step(st: dict[str, np.ndarray], pr: dict[str, np.ndarray], cum: np.ndarray, nu: np.ndarray, nr: np.ndarray,
         draw: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]) -> None:
    """Advance every element one control step DT in place (the generator's definition).

    ``nu``, ``nr``: standard normals of the speed and turn-rate wobbles; ``draw(mask)`` returns,
    for the elements whose mode ends now, a uniform (next mode), a standard Gamma(K_DUR) (its
    duration) and a uniform (leg length). A mode ends when its progress (time in a wander mode,
    distance along a survey leg, heading change in a U-turn) reaches its drawn threshold."""
    mode = st["mode"]
    u_cmd, r_cmd = _commands(mode, st["side"], pr)
    st["ub"] += (u_cmd - st["ub"]) * (1.0 - _A_U)
    st["rb"] += (r_cmd - st["rb"]) * (1.0 - _A_R)
    st["wu"] = _A_WU * st["wu"] + _B_WU * nu
    st["wr"] = _A_WR * st["wr"] + _B_WR * nr
    u = np.maximum(st["ub"] + st["wu"], 0.0)
    r = st["rb"] + st["wr"]
    pm = st["psi"] + 0.5 * DT * r
    st["x"] += DT * u * np.cos(pm)
    st["y"] += DT * u * np.sin(pm)
    st["psi"] += DT * r
    st["u"], st["r"] = u, r
    st["prog"] += np.where(mode <= SPRINT, DT, np.where(mode == LEG, DT * u, DT * np.abs(r)))
    sw = st["prog"] >= st["thr"]
    if not sw.any():
        return
    sel = np.nonzero(sw)
    old = mode[sel]
    if "n_dur" in st:  # (the particle filter) record the completed mode's length for the parameters' Gibbs move
        kind = _KIND[old]
        ok = ~st["first"][sel] & (kind >= 0)
        idx = tuple(a[ok] for a in sel)
        done, kind = st["prog"][sel][ok], kind[ok]
        st["n_dur"][idx + (kind,)] += 1
        st["s_dur"][idx + (kind,)] += done
        leg = kind == 4
        li = tuple(a[leg] for a in idx)
        st["leg_lo"][li] = np.maximum(st["leg_lo"][li], done[leg] / (1 + LEG_JITTER))
        st["leg_hi"][li] = np.minimum(st["leg_hi"][li], done[leg] / (1 - LEG_JITTER))
        st["first"][sel] = False
    u1, g, u2 = draw(sw)
    new = np.minimum((u1[:, None] >= cum[old]).sum(1), 6)
    st["thr"][sel] = _threshold(new, pr, sel, g, u2)
    st["prog"][sel] = 0.0
    st["side"][sel] = np.where(old == UTURN, -st["side"][sel], st["side"][sel])
    mode[sel] = new


# --- episodes: truth and fixes ----------------------------------------------------------------

@dataclass
class Episodes:
    """Simulated episodes of one behaviour and link (truth at every step, the received fixes)."""

    seeds: list[int]
    truth: np.ndarray  #: (E, N_STEPS, 5) x, y, psi, u, r of the target
    ref: np.ndarray  #: (E, len(EVAL_STEPS), 2) true reference point at the scored steps [m]
    fixes: list[dict[str, np.ndarray]]  #: per episode: send, arr (steps), z (M, 5), outlier (M,)
    sigma: np.ndarray  #: (E, 5) fix noise std of x, y, psi, u, r
    eps: np.ndarray  #: (E,) outlier share
    survey: np.ndarray  #: (E,) survey episode
    lost_share: np.ndarray  #: (E,) share of sends lost
    params: dict[str, np.ndarray]  #: (E,) the generator's drawn parameters


def ref_point(x: np.ndarray, y: np.ndarray, psi: np.ndarray) -> np.ndarray:
    """The reference point p + R(psi) p_d (..., 2) [m]."""
    c, s = np.cos(psi), np.sin(psi)
    return np.stack([x + c * P_D[0] - s * P_D[1], y + s * P_D[0] + c * P_D[1]], -1)


def _link_fixes(link: Link, truth: np.ndarray, eps: float, rng: np.random.Generator) -> tuple[dict, np.ndarray, float]:
    """The fixes one episode's follower receives (send and arrival steps, noisy fix, outlier
    flag), its fix-noise stds and the share of sends lost; mirrors the env's ``_send``."""
    period = rng.uniform(*link.period_s)
    lat_mean, spread = rng.uniform(*link.latency_s), rng.uniform(*link.spread_s)
    loss, p_bg = rng.uniform(*link.loss), rng.uniform(*link.p_bad_good)
    sig_pos = rng.uniform(*link.sigma_m) + link.sigma_per_m * math.hypot(*P_D)
    sigma = np.array([sig_pos, sig_pos, link.sigma_psi, link.sigma_u, link.sigma_r])
    sched = rng.uniform(0.0, period)  # [s] since the start
    t_end = (N_STEPS - 1) * DT
    sends, lats, kept = [], [], []
    latx, bad, last = 0.0, False, None
    while sched < t_end:
        s = int(np.clip(round((sched + rng.uniform(-link.jitter_s, link.jitter_s)) / DT), 0, N_STEPS - 1))
        sched += period
        if last is not None and s <= last:
            continue
        if link.latency_model == "gauss_markov":
            a = math.exp(-((s - last) * DT if last is not None else 1e9) / link.latency_corr_s)
            latx = a * latx + spread * math.sqrt(1 - a * a) * rng.standard_normal()
            lat = max(0.0, lat_mean + latx)
        elif link.latency_model == "uniform":
            lat = lat_mean + spread * (2 * rng.random() - 1)
        else:
            lat = lat_mean
        last = s
        lost = rng.random() < loss
        if link.p_good_bad > 0:
            if bad:
                lost |= rng.random() < link.loss_bad
                bad = not (rng.random() < p_bg)
            else:
                bad = rng.random() < link.p_good_bad
        sends.append(s)
        lats.append(lat)
        kept.append(not lost)
    send = np.array(sends, dtype=np.int64)
    arr = send + np.ceil(np.array(lats) / DT - 1e-6).astype(np.int64)
    ok = np.array(kept) & (arr < N_STEPS)
    send, arr = send[ok], arr[ok]
    z = truth[send].copy()
    z += sigma * rng.standard_normal(z.shape)
    out = rng.random(len(send)) < eps
    if out.any():  # multipath: a 2-D Student-t position error instead of the Gaussian one
        n = int(out.sum())
        t = rng.standard_normal((n, 2)) / np.sqrt(rng.chisquare(OUTLIER_DOF, (n, 1)) / OUTLIER_DOF)
        z[out, :2] = truth[send[out], :2] + OUTLIER_SCALE_M * t
    lost_share = 1.0 - float(np.mean(kept)) if kept else 0.0
    return {"send": send, "arr": arr, "z": z, "outlier": out}, sigma, lost_share


def make_episodes(beh: Behaviour, link: Link, seeds: Sequence[int]) -> Episodes:
    """Simulate the target and the link for each seed (the episode depends on its seed, the
    behaviour's name and the link's tier only: not on the batch)."""
    E = len(seeds)
    cum = transition_cum(beh)
    rngs = [np.random.default_rng([int(s), zlib.crc32(beh.name.encode()), zlib.crc32(link.tier.encode())])
            for s in seeds]
    prs = [draw_params(beh, r, (1,)) for r in rngs]
    sts = [init_state(beh, p, r) for p, r in zip(prs, rngs, strict=True)]
    pr = {k: np.concatenate([p[k] for p in prs]) for k in prs[0]}
    st = {k: np.concatenate([s[k] for s in sts]) for k in sts[0]}
    noise = np.stack([r.standard_normal((N_STEPS, 2)) for r in rngs])  # (E, T, 2)
    sw_draw = np.stack([np.column_stack([r.random(N_STEPS), r.standard_gamma(K_DUR, N_STEPS), r.random(N_STEPS)])
                        for r in rngs])  # (E, T, 3)
    eps = np.array([r.uniform(*beh.outliers) for r in rngs])
    truth = np.empty((E, N_STEPS, 5))
    k_now = [0]

    def draw(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        d = sw_draw[mask, k_now[0]]
        return d[:, 0], d[:, 1], d[:, 2]

    for k in range(N_STEPS):
        if k > 0:
            k_now[0] = k
            step(st, pr, cum, noise[:, k, 0], noise[:, k, 1], draw)
        truth[:, k] = np.column_stack([st["x"], st["y"], st["psi"], st["u"], st["r"]])
    fixes, sig, lost = [], [], []
    for e, r in enumerate(rngs):
        f, s, ls = _link_fixes(link, truth[e], float(eps[e]), r)
        fixes.append(f)
        sig.append(s)
        lost.append(ls)
    ref = ref_point(truth[:, EVAL_STEPS, 0], truth[:, EVAL_STEPS, 1], truth[:, EVAL_STEPS, 2])
    return Episodes(seeds=list(seeds), truth=truth, ref=ref, fixes=fixes, sigma=np.array(sig), eps=eps,
                    survey=pr["survey"].copy(), lost_share=np.array(lost),
                    params={k: v.copy() for k, v in pr.items()})


# --- generic estimators (batched over a parameter grid G) -------------------------------------

def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + math.pi) % (2 * math.pi) - math.pi


def _prop(x: np.ndarray, T: np.ndarray, turn: bool, jac: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """Mean motion of states (..., 5) = (x, y, psi, u, r) over T (...) seconds and its Jacobian
    (..., 5, 5): exact arcs at constant speed and turn rate (``turn``), or straight with the turn
    rate held at 0 (constant velocity)."""
    px, py, psi, u, r = np.moveaxis(x, -1, 0)
    s0, c0 = np.sin(psi), np.cos(psi)
    if turn:
        rs = np.where(np.abs(r) < 1e-5, np.where(r >= 0, 1e-5, -1e-5), r)
        p1 = psi + rs * T
        s1, c1 = np.sin(p1), np.cos(p1)
        ds, dc = s1 - s0, c0 - c1
        out = np.stack([px + u * ds / rs, py + u * dc / rs, psi + r * T, u, r], -1)
    else:
        out = np.stack([px + u * T * c0, py + u * T * s0, psi, u, np.zeros_like(r)], -1)
    if not jac:
        return out, None
    J = np.zeros(x.shape + (5,))
    for i in range(4):
        J[..., i, i] = 1.0
    if turn:
        J[..., 4, 4] = 1.0
        J[..., 0, 2], J[..., 0, 3] = u * (c1 - c0) / rs, ds / rs
        J[..., 0, 4] = -u * ds / rs ** 2 + u * T * c1 / rs
        J[..., 1, 2], J[..., 1, 3] = u * (s1 - s0) / rs, dc / rs
        J[..., 1, 4] = -u * dc / rs ** 2 + u * T * s1 / rs
        J[..., 2, 4] = T
    else:
        J[..., 0, 2], J[..., 0, 3] = -u * T * s0, T * c0
        J[..., 1, 2], J[..., 1, 3] = u * T * c0, T * s0
    return out, J


def _q_disc(x0: np.ndarray, T: np.ndarray, turn: bool, qc: np.ndarray) -> np.ndarray:
    """Discrete process noise int_0^T Phi(T, s) diag(qc) Phi(T, s)^T ds by Simpson's rule, Phi
    from the Jacobian along the mean."""
    out = 0.0
    for w, f in ((1.0, 0.0), (4.0, 0.5), (1.0, 1.0)):
        xm, _ = _prop(x0, f * T, turn, jac=False)
        _, J = _prop(xm, (1.0 - f) * T, turn)
        out = out + w * np.einsum("...ij,...j,...kj->...ik", J, qc, J)
    return out * (T / 6.0)[..., None, None]


class IMM:
    """Generic IMM (constant velocity + coordinated turn) on (x, y, psi, u, r), batched over G
    parameter sets: q_u [m^2/s^3] (both), q_r [rad^2/s^3] (CT), q_h [rad^2/s] (CV heading),
    tau_s [s] (mean time between mode switches), gate (position chi-square gate on/off)."""

    def __init__(self, q_u: np.ndarray, q_r: np.ndarray, q_h: np.ndarray, tau_s: np.ndarray, gate: np.ndarray):
        self.G = len(q_u)
        z = np.zeros(self.G)
        self.qc = np.stack([np.stack([z, z, q_h, q_u, z], -1), np.stack([z, z, z, q_u, q_r], -1)], 1)  # (G, 2, 5)
        self.tau_s, self.gate = np.asarray(tau_s, float), np.asarray(gate, bool)
        self.reset()

    def reset(self) -> None:
        self.m = None
        self.t_f = None

    def snapshot(self) -> tuple:
        return None if self.m is None else (self.m.copy(), self.P.copy(), self.mu.copy(), self.ng.copy(), self.t_f)

    def restore(self, snap: tuple | None) -> None:
        if snap is None:
            self.reset()
        else:
            self.m, self.P, self.mu, self.ng, self.t_f = (a.copy() if isinstance(a, np.ndarray) else a for a in snap)

    def _init(self, z: np.ndarray, sig: np.ndarray, which: np.ndarray) -> None:
        m = np.broadcast_to(z, (self.G, 2, 5)).copy()
        m[:, 0, 4] = 0.0
        P = np.zeros((self.G, 2, 5, 5))
        P[:, :, range(5), range(5)] = sig ** 2
        P[:, 0, 4, 4] = 1e-10
        if self.m is None:
            self.m, self.P, self.mu, self.ng = m, P, np.full((self.G, 2), 0.5), np.zeros(self.G, int)
        else:
            self.m[which], self.P[which], self.mu[which], self.ng[which] = m[which], P[which], 0.5, 0

    def _mix(self, m: np.ndarray, mu: np.ndarray, T: np.ndarray, P: np.ndarray | None = None):
        """Mode probabilities c after T, mixed means (and covariances) per model; leading axes of m
        (..., 2, 5), mu (..., 2), T (...)."""
        p = 0.5 * (1.0 - np.exp(-2.0 * T / self.tau_s.reshape(self.tau_s.shape + (1,) * (T.ndim - 1))))
        Pi = np.stack([np.stack([1 - p, p], -1), np.stack([p, 1 - p], -1)], -2)  # (..., i, j)
        c = np.einsum("...i,...ij->...j", mu, Pi)
        w = mu[..., :, None] * Pi / np.maximum(c[..., None, :], 1e-300)
        d = m[..., :, None, :] - m[..., None, :, :]  # (..., i, j, 5): m_i - m_j
        d[..., 2] = _wrap(d[..., 2])
        shift = np.einsum("...ij,...ijk->...jk", w, d)
        x0 = m + shift
        x0[..., 0, 4] = 0.0
        if P is None:
            return c, x0, None
        e = d - shift[..., None, :, :]
        P0 = np.einsum("...ij,...ikl->...jkl", w, P) + np.einsum("...ij,...ijk,...ijl->...jkl", w, e, e)
        P0[..., 0, 4, :] = 0.0
        P0[..., 0, :, 4] = 0.0
        P0[..., 0, 4, 4] = 1e-10
        return c, x0, P0

    def process(self, z: np.ndarray, sig: np.ndarray, s: int) -> None:
        """Take the fix z (5,) with stds sig (5,) measured at step s (>= the last one's)."""
        if self.m is None:
            self._init(z, sig, np.ones(self.G, bool))
            self.t_f = s
            return
        T = np.full(self.G, (s - self.t_f) * DT)
        c, x0, P0 = self._mix(self.m, self.mu, T, self.P)
        m = np.empty_like(x0)
        P = np.empty_like(P0)
        for j, turn in ((0, False), (1, True)):
            m[:, j], J = _prop(x0[:, j], T, turn)
            P[:, j] = J @ P0[:, j] @ np.swapaxes(J, -1, -2) + _q_disc(x0[:, j], T, turn, self.qc[:, j])
        nu = z - m
        nu[..., 2] = _wrap(nu[..., 2])
        Rd = np.broadcast_to(sig ** 2, (self.G, 5)).copy()
        Sp = P[..., :2, :2] + np.diag(Rd[0, :2])
        d2 = np.einsum("...i,...ij,...j->...", nu[..., :2], np.linalg.inv(Sp), nu[..., :2])
        gated = self.gate & (d2.min(1) > GATE_POS)
        Rd[gated, :2] = 1e8  # a gated fix: its position is not used (heading, speed, turn rate are)
        S = P + np.eye(5) * Rd[:, None, None, :]
        Sinv = np.linalg.inv(S)
        K = P @ Sinv
        self.m = m + np.einsum("...ij,...j->...i", K, nu)
        self.m[:, 0, 4] = 0.0
        self.P = P - K @ P
        self.P = 0.5 * (self.P + np.swapaxes(self.P, -1, -2))
        _, logdet = np.linalg.slogdet(S)
        ll = -0.5 * (np.einsum("...i,...ij,...j->...", nu, Sinv, nu) + logdet)
        ll -= ll.max(1, keepdims=True)
        mu = c * np.exp(ll)
        self.mu = mu / mu.sum(1, keepdims=True)
        self.ng = np.where(gated, self.ng + 1, 0)
        self.t_f = s
        again = self.ng >= 2
        if again.any():
            self._init(z, sig, again)

    def predict_ref(self, T: np.ndarray) -> np.ndarray:
        """(G, n, 2) the estimated reference point T (n,) seconds after the last fix."""
        Tg = np.broadcast_to(T, (self.G, len(T)))
        c, x0, _ = self._mix(self.m[:, None], self.mu[:, None], Tg)
        cv, _ = _prop(x0[..., 0, :], Tg, False, jac=False)
        ct, _ = _prop(x0[..., 1, :], Tg, True, jac=False)
        ref = c[..., 0, None] * ref_point(cv[..., 0], cv[..., 1], cv[..., 2])
        return ref + c[..., 1, None] * ref_point(ct[..., 0], ct[..., 1], ct[..., 2])


class LinearKF:
    """Linear Kalman filter on (x, y, vx, vy), velocity an Ornstein-Uhlenbeck process (intensity
    q [m^2/s^3], time constant tau [s]; inf: constant velocity), batched over G parameter sets;
    ``gate``: chi-square gate on the fix position. The reference point's heading is the estimated
    velocity's direction (the last fix's heading below 0.05 m/s)."""

    def __init__(self, q: np.ndarray, tau: np.ndarray, gate: np.ndarray):
        self.G = len(q)
        self.q, self.tau, self.gate = np.asarray(q, float), np.asarray(tau, float), np.asarray(gate, bool)
        self.reset()

    reset = IMM.reset

    def snapshot(self) -> tuple:
        return None if self.m is None else (self.m.copy(), self.P.copy(), self.ng.copy(), self.t_f, self.psi)

    def restore(self, snap: tuple | None) -> None:
        if snap is None:
            self.reset()
        else:
            self.m, self.P, self.ng, self.t_f, self.psi = (a.copy() if isinstance(a, np.ndarray) else a for a in snap)

    def _ab(self, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Velocity decay a and position gain b over T (G, ...)."""
        tau = self.tau.reshape(self.tau.shape + (1,) * (T.ndim - 1))
        fin = np.isfinite(tau)
        tf = np.where(fin, tau, 1.0)
        a = np.where(fin, np.exp(-T / tf), 1.0)
        b = np.where(fin, tf * (1.0 - np.exp(-T / tf)), T)
        return a, b

    @staticmethod
    def _meas(z: np.ndarray, sig: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The fix as (x, y, vx, vy) and its covariance (first order in the heading noise)."""
        c, s, u = math.cos(z[2]), math.sin(z[2]), z[3]
        Jv = np.array([[c, -u * s], [s, u * c]])
        R = np.zeros((4, 4))
        R[0, 0] = R[1, 1] = sig[0] ** 2
        R[2:, 2:] = Jv @ np.diag([sig[3] ** 2, sig[2] ** 2]) @ Jv.T + 1e-8 * np.eye(2)
        return np.array([z[0], z[1], u * c, u * s]), R

    def process(self, z: np.ndarray, sig: np.ndarray, s: int) -> None:
        """Take the fix z (5,) with stds sig (5,) measured at step s (>= the last one's)."""
        y, R = self._meas(z, sig)
        if self.m is None:
            self.m, self.P = np.broadcast_to(y, (self.G, 4)).copy(), np.broadcast_to(R, (self.G, 4, 4)).copy()
            self.ng, self.t_f, self.psi = np.zeros(self.G, int), s, float(z[2])
            return
        T = np.full(self.G, (s - self.t_f) * DT)
        a, b = self._ab(T)
        F = np.zeros((self.G, 4, 4))
        F[:, [0, 1], [0, 1]] = 1.0
        F[:, 0, 2] = F[:, 1, 3] = b
        F[:, 2, 2] = F[:, 3, 3] = a
        fin = np.isfinite(self.tau)
        tf = np.where(fin, self.tau, 1.0)
        qvv = np.where(fin, self.q * tf / 2 * (1 - a * a), self.q * T)
        qpv = np.where(fin, self.q * tf ** 2 / 2 * (1 - a) ** 2, self.q * T ** 2 / 2)
        qpp = np.where(fin, self.q * tf ** 2 * (T - 2 * tf * (1 - a) + tf / 2 * (1 - a * a)), self.q * T ** 3 / 3)
        Q = np.zeros((self.G, 4, 4))
        Q[:, [0, 1], [0, 1]] = qpp[:, None]
        Q[:, [2, 3], [2, 3]] = qvv[:, None]
        Q[:, [0, 1], [2, 3]] = Q[:, [2, 3], [0, 1]] = qpv[:, None]
        m = np.einsum("gij,gj->gi", F, self.m)
        P = F @ self.P @ np.swapaxes(F, 1, 2) + Q
        nu = y - m
        d2 = np.einsum("gi,gij,gj->g", nu[:, :2], np.linalg.inv(P[:, :2, :2] + R[:2, :2]), nu[:, :2])
        gated = self.gate & (d2 > GATE_POS)
        Rg = np.broadcast_to(R, (self.G, 4, 4)).copy()
        Rg[gated, 0, 0] = Rg[gated, 1, 1] = 1e8
        K = P @ np.linalg.inv(P + Rg)
        self.m = m + np.einsum("gij,gj->gi", K, nu)
        self.P = P - K @ P
        self.P = 0.5 * (self.P + np.swapaxes(self.P, 1, 2))
        self.ng = np.where(gated, self.ng + 1, 0)
        self.t_f, self.psi = s, float(z[2])
        again = self.ng >= 2
        if again.any():
            self.m[again], self.P[again], self.ng[again] = y, R, 0

    def predict_ref(self, T: np.ndarray) -> np.ndarray:
        """(G, n, 2) the estimated reference point T (n,) seconds after the last fix."""
        Tg = np.broadcast_to(T, (self.G, len(T)))
        a, b = self._ab(Tg)
        m = self.m[:, None, :]
        x, y = m[..., 0] + b * m[..., 2], m[..., 1] + b * m[..., 3]
        vx, vy = a * m[..., 2], a * m[..., 3]
        psi = np.where(np.hypot(vx, vy) >= 0.05, np.arctan2(vy, vx), self.psi)
        return ref_point(x, y, psi)


def run_generic(flt: IMM | LinearKF, fixes: dict[str, np.ndarray], sigma: np.ndarray) -> tuple[np.ndarray, int]:
    """Run a generic filter over one episode's fixes in arrival order; an out-of-order fix is
    inserted in the send-time-sorted buffer and the filter re-run from the snapshot before it.
    Returns (G, len(EVAL_STEPS), 2) estimates (NaN before the first arrival) and the number of
    out-of-order arrivals."""
    send, arr, z = fixes["send"], fixes["arr"], fixes["z"]
    out = np.full((flt.G, len(EVAL_STEPS), 2), np.nan)
    flt.reset()
    order = np.lexsort((send, arr))
    buf: list[int] = []  # fix indices sorted by send step
    snaps: list[tuple] = []  # the filter after each buffered fix
    n_ooo = 0
    i = 0
    while i < len(order):
        a = arr[order[i]]
        while i < len(order) and arr[order[i]] == a:
            f = order[i]
            pos = bisect_right([send[j] for j in buf], send[f])
            buf.insert(pos, f)
            if pos < len(buf) - 1:
                n_ooo += 1
            flt.restore(snaps[pos - 1] if pos > 0 else None)
            del snaps[pos:]
            for j in buf[pos:]:
                flt.process(z[j], sigma, int(send[j]))
                snaps.append(flt.snapshot())
            i += 1
        nxt = arr[order[i]] if i < len(order) else N_STEPS
        sel = (EVAL_STEPS >= a) & (EVAL_STEPS < nxt)
        if sel.any():
            out[:, sel] = flt.predict_ref((EVAL_STEPS[sel] - flt.t_f) * DT)
    return out, n_ooo


def generic_errors(make: Callable[[], IMM | LinearKF], ep: Episodes) -> tuple[np.ndarray, int]:
    """(G, E) per-episode mean error [m] of a generic filter (every grid entry), and the total
    number of out-of-order arrivals."""
    errs, n_ooo = [], 0
    for e in range(len(ep.seeds)):
        est, k = run_generic(make(), ep.fixes[e], ep.sigma[e])
        n_ooo += k
        errs.append(np.nanmean(np.linalg.norm(est - ep.ref[e], axis=-1), axis=1))
    return np.array(errs).T, n_ooo


KF_GRID = list(product([1e-4, 3e-4, 1e-3, 3e-3, 1e-2, 3e-2], [2.0, 5.0, 15.0, math.inf], [False, True]))
IMM_GRID = list(product([1e-3, 1e-2, 3e-2, 1e-1], [1e-4, 1e-3, 1e-2, 3e-2], [1e-4, 1e-3], [5.0, 15.0, 40.0], [True]))


def make_kf(grid: Sequence[tuple]) -> Callable[[], LinearKF]:
    g = np.array(grid, dtype=float)
    return lambda: LinearKF(g[:, 0], g[:, 1], g[:, 2] > 0)


def make_imm(grid: Sequence[tuple]) -> Callable[[], IMM]:
    g = np.array(grid, dtype=float)
    return lambda: IMM(g[:, 0], g[:, 1], g[:, 2], g[:, 3], g[:, 4] > 0)


# --- the model-aware particle filter ----------------------------------------------------------

def _weiszfeld(p: np.ndarray, w: np.ndarray, iters: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Weighted geometric median of points p (B, N, 2) with weights w (B, N) (summing to 1), by
    Weiszfeld's iteration from the weighted mean; returns (median, mean), each (B, 2)."""
    mean = np.einsum("bn,bnk->bk", w, p)
    m = mean.copy()
    for _ in range(iters):
        d = np.maximum(np.hypot(p[..., 0] - m[:, None, 0], p[..., 1] - m[:, None, 1]), 1e-9)
        v = w / d
        m = np.einsum("bn,bnk->bk", v, p) / v.sum(1, keepdims=True)
    return m, mean


def _log_t2(d2: np.ndarray) -> np.ndarray:
    """Log density of the 2-D Student-t outlier position error at squared distance d2 [m^2]."""
    nu, s2 = OUTLIER_DOF, OUTLIER_SCALE_M ** 2
    return (gammaln((nu + 2) / 2) - gammaln(nu / 2) - math.log(nu * math.pi * s2)
            - (nu + 2) / 2 * np.log1p(d2 / (nu * s2)))


def _rot(d: np.ndarray, c: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Rotate vectors d (..., 2) by the angle with cosine c and sine s (...)."""
    return np.stack([c * d[..., 0] - s * d[..., 1], s * d[..., 0] + c * d[..., 1]], -1)


def run_pf(beh: Behaviour, ep: Episodes, n: int, seed: int, temper: float = PF_TEMPER,
           pose_drift: tuple[float, float] = PF_POSE_DRIFT, chunk_mb: float = 150.0) -> dict[str, object]:
    """The model-aware particle filter with ``n`` particles on every episode of ``ep``.

    Episodes are filtered in batches (arrays (B, n)). Every control step the particles move by
    the generator's own :func:`step` (mode ends in their hazard form). The generator's dynamics
    do not depend on the target's position or heading, so a particle is a *path shape*
    (displacement, heading change, speed, turn rate, modes, parameters) and the pose it is
    placed at, (o_x, o_y, delta): position = o + R(delta) (displacement - its value at the
    first fix), heading = simulated heading + delta. That pose is static, so it is marginalised
    (Rao-Blackwellised): each particle carries its Gaussian, updated in closed form by each fix
    (linearised in delta about its mean at every fix). The particles' displacement, heading,
    speed and turn rate of the last HIST_S seconds are kept, so a fix arriving at step k
    measured at step s weights each particle by its state at s (found through the resampling
    ancestry); out-of-order fixes need nothing else. If two fixes in a row are far from every
    particle's pose (chi-square 99.9 % on position and heading), every pose is re-anchored on the
    newest fix. Outlier fixes:
    the likelihood is the generator's Gaussian / Student-t mixture (share: the middle of the
    behaviour's range), the pose update its moment-matched posterior. Resampling (systematic)
    when the effective sample size falls below n / 2, then a Gibbs move of the mean durations and
    the leg length given each particle's own completed modes (:func:`gibbs_lengths`), Liu-West
    moves (a = 0.98, spread at least LW_FLOOR of the prior range) on the speeds and rates, and
    new mode thresholds given survival (:func:`redraw_threshold`).

    Returns ``est`` and ``mean`` (E, len(EVAL_STEPS), 2): the geometric median and the mean of
    the particles' reference points; ``expected`` (E, len(EVAL_STEPS)): the posterior's mean
    distance to the median (one draw of each particle's pose); ``ess`` (all fixes) the
    effective sample share after each fix; counts of dropped (older than HIST_S), re-anchored
    and out-of-order fixes."""
    H = int(round(HIST_S / DT))
    E = len(ep.seeds)
    B = max(1, min(E, int(chunk_mb * 1e6 / (H * n * 5 * 4))))
    cum = transition_cum(beh)
    eps_pf = 0.5 * (beh.outliers[0] + beh.outliers[1])
    a_lw = 0.98
    est = np.full((E, len(EVAL_STEPS), 2), np.nan)
    mean_est = np.full_like(est, np.nan)
    expected = np.full((E, len(EVAL_STEPS)), np.nan)
    ess_all: list[float] = []
    counts = {"dropped": 0, "rescued": 0, "out_of_order": 0}
    eval_pos = {int(k): i for i, k in enumerate(EVAL_STEPS)}
    for b0 in range(0, E, B):
        eb = list(range(b0, min(E, b0 + B)))
        nb = len(eb)
        rng = np.random.default_rng([n, seed, ep.seeds[eb[0]], zlib.crc32(beh.name.encode())])
        pr = draw_params(beh, rng, (nb, n))
        st = init_state(beh, pr, rng)
        add_stats(st, beh)
        hist = np.zeros((H, nb, n, 5), dtype=np.float32)  # displacement x, y [m], psi, u, r
        anchor = np.zeros((nb, n, 2))  # displacement at the first fix [m]
        mo = np.zeros((nb, n, 3))  # pose mean: o_x, o_y [m], delta [rad]
        Po = np.zeros((nb, n, 3, 3))  # its covariance
        logw = np.zeros((nb, n))
        anchored = np.zeros(nb, bool)
        t_pose = np.zeros(nb, int)  # step of the newest fix the poses have taken
        orphans = np.zeros(nb, int)
        events: list[list[tuple[int, np.ndarray]]] = [[] for _ in range(nb)]
        newest = np.full(nb, -1)
        arrivals: dict[int, list[tuple[int, int]]] = {}
        for j, e in enumerate(eb):
            f = ep.fixes[e]
            for i in np.lexsort((f["send"], f["arr"])):
                arrivals.setdefault(int(f["arr"][i]), []).append((j, int(i)))

        def draw(mask: np.ndarray, rng: np.random.Generator = rng) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            m = int(mask.sum())
            return rng.random(m), rng.standard_gamma(K_DUR, m), rng.random(m)

        for k in range(N_STEPS):
            if k > 0:
                nz = rng.standard_normal((2, nb, n), dtype=np.float32)
                step(st, pr, cum, nz[0], nz[1], draw)
            hist[k % H] = np.stack([st["x"], st["y"], st["psi"], st["u"], st["r"]], -1)
            for j, i in arrivals.get(k, ()):
                e = eb[j]
                f = ep.fixes[e]
                s, z, sig = int(f["send"][i]), f["z"][i], ep.sigma[e] * np.array([1, 1, 1, temper, temper])
                if k - s >= H:
                    counts["dropped"] += 1
                    continue
                if s < newest[j]:
                    counts["out_of_order"] += 1
                newest[j] = max(newest[j], s)
                anc = np.arange(n)
                for ev_step, idx in reversed(events[j]):
                    if ev_step < s:
                        break
                    anc = idx[anc]
                xs = hist[s % H, j][anc].astype(np.float64)  # (n, 5) each particle at the send step
                ll = -0.5 * (((z[3] - xs[:, 3]) / sig[3]) ** 2 + ((z[4] - xs[:, 4]) / sig[4]) ** 2)
                if not anchored[j]:  # position and heading are flat a priori: the fix places every particle
                    anchor[j] = xs[:, :2]
                    mo[j] = np.column_stack([np.full(n, z[0]), np.full(n, z[1]), z[2] - xs[:, 2]])
                    Po[j] = np.diag([sig[0] ** 2, sig[0] ** 2, sig[2] ** 2])
                    anchored[j] = True
                    t_pose[j] = s
                else:
                    # the pose drifts (a random walk): what the particles' path shapes get wrong
                    gap = abs(s - t_pose[j]) * DT
                    t_pose[j] = max(t_pose[j], s)
                    Po[j, :, 0, 0] += pose_drift[0] * sig[0] ** 2 * gap
                    Po[j, :, 1, 1] += pose_drift[0] * sig[0] ** 2 * gap
                    Po[j, :, 2, 2] += pose_drift[1] * sig[2] ** 2 * gap
                    dp = xs[:, :2] - anchor[j]
                    c, sn = np.cos(mo[j, :, 2]), np.sin(mo[j, :, 2])
                    rd = _rot(dp, c, sn)
                    nu = np.column_stack([z[:2] - mo[j, :, :2] - rd, _wrap(z[2] - xs[:, 2] - mo[j, :, 2])])
                    Hm = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
                    Hm[:, 0, 2], Hm[:, 1, 2] = -rd[:, 1], rd[:, 0]
                    R = np.diag([sig[0] ** 2, sig[0] ** 2, sig[2] ** 2])
                    S = Hm @ Po[j] @ np.swapaxes(Hm, 1, 2) + R
                    d2 = np.einsum("ni,nij,nj->n", nu, np.linalg.inv(S), nu)
                    if d2.min() > GATE_POSE:
                        orphans[j] += 1
                        if orphans[j] >= 2:  # lost: re-anchor every particle's pose on this fix
                            mo[j, :, 2] = z[2] - xs[:, 2]
                            c, sn = np.cos(mo[j, :, 2]), np.sin(mo[j, :, 2])
                            rd = _rot(dp, c, sn)
                            mo[j, :, :2] = z[:2] - rd
                            Po[j] = np.diag([sig[0] ** 2, sig[0] ** 2, sig[2] ** 2])
                            Hm[:, 0, 2], Hm[:, 1, 2] = -rd[:, 1], rd[:, 0]
                            counts["rescued"] += 1
                            orphans[j] = 0
                            nu[:] = 0.0
                            S = Hm @ Po[j] @ np.swapaxes(Hm, 1, 2) + R
                    else:
                        orphans[j] = 0
                    Sinv = np.linalg.inv(S)
                    _, logdet = np.linalg.slogdet(S)
                    lin = -0.5 * (np.einsum("ni,nij,nj->n", nu, Sinv, nu) + logdet) - 1.5 * math.log(2 * math.pi)
                    K = Po[j] @ np.swapaxes(Hm, 1, 2) @ Sinv
                    m_in = mo[j] + np.einsum("nij,nj->ni", K, nu)
                    P_in = Po[j] - K @ S @ np.swapaxes(K, 1, 2)
                    if eps_pf > 0:  # inlier or outlier (the outlier's position says nothing; its heading does)
                        sh = S[:, 2, 2]
                        lout = -0.5 * (nu[:, 2] ** 2 / sh + np.log(2 * math.pi * sh)) + _log_t2((nu[:, :2] ** 2).sum(1))
                        lin = math.log1p(-eps_pf) + lin
                        lg = np.logaddexp(lin, math.log(eps_pf) + lout)
                        rho = np.exp(lin - lg)[:, None]
                        kh = Po[j][:, :, 2] / sh[:, None]
                        m_out = mo[j] + kh * nu[:, 2:3]
                        P_out = Po[j] - kh[:, :, None] * kh[:, None, :] * sh[:, None, None]
                        m_new = rho * m_in + (1 - rho) * m_out
                        da, db = m_in - m_new, m_out - m_new
                        Po[j] = (rho[:, :, None] * (P_in + da[:, :, None] * da[:, None, :])
                                 + (1 - rho)[:, :, None] * (P_out + db[:, :, None] * db[:, None, :]))
                        mo[j] = m_new
                        ll = ll + lg
                    else:
                        mo[j], Po[j] = m_in, P_in
                        ll = ll + lin
                    Po[j] = 0.5 * (Po[j] + np.swapaxes(Po[j], 1, 2))
                lw = logw[j] + ll
                w = np.exp(lw - lw.max())
                w /= w.sum()
                ess = 1.0 / np.sum(w * w)
                ess_all.append(ess / n)
                logw[j] = np.log(np.maximum(w, 1e-300))
                if ess < 0.5 * n:
                    idx = np.minimum(np.searchsorted(np.cumsum(w), (rng.random() + np.arange(n)) / n), n - 1)
                    for arr in (*st.values(), anchor, mo, Po):
                        arr[j] = arr[j][idx]
                    for key, arr in pr.items():
                        arr[j] = arr[j][idx]
                        if key in CONT_PARAMS:
                            lo_, hi_ = getattr(beh, CONT_PARAMS[key])
                            # (a floor on the spread: a collapsed parameter would never move again)
                            mu_, sd_ = arr[j].mean(), max(arr[j].std(), LW_FLOOR * (hi_ - lo_))
                            arr[j] = np.clip(a_lw * arr[j] + (1 - a_lw) * mu_
                                             + math.sqrt(1 - a_lw ** 2) * sd_ * rng.standard_normal(n), lo_, hi_)
                    sub = {key: arr[j] for key, arr in st.items()}
                    psub = {key: arr[j] for key, arr in pr.items()}
                    gibbs_lengths(sub, psub, beh, rng)
                    redraw_threshold(sub, psub, rng)
                    st["thr"][j] = sub["thr"]
                    for key in (*_MEAN_KEYS, "leg"):
                        pr[key][j] = psub[key]
                    logw[j] = 0.0
                    events[j].append((k, idx))
                    events[j] = [ev for ev in events[j] if ev[0] > k - H]
            if k in eval_pos and anchored.any():
                sel = np.flatnonzero(anchored)
                dp = np.stack([st["x"][sel], st["y"][sel]], -1) - anchor[sel]

                psi_now = st["psi"][sel]

                def place(pose: np.ndarray, dp: np.ndarray = dp, psi_now: np.ndarray = psi_now) -> np.ndarray:
                    pos = pose[..., :2] + _rot(dp, np.cos(pose[..., 2]), np.sin(pose[..., 2]))
                    return ref_point(pos[..., 0], pos[..., 1], psi_now + pose[..., 2])

                p = place(mo[sel])
                w = np.exp(logw[sel] - logw[sel].max(1, keepdims=True))
                w /= w.sum(1, keepdims=True)
                med, mean = _weiszfeld(p, w)
                rows = [eb[j] for j in sel]
                est[rows, eval_pos[k]] = med
                mean_est[rows, eval_pos[k]] = mean
                if eval_pos[k] % 2 == 0:  # (every other scored step: the expectation is a smooth curve)
                    Lc = np.linalg.cholesky(Po[sel] + 1e-12 * np.eye(3))
                    q = place(mo[sel] + np.einsum("bnij,bnj->bni", Lc, rng.standard_normal(mo[sel].shape)))
                    expected[rows, eval_pos[k]] = np.einsum("bn,bn->b", w, np.hypot(q[..., 0] - med[:, None, 0],
                                                                                     q[..., 1] - med[:, None, 1]))
    return {"est": est, "mean": mean_est, "expected": expected, "ess": np.array(ess_all), **counts}


# --- statistics and the study -----------------------------------------------------------------

def per_episode(est: np.ndarray, ep: Episodes) -> np.ndarray:
    """(E,) mean error norm [m] over the scored steps that have an estimate."""
    return np.nanmean(np.linalg.norm(est - ep.ref, axis=-1), axis=1)


def boot_mean(x: np.ndarray, reps: int = 2000, seed: int = 0) -> tuple[float, float, float]:
    """Mean and 95 % percentile-bootstrap CI over episodes."""
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    idx = np.random.default_rng(seed).integers(0, len(x), (reps, len(x)))
    b = x[idx].mean(1)
    return float(x.mean()), float(np.percentile(b, 2.5)), float(np.percentile(b, 97.5))


def iqm(x: np.ndarray, axis: int = -1) -> np.ndarray:
    """Interquartile mean (the leaderboard's statistic)."""
    return trim_mean(x, 0.25, axis=axis)


def boot_ratio(a: np.ndarray, b: np.ndarray, reps: int = 2000, seed: int = 0,
               stat: Callable[..., np.ndarray] = np.mean) -> tuple[float, float, float]:
    """stat(a) / stat(b) - 1 (stat: mean or IQM over episodes) with a paired 95 % bootstrap CI."""
    ok = np.isfinite(a) & np.isfinite(b)
    a, b = a[ok], b[ok]
    idx = np.random.default_rng(seed).integers(0, len(a), (reps, len(a)))
    r = stat(a[idx], axis=1) / stat(b[idx], axis=1) - 1
    return float(stat(a) / stat(b) - 1), float(np.percentile(r, 2.5)), float(np.percentile(r, 97.5))


def boot_share(g: np.ndarray, m: np.ndarray, f: np.ndarray, reps: int = 2000, seed: int = 0) -> tuple[float, ...]:
    """(mean g - mean m) / (mean g - mean f): the share of the g-to-f gap that m closes, paired CI."""
    ok = np.isfinite(g) & np.isfinite(m) & np.isfinite(f)
    g, m, f = g[ok], m[ok], f[ok]
    idx = np.random.default_rng(seed).integers(0, len(g), (reps, len(g)))
    gb, mb, fb = g[idx].mean(1), m[idx].mean(1), f[idx].mean(1)
    s = (gb - mb) / (gb - fb)
    return float((g.mean() - m.mean()) / (g.mean() - f.mean())), float(np.percentile(s, 2.5)), \
        float(np.percentile(s, 97.5))


def fit_generic(beh: Behaviour, link: Link, seeds: Sequence[int]) -> dict[str, object]:
    """Pick the linear KF's and the IMM's parameters (lowest mean error over the fitting seeds)."""
    ep = make_episodes(beh, link, seeds)
    out = {}
    for name, grid, make in (("linear", KF_GRID, make_kf), ("IMM", IMM_GRID, make_imm)):
        errs, _ = generic_errors(make(grid), ep)
        score = np.nanmean(errs, axis=1)
        best = int(np.nanargmin(score))
        out[name] = {"params": grid[best], "fit_error": float(score[best])}
    return out


def evaluate(beh: Behaviour, link: Link, seeds: Sequence[int], fitted: dict[str, object], n: int,
             both_n: bool = True) -> dict[str, object]:
    """Every estimator on ``seeds``: per-episode errors [m], the PF's diagnostics, link figures
    and the cost [s per episode]."""
    t0 = time.perf_counter()
    ep = make_episodes(beh, link, seeds)
    res: dict[str, object] = {"sim_s": (time.perf_counter() - t0) / len(seeds), "E": len(seeds)}
    errs, cost, diag = {}, {}, {}
    for name, make in (("linear", make_kf), ("IMM", make_imm)):
        t0 = time.perf_counter()
        e, n_ooo = generic_errors(make([fitted[name]["params"]]), ep)
        errs[name], cost[name] = e[0], (time.perf_counter() - t0) / len(seeds)
        res["out_of_order"] = n_ooo
    for nn in ((n, 2 * n) if both_n else (n,)):
        t0 = time.perf_counter()
        pf = run_pf(beh, ep, nn, seed=1)
        cost[f"PF {nn}"] = (time.perf_counter() - t0) / len(seeds)
        errs[f"PF {nn}"] = per_episode(pf["est"], ep)
        errs[f"PF {nn} mean"] = per_episode(pf["mean"], ep)
        errs[f"PF {nn} expected"] = np.nanmean(pf["expected"], axis=1)
        diag[nn] = {k: pf[k] for k in ("ess", "dropped", "rescued", "out_of_order")}
    res.update(errs=errs, cost=cost, diag=diag)
    ages = []  # mean age of the newest received fix at the scored steps [s]
    for f in ep.fixes:
        have = f["arr"][None, :] <= EVAL_STEPS[:, None]
        newest = np.where(have, f["send"][None, :], -1).max(1)
        ages.append(np.mean((EVAL_STEPS - newest)[newest >= 0]) * DT)
    res["age_s"], res["lost"] = float(np.mean(ages)), float(ep.lost_share.mean())
    res["outlier_share"] = float(np.mean(np.concatenate([f["outlier"] for f in ep.fixes])))
    res["fixes_per_ep"] = float(np.mean([len(f["send"]) for f in ep.fixes]))
    return res


def summarise(res: dict[str, object], n: int) -> dict[str, object]:
    """Headline numbers of one evaluation: means with CIs, the best generic (lower mean), the gap
    from it to the PF with the most particles (the floor's estimate), the share of that gap the
    PF with N particles closes, and the IMM's share of the linear-to-floor gap."""
    e = res["errs"]
    best = "linear" if np.nanmean(e["linear"]) <= np.nanmean(e["IMM"]) else "IMM"
    floor = f"PF {2 * n}" if f"PF {2 * n}" in e else f"PF {n}"
    out: dict[str, object] = {name: boot_mean(e[name]) for name in e}
    out["best"], out["floor"] = best, floor
    out["gap"] = boot_ratio(e[best], e[floor])
    best_iqm = "linear" if iqm(e["linear"]) <= iqm(e["IMM"]) else "IMM"
    out["gap_iqm"] = boot_ratio(e[best_iqm], e[floor], stat=iqm)
    out["iqm"] = {name: float(iqm(e[name][np.isfinite(e[name])])) for name in e}
    if floor != f"PF {n}":
        out["share_pf"] = boot_share(e[best], e[f"PF {n}"], e[floor])
        out["n_vs_2n"] = boot_ratio(e[f"PF {n}"], e[floor])
        out["median_vs_mean"] = boot_ratio(e[floor], e[f"{floor} mean"])
        out["realised_vs_expected"] = boot_ratio(e[floor], e[f"{floor} expected"])
    out["share_imm"] = boot_share(e["linear"], e["IMM"], e[floor])
    return out


# --- units of work (cached, so the study can be run in parts) ---------------------------------

CACHE = ROOT / "results" / "tmp" / "leader_study_cache"
#: bump when a change alters results (the cache key includes it)
VERSION = 3


def all_units(tiers: Sequence[str]) -> list[str]:
    """Every unit of the study: one per behaviour mix, one per tier candidate, and the check of
    the proposed Leader-Hard generator on the report seeds."""
    units = [f"mix:{m}" for m in MIXES]
    units += [f"tier:{t}:{c}" for (t, c) in TIER_CANDIDATES if t in tiers]
    if "Hard" in tiers:
        units.append("check:Hard")
    return units


def choose_hard(results: dict[str, dict]) -> str:
    """The proposed Leader-Hard candidate: the mildest (first listed) whose gap from the best
    generic estimator to the PF on the fitting seeds has its lower 95 % bound >= 25 %; if none
    does, the one with the largest gap."""
    cands = [c for (t, c) in TIER_CANDIDATES if t == "Hard"]
    for c in cands:
        if results[f"tier:Hard:{c}"]["summary"]["gap"][1] >= 0.25:
            return c
    return max(cands, key=lambda c: results[f"tier:Hard:{c}"]["summary"]["gap"][0])


def run_unit(unit: str, fit: list[int], rep: list[int], n: int, done: dict[str, dict]) -> dict[str, object]:
    """Compute one unit: fit the generic filters, evaluate every estimator, summarise."""
    t0 = time.perf_counter()
    kind, *rest = unit.split(":")
    if kind == "mix":
        beh, link, seeds, both = MIXES[rest[0]], link_of("Hard"), rep, True
        fitted = fit_generic(beh, link, fit)
    elif kind == "tier":
        link_tier, beh = TIER_CANDIDATES[(rest[0], rest[1])]
        link, seeds, both = link_of(link_tier), fit, rest[0] == "Hard"
        fitted = fit_generic(beh, link, fit)
    elif kind == "check":
        cand = choose_hard(done)
        link_tier, beh = TIER_CANDIDATES[("Hard", cand)]
        link, seeds, both = link_of(link_tier), rep, True
        fitted = done[f"tier:Hard:{cand}"]["fitted"]
    else:
        raise ValueError(f"unknown unit {unit!r}")
    res = evaluate(beh, link, seeds, fitted, n, both_n=both)
    out = {"fitted": fitted, "res": res, "summary": summarise(res, n), "seconds": time.perf_counter() - t0}
    if kind == "check":
        out["candidate"] = cand
    return out


def _key(unit: str, fit: list[int], rep: list[int], n: int) -> str:
    return repr((VERSION, unit, fit, rep, n, PF_TEMPER, PF_POSE_DRIFT, LW_FLOOR, KF_GRID, IMM_GRID))


def load_or_run(units: Sequence[str], fit: list[int], rep: list[int], n: int, recompute: bool,
                wanted: Sequence[str]) -> dict[str, dict]:
    """Results of every unit in ``units`` that is cached with these settings; computes (and
    caches) those in ``wanted`` that are not (or all of ``wanted`` with ``recompute``)."""
    CACHE.mkdir(parents=True, exist_ok=True)
    out: dict[str, dict] = {}
    for unit in units:
        key = _key(unit, fit, rep, n)
        tag = hashlib.sha1(key.encode()).hexdigest()[:10]  # (other settings: another file)
        path = CACHE / (unit.replace(":", "_").replace("+", "-") + f"_{tag}.pkl")
        cached = None
        if path.exists() and not (recompute and unit in wanted):
            with path.open("rb") as fh:
                blob = pickle.load(fh)
            cached = blob["data"] if blob.get("key") == key else None
        if cached is None and unit in wanted:
            cached = run_unit(unit, fit, rep, n, out)
            with path.open("wb") as fh:
                pickle.dump({"key": key, "data": cached}, fh)
            sm = cached["summary"]
            print(f"{unit}: linear {sm['linear'][0]:.3f} IMM {sm['IMM'][0]:.3f} PF {sm[f'PF {n}'][0]:.3f} "
                  f"floor ({sm['floor']}) {sm[sm['floor']][0]:.3f}, gap {sm['gap'][0]:+.1%} "
                  f"({cached['seconds']:.0f} s)", flush=True)
        if cached is not None:
            cached["summary"] = summarise(cached["res"], n)  # (recomputed: the statistics may have changed)
            out[unit] = cached
    return out


# --- the report -------------------------------------------------------------------------------

def _ci(t: tuple[float, float, float], digits: int = 3) -> str:
    return f"{t[0]:.{digits}f} ({t[1]:.{digits}f}-{t[2]:.{digits}f})"


def _pct(t: tuple[float, float, float]) -> str:
    return f"{100 * t[0]:+.0f} % ({100 * t[1]:+.0f} to {100 * t[2]:+.0f})"


def _share(t: tuple[float, float, float]) -> str:
    return f"{100 * t[0]:.0f} % ({100 * t[1]:.0f} to {100 * t[2]:.0f})"


def _fmt_params(name: str, p: tuple) -> str:
    if name == "linear":
        return f"q = {p[0]:g} m^2/s^3, tau = {p[1]:g} s, gate {'on' if p[2] else 'off'}"
    return f"q_u = {p[0]:g} m^2/s^3, q_r = {p[1]:g} rad^2/s^3, q_h = {p[2]:g} rad^2/s, tau_s = {p[3]:g} s"


def _rng(r: tuple[float, float], unit: str = "") -> str:
    return (f"{r[0]:g}" if r[0] == r[1] else f"U[{r[0]:g}, {r[1]:g}]") + (f" {unit}" if unit else "")


def _link_line(lk: Link) -> str:
    return (f"fix every {_rng(lk.period_s, 's')} +- {lk.jitter_s:g} s, {lk.latency_model} latency "
            f"{_rng(lk.latency_s, 's')} (spread {_rng(lk.spread_s, 's')}), i.i.d. loss {_rng(lk.loss)}, "
            f"bursts {lk.p_good_bad:g} / "
            f"{_rng(lk.p_bad_good)} / {lk.loss_bad:g}, fix sigma {_rng(lk.sigma_m, 'm')} + {lk.sigma_per_m:g} x range, "
            f"heading / speed / turn-rate sigma {lk.sigma_psi:g} rad / {lk.sigma_u:g} m/s / {lk.sigma_r:g} rad/s")


def _range_rows(beh: Behaviour) -> list[tuple[str, str]]:
    """(field, value) rows of a behaviour's generator ranges."""
    rows = [("survey share of episodes", f"{beh.p_survey:g}"),
            ("wander modes", "cruise, turn left/right" + (", loiter, sprint" if beh.speed_modes else "")),
            ("cruise speed (also turns, survey)", _rng(beh.v_cruise, "m/s"))]
    if beh.speed_modes:
        rows += [("loiter speed", _rng(beh.v_loiter, "m/s")), ("sprint speed", _rng(beh.v_sprint, "m/s"))]
    rows += [("turn rate", _rng(beh.turn_rate, "rad/s")), ("mean cruise duration", _rng(beh.m_cruise, "s")),
             ("mean turn duration", _rng(beh.m_turn, "s"))]
    if beh.speed_modes:
        rows += [("mean loiter duration", _rng(beh.m_loiter, "s")), ("mean sprint duration", _rng(beh.m_sprint, "s"))]
    if beh.p_survey > 0:
        rows += [("survey leg length", _rng(beh.leg_m, "m") + f" (each leg +- {LEG_JITTER:.0%})"),
                 ("survey U-turn rate", _rng(beh.survey_rate, "rad/s"))]
    rows.append(("outlier share of fixes", _rng(beh.outliers)))
    return rows


def report(results: dict[str, dict], n: int, fit: list[int], rep: list[int], cmd: str, tiers: Sequence[str]) -> str:
    """The Markdown report (summary, tables, proposed ranges, cost)."""
    total = sum(r["seconds"] for r in results.values())
    mixes = [m for m in MIXES if f"mix:{m}" in results]
    sm = {m: results[f"mix:{m}"]["summary"] for m in mixes}
    L = ["# Leader study: room between a generic tracker and a model-aware filter", "",
         f"Reproduce: `{cmd}` ({total / 60:.0f} min of compute in one process; `--units` runs it in parts, "
         f"cached in `results/tmp/leader_study_cache/`). Code and model: `experiments/leader_study.py`. "
         f"A numpy study, not the env. Generic filters fitted on seeds {fit[0]}-{fit[-1]}, tables on seeds "
         f"{rep[0]}-{rep[-1]} unless said otherwise (training seeds, far below the test seeds >= 1,000,000).", ""]
    L += ["## Summary", ""] + summary_lines(results, n, mixes, sm, tiers) + [""]
    hard = link_of("Hard")
    L += ["## Setup", "",
          f"- **Link** (Hard tier's ranges from `auv_follow_env/tiers.py`, drawn per episode): {_link_line(hard)}. "
          "Fixes that arrive after a newer one are delivered.",
          "- **Target**: hidden semi-Markov modes (cruise, turn left/right, loiter, sprint; Gamma(4) durations about "
          "per-episode means) or a survey (legs of similar length, 180-degree turns alternately left and right); speed "
          f"and turn rate follow the mode's command with lags of {TAU_U:g} s and {TAU_R:g} s plus OU wobbles "
          f"({WOBBLE_U[0]:g} m/s, {WOBBLE_R[0]:g} rad/s, {WOBBLE_U[1]:g} s). Outliers: a 2-D Student-t "
          f"({OUTLIER_DOF:g} dof, scale {OUTLIER_SCALE_M:g} m) position error.",
          f"- **Mixes**: base ranges: cruise {_rng(_BASE.v_cruise, 'm/s')} for {_rng(_BASE.m_cruise, 's')}, turns "
          f"{_rng(_BASE.turn_rate, 'rad/s')} for {_rng(_BASE.m_turn, 's')}; speed modes add loiter "
          f"{_rng(_BASE.v_loiter, 'm/s')} ({_rng(_BASE.m_loiter, 's')}) and sprint {_rng(_BASE.v_sprint, 'm/s')} "
          f"({_rng(_BASE.m_sprint, 's')}); survey: legs {_rng(_BASE.leg_m, 'm')}, U-turns "
          f"{_rng(_BASE.survey_rate, 'rad/s')}; outliers: {_rng((0.05, 0.15))} of the fixes.",
          "- **Estimators**: *linear* (KF on position and velocity, OU or constant velocity), *IMM* (constant "
          "velocity + coordinated turn, position gating), both fitted per mix on the fitting seeds over a grid "
          f"({len(KF_GRID)} and {len(IMM_GRID)} settings) and re-run from a fix buffer when a fix arrives out of "
          "order; "
          f"*PF N / PF 2N*: the model-aware particle filter (N = {n}, {2 * n}); its estimate is the particles' "
          "geometric median of the reference point; its own settings (likelihood tempering "
          f"{PF_TEMPER:g} on speed and turn rate, pose drift {PF_POSE_DRIFT[0]:g} / {PF_POSE_DRIFT[1]:g} fix "
          f"variances per second, Liu-West floor {LW_FLOOR:g}) were chosen on seeds 0-15 of three mixes. The "
          "floor is estimated by PF 2N: a realised error of an "
          "estimator that uses only the received fixes, so (up to sampling error) it is an upper bound of the "
          "Bayes floor, and the gaps below are lower bounds of the room.",
          "- **Metric**: per episode the mean over t in [10, 60] s (every 5th step) of the distance between the "
          "estimated and the true present reference point; mean over episodes, 95 % bootstrap CI (paired for gaps "
          "and shares).", ""]
    L += [f"## Per behaviour mix (Hard link, seeds {rep[0]}-{rep[-1]})", "",
          f"| mix | linear [m] | IMM [m] | PF {n} [m] | PF {2 * n} [m] | best generic -> PF {2 * n} | same, IQM | "
          f"PF {n}'s share of that gap | IMM's share of linear -> PF {2 * n} |", "|---" * 9 + "|"]
    for m in mixes:
        s = sm[m]
        L.append(f"| {m} | {_ci(s['linear'])} | {_ci(s['IMM'])} | {_ci(s[f'PF {n}'])} | {_ci(s[f'PF {2 * n}'])} | "
                 f"{s['best']} {_pct(s['gap'])} | {_pct(s['gap_iqm'])} | {_share(s['share_pf'])} | "
                 f"{_share(s['share_imm'])} |")
    L += ["", "Errors: mean over episodes (95 % CI). Gap: mean(best generic) / mean(PF 2N) - 1; IQM: the same with "
          "interquartile means (the leaderboard's statistic; fewer of the episodes where a long loss burst leaves "
          "every estimator metres off). Share: (generic - method) / (generic - PF 2N).", "",
          "### The particle filter's convergence and calibration", "",
          f"| mix | PF {n} vs PF {2 * n} | PF {2 * n} expected [m] | realised vs expected | geometric median vs "
          "mean | ESS after a fix: median / 5th pct [share of N] | re-anchored fixes | fixes / episode | newest fix "
          "age [s] | sends lost | outlier fixes | out-of-order arrivals |", "|---" * 12 + "|"]
    for m in mixes:
        s, r = sm[m], results[f"mix:{m}"]["res"]
        d = r["diag"][2 * n]
        L.append(f"| {m} | {_pct(s['n_vs_2n'])} | {_ci(s[f'PF {2 * n} expected'])} | {_pct(s['realised_vs_expected'])}"
                 f" | {_pct(s['median_vs_mean'])} | {np.median(d['ess']):.2f} / {np.percentile(d['ess'], 5):.3f} | "
                 f"{d['rescued']} | {r['fixes_per_ep']:.1f} | {r['age_s']:.1f} | {r['lost']:.0%} | "
                 f"{r['outlier_share']:.1%} | {r['out_of_order']} |")
    L += ["", "Expected: the PF's own posterior mean distance to its median (what it believes its error is); realised "
          "above expected means it is over-confident. Geometric median vs mean: the realised error of the "
          "particles' median over that of their weighted mean.", "",
          "### Fitted generic settings (fitting seeds)", "", "| mix | linear | IMM |", "|---|---|---|"]
    for m in mixes:
        f = results[f"mix:{m}"]["fitted"]
        L.append(f"| {m} | {_fmt_params('linear', f['linear']['params'])} | {_fmt_params('IMM', f['IMM']['params'])} |")
    edge = [m for m in mixes if results[f"mix:{m}"]["fitted"]["IMM"]["params"][3] == max(p[3] for p in IMM_GRID)]
    if edge:
        L += ["", f"The IMM's switching time sits at the grid's top ({max(p[3] for p in IMM_GRID):g} s) on "
              f"{len(edge)} of {len(mixes)} mixes ({', '.join(edge)}): it prefers rare mode switches; a wider grid "
              "might gain it a little."]
    L += [""] + tier_lines(results, n, fit, rep, tiers)
    L += ["## Cost", "", "Seconds per episode (60 s plus 9 s warm-up at 0.05 s, scored every 5th step), one process, "
          "numpy; the machine was shared with training runs, so the numbers are upper bounds.", "",
          f"| unit | simulate | linear | IMM | PF {n} | PF {2 * n} |", "|---|---|---|---|---|---|"]
    for unit, r in results.items():
        c = r["res"]["cost"]
        p2 = f"{c[f'PF {2 * n}']:.3f}" if f"PF {2 * n}" in c else "-"
        L.append(f"| {unit} | {r['res']['sim_s']:.4f} | {c['linear']:.4f} | {c['IMM']:.4f} | {c[f'PF {n}']:.3f} | "
                 f"{p2} |")
    L += ["", "The fits run the whole grid at once (batched), so a grid search costs little more than one setting.", ""]
    return "\n".join(L)


def summary_lines(results: dict[str, dict], n: int, mixes: list[str], sm: dict, tiers: Sequence[str]) -> list[str]:
    """Plain-words findings, with the numbers filled in from the results."""
    out: list[str] = []
    g = {m: sm[m]["gap"] for m in mixes}
    wander = [m for m in mixes if not m.startswith("survey")]
    survey = [m for m in mixes if m.startswith("survey")]
    if mixes:
        age = np.mean([results[f"mix:{m}"]["res"]["age_s"] for m in mixes])
        lo = min(wander, key=lambda m: g[m][0]) if wander else None
        hi = max(wander, key=lambda m: g[m][0]) if wander else None
        line = (f"- **A target that surveys leaves a lot of room, one that wanders some.** With the newest fix about "
                f"{age:.1f} s old (Hard link), the best generic estimator"
                + (" (the IMM on every mix)" if all(sm[m]["best"] == "IMM" for m in mixes) else "") + " is ")
        if survey:
            line += " and ".join(f"{_pct(g[m])} ({m})" for m in survey) + " above the model-aware PF; "
        if wander:
            line += (f"on wandering targets {100 * g[lo][0]:.0f} % ({lo}) to {100 * g[hi][0]:.0f} % ({hi}). "
                     "Why: the fix reports the target's present speed and turn rate, so what a filter cannot see is "
                     "the mode changes since the fix was sent. Survey legs of similar length make the next U-turn "
                     "predictable for a filter that knows the pattern; a constant-velocity / coordinated-turn IMM "
                     "only sees a turn once it has begun. Wander modes with Gamma(4) durations are only partly "
                     "predictable even when their law is known.")
        out.append(line)
        if any(m + "+outliers" in sm for m in ("turn", "turn+speed", "survey")):
            pairs = [(m, m + "+outliers") for m in ("turn", "turn+speed", "survey")
                     if m in sm and m + "+outliers" in sm]
            out.append("- **Outliers** (5-15 % multipath fixes) cost both sides: the mean error rises by "
                       + ", ".join(f"{100 * (sm[b]['IMM'][0] / sm[a]['IMM'][0] - 1):+.0f} % (IMM) and "
                                   f"{100 * (sm[b][f'PF {2 * n}'][0] / sm[a][f'PF {2 * n}'][0] - 1):+.0f} % (PF) on "
                                   f"{a}" for a, b in pairs)
                       + "; the gap changes to " + ", ".join(f"{_pct(g[b])} ({b})" for _, b in pairs)
                       + (". So outliers do not add room here: the IMM's chi-square gate handles most of them, and "
                          "the PF's heavy-tailed likelihood loses at least as much as the gate does."
                          if all(g[b][0] <= g[a][0] for a, b in pairs) else "."))
        out.append("- **The generic IMM earns its place**: it beats the best-tuned linear filter on every mix and "
                   "closes "
                   + ", ".join(f"{100 * sm[m]['share_imm'][0]:.0f} %" for m in mixes)
                   + " of the linear-to-PF gap (mixes in table order).")
    if "check:Hard" in results:
        ch = results["check:Hard"]
        s = ch["summary"]
        cands = [c for (t, c) in TIER_CANDIDATES if t == "Hard" and f"tier:Hard:{c}" in results]
        fit_txt = "; ".join(f"{c}: {_pct(results[f'tier:Hard:{c}']['summary']['gap'])}" for c in cands)
        out.append(f"- **Leader-Hard as proposed reaches the issue's goal.** On the fitting seeds (gap of the best "
                   f"generic over the PF with {2 * n} particles, mean) {fit_txt}: candidate {ch['candidate']} is the "
                   "mildest whose lower 95 % bound clears 25 %. On the report seeds, which played no part in the "
                   f"choice, its gap is {_pct(s['gap'])} (IQM {_pct(s['gap_iqm'])}).")
    if mixes:
        conv = max(abs(sm[m]["n_vs_2n"][0]) for m in mixes)
        cal = [sm[m]["realised_vs_expected"][0] for m in mixes]
        line = (f"- **The PF floor {'is close to' if conv <= 0.1 else 'is not'} converged on the mixes**: doubling "
                f"its particles from {n} to {2 * n} changes the mean error by at most {100 * conv:.0f} %, and its "
                f"realised error is within {100 * min(cal):+.0f} to {100 * max(cal):+.0f} % of what its posterior "
                f"expects{' (calibrated)' if max(abs(c) for c in cal) <= 0.15 else ''}. ")
        if "check:Hard" in results:
            line += (f"On the proposed Leader-Hard (sharper manoeuvres) PF {n} is still "
                     f"{_pct(results['check:Hard']['summary']['n_vs_2n'])} above PF {2 * n}. ")
        line += ("A PF error is that of an estimator that uses only the received fixes, so the true floor is lower and "
                 "every gap here is a lower bound of the room. Getting there in numpy took a Rao-Blackwellised pose, "
                 "tempered speed / turn-rate likelihoods, a small pose drift, and Gibbs moves of the mode-duration "
                 "and leg-length parameters; without them the bootstrap filter lost track at mode switches.")
        out.append(line)
    weak = [t for t in ("Easy", "Medium") if f"tier:{t}:{_cand(t)}" in results]
    if weak:
        parts = []
        for t in weak:
            s = results[f"tier:{t}:{_cand(t)}"]["summary"]
            parts.append(f"{t} PF {n} {s[f'PF {n}'][0]:.3f} m against IMM {s['IMM'][0]:.3f} m")
        out.append("- **On the Easy and Medium links this PF is not a floor**: " + "; ".join(parts)
                   + ". With fixes every 0.5-2 s and heading / turn-rate noise of 0.01-0.02 rad and 0.002-0.005 rad/s, "
                   "too few particles fall near each fix and the filter re-anchors often. The room on those tiers is "
                   "not measured here (their floor is at most the IMM's error); it needs the issue's numba PF with "
                   "many more particles or a better proposal.")
    if mixes:
        mv = [sm[m]["median_vs_mean"][0] for m in mixes]
        out.append(f"- **Median or mean hardly matters**: the particles' geometric median is {100 * min(mv):+.1f} "
                   f"to {100 * max(mv):+.1f} % against their weighted mean (negative: the median is better, as it "
                   "should be for the mean-norm metric).")
        ooo = sum(results[f"mix:{m}"]["res"]["out_of_order"] for m in mixes)
        out.append(f"- **No fix arrived out of order on the Hard link** ({ooo} in {len(mixes)} x "
                   f"{results[f'mix:{mixes[0]}']['res']['E']} episodes): the latency's spread (0.2-0.5 s) is far "
                   "below the 2-4 s between sends. All three estimators handle out-of-order fixes, but only a test "
                   "(or a link with a wider latency spread) exercises that.")
        c = results[f"mix:{mixes[0]}"]["res"]["cost"]
        out.append(f"- **Cost** (numpy, one process, shared machine): linear {1e3 * c['linear']:.1f} ms, IMM "
                   f"{1e3 * c['IMM']:.1f} ms, PF {c[f'PF {n}']:.2f} s ({n} particles) and {c[f'PF {2 * n}']:.2f} s "
                   f"({2 * n}) per 69 s episode on the Hard link.")
    return out


def _cand(tier: str) -> str:
    """The (single) candidate of a tier other than Hard."""
    return next(c for (t, c) in TIER_CANDIDATES if t == tier)


def tier_lines(results: dict[str, dict], n: int, fit: list[int], rep: list[int], tiers: Sequence[str]) -> list[str]:
    """The Leader-tier proposal: candidates on the fitting seeds, the chosen ranges, the check."""
    cands = [(t, c) for (t, c) in TIER_CANDIDATES if t in tiers and f"tier:{t}:{c}" in results]
    if not cands:
        return []
    L = ["## Proposed generator ranges for the Leader tiers", "",
         f"Each tier keeps the v1 tier's link of the same level. Candidates evaluated on the fitting seeds "
         f"{fit[0]}-{fit[-1]} (generic filters fitted on the same seeds, so the generic side is, if anything, "
         "favoured); the Hard rule: the mildest candidate whose gap's lower 95 % bound is >= 25 %.", "",
         f"| tier | candidate | linear [m] | IMM [m] | PF {n} [m] | PF {2 * n} [m] | best generic -> PF (most "
         f"particles) | same, IQM | PF {n} vs PF {2 * n} |", "|---" * 9 + "|"]
    for t, c in cands:
        s = results[f"tier:{t}:{c}"]["summary"]
        p2 = _ci(s[f"PF {2 * n}"]) if f"PF {2 * n}" in s else "-"
        conv = _pct(s["n_vs_2n"]) if "n_vs_2n" in s else "-"
        L.append(f"| Leader-{t} | {c} | {_ci(s['linear'])} | {_ci(s['IMM'])} | {_ci(s[f'PF {n}'])} | {p2} | "
                 f"{s['best']} {_pct(s['gap'])} | {_pct(s['gap_iqm'])} | {conv} |")
    L += ["", "(A negative gap: the PF is worse than the generic filter, i.e. it is no floor on that link; "
          "see the summary.)"]
    chosen = {t: c for t, c in cands if t != "Hard"}
    if all(f"tier:Hard:{c}" in results for (t, c) in TIER_CANDIDATES if t == "Hard") and "Hard" in tiers:
        chosen["Hard"] = choose_hard(results)
    L += ["", "Proposed ranges (U[a, b]: drawn per episode):", "",
          "| field | " + " | ".join(f"Leader-{t}" for t in chosen) + " |", "|---|" + "---|" * len(chosen)]
    rows = {t: dict(_range_rows(TIER_CANDIDATES[(t, c)][1])) for t, c in chosen.items()}
    fields = list(dict.fromkeys(f for t in chosen for f in rows[t]))
    for f in fields:
        L.append(f"| {f} | " + " | ".join(rows[t].get(f, "-") for t in chosen) + " |")
    L.append("| link | " + " | ".join(f"v1 {TIER_CANDIDATES[(t, c)][0]}" for t, c in chosen.items()) + " |")
    if "check:Hard" in results:
        s = results["check:Hard"]["summary"]
        L += ["", f"Check of the proposed Leader-Hard on seeds {rep[0]}-{rep[-1]} (not used to choose): linear "
              f"{_ci(s['linear'])} m, IMM {_ci(s['IMM'])} m, PF {n} {_ci(s[f'PF {n}'])} m, PF {2 * n} "
              f"{_ci(s[f'PF {2 * n}'])} m; best generic -> PF {2 * n}: {_pct(s['gap'])}."]
    L += ["", "**Why these ranges.** " + WHY, ""]
    return L


WHY = (
    "Each tier keeps the link of the v1 tier of the same level, as the issue asks, and target speeds of the v1 "
    "targets (cruise 0.4-0.6 m/s), so the follower's control problem is unchanged and only the target's behaviour "
    "is new. Every Leader tier draws a survey in half of its episodes and a wandering target in the other half: "
    "the two carry different room (a survey is a regular pattern a model can exploit, wander modes are switches "
    "that are only partly predictable), and a benchmark with only one of them would reward a special-purpose "
    "trick. Difficulty rises from Easy to Hard in every field: faster and shorter turns, shorter cruise phases "
    "and survey legs, speed modes (loiter, sprint) from Medium on, more multipath outliers. On Hard the base "
    "ranges of the study (candidate A) were tried first and the sharper set (candidate B) only if A's gap did "
    "not clear the goal with its lower 95 % bound, on the fitting seeds only; the ranges are chosen so that the "
    "benchmark has room for an estimator that learns the behaviour, and docs/tiers.md should say so. The "
    "sharpest manoeuvre allowed (0.4 rad/s at 0.6 m/s: a 1.5 m turn radius) is still within what a small AUV or "
    "a diver does. Easy and Medium are not tuned for room (this PF cannot measure it on their links); their "
    "ranges sit between no manoeuvres and Hard's."
)


def _parse_seeds(text: str) -> list[int]:
    if "-" in text:
        a, b = text.split("-")
        return list(range(int(a), int(b) + 1))
    return [int(s) for s in text.split(",")]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--fit-seeds", default="0-99", help="seeds to fit the generic filters and choose ranges on")
    parser.add_argument("--report-seeds", default="100-299", help="seeds the tables report")
    parser.add_argument("--particles", type=int, default=1000, help="N: the PF runs with N and 2N particles")
    parser.add_argument("--tiers", default="Easy,Medium,Hard", help="Leader tiers to propose ('' for none)")
    parser.add_argument("--units", default="all",
                        help="units to compute now ('all', or a comma list of: " + ", ".join(all_units(
                            ["Easy", "Medium", "Hard"])) + "); the report is written once every unit is cached")
    parser.add_argument("--recompute", action="store_true", help="recompute the units asked for even if cached")
    parser.add_argument("--out", default=None, help="report path (default: results/leader_study.md)")
    args = parser.parse_args(argv)
    fit = check_training_seeds(_parse_seeds(args.fit_seeds), name="--fit-seeds")
    rep = check_training_seeds(_parse_seeds(args.report_seeds), name="--report-seeds")
    if set(fit) & set(rep):
        parser.error("--fit-seeds and --report-seeds overlap")
    tiers = [t for t in args.tiers.split(",") if t]
    units = all_units(tiers)
    wanted = units if args.units == "all" else [u for u in args.units.split(",") if u]
    bad = [u for u in wanted if u not in units]
    if bad:
        parser.error(f"unknown units {bad}: choose from {units}")
    if "check:Hard" in wanted:  # it needs the Hard candidates
        wanted = list(dict.fromkeys([u for u in units if u.startswith("tier:Hard:")] + wanted))
    results = load_or_run(units, fit, rep, args.particles, args.recompute, wanted)
    missing = [u for u in units if u not in results]
    if missing:
        print(f"not written: units still to compute: {', '.join(missing)} (run with --units ...)")
        return 0
    path = output_path(args, parser, COMMITTED, ignore=("units", "recompute"))
    skip = {"out", "units", "recompute"}
    cmd = "python -m experiments.leader_study" + "".join(
        f" --{k.replace('_', '-')} {v}" for k, v in vars(args).items() if k not in skip and v != parser.get_default(k))
    write_report(path, report(results, args.particles, fit, rep, cmd, tiers))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
