"""The Stable-Baselines3 path: vector envs, normalisation, action noise and the callbacks
(wall clock, Ctrl-C, progress, checkpoints) of a run."""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from agents.training.config import _ZOO_KEYS, ConfigError, TrainConfig, _one_line, _Plan
from agents.training.obs_stats import (
    write_obs_stats,
)
from agents.training.residual import _wrapper
from agents.training.rundir import _write_atomic


def _make_venv(env_id: str, env_kwargs: dict, n_envs: int, seed: int, mode: str, residual: dict | None,
               monitor_dir: str | None, vec: str = "dummy"):
    from stable_baselines3.common.env_util import make_vec_env

    if vec == "native":
        from agents.training.vec_adapter import NativeVecEnv

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
    """Ctrl-C (SIGINT; SIGTERM and SIGHUP under the CLI) during ``learn`` asks training to stop at
    the next step instead of raising wherever the signal lands (inside torch, numba or a library that catches and
    continues, which made an interrupt occasionally ineffective). A second Ctrl-C raises
    KeyboardInterrupt at once. Only installed in the main thread."""

    def __init__(self) -> None:
        self.requested = False
        self._old: dict[int, Any] = {}

    def __enter__(self) -> _StopOnSigint:
        import signal
        import threading

        self._old = {}
        if threading.current_thread() is threading.main_thread():
            # SIGINT, and SIGTERM/SIGHUP where the command made them stop it (auv_follow_env._signals)
            for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
                if sig == signal.SIGINT or callable(signal.getsignal(sig)):
                    self._old[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum: int, frame: Any) -> None:
        from auv_follow_env._signals import record_stop

        record_stop(signum)
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True

    def __exit__(self, *exc: Any) -> None:
        import signal

        for sig, old in self._old.items():
            signal.signal(sig, old)

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

    def __init__(self, total: int, start: int, enabled: bool, stream: Any = None,
                 max_seconds: float | None = None) -> None:
        self.total, self.start, self.enabled = total, start, enabled
        self.max_seconds = max_seconds  #: a wall-clock budget (--max-minutes): shown beside the steps' ETA
        self.t0 = time.perf_counter()
        self.stream = stream if stream is not None else sys.stderr
        self.bar = None
        self.shown = 0
        self.next_line = 0.1
        if enabled and getattr(self.stream, "isatty", lambda: False)():
            from tqdm.auto import tqdm

            self.bar = tqdm(total=total, unit="step", unit_scale=True, desc="training", file=self.stream)

    def update(self, num_timesteps: int) -> None:
        """Show ``num_timesteps`` (steps collected so far, ``start`` included): the bar moves to it;
        a log gets one line whenever it passes the next tenth, with the count collected."""
        if not self.enabled:
            return
        done = max(num_timesteps - self.start, 0)  # an algorithm may collect past the budget (whole rollouts)
        budget = self.budget_text()
        if self.bar is not None:
            if budget:
                self.bar.set_postfix_str(budget, refresh=False)
            self.bar.update(min(done, self.total) - min(self.shown, self.total))
        elif (self.next_line <= 1.0 + 1e-9 and done >= self.next_line * self.total - 1e-9) or self._time_tick():
            pct = min(math.floor(100 * done / max(self.total, 1)), 100)
            print(f"training: {pct}% ({done:,}/{self.total:,} steps)" + (f", {budget}" if budget else ""),
                  file=self.stream, flush=True)
            self.next_line = max(self.next_line, math.floor(10 * done / max(self.total, 1) + 1e-9) / 10 + 0.1)
        self.shown = done

    def _time_tick(self) -> bool:
        """True once per tenth of a --max-minutes budget (a log line then, whatever the steps)."""
        if self.max_seconds is None:
            return False
        tenth = math.floor(10 * (time.perf_counter() - self.t0) / self.max_seconds)
        if tenth > getattr(self, "_tenth", 0):
            self._tenth = tenth
            return True
        return False

    def budget_text(self) -> str:
        """"time budget: 4m 10s left" while a --max-minutes budget runs (the bar's ETA counts steps)."""
        if self.max_seconds is None:
            return ""
        left = max(self.max_seconds - (time.perf_counter() - self.t0), 0.0)
        return f"time budget: {int(left // 60)}m {int(left % 60):02d}s left"

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


