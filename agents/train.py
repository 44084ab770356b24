"""Training and evaluation of SB3 agents (PPO, SAC, TD3) on AUVFollow, from scratch or as a
residual on top of one of the paper's controllers.

A run writes everything into its own directory ``<out>/<algo>-<env>-<mode>-seed<k>-<timestamp>/``:

* ``config.yaml``: the resolved configuration (run settings, hyperparameters, residual
  settings) and the versions used (python, torch, stable-baselines3, gymnasium, numpy, git);
* ``model.zip`` and ``vecnormalize.pkl`` (observation/reward statistics, if normalised);
* ``checkpoints/`` (``CheckpointCallback``, with the matching VecNormalize statistics);
* ``monitor/`` (per-episode Monitor CSVs of the training envs) and ``eval/evaluations.npz``
  (``EvalCallback``); ``tb/`` (TensorBoard, when ``tensorboard`` is importable).

:func:`load_agent` turns a run directory (or a ``.zip`` inside it) back into a policy with
SB3's ``predict`` protocol plus the env wrapper it needs, for
:func:`controllers.evaluation.evaluate`.
"""

from __future__ import annotations

import datetime as _dt
import json
import pickle
import platform
import subprocess
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import yaml

import auv_follow_env
from agents.residual import (
    DEFAULT_CONTROLLER,
    DEFAULT_HISTORY_LEN,
    DEFAULT_HISTORY_STRIDE,
    DEFAULT_SCALE,
    make_residual_wrapper,
)

__all__ = ["ALGOS", "MODES", "TrainConfig", "train", "load_hyperparams", "load_agent", "Agent",
           "versions", "evaluate_agent", "HYPERPARAMS_DIR"]

ALGOS: tuple[str, ...] = ("ppo", "sac", "td3", "recurrentppo")
#: algorithms whose policy carries a recurrent state (sb3-contrib's RecurrentPPO, an LSTM policy)
RECURRENT_ALGOS: tuple[str, ...] = ("recurrentppo",)
MODES: tuple[str, ...] = ("residual", "scratch")
VEC_KINDS = ("dummy", "native")
HYPERPARAMS_DIR = Path(__file__).with_name("hyperparams")
_ZOO_KEYS = ("n_timesteps", "policy", "n_envs", "normalize", "policy_kwargs", "noise_type", "noise_std")


def _algo_class(algo: str):
    from stable_baselines3 import PPO, SAC, TD3

    classes = {"ppo": PPO, "sac": SAC, "td3": TD3}
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


def _eval_zoo(value: Any) -> Any:
    """rl-zoo writes dicts as strings like ``"dict(net_arch=[64, 64])"``; evaluate those with
    nothing but ``dict`` and ``torch.nn`` in scope."""
    if isinstance(value, str) and value.strip().startswith("dict("):
        import torch.nn as nn

        return eval(value, {"__builtins__": {}}, {"dict": dict, "nn": nn})  # noqa: S307 (trusted YAML)
    return value


def load_hyperparams(algo: str, env_id: str, path: str | Path | None = None,
                     overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """Hyperparameters for ``algo`` on ``env_id`` from an rl-zoo3-format YAML file
    (``agents/hyperparams/<algo>.yml`` by default): the ``default`` section updated by the
    env id's section, then by ``overrides``. Strings ``"dict(...)"`` are evaluated."""
    _algo_class(algo)
    path = Path(path) if path is not None else HYPERPARAMS_DIR / f"{algo}.yml"
    if not path.is_file():
        raise FileNotFoundError(f"hyperparameter file {path} does not exist")
    with open(path) as f:
        table = yaml.safe_load(f) or {}
    hp = dict(table.get("default", {}))
    hp.update(table.get(env_id, {}) or {})
    hp.update(overrides or {})
    return {k: _eval_zoo(v) for k, v in hp.items()}


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
    history_len: int = DEFAULT_HISTORY_LEN  #: lagged delayed-target velocity differences
    history_stride: int = DEFAULT_HISTORY_STRIDE  #: steps between lagged samples
    total_timesteps: int | None = None  #: env steps (None: the YAML's n_timesteps)
    max_minutes: float | None = None  #: wall-clock budget; training stops when it runs out
    seed: int = 0  #: seeds the model and the training envs (env i: seed + i)
    n_envs: int | None = None  #: parallel training envs (None: the YAML's)
    vec: str = "dummy"  #: training VecEnv: "dummy" (SB3 DummyVecEnv) or "native" (batched AUVFollowVectorEnv)
    out_dir: str = "runs"  #: parent of the run directory
    run_name: str | None = None  #: run directory name (None: <algo>-<env>-<mode>-seed<k>-<timestamp>)
    checkpoint_freq: int = 100_000  #: env steps between checkpoints (0: none)
    eval_freq: int = 50_000  #: env steps between EvalCallback evaluations (0: none)
    eval_episodes: int = 3  #: episodes per evaluation
    eval_seed: int = 500  #: seed of the EvalCallback env (distinct from training and test seeds)
    resume_from: str | None = None  #: checkpoint/model .zip to continue (keeps num_timesteps)
    hyperparams_file: str | None = None  #: YAML file (None: agents/hyperparams/<algo>.yml)
    hyperparams: dict[str, Any] = field(default_factory=dict)  #: overrides of the YAML entries
    progress_bar: bool = True  #: tqdm/rich progress bar
    tensorboard: bool = True  #: TensorBoard logs if tensorboard is importable
    verbose: int = 0  #: SB3 verbosity

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first invalid field."""
        _algo_class(self.algo)
        check_env_id(self.env_id, allow_any=self.mode == "scratch")
        if self.mode not in MODES:
            raise ValueError(f"mode={self.mode!r} is unknown: valid modes are {list(MODES)}")
        if self.vec not in VEC_KINDS:
            raise ValueError(f"vec={self.vec!r} is unknown: valid kinds are {list(VEC_KINDS)}")
        if self.vec == "native" and self.mode != "scratch":
            raise ValueError("vec='native' trains from scratch only (mode='scratch'): the residual wrapper is a "
                             "per-env gymnasium wrapper; use vec='dummy' for residual agents")
        if self.mode == "residual":
            make_residual_wrapper(**self.residual_kwargs())
        for name in ("total_timesteps", "n_envs"):
            v = getattr(self, name)
            if v is not None and (isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v <= 0):
                raise ValueError(f"{name}={v!r} is invalid: must be a positive integer")
        if self.max_minutes is not None and not (np.isfinite(self.max_minutes) and self.max_minutes > 0):
            raise ValueError(f"max_minutes={self.max_minutes!r} is invalid: must be a positive number")
        for name in ("checkpoint_freq", "eval_freq"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name}={getattr(self, name)!r} is invalid: must be >= 0 (0 disables)")
        if self.eval_episodes <= 0:
            raise ValueError(f"eval_episodes={self.eval_episodes!r} is invalid: must be a positive integer")
        check_tier_training_seeds(self.env_id, [self.seed + i for i in range(self.n_envs or 16)] + [self.eval_seed])
        if self.resume_from is not None and not Path(self.resume_from).is_file():
            raise FileNotFoundError(f"resume_from={self.resume_from!r}: no such model file")

    def residual_kwargs(self) -> dict[str, Any]:
        return {"controller": self.controller, "scale": self.scale, "include_base_action": self.include_base_action,
                "history_len": self.history_len, "history_stride": self.history_stride}


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
    if not normalize:
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


def _vecnorm_for(model_path: Path) -> Path | None:
    """The VecNormalize statistics saved with a model or a checkpoint."""
    if model_path.name == "model.zip":
        p = model_path.with_name("vecnormalize.pkl")
        return p if p.is_file() else None
    stem = model_path.stem  # <prefix>_<steps>_steps
    if stem.endswith("_steps"):
        prefix, steps, _ = stem.rsplit("_", 2)
        p = model_path.with_name(f"{prefix}_vecnormalize_{steps}_steps.pkl")
        if p.is_file():
            return p
    p = model_path.parent / "vecnormalize.pkl"
    return p if p.is_file() else None


def train(cfg: TrainConfig, return_model: bool = False) -> Path | tuple[Path, Any]:
    """Train one agent as ``cfg`` says and return its run directory (and the trained SB3
    model if ``return_model``).

    Raises:
        ValueError: invalid configuration (the message names the field and the valid values).
        FileNotFoundError: ``resume_from`` or the hyperparameter file does not exist.
    """
    import torch
    from stable_baselines3.common.callbacks import CheckpointCallback, EvalCallback
    from stable_baselines3.common.utils import set_random_seed
    from stable_baselines3.common.vec_env import VecNormalize

    cfg.validate()
    torch.set_num_threads(1)
    cls = _algo_class(cfg.algo)
    hp = load_hyperparams(cfg.algo, cfg.env_id, cfg.hyperparams_file, cfg.hyperparams)
    total = int(cfg.total_timesteps if cfg.total_timesteps is not None else float(hp["n_timesteps"]))
    n_envs = int(cfg.n_envs if cfg.n_envs is not None else hp.get("n_envs", 1))
    residual = cfg.residual_kwargs() if cfg.mode == "residual" else None
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    name = cfg.run_name or f"{cfg.algo}-{cfg.env_id}-{cfg.mode}-seed{cfg.seed}-{stamp}"
    run = Path(cfg.out_dir) / name
    if run.exists() and any(run.iterdir()):
        raise ValueError(f"run directory {run} already exists and is not empty: choose another run_name/out_dir")
    (run / "monitor").mkdir(parents=True, exist_ok=True)

    set_random_seed(cfg.seed)
    venv = _make_venv(cfg.env_id, cfg.env_kwargs, n_envs, cfg.seed, cfg.mode, residual, str(run / "monitor"),
                      cfg.vec)
    algo_kwargs = {k: v for k, v in hp.items() if k not in _ZOO_KEYS}
    gamma = float(algo_kwargs.get("gamma", 0.99))
    norm_kw = _normalize_kwargs(_eval_zoo(hp.get("normalize", False)), gamma)
    if cfg.resume_from is not None:
        vn_path = _vecnorm_for(Path(cfg.resume_from))
        if norm_kw is not None and vn_path is not None:
            venv = VecNormalize.load(str(vn_path), venv)
            venv.training = True
        elif norm_kw is not None:
            venv = VecNormalize(venv, **norm_kw)
    elif norm_kw is not None:
        venv = VecNormalize(venv, **norm_kw)

    tb = str(run / "tb") if cfg.tensorboard and _tensorboard_available() else None
    if cfg.resume_from is not None:
        model = cls.load(cfg.resume_from, env=venv, device="cpu", tensorboard_log=tb)
    else:
        noise = _action_noise(hp, venv.action_space.shape[0]) if cfg.algo in ("sac", "td3") else None
        if noise is not None:
            algo_kwargs["action_noise"] = noise
        model = cls(hp.get("policy", "MlpPolicy"), venv, seed=cfg.seed, device="cpu", verbose=cfg.verbose,
                    tensorboard_log=tb, policy_kwargs=hp.get("policy_kwargs"), **algo_kwargs)
    start_steps = int(model.num_timesteps)
    remaining = total - start_steps if cfg.resume_from is not None else total
    if remaining <= 0:
        raise ValueError(f"total_timesteps={total} is not beyond the checkpoint's {start_steps} steps: "
                         f"give a larger total_timesteps to resume")

    callbacks = []
    if cfg.checkpoint_freq:
        callbacks.append(CheckpointCallback(max(cfg.checkpoint_freq // n_envs, 1), str(run / "checkpoints"),
                                            name_prefix="model", save_vecnormalize=True))
    if cfg.eval_freq:
        eval_env = _make_venv(cfg.env_id, cfg.env_kwargs, 1, cfg.eval_seed, cfg.mode, residual, None)
        if norm_kw is not None:
            eval_env = VecNormalize(eval_env, training=False, norm_obs=norm_kw.get("norm_obs", True),
                                    norm_reward=False, gamma=gamma)
        callbacks.append(EvalCallback(eval_env, n_eval_episodes=cfg.eval_episodes,
                                      eval_freq=max(cfg.eval_freq // n_envs, 1), log_path=str(run / "eval"),
                                      best_model_save_path=None, deterministic=True, verbose=0))
    if cfg.max_minutes is not None:
        callbacks.append(_wall_clock_callback(60.0 * cfg.max_minutes))

    resolved = {"run": {**asdict(cfg), "total_timesteps": total, "n_envs": n_envs, "run_dir": str(run)},
                "hyperparams": {k: (v if isinstance(v, (int, float, str, bool, list, dict, type(None))) else repr(v))
                                for k, v in hp.items()},
                "normalize": norm_kw, "residual": residual, "versions": versions()}
    _write_yaml(run / "config.yaml", resolved)

    t0 = time.perf_counter()
    model.learn(total_timesteps=remaining, callback=callbacks, progress_bar=cfg.progress_bar,
                reset_num_timesteps=cfg.resume_from is None, tb_log_name="tb")
    elapsed = time.perf_counter() - t0
    model.save(run / "model.zip")
    if isinstance(venv, VecNormalize):
        venv.save(str(run / "vecnormalize.pkl"))
    resolved["result"] = {"num_timesteps": int(model.num_timesteps), "start_timesteps": start_steps,
                          "wall_clock_s": round(elapsed, 2),
                          "steps_per_s": round((model.num_timesteps - start_steps) / max(elapsed, 1e-9), 1)}
    _write_yaml(run / "config.yaml", resolved)
    venv.close()
    return (run, model) if return_model else run


def _write_yaml(path: Path, data: dict) -> None:
    with open(path, "w") as f:
        yaml.safe_dump(json.loads(json.dumps(data, default=str)), f, sort_keys=False)


# --- loading and evaluation ---------------------------------------------------------------

class Agent:
    """A trained agent as a policy with SB3's ``predict`` protocol, over the observation of
    its (wrapped) env; ``env_wrapper`` is the wrapper to apply to a raw AUVFollow env (None
    for a from-scratch agent). Observation normalisation (VecNormalize) is applied inside
    :meth:`predict`.
    """

    def __init__(self, model: Any, config: dict[str, Any], obs_rms: Any = None, clip_obs: float = 10.0,
                 epsilon: float = 1e-8, name: str | None = None) -> None:
        self.model = model
        self.config = config
        run = config["run"]
        self.env_id: str = run["env_id"]
        self.env_kwargs: dict = dict(run.get("env_kwargs") or {})
        self.mode: str = run["mode"]
        self.residual: dict | None = config.get("residual")
        self.env_wrapper = _wrapper(self.mode, self.residual)
        self._obs_rms, self._clip, self._eps = obs_rms, clip_obs, epsilon
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
        if self._obs_rms is None:
            return obs
        return np.clip((obs - self._obs_rms.mean) / np.sqrt(self._obs_rms.var + self._eps),
                       -self._clip, self._clip).astype(np.float32)

    @property
    def recurrent(self) -> bool:
        """True for an LSTM policy (RecurrentPPO): :meth:`predict` then keeps its state."""
        return self.config["run"]["algo"] in RECURRENT_ALGOS

    def reset(self) -> None:
        """Forget the recurrent state: the next call starts every env afresh."""
        self._lstm, self._lstm_n = None, None

    def predict(self, observation: Any, state: Any = None, episode_start: Any = None,
                deterministic: bool = True) -> tuple[np.ndarray, Any]:
        obs = self.normalize(np.asarray(observation, dtype=np.float32))
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

    Raises:
        FileNotFoundError: no model file, or no ``config.yaml`` in the run directory.
    """
    p = Path(path)
    model_path = p / "model.zip" if p.is_dir() else p
    if not model_path.is_file():
        raise FileNotFoundError(f"model file {model_path} does not exist: give a run directory or a model .zip")
    run_dir = model_path.parent if model_path.name == "model.zip" else model_path.parent.parent
    cfg_path = next((d / "config.yaml" for d in (model_path.parent, run_dir) if (d / "config.yaml").is_file()), None)
    if cfg_path is None:
        raise FileNotFoundError(f"no config.yaml next to {model_path} or in {run_dir}: not a run directory")
    with open(cfg_path) as f:
        config = yaml.safe_load(f)
    model = _algo_class(config["run"]["algo"]).load(str(model_path), device="cpu")
    obs_rms, clip_obs, eps = None, 10.0, 1e-8
    vn = _vecnorm_for(model_path)
    if vn is not None:
        with open(vn, "rb") as f:
            stats = pickle.load(f)
        if getattr(stats, "norm_obs", False):
            obs_rms, clip_obs, eps = stats.obs_rms, stats.clip_obs, stats.epsilon
    return Agent(model, config, obs_rms, clip_obs, eps, name=name)


def evaluate_agent(agent: Agent | str | Path, seeds: Any = range(1000, 1010), *, env_id: str | None = None,
                   env_kwargs: dict | None = None, progress: bool = True):
    """The agent's metrics DataFrame from :func:`controllers.evaluation.evaluate` (one row per
    seed; ``own_*`` columns are NaN: an agent generates no reference of its own)."""
    from controllers.evaluation import evaluate

    if not isinstance(agent, Agent):
        agent = load_agent(agent)
    env_id = env_id or agent.env_id
    kw = agent.env_kwargs if env_kwargs is None else env_kwargs
    return evaluate(agent, env_id, seeds, env_kwargs=kw, env_wrapper=agent.env_wrapper, policy_name=agent.name,
                    progress=progress)
