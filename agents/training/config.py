"""A training run's configuration: :class:`TrainConfig`, the algorithms and modes, zoo-format
hyperparameters and every check made before any work starts."""

from __future__ import annotations

import inspect
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import yaml

import auv_follow_env
from agents.training.history import DEFAULT_CONTROLLER, DEFAULT_HISTORY_LEN, DEFAULT_HISTORY_STRIDE, DEFAULT_SCALE
from agents.training.residual import make_residual_wrapper
from auv_follow_env._files import check_size

ALGOS: tuple[str, ...] = ("ppo", "sac", "td3", "recurrentppo", "bppo")


#: algorithms trained by our own batched loop (agents.training.batched_ppo) rather than SB3
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


#: the largest step budget and time budget accepted (far beyond any run; a typo is refused, not run forever)
MAX_TIMESTEPS = 10**12
MAX_MINUTES = 525_600.0


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
        from agents.training.batched_ppo import BatchedPPO

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
    ``eval`` (:func:`agents.training.zoo_parse.parse_zoo_value`: literals, ``dict(...)`` and
    ``nn.<activation>`` only)."""
    if isinstance(value, str) and value.strip().startswith("dict("):
        from agents.training.zoo_parse import parse_zoo_value

        return parse_zoo_value(value, f"hyperparameter {key}")
    return value


def load_hyperparams(algo: str, env_id: str, path: str | Path | None = None,
                     overrides: dict[str, Any] | None = None, mode: str | None = None) -> dict[str, Any]:
    """Hyperparameters for ``algo`` on ``env_id`` from an rl-zoo3-format YAML file
    (``agents/training/hyperparams/<algo>.yml`` by default): the ``default`` section updated by the
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
    with open(check_size(path, "text")) as f:
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
    "obs_norm_window": (0, True, math.inf),
    "reward_norm_window": (0, True, math.inf), "action_rate_coef": (0, True, math.inf),
    "heading_coef": (0, True, math.inf), "bounds_loss_coef": (0, True, math.inf),
    "yaw_rate_coef": (0, True, math.inf),
    "action_filter": (0, False, 1), "distill_steps": (0, True, math.inf)}


#: hyperparameters whose value must be a whole number (an int, or a float such as 1.0e+6 that is one; never a bool)
_INTEGER_KEYS = frozenset({"n_steps", "batch_size", "n_epochs", "buffer_size", "policy_delay", "n_envs",
                           "learning_starts", "target_update_interval", "stats_window_size", "sde_sample_freq",
                           "gradient_steps", "torch_threads", "n_eval_seeds", "obs_norm_window", "distill_steps",
                           "reward_norm_window"})


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
    """The agent's observation: "raw" or "estimator" (the estimator block, agents.training.batched_obs);
    None: "estimator" for bppo on v1 ids, else "raw". SB3 algorithms take "estimator" in residual mode only."""
    eval_episodes: int = 3  #: episodes per evaluation (and of the final score)
    #: first seed of the learning-curve / EvalCallback episodes: held out from the training envs' seeds
    #: (``seed`` .. ``seed + n_envs - 1``), the sweep's validation seeds and every test seed
    eval_seed: int = 990_000
    resume_from: str | None = None  #: checkpoint/model .zip to continue (keeps num_timesteps)
    hyperparams_file: str | None = None  #: YAML file (None: agents/training/hyperparams/<algo>.yml)
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
        for name, lo, hi in (("total_timesteps", 1, MAX_TIMESTEPS), ("n_envs", 1, MAX_N_ENVS),
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
        mm = self.max_minutes
        if mm is not None and (isinstance(mm, (bool, np.bool_)) or not isinstance(
                mm, (int, float, np.integer, np.floating)) or not (math.isfinite(mm) and 0 < mm <= MAX_MINUTES)):
            raise ConfigError("max_minutes", f"max_minutes={mm!r} is invalid: must be a finite number in "
                                             f"(0, {MAX_MINUTES:g}] (a year of minutes)")
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
                from agents.training.history import _check
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
        """The :class:`agents.training.batched_obs.ObservationBuilder` settings of this run."""
        return {"mode": self.mode, "controller": self.controller if self.mode == "residual" else None,
                "scale": self.scale, "include_base_action": self.include_base_action,
                "observation": self.resolved_observation(), "history_len": self.resolved_history_len(),
                "history_stride": self.history_stride, "observer_feed": "applied"}


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
