"""Compatibility: the names ``agents.train`` offered before training became the
``agents.training`` package (``from agents.train import train, load_agent`` keeps working)."""

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
