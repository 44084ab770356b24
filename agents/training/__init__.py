"""Training: everything that makes and loads a run directory.

By concern (data flows one way: ``runner`` -> ``sb3`` / ``batched_ppo`` -> ``batched_env`` ->
``batched_obs`` -> ``history``, with ``config``, ``rundir`` and ``obs_stats`` below them):
``config`` (:class:`TrainConfig`, algorithms, zoo-format hyperparameters, every check made
before work starts), ``rundir`` (the run-directory contract: ``config.yaml``, statistics beside
each model, atomic writes), ``obs_stats`` (the observation statistics as plain JSON),
``history`` and ``residual`` (the residual agent), ``batched_obs`` (the agent's observation for
N envs), ``batched_env`` (the training env), ``batched_ppo`` (the batched trainer),
``vec_adapter`` (the native vector env for SB3), ``sb3`` (the Stable-Baselines3 path), ``runner``
(:func:`train`) and ``loading`` (:func:`load_agent`, :func:`evaluate_agent`). Hyperparameters in
rl-baselines3-zoo's format are in ``hyperparams/``.
"""

from __future__ import annotations

from agents.training.config import (
    ALGOS,
    HYPERPARAMS_DIR,
    MAX_N_ENVS,
    MODES,
    ConfigError,
    TrainConfig,
    TrainingFailed,
    TrainingInterrupted,
    check_env_id,
    check_hyperparams,
    load_hyperparams,
)
from agents.training.loading import Agent, evaluate_agent, load_agent
from agents.training.rundir import read_run_config, versions
from agents.training.runner import train

__all__ = ["ALGOS", "Agent", "ConfigError", "HYPERPARAMS_DIR", "MAX_N_ENVS", "MODES", "TrainConfig", "TrainingFailed",
           "TrainingInterrupted", "check_env_id", "check_hyperparams", "evaluate_agent", "load_agent",
           "load_hyperparams", "read_run_config", "train", "versions"]
