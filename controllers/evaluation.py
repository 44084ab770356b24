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

import sys
from collections.abc import Callable, Iterable, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
import pandas as pd
from tqdm.auto import tqdm

import auv_follow_env  # noqa: F401  (registers the ids)
from auv_follow_env.metrics import METRIC_KEYS, tracking_metrics
from auv_follow_env.params import TaskSpec

__all__ = ["evaluate", "evaluate_controllers", "evaluate_batched", "check_task_spec", "METRIC_COLUMNS",
           "TRAJECTORY_COLUMNS", "SPEC_FIELDS", "MAX_SEED", "PolicyError", "BadAction"]

METRIC_COLUMNS: tuple[str, ...] = tuple(f"{ref}_{k}" for ref in ("true", "own") for k in METRIC_KEYS)
TRAJECTORY_COLUMNS: tuple[str, ...] = (
    "scenario", "disturbance", "policy", "seed", "step", "time",
    "follower_x", "follower_y", "follower_psi", "target_x", "target_y", "target_psi",
    "true_ref_x", "true_ref_y", "own_ref_x", "own_ref_y", "err_true", "err_own",
    "F_u", "F_v", "F_r")


#: gym.make keywords that are not env configuration
_MAKE_ONLY_KWARGS = frozenset({"max_episode_steps", "disable_env_checker", "render_mode", "autoreset"})


#: TaskSpec fields a scripted policy uses: they must be equal to the env's
SPEC_FIELDS: tuple[str, ...] = ("dt", "delay_s", "delay_steps", "p_d", "psi_d", "nominal", "force_limits",
                               "thruster_tc_s", "thruster_rate")


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, (tuple, list)) or isinstance(b, (tuple, list)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    return a == b


def check_task_spec(policy: Any, spec: TaskSpec, env_id: str = "the env") -> None:
    """Raise ``ValueError`` if ``policy`` was built for another task than ``spec``.

    Applies to policies with a ``spec`` attribute that is a :class:`TaskSpec` (the scripted
    controllers, :class:`agents.training.residual.ResidualPolicy`); compares :data:`SPEC_FIELDS`, the
    facts such a policy computes with (its delay, rate, offset, nominal model, force limits).
    Other policies are not checked.
    """
    own = getattr(policy, "spec", None)
    if not isinstance(own, TaskSpec):
        return
    bad = [f for f in SPEC_FIELDS if not _same(getattr(own, f), getattr(spec, f))]
    if bad:
        diffs = "; ".join(f"{f}: policy {getattr(own, f)!r}, env {getattr(spec, f)!r}" for f in bad)
        name = getattr(policy, "name", type(policy).__name__)
        raise ValueError(f"policy {name!r} was built for another task than {env_id} ({diffs}): build it with "
                         f"that env's env.unwrapped.task_spec")


def _bar(iterable: Iterable, desc: str, progress: bool, nested: bool = False, **kw: Any):
    """tqdm over ``iterable`` if ``progress``; off for nested bars when stderr is not a terminal
    (no cursor-movement escape codes in logs), and plain lines rarely for the outer ones."""
    tty = sys.stderr.isatty()
    disable = not progress or (nested and not tty)
    return tqdm(iterable, desc=desc, disable=disable, leave=not nested, mininterval=0.1 if tty else 30.0,
                ascii=not tty, **kw)


#: largest seed accepted: the result tables store seeds as 64-bit integers
MAX_SEED = 2**63 - 1


def _check_seeds(seeds: Iterable[int]) -> list[int]:
    if isinstance(seeds, (str, bytes)):
        raise ValueError(f"seeds={seeds!r} is invalid: give a list of integers, e.g. [1000, 1001]")
    out = []
    for s in seeds:
        if isinstance(s, bool) or not isinstance(s, (int, np.integer)) or not 0 <= s <= MAX_SEED:
            raise ValueError(f"seeds must be integers in [0, 2**63 - 1], got {s!r}")
        out.append(int(s))
    if not out:
        raise ValueError("seeds is empty: give at least one seed")
    return out


class PolicyError(ValueError):
    """A policy's ``predict`` (or ``reference``) raised or returned an unusable action; the
    message names the policy, the env, the seed(s) and the step."""


class BadAction(ValueError):
    """Raised by a wrapper around a policy whose action is unusable (e.g. a wrong shape): the
    evaluation puts the policy, env, seed and step before its message."""


def _seed_text(seeds: Sequence[int]) -> str:
    seeds = list(seeds)
    if len(seeds) == 1:
        return f"seed {seeds[0]}"
    if seeds == list(range(seeds[0], seeds[0] + len(seeds))):
        return f"seeds {seeds[0]}-{seeds[-1]}"
    return f"seeds {seeds[:4]}" if len(seeds) <= 4 else f"seeds [{seeds[0]}, {seeds[1]}, ..., {seeds[-1]}]"


def _call(fn: Callable[..., Any], what: str, name: str, env_id: str, seeds: Sequence[int], step: int,
          *args: Any, **kw: Any) -> Any:
    """``fn(*args, **kw)``; an exception from it becomes a :class:`PolicyError` naming the policy,
    the env, the seed(s) and the step (the original is chained as its cause)."""
    try:
        return fn(*args, **kw)
    except PolicyError:
        raise
    except BadAction as exc:
        raise PolicyError(f"policy {name!r} on {env_id}, {_seed_text(seeds)}, step {step + 1}: {exc}") from exc
    except Exception as exc:  # noqa: BLE001 (a user's code can raise anything)
        text = " ".join(str(exc).split())[:300]
        raise PolicyError(f"policy {name!r} on {env_id}, {_seed_text(seeds)}, step {step + 1}: {what} raised "
                          f"{type(exc).__name__}" + (f": {text}" if text else "")) from exc


def _checked_action(out: Any, shape: tuple[int, ...], name: str, env_id: str, seeds: Sequence[int],
                    step: int) -> Any:
    """The action of ``predict``'s ``(action, state)``, checked to have ``shape``, a real numeric
    dtype and finite values (returned as given: the env sees exactly what the policy returned)."""
    def where() -> str:  # (built only for an error message: formatting a long seed list costs a step's time)
        return f"policy {name!r} on {env_id}, {_seed_text(seeds)}, step {step + 1}"

    if not isinstance(out, tuple) or len(out) != 2:
        raise PolicyError(f"{where()}: predict returned {type(out).__name__}, expected a pair (action, state)")
    action = out[0]
    try:
        a = np.asarray(action)
    except Exception as exc:  # noqa: BLE001 (ragged lists and odd objects)
        raise PolicyError(f"{where()}: its action is not an array ({type(exc).__name__})") from None
    if a.dtype.kind not in "biuf":
        raise PolicyError(f"{where()}: its action has dtype {a.dtype}, expected real numbers (float32 or float64)")
    if a.shape != shape:
        raise PolicyError(f"{where()}: its action has shape {a.shape}, expected {shape} (F_u, F_v, F_r in [-1, 1] "
                          f"{'per env of the batch' if len(shape) == 2 else 'for one observation'})")
    finite = np.isfinite(a)
    if not finite.all():
        bad = int(np.flatnonzero(~finite.reshape(len(seeds), -1).all(axis=1))[0]) if a.ndim == 2 else 0
        raise PolicyError(f"policy {name!r} on {env_id}, seed {seeds[bad]}, step {step + 1}: its action "
                          f"{np.array2string(a.reshape(-1, 3)[bad], precision=4)} is not finite (NaN or inf)")
    return action


def _episode_outputs(spec: TaskSpec, name: str, seed: int, terminated: bool, ret: float, err: np.ndarray,
                     own: np.ndarray | None, pose: np.ndarray | None = None, target: np.ndarray | None = None,
                     ref: np.ndarray | None = None, force: np.ndarray | None = None, *,
                     err_own: np.ndarray | None = None, metrics: tuple[dict, dict] | None = None):
    """One episode's metrics row and (if ``pose`` is given) its trajectory frame.

    ``err`` (n,) true-reference errors; ``own`` (n, 3) own reference in the follower body frame;
    ``pose`` (n, 3), ``target`` (n, 3), ``ref`` (n, 2), ``force`` (n, 3) per step.
    ``err_own`` (n,): ``hypot`` of own's first two columns, if already computed (``own`` is then
    needed only for the frame); ``metrics``: the (true, own) :func:`tracking_metrics`, if already
    computed.
    """
    n = len(err)
    times = spec.dt * np.arange(1, n + 1)
    if err_own is None:
        err_own = np.hypot(own[:, 0], own[:, 1])
    if metrics is None:
        metrics = (tracking_metrics(err, times, spec.steady_start_s),
                   tracking_metrics(err_own, times, spec.steady_start_s))
    m_true, m_own = metrics
    row = {"scenario": spec.scenario, "disturbance": spec.disturbance, "policy": name, "seed": seed,
           "steps": n, "terminated": bool(terminated), "return": float(ret),
           **{f"true_{k}": v for k, v in m_true.items()}, **{f"own_{k}": v for k, v in m_own.items()}}
    if pose is None:
        return row, None
    c, s = np.cos(pose[:, 2]), np.sin(pose[:, 2])
    frame = pd.DataFrame({
        "scenario": spec.scenario, "disturbance": spec.disturbance, "policy": name,
        "seed": seed, "step": np.arange(1, n + 1), "time": times,
        "follower_x": pose[:, 0], "follower_y": pose[:, 1], "follower_psi": pose[:, 2],
        "target_x": target[:, 0], "target_y": target[:, 1], "target_psi": target[:, 2],
        "true_ref_x": ref[:, 0], "true_ref_y": ref[:, 1],
        "own_ref_x": pose[:, 0] + c * own[:, 0] - s * own[:, 1],
        "own_ref_y": pose[:, 1] + s * own[:, 0] + c * own[:, 1],
        "err_true": err, "err_own": err_own,
        "F_u": force[:, 0], "F_v": force[:, 1], "F_r": force[:, 2]})
    return row, frame


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
            the own-reference metric is then computed only for policies with a ``reference``
            method (which must accept the wrapped observation), and forces are not recorded.
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
    try:
        check_task_spec(policy, spec, env_id)
    except ValueError:
        env.close()
        raise
    if env_wrapper is not None:
        env = env_wrapper(env)
    name = policy_name or getattr(policy, "name", None) or type(policy).__name__
    has_ref = hasattr(policy, "reference")
    limits = np.asarray(spec.force_limits)
    act_shape = tuple(env.action_space.shape)
    rows, trajs = [], []
    for seed in _bar(seeds, f"{name} on {env_id}", progress, nested=True):
        obs, info = env.reset(seed=seed)
        state, start = None, np.ones(1, dtype=bool)
        rec: dict[str, list] = {k: [] for k in ("pose", "target", "ref", "err", "own", "force")}
        ret, terminated = 0.0, False
        while True:
            k = len(rec["err"])
            out = _call(policy.predict, "predict", name, env_id, (seed,), k, obs, state=state, episode_start=start,
                        deterministic=deterministic)
            action, state = _checked_action(out, act_shape, name, env_id, (seed,), k), out[1]
            start = np.zeros(1, dtype=bool)
            obs, reward, terminated, truncated, info = env.step(action)
            ret += reward
            rec["pose"].append(info["follower_pose"])
            rec["target"].append(info["true_target"][:3])
            rec["ref"].append(info["true_reference"][:2])
            rec["err"].append(info["tracking_error"])
            rec["force"].append(np.clip(np.asarray(action, dtype=np.float64).reshape(-1)[:3], -1, 1) * limits
                                if env_wrapper is None else np.full(3, np.nan))
            rec["own"].append(_call(policy.reference, "reference", name, env_id, (seed,), k, obs)[0] if has_ref
                              else np.full(3, np.nan))
            if terminated or truncated:
                break
        arr = {k: np.asarray(v) for k, v in rec.items()}
        row, frame = _episode_outputs(spec, name, seed, terminated, ret, arr["err"], arr["own"],
                                      *((arr["pose"], arr["target"], arr["ref"], arr["force"]) if trajectories
                                        else ()))
        rows.append(row)
        if trajectories:
            trajs.append(frame)
    env.close()
    metrics = pd.DataFrame(rows)
    if trajectories:
        return metrics, pd.concat(trajs, ignore_index=True)
    return metrics


def evaluate_controllers(names: Sequence[str] | None = None,
                         scenarios: Sequence[str] = ("S1", "S2", "S3", "S4"),
                         seeds: Iterable[int] = (0,), *, env_kwargs: dict | None = None,
                         trajectories: bool = False, progress: bool = True, batched: bool = True):
    """The paper's controllers on the paper's scenarios: one gain set, identical seeds.

    With ``batched`` (default) each scenario runs all controllers and seeds in one native
    vector env (:func:`evaluate_batched`); otherwise one single-env episode at a time
    (:func:`evaluate`). Both give the same numbers.

    Returns the concatenated metrics DataFrame (and trajectories if requested).
    """
    from controllers import CONTROLLERS, make_controller

    names = list(CONTROLLERS if names is None else names)
    seeds = _check_seeds(seeds)
    cfg_kwargs = {k: v for k, v in (env_kwargs or {}).items() if k not in _MAKE_ONLY_KWARGS}
    ms, ts = [], []
    if batched:
        for sc in _bar(scenarios, "scenarios", progress):
            spec = auv_follow_env.make_task_spec(sc, **cfg_kwargs)
            out = evaluate_batched([make_controller(n, spec) for n in names], f"AUVFollow-{sc}-v0", seeds,
                                   env_kwargs=env_kwargs, trajectories=trajectories, progress=progress)
            ms.append(out[0] if trajectories else out)
            if trajectories:
                ts.append(out[1])
    else:
        jobs = [(sc, n) for sc in scenarios for n in names]
        for sc, n in _bar(jobs, "controllers x scenarios", progress):
            spec = auv_follow_env.make_task_spec(sc, **cfg_kwargs)
            out = evaluate(make_controller(n, spec), f"AUVFollow-{sc}-v0", seeds, env_kwargs=env_kwargs,
                           trajectories=trajectories, progress=False)
            ms.append(out[0] if trajectories else out)
            if trajectories:
                ts.append(out[1])
    metrics = pd.concat(ms, ignore_index=True)
    return (metrics, pd.concat(ts, ignore_index=True)) if trajectories else metrics


_ROWS = 64  #: rows per block in _tracking_metrics_rows


def _tracking_metrics_rows(errors: np.ndarray, times: np.ndarray, steady_start: float) -> list[dict[str, float]]:
    """:func:`tracking_metrics` of each row of ``errors`` (m, T) over the same ``times`` (T,), T >= 1.

    The same numpy reductions, each over one C-contiguous row (numpy's pairwise sum over the
    same values in the same order; a reduction across a strided axis would add in another
    order), so every value equals the 1-D call's bit for bit (tested).
    """
    e = np.asarray(errors, dtype=np.float64)
    if e.strides[1] != e.itemsize:
        e = np.ascontiguousarray(e)
    window = np.asarray(times, dtype=np.float64) >= steady_start - 1e-9
    first = int(np.argmax(window))
    if window[first:].all():  # a suffix (times increase): a view of contiguous rows
        steady = e[:, first:] if window.any() else e[:, :0]
    else:  # (boolean indexing along axis 1 returns an F-ordered array: made C-contiguous)
        steady = np.ascontiguousarray(e[:, window])
    cols = [np.full(len(e), np.nan) for _ in METRIC_KEYS]
    for a in range(0, len(e), _ROWS):  # blocks of rows: small temporaries, rows still in cache
        b = min(a + _ROWS, len(e))
        for j, w in ((0, e[a:b]), (3, steady[a:b])):
            if w.shape[1]:
                cols[j][a:b] = w.mean(axis=1)
                cols[j + 1][a:b] = np.sqrt(np.mean(w * w, axis=1))
                cols[j + 2][a:b] = w.max(axis=1)
    return [dict(zip(METRIC_KEYS, vals, strict=True)) for vals in zip(*(c.tolist() for c in cols), strict=True)]


def evaluate_batched(policies: Sequence[Any], env_id: str = "AUVFollow-S4-v0", seeds: Iterable[int] = (0,), *,
                     env_kwargs: dict | None = None, policy_names: Sequence[str] | None = None,
                     trajectories: bool = False, progress: bool = True, deterministic: bool = True):
    """Like :func:`evaluate` for several policies at once, on the native vector env.

    Runs one episode per (policy, seed) in a single ``AUVFollowVectorEnv`` of
    ``len(policies) * len(seeds)`` envs (env ``p * S + j`` is policy p with seed j); each
    policy predicts for its block of envs in one batched call. Results equal those of
    :func:`evaluate` to floating-point rounding (same kernels, same seeds).
    """
    seeds = _check_seeds(seeds)
    policies = list(policies)
    if not policies:
        raise ValueError("policies is empty: give at least one policy")
    names = list(policy_names) if policy_names is not None else [
        getattr(p, "name", None) or type(p).__name__ for p in policies]
    if len(names) != len(policies):
        raise ValueError(f"policy_names has {len(names)} entries for {len(policies)} policies")
    S, P = len(seeds), len(policies)
    n = S * P
    venv = gym.make_vec(env_id, num_envs=n, vectorization_mode="vector_entry_point", **(env_kwargs or {}))
    spec: TaskSpec = venv.unwrapped.task_spec if hasattr(venv, "unwrapped") else venv.task_spec
    try:
        for p in policies:
            check_task_spec(p, spec, env_id)
    except ValueError:
        venv.close()
        raise
    obs, _ = venv.reset(seed=[s for _ in range(P) for s in seeds])
    limits = np.asarray(spec.force_limits)
    T = spec.n_steps
    blocks = [slice(p * S, (p + 1) * S) for p in range(P)]
    has_ref = [hasattr(p, "reference") for p in policies]
    # one row per step while stepping (each step writes a contiguous row); transposed to one row
    # per env at the end, so that each episode's series is contiguous for its metrics
    err_k = np.full((T, n), np.nan)
    err_own_k = np.full((T, n), np.nan)
    own = np.full((T, n, 3), np.nan) if trajectories else None
    own_k = [np.full((S, 3), np.nan) for _ in range(P)]  # this step's own reference of each block
    pose = np.zeros((T, n, 3)) if trajectories else None
    target = np.zeros((T, n, 3)) if trajectories else None
    ref = np.zeros((T, n, 2)) if trajectories else None
    force = np.zeros((T, n, 3)) if trajectories else None
    alive = np.ones(n, dtype=bool)
    length = np.full(n, T)
    terminated_any = np.zeros(n, dtype=bool)
    ret = np.zeros(n)
    start = np.ones(S, dtype=bool)
    actions = np.zeros((n, 3), dtype=np.float32)
    act_shape = (S, 3)  # each policy's block of the batch
    for k in _bar(range(T), f"{P} policies x {S} seeds on {env_id}", progress, nested=True):
        for p, blk in enumerate(blocks):
            actions[blk] = _checked_action(
                _call(policies[p].predict, "predict", names[p], env_id, seeds, k, obs[blk], state=None,
                      episode_start=start, deterministic=deterministic), act_shape, names[p], env_id, seeds, k)
        start = np.zeros(S, dtype=bool)
        obs, reward, term, trunc, info = venv.step(actions)
        np.copyto(err_k[k], info["tracking_error"], where=alive)  # err is NaN where not written
        np.add(ret, reward, out=ret, where=alive)
        for p, blk in enumerate(blocks):
            if has_ref[p]:
                own_k[p][...] = _call(policies[p].reference, "reference", names[p], env_id, seeds, k, obs[blk])
                np.hypot(own_k[p][:, 0], own_k[p][:, 1], out=err_own_k[k, blk])
                if trajectories:
                    own[k, blk] = own_k[p]
        if trajectories:
            pose[k] = info["follower_pose"]
            target[k] = info["true_target"][:, :3]
            ref[k] = info["true_reference"][:, :2]
            force[k] = np.clip(actions, -1, 1) * limits
        done = term | trunc
        if done.any():
            ended = alive & done
            length[ended] = k + 1
            terminated_any |= ended & term
            alive &= ~ended
            if not alive.any():
                break
    venv.close()
    err, err_own = np.ascontiguousarray(err_k.T), np.ascontiguousarray(err_own_k.T)
    nan = np.full(T, np.nan)
    for p in range(P):
        if not has_ref[p]:  # own reference NaN: its distance as _episode_outputs computes it
            err_own[blocks[p]] = np.hypot(nan, nan)
    # the metrics of the full-length episodes at once (row by row), the others one by one
    times = spec.dt * np.arange(1, T + 1)
    full = np.flatnonzero(length == T)
    sel = slice(None) if full.size == n else full  # (a view if every episode ran to the end)
    m_full = {int(i): m for i, m in zip(full, zip(_tracking_metrics_rows(err[sel], times, spec.steady_start_s),
                                                   _tracking_metrics_rows(err_own[sel], times, spec.steady_start_s),
                                                   strict=True), strict=True)}
    rows, trajs = [], []
    for p in range(P):
        for j, seed in enumerate(seeds):
            i = p * S + j
            L = int(length[i])
            per_step = (pose[:L, i], target[:L, i], ref[:L, i], force[:L, i]) if trajectories else ()
            row, frame = _episode_outputs(spec, names[p], seed, terminated_any[i], ret[i], err[i, :L],
                                          own[:L, i] if trajectories else None, *per_step, err_own=err_own[i, :L],
                                          metrics=m_full.get(i))
            rows.append(row)
            if trajectories:
                trajs.append(frame)
    metrics = pd.DataFrame(rows)
    return (metrics, pd.concat(trajs, ignore_index=True)) if trajectories else metrics
