"""What a learned agent observes and how its action reaches the env, for N envs at once.

:class:`ObservationBuilder` is the one implementation behind every learned agent's
observation: the batched training env (:mod:`agents.training.batched_env`), the single-env
:class:`agents.training.residual.ResidualWrapper`, and the evaluation-time policies
(:class:`agents.training.residual.ResidualPolicy`, :class:`agents.training.batched_ppo.BatchedAgent`). It runs
on a batch (N, W) of raw AUVFollow observations with a per-env episode-start mask:

* ``observe(raw, start)``: the agent's observation (N, D), float32: the env's own fields
  (16 on v0, 20 on v1), then optionally the base controller's action (3, residual agents),
  then optionally the **estimator block** (:data:`ESTIMATOR_FIELDS`, 18 fields), then
  optionally the finite-difference history of the delayed target's velocities
  (:class:`agents.training.residual.DelayedTargetHistory`, 3 per lag; kept for v0, off by default on v1);
* ``act(action)``: the env action (N, 3) for the agent's action in [-1, 1]^3: for a
  residual agent ``clip(a_base + scale * a, -1, 1)``, from scratch ``clip(a, -1, 1)``.
  Then every disturbance observer involved is told the force actually commanded,
  ``clip(F_base + scale * a * limits, -limits, limits)`` (residual) or ``a * limits``
  (scratch): the base's observer no longer takes the residual for a disturbance and
  cancels it, as it did in earlier versions. With a zero residual this is exactly what the
  base told its observer itself, so a zero residual reproduces the base bit for bit.

**The estimator block** is read through the public API only
(``TargetEstimator.step(obs, reset_mask, commit=, with_cov=)``, ``DisturbanceObserver.d_hat``):
a base controller with its own estimator (``PROPOSED_KF``, ``PROPOSED_KF_DOB``, ``MPC``) is
*peeked* at the same observation and mask just before the base commits it (so the block is
exactly the estimate the base acts on, plus its covariance); otherwise (scratch agents, the
paper's controllers) a standalone ``TargetEstimator(spec)`` is stepped. The force estimate
is the base's observer's ``d_hat`` after its update on this observation, or a standalone
``DisturbanceObserver`` (time constant ``controllers.DOB_TIME_CONSTANT``) fed the same way.
Before the first fix of an episode (``est_valid`` = 0) the estimate fields are 0.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from auv_follow_env.layout import LAYOUTS, OBS_DIM_V1, OBS_INDEX_V1, ObsField, decode
from controllers import ALL_CONTROLLERS, DOB_TIME_CONSTANT, DisturbanceObserver, TargetEstimator, make_controller
from controllers.base import ObservationHold
from controllers.hierarchical import reference_point

__all__ = ["ESTIMATOR_FIELDS", "ESTIMATOR_INDEX", "ESTIMATOR_DIM", "OBSERVATIONS", "ObservationBuilder",
           "estimator_features", "default_observation", "check_observation", "observation_dim"]

#: the estimator block of the observation: name, unit, meaning (defined once; agents/README.md shows it)
ESTIMATOR_FIELDS: tuple[ObsField, ...] = (
    ObsField("est_dx", "m", "present target position estimate minus follower position, body x (TargetEstimate.rel_x)"),
    ObsField("est_dy", "m", "present target position estimate minus follower position, body y (rel_y)"),
    ObsField("est_cos_dpsi", "-", "cosine of (estimated target heading - follower heading) (cos rel_psi)"),
    ObsField("est_sin_dpsi", "-", "sine of (estimated target heading - follower heading) (sin rel_psi)"),
    ObsField("est_u", "m/s", "estimated target surge velocity (target body frame)"),
    ObsField("est_v", "m/s", "estimated target sway velocity (target body frame)"),
    ObsField("est_r", "rad/s", "estimated target yaw rate"),
    ObsField("est_ref_dx", "m", "estimated present reference point p_hat + R(psi_hat) p_d minus follower, body x"),
    ObsField("est_ref_dy", "m", "estimated present reference point minus follower, body y"),
    ObsField("est_sd_pos", "m", "sqrt(P_xx + P_yy): position standard deviation of the estimate (rotation invariant)"),
    ObsField("est_sd_psi", "rad", "sqrt(P_psipsi): heading standard deviation"),
    ObsField("est_sd_vel", "m/s", "sqrt(P_uu + P_vv): target velocity standard deviation (P_uu alone for the "
             "no-sway model OU0; CV: the inertial velocity's)"),
    ObsField("est_age", "s", "now minus the measurement time of the newest fix the estimator used (est.age)"),
    ObsField("est_since_arrival", "s", "now minus the arrival time of the newest packet (v1 since_arrival; 0 on v0)"),
    ObsField("est_valid", "-", "1 once the estimator has a fix this episode, else 0 (then the fields above are 0)"),
    ObsField("dob_u", "N", "disturbance observer's lumped-force estimate d_hat, surge"),
    ObsField("dob_v", "N", "d_hat, sway"),
    ObsField("dob_r", "N m", "d_hat, yaw"),
)
ESTIMATOR_INDEX = {f.name: i for i, f in enumerate(ESTIMATOR_FIELDS)}
ESTIMATOR_DIM = len(ESTIMATOR_FIELDS)

#: observation kinds: the env's fields only ("raw") or with the estimator block ("estimator")
OBSERVATIONS: tuple[str, ...] = ("raw", "estimator")
MODES: tuple[str, ...] = ("residual", "scratch")
#: what a residual's base disturbance observer is told (ObservationBuilder's observer_feed)
OBSERVER_FEEDS: tuple[str, ...] = ("applied", "base")


def default_observation(env_id: str) -> str:
    """``"estimator"`` on the v1 ids (acoustic link), ``"raw"`` on v0 (and other ids)."""
    return "estimator" if str(env_id).endswith("-v1") else "raw"


def check_observation(observation: Any) -> str:
    if observation not in OBSERVATIONS:
        raise ValueError(f"observation={observation!r} is unknown: valid kinds are {list(OBSERVATIONS)}")
    return observation


def observation_dim(obs_width: int, mode: str, observation: str, include_base_action: bool, history_len: int,
                    action_filter: float = 1.0) -> int:
    """Width of the agent's observation."""
    return (int(obs_width) + (3 if mode == "residual" and include_base_action else 0)
            + (ESTIMATOR_DIM if observation == "estimator" else 0) + 3 * int(history_len)
            + (3 if float(action_filter) < 1.0 else 0))


def check_action_filter(action_filter: Any) -> float:
    """The low-pass gain of the agent's action: a number in (0, 1] (1: no filter)."""
    ok = isinstance(action_filter, (int, float, np.integer, np.floating)) and not isinstance(action_filter, bool)
    if not ok or not math.isfinite(float(action_filter)) or not 0.0 < float(action_filter) <= 1.0:
        raise ValueError(f"action_filter={action_filter!r} is invalid: must be a number in (0, 1] (1: no filter)")
    return float(action_filter)


#: estimator model -> indices of its velocity states (the state starts x, y, psi for every model)
_VEL_STATES = {"CV": (3, 4), "CT": (3, 4), "CTA": (3, 4), "OU": (3, 4), "OU0": (3,), "IMM": (3,)}


def estimator_features(est: Any, d_hat: np.ndarray, since_arrival: np.ndarray, spec: Any,
                       model: str = "OU0") -> np.ndarray:
    """The estimator block (N, 18) float64 from a ``TargetEstimate`` (with ``cov``) of an
    estimator with state model ``model``, the force estimate d_hat (N, 3) and the time since
    the newest packet's arrival (N,)."""
    valid = np.asarray(est.valid, dtype=bool)
    n = valid.shape[0]
    out = np.zeros((n, ESTIMATOR_DIM))
    rel_psi = np.asarray(est.rel_psi, dtype=np.float64)
    out[:, 0] = est.rel_x
    out[:, 1] = est.rel_y
    out[:, 2] = np.cos(rel_psi)
    out[:, 3] = np.sin(rel_psi)
    out[:, 4] = est.u
    out[:, 5] = est.v
    out[:, 6] = est.r
    xr, yr, _ = reference_point(np.asarray(est.rel_x), np.asarray(est.rel_y), rel_psi, spec.p_d, spec.psi_d)
    out[:, 7] = np.where(valid, xr, 0.0)
    out[:, 8] = np.where(valid, yr, 0.0)
    cov = est.cov
    if cov is not None:
        out[:, 9] = np.sqrt(np.maximum(cov[:, 0, 0] + cov[:, 1, 1], 0.0))
        out[:, 10] = np.sqrt(np.maximum(cov[:, 2, 2], 0.0))
        vel = _VEL_STATES.get(model, (3, 4))
        out[:, 11] = np.sqrt(np.maximum(sum(cov[:, i, i] for i in vel), 0.0))
        out[~valid, 9:12] = 0.0
    out[:, 12] = np.where(valid, est.age, 0.0)
    out[:, 13] = since_arrival
    out[:, 14] = valid
    out[:, 15:18] = d_hat
    return out


def _check_mode(mode: str) -> None:
    if mode not in MODES:
        raise ValueError(f"mode={mode!r} is unknown: valid modes are {list(MODES)}")


class ObservationBuilder:
    """The agent's observation and the env action for a batch of N envs (module docstring).

    Args:
        spec: the env's TaskSpec.
        mode: ``"residual"`` (on top of ``controller``) or ``"scratch"``.
        controller: base controller of a residual agent (one of ``controllers.ALL_CONTROLLERS``).
        scale: residual authority (fraction of the force limits, > 0).
        include_base_action: append the base action (residual only).
        observation: ``"raw"`` or ``"estimator"`` (append :data:`ESTIMATOR_FIELDS`).
        history_len, history_stride: the finite-difference history (0: none).
        observer_feed: what the base's disturbance observer is told: ``"applied"`` (base +
            residual, the force commanded) or ``"base"`` (only the base's own command, as in earlier
            versions: the observer then cancels a residual; kept to evaluate agents trained so).
        action_filter: low-pass gain alpha in (0, 1] of the agent's action: the action used is
            ``u_k = u_{k-1} + alpha (a_k - u_{k-1})`` (``u`` = 0 at an episode's start), and
            ``u_{k-1}`` is appended to the observation (3 fields) so the policy sees its own
            state. 1 (the default): no filter, nothing appended.
        yaw_from: a controller (one of ``controllers.ALL_CONTROLLERS``) whose yaw moment replaces
            the agent's (scratch only): the agent commands surge and sway, the classical law
            keeps the heading; its disturbance observer is told the force applied. None (the
            default): the agent commands all three.

    The memory of every part (base controller, estimators, observers, history) restarts
    for the envs where ``start`` is set, and for all on the first call or a change of N.
    """

    def __init__(self, spec: Any, *, mode: str = "scratch", controller: str | None = None, scale: float = 0.2,
                 include_base_action: bool = True, observation: str = "raw", history_len: int = 0,
                 history_stride: int = 10, observer_feed: str = "applied", action_filter: float = 1.0,
                 yaw_from: str | None = None) -> None:
        from agents.training.history import DelayedTargetHistory, _check

        _check_mode(mode)
        check_observation(observation)
        if observer_feed not in OBSERVER_FEEDS:
            raise ValueError(f"observer_feed={observer_feed!r} is unknown: valid feeds are {list(OBSERVER_FEEDS)}")
        self.observer_feed = observer_feed
        self.action_filter = check_action_filter(action_filter)
        self._u: np.ndarray | None = None  #: (N, 3) the filtered action of the last act (action_filter < 1)
        if mode == "residual":
            _check(controller, scale, history_len, history_stride)
        else:
            _check(ALL_CONTROLLERS[0], 1.0, history_len, history_stride)
        self.spec = spec
        self.mode = mode
        self.observation = observation
        self.scale = float(scale)
        self.include_base_action = bool(include_base_action) and mode == "residual"
        self.history_len, self.history_stride = int(history_len), int(history_stride)
        self.obs_width = int(spec.obs_dim)
        if self.obs_width not in LAYOUTS:
            raise ValueError(f"spec.obs_dim={spec.obs_dim!r} is not an AUVFollow layout width {sorted(LAYOUTS)}")
        self.limits = np.asarray(spec.force_limits, dtype=np.float64)
        self.base = make_controller(controller, spec) if mode == "residual" else None
        if yaw_from is not None and (mode != "scratch" or yaw_from not in ALL_CONTROLLERS):
            raise ValueError(f"yaw_from={yaw_from!r} is invalid with mode={mode!r}: must be None or, from scratch, "
                             f"one of {list(ALL_CONTROLLERS)}")
        self.yaw_from = yaw_from
        self.yaw_base = make_controller(yaw_from, spec) if yaw_from is not None else None
        self.yaw_action: np.ndarray | None = None  #: (N, 3) the yaw controller's action at the last observe
        base_est = getattr(self.base, "estimator", None)
        base_dob = getattr(self.base, "disturbance_observer", None)
        self.base_estimator: TargetEstimator | None = base_est if isinstance(base_est, TargetEstimator) else None
        self.base_dob: DisturbanceObserver | None = base_dob if isinstance(base_dob, DisturbanceObserver) else None
        want = observation == "estimator"
        self.estimator = TargetEstimator(spec) if want and self.base_estimator is None else None
        self.dob = (DisturbanceObserver(spec.nominal, spec.dt, spec.force_limits, DOB_TIME_CONSTANT)
                    if want and self.base_dob is None else None)
        self.history = DelayedTargetHistory(self.history_len, self.history_stride, spec.dt)
        self.dim = observation_dim(self.obs_width, mode, observation, self.include_base_action, self.history_len,
                                   self.action_filter)
        self._n: int | None = None
        #: the recovery rule for non-finite observation fields (controllers.base.ObservationHold)
        self.hold = ObservationHold(spec.dt)
        self.base_action: np.ndarray | None = None  #: (N, 3) float32, the base's action at the last observe
        self.base_forces: np.ndarray | None = None  #: (N, 3) float64, the base's command [N, N, N m]
        self.last_estimate: Any = None  #: the TargetEstimate behind the last estimator block
        self.last_d_hat: np.ndarray | None = None
        #: wall-clock seconds spent in :meth:`observe` ("observe", everything) and in its base controller ("base")
        self.timing: dict[str, float] = {"observe": 0.0, "base": 0.0}

    @property
    def config(self) -> dict[str, Any]:
        return {"mode": self.mode, "controller": getattr(self.base, "name", None) if self.base else None,
                "scale": self.scale, "include_base_action": self.include_base_action,
                "observation": self.observation, "history_len": self.history_len,
                "history_stride": self.history_stride, "observer_feed": self.observer_feed,
                **({"action_filter": self.action_filter} if self.action_filter < 1.0 else {}),
                **({"yaw_from": self.yaw_from} if self.yaw_from is not None else {})}

    @property
    def error_indices(self) -> list[int]:
        """Columns of the agent's observation that are reference errors, zero on the reference:
        the raw ``ref_dx``, ``ref_dy`` and, with the estimator block, ``est_ref_dx``, ``est_ref_dy``."""
        names = [f.name for f in LAYOUTS[self.obs_width]]
        cols = [names.index("ref_dx"), names.index("ref_dy")]
        if self.observation == "estimator":
            at = self.obs_width + (3 if self.include_base_action else 0)
            cols += [at + ESTIMATOR_INDEX["est_ref_dx"], at + ESTIMATOR_INDEX["est_ref_dy"]]
        return cols

    def reset(self) -> None:
        """Forget everything: the next :meth:`observe` starts every env afresh."""
        self._n = None

    def observe(self, raw: Any, start: Any = None) -> np.ndarray:
        """The agent's observation (N, D) float32 for raw env observations (N, W)."""
        t0 = time.perf_counter()
        out = self._observe(raw, start)
        self.timing["observe"] += time.perf_counter() - t0
        return out

    def _observe(self, raw: Any, start: Any) -> np.ndarray:
        obs = np.asarray(raw)
        if obs.ndim != 2 or obs.shape[1] != self.obs_width:
            raise ValueError(f"raw observation has shape {obs.shape}: expected (N, {self.obs_width})")
        n = obs.shape[0]
        if start is None:
            start = np.zeros(n, dtype=bool)
        else:
            start = np.asarray(start, dtype=bool).reshape(n)
        if self._n != n:
            start = np.ones(n, dtype=bool)
            for part in (self.base, self.estimator, self.base_estimator, self.yaw_base):
                if part is not None:
                    part.reset()
            self.hold.reset()
            self._n = n
        raw64 = np.asarray(obs, dtype=np.float64)
        obs64 = self.hold(raw64, start)
        if obs64 is not raw64:
            obs = obs64  # a field held (controllers.base.ObservationHold)
        parts = [obs.astype(np.float32, copy=False)]
        if self.yaw_base is not None:
            self.yaw_action, _ = self.yaw_base.predict(obs64, episode_start=start)
        est = None
        if self.base is not None:
            if self.observation == "estimator" and self.base_estimator is not None:
                # a peek at exactly what the base commits below (same bits and mask), with the covariance
                est = self.base_estimator.step(obs64, start, commit=False, with_cov=True)
            tb = time.perf_counter()
            self.base_action, _ = self.base.predict(obs64, episode_start=start)
            self.timing["base"] += time.perf_counter() - tb
            self.base_forces = np.asarray(self.base.last_forces, dtype=np.float64)
            if self.include_base_action:
                parts.append(self.base_action.astype(np.float32))
        if self.observation == "estimator":
            estimator = self.base_estimator if self.base_estimator is not None else self.estimator
            if est is None:
                est = estimator.step(obs64, start, commit=True, with_cov=True)
            if self.base_dob is not None:
                d_hat = self.base_dob.d_hat.copy()
            else:
                o = decode(obs64)
                nu = np.stack([o["u"], o["v"], o["r"]], axis=-1)
                d_hat = self.dob.update(nu, np.stack([o["current_u"], o["current_v"]], axis=-1), start)
            since = obs64[:, OBS_INDEX_V1["since_arrival"]] if self.obs_width == OBS_DIM_V1 else np.zeros(n)
            self.last_estimate, self.last_d_hat = est, d_hat
            parts.append(estimator_features(est, d_hat, since, self.spec, estimator.model).astype(np.float32))
        if self.history_len:
            parts.append(self.history(obs, start))
        if self.action_filter < 1.0:
            if self._u is None or self._u.shape[0] != n:
                self._u = np.zeros((n, 3))
            self._u[start] = 0.0
            parts.append(self._u.astype(np.float32))
        return np.concatenate(parts, axis=1) if len(parts) > 1 else parts[0].copy()

    def act(self, action: Any) -> np.ndarray:
        """The env action (N, 3) float64 in [-1, 1] for the agent's action (N, 3) (clipped to
        [-1, 1]); tells every disturbance observer the force commanded."""
        n = self._n
        if n is None:
            raise ValueError("act() needs an observe() first")
        res = np.clip(np.asarray(action, dtype=np.float64).reshape(n, 3), -1.0, 1.0)
        if self.action_filter < 1.0:
            self._u = self._u + self.action_filter * (res - self._u)
            res = self._u.copy()
        if self.base is not None:
            a = np.clip(self.base_action.astype(np.float64) + self.scale * res, -1.0, 1.0)
            force = np.clip(self.base_forces + self.scale * res * self.limits, -self.limits, self.limits)
        else:
            a = res
            if self.yaw_base is not None:  # the classical law's yaw moment, the agent's surge and sway
                a = res.copy()
                a[:, 2] = np.clip(self.yaw_action[:, 2].astype(np.float64), -1.0, 1.0)
            force = a * self.limits
        yaw_dob = getattr(self.yaw_base, "disturbance_observer", None)
        if yaw_dob is not None:
            yaw_dob.applied(force)
        if self.base_dob is not None and self.observer_feed == "applied":
            self.base_dob.applied(force)
        if self.dob is not None:
            self.dob.applied(force)
        return a
