"""Floors per tier: how much is possible.

Two reference scores per v1 tier, per test episode, on the same episodes (same seeds, same
drawn condition, same target path, current, disturbances, plant and thrusters) as the
leaderboard's policies:

* **Control floor** (:func:`control_floor`): the best classical controller (lowest IQM of the
  steady-state error among the scripted controllers evaluated) when the follower hears its
  target over a *perfect link*: every control step it observes the present target exactly,
  as a packet measured on this step, with zero latency, no loss and no fix noise
  (``packet_age = since_arrival = 0``, ``new_packet = has_packet = 1``). Everything else is
  the tier's: thruster lag and rate limit on, current, disturbances, damping mismatch. The
  observation is substituted for the controller only (:func:`perfect_link_observation`); the
  env itself still runs the tier's link, so its generator draws exactly what it draws on the
  real link and the target path is the real episode's. (Setting the equivalent overrides,
  :func:`perfect_link_overrides`, instead changes how many random numbers the link draws
  and hence the target path; ``tests/test_floors.py`` checks that the substituted
  observation equals those overrides on a link that draws none.)
* **Oracle-parameter floor** (:func:`information_floor`; the row :data:`INFORMATION_FLOOR`, named
  "information floor" before 2026-12-07): the expected error of the optimal
  estimate of the present reference point given the packets the follower actually received,
  *with the episode's true parameters* - what no follower knows, so it bounds every follower
  but is not one a follower can reach (docs/benchmark.md, "Floors"): a Kalman filter with the
  target's true Ornstein-Uhlenbeck speed and turn-rate model and fix noise, linearised about
  the true trajectory, run on the actual packet timing (measurement and arrival steps
  recovered from the observations), gives the posterior covariance of the reference point
  at every step; its exact mean norm E||e|| (a zero-mean 2-D Gaussian: elliptic integral) is
  averaged over the steady-state window. Also reported: the *realised* error of an extended
  Kalman filter with the true parameters (linearised about its own estimate) on the same
  packets - what an estimator with perfect knowledge of the model actually achieves.

:func:`floor_episodes` returns the floors as rows of the benchmark's episodes table with
``kind = "reference"`` (not competitors): on a Leader tier the oracle-parameter floor and, where
it converged, the tier-prior floor (:func:`leader_floor` with ``knows="tier"``: the floor of a
follower who knows the tier's generator and published ranges, not the episode's draws).
:func:`add_gap_closed` adds the leaderboard column ``gap_closed`` = (best classical - method) /
(best classical - floor), against the tier-prior floor where there is one, and
``gap_closed_oracle`` against the oracle-parameter floor.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pandas as pd
from numba import njit
from scipy import special

import auv_follow_env  # noqa: F401  (registers the ids)
from agents.benchmark.bayes_floor import (
    DEFAULT_CHILDREN,
    DEFAULT_PARTICLES,
    episode_params,
    fix_ranges,
    packet_sigmas,
    particle_floor_episode,
    tier_prior,
    warmup_start,
)
from auv_follow_env.layout import OBS_INDEX_V1
from auv_follow_env.metrics import tracking_metrics
from auv_follow_env.perfect_link import perfect_link_observation

__all__ = ["CONTROL_FLOOR", "INFORMATION_FLOOR", "LEGACY_LABELS", "REFERENCE_KIND", "DEFAULT_FOLLOWER", "ControlFloor",
           "perfect_link_episodes", "control_floor",
           "record_episodes", "extract_packets", "mean_norm_2d", "delayed_kalman", "information_floor",
           "floor_episodes", "particle_floor_rows", "add_gap_closed", "leader_floor", "TIER_PRIOR_FLOOR",
           "TIER_PRIOR_TIERS", "FLOOR_KNOWS", "leader_bayes_floor", "LEADER_FOLLOWER"]

#: leaderboard labels of the two reference rows
CONTROL_FLOOR = "control floor"
INFORMATION_FLOOR = "oracle-parameter floor"
#: the row's name in benchmark folders written before 2026-12-07 (read back as :data:`INFORMATION_FLOOR`)
LEGACY_LABELS = {"information floor": INFORMATION_FLOOR}
#: the ``kind`` of reference rows in the episodes table and the leaderboard
REFERENCE_KIND = "reference"
#: controller that plays the episodes whose packets the oracle-parameter floor is computed from
#: (the link's timing and losses do not depend on the follower; the fix-noise sigma does, weakly,
#: through the range: sigma = fix_sigma_m + fix_sigma_per_m * range). Ours: the best classical
#: controller of every tier on the committed leaderboard.
DEFAULT_FOLLOWER = "PROPOSED_KF_DOB"
#: controllers left out of the control floor by default (none since the MPC solves all envs in one
#: batched QP: about a minute per tier; kept so a slow controller can be left out again)
SLOW_CONTROLLERS: tuple[str, ...] = ()
#: heading posterior std [rad] above which the floor's linearisation is counted as strained
#: (ours: 1 - E[cos] = 1 - exp(-s^2 / 2) is 3 % of the displacement at s = 0.25 rad)
WIDE_HEADING_RAD = 0.25
#: the recording run's loss threshold [m]: the follower never ends the episode, so every
#: episode's packets cover the full 60 s (the link and the target do not depend on the follower)
RECORD_MAX_DISTANCE_M = 1e4

_I = OBS_INDEX_V1


def _check_tier(tier: object, information: bool = False) -> str:
    """A tier with floors: the control floor for every v1 and Leader tier; the oracle-parameter floor
    (a linear model of the target) for the v1 tiers only."""
    from auv_follow_env.tiers import ALL_TIERS, TIERS

    allowed = TIERS if information else ALL_TIERS
    if not isinstance(tier, str) or tier not in allowed:
        what = ("the oracle-parameter floor exists for the v1 tiers (a Leader tier's target has modes: its floor is "
                "not a linear filter's)") if information else "floors exist for the v1 and Leader tiers"
        raise ValueError(f"tier={tier!r} is invalid: {what} {list(allowed)}")
    return tier


def _check_seeds(seeds: Iterable[int] | None, tier: str) -> list[int]:
    from agents.benchmark.protocol import check_seed_list
    from auv_follow_env.tiers import ALL_TIERS

    if seeds is None:
        return list(ALL_TIERS[tier].test_seeds)
    if isinstance(seeds, (str, bytes)) or not isinstance(seeds, Iterable):
        raise ValueError(f"seeds={seeds!r} is invalid: give a list of integers (None: the tier's published test seeds)")
    seeds = list(seeds)
    if not seeds:
        raise ValueError("seeds is empty: give at least one seed (None: the tier's published test seeds)")
    return check_seed_list(seeds)  # distinct integers in [0, 2**63 - 1]: a repeat would count an episode twice


# --- control floor -----------------------------------------------------------------------





def _rollout(policies: Sequence[Any], names: Sequence[str], env_id: str, seeds: Sequence[int], *,
             perfect: bool, env_kwargs: dict | None = None, record: bool = False, progress: bool = False):
    """Every policy on every seed in one vector env (env p * S + j: policy p, seed j); with
    ``perfect`` each policy sees :func:`perfect_link_observation`. Returns the per-episode rows
    and, with ``record``, the per-step (T + 1, n, .) obs, true target, follower pose, true
    reference and the episode lengths and conditions."""
    from controllers.evaluation import _bar

    S, P = len(seeds), len(policies)
    n = S * P
    venv = gym.make_vec(env_id, num_envs=n, vectorization_mode="vector_entry_point", **(env_kwargs or {}))
    spec = venv.unwrapped.task_spec if hasattr(venv, "unwrapped") else venv.task_spec
    obs, info = venv.reset(seed=[s for _ in range(P) for s in seeds])
    conditions = info.get("condition")
    T = spec.n_steps
    blocks = [slice(p * S, (p + 1) * S) for p in range(P)]
    err = np.full((n, T), np.nan)
    alive = np.ones(n, dtype=bool)
    length = np.full(n, T)
    terminated = np.zeros(n, dtype=bool)
    ret = np.zeros(n)
    rec = None
    if record:
        rec = {"obs": np.zeros((T + 1, n, obs.shape[1]), dtype=np.float32), "target": np.zeros((T + 1, n, 6)),
               "pose": np.zeros((T + 1, n, 3)), "ref": np.zeros((T + 1, n, 3))}

    def store(k: int, o: np.ndarray, inf: dict) -> None:
        if rec is not None:
            rec["obs"][k], rec["target"][k] = o, inf["true_target"]
            rec["pose"][k], rec["ref"][k] = inf["follower_pose"], inf["true_reference"]

    store(0, obs, info)
    start = np.ones(S, dtype=bool)
    actions = np.zeros((n, 3), dtype=np.float32)
    for k in _bar(range(T), f"{P} policies x {S} seeds on {env_id}" + (" (perfect link)" if perfect else ""),
                  progress, nested=True):
        seen = perfect_link_observation(obs, info["true_target"], info["follower_pose"], spec.p_d) if perfect \
            else obs
        for p, blk in enumerate(blocks):
            actions[blk], _ = policies[p].predict(seen[blk], state=None, episode_start=start, deterministic=True)
        start = np.zeros(S, dtype=bool)
        obs, reward, term, trunc, info = venv.step(actions)
        np.copyto(err[:, k], info["tracking_error"], where=alive)
        np.add(ret, reward, out=ret, where=alive)
        store(k + 1, obs, info)
        done = term | trunc
        ended = alive & done
        if ended.any():
            length[ended] = k + 1
            terminated |= ended & term
            alive &= ~ended
            if not alive.any():
                break
    venv.close()
    times = spec.dt * np.arange(1, T + 1)
    rows = []
    for p in range(P):
        for j, seed in enumerate(seeds):
            i = p * S + j
            L = int(length[i])
            m = tracking_metrics(err[i, :L], times[:L], spec.steady_start_s)
            rows.append({"policy": names[p], "seed": int(seed), "steps": L, "terminated": bool(terminated[i]),
                         "return": float(ret[i]), **{f"true_{key}": v for key, v in m.items()}})
    out = pd.DataFrame(rows)
    if record:
        rec.update(length=length, conditions=conditions, spec=spec)
        return out, rec
    return out


def perfect_link_episodes(tier: str, seeds: Iterable[int] | None = None, controllers: Sequence[str] | None = None,
                          *, progress: bool = False) -> pd.DataFrame:
    """Per-episode scores of scripted controllers on a tier's episodes with a perfect link.

    Args:
        tier: a v1 tier name (``"Easy"`` ... ``"Extreme"``).
        seeds: episode seeds (None: the tier's published test seeds).
        controllers: controller names (None: ``controllers.ALL_CONTROLLERS`` without
            :data:`SLOW_CONTROLLERS`), each built for the tier's own task spec.

    Returns:
        one row per (controller, seed): policy, seed, steps, terminated, return, ``true_*``.
    """
    import controllers as ctl

    tier = _check_tier(tier)
    seeds = _check_seeds(seeds, tier)
    names = [c for c in ctl.ALL_CONTROLLERS if c not in SLOW_CONTROLLERS] if controllers is None else list(controllers)
    bad = [c for c in names if c not in ctl.ALL_CONTROLLERS]
    if bad or not names:
        raise ValueError(f"controllers={controllers!r} is invalid: give names from {list(ctl.ALL_CONTROLLERS)}")
    env_id = f"AUVFollow-{tier}-v1"
    probe = gym.make(env_id)
    spec = probe.unwrapped.task_spec
    probe.close()
    return _rollout([ctl.make_controller(c, spec) for c in names], names, env_id, seeds, perfect=True,
                    progress=progress)


@dataclass
class ControlFloor:
    """What :func:`control_floor` returns."""

    tier: str
    best: str  #: the controller with the lowest steady-state IQM on the perfect link
    episodes: pd.DataFrame  #: every controller's per-episode rows (perfect link)
    iqm: dict[str, float]  #: steady-state IQM per controller [m]

    @property
    def scores(self) -> pd.DataFrame:
        """The best controller's per-episode rows: the control floor of each episode."""
        return self.episodes[self.episodes["policy"] == self.best].reset_index(drop=True)


def control_floor(tier: str, seeds: Iterable[int] | None = None, controllers: Sequence[str] | None = None, *,
                  progress: bool = False) -> ControlFloor:
    """The control floor of a tier: the best classical controller (lowest IQM of the
    steady-state true-reference error, a terminated episode scoring the loss threshold) on the
    tier's episodes with a perfect link (:func:`perfect_link_episodes`)."""
    from agents.benchmark.stats import iqm

    eps = perfect_link_episodes(tier, seeds, controllers, progress=progress)
    score = eps["true_steady_mean"].where(~eps["terminated"], _max_distance())
    table = {str(p): float(iqm(score[eps["policy"] == p].to_numpy())) for p in dict.fromkeys(eps["policy"])}
    best = min(table, key=table.get)
    return ControlFloor(tier=tier, best=best, episodes=eps, iqm=table)


def _max_distance() -> float:
    from auv_follow_env.params import EnvConfig

    return float(EnvConfig.__dataclass_fields__["max_distance_m"].default)


# --- oracle-parameter floor -------------------------------------------------------------------

def mean_norm_2d(cov: np.ndarray) -> np.ndarray:
    """E||e|| of zero-mean 2-D Gaussians with covariances ``cov`` (..., 2, 2), exactly:
    with eigenvalues l1 >= l2 >= 0, E||e|| = sqrt(2 l1 / pi) E(1 - l2 / l1), E the complete
    elliptic integral of the second kind (parameter m = k^2). Checks: l1 = l2 = s^2 gives the
    Rayleigh mean s sqrt(pi / 2); l2 = 0 the half-normal mean s sqrt(2 / pi). NaN in, NaN out."""
    c = np.asarray(cov, dtype=np.float64)
    a, b, d = c[..., 0, 0], 0.5 * (c[..., 0, 1] + c[..., 1, 0]), c[..., 1, 1]
    mid, rad = 0.5 * (a + d), np.sqrt((0.5 * (a - d)) ** 2 + b * b)
    l1 = np.maximum(mid + rad, 0.0)
    l2 = np.clip(mid - rad, 0.0, None)
    with np.errstate(invalid="ignore", divide="ignore"):
        m = np.where(l1 > 0, 1.0 - l2 / np.where(l1 > 0, l1, 1.0), 0.0)
    return np.sqrt(2.0 * l1 / np.pi) * special.ellipe(np.clip(m, 0.0, 1.0))


@njit(cache=True)
def _unicycle(x, F, par):
    """One control step of the target model (mean in place) and its Jacobian F:
    psi += R dt; (x, y) += U dt (cos, sin)(psi + R dt / 2) sinc(R dt / 2) (the exact arc of a step
    with U, R held, the env's zero-order hold); U = v_bar + a_u (U - v_bar); R = a_r R.
    U and R enter the kinematics clipped to the target's bounds (par = dt, v_bar, a_u, a_r,
    u_min, u_max, r_max)."""
    dt, vbar, au, ar, ulo, uhi, rmax = par[0], par[1], par[2], par[3], par[4], par[5], par[6]
    u = min(max(x[3], ulo), uhi)
    r = min(max(x[4], -rmax), rmax)
    du = 1.0 if (x[3] > ulo and x[3] < uhi) else 0.0
    dr = 1.0 if (x[4] > -rmax and x[4] < rmax) else 0.0
    h = 0.5 * r * dt
    sinc = 1.0 - h * h / 6.0 if abs(h) < 1e-4 else math.sin(h) / h
    pm = x[2] + h
    c = math.cos(pm)
    s = math.sin(pm)
    n = F.shape[0]
    for i in range(n):
        for j in range(n):
            F[i, j] = 1.0 if i == j else 0.0
    F[0, 2] = -u * dt * s
    F[0, 3] = dt * c * du
    F[0, 4] = -u * dt * s * 0.5 * dt * dr
    F[1, 2] = u * dt * c
    F[1, 3] = dt * s * du
    F[1, 4] = u * dt * c * 0.5 * dt * dr
    F[2, 4] = dt * dr
    F[3, 3] = au
    F[4, 4] = ar
    x[0] += u * dt * c * sinc
    x[1] += u * dt * s * sinc
    x[2] += r * dt
    x[3] = vbar + au * (x[3] - vbar)
    x[4] = ar * x[4]


@njit(cache=True)
def _predict(mode, i, x, P, F, Q, par, Fk):
    if mode == 0:
        Fk[:, :] = F[i]
        x[:] = Fk @ x
    else:
        _unicycle(x, Fk, par)
    Pn = Fk @ P @ Fk.T + Q[i]
    P[:, :] = 0.5 * (Pn + Pn.T)


@njit(cache=True)
def _update(x, P, z, H, R, wrap):
    y = z - H @ x
    for r in range(y.shape[0]):
        if wrap[r]:
            y[r] = (y[r] + math.pi) % (2.0 * math.pi) - math.pi
    S = H @ P @ H.T + R
    K = P @ H.T @ np.linalg.inv(S)
    x += K @ y
    IKH = np.eye(P.shape[0]) - K @ H
    Pn = IKH @ P @ IKH.T + K @ R @ K.T
    P[:, :] = 0.5 * (Pn + Pn.T)


@njit(cache=True)
def _delayed_filter(mode, k0, T, F, Q, par, meas, arr, Z, H, R, wrap, x0, P0, J, pd, est, cov, hvar):
    n = x0.shape[0]
    M = meas.shape[0]
    xs = np.empty((max(M, 1), n))
    Ps = np.empty((max(M, 1), n, n))
    x = x0.copy()
    P = P0.copy()
    Fk = np.eye(n)
    k = meas[0] if M > 0 else T
    for j in range(M):  # the filter on the measurement clock: every received packet in order
        while k < meas[j]:
            _predict(mode, k - k0, x, P, F, Q, par, Fk)
            k += 1
        _update(x, P, Z[j], H[j], R[j], wrap)
        xs[j] = x
        Ps[j] = P
    cur = -1
    kk = 0
    for t in range(1, T + 1):  # the estimate at step t from the packets that arrived by step t - 1
        jn = cur
        while jn + 1 < M and arr[jn + 1] <= t - 1:
            jn += 1
        if jn < 0:
            continue
        if jn != cur:
            cur = jn
            x[:] = xs[jn]
            P[:, :] = Ps[jn]
            kk = meas[jn]
        while kk < t:
            _predict(mode, kk - k0, x, P, F, Q, par, Fk)
            kk += 1
        if mode == 0:
            Jt = J[t]
            est[t] = Jt @ x
        else:
            c = math.cos(x[2])
            s = math.sin(x[2])
            Jt = np.zeros((2, n))
            Jt[0, 0] = 1.0
            Jt[1, 1] = 1.0
            Jt[0, 2] = -s * pd[0] - c * pd[1]
            Jt[1, 2] = c * pd[0] - s * pd[1]
            est[t, 0] = x[0] + c * pd[0] - s * pd[1]
            est[t, 1] = x[1] + s * pd[0] + c * pd[1]
        cov[t] = Jt @ P @ Jt.T
        if n > 2:
            hvar[t] = P[2, 2]  # (the heading's variance in the target model)


def delayed_kalman(F: np.ndarray, Q: np.ndarray, k0: int, T: int, meas: np.ndarray, arr: np.ndarray,
                   Z: np.ndarray, H: np.ndarray, R: np.ndarray, x0: np.ndarray, P0: np.ndarray, J: np.ndarray,
                   wrap: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Kalman filter of a linear (time-varying) model with delayed packets.

    The state at control step k (k0 <= k <= T) moves as x_{k+1} = F[k - k0] x_k + w_k,
    w_k ~ N(0, Q[k - k0]). Packet j measures z_j = H[j] x_{meas[j]} + v_j, v_j ~ N(0, R[j]), and
    becomes known at step ``arr[j]`` (both increasing in j, as the packets a follower accepts).
    The estimate at step t (1 <= t <= T) uses the packets with arr <= t - 1 (what a follower
    has when it chooses the action that moves it to step t): the filter at the newest such
    packet's measurement step, predicted to t.

    Args:
        F, Q: (T - k0, n, n). meas, arr: (M,) int steps. Z: (M, m). H: (M, m, n). R: (M, m, m).
        x0, P0: prior mean and covariance at step meas[0]. J: (T + 1, 2, n) the reference point
            J[t] x_t. wrap: (m,) bool, innovation components wrapped to [-pi, pi).

    Returns:
        (est, cov): (T + 1, 2) the estimated reference point and (T + 1, 2, 2) its posterior
        covariance at each step (NaN before the first packet has arrived and at t = 0).
    """
    n = int(np.asarray(x0).shape[0])
    m = int(np.asarray(Z).shape[1]) if np.asarray(Z).ndim == 2 else 1
    if np.asarray(F).shape != (T - k0, n, n) or np.asarray(Q).shape != (T - k0, n, n):
        raise ValueError(f"F and Q must have shape {(T - k0, n, n)}, got {np.shape(F)} and {np.shape(Q)}")
    meas = np.asarray(meas, dtype=np.int64)
    arr = np.asarray(arr, dtype=np.int64)
    if meas.shape != arr.shape or (meas.size and (np.any(np.diff(meas) <= 0) or np.any(np.diff(arr) < 0)
                                                 or np.any(arr < meas) or meas[0] < k0)):
        raise ValueError("meas and arr must be increasing step indices with arr >= meas >= k0")
    est = np.full((T + 1, 2), np.nan)
    cov = np.full((T + 1, 2, 2), np.nan)
    wrap = np.zeros(m, dtype=np.bool_) if wrap is None else np.asarray(wrap, dtype=np.bool_)
    _delayed_filter(0, int(k0), int(T), np.ascontiguousarray(F, dtype=np.float64),
                    np.ascontiguousarray(Q, dtype=np.float64), np.zeros(7), meas, arr,
                    np.ascontiguousarray(Z, dtype=np.float64), np.ascontiguousarray(H, dtype=np.float64),
                    np.ascontiguousarray(R, dtype=np.float64), wrap, np.asarray(x0, dtype=np.float64).copy(),
                    np.asarray(P0, dtype=np.float64).copy(), np.ascontiguousarray(J, dtype=np.float64),
                    np.zeros(2), est, cov, np.full(T + 1, np.nan))
    return est, cov


def record_episodes(tier: str, seeds: Iterable[int] | None = None, follower: str = DEFAULT_FOLLOWER, *,
                    progress: bool = False, overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """Play a tier's episodes with ``follower`` on the real link and keep, per step 0..T,
    the observations, true target, follower pose and true reference (``obs``, ``target``,
    ``pose``, ``ref``: (T + 1, n, .)), with ``length``, ``conditions``, ``spec``, ``seeds`` and
    the follower's per-episode rows (``episodes``). ``overrides``: condition fields for the
    env (``gym.make(env_id, **overrides)``; for studies and tests, never the leaderboard)."""
    import controllers as ctl

    tier = _check_tier(tier)
    seeds = _check_seeds(seeds, tier)
    if follower not in ctl.ALL_CONTROLLERS:
        raise ValueError(f"follower={follower!r} is invalid: must be one of {list(ctl.ALL_CONTROLLERS)}")
    env_id = f"AUVFollow-{tier}-v1"
    probe = gym.make(env_id, **(overrides or {}))
    spec = probe.unwrapped.task_spec
    probe.close()
    eps, rec = _rollout([ctl.make_controller(follower, spec)], [follower], env_id, seeds, perfect=False, record=True,
                        env_kwargs={**(overrides or {}), "max_distance_m": RECORD_MAX_DISTANCE_M}, progress=progress)
    # the benchmark's score of the follower: an episode that went beyond the tier's loss threshold
    # counts as terminated there (the recording ran on to 60 s)
    lost = eps["true_full_max"] > _max_distance()
    eps.loc[lost, "terminated"] = True
    rec.update(seeds=seeds, episodes=eps, tier=tier, follower=follower)
    return rec


def extract_packets(obs: np.ndarray, pose: np.ndarray, dt: float) -> dict[str, np.ndarray]:
    """The packets a follower received in one episode, from its observations.

    Args:
        obs: (L + 1, 20) v1 observations of steps 0..L.
        pose: (L + 1, 3) the follower's pose at the same steps (to put the relative fix into the
            world frame).
        dt: control step [s].

    Returns:
        ``meas`` and ``arr`` (M,) measurement and arrival steps (the packet held at reset
        counts, with its age; afterwards every step with ``new_packet`` = 1), ``z`` (M, 5)
        the received fix in the world frame: x, y, psi, u, r (the reported sway, pure noise
        about the target's v = 0, carries no information and is left out).
    """
    o = np.asarray(obs, dtype=np.float64)
    ps = np.asarray(pose, dtype=np.float64)
    steps = np.arange(len(o))
    has = o[:, _I["has_packet"]] > 0.5
    take = has & ((o[:, _I["new_packet"]] > 0.5) | (steps == 0))
    idx = np.flatnonzero(take)
    age = np.rint(o[idx, _I["packet_age"]] / dt).astype(np.int64)
    since = np.rint(o[idx, _I["since_arrival"]] / dt).astype(np.int64)
    meas, arr = idx - age, idx - since
    c, s = np.cos(ps[idx, 2]), np.sin(ps[idx, 2])
    dx, dy = o[idx, _I["target_dx"]], o[idx, _I["target_dy"]]
    z = np.column_stack([ps[idx, 0] + c * dx - s * dy, ps[idx, 1] + s * dx + c * dy,
                         ps[idx, 2] + np.arctan2(o[idx, _I["target_sin_dpsi"]], o[idx, _I["target_cos_dpsi"]]),
                         o[idx, _I["target_u"]], o[idx, _I["target_r"]]])
    return {"meas": meas, "arr": arr, "z": z}


def _episode_floor(target: np.ndarray, pose: np.ndarray, ref: np.ndarray, obs: np.ndarray, L: int,
                   cond: dict[str, float], dt: float, p_d: Sequence[float], steady_start: float) -> dict[str, float]:
    """Expected (linearised about the truth) and realised (EKF) estimation error of one episode."""
    pk = extract_packets(obs[:L + 1], pose[:L + 1], dt)
    meas, arr, z = pk["meas"], pk["arr"], pk["z"]
    vbar = float(cond["target_speed"])
    su, sr = float(cond["target_speed_std"]), float(cond["target_yaw_rate_std"])
    au = math.exp(-dt / float(cond["target_speed_corr_s"]))
    ar = math.exp(-dt / float(cond["target_yaw_rate_corr_s"]))
    rmax = float(cond["target_yaw_rate_max"])
    par = np.array([dt, vbar, au, ar, float(cond["target_speed_min"]), float(cond["target_speed_max"]), rmax])
    k0 = int(min(0, meas.min())) if meas.size else 0
    # the true trajectory at steps k0..L (before t = 0: held back from step 0 with its u and r)
    kk = np.arange(k0, L + 1)
    psi = np.empty(len(kk))
    u = np.empty(len(kk))
    r = np.empty(len(kk))
    neg = kk < 0
    psi[~neg], u[~neg], r[~neg] = target[:L + 1, 2], target[:L + 1, 3], target[:L + 1, 5]
    psi[neg] = target[0, 2] + target[0, 5] * kk[neg] * dt
    u[neg], r[neg] = target[0, 3], target[0, 5]
    # Jacobians along the true trajectory (the linear model of the unclipped OU processes)
    h = 0.5 * r[:-1] * dt
    pm = psi[:-1] + h
    c, s = np.cos(pm), np.sin(pm)
    N = len(kk) - 1
    F = np.tile(np.eye(5), (N, 1, 1))
    uu = u[:-1]
    F[:, 0, 2], F[:, 0, 3], F[:, 0, 4] = -uu * dt * s, dt * c, -uu * dt * s * 0.5 * dt
    F[:, 1, 2], F[:, 1, 3], F[:, 1, 4] = uu * dt * c, dt * s, uu * dt * c * 0.5 * dt
    F[:, 2, 4], F[:, 3, 3], F[:, 4, 4] = dt, au, ar
    q = np.zeros((5, 5))
    q[3, 3], q[4, 4] = (1.0 - au * au) * su * su, (1.0 - ar * ar) * sr * sr
    Q = np.broadcast_to(q, (N, 5, 5))
    # fix noise of each packet: sigma = fix_sigma_m + fix_sigma_per_m * range. The floor takes the
    # range of a follower on the reference point, |p_d| (independent of how a policy tracks); the
    # realised EKF the range at the packet's measurement (the noise the packet really has)
    mi = np.clip(meas, 0, L)
    actual = np.hypot(target[mi, 0] - pose[mi, 0], target[mi, 1] - pose[mi, 1])

    def noise(rng: np.ndarray) -> np.ndarray:
        sig = float(cond["fix_sigma_m"]) + float(cond["fix_sigma_per_m"]) * rng
        Rm = np.zeros((len(meas), 5, 5))
        Rm[:, 0, 0] = Rm[:, 1, 1] = sig ** 2
        Rm[:, 2, 2] = float(cond["heading_sigma_rad"]) ** 2
        Rm[:, 3, 3] = float(cond["velocity_sigma_mps"]) ** 2
        Rm[:, 4, 4] = float(cond["yaw_rate_sigma_radps"]) ** 2
        Rm[:, range(5), range(5)] += 1e-12  # (a zero sigma: the update stays defined)
        return Rm

    R_floor = noise(np.full(len(meas), math.hypot(float(p_d[0]), float(p_d[1]))))
    R_real = noise(actual)
    H = np.broadcast_to(np.eye(5), (len(meas), 5, 5))
    wrap = np.array([False, False, True, False, False])
    P0 = np.diag([100.0, 100.0, 10.0, su * su + 1e-12, sr * sr + 1e-12])
    ct, st = np.cos(target[:L + 1, 2]), np.sin(target[:L + 1, 2])
    pdx, pdy = float(p_d[0]), float(p_d[1])
    J = np.zeros((L + 1, 2, 5))
    J[:, 0, 0] = J[:, 1, 1] = 1.0
    J[:, 0, 2], J[:, 1, 2] = -st * pdx - ct * pdy, ct * pdx - st * pdy
    x0 = np.array([z[0, 0], z[0, 1], z[0, 2], vbar, 0.0]) if len(meas) else np.array([0.0, 0.0, 0.0, vbar, 0.0])
    est0 = np.full((L + 1, 2), np.nan)
    cov0 = np.full((L + 1, 2, 2), np.nan)
    ms, ar_ = np.asarray(meas, np.int64), np.asarray(arr, np.int64)
    H, zc, Qc = np.ascontiguousarray(H), np.ascontiguousarray(z), np.ascontiguousarray(Q)
    hvar = np.full(L + 1, np.nan)
    _delayed_filter(0, k0, L, np.ascontiguousarray(F), Qc, par, ms, ar_, zc, H, R_floor, wrap, x0, P0, J,
                    np.zeros(2), est0, cov0, hvar)
    est1 = np.full((L + 1, 2), np.nan)
    cov1 = np.full((L + 1, 2, 2), np.nan)
    _delayed_filter(1, k0, L, np.zeros((N, 5, 5)), Qc, par, ms, ar_, zc, H, R_real, wrap, x0, P0, J,
                    np.array([pdx, pdy]), est1, cov1, np.full(L + 1, np.nan))
    times = dt * np.arange(1, L + 1)
    expected = mean_norm_2d(cov0[1:])
    realised = np.hypot(est1[1:, 0] - ref[1:L + 1, 0], est1[1:, 1] - ref[1:L + 1, 1])
    steady = times >= steady_start - 1e-9
    have = steady & np.isfinite(expected)
    clipped = np.abs(target[1:L + 1, 5]) >= rmax - 1e-12
    nan = math.nan
    return {"expected_steady_mean": float(expected[have].mean()) if have.any() else nan,
            "expected_full_mean": float(np.nanmean(expected)) if np.isfinite(expected).any() else nan,
            "realised_steady_mean": float(realised[have].mean()) if have.any() else nan,
            "realised_full_mean": float(np.nanmean(realised)) if np.isfinite(realised).any() else nan,
            "packets": int(len(meas)), "steady_steps_without_packet": int((steady & ~have).sum()),
            "clipped_turn_share": float(clipped.mean()),
            "wide_heading_share": float((hvar[1:][have] > WIDE_HEADING_RAD ** 2).mean()) if have.any() else nan,
            "mean_packet_age_s": float(obs[1:L + 1, _I["packet_age"]][obs[1:L + 1, _I["has_packet"]] > 0.5].mean())
            if (obs[1:L + 1, _I["has_packet"]] > 0.5).any() else nan}


def information_floor(tier: str, seeds: Iterable[int] | None = None, follower: str = DEFAULT_FOLLOWER, *,
                      progress: bool = False, recording: dict[str, Any] | None = None) -> pd.DataFrame:
    """The oracle-parameter floor of each episode of a tier (see the module docstring and
    docs/benchmark.md, "Floors").

    Args:
        tier: a v1 tier name.
        seeds: episode seeds (None: the tier's published test seeds).
        follower: the controller that plays the episodes (:data:`DEFAULT_FOLLOWER`).
        recording: a :func:`record_episodes` result to reuse (then ``seeds``/``follower`` are its).

    Returns:
        one row per seed: ``expected_steady_mean`` / ``expected_full_mean`` (the floor: mean over
        the window of E||e|| of the reference point's posterior), ``realised_steady_mean`` /
        ``realised_full_mean`` (the EKF's actual error), ``packets``,
        ``steady_steps_without_packet`` (steady-state steps before any packet arrived: left out
        of both means), ``clipped_turn_share`` (share of steps with the turn rate at its clip,
        where the linear model is wrong), ``wide_heading_share`` (share of the steady-state steps
        whose heading posterior std exceeds :data:`WIDE_HEADING_RAD`, where the linearisation
        strains), ``mean_packet_age_s``.

    The floor's fix-noise sigma is that of a follower on the reference point (range |p_d|);
    the realised EKF uses each packet's true sigma (the follower's actual range).
    """
    if recording is None:
        _check_tier(tier, information=True)
    rec = recording if recording is not None else record_episodes(tier, seeds, follower, progress=progress)
    spec = rec["spec"]
    rows = []
    for j, seed in enumerate(rec["seeds"]):
        cond = {k: v[j] for k, v in rec["conditions"].items()}
        L = int(rec["length"][j])
        row = _episode_floor(rec["target"][:, j], rec["pose"][:, j], rec["ref"][:, j], rec["obs"][:, j], L, cond,
                             spec.dt, spec.p_d, spec.steady_start_s)
        rows.append({"seed": int(seed), "steps": L, **row})
    return pd.DataFrame(rows)


# --- leaderboard integration -------------------------------------------------------------

def floor_episodes(tier: str, seeds: Iterable[int] | None = None, *, controllers: Sequence[str] | None = None,
                   follower: str = DEFAULT_FOLLOWER, progress: bool = False,
                   cache_dir: str | Path | None = None, tier_prior: bool = True) -> pd.DataFrame:
    """The floors of a tier as rows of the benchmark's episodes table (``kind`` =
    :data:`REFERENCE_KIND`; policy :data:`CONTROL_FLOOR` with ``run`` = the best controller,
    and :data:`INFORMATION_FLOOR` with ``run`` = ``"kalman"`` on a v1 tier, the particle filter
    of :mod:`agents.benchmark.bayes_floor` on a Leader tier, its rows cached in ``cache_dir``
    if given; on the Leader tiers of :data:`TIER_PRIOR_TIERS` with ``tier_prior`` also
    :data:`TIER_PRIOR_FLOOR`, about 25-30 minutes per tier of 100 seeds on 2 cores), with the drawn
    condition (``cond_*``) and the loss threshold like :func:`agents.benchmark.evaluate_tier`'s rows.
    The oracle-parameter floors' ``true_*_mean`` are the expected errors, the tier-prior floor's
    its realised errors (what a follower running that filter reaches); their other metrics are NaN."""
    tier = _check_tier(tier)
    seeds = _check_seeds(seeds, tier)
    cf = control_floor(tier, seeds, controllers, progress=progress)
    ctrl = cf.scores.copy()
    ctrl["policy"] = CONTROL_FLOOR
    ctrl["run"] = cf.best
    frames = [ctrl]
    from auv_follow_env.tiers import TIERS

    if tier in TIERS:
        inf = information_floor(tier, seeds, follower, progress=progress)
        frames.append(_floor_rows(INFORMATION_FLOOR, "kalman", inf))
    else:  # a Leader tier: the particle filter under the true generator (agents/benchmark/bayes_floor.py)
        frames += [_particle_floor_frame(tier, seeds, knows, cache_dir, progress)
                   for knows in (("episode", "tier") if tier_prior and tier in TIER_PRIOR_TIERS else ("episode",))]
    return _reference_table(tier, seeds, frames)


def particle_floor_rows(tier: str, seeds: Iterable[int] | None = None, knows: str = "episode", *,
                        cache_dir: str | Path | None = None, progress: bool = False) -> pd.DataFrame:
    """One particle floor of a Leader tier (:func:`leader_floor` with its default settings; None
    seeds: the published test seeds) as reference rows of the benchmark's episodes table, like
    :func:`floor_episodes`'s: policy ``FLOOR_KNOWS[knows]``."""
    if knows not in FLOOR_KNOWS:
        raise ValueError(f"knows={knows!r} is invalid: must be one of {list(FLOOR_KNOWS)}")
    tier = _check_tier(tier)
    seeds = _check_seeds(seeds, tier)
    return _reference_table(tier, seeds, [_particle_floor_frame(tier, seeds, knows, cache_dir, progress)])


def _particle_floor_frame(tier: str, seeds: Sequence[int], knows: str, cache_dir: str | Path | None,
                          progress: bool) -> pd.DataFrame:
    df = leader_floor(tier, seeds, knows=knows, cache_dir=None if cache_dir is None else str(cache_dir),
                      progress=progress)
    if knows == "tier":  # its realised error: the posterior can collapse onto wrong parameters and
        # then reports an expected error far below the truth (8 Leader-Easy test episodes: 0.007 m
        # expected, up to 4 m realised); the realised error is what a follower running it reaches
        run = (f"particle filter, {TIER_PRIOR_PARTICLES} particles, the tier's parameter law as prior, "
               f"Liu-West a = {TIER_PRIOR_SHRINK:g}; realised error")
        return _floor_rows(FLOOR_KNOWS[knows], run, df, "realised")
    return _floor_rows(FLOOR_KNOWS[knows], f"particle filter, {DEFAULT_PARTICLES} particles", df)


def _floor_rows(policy: str, run: str, inf: pd.DataFrame, which: str = "expected") -> pd.DataFrame:
    """A floor's per-episode table as episode rows: its ``{which}_steady_mean`` / ``_full_mean``
    as the true-reference errors."""
    return pd.DataFrame({"policy": policy, "run": run, "seed": inf["seed"], "steps": inf["steps"],
                         "terminated": False, "return": np.nan, "true_steady_mean": inf[f"{which}_steady_mean"],
                         "true_full_mean": inf[f"{which}_full_mean"]})


def _reference_table(tier: str, seeds: Sequence[int], frames: list[pd.DataFrame]) -> pd.DataFrame:
    """Reference rows with the columns of the benchmark's episodes table."""
    from agents.benchmark.protocol import _condition_columns
    from agents.benchmark.protocol import _max_distance as bench_max_distance

    env_id = f"AUVFollow-{tier}-v1"
    df = pd.concat(frames, ignore_index=True)
    for m in ("full_mean", "full_rmse", "full_max", "steady_mean", "steady_rmse", "steady_max"):
        if f"true_{m}" not in df:
            df[f"true_{m}"] = np.nan
        df[f"own_{m}"] = np.nan
    df.insert(0, "env_id", env_id)
    df.insert(0, "tier", tier)
    probe = gym.make(env_id)
    spec = probe.unwrapped.task_spec
    probe.close()
    df["scenario"], df["disturbance"] = spec.scenario, spec.disturbance
    df["kind"] = REFERENCE_KIND
    df["fail_error_m"] = bench_max_distance(env_id)
    return df.merge(_condition_columns(env_id, list(seeds), spec), on="seed", how="left")


# --- the Leader tiers' oracle-parameter floor (agents/benchmark/bayes_floor.py) -------------------

def leader_bayes_floor(recording: dict[str, Any], params: np.ndarray, *, particles: int = DEFAULT_PARTICLES,
                children: int = DEFAULT_CHILDREN,
                nominal_sigma: bool = False, progress: bool = False, seed: int = 0,
                prior: np.ndarray | None = None, shrink: float = 1.0) -> pd.DataFrame:
    """The particle floor (:mod:`agents.benchmark.bayes_floor`) of every episode of a recording
    (:func:`record_episodes`): with ``params`` (S, NP), each episode's own drawn parameters (the
    oracle-parameter floor); with ``prior`` (K, NP) instead (``params`` then unused), the
    tier-prior floor: each particle a draw of the tier's parameter law, each fix's noise from the
    particle's own level and the range the fix shows. One row per seed: ``expected_steady_mean``
    / ``expected_full_mean`` (the floor), ``realised_steady_mean`` / ``realised_full_mean``,
    ``min_ess_share`` / ``median_ess_share`` (the effective sample size at the fixes over N),
    ``packets``, ``dropped``, ``steady_steps_without_packet``."""
    from controllers.evaluation import _bar

    spec = recording["spec"]
    dt = spec.dt
    rows = []
    for j in _bar(range(len(recording["seeds"])), f"particle floor ({particles} particles)", progress):
        L = int(recording["length"][j])
        pk = extract_packets(recording["obs"][:L + 1, j], recording["pose"][:L + 1, j], dt)
        sig = packet_sigmas(recording, j, pk["meas"], nominal=nominal_sigma)
        rows_j, rng_j = ((params[j], None) if prior is None else
                         (prior, fix_ranges(recording, j, pk["meas"], pk["z"])))
        res = particle_floor_episode(rows_j, pk["meas"], pk["arr"], pk["z"], sig, recording["ref"][:, j, :2],
                                     spec.p_d, L, warmup_start(recording, j), particles=particles,
                                     children=children, seed=seed + j, fix_range=rng_j, shrink=shrink)
        times = dt * np.arange(1, L + 1)
        steady = times >= spec.steady_start_s - 1e-9
        ex, re = res["expected"][1:], res["realised"][1:]
        have = steady & np.isfinite(ex)
        e = res["ess"][np.isfinite(res["ess"])] / particles
        nan = math.nan
        rows.append({"seed": int(recording["seeds"][j]), "steps": L,
                     "expected_steady_mean": float(ex[have].mean()) if have.any() else nan,
                     "expected_full_mean": float(np.nanmean(ex)) if np.isfinite(ex).any() else nan,
                     "realised_steady_mean": float(re[have].mean()) if have.any() else nan,
                     "realised_full_mean": float(np.nanmean(re)) if np.isfinite(re).any() else nan,
                     "min_ess_share": float(e.min()) if e.size else nan,
                     "median_ess_share": float(np.median(e)) if e.size else nan,
                     "packets": int(len(pk["meas"])), "dropped": int(res["dropped"]),
                     "steady_steps_without_packet": int((steady & ~have).sum())})
    return pd.DataFrame(rows)


#: the controller whose episodes the Leader floors are computed from: the best generic classical
#: of the Leader tiers (the packets' timing does not depend on it; their fix noise, through the
#: range, weakly does)
LEADER_FOLLOWER = "PROPOSED_IMM_DOB"


def _cache_key(rec: dict[str, Any], params: np.ndarray, particles: int, children: int, seed: int) -> str:
    import hashlib

    from agents.benchmark import bayes_floor
    from auv_follow_env import dynamics

    h = hashlib.sha256()
    for mod in (Path(bayes_floor.__file__), Path(dynamics.__file__)):
        h.update(mod.read_bytes())
    h.update(_floor_source())
    for name in ("obs", "target", "pose", "ref", "length"):
        h.update(np.ascontiguousarray(rec[name]).tobytes())
    h.update(np.ascontiguousarray(params).tobytes())
    h.update(repr((particles, children, seed, list(map(int, rec["seeds"])))).encode())
    return h.hexdigest()[:20]


#: the floor a follower who knows the tier (its generator and published ranges, not the
#: episode's draws) could reach: :func:`leader_floor` with ``knows="tier"``
TIER_PRIOR_FLOOR = "tier-prior floor"
#: its settings: particles, Liu-West shrinkage, prior draws per particle (experiments/tier_prior_floor.py:
#: on Leader-Medium's check seeds 16,384 and 32,768 particles agree within 2 %)
TIER_PRIOR_PARTICLES, TIER_PRIOR_SHRINK, TIER_PRIOR_DRAWS = 16384, 0.98, 4
#: what each floor knows -> its row name
FLOOR_KNOWS = {"episode": INFORMATION_FLOOR, "tier": TIER_PRIOR_FLOOR}
#: the Leader tiers whose benchmark floors include the tier-prior floor: those where it converged
#: (doubling the particles changes its IQM by < 2 % on the check seeds, experiments/tier_prior_floor.py)
#: and lies below every causal estimator there: all three (docs/floors.md)
TIER_PRIOR_TIERS = ("Leader-Easy", "Leader-Medium", "Leader-Hard")


def leader_floor(tier: str, seeds: Iterable[int] | None = None, *, particles: int | None = None,
                 children: int = DEFAULT_CHILDREN, follower: str = LEADER_FOLLOWER, seed: int = 0,
                 cache_dir: str | Path | None = None, progress: bool = False, knows: str = "episode",
                 shrink: float | None = None) -> pd.DataFrame:
    """A particle floor of a Leader tier, per episode (:func:`leader_bayes_floor` on the episodes
    ``follower`` plays; None seeds: the tier's published test seeds). ``knows="episode"``: the
    oracle-parameter floor (each episode's drawn parameters; default particles
    DEFAULT_PARTICLES, no move); ``"tier"``: the tier-prior floor (TIER_PRIOR_DRAWS x particles
    draws of the tier's parameter law as the prior; defaults TIER_PRIOR_PARTICLES and
    TIER_PRIOR_SHRINK). With ``cache_dir`` the rows are stored there, keyed by the floor's code
    (agents/benchmark/bayes_floor.py, the dynamics, and this module's :func:`leader_bayes_floor`
    and :func:`extract_packets`), the recording, the parameters and the settings, and reused
    while all of them are unchanged."""
    from auv_follow_env.tiers import LEADER_TIERS

    if knows not in FLOOR_KNOWS:
        raise ValueError(f"knows={knows!r} is invalid: must be one of {list(FLOOR_KNOWS)}")
    if particles is None:
        particles = DEFAULT_PARTICLES if knows == "episode" else TIER_PRIOR_PARTICLES
    if shrink is None:
        shrink = 1.0 if knows == "episode" else TIER_PRIOR_SHRINK

    if not isinstance(tier, str) or tier not in LEADER_TIERS:
        raise ValueError(f"tier={tier!r} is invalid: the particle floor is for the Leader tiers {list(LEADER_TIERS)} "
                         "(the v1 tiers' floor is the Kalman floor, agents.benchmark.floors.information_floor)")
    seeds = _check_seeds(seeds, tier)
    rec = record_episodes(tier, seeds, follower, progress=progress)
    env_id = f"AUVFollow-{tier}-v1"
    params = episode_params(env_id, seeds)
    draws = TIER_PRIOR_DRAWS * int(particles)
    path = None
    if cache_dir is not None:
        key = _cache_key(rec, params, particles, children, seed)
        if knows == "tier":  # the prior is a function of the env's code (in the key), the id and the draws
            key = f"tier-{key}-a{float(shrink):g}-d{draws}"
        path = Path(cache_dir) / f"leader-floor-{tier}-{key}.parquet"
        if path.is_file():
            return pd.read_parquet(path)
    prior = tier_prior(env_id, draws) if knows == "tier" else None
    df = leader_bayes_floor(rec, params, particles=particles, children=children, progress=progress, seed=seed,
                            prior=prior, shrink=shrink)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp")
        df.to_parquet(tmp)
        tmp.replace(path)
    return df


def estimator_error(recording: dict[str, Any], config: Any = None) -> np.ndarray:
    """The realised error of a :class:`controllers.estimator.TargetEstimator` (the tier's own
    settings unless ``config`` is given) on a :func:`record_episodes` recording, with the
    oracle-parameter floor's conventions: the estimate of the reference point at step t uses the
    observations up to step t - 1 (predicted one control step ahead), steps before the first
    packet are left out, and the per-episode value is the mean over the steady-state window
    (t >= steady_start_s). Returns one value per episode [m] (NaN: no packet in the window)."""
    from controllers.estimator import TargetEstimator

    spec = recording["spec"]
    obs, pose, ref, length = recording["obs"], recording["pose"], recording["ref"], recording["length"]
    T, n = obs.shape[0] - 1, obs.shape[1]
    est = TargetEstimator(spec, config)
    pdx, pdy = spec.p_d
    dt = spec.dt
    total, count = np.zeros(n), np.zeros(n)
    start = np.ones(n, dtype=bool)
    ahead = np.array([dt])
    for k in range(T):
        e = est.step(obs[k].astype(np.float64), start, with_cov=False)
        start = np.zeros(n, dtype=bool)
        t = k + 1
        if t * dt < spec.steady_start_s - 1e-9:
            continue
        x, y, psi = (a[:, 0] for a in est.trajectory(ahead, frame="body"))
        c, s = np.cos(pose[k, :, 2]), np.sin(pose[k, :, 2])
        px, py, ps = pose[k, :, 0] + c * x - s * y, pose[k, :, 1] + s * x + c * y, pose[k, :, 2] + psi
        rx = px + np.cos(ps) * pdx - np.sin(ps) * pdy
        ry = py + np.sin(ps) * pdx + np.cos(ps) * pdy
        ok = e.valid & (t <= length)
        err = np.hypot(rx - ref[t, :, 0], ry - ref[t, :, 1])
        total[ok] += err[ok]
        count[ok] += 1
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / count, np.nan)


def add_gap_closed(board: pd.DataFrame, metric: str = "true_steady_mean") -> pd.DataFrame:
    """Add ``gap_closed``, ``gap_floor`` and ``gap_closed_oracle`` to a leaderboard. Per tier with
    a floor row and a classical baseline, gap closed = (best generic classical IQM - method IQM)
    / (best generic classical IQM - floor IQM): 0 for the best generic classical, 1 for a method
    at the floor, negative for one worse; NaN for reference rows and tiers without a floor.
    ``gap_closed`` is measured against the floor a follower could reach where the tier has one
    (:data:`TIER_PRIOR_FLOOR`), else against the :data:`INFORMATION_FLOOR`; ``gap_floor`` names
    it; ``gap_closed_oracle`` is always against the oracle-parameter floor.
    *Generic*: not one of ``controllers.MODEL_AWARE_CONTROLLERS`` (which know a Leader tier's
    generator); on the v1 tiers that is every classical row, the best classical."""
    from controllers import MODEL_AWARE_CONTROLLERS

    out = board.copy()
    out["gap_closed"] = np.nan
    out["gap_closed_oracle"] = np.nan
    out["gap_floor"] = ""
    col = f"{metric}_iqm"
    if col not in out or "kind" not in out:
        return out
    for _, idx in out.groupby("tier", sort=False).groups.items():
        sub = out.loc[idx]
        generic = sub[(sub["kind"] == "classical") & ~sub["policy"].isin(list(MODEL_AWARE_CONTROLLERS))]
        if generic.empty:
            continue
        b = float(generic[col].min())
        comp = sub["kind"] != REFERENCE_KIND
        for name, target in ((INFORMATION_FLOOR, "gap_closed_oracle"), (INFORMATION_FLOOR, "gap_closed"),
                             (TIER_PRIOR_FLOOR, "gap_closed")):
            floor = sub[(sub["policy"] == name) & (sub["kind"] == REFERENCE_KIND)]
            if floor.empty or not b > float(floor[col].iloc[0]):
                continue
            out.loc[sub.index[comp], target] = (b - sub.loc[comp, col]) / (b - float(floor[col].iloc[0]))
            if target == "gap_closed":
                out.loc[sub.index, "gap_floor"] = name
    return out


@functools.cache
def _floor_source() -> bytes:
    """Of this module, the source of the code a particle floor row depends on beyond the
    recording: edits elsewhere here (the leaderboard's use of the rows) keep the cached rows.
    Read once per process, so that a file edited while a long run goes on does not change that
    run's keys."""
    import inspect

    return b"".join(inspect.getsource(fn).encode() for fn in (leader_bayes_floor, extract_packets, _cache_key))
