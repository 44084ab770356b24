"""Residual reinforcement learning on top of a scripted controller.

:class:`ResidualWrapper` turns an AUVFollow env into the env a residual agent sees: the
wrapper owns one of the paper's controllers (``PROPOSED`` by default), asks it for its
action on every observation, and applies

    a = clip(a_base + scale * a_residual, -1, 1)

where ``a_residual`` in [-1, 1]^3 is the agent's action. A zero residual therefore
reproduces the base controller's trajectory bit for bit.

The agent's observation is the env's 16 fields, then (optionally) the base action (3), then
(optionally) a short history of the delayed target's body velocities: for lags
``j * history_stride`` steps, j = 1..history_len, the difference
``(target_{u,v,r}(k) - target_{u,v,r}(k - lag)) / (lag * dt)`` [m/s^2, m/s^2, rad/s^2] -
finite-difference accelerations of the delayed target, which is what a first-order
predictor (eqs. (13)-(17)) misses: the true present target is roughly the delayed one
extrapolated with its acceleration over the delay. Lags reaching before the episode's
start use the first observation (difference 0).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from agents.training.history import (
    DEFAULT_CONTROLLER,
    DEFAULT_HISTORY_LEN,
    DEFAULT_HISTORY_STRIDE,
    DEFAULT_SCALE,
    _check,
)
from auv_follow_env.layout import LAYOUTS


class ResidualWrapper(gym.Wrapper):
    """Residual action on top of a scripted controller, with an augmented observation.

    A single-env view of :class:`agents.training.batched_obs.ObservationBuilder` (the same code as the
    batched training env, with N = 1).

    Args:
        env: an AUVFollow env (``gym.make("AUVFollow-S4-v0")``, possibly wrapped by Monitor
            or TimeLimit); its ``unwrapped.task_spec`` configures the base controller.
        controller: base controller name, one of ``controllers.ALL_CONTROLLERS`` (the paper's four or ours).
        scale: residual authority as a fraction of the force limits (default 0.2).
        include_base_action: append the base action (3) to the observation (default True).
        history_len: number K of lagged delayed-target velocity differences (default 4;
            0 disables the history).
        history_stride: steps between lagged samples (default 10 = 0.5 s).
        observation: ``"raw"`` (default) or ``"estimator"`` (append the estimator block,
            :data:`agents.training.batched_obs.ESTIMATOR_FIELDS`).
        observer_feed: ``"applied"`` (default: the base's disturbance observer is told base +
            residual) or ``"base"`` (its own command only, as in earlier versions).

    The base controller's disturbance observer (if any) is told the force actually commanded
    (base + residual), so it does not cancel the residual.

    Raises:
        ValueError: unknown controller or invalid scale / history / observation settings.
    """

    def __init__(self, env: gym.Env, controller: str = DEFAULT_CONTROLLER, scale: float = DEFAULT_SCALE,
                 include_base_action: bool = True, history_len: int = DEFAULT_HISTORY_LEN,
                 history_stride: int = DEFAULT_HISTORY_STRIDE, observation: str = "raw",
                 observer_feed: str = "applied") -> None:
        from agents.training.batched_obs import ObservationBuilder

        super().__init__(env)
        _check(controller, scale, history_len, history_stride)
        if len(env.observation_space.shape) != 1 or env.observation_space.shape[0] not in LAYOUTS:
            raise ValueError(f"env observation shape {env.observation_space.shape} is not an AUVFollow "
                             f"layout (width {sorted(LAYOUTS)}): apply ResidualWrapper to an AUVFollow env")
        spec = env.unwrapped.task_spec
        self.controller_name = controller
        self.builder = ObservationBuilder(spec, mode="residual", controller=controller, scale=scale,
                                          include_base_action=include_base_action, observation=observation,
                                          history_len=history_len, history_stride=history_stride,
                                          observer_feed=observer_feed)
        self.base = self.builder.base
        self.scale = float(scale)
        self.include_base_action = bool(include_base_action)
        self.history_len = int(history_len)
        self.history_stride = int(history_stride)
        self.observation = observation
        self._k = 0
        self._base_action = np.zeros(3, dtype=np.float32)
        self.observation_space = spaces.Box(-np.inf, np.inf, (self.builder.dim,), np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, (3,), np.float32)

    @property
    def config(self) -> dict[str, Any]:
        """The wrapper's keyword arguments (to save with a model)."""
        cfg = {"controller": self.controller_name, "scale": self.scale,
               "include_base_action": self.include_base_action, "history_len": self.history_len,
               "history_stride": self.history_stride}
        if self.observation != "raw":
            cfg["observation"] = self.observation
        cfg["observer_feed"] = self.builder.observer_feed
        return cfg

    def _augment(self, obs: np.ndarray) -> np.ndarray:
        out = self.builder.observe(np.asarray(obs)[None, :], np.array([self._k == 0]))[0]
        self._base_action = self.builder.base_action[0]
        return out

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        obs, info = self.env.reset(seed=seed, options=options)
        self._k = 0
        out = self._augment(obs)
        info["base_action"] = self._base_action
        return out, info

    def step(self, action: Any):
        applied = self.builder.act(np.asarray(action, dtype=np.float64).reshape(1, 3))[0]
        obs, reward, terminated, truncated, info = self.env.step(applied)
        info["applied_action"] = applied
        self._k += 1
        out = self._augment(obs)
        info["base_action"] = self._base_action
        return out, reward, terminated, truncated, info


def make_residual_wrapper(**kwargs: Any) -> Callable[[gym.Env], gym.Env]:
    """A one-argument wrapper factory (for ``evaluate(env_wrapper=...)`` and SB3's
    ``make_vec_env(wrapper_class=...)``), validated now rather than at first use."""
    _check(kwargs.get("controller", DEFAULT_CONTROLLER), kwargs.get("scale", DEFAULT_SCALE),
           kwargs.get("history_len", DEFAULT_HISTORY_LEN), kwargs.get("history_stride", DEFAULT_HISTORY_STRIDE))

    def wrap(env: gym.Env) -> gym.Env:
        return ResidualWrapper(env, **kwargs)

    return wrap


class ResidualPolicy:
    """A residual agent as one policy over *raw* AUVFollow observations (SB3 ``predict``
    protocol, single (W,) or batched (N, W)): it runs the base controller, the history and
    (if trained with it) the estimator block itself through
    :class:`agents.training.batched_obs.ObservationBuilder`, so it needs no wrapper (e.g. for
    ``controllers.evaluation.evaluate`` or ``evaluate_batched``). Per-env memory restarts where
    ``episode_start`` is True (and on the first call / a change of batch size).

    Args:
        agent: the residual agent's policy over the wrapped observation (anything with
            ``predict``, e.g. :class:`agents.training.Agent`).
        spec: the task spec of the env it will run on.
        residual: the wrapper settings the agent was trained with (``ResidualWrapper.config``).
        name: label.
    """

    def __init__(self, agent: Any, spec: Any, residual: dict[str, Any], name: str | None = None) -> None:
        from agents.training.batched_obs import ObservationBuilder

        # a run saved without observer_feed was trained by an earlier version (observer told the base's
        # command only): evaluate it as it was trained
        cfg = {"controller": DEFAULT_CONTROLLER, "scale": DEFAULT_SCALE, "include_base_action": True,
               "history_len": DEFAULT_HISTORY_LEN, "history_stride": DEFAULT_HISTORY_STRIDE, "observation": "raw",
               "observer_feed": "base", **residual}
        _check(cfg["controller"], cfg["scale"], cfg["history_len"], cfg["history_stride"])
        self.agent = agent
        self.spec = spec  #: the task spec it was built for (checked by controllers.evaluation.evaluate)
        self.builder = ObservationBuilder(spec, mode="residual", controller=cfg["controller"], scale=cfg["scale"],
                                          include_base_action=cfg["include_base_action"],
                                          observation=cfg["observation"], history_len=cfg["history_len"],
                                          history_stride=cfg["history_stride"], observer_feed=cfg["observer_feed"])
        self.base = self.builder.base
        self.scale = float(cfg["scale"])
        self.include_base_action = bool(cfg["include_base_action"])
        self.history = self.builder.history
        self.name = name or getattr(agent, "name", "residual")

    def reset(self) -> None:
        """Forget all memory: the next call starts fresh for every env."""
        self.builder.reset()

    def predict(self, observation: Any, state: Any = None, episode_start: Any = None,
                deterministic: bool = True) -> tuple[np.ndarray, Any]:
        obs = np.asarray(observation)
        single = obs.ndim == 1
        if single:
            obs = obs[None, :]
        if obs.ndim != 2 or obs.shape[1] not in LAYOUTS:
            raise ValueError(f"observation has shape {np.shape(observation)}: expected (W,) or (N, W) with an "
                             f"AUVFollow layout width W in {sorted(LAYOUTS)}")
        if obs.shape[1] != self.builder.obs_width:
            raise ValueError(f"observation has shape {np.shape(observation)}: this policy was built for "
                             f"{self.builder.obs_width}-wide observations")
        n = obs.shape[0]
        feats = self.builder.observe(obs, episode_start)
        res, _ = self.agent.predict(feats, deterministic=deterministic)
        action = self.builder.act(np.asarray(res, dtype=np.float64).reshape(n, 3))
        return (action[0] if single else action), state


def _wrapper(mode: str, residual: dict[str, Any] | None):
    return make_residual_wrapper(**residual) if mode == "residual" else None
