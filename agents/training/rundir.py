"""The run-directory contract: ``config.yaml``, the statistics beside each model and checkpoint,
versions, atomic writes and the record of a failed run."""

from __future__ import annotations

import json
import platform
import subprocess
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import yaml

import auv_follow_env
from agents.training.config import ALGOS, MODES, _one_line, check_env_id
from agents.training.obs_stats import _CKPT
from auv_follow_env._files import check_size


def versions() -> dict[str, str]:
    """Versions of the software a result depends on, and the git commit of this checkout."""
    import stable_baselines3
    import torch

    try:
        root = Path(__file__).resolve().parents[2]
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






def _checkpoints(run: Path) -> list[Path]:
    """Checkpoints of a run, oldest first (by step count)."""
    found = [(int(m["steps"]), p) for p in (run / "checkpoints").glob("*.zip") if (m := _CKPT.match(p.stem))]
    return [p for _, p in sorted(found)]


def _run_config_path(model_path: Path) -> Path | None:
    for d in (model_path.parent, model_path.parent.parent):
        if (d / "config.yaml").is_file():
            return d / "config.yaml"
    return None


#: run kinds that load and score like a trained agent but are not made by ``auv-follow train``:
#: ``estimator`` (:mod:`agents.training.learned_estimator`, its algo and mode)
LOADABLE_ONLY_ALGOS: tuple[str, ...] = ("estimator",)


def read_run_config(path: str | Path) -> dict[str, Any]:
    """A run's ``config.yaml``, checked: a mapping with a ``run`` section naming a known algo and mode.

    Raises:
        ValueError: broken YAML or not a run configuration (the message names the file).
    """
    path = Path(path)
    try:
        data = yaml.safe_load(check_size(path, "text").read_text())
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path} is not valid YAML ({_one_line(exc)})") from None
    what = "a run configuration written by auv-follow train (a mapping with a 'run' section)"
    if not isinstance(data, dict) or not isinstance(data.get("run"), dict):
        raise ValueError(f"{path} is {'empty' if data is None else 'not ' + what}: expected {what}")
    run = data["run"]
    for key, valid in (("algo", ALGOS + LOADABLE_ONLY_ALGOS), ("mode", MODES + LOADABLE_ONLY_ALGOS)):
        if run.get(key) not in valid:
            raise ValueError(f"{path}: run.{key}={run.get(key)!r} is invalid: must be one of {list(valid)}")
    if not isinstance(run.get("env_id"), str):
        raise ValueError(f"{path}: run.env_id={run.get('env_id')!r} is invalid: must be an env id")
    try:  # a registered id, never "module:Env" (gymnasium would import the module)
        check_env_id(run["env_id"], allow_any=run["mode"] == "scratch")
    except ValueError as exc:
        raise ValueError(f"{path}: run.{exc}") from None
    if run.get("env_kwargs") is not None and not isinstance(run["env_kwargs"], dict):
        raise ValueError(f"{path}: run.env_kwargs={run['env_kwargs']!r} is invalid: must be a mapping")
    if run["mode"] == "residual" and not isinstance(data.get("residual"), dict):
        raise ValueError(f"{path}: a residual run needs a 'residual' section (the wrapper settings)")
    if data.get("normalize") is not None and not isinstance(data["normalize"], dict):
        raise ValueError(f"{path}: normalize={data['normalize']!r} is invalid: must be a mapping or null")
    return data


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


def _failure(cfg_path: Path) -> str | None:
    """``result.failed`` of a run's config.yaml (None if absent or unreadable)."""
    try:
        res = (yaml.safe_load(check_size(cfg_path, "text").read_text()) or {}).get("result")
    except (OSError, UnicodeDecodeError, yaml.YAMLError, AttributeError, ValueError):
        return None
    return str(res["failed"]) if isinstance(res, dict) and res.get("failed") else None
