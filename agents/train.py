"""Training and evaluation of SB3 agents (PPO, SAC, TD3, RecurrentPPO) on AUVFollow, from scratch
or as a residual on top of one of the scripted controllers, and of the batched PPO ``algo="bppo"``
(:mod:`agents.batched_ppo`: plain torch on the native vector env; same run-directory contract,
with ``steps_done`` / ``train_seconds`` in ``config.yaml``, ``eval.csv`` and ``progress.csv``).

A run writes everything into its own directory ``<out>/<algo>-<env>-<mode>-seed<k>-<timestamp>/``:

* ``config.yaml``: the resolved configuration (run settings, hyperparameters, residual
  settings), the versions used (python, torch, stable-baselines3, gymnasium, numpy, git) and,
  at the end, ``result`` (steps, wall clock, ``interrupted``, the final score);
* ``model.zip``; ``vecnormalize.json`` (the observation statistics evaluation needs, plain
  JSON, see :mod:`agents.obs_stats`) and ``vecnormalize.pkl`` (SB3's pickle of the whole
  wrapper, read only by ``resume_from``);
* ``checkpoints/`` (``model_<steps>_steps.zip`` with the matching ``.json`` and ``.pkl``
  statistics);
* ``monitor/`` (per-episode Monitor CSVs of the training envs) and ``eval/evaluations.npz``
  (``EvalCallback``); ``tb/`` (TensorBoard, when ``tensorboard`` is importable).

Everything is validated before the run directory is created (hyperparameters and their
values, the ``normalize`` settings, ``out_dir``'s writability, a ``--resume`` checkpoint and its
statistics): a refused configuration leaves nothing behind. Ctrl-C during training saves the
model and the statistics, records ``interrupted: true`` and re-raises
(:class:`TrainingInterrupted`). Training that diverges (NaN or infinite values) or fails (the
algorithm raises, a write fails) writes no final ``model.zip``, records ``result.failed`` and
raises :class:`TrainingFailed`: such a run is never taken for a finished one. Files are written
through a temporary file beside them, removed if the write fails.

:func:`load_agent` turns a run directory (or a ``.zip`` inside it) back into a policy with
SB3's ``predict`` protocol plus the env wrapper it needs, for
:func:`controllers.evaluation.evaluate`. It never unpickles the statistics, but an SB3
``model.zip`` may itself hold pickled objects: load run directories and models only from
sources you would trust with code.
"""

from __future__ import annotations

import datetime as _dt
import inspect
import json
import math
import os
import platform
import re
import shutil
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import yaml

import auv_follow_env
from agents.obs_stats import ObsStats, check_against_config, read_obs_stats, stats_from_vecnormalize, write_obs_stats
from agents.residual import (
    DEFAULT_CONTROLLER,
    DEFAULT_HISTORY_LEN,
    DEFAULT_HISTORY_STRIDE,
    DEFAULT_SCALE,
    make_residual_wrapper,
)

__all__ = ["ALGOS", "MODES", "TrainConfig", "train", "load_hyperparams", "check_hyperparams", "load_agent",
           "Agent", "versions", "evaluate_agent", "HYPERPARAMS_DIR", "ConfigError", "TrainingInterrupted",
           "TrainingFailed", "MAX_N_ENVS"]

ALGOS: tuple[str, ...] = ("ppo", "sac", "td3", "recurrentppo", "bppo")
#: algorithms trained by our own batched loop (agents.batched_ppo) rather than SB3
BATCHED_ALGOS: tuple[str, ...] = ("bppo",)
#: checkpoint / evaluation intervals [env steps] when not given: (SB3 algorithms, batched algorithms)
DEFAULT_CHECKPOINT_FREQ = (100_000, 5_000_000)
DEFAULT_EVAL_FREQ = (50_000, 1_000_000)
#: algorithms whose policy carries a recurrent state (sb3-contrib's RecurrentPPO, an LSTM policy)
RECURRENT_ALGOS: tuple[str, ...] = ("recurrentppo",)
MODES: tuple[str, ...] = ("residual", "scratch")
VEC_KINDS = ("dummy", "native")
HYPERPARAMS_DIR = Path(__file__).with_name("hyperparams")
_ZOO_KEYS = ("n_timesteps", "policy", "n_envs", "normalize", "policy_kwargs", "noise_type", "noise_std")
MAX_N_ENVS = 4096  #: upper bound of n_envs (each env is a Python object in the DummyVecEnv)


class ConfigError(ValueError):
    """An invalid training/evaluation setting; ``field`` names the :class:`TrainConfig` field
    (the CLI maps it to its flag)."""

    def __init__(self, field: str, message: str) -> None:
        super().__init__(message)
        self.field = field


class TrainingInterrupted(KeyboardInterrupt):
    """Ctrl-C during :func:`train`, raised after the model, the statistics and ``config.yaml``
    (``interrupted: true``) were saved in ``run``."""

    def __init__(self, run: Path, num_timesteps: int) -> None:
        super().__init__(f"training interrupted at {num_timesteps} steps; saved in {run}")
        self.run = run
        self.num_timesteps = num_timesteps


class TrainingFailed(RuntimeError):
    """Training stopped on an error after the run directory was created: it diverged (a NaN or
    infinite action, loss or parameter) or the algorithm or a write failed. ``config.yaml``
    records ``result.failed`` (the reason) and no final ``model.zip`` is written, so the run is
    never taken for a finished one; checkpoints from before the failure are kept."""

    def __init__(self, run: Path, num_timesteps: int, reason: str) -> None:
        super().__init__(f"training failed at {num_timesteps:,} steps: {reason}; nothing was saved as a finished "
                         f"run (run directory {run})")
        self.run = run
        self.num_timesteps = num_timesteps
        self.reason = reason


def _one_line(exc: BaseException) -> str:
    return f"{type(exc).__name__}: " + " ".join(str(exc).split())


def _algo_class(algo: str):
    from stable_baselines3 import PPO, SAC, TD3

    classes = {"ppo": PPO, "sac": SAC, "td3": TD3}
    if algo in BATCHED_ALGOS:
        from agents.batched_ppo import BatchedPPO

        return BatchedPPO
    if algo in RECURRENT_ALGOS:
        from sb3_contrib import RecurrentPPO

        classes["recurrentppo"] = RecurrentPPO
    if algo not in classes:
        raise ValueError(f"algo={algo!r} is unknown: valid algorithms are {list(ALGOS)}")
    return classes[algo]


def check_env_id(env_id: str, *, allow_any: bool = False) -> None:
    """Raise ``ValueError`` unless ``env_id`` is a registered AUVFollow id (or any registered
    id when ``allow_any``)."""
    valid = list(auv_follow_env.ENV_IDS) + list(getattr(auv_follow_env, "ENV_IDS_V1", ()))
    if env_id in valid or (allow_any and env_id in gym.registry):
        return
    raise ValueError(f"env_id={env_id!r} is unknown: valid ids are {valid}")


def check_tier_training_seeds(env_id: str, seeds: list[int]) -> None:
    """On a v1 tier, refuse training/evaluation-callback seeds that could be test seeds
    (``auv_follow_env.check_training_seeds``: every published test seed is above the limit)."""
    check = getattr(auv_follow_env, "check_training_seeds", None)
    if check is not None and env_id in getattr(auv_follow_env, "ENV_IDS_V1", ()):
        check(seeds, name=f"training seeds of {env_id}")


def _eval_zoo(value: Any, key: str = "value") -> Any:
    """rl-zoo writes dicts as strings like ``"dict(net_arch=[64, 64])"``; read those without
    ``eval`` (:func:`agents.zoo_parse.parse_zoo_value`: literals, ``dict(...)`` and
    ``nn.<activation>`` only)."""
    if isinstance(value, str) and value.strip().startswith("dict("):
        from agents.zoo_parse import parse_zoo_value

        return parse_zoo_value(value, f"hyperparameter {key}")
    return value


def load_hyperparams(algo: str, env_id: str, path: str | Path | None = None,
                     overrides: dict[str, Any] | None = None, mode: str | None = None) -> dict[str, Any]:
    """Hyperparameters for ``algo`` on ``env_id`` from an rl-zoo3-format YAML file
    (``agents/hyperparams/<algo>.yml`` by default): the ``default`` section updated by the
    ``residual`` section (if ``mode="residual"`` and the file has one), then by the env id's
    section, then by ``overrides``. Strings ``"dict(...)"`` are parsed (never evaluated).

    rl-zoo3 reads only the env id's section (else ``default``), so the shipped files start each
    env id's section from the default with YAML's merge key (``<<: *default``); a value of the
    env id's section equal to the default's counts as the default's, so the ``residual``
    section still overrides it."""
    _algo_class(algo)
    path = Path(path) if path is not None else HYPERPARAMS_DIR / f"{algo}.yml"
    if not path.is_file():
        raise FileNotFoundError(f"hyperparameter file {path} does not exist")
    with open(path) as f:
        table = yaml.safe_load(f) or {}
    if not isinstance(table, dict) or not all(isinstance(table.get(k) or {}, dict)
                                              for k in ("default", "residual", env_id)):
        raise ValueError(f"hyperparameter file {path} is not in rl-zoo's format: expected a mapping of sections "
                         "(default, residual, <env id>) to mappings of hyperparameters")
    default = dict(table.get("default") or {})
    hp = dict(default)
    if mode == "residual":
        hp.update(table.get("residual") or {})
    own = {k: v for k, v in (table.get(env_id) or {}).items()
           if k not in default or v != default[k] or type(v) is not type(default[k])}
    hp.update(own)  # (the keys merged in from the default with "<<: *default" are left out)
    hp.update(overrides or {})
    return {k: _eval_zoo(v, k) for k, v in hp.items()}


def versions() -> dict[str, str]:
    """Versions of the software a result depends on, and the git commit of this checkout."""
    import stable_baselines3
    import torch

    try:
        root = Path(__file__).resolve().parent.parent
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True,
                                timeout=10).stdout.strip() or "unknown"
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "agents"], cwd=root, capture_output=True,
                               text=True, timeout=10).stdout.strip()
        if dirty:
            commit += " (agents/ modified)"
    except (OSError, subprocess.SubprocessError):
        commit = "unknown"
    return {"python": platform.python_version(), "torch": torch.__version__,
            "stable_baselines3": stable_baselines3.__version__, "gymnasium": gym.__version__,
            "numpy": np.__version__, "auv_follow_env": auv_follow_env.__version__, "git_commit": commit,
            "platform": platform.platform()}


# --- hyperparameter checks ---------------------------------------------------------------

#: (lower bound, lower bound inclusive, upper bound) of numeric hyperparameters
_NUMERIC_BOUNDS: dict[str, tuple[float, bool, float]] = {
    "learning_rate": (0.0, False, 1.0), "clip_range": (0.0, False, math.inf),
    "max_grad_norm": (0.0, False, math.inf), "n_timesteps": (0.0, False, math.inf),
    "gamma": (0.0, False, 1.0), "gae_lambda": (0.0, True, 1.0), "tau": (0.0, False, 1.0),
    "vf_coef": (0.0, True, math.inf), "ent_coef": (0.0, True, math.inf), "noise_std": (0.0, True, math.inf),
    "target_policy_noise": (0.0, True, math.inf), "target_noise_clip": (0.0, True, math.inf),
    "target_kl": (0.0, False, math.inf), "clip_range_vf": (0.0, False, math.inf),
    "n_steps": (1, True, math.inf), "batch_size": (1, True, math.inf), "n_epochs": (1, True, math.inf),
    "buffer_size": (1, True, math.inf), "policy_delay": (1, True, math.inf), "n_envs": (1, True, MAX_N_ENVS),
    "learning_starts": (0, True, math.inf), "target_update_interval": (1, True, math.inf),
    "stats_window_size": (1, True, math.inf), "torch_threads": (1, True, 64), "n_eval_seeds": (1, True, 10_000),
    "obs_norm_window": (0, True, math.inf), "distill_steps": (0, True, math.inf)}
#: hyperparameters whose value must be a whole number (an int, or a float such as 1.0e+6 that is one; never a bool)
_INTEGER_KEYS = frozenset({"n_steps", "batch_size", "n_epochs", "buffer_size", "policy_delay", "n_envs",
                           "learning_starts", "target_update_interval", "stats_window_size", "sde_sample_freq",
                           "gradient_steps", "torch_threads", "n_eval_seeds", "obs_norm_window", "distill_steps"})
#: allowed values of the VecNormalize settings in ``normalize=dict(...)`` (bools, or (lower, upper] numbers)
_NORMALIZE_BOUNDS: dict[str, tuple[float, float] | None] = {
    "norm_obs": None, "norm_reward": None, "clip_obs": (0.0, math.inf), "clip_reward": (0.0, math.inf),
    "gamma": (0.0, 1.0), "epsilon": (0.0, math.inf)}
#: policy_kwargs log_std_init: the policy's initial std is exp(log_std_init) in action units ([-1, 1])
_LOG_STD_INIT_RANGE = (-20.0, 2.0)
#: set by TrainConfig / train, not through the hyperparameters
_RESERVED_KEYS = {"seed": "seed", "device": "(always cpu)", "verbose": "verbose", "tensorboard_log": "tensorboard",
                  "env": "env_id", "_init_setup_model": "(internal)", "action_noise": "noise_type/noise_std"}
_NORMALIZE_KEYS = ("norm_obs", "norm_reward", "clip_obs", "clip_reward", "gamma", "epsilon")


def _bounds_text(lo: float, inclusive: bool, hi: float) -> str:
    if hi == math.inf:
        return f"{'>=' if inclusive else '>'} {lo:g}"
    return f"in {'[' if inclusive else '('}{lo:g}, {hi:g}]"


def _finite(v: Any) -> bool:
    """``v`` is a finite number (a huge int counts as finite; floats are checked)."""
    if isinstance(v, (int, np.integer)):
        return True
    return math.isfinite(v)


def _check_number(key: str, v: Any) -> Any:
    if isinstance(v, str):  # YAML 1.1 reads 1e-4 and 3.0e6 as strings; rl-zoo accepts them as numbers
        try:
            v = float(v)
        except ValueError:
            pass
    is_num = isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))
    if key in _INTEGER_KEYS:
        if not (is_num and _finite(v) and (isinstance(v, (int, np.integer)) or float(v).is_integer())):
            lo, inclusive, hi = _NUMERIC_BOUNDS.get(key, (-math.inf, True, math.inf))
            what = "" if lo == -math.inf else " " + _bounds_text(lo, inclusive, hi)
            raise ConfigError("hyperparams", f"hyperparameter {key}={v!r} is invalid: must be a whole number{what} "
                                             "(an integer, or a float such as 1.0e+6 that is one)")
        v = int(v)
        if key == "gradient_steps" and not (v >= 1 or v == -1):
            raise ConfigError("hyperparams", f"hyperparameter gradient_steps={v!r} is invalid: must be >= 1 or -1")
    elif key in _NUMERIC_BOUNDS:
        try:
            ok = is_num and math.isfinite(float(v))
        except OverflowError:  # an int beyond float's range
            ok = False
        if not ok:
            raise ConfigError("hyperparams", f"hyperparameter {key}={v!r} is invalid: must be a finite number "
                                             f"{_bounds_text(*_NUMERIC_BOUNDS[key])}")
        v = float(v)
    if key in _NUMERIC_BOUNDS:
        lo, inclusive, hi = _NUMERIC_BOUNDS[key]
        if not ((v >= lo if inclusive else v > lo) and v <= hi):
            raise ConfigError("hyperparams", f"hyperparameter {key}={v!r} is invalid: must be "
                                             f"{_bounds_text(lo, inclusive, hi)}")
    return float(v) if key in _NUMERIC_BOUNDS and key not in _INTEGER_KEYS else v


def _check_normalize(v: dict[str, Any]) -> dict[str, Any]:
    """The VecNormalize settings of ``normalize=dict(...)``, each checked (bools; finite numbers > 0,
    ``gamma`` in (0, 1]); whole numbers come back as floats."""
    bad = sorted(map(str, set(v) - set(_NORMALIZE_KEYS)))
    if bad:
        raise ConfigError("hyperparams", f"hyperparameter normalize has unknown key(s) {bad}: valid "
                                         f"keys are {list(_NORMALIZE_KEYS)}")
    out = {}
    for k, x in v.items():
        bounds = _NORMALIZE_BOUNDS[k]
        if bounds is None:
            if not isinstance(x, bool):
                raise ConfigError("hyperparams", f"hyperparameter normalize {k}={x!r} is invalid: must be true or "
                                                 "false")
            out[k] = x
            continue
        lo, hi = bounds
        y = x
        if isinstance(y, str):
            try:
                y = float(y)
            except ValueError:
                pass
        ok = isinstance(y, (int, float, np.integer, np.floating)) and not isinstance(y, (bool, np.bool_))
        try:
            ok = ok and math.isfinite(float(y)) and lo < float(y) <= hi
        except OverflowError:
            ok = False
        if not ok:
            raise ConfigError("hyperparams", f"hyperparameter normalize {k}={x!r} is invalid: must be a finite number "
                                             f"{_bounds_text(lo, False, hi)}")
        out[k] = float(y)
    return out


#: bounds of policy_kwargs net_arch: hidden layers, and units per layer
_MAX_LAYERS, _MAX_HIDDEN = 16, 8192
#: the keys of a net_arch dict each algorithm reads (SB3 ignores any other key without a word)
_NET_ARCH_KEYS = {"ppo": ("pi", "vf"), "recurrentppo": ("pi", "vf"), "bppo": ("pi", "vf"), "sac": ("pi", "qf"),
                  "td3": ("pi", "qf")}


def _check_net_arch(algo: str, arch: Any) -> Any:
    """policy_kwargs net_arch: a list of hidden sizes (whole numbers in [1, 8192], at most 16), or
    a dict of such lists under the keys the algorithm reads; whole floats become ints."""
    keys = _NET_ARCH_KEYS.get(algo, ("pi", "vf"))
    what = (f"a list of at most {_MAX_LAYERS} hidden sizes (whole numbers in [1, {_MAX_HIDDEN}]) or "
            f"dict({', '.join(k + '=[...]' for k in keys)})")

    def sizes(v: Any) -> list[int]:
        ok = isinstance(v, (list, tuple)) and len(v) <= _MAX_LAYERS
        out = []
        for h in v if ok else ():
            good = isinstance(h, (int, float, np.integer, np.floating)) and not isinstance(h, (bool, np.bool_))
            good = good and (isinstance(h, (int, np.integer)) or (math.isfinite(h) and float(h).is_integer()))
            if not (good and 1 <= h <= _MAX_HIDDEN):
                ok = False
                break
            out.append(int(h))
        if not ok:
            raise ConfigError("hyperparams", f"hyperparameter policy_kwargs net_arch={arch!r} is invalid: must be "
                                             f"{what}")
        return out

    if isinstance(arch, dict):
        bad = sorted(map(str, set(arch) - set(keys)))
        if bad:
            raise ConfigError("hyperparams", f"hyperparameter policy_kwargs net_arch has key(s) {bad} that {algo} "
                                             f"does not read: valid keys are {list(keys)}")
        return {k: sizes(v) for k, v in arch.items()}
    return sizes(arch)


def _check_log_std_init(x: Any) -> float:
    lo, hi = _LOG_STD_INIT_RANGE
    y = x
    if isinstance(y, str):
        try:
            y = float(y)
        except ValueError:
            pass
    ok = isinstance(y, (int, float, np.integer, np.floating)) and not isinstance(y, (bool, np.bool_))
    try:
        ok = ok and math.isfinite(float(y)) and lo <= float(y) <= hi
    except OverflowError:
        ok = False
    if not ok:
        raise ConfigError("hyperparams", f"hyperparameter policy_kwargs log_std_init={x!r} is invalid: must be a "
                                         f"finite number in [{lo:g}, {hi:g}] (the policy's initial std is "
                                         "exp(log_std_init) in action units)")
    return float(y)


def check_hyperparams(algo: str, hp: dict[str, Any]) -> dict[str, Any]:
    """Validate resolved hyperparameters (after :func:`load_hyperparams`) for ``algo`` and return
    them with whole numbers as ``int``.

    Checks: every key is a parameter of the algorithm's constructor or one of rl-zoo's keys
    (``n_timesteps``, ``policy``, ``n_envs``, ``normalize``, ``policy_kwargs``, ``noise_type``,
    ``noise_std``); numbers are finite and in range; ``normalize`` is a bool or a dict of
    VecNormalize settings; ``policy_kwargs`` is a dict. The algorithm's own checks run when
    :func:`train` builds the model (before the run directory is created).

    Raises:
        ConfigError: (``field="hyperparams"``) naming the key, its value and what is allowed.
    """
    cls = _algo_class(algo)
    params = {k: p.default for k, p in inspect.signature(cls.__init__).parameters.items()
              if k not in ("self", "policy")}
    out: dict[str, Any] = {}
    for key, v in hp.items():
        if key in _RESERVED_KEYS:
            raise ConfigError("hyperparams", f"hyperparameter {key!r} cannot be set: it is set by "
                                             f"{_RESERVED_KEYS[key]}")
        if key not in params and key not in _ZOO_KEYS:
            valid = sorted((set(params) - set(_RESERVED_KEYS)) | set(_ZOO_KEYS))
            raise ConfigError("hyperparams", f"hyperparameter {key!r} is unknown for {algo}: valid keys are {valid}")
        if key == "ent_coef" and isinstance(v, str):
            if not re.fullmatch(r"auto(_[0-9.eE+-]+)?", v) or algo != "sac":
                raise ConfigError("hyperparams", f"hyperparameter ent_coef={v!r} is invalid: must be a number >= 0"
                                                 + (" or 'auto' / 'auto_<init>'" if algo == "sac" else ""))
        elif key == "train_freq" and isinstance(v, (list, tuple)):
            if len(v) != 2 or v[1] not in ("step", "episode"):
                raise ConfigError("hyperparams", f"hyperparameter train_freq={v!r} is invalid: must be a whole "
                                                 "number >= 1 or [n, 'step' | 'episode']")
            v = [_check_number("n_steps", v[0]), v[1]]
        elif key == "train_freq":
            v = _check_number("n_steps", v)
        elif key == "normalize":
            if isinstance(v, dict):
                v = _check_normalize(v)
            elif not isinstance(v, bool):
                raise ConfigError("hyperparams", f"hyperparameter normalize={v!r} is invalid: must be true, false "
                                                 "or dict(norm_obs=..., norm_reward=..., ...)")
        elif key == "policy_kwargs":
            if v is not None and not isinstance(v, dict):
                raise ConfigError("hyperparams", f"hyperparameter policy_kwargs={v!r} is invalid: must be a dict")
            if v is not None and "log_std_init" in v:
                v = {**v, "log_std_init": _check_log_std_init(v["log_std_init"])}
            if v is not None and "net_arch" in v:
                v = {**v, "net_arch": _check_net_arch(algo, v["net_arch"])}
        elif key == "policy":
            if not isinstance(v, str):
                raise ConfigError("hyperparams", f"hyperparameter policy={v!r} is invalid: must be a policy name "
                                                 "such as 'MlpPolicy'")
        elif key == "noise_type":
            if v not in (None, "normal", "ornstein-uhlenbeck"):
                raise ConfigError("hyperparams", f"hyperparameter noise_type={v!r} is unknown: valid types are "
                                                 "['normal', 'ornstein-uhlenbeck']")
        elif v is None and params.get(key, 0) is None:
            pass
        elif key in _NUMERIC_BOUNDS or key in _INTEGER_KEYS:
            v = _check_number(key, v)
        elif isinstance(params.get(key), bool) and not isinstance(v, bool):
            raise ConfigError("hyperparams", f"hyperparameter {key}={v!r} is invalid: must be true or false")
        out[key] = v
    if "n_timesteps" not in out:
        out["n_timesteps"] = None
    return out


@dataclass
class TrainConfig:
    """One training run (everything not given comes from the hyperparameter YAML)."""

    algo: str = "ppo"  #: one of ALGOS
    env_id: str = "AUVFollow-S4-v0"  #: a registered AUVFollow id
    env_kwargs: dict[str, Any] = field(default_factory=dict)  #: scenario overrides for gym.make
    mode: str = "residual"  #: "residual" (on top of `controller`) or "scratch"
    controller: str = DEFAULT_CONTROLLER  #: base controller of a residual agent
    scale: float = DEFAULT_SCALE  #: residual authority (fraction of the force limits)
    include_base_action: bool = True  #: append the base action to the agent's observation
    history_len: int | None = None
    """Lagged delayed-target velocity differences (None: 4 for residual agents on v0 ids; 0 on v1 ids,
    off on the acoustic link, and from scratch)."""
    history_stride: int = DEFAULT_HISTORY_STRIDE  #: steps between lagged samples
    total_timesteps: int | None = None  #: env steps (None: the YAML's n_timesteps)
    max_minutes: float | None = None  #: wall-clock budget; training stops when it runs out
    seed: int = 0  #: seeds the model and the training envs (env i: seed + i)
    n_envs: int | None = None  #: parallel training envs (None: the YAML's); at most MAX_N_ENVS
    vec: str = "dummy"  #: training VecEnv: "dummy" (SB3 DummyVecEnv) or "native" (batched AUVFollowVectorEnv)
    out_dir: str = "runs"  #: parent of the run directory
    run_name: str | None = None
    """Run directory name, one path component (None: ``<algo>-<env>-<mode>-seed<k>-<timestamp>``)."""
    checkpoint_freq: int | None = None
    """Env steps between checkpoints (0: none; None: 100,000, or 5,000,000 for bppo)."""
    eval_freq: int | None = None
    """Env steps between evaluations (0: none; None: 50,000, or 1,000,000 for bppo)."""
    observation: str | None = None
    """The agent's observation: "raw" or "estimator" (the estimator block, agents.batched_obs);
    None: "estimator" for bppo on v1 ids, else "raw". SB3 algorithms take "estimator" in residual mode only."""
    eval_episodes: int = 3  #: episodes per evaluation (and of the final score)
    eval_seed: int = 500  #: seed of the EvalCallback env (distinct from training and test seeds)
    resume_from: str | None = None  #: checkpoint/model .zip to continue (keeps num_timesteps)
    hyperparams_file: str | None = None  #: YAML file (None: agents/hyperparams/<algo>.yml)
    hyperparams: dict[str, Any] = field(default_factory=dict)  #: overrides of the YAML entries
    progress_bar: bool = True  #: progress bar on a terminal, a line per 10 % otherwise
    tensorboard: bool = True  #: TensorBoard logs if tensorboard is importable
    final_eval: bool = True  #: score the final model on eval_episodes seeds (eval_seed, ...) and print it
    verbose: int = 0  #: SB3 verbosity

    def validate(self) -> None:
        """Raise :class:`ConfigError` (a ``ValueError``) naming the first invalid field."""
        try:
            _algo_class(self.algo)
            check_env_id(self.env_id, allow_any=self.mode == "scratch")
        except ValueError as exc:
            raise ConfigError("algo" if "algo" in str(exc) else "env_id", str(exc)) from None
        if self.mode not in MODES:
            raise ConfigError("mode", f"mode={self.mode!r} is unknown: valid modes are {list(MODES)}")
        if self.vec not in VEC_KINDS:
            raise ConfigError("vec", f"vec={self.vec!r} is unknown: valid kinds are {list(VEC_KINDS)}")
        if self.observation is not None and self.observation not in ("raw", "estimator"):
            raise ConfigError("observation", f"observation={self.observation!r} is unknown: valid kinds are "
                                             "['raw', 'estimator']")
        if (self.algo not in BATCHED_ALGOS and self.mode == "scratch"
                and self.resolved_observation() == "estimator"):
            raise ConfigError("observation", f"observation='estimator' with algo={self.algo!r} needs "
                                             "mode='residual' (or algo='bppo', which takes it in both modes)")
        if self.vec == "native" and self.mode != "scratch" and self.algo not in BATCHED_ALGOS:
            raise ConfigError("vec", "vec='native' trains from scratch only (mode='scratch'): the residual wrapper "
                                     "is a per-env gymnasium wrapper; use vec='dummy' for residual agents")
        if self.mode == "residual":
            try:
                make_residual_wrapper(**self.residual_kwargs())
            except ValueError as exc:
                name = str(exc).split("=", 1)[0]
                raise ConfigError(name if name in self.residual_kwargs() else "controller", str(exc)) from None
        if not isinstance(self.env_kwargs, dict):
            raise ConfigError("env_kwargs", f"env_kwargs={self.env_kwargs!r} is invalid: must be a dict")
        if not isinstance(self.hyperparams, dict):
            raise ConfigError("hyperparams", f"hyperparams={self.hyperparams!r} is invalid: must be a dict")
        for name, lo, hi in (("total_timesteps", 1, math.inf), ("n_envs", 1, MAX_N_ENVS),
                             ("checkpoint_freq", 0, math.inf), ("eval_freq", 0, math.inf),
                             ("history_len", 0, math.inf),
                             ("eval_episodes", 1, 10_000), ("seed", 0, 2**32 - 1),
                             ("eval_seed", 0, 2**32 - 1), ("verbose", 0, 2)):
            v = getattr(self, name)
            if v is None and name in ("total_timesteps", "n_envs", "checkpoint_freq", "eval_freq", "history_len"):
                continue
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not lo <= v <= hi:
                allowed = f"an integer >= {lo}" if hi == math.inf else f"an integer in [{lo}, {hi}]"
                raise ConfigError(name, f"{name}={v!r} is invalid: must be {allowed}")
        if self.max_minutes is not None and (isinstance(self.max_minutes, bool) or not isinstance(
                self.max_minutes, (int, float)) or not (math.isfinite(self.max_minutes) and self.max_minutes > 0)):
            raise ConfigError("max_minutes", f"max_minutes={self.max_minutes!r} is invalid: must be a finite "
                                             "number > 0")
        if self.run_name is not None:
            n = self.run_name
            if (not isinstance(n, str) or n in ("", ".", "..") or "/" in n or "\\" in n or "\0" in n
                    or Path(n).name != n):
                raise ConfigError("run_name", f"run_name={n!r} is invalid: must be a single directory name (no "
                                              "path separators, not '.' or '..'); use out_dir for the parent")
        for name in ("include_base_action", "progress_bar", "tensorboard", "final_eval"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(name, f"{name}={getattr(self, name)!r} is invalid: must be True or False")
        if self.mode != "residual":  # recorded (and handed to bppo's observation) in every mode
            try:
                from agents.residual import _check
                from controllers import ALL_CONTROLLERS

                _check(ALL_CONTROLLERS[0], self.scale, self.resolved_history_len(), self.history_stride)
            except ValueError as exc:
                name = str(exc).split("=", 1)[0]
                raise ConfigError(name if name in self.residual_kwargs() else "scale", str(exc)) from None
        if not isinstance(self.out_dir, (str, Path)) or str(self.out_dir) == "":
            raise ConfigError("out_dir", f"out_dir={self.out_dir!r} is invalid: must be a directory path")
        out = Path(self.out_dir)
        if out.exists() and not out.is_dir():
            raise ConfigError("out_dir", f"out_dir={self.out_dir!r} is invalid: it exists and is not a directory")
        anc = out
        while not anc.exists() and anc != anc.parent:
            anc = anc.parent
        if not anc.is_dir():
            raise ConfigError("out_dir", f"out_dir={self.out_dir!r} cannot be created: {anc} is not a directory")
        if not os.access(anc, os.W_OK):
            raise ConfigError("out_dir", f"out_dir={self.out_dir!r} cannot be written: {anc} is not writable "
                                         "(read-only file system or no permission)")
        try:
            check_tier_training_seeds(self.env_id, [self.seed + i for i in range(self.n_envs or 16)]
                                      + [self.eval_seed])
        except ValueError as exc:
            raise ConfigError("seed", str(exc)) from None
        if self.resume_from is not None and not Path(self.resume_from).is_file():
            raise ConfigError("resume_from", f"resume_from={self.resume_from!r}: no such model file")
        if self.hyperparams_file is not None and not Path(self.hyperparams_file).is_file():
            raise ConfigError("hyperparams_file", f"hyperparams_file={self.hyperparams_file!r}: no such file")

    def resolved_history_len(self) -> int:
        if self.history_len is not None:
            return self.history_len
        return 0 if str(self.env_id).endswith("-v1") or self.mode == "scratch" else DEFAULT_HISTORY_LEN

    def resolved_observation(self) -> str:
        if self.observation is not None:
            return self.observation
        return "estimator" if self.algo in BATCHED_ALGOS and str(self.env_id).endswith("-v1") else "raw"

    def resolved_freqs(self) -> tuple[int, int]:
        """(checkpoint_freq, eval_freq) with None replaced by the algorithm's default."""
        b = int(self.algo in BATCHED_ALGOS)
        return (DEFAULT_CHECKPOINT_FREQ[b] if self.checkpoint_freq is None else int(self.checkpoint_freq),
                DEFAULT_EVAL_FREQ[b] if self.eval_freq is None else int(self.eval_freq))

    def residual_kwargs(self) -> dict[str, Any]:
        kw = {"controller": self.controller, "scale": self.scale, "include_base_action": self.include_base_action,
              "history_len": self.resolved_history_len(), "history_stride": self.history_stride,
              "observer_feed": "applied"}
        if self.resolved_observation() != "raw":
            kw["observation"] = self.resolved_observation()
        return kw

    def builder_kwargs(self) -> dict[str, Any]:
        """The :class:`agents.batched_obs.ObservationBuilder` settings of this run."""
        return {"mode": self.mode, "controller": self.controller if self.mode == "residual" else None,
                "scale": self.scale, "include_base_action": self.include_base_action,
                "observation": self.resolved_observation(), "history_len": self.resolved_history_len(),
                "history_stride": self.history_stride, "observer_feed": "applied"}


def _wrapper(mode: str, residual: dict[str, Any] | None):
    return make_residual_wrapper(**residual) if mode == "residual" else None


def _make_venv(env_id: str, env_kwargs: dict, n_envs: int, seed: int, mode: str, residual: dict | None,
               monitor_dir: str | None, vec: str = "dummy"):
    from stable_baselines3.common.env_util import make_vec_env

    if vec == "native":
        from agents.vec_adapter import NativeVecEnv

        return NativeVecEnv(env_id, n_envs, seed=seed, env_kwargs=env_kwargs)
    return make_vec_env(env_id, n_envs=n_envs, seed=seed, env_kwargs=env_kwargs or None,
                        wrapper_class=_wrapper(mode, residual), monitor_dir=monitor_dir)


def _normalize_kwargs(normalize: Any, gamma: float) -> dict[str, Any] | None:
    """VecNormalize's keywords: None for ``normalize=False``; ``True`` and a dict (even an empty
    one, as rl-zoo reads ``dict()``) normalise, with ``gamma`` the algorithm's unless given."""
    if normalize is False or normalize is None:
        return None
    kw = dict(normalize) if isinstance(normalize, dict) else {}
    kw.setdefault("gamma", gamma)
    return kw


def _action_noise(hp: dict[str, Any], n_actions: int):
    from stable_baselines3.common.noise import NormalActionNoise, OrnsteinUhlenbeckActionNoise

    kind, std = hp.get("noise_type"), float(hp.get("noise_std", 0.1))
    if kind is None:
        return None
    if kind == "normal":
        return NormalActionNoise(np.zeros(n_actions), std * np.ones(n_actions))
    if kind == "ornstein-uhlenbeck":
        return OrnsteinUhlenbeckActionNoise(np.zeros(n_actions), std * np.ones(n_actions))
    raise ValueError(f"noise_type={kind!r} is unknown: valid types are ['normal', 'ornstein-uhlenbeck']")


def _tensorboard_available() -> bool:
    try:
        import tensorboard  # noqa: F401
    except ImportError:
        return False
    return True


def _wall_clock_callback(max_seconds: float):
    from stable_baselines3.common.callbacks import BaseCallback

    class StopOnWallClock(BaseCallback):
        """Stop training once ``max_seconds`` of wall clock have passed since it started."""

        def _on_training_start(self) -> None:
            self.t0 = time.perf_counter()

        def _on_step(self) -> bool:
            return time.perf_counter() - self.t0 < max_seconds

    return StopOnWallClock()


class _StopOnSigint:
    """Ctrl-C (SIGINT) during ``learn`` asks training to stop at the next step instead of
    raising wherever the signal lands (inside torch, numba or a library that catches and
    continues, which made an interrupt occasionally ineffective). A second Ctrl-C raises
    KeyboardInterrupt at once. Only installed in the main thread."""

    def __init__(self) -> None:
        self.requested = False
        self._old: Any = None

    def __enter__(self) -> _StopOnSigint:
        import signal
        import threading

        if threading.current_thread() is threading.main_thread():
            self._old = signal.signal(signal.SIGINT, self._handle)
        return self

    def _handle(self, signum: int, frame: Any) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True

    def __exit__(self, *exc: Any) -> None:
        import signal

        if self._old is not None:
            signal.signal(signal.SIGINT, self._old)

    def callback(self):
        from stable_baselines3.common.callbacks import BaseCallback

        flag = self

        class StopOnSigint(BaseCallback):
            def _on_step(self) -> bool:
                return not flag.requested

        return StopOnSigint()


class _Progress:
    """Training progress over ``total`` new steps, never past 100 %: a tqdm bar on a terminal,
    otherwise a plain line per 10 % (no carriage returns or escape codes in logs)."""

    def __init__(self, total: int, start: int, enabled: bool, stream: Any = None) -> None:
        self.total, self.start, self.enabled = total, start, enabled
        self.stream = stream if stream is not None else sys.stderr
        self.bar = None
        self.shown = 0
        self.next_line = 0.1
        if enabled and getattr(self.stream, "isatty", lambda: False)():
            from tqdm.auto import tqdm

            self.bar = tqdm(total=total, unit="step", unit_scale=True, desc="training", file=self.stream)

    def update(self, num_timesteps: int) -> None:
        if not self.enabled:
            return
        done = min(max(num_timesteps - self.start, 0), self.total)
        if self.bar is not None:
            self.bar.update(done - self.shown)
        else:
            while done >= self.next_line * self.total - 1e-9 and self.next_line <= 1.0 + 1e-9:
                print(f"training: {round(self.next_line * 100)}% ({done:,}/{self.total:,} steps)", file=self.stream,
                      flush=True)
                self.next_line += 0.1
        self.shown = done

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def _progress_callback(progress: _Progress):
    from stable_baselines3.common.callbacks import BaseCallback

    class ProgressCallback(BaseCallback):
        def _on_step(self) -> bool:
            progress.update(self.num_timesteps)
            return True

    return ProgressCallback()


def _checkpoint_callback(save_freq: int, path: str):
    """SB3's CheckpointCallback that also writes the JSON statistics beside each pickle."""
    from stable_baselines3.common.callbacks import CheckpointCallback

    class Checkpoint(CheckpointCallback):
        def _on_step(self) -> bool:
            due = self.n_calls % self.save_freq == 0
            out = super()._on_step()
            vn = self.model.get_vec_normalize_env()
            if due and vn is not None:
                write_obs_stats(vn, self._checkpoint_path("vecnormalize_", extension="json"))
            return out

    return Checkpoint(save_freq, path, name_prefix="model", save_vecnormalize=True)


_CKPT = re.compile(r"^(?P<prefix>.+)_(?P<steps>\d+)_steps$")


def _stats_path(model_path: Path, suffix: str) -> Path:
    """The normalisation statistics saved with a model (``vecnormalize<suffix>``) or a checkpoint
    (``<prefix>_vecnormalize_<steps>_steps<suffix>``); other names: ``vecnormalize<suffix>`` beside."""
    m = _CKPT.match(model_path.stem)
    if model_path.name != "model.zip" and m:
        return model_path.with_name(f"{m['prefix']}_vecnormalize_{m['steps']}_steps{suffix}")
    return model_path.with_name(f"vecnormalize{suffix}")


def _checkpoints(run: Path) -> list[Path]:
    """Checkpoints of a run, oldest first (by step count)."""
    found = [(int(m["steps"]), p) for p in (run / "checkpoints").glob("*.zip") if (m := _CKPT.match(p.stem))]
    return [p for _, p in sorted(found)]


def _run_config_path(model_path: Path) -> Path | None:
    for d in (model_path.parent, model_path.parent.parent):
        if (d / "config.yaml").is_file():
            return d / "config.yaml"
    return None


def read_run_config(path: str | Path) -> dict[str, Any]:
    """A run's ``config.yaml``, checked: a mapping with a ``run`` section naming a known algo and mode.

    Raises:
        ValueError: broken YAML or not a run configuration (the message names the file).
    """
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path} is not valid YAML ({_one_line(exc)})") from None
    what = "a run configuration written by auv-follow train (a mapping with a 'run' section)"
    if not isinstance(data, dict) or not isinstance(data.get("run"), dict):
        raise ValueError(f"{path} is {'empty' if data is None else 'not ' + what}: expected {what}")
    run = data["run"]
    for key, valid in (("algo", ALGOS), ("mode", MODES)):
        if run.get(key) not in valid:
            raise ValueError(f"{path}: run.{key}={run.get(key)!r} is invalid: must be one of {list(valid)}")
    if not isinstance(run.get("env_id"), str):
        raise ValueError(f"{path}: run.env_id={run.get('env_id')!r} is invalid: must be an env id")
    if run.get("env_kwargs") is not None and not isinstance(run["env_kwargs"], dict):
        raise ValueError(f"{path}: run.env_kwargs={run['env_kwargs']!r} is invalid: must be a mapping")
    if run["mode"] == "residual" and not isinstance(data.get("residual"), dict):
        raise ValueError(f"{path}: a residual run needs a 'residual' section (the wrapper settings)")
    if data.get("normalize") is not None and not isinstance(data["normalize"], dict):
        raise ValueError(f"{path}: normalize={data['normalize']!r} is invalid: must be a mapping or null")
    return data


def _check_resume(cfg: TrainConfig, residual: dict | None) -> None:
    """Refuse a checkpoint whose run was trained with another algorithm or observation layout."""
    cpath = _run_config_path(Path(cfg.resume_from))
    if cpath is None:
        return  # a bare model file: the trial load below checks it
    try:
        old = read_run_config(cpath)
    except ValueError as exc:
        raise ConfigError("resume_from", str(exc)) from None
    run = old["run"]
    if run["algo"] != cfg.algo:
        raise ConfigError("resume_from", f"resume_from={cfg.resume_from!r} was trained with algo={run['algo']!r} "
                                         f"({cpath}): resume it with algo={run['algo']!r}, not {cfg.algo!r}")
    if run["mode"] != cfg.mode:
        raise ConfigError("resume_from", f"resume_from={cfg.resume_from!r} was trained in mode={run['mode']!r} "
                                         f"({cpath}): resume it with mode={run['mode']!r}, not {cfg.mode!r}")
    if residual is not None:
        for key in ("include_base_action", "history_len", "history_stride", "controller", "scale"):
            if key in old["residual"] and old["residual"][key] != residual[key]:
                raise ConfigError("resume_from", f"resume_from={cfg.resume_from!r} was trained with "
                                                 f"{key}={old['residual'][key]!r} ({cpath}), not {residual[key]!r}")


@dataclass
class _Plan:
    """Everything train() resolved and checked before it creates the run directory."""

    cls: Any
    hp: dict[str, Any]
    total: int
    n_envs: int
    residual: dict[str, Any] | None
    norm_kw: dict[str, Any] | None
    gamma: float
    run: Path
    vecnorm_pickle: Path | None


def _plan(cfg: TrainConfig) -> _Plan:
    cfg.validate()
    cls = _algo_class(cfg.algo)
    try:
        hp = load_hyperparams(cfg.algo, cfg.env_id, cfg.hyperparams_file, cfg.hyperparams, mode=cfg.mode)
    except (yaml.YAMLError, SyntaxError, NameError, TypeError, ValueError) as exc:
        if isinstance(exc, ConfigError):
            raise
        where = "hyperparams" if cfg.hyperparams else "hyperparams_file"
        raise ConfigError(where, f"hyperparameters could not be read: {_one_line(exc)}") from None
    hp = check_hyperparams(cfg.algo, hp)
    n_envs = int(cfg.n_envs if cfg.n_envs is not None else hp.get("n_envs", 1))
    if cfg.algo in BATCHED_ALGOS:
        from agents.batched_ppo import _check_teacher, check_bppo_hyperparams

        try:
            check_bppo_hyperparams(hp, n_envs=n_envs)
            _check_teacher(hp, cfg.mode, cfg.env_id)
        except ValueError as exc:
            raise ConfigError("hyperparams", str(exc)) from None
    if cfg.total_timesteps is None and hp["n_timesteps"] is None:
        raise ConfigError("total_timesteps", "total_timesteps is not given and the hyperparameters have no "
                                             "n_timesteps")
    total = int(cfg.total_timesteps if cfg.total_timesteps is not None else hp["n_timesteps"])
    residual = cfg.residual_kwargs() if cfg.mode == "residual" else None
    algo_kwargs = {k: v for k, v in hp.items() if k not in _ZOO_KEYS}
    # the algorithm's own default gamma (bppo's is 0.995) when the hyperparameters give none
    gamma_default = inspect.signature(cls.__init__).parameters["gamma"].default
    gamma = float(algo_kwargs.get("gamma", gamma_default))
    norm_kw = _normalize_kwargs(hp.get("normalize", False), gamma)
    try:
        gym.make(cfg.env_id, **cfg.env_kwargs).close()
    except Exception as exc:  # noqa: BLE001 (any refusal of the env settings is a config error)
        raise ConfigError("env_kwargs", f"env_kwargs={cfg.env_kwargs!r} are refused by {cfg.env_id}: "
                                        f"{_one_line(exc)}") from None
    vecnorm_pickle = None
    if cfg.resume_from is not None:
        _check_resume(cfg, residual)
        if norm_kw is not None and cfg.algo not in BATCHED_ALGOS:
            vecnorm_pickle = _stats_path(Path(cfg.resume_from), ".pkl")
            if not vecnorm_pickle.is_file():
                raise ConfigError("resume_from", f"{vecnorm_pickle} is missing: resuming an agent trained with "
                                                 "normalisation needs the VecNormalize statistics saved with "
                                                 f"{cfg.resume_from}")
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    name = cfg.run_name or f"{cfg.algo}-{cfg.env_id}-{cfg.mode}-seed{cfg.seed}-{stamp}"
    run = Path(cfg.out_dir) / name
    if run.exists() and (not run.is_dir() or any(run.iterdir())):
        raise ConfigError("run_name", f"run directory {run} already exists and is not empty: choose another "
                                      "run_name/out_dir")
    return _Plan(cls, hp, total, n_envs, residual, norm_kw, gamma, run, vecnorm_pickle)


def _build(cfg: TrainConfig, plan: _Plan, monitor_dir: str | None, tb: str | None):
    """The training VecEnv (normalised if configured) and the model (new or resumed)."""
    from stable_baselines3.common.vec_env import VecNormalize

    venv = _make_venv(cfg.env_id, cfg.env_kwargs, plan.n_envs, cfg.seed, cfg.mode, plan.residual, monitor_dir,
                      cfg.vec)
    try:
        if plan.vecnorm_pickle is not None:
            try:
                venv = VecNormalize.load(str(plan.vecnorm_pickle), venv)
            except Exception as exc:  # noqa: BLE001
                raise ConfigError("resume_from", f"{plan.vecnorm_pickle} is not a VecNormalize pickle for this env: "
                                                 f"{_one_line(exc)}") from None
            venv.training = True
        elif plan.norm_kw is not None:
            try:
                venv = VecNormalize(venv, **plan.norm_kw)
            except (TypeError, ValueError) as exc:
                raise ConfigError("hyperparams", f"normalize={plan.norm_kw!r} is refused: {_one_line(exc)}") from None
        if cfg.resume_from is not None:
            try:
                model = plan.cls.load(cfg.resume_from, env=venv, device="cpu", tensorboard_log=tb)
            except Exception as exc:  # noqa: BLE001
                raise ConfigError("resume_from", f"resume_from={cfg.resume_from!r} cannot be resumed as "
                                                 f"{cfg.algo} in mode {cfg.mode!r}: {_one_line(exc)}") from None
        else:
            algo_kwargs = {k: v for k, v in plan.hp.items() if k not in _ZOO_KEYS}
            noise = _action_noise(plan.hp, venv.action_space.shape[0]) if cfg.algo in ("sac", "td3") else None
            if noise is not None:
                algo_kwargs["action_noise"] = noise
            try:
                model = plan.cls(plan.hp.get("policy", "MlpPolicy"), venv, seed=cfg.seed, device="cpu",
                                 verbose=cfg.verbose, tensorboard_log=tb, policy_kwargs=plan.hp.get("policy_kwargs"),
                                 **algo_kwargs)
            except Exception as exc:  # noqa: BLE001 (SB3 checks with asserts, TypeErrors, ValueErrors)
                raise ConfigError("hyperparams", f"{cfg.algo} refused the hyperparameters: {_one_line(exc)}") from None
    except BaseException:
        venv.close()
        raise
    start = int(model.num_timesteps)
    if cfg.resume_from is not None and plan.total <= start:
        venv.close()
        raise ConfigError("total_timesteps", f"total_timesteps={plan.total} is not beyond the checkpoint's {start} "
                                             "steps: give a larger total_timesteps to resume")
    return venv, model


def train(cfg: TrainConfig, return_model: bool = False) -> Path | tuple[Path, Any]:
    """Train one agent as ``cfg`` says and return its run directory (and the trained SB3
    model if ``return_model``).

    Everything (settings, hyperparameters, the env, the model or checkpoint) is checked, and
    the model built once as a trial, before the run directory is created.

    Raises:
        ConfigError: invalid configuration (a ``ValueError``; the message names the field, its
            value and what is allowed; ``.field`` is the field).
        TrainingInterrupted: Ctrl-C; the model, statistics and config were saved first.
    """
    import torch
    from stable_baselines3.common.callbacks import EvalCallback
    from stable_baselines3.common.utils import set_random_seed
    from stable_baselines3.common.vec_env import VecNormalize

    torch.set_num_threads(1)
    plan = _plan(cfg)
    if cfg.algo in BATCHED_ALGOS:
        return _train_batched(cfg, plan, return_model)
    trial_venv, _ = _build(cfg, plan, None, None)  # raises ConfigError before anything is written
    trial_venv.close()

    run = plan.run
    created = not run.exists()
    try:
        (run / "monitor").mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        if created:
            shutil.rmtree(run, ignore_errors=True)
        raise ConfigError("out_dir", f"cannot write the run directory {run}: {_one_line(exc)}") from None
    try:
        set_random_seed(cfg.seed)
        tb = str(run / "tb") if cfg.tensorboard and _tensorboard_available() else None
        venv, model = _build(cfg, plan, str(run / "monitor"), tb)
        start_steps = int(model.num_timesteps)
        remaining = plan.total - start_steps if cfg.resume_from is not None else plan.total
        n_envs = plan.n_envs
        callbacks = []
        checkpoint_freq, eval_freq = cfg.resolved_freqs()
        if checkpoint_freq:
            callbacks.append(_checkpoint_callback(max(checkpoint_freq // n_envs, 1), str(run / "checkpoints")))
        if eval_freq:
            eval_env = _make_venv(cfg.env_id, cfg.env_kwargs, 1, cfg.eval_seed, cfg.mode, plan.residual, None)
            if plan.norm_kw is not None:
                eval_env = VecNormalize(eval_env, training=False, norm_obs=plan.norm_kw.get("norm_obs", True),
                                        norm_reward=False, gamma=plan.gamma)
            callbacks.append(EvalCallback(eval_env, n_eval_episodes=cfg.eval_episodes,
                                          eval_freq=max(eval_freq // n_envs, 1), log_path=str(run / "eval"),
                                          best_model_save_path=None, deterministic=True, verbose=0))
        if cfg.max_minutes is not None:
            callbacks.append(_wall_clock_callback(60.0 * cfg.max_minutes))
        progress = _Progress(remaining, start_steps if cfg.resume_from is not None else 0, cfg.progress_bar)
        callbacks.append(_progress_callback(progress))
        resolved = {"run": {**asdict(cfg), "total_timesteps": plan.total, "n_envs": n_envs, "run_dir": str(run)},
                    "hyperparams": {k: (v if isinstance(v, (int, float, str, bool, list, dict, type(None)))
                                        else repr(v)) for k, v in plan.hp.items()},
                    "normalize": plan.norm_kw, "residual": plan.residual, "versions": versions()}
        _write_yaml(run / "config.yaml", resolved)
    except BaseException as exc:
        if created:
            shutil.rmtree(run, ignore_errors=True)  # nothing was trained: leave nothing behind
        if isinstance(exc, OSError):
            raise ConfigError("out_dir", f"cannot write the run directory {run}: {_one_line(exc)}") from None
        raise

    t0 = time.perf_counter()
    interrupted = False
    try:
        with _StopOnSigint() as sigint:
            model.learn(total_timesteps=remaining, callback=[*callbacks, sigint.callback()], progress_bar=False,
                        reset_num_timesteps=cfg.resume_from is None, tb_log_name="tb")
        interrupted = sigint.requested
    except KeyboardInterrupt:
        interrupted = True
    except Exception as exc:  # noqa: BLE001 (NaN parameters fail in torch's distributions, NaN actions in the env)
        progress.close()
        venv.close()
        steps = int(model.num_timesteps)
        nan = re.search(r"\bnan\b|\binf\b|invalid values", str(exc), re.IGNORECASE) is not None
        reason = ("training diverged (NaN or infinite values): " if nan else f"{cfg.algo} failed: ") + _one_line(exc)
        _record_failure(run, resolved, steps, start_steps, reason)
        raise TrainingFailed(run, steps, reason) from exc
    finally:
        progress.close()
    elapsed = time.perf_counter() - t0
    try:
        _save_sb3(model, venv, run)
    except OSError as exc:
        venv.close()
        steps = int(model.num_timesteps)
        _record_failure(run, resolved, steps, start_steps, f"a write failed: {_one_line(exc)}")
        raise TrainingFailed(run, steps, f"a write failed: {_one_line(exc)}") from exc
    steps = int(model.num_timesteps)
    resolved["result"] = {"num_timesteps": steps, "start_timesteps": start_steps,
                          "wall_clock_s": round(elapsed, 2),
                          "steps_per_s": round((steps - start_steps) / max(elapsed, 1e-9), 1),
                          "interrupted": interrupted}
    _write_yaml(run / "config.yaml", resolved)
    if interrupted:
        venv.close()
        print(f"training interrupted at {steps:,} steps: model.zip, normalisation statistics and config.yaml "
              f"(interrupted: true) saved in {run}", file=sys.stderr)
        raise TrainingInterrupted(run, steps)
    if steps > plan.total:
        print(f"trained {steps - start_steps:,} steps ({plan.total - start_steps:,} asked: the algorithm collects "
              "whole rollouts)", file=sys.stderr)
    if cfg.final_eval:
        score = _final_score(cfg, model, venv, resolved)
        if score is not None:
            resolved["result"]["final_score"] = score
            _write_yaml(run / "config.yaml", resolved)
    venv.close()
    return (run, model) if return_model else run


def _check_bppo_resume(cfg: TrainConfig, plan: _Plan, obs_dim: int) -> int:
    """Refuse a bppo checkpoint that cannot continue this run (another observation width or
    policy_kwargs, missing or unfit observation statistics); returns its steps."""
    from agents.batched_ppo import _load_model_file, _policy_kwargs

    path = Path(cfg.resume_from)
    try:
        data = _load_model_file(path)
        old_pk = _policy_kwargs(data.get("policy_kwargs"))
        steps = int(data["steps_done"])
        width = int(data["obs_dim"])
        if not isinstance(data.get("state_dict"), dict) or not isinstance(data.get("ret_rms"), dict):
            raise ValueError(f"{path} is not a complete bppo model file (no state_dict or ret_rms)")
    except (KeyError, TypeError, ValueError) as exc:
        raise ConfigError("resume_from", f"resume_from={cfg.resume_from!r} cannot be resumed: {_one_line(exc)}") \
            from None
    new_pk = _policy_kwargs(plan.hp.get("policy_kwargs"))
    if old_pk != new_pk:
        diff = sorted(k for k in new_pk if old_pk.get(k) != new_pk[k])
        was, asked = {k: old_pk.get(k) for k in diff}, {k: new_pk[k] for k in diff}
        raise ConfigError("resume_from", f"resume_from={cfg.resume_from!r} was trained with policy_kwargs {was}, this "
                                         f"run asks for {asked}: resume with the checkpoint's policy_kwargs")
    if width != obs_dim:
        raise ConfigError("resume_from", f"resume_from={cfg.resume_from!r} observes {width} features, this run's "
                                         f"observation has {obs_dim}: resume with the checkpoint's observation "
                                         "settings (--obs, --history-len, --no-base-action, mode, env)")
    if plan.norm_kw is not None and plan.norm_kw.get("norm_obs", True):
        sp = _stats_path(path, ".json")
        if not sp.is_file():
            raise ConfigError("resume_from", f"{sp} is missing: resuming bppo with observation normalisation "
                                             f"needs the statistics saved with {path} (without them the statistics "
                                             "would restart from zero)")
        try:
            st = read_obs_stats(sp)
        except ValueError as exc:
            raise ConfigError("resume_from", str(exc)) from None
        if st.mean.shape != (obs_dim,):
            raise ConfigError("resume_from", f"{sp} has statistics for {st.mean.shape[0]} features, the model "
                                             f"observes {obs_dim}")
    if plan.total <= steps:
        raise ConfigError("total_timesteps", f"total_timesteps={plan.total} is not beyond the checkpoint's "
                                             f"{steps} steps: give a larger total_timesteps to resume")
    return steps


def _save_sb3(model: Any, venv: Any, run: Path) -> None:
    """The final model.zip (and the statistics), each written whole or not at all."""
    import io
    import pickle

    from stable_baselines3.common.vec_env import VecNormalize

    buf = io.BytesIO()
    model.save(buf)
    _write_atomic(run / "model.zip", buf.getvalue())
    if isinstance(venv, VecNormalize):
        # VecNormalize.save pickles the wrapper itself (its __getstate__ leaves the venv out): the same bytes
        _write_atomic(run / "vecnormalize.pkl", pickle.dumps(venv))
        write_obs_stats(venv, run / "vecnormalize.json")


def _train_batched(cfg: TrainConfig, plan: _Plan, return_model: bool):
    """:func:`train` for ``algo="bppo"`` (:mod:`agents.batched_ppo`), same run-directory contract."""
    from agents.batched_env import BatchedTrainEnv
    from agents.batched_ppo import train_bppo

    builder = cfg.builder_kwargs()
    n_eval = int(plan.hp.get("n_eval_seeds", 32))
    try:
        check_tier_training_seeds(cfg.env_id, [cfg.seed + i for i in range(plan.n_envs)]
                                  + list(range(cfg.eval_seed, cfg.eval_seed + n_eval)))
    except ValueError as exc:
        raise ConfigError("eval_seed", str(exc)) from None
    try:  # a trial of the env and the observation before anything is written
        trial = BatchedTrainEnv(cfg.env_id, 1, seed=cfg.seed, env_kwargs=cfg.env_kwargs, builder=builder)
    except ValueError as exc:
        raise ConfigError("observation", f"the observation settings are refused: {_one_line(exc)}") from None
    obs_dim = trial.obs_dim
    trial.close()
    start = _check_bppo_resume(cfg, plan, obs_dim) if cfg.resume_from is not None else 0
    run = plan.run
    created = not run.exists()
    checkpoint_freq, eval_freq = cfg.resolved_freqs()
    resolved = {"run": {**asdict(cfg), "total_timesteps": plan.total, "n_envs": plan.n_envs, "run_dir": str(run),
                        "checkpoint_freq": checkpoint_freq, "eval_freq": eval_freq,
                        "history_len": cfg.resolved_history_len(), "observation": cfg.resolved_observation()},
                "hyperparams": {k: (v if isinstance(v, (int, float, str, bool, list, dict, type(None))) else repr(v))
                                for k, v in plan.hp.items()},
                "normalize": plan.norm_kw, "residual": plan.residual, "observation": builder,
                "threads": {"env_kernel": "numba serial (parallel=False)",
                            "torch": int(plan.hp.get("torch_threads", 1))},
                "versions": versions(), "steps_done": 0, "train_seconds": 0.0}
    try:
        run.mkdir(parents=True, exist_ok=True)
        _write_yaml(run / "config.yaml", resolved)
    except BaseException as exc:
        if created:
            shutil.rmtree(run, ignore_errors=True)
        if isinstance(exc, OSError):
            raise ConfigError("out_dir", f"cannot write the run directory {run}: {_one_line(exc)}") from None
        raise
    cfg_run = TrainConfig(**{**asdict(cfg), "checkpoint_freq": checkpoint_freq, "eval_freq": eval_freq})
    progress = _Progress(plan.total - start, start, cfg.progress_bar)
    try:
        with _StopOnSigint() as sigint:
            result, interrupted = train_bppo(cfg_run, plan, resolved, run, progress, sigint, _write_yaml)
    except OSError as exc:  # a write failed (disk full, read-only): the run is not finished
        steps = int(resolved.get("steps_done", start))
        _record_failure(run, resolved, steps, start, f"a write failed: {_one_line(exc)}")
        raise TrainingFailed(run, steps, f"a write failed: {_one_line(exc)}") from exc
    resolved["result"] = result
    _write_yaml(run / "config.yaml", resolved)
    if result.get("failed"):  # config.yaml records result.failed; no model.zip (checkpoints before it are kept)
        raise TrainingFailed(run, result["num_timesteps"], result["failed"])
    if interrupted:
        print(f"training interrupted at {result['num_timesteps']:,} steps: model.zip, normalisation statistics and "
              f"config.yaml (interrupted: true) saved in {run}", file=sys.stderr)
        raise TrainingInterrupted(run, result["num_timesteps"])
    return (run, load_agent(run)) if return_model else run


def _record_failure(run: Path, resolved: dict, steps: int, start: int, reason: str) -> None:
    """Record ``result.failed`` in the run's config.yaml if it can still be written (best effort:
    the failure may be the disk itself); a final model.zip of the failed run is removed."""
    resolved["result"] = {"num_timesteps": int(steps), "start_timesteps": int(start), "interrupted": False,
                          "failed": reason}
    try:
        (run / "model.zip").unlink(missing_ok=True)
        _write_yaml(run / "config.yaml", resolved)
    except OSError:
        pass


def _final_score(cfg: TrainConfig, model: Any, venv: Any, resolved: dict) -> dict | None:
    """Score the final model on eval_episodes seeds (eval_seed, eval_seed + 1, ...) and print it."""
    from stable_baselines3.common.vec_env import VecNormalize

    seeds = list(range(cfg.eval_seed, cfg.eval_seed + cfg.eval_episodes))
    if cfg.env_id not in auv_follow_env.ENV_IDS + auv_follow_env.ENV_IDS_V1:
        print(f"final score: not computed ({cfg.env_id} is not an AUVFollow env)")
        return None
    stats = stats_from_vecnormalize(venv) if isinstance(venv, VecNormalize) else None
    df = evaluate_agent(Agent(model, resolved, stats), seeds, progress=False)
    score = {"seeds": seeds, "true_steady_mean_m": float(df["true_steady_mean"].mean()),
             "true_full_mean_m": float(df["true_full_mean"].mean()), "return": float(df["return"].mean())}
    print(f"final score on {cfg.env_id}, seeds {seeds[0]}-{seeds[-1]}: steady-state mean error to the true "
          f"reference {score['true_steady_mean_m']:.4f} m (full run {score['true_full_mean_m']:.4f} m), "
          f"mean return {score['return']:.1f}")
    return score


def _write_yaml(path: Path, data: dict) -> None:
    text = yaml.safe_dump(json.loads(json.dumps(data, default=str)), sort_keys=False)
    _write_atomic(path, text.encode())


def _write_atomic(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file beside it: ``path`` is either its old
    or its new content, and a failed write (disk full, read-only) leaves no temporary file."""
    tmp = path.with_name(path.name + ".tmp")
    try:
        tmp.write_bytes(data)
        tmp.replace(path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


# --- loading and evaluation ---------------------------------------------------------------

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
        :class:`agents.residual.ResidualPolicy` (runs its own base controller and history),
        for a from-scratch agent ``self``."""
        if self.mode != "residual":
            return self
        from agents.residual import ResidualPolicy

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
        obs = self.normalize(obs)
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


def _failure(cfg_path: Path) -> str | None:
    """``result.failed`` of a run's config.yaml (None if absent or unreadable)."""
    try:
        res = (yaml.safe_load(cfg_path.read_text()) or {}).get("result")
    except (OSError, UnicodeDecodeError, yaml.YAMLError, AttributeError):
        return None
    return str(res["failed"]) if isinstance(res, dict) and res.get("failed") else None


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
    cfg_path = _run_config_path(model_path)
    if cfg_path is None:
        raise FileNotFoundError(f"no config.yaml next to {model_path} or in {model_path.parent.parent}: "
                                "not a run directory")
    config = read_run_config(cfg_path)
    stats = None
    norm = config.get("normalize")
    if norm is not None and norm.get("norm_obs", True):
        json_path = _stats_path(model_path, ".json")
        if not json_path.is_file():
            pkl = json_path.with_suffix(".pkl")
            convert = (f"; {pkl} exists: if you trust it like code, convert it with "
                       f"`python -m agents.obs_stats {pkl}`" if pkl.is_file() else "")
            raise FileNotFoundError(f"observation-normalisation statistics {json_path} are missing: the agent was "
                                    f"trained with normalize={norm} ({cfg_path}) and gives wrong actions without "
                                    f"them{convert}")
        stats = read_obs_stats(json_path)
        check_against_config(stats, norm, json_path, cfg_path)
    if config["run"]["algo"] in BATCHED_ALGOS:
        from agents.batched_ppo import load_bppo_agent

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
