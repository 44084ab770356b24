"""Run any policy (scripted controller or SB3 model) on AUVFollow and score it with the
paper's metrics, eqs. (64)-(65), against two references:

* ``own``: the reference the controller generated itself from the delayed (or predicted)
  target - the paper's convention; only defined for policies with a ``reference`` method;
* ``true``: the reference from the present, undelayed target - the task metric the
  environment rewards, and the only one that applies to learned agents.

Samples are the states after each control step, t = dt, 2 dt, ..., T; the steady-state
window is t >= 10 s.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
import pandas as pd
from tqdm.auto import tqdm

import auv_follow_env  # noqa: F401  (registers the ids)
from auv_follow_env.metrics import METRIC_KEYS, tracking_metrics
from auv_follow_env.params import TaskSpec

__all__ = ["evaluate", "evaluate_controllers", "METRIC_COLUMNS", "TRAJECTORY_COLUMNS"]

METRIC_COLUMNS: tuple[str, ...] = tuple(f"{ref}_{k}" for ref in ("true", "own") for k in METRIC_KEYS)
TRAJECTORY_COLUMNS: tuple[str, ...] = (
    "scenario", "disturbance", "policy", "seed", "step", "time",
    "follower_x", "follower_y", "follower_psi", "target_x", "target_y", "target_psi",
    "true_ref_x", "true_ref_y", "own_ref_x", "own_ref_y", "err_true", "err_own",
    "F_u", "F_v", "F_r")


def _check_seeds(seeds: Iterable[int]) -> list[int]:
    out = []
    for s in seeds:
        if isinstance(s, bool) or not isinstance(s, (int, np.integer)) or s < 0:
            raise ValueError(f"seeds must be non-negative integers, got {s!r}")
        out.append(int(s))
    if not out:
        raise ValueError("seeds is empty: give at least one seed")
    return out


def evaluate(policy: Any, env_id: str = "AUVFollow-S4-v0", seeds: Iterable[int] = (0,), *,
             env_kwargs: dict | None = None, env_wrapper: Callable[[gym.Env], gym.Env] | None = None,
             policy_name: str | None = None, trajectories: bool = False, progress: bool = True,
             deterministic: bool = True) -> pd.DataFrame | tuple[pd.DataFrame, pd.DataFrame]:
    """Run ``policy`` for one episode per seed and return one metrics row per episode.

    Args:
        policy: anything with SB3's ``predict(obs, state, episode_start, deterministic)``.
        env_id: a registered AUVFollow id.
        seeds: reset seeds (identical seeds give identical targets and disturbances).
        env_kwargs: overrides passed to ``gym.make`` (e.g. ``disturbance="L1"``).
        env_wrapper: applied to the env before the policy sees it (e.g. an agent's wrappers);
            the own-reference metric is then not computed.
        policy_name: label (default: the policy's ``name`` or class name).
        trajectories: also return the per-step long-format DataFrame.
        progress: show a progress bar over episodes.

    Returns:
        metrics DataFrame (columns scenario, disturbance, policy, seed, steps, terminated,
        return and :data:`METRIC_COLUMNS`), and the trajectory DataFrame if requested.
    """
    seeds = _check_seeds(seeds)
    env = gym.make(env_id, **(env_kwargs or {}))
    spec: TaskSpec = env.unwrapped.task_spec
    if env_wrapper is not None:
        env = env_wrapper(env)
    name = policy_name or getattr(policy, "name", None) or type(policy).__name__
    has_ref = env_wrapper is None and hasattr(policy, "reference")
    limits = np.asarray(spec.force_limits)
    rows, trajs = [], []
    for seed in tqdm(seeds, desc=f"{name} on {env_id}", disable=not progress, leave=False):
        obs, info = env.reset(seed=seed)
        state, start = None, np.ones(1, dtype=bool)
        rec: dict[str, list] = {k: [] for k in ("pose", "target", "ref", "err", "own", "force")}
        ret, terminated = 0.0, False
        while True:
            action, state = policy.predict(obs, state=state, episode_start=start,
                                           deterministic=deterministic)
            start = np.zeros(1, dtype=bool)
            obs, reward, terminated, truncated, info = env.step(action)
            ret += reward
            rec["pose"].append(info["follower_pose"])
            rec["target"].append(info["true_target"][:3])
            rec["ref"].append(info["true_reference"][:2])
            rec["err"].append(info["tracking_error"])
            rec["force"].append(np.clip(np.asarray(action, dtype=np.float64).reshape(-1)[:3], -1, 1) * limits
                                if env_wrapper is None else np.full(3, np.nan))
            rec["own"].append(policy.reference(obs)[0] if has_ref else np.full(3, np.nan))
            if terminated or truncated:
                break
        n = len(rec["err"])
        times = spec.dt * np.arange(1, n + 1)
        err = np.asarray(rec["err"])
        pose = np.asarray(rec["pose"])
        own = np.asarray(rec["own"])
        c, s = np.cos(pose[:, 2]), np.sin(pose[:, 2])
        own_xy = pose[:, :2] + np.stack([c * own[:, 0] - s * own[:, 1], s * own[:, 0] + c * own[:, 1]], -1)
        err_own = np.hypot(own[:, 0], own[:, 1])
        m_true = tracking_metrics(err, times, spec.steady_start_s)
        m_own = tracking_metrics(err_own, times, spec.steady_start_s)
        rows.append({"scenario": spec.scenario, "disturbance": spec.disturbance, "policy": name,
                     "seed": seed, "steps": n, "terminated": bool(terminated), "return": ret,
                     **{f"true_{k}": v for k, v in m_true.items()},
                     **{f"own_{k}": v for k, v in m_own.items()}})
        if trajectories:
            target = np.asarray(rec["target"])
            ref = np.asarray(rec["ref"])
            force = np.asarray(rec["force"])
            trajs.append(pd.DataFrame({
                "scenario": spec.scenario, "disturbance": spec.disturbance, "policy": name,
                "seed": seed, "step": np.arange(1, n + 1), "time": times,
                "follower_x": pose[:, 0], "follower_y": pose[:, 1], "follower_psi": pose[:, 2],
                "target_x": target[:, 0], "target_y": target[:, 1], "target_psi": target[:, 2],
                "true_ref_x": ref[:, 0], "true_ref_y": ref[:, 1],
                "own_ref_x": own_xy[:, 0], "own_ref_y": own_xy[:, 1],
                "err_true": err, "err_own": err_own,
                "F_u": force[:, 0], "F_v": force[:, 1], "F_r": force[:, 2]}))
    env.close()
    metrics = pd.DataFrame(rows)
    if trajectories:
        return metrics, pd.concat(trajs, ignore_index=True)
    return metrics


def evaluate_controllers(names: Sequence[str] | None = None,
                         scenarios: Sequence[str] = ("S1", "S2", "S3", "S4"),
                         seeds: Iterable[int] = (0,), *, env_kwargs: dict | None = None,
                         trajectories: bool = False, progress: bool = True):
    """The paper's controllers on the paper's scenarios: one gain set, identical seeds.

    Returns the concatenated metrics DataFrame (and trajectories if requested).
    """
    from controllers import CONTROLLERS, make_controller

    names = list(CONTROLLERS if names is None else names)
    seeds = _check_seeds(seeds)
    jobs = [(sc, n) for sc in scenarios for n in names]
    ms, ts = [], []
    for sc, n in tqdm(jobs, desc="controllers x scenarios", disable=not progress):
        env_id = f"AUVFollow-{sc}-v0"
        spec = auv_follow_env.make_task_spec(sc, **(env_kwargs or {}))
        out = evaluate(make_controller(n, spec), env_id, seeds, env_kwargs=env_kwargs,
                       trajectories=trajectories, progress=False)
        if trajectories:
            ms.append(out[0])
            ts.append(out[1])
        else:
            ms.append(out)
    metrics = pd.concat(ms, ignore_index=True)
    return (metrics, pd.concat(ts, ignore_index=True)) if trajectories else metrics
