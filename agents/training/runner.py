""":func:`train`: plan, build and run one training run (SB3 or the batched trainer), resumable."""

from __future__ import annotations

import datetime as _dt
import inspect
import re
import shutil
import sys
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import yaml

import auv_follow_env
from agents.training.config import (
    _ZOO_KEYS,
    BATCHED_ALGOS,
    ConfigError,
    TrainConfig,
    TrainingFailed,
    TrainingInterrupted,
    _algo_class,
    _one_line,
    _Plan,
    check_hyperparams,
    check_tier_training_seeds,
    load_hyperparams,
)
from agents.training.loading import Agent, evaluate_agent, load_agent
from agents.training.obs_stats import (
    _stats_path,
    read_obs_stats,
    stats_from_vecnormalize,
)
from agents.training.rundir import (
    _record_failure,
    _run_config_path,
    _write_yaml,
    read_run_config,
    versions,
)
from agents.training.sb3 import (
    _build,
    _checkpoint_callback,
    _make_venv,
    _normalize_kwargs,
    _Progress,
    _progress_callback,
    _save_sb3,
    _StopOnSigint,
    _tensorboard_available,
    _wall_clock_callback,
)


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
    for key, now in (("env_id", cfg.env_id), ("env_kwargs", dict(cfg.env_kwargs or {}))):
        was = run.get(key) if key == "env_id" else dict(run.get(key) or {})
        if was != now:
            raise ConfigError("resume_from", f"resume_from={cfg.resume_from!r} was trained with {key}={was!r} "
                                             f"({cpath}), this run asks for {now!r}: a resumed run continues the same "
                                             "task (to fine-tune on another, start a new run from the model with "
                                             "agents.training's API)")
    if residual is not None:
        for key in ("include_base_action", "history_len", "history_stride", "controller", "scale"):
            if key in old["residual"] and old["residual"][key] != residual[key]:
                raise ConfigError("resume_from", f"resume_from={cfg.resume_from!r} was trained with "
                                                 f"{key}={old['residual'][key]!r} ({cpath}), not {residual[key]!r}")




def _budget_s(cfg: TrainConfig) -> float | None:
    return 60.0 * float(cfg.max_minutes) if cfg.max_minutes is not None else None


def _note_budget(cfg: TrainConfig, result: dict[str, Any], total: int) -> None:
    """Say (on stderr and as ``result.stopped_by``) when --max-minutes, not --timesteps, ended the run."""
    steps = int(result["num_timesteps"])
    if cfg.max_minutes is None or result.get("interrupted") or result.get("failed") or steps >= total:
        return
    result["stopped_by"] = "max_minutes"
    print(f"training stopped by the time budget (--max-minutes {cfg.max_minutes:g}) after {steps:,} of {total:,} "
          f"steps ({result['wall_clock_s']:.0f} s); the model so far is saved", file=sys.stderr)


def _check_eval_seeds(cfg: TrainConfig, n_envs: int, n_eval: int) -> None:
    """The learning-curve episodes must be held out: no evaluation seed may be a training env's
    seed (env i is seeded ``seed + i``; its later episodes continue its generator)."""
    train_lo, train_hi = cfg.seed, cfg.seed + n_envs - 1
    eval_lo, eval_hi = cfg.eval_seed, cfg.eval_seed + n_eval - 1
    if eval_lo <= train_hi and train_lo <= eval_hi:
        raise ConfigError("eval_seed", f"eval_seed={cfg.eval_seed} gives evaluation seeds {eval_lo}-{eval_hi}, which "
                                       f"overlap the training env seeds {train_lo}-{train_hi} (seed + env index): "
                                       f"choose an eval_seed above {train_hi} or below {train_lo - n_eval + 1}")


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
        from agents.training.batched_ppo import _check_teacher, check_bppo_hyperparams

        try:
            check_bppo_hyperparams(hp, n_envs=n_envs)
            _check_teacher(hp, cfg.mode, cfg.env_id)
        except ValueError as exc:
            raise ConfigError("hyperparams", str(exc)) from None
    if cfg.total_timesteps is None and hp["n_timesteps"] is None:
        raise ConfigError("total_timesteps", "total_timesteps is not given and the hyperparameters have no "
                                             "n_timesteps")
    total = int(cfg.total_timesteps if cfg.total_timesteps is not None else hp["n_timesteps"])
    if cfg.algo in BATCHED_ALGOS:  # whole rollouts: the budget is what will be collected (and recorded)
        per = int(hp.get("n_steps", 32)) * n_envs
        total = -(-total // per) * per
    _check_eval_seeds(cfg, n_envs, int(hp.get("n_eval_seeds", 32)) if cfg.algo in BATCHED_ALGOS else 1)
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
        progress = _Progress(remaining, start_steps if cfg.resume_from is not None else 0, cfg.progress_bar,
                             max_seconds=_budget_s(cfg))
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
    progress.t0 = t0  # the time budget's clock (--max-minutes) starts with learn
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
    lr = plan.hp.get("learning_rate")
    resolved["training"] = {"lr_schedule": "constant" if isinstance(lr, (int, float)) or lr is None else repr(lr),
                            "learning_rate": lr if isinstance(lr, (int, float)) else None}
    resolved["steps_done"], resolved["train_seconds"] = steps, round(float(elapsed), 2)
    resolved["result"] = {"num_timesteps": steps, "start_timesteps": start_steps,
                          "wall_clock_s": round(elapsed, 2),
                          "steps_per_s": round((steps - start_steps) / max(elapsed, 1e-9), 1),
                          "interrupted": interrupted}
    _note_budget(cfg, resolved["result"], plan.total)
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


#: a bppo run's hyperparameters that change its reward: a resumed run must keep them
_REWARD_HP = ("action_rate_coef", "heading_coef", "yaw_rate_coef")


def _check_same_policy(cfg: TrainConfig, plan: _Plan, observation: dict[str, Any]) -> None:
    """Refuse a bppo checkpoint trained with another policy interface (the builder's resolved
    ``observation`` section of its config.yaml: base controller, observation, history, action
    filter, ``yaw_from``, ...) or another reward (:data:`_REWARD_HP`)."""
    from agents.training.batched_ppo import BatchedPPO

    cpath = _run_config_path(Path(cfg.resume_from))
    if cpath is None:
        return
    old = read_run_config(cpath)
    was_obs = {"action_filter": 1.0, "yaw_from": None, **(old.get("observation") or {})}
    now_obs = {"action_filter": 1.0, "yaw_from": None, **observation}
    diff = [k for k in sorted(set(was_obs) | set(now_obs)) if was_obs.get(k) != now_obs.get(k)]
    defaults = BatchedPPO().__dict__
    was_hp = {k: (old.get("training") or {}).get(k, (old.get("hyperparams") or {}).get(k, defaults.get(k)))
              for k in _REWARD_HP}
    now_hp = {k: plan.hp.get(k, defaults.get(k)) for k in _REWARD_HP}
    diff_hp = [k for k in _REWARD_HP if was_hp[k] is not None and now_hp[k] is not None
               and float(was_hp[k]) != float(now_hp[k])]
    if diff or diff_hp:
        parts = [f"{k}={was_obs.get(k)!r} (now {now_obs.get(k)!r})" for k in diff]
        parts += [f"{k}={was_hp[k]!r} (now {now_hp[k]!r})" for k in diff_hp]
        raise ConfigError("resume_from", f"resume_from={cfg.resume_from!r} was trained with {', '.join(parts)} "
                                         f"({cpath}): resume it with the checkpoint's settings")


def _check_bppo_resume(cfg: TrainConfig, plan: _Plan, obs_dim: int, error_cols: list[int],
                       observation: dict[str, Any] | None = None) -> int:
    """Refuse a bppo checkpoint that cannot continue this run (another observation width, policy
    interface, reward or policy_kwargs, missing or unfit observation statistics, the reference-error
    fields (``error_cols``) normalised the other way); returns its steps. Runs before anything is written."""
    from agents.training.batched_ppo import OBS_ERROR_NORM_DEFAULT, _load_model_file, _policy_kwargs

    if observation is not None:
        _check_same_policy(cfg, plan, observation)
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
        # scaled statistics hold the error fields' mean at exactly 0 (their var is a mean square);
        # centred ones never do: continuing them the other way would misread every statistic
        was = "scaled" if error_cols and np.all(st.mean[error_cols] == 0.0) else "centered"
        asked = str(plan.hp.get("obs_error_norm", OBS_ERROR_NORM_DEFAULT))
        if error_cols and asked != was:
            held = "hold mean 0" if was == "scaled" else "are centred"
            raise ConfigError("resume_from", f"resume_from={cfg.resume_from!r} was trained with obs_error_norm="
                                             f"{was!r} (the reference-error columns {list(error_cols)} of {sp} "
                                             f"{held}), this run asks for obs_error_norm={asked!r}: resume it "
                                             f"with obs_error_norm={was!r}")
    if plan.total <= steps:
        raise ConfigError("total_timesteps", f"total_timesteps={plan.total} is not beyond the checkpoint's "
                                             f"{steps} steps: give a larger total_timesteps to resume")
    return steps


def _train_batched(cfg: TrainConfig, plan: _Plan, return_model: bool):
    """:func:`train` for ``algo="bppo"`` (:mod:`agents.training.batched_ppo`), same run-directory contract."""
    from agents.training.batched_env import BatchedTrainEnv
    from agents.training.batched_ppo import train_bppo

    builder = cfg.builder_kwargs()
    if float(plan.hp.get("action_filter", 1.0)) < 1.0:  # the low-pass action is part of what the agent observes
        builder["action_filter"] = float(plan.hp["action_filter"])
    if plan.hp.get("yaw_from") is not None:  # the yaw moment from a classical law: part of the policy
        if cfg.mode != "scratch":
            raise ConfigError("hyperparams", f"hyperparameter yaw_from={plan.hp['yaw_from']!r} needs --mode scratch "
                                                          f"(got {cfg.mode!r})")
        builder["yaw_from"] = str(plan.hp["yaw_from"])
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
    obs_dim, error_cols, observation = trial.obs_dim, list(trial.builder.error_indices), dict(builder)
    trial.close()
    start = _check_bppo_resume(cfg, plan, obs_dim, error_cols, observation) if cfg.resume_from is not None else 0
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
                            "torch": int(plan.hp.get("torch_threads", 2 if cfg.algo == "bppo" else 1))},
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
    progress = _Progress(plan.total - start, start, cfg.progress_bar, max_seconds=_budget_s(cfg))
    try:
        with _StopOnSigint() as sigint:
            result, interrupted = train_bppo(cfg_run, plan, resolved, run, progress, sigint, _write_yaml)
    except OSError as exc:  # a write failed (disk full, read-only): the run is not finished
        steps = int(resolved.get("steps_done", start))
        _record_failure(run, resolved, steps, start, f"a write failed: {_one_line(exc)}")
        raise TrainingFailed(run, steps, f"a write failed: {_one_line(exc)}") from exc
    resolved["result"] = result
    _note_budget(cfg, result, plan.total)
    _write_yaml(run / "config.yaml", resolved)
    if result.get("failed"):  # config.yaml records result.failed; no model.zip (checkpoints before it are kept)
        raise TrainingFailed(run, result["num_timesteps"], result["failed"])
    if interrupted:
        print(f"training interrupted at {result['num_timesteps']:,} steps: model.zip, normalisation statistics and "
              f"config.yaml (interrupted: true) saved in {run}", file=sys.stderr)
        raise TrainingInterrupted(run, result["num_timesteps"])
    return (run, load_agent(run)) if return_model else run


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
