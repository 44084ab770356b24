"""Loading a finished run as an :class:`Agent` (raw observations in, env actions out) and
evaluating it on seeds."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from agents.training.config import BATCHED_ALGOS, RECURRENT_ALGOS, _algo_class, _one_line
from agents.training.obs_stats import (
    ObsStats,
    _stats_path,
    check_against_config,
    read_obs_stats,
)
from agents.training.residual import _wrapper
from agents.training.rundir import _checkpoints, _failure, _run_config_path, read_run_config
from auv_follow_env._files import check_size
from auv_follow_env.layout import LAYOUTS
from controllers.base import ObservationHold


class Agent:
    """A trained agent as a policy with SB3's ``predict`` protocol, over the observation of
    its (wrapped) env; ``env_wrapper`` is the wrapper to apply to a raw AUVFollow env (None
    for a from-scratch agent). Observation normalisation (``stats``) is applied inside
    :meth:`predict`.
    """

    def __init__(self, model: Any, config: dict[str, Any], stats: ObsStats | None = None,
                 name: str | None = None) -> None:
        self.model = model
        self.config = config
        run = config["run"]
        self.env_id: str = run["env_id"]
        self.env_kwargs: dict = dict(run.get("env_kwargs") or {})
        self.mode: str = run["mode"]
        self.residual: dict | None = config.get("residual")
        self.env_wrapper = _wrapper(self.mode, self.residual)
        self.stats = stats
        self.name = name or (f"{run['algo'].upper()}+{self.residual['controller']} (residual)"
                             if self.mode == "residual" else f"{run['algo'].upper()} (scratch)")

    def raw_policy(self, env_id: str | None = None, env_kwargs: dict | None = None) -> Any:
        """A policy over raw AUVFollow observations: for a residual agent an
        :class:`agents.training.residual.ResidualPolicy` (runs its own base controller and history),
        for a from-scratch agent ``self``."""
        if self.mode != "residual":
            return self
        from agents.training.residual import ResidualPolicy

        env = gym.make(env_id or self.env_id, **(self.env_kwargs if env_kwargs is None else env_kwargs))
        spec = env.unwrapped.task_spec
        env.close()
        return ResidualPolicy(self, spec, self.residual, name=self.name)

    def normalize(self, obs: np.ndarray) -> np.ndarray:
        return obs if self.stats is None else self.stats.normalize(obs)

    @property
    def recurrent(self) -> bool:
        """True for an LSTM policy (RecurrentPPO): :meth:`predict` then keeps its state."""
        return self.config["run"]["algo"] in RECURRENT_ALGOS

    def reset(self) -> None:
        """Forget the recurrent state: the next call starts every env afresh."""
        self._lstm, self._lstm_n = None, None
        if getattr(self, "_hold", None) is not None:
            self._hold.reset()

    def _held(self, obs: np.ndarray, episode_start: Any) -> np.ndarray:
        """A raw observation (scratch) with the recovery rule for non-finite fields applied
        (controllers.base.ObservationHold); a residual agent's base applies it itself."""
        if self.mode == "residual" or obs.shape[-1] not in LAYOUTS:
            return obs
        if getattr(self, "_hold", None) is None:
            env = gym.make(self.env_id, **self.env_kwargs)
            self._hold = ObservationHold(env.unwrapped.task_spec.dt)
            env.close()
        batch = np.asarray(obs, dtype=np.float64).reshape(-1, obs.shape[-1])
        start = None if episode_start is None else np.asarray(episode_start, dtype=bool).reshape(-1)
        if start is not None and start.shape != (batch.shape[0],):
            start = None
        out = self._hold(batch, start)
        return obs if out is batch else out.astype(np.float32).reshape(obs.shape)

    def predict(self, observation: Any, state: Any = None, episode_start: Any = None,
                deterministic: bool = True) -> tuple[np.ndarray, Any]:
        obs = np.asarray(observation, dtype=np.float32)
        width = self.model.observation_space.shape[-1]
        if obs.ndim not in (1, 2) or obs.shape[-1] != width:
            hint = ""
            if self.mode == "residual":
                hint = (f": a residual agent observes the {width}-wide wrapped observation (raw fields, base action, "
                        "history); for raw AUVFollow observations use agent.raw_policy(), or run it in "
                        "agent.env_wrapper(env)")
            raise ValueError(f"observation has shape {obs.shape}: this agent expects ({width},) or (N, {width})"
                             + hint)
        obs = self.normalize(self._held(obs, episode_start))
        if not self.recurrent:
            action, _ = self.model.predict(obs, deterministic=deterministic)
            return action, state
        # a recurrent policy keeps its LSTM state itself (callers such as evaluate_batched pass
        # state=None on every step), restarted per env where episode_start is set
        n = 1 if obs.ndim == 1 else obs.shape[0]
        if getattr(self, "_lstm_n", None) != n:
            self._lstm, self._lstm_n = None, n
            start = np.ones(n, dtype=bool)
        elif episode_start is None:
            start = np.zeros(n, dtype=bool)
        else:
            start = np.asarray(episode_start, dtype=bool).reshape(n)
        lstm = state if state is not None else getattr(self, "_lstm", None)
        action, self._lstm = self.model.predict(obs, state=lstm, episode_start=start, deterministic=deterministic)
        return action, (self._lstm if state is not None else state)


def load_agent(path: str | Path, name: str | None = None) -> Agent:
    """Load a run directory (its ``model.zip``) or a ``.zip`` model/checkpoint inside a run.

    The observation statistics are read from the JSON file beside the model
    (``vecnormalize.json`` or ``<prefix>_vecnormalize_<steps>_steps.json``), never from a
    pickle. The SB3 ``.zip`` itself can hold pickled objects: load only trusted files.

    Raises:
        FileNotFoundError: no model file (naming the newest checkpoint, if any), no
            ``config.yaml``, or a run trained with normalisation whose statistics file is missing.
        ValueError: a broken ``config.yaml``, model file or statistics file (naming the file).
    """
    p = Path(path)
    model_path = p / "model.zip" if p.is_dir() else p
    if not model_path.is_file():
        ckpts = _checkpoints(p) if p.is_dir() else []
        failed = _failure(p / "config.yaml") if p.is_dir() else None
        if failed:
            raise FileNotFoundError(f"model file {model_path} does not exist: the training failed ({failed}; "
                                    f"{p / 'config.yaml'} result.failed)"
                                    + (f"; its newest checkpoint from before is {ckpts[-1]}" if ckpts else ""))
        hint = (f"; the run has no final model (interrupted or still training?): its newest checkpoint is "
                f"{ckpts[-1]}" if ckpts else ": give a run directory or a model .zip")
        raise FileNotFoundError(f"model file {model_path} does not exist{hint}")
    check_size(model_path, "model")
    cfg_path = _run_config_path(model_path)
    if cfg_path is None:
        raise FileNotFoundError(f"no config.yaml next to {model_path} or in {model_path.parent.parent}: "
                                "not a run directory")
    config = read_run_config(cfg_path)
    if config["run"]["algo"] == "estimator":
        from agents.training.learned_estimator import load_estimator_agent

        return load_estimator_agent(model_path, config, name=name)
    _check_env(config, cfg_path)
    stats = None
    norm = config.get("normalize")
    if norm is None and _stats_path(model_path, ".json").is_file():
        raise ValueError(f"{cfg_path} records no normalize section, but {_stats_path(model_path, '.json')} beside "
                         f"{model_path} holds observation statistics: the model was trained with normalisation and "
                         "its configuration was edited or cut; restore the normalize section (or remove the "
                         "statistics file if the model truly reads raw observations)")
    if norm is not None and norm.get("norm_obs", True):
        json_path = _stats_path(model_path, ".json")
        if not json_path.is_file():
            pkl = json_path.with_suffix(".pkl")
            convert = (f"; {pkl} exists: if you trust it like code, convert it with "
                       f"`python -m agents.training.obs_stats {pkl}`" if pkl.is_file() else "")
            raise FileNotFoundError(f"observation-normalisation statistics {json_path} are missing: the agent was "
                                    f"trained with normalize={norm} ({cfg_path}) and gives wrong actions without "
                                    f"them{convert}")
        stats = read_obs_stats(json_path)
        check_against_config(stats, norm, json_path, cfg_path)
    if config["run"]["algo"] in BATCHED_ALGOS:
        from agents.training.batched_ppo import load_bppo_agent

        return load_bppo_agent(model_path, config, stats, name=name)
    try:
        model = _algo_class(config["run"]["algo"]).load(str(model_path), device="cpu")
    except Exception as exc:  # noqa: BLE001 (zipfile, pickle, torch and SB3 errors alike)
        algo = config["run"]["algo"]
        raise ValueError(f"{model_path} is not a {algo} model SB3 can load: {_one_line(exc)}") from None
    if stats is not None and stats.mean.shape != model.observation_space.shape:
        raise ValueError(f"{_stats_path(model_path, '.json')} has statistics for {stats.mean.shape} observations, "
                         f"the model observes {model.observation_space.shape}")
    return Agent(model, config, stats, name=name)


def _check_env(config: dict[str, Any], cfg_path: Path) -> None:
    """The run's env id and keywords make an env, or a one-line ValueError naming the file;
    read_run_config has checked that the id is registered."""
    run = config["run"]
    try:
        gym.make(run["env_id"], **(run.get("env_kwargs") or {})).close()
    except Exception as exc:  # noqa: BLE001 (any refusal of the env settings)
        raise ValueError(f"{cfg_path}: run.env_kwargs={run.get('env_kwargs')!r} are refused by {run['env_id']}: "
                         f"{_one_line(exc)}") from None


def evaluate_agent(agent: Agent | str | Path, seeds: Any = range(1000, 1010), *, env_id: str | None = None,
                   env_kwargs: dict | None = None, progress: bool = True):
    """The agent's metrics DataFrame from :func:`controllers.evaluation.evaluate` (one row per
    seed; ``own_*`` columns are NaN: an agent generates no reference of its own)."""
    from controllers.evaluation import evaluate

    if isinstance(agent, (str, Path)):
        agent = load_agent(agent)
    env_id = env_id or agent.env_id
    kw = agent.env_kwargs if env_kwargs is None else env_kwargs
    return evaluate(agent, env_id, seeds, env_kwargs=kw, env_wrapper=agent.env_wrapper, policy_name=agent.name,
                    progress=progress)
