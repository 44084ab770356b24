"""The benchmark protocol: one function scores any set of policies on the tiers' published
test seeds and writes the leaderboard.

>>> from agents.benchmark import benchmark
>>> result = benchmark(["PID", "PROPOSED", "results/benchmark/runs/ppo-residual"], tiers=["S4", "Hard"],
...                    out_dir="results/benchmark")          # doctest: +SKIP
>>> result.leaderboard                                        # doctest: +SKIP

Protocol (written once, here; the CLI ``auv-follow benchmark``, the sweep, the README's tables
and the HTML report all call :func:`benchmark` / :func:`leaderboard`):

* **Tiers and seeds.** A tier is a v1 tier (``Easy``, ``Medium``, ``Hard``, ``Extreme`` ->
  ``AUVFollow-<tier>-v1``, scored on the test seeds the environment package publishes) or a
  paper scenario (``S1`` ... ``S4`` -> ``AUVFollow-S<k>-v0``, scored on :data:`V0_TEST_SEEDS`,
  our choice: 100 seeds disjoint from every seed the training code uses).
* **Policies.** A scripted controller by name (``"PROPOSED"``), a trained agent by run
  directory, or a group of runs of one method (``"label=run_a,run_b,run_c"`` or a directory
  whose sub-directories are runs): the runs of a group are its training seeds.
* **Scores.** Per episode, the true-reference tracking metrics of eq. (65) (steady state
  t >= 10 s and full run). An episode that ends by termination (target lost) scores
  ``max_distance_m`` (the loss threshold) on every error metric - it is at least that bad.
* **Aggregates** per (tier, policy): IQM (interquartile mean, 25 % trimmed on each side,
  as rliable) and mean, each with a 95 % percentile **stratified bootstrap** CI (strata =
  the group's training runs; one stratum for a scripted controller; the runs share the test
  seeds, so one draw of seed indices resamples every run alike), ``scipy.stats.bootstrap``
  with a fixed seed so a rerun gives the same numbers;
  termination rate; and the **probability of improvement** over the tier's best classical
  baseline (the scripted controller with the lowest steady-state IQM), rliable's definition
  for lower-is-better scores: P(X < Y) + P(X = Y) / 2 over all pairs of episodes, with a
  bootstrap CI.
"""

from __future__ import annotations

import dataclasses
import json
import math
import platform
import warnings
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pandas as pd
from scipy import stats
from tqdm.auto import tqdm

import auv_follow_env  # noqa: F401  (registers the ids)

__all__ = ["V0_TIERS", "V1_TIERS", "V0_TEST_SEEDS", "LEADERBOARD_METRICS", "PolicySpec", "BenchmarkResult",
           "resolve_tier", "tier_test_seeds", "parse_policy", "iqm", "stratified_bootstrap_ci",
           "probability_of_improvement", "evaluate_tier", "leaderboard", "benchmark", "provenance",
           "leaderboard_markdown", "plot_leaderboard", "goal_check", "load_result"]

V0_TIERS: tuple[str, ...] = ("S1", "S2", "S3", "S4")
V1_TIERS: tuple[str, ...] = ("Easy", "Medium", "Hard", "Extreme")
#: test seeds of the paper scenarios (our choice: 100 seeds; training uses seeds < 1000 and the
#: EvalCallback seed 500, so these are held out)
V0_TEST_SEEDS: tuple[int, ...] = tuple(range(1000, 1100))
#: per-episode columns aggregated by the leaderboard (true reference, eq. (65))
LEADERBOARD_METRICS: tuple[str, ...] = ("true_steady_mean", "true_full_mean")
#: every error metric (replaced by the loss threshold for terminated episodes)
ERROR_METRICS: tuple[str, ...] = tuple(f"true_{w}_{s}" for w in ("full", "steady") for s in ("mean", "rmse", "max"))
DEFAULT_RESAMPLES = 10_000
#: policy token standing for every registered scripted controller
CLASSICAL = "classical"
DEFAULT_BOOTSTRAP_SEED = 0


# --- statistics --------------------------------------------------------------------------

def iqm(x: np.ndarray, axis: int | None = -1) -> np.ndarray:
    """Interquartile mean: the mean of the middle 50 % (``scipy.stats.trim_mean(x, 0.25)``,
    rliable's ``aggregate_iqm``); with n samples, ``int(0.25 n)`` are cut from each end."""
    return stats.trim_mean(np.asarray(x, dtype=np.float64), 0.25, axis=axis)


def _mean(x: np.ndarray, axis: int | None = -1) -> np.ndarray:
    return np.mean(x, axis=axis)


_STATISTICS: dict[str, Callable[..., np.ndarray]] = {"iqm": iqm, "mean": _mean}


def stratified_bootstrap_ci(strata: Sequence[Sequence[float]], statistic: str | Callable = "iqm", *,
                            confidence: float = 0.95, n_resamples: int = DEFAULT_RESAMPLES,
                            seed: int = DEFAULT_BOOTSTRAP_SEED, paired: bool | None = None
                            ) -> tuple[float, float, float]:
    """Point estimate and percentile-bootstrap CI of ``statistic`` over the pooled strata.

    Each stratum is resampled with replacement (its size kept), the resampled strata are
    pooled and the statistic is taken over the pool (rliable's stratified bootstrap, with
    ``scipy.stats.bootstrap`` doing the resampling). With ``paired`` the strata are aligned
    (entry j of every stratum is the same test seed) and one draw of indices is applied to all
    of them: the test seed, not the episode, is the unit resampled - several training runs
    scored on the same seeds do not count as independent conditions. ``None``: paired when
    there are several strata of equal length.

    Args:
        strata: one 1-D sequence of scores per stratum (e.g. per training run).
        statistic: ``"iqm"``, ``"mean"`` or a function ``f(x, axis=-1)``.
        confidence: CI level in (0, 1).
        n_resamples: bootstrap resamples (>= 1).
        seed: seed of the resampling generator (same seed, same CI).

    Returns:
        (estimate, low, high). A pool of one sample gives a zero-width CI.

    Raises:
        ValueError: empty strata, non-finite scores, unknown statistic, bad confidence.
    """
    if isinstance(statistic, str):
        if statistic not in _STATISTICS:
            raise ValueError(f"statistic={statistic!r} is unknown: valid statistics are {list(_STATISTICS)} "
                             f"or a function f(x, axis)")
        statistic = _STATISTICS[statistic]
    if not (isinstance(confidence, (int, float)) and 0.0 < confidence < 1.0):
        raise ValueError(f"confidence={confidence!r} is invalid: must be a number in (0, 1)")
    if isinstance(n_resamples, bool) or not isinstance(n_resamples, (int, np.integer)) or n_resamples < 1:
        raise ValueError(f"n_resamples={n_resamples!r} is invalid: must be an integer >= 1")
    arrays = [np.asarray(s, dtype=np.float64).reshape(-1) for s in strata]
    if not arrays or any(a.size == 0 for a in arrays):
        raise ValueError(f"strata={strata!r} is invalid: give at least one non-empty stratum")
    pooled = np.concatenate(arrays)
    if not np.all(np.isfinite(pooled)):
        raise ValueError("strata contain NaN or inf scores: replace them (e.g. by the failure value) first")
    est = float(statistic(pooled, axis=-1))
    if pooled.size == 1 or np.all(pooled == pooled[0]):
        return est, est, est
    resampled = tuple(a for a in arrays)
    if paired is None:
        paired = len(arrays) > 1 and len({a.size for a in arrays}) == 1
    if paired and len({a.size for a in arrays}) != 1:
        raise ValueError(f"paired=True needs strata of equal length, got sizes {[a.size for a in arrays]}")

    def pooled_stat(*samples: np.ndarray, axis: int = -1) -> np.ndarray:
        return statistic(np.concatenate(samples, axis=axis), axis=axis)

    res = stats.bootstrap(resampled, pooled_stat, n_resamples=int(n_resamples), confidence_level=confidence,
                          method="percentile", vectorized=True, paired=bool(paired), axis=-1, batch=1000,
                          rng=np.random.default_rng(seed))
    lo, hi = float(res.confidence_interval.low), float(res.confidence_interval.high)
    return est, lo, hi


def _poi(x: np.ndarray, y: np.ndarray, axis: int = -1) -> np.ndarray:
    """P(X < Y) + P(X = Y)/2 over all pairs (lower is better), batched over leading axes."""
    x = np.moveaxis(np.asarray(x, dtype=np.float64), axis, -1)
    y = np.moveaxis(np.asarray(y, dtype=np.float64), axis, -1)
    xb, yb = x[..., :, None], y[..., None, :]
    return ((xb < yb).mean(axis=(-2, -1)) + 0.5 * (xb == yb).mean(axis=(-2, -1)))


def probability_of_improvement(x: Sequence[float], y: Sequence[float], *, confidence: float = 0.95,
                               n_resamples: int = 2000, seed: int = DEFAULT_BOOTSTRAP_SEED
                               ) -> tuple[float, float, float]:
    """Probability that an episode of X has a *lower* error than an episode of Y (rliable's
    probability of improvement, Mann-Whitney U / (n_x n_y), for lower-is-better scores),
    with a percentile-bootstrap CI (X and Y resampled independently).

    Returns:
        (estimate, low, high).
    """
    xa, ya = np.asarray(x, dtype=np.float64).reshape(-1), np.asarray(y, dtype=np.float64).reshape(-1)
    if xa.size == 0 or ya.size == 0:
        raise ValueError(f"x and y must be non-empty, got sizes {xa.size} and {ya.size}")
    est = float(_poi(xa, ya))
    if xa.size == 1 and ya.size == 1:
        return est, est, est
    res = stats.bootstrap((xa, ya), _poi, n_resamples=int(n_resamples), confidence_level=confidence,
                          method="percentile", vectorized=True, paired=False, axis=-1,
                          batch=max(1, 4_000_000 // max(xa.size * ya.size, 1)), rng=np.random.default_rng(seed))
    lo, hi = float(res.confidence_interval.low), float(res.confidence_interval.high)
    if not (np.isfinite(lo) and np.isfinite(hi)):  # degenerate bootstrap distribution
        lo = hi = est
    return est, lo, hi


# --- tiers -------------------------------------------------------------------------------

def _v1_registered(tier: str) -> bool:
    return f"AUVFollow-{tier}-v1" in gym.registry


def available_tiers() -> list[str]:
    """The tier names this installation can score (v1 tiers appear once registered)."""
    return list(V0_TIERS) + [t for t in V1_TIERS if _v1_registered(t)]


def resolve_tier(tier: str) -> tuple[str, str]:
    """``(name, env_id)`` for a tier name (``"S4"``, ``"Hard"``) or its env id.

    Raises:
        ValueError: unknown or unregistered tier (lists the available ones).
    """
    if not isinstance(tier, str):
        raise ValueError(f"tier={tier!r} is invalid: must be a tier name, one of {available_tiers()}")
    name = tier
    if tier.startswith("AUVFollow-") and tier.count("-") == 2:
        name = tier.split("-")[1]
    if name in V0_TIERS:
        return name, f"AUVFollow-{name}-v0"
    if name in V1_TIERS and _v1_registered(name):
        return name, f"AUVFollow-{name}-v1"
    raise ValueError(f"tier={tier!r} is unknown or not registered: valid tiers are {available_tiers()}")


def tier_test_seeds(tier: str) -> list[int]:
    """The published test seeds of a tier (v1: from the environment package; S1-S4:
    :data:`V0_TEST_SEEDS`)."""
    name, env_id = resolve_tier(tier)
    if name in V0_TIERS:
        return list(V0_TEST_SEEDS)
    seeds = _published_seeds(name, env_id)
    if seeds is None:
        raise ValueError(f"tier={tier!r}: the environment package publishes no test seeds for {env_id}")
    return seeds


def _published_seeds(name: str, env_id: str) -> list[int] | None:
    """Find the test seeds the env package publishes for a v1 tier."""
    import importlib

    for modname in ("auv_follow_env", "auv_follow_env.tiers"):
        try:
            mod = importlib.import_module(modname)
        except ImportError:
            continue
        fn = getattr(mod, "test_seeds", None)
        if callable(fn):
            for arg in (name, env_id):
                try:
                    return [int(s) for s in fn(arg)]
                except (ValueError, KeyError, TypeError):
                    pass
        table = getattr(mod, "TEST_SEEDS", None)
        if isinstance(table, Mapping):
            for key in (name, env_id):
                if key in table:
                    return [int(s) for s in table[key]]
        tiers = getattr(mod, "TIERS", None)
        if isinstance(tiers, Mapping):
            for key in (name, env_id):
                t = tiers.get(key)
                if t is not None and getattr(t, "test_seeds", None) is not None:
                    return [int(s) for s in t.test_seeds]
    return None


# --- policies ----------------------------------------------------------------------------

@dataclass(frozen=True)
class PolicySpec:
    """One leaderboard entry: a scripted controller, or a learned method with its runs."""

    label: str  #: name on the leaderboard
    kind: str  #: "classical" (scripted controller) or "learned"
    controller: str | None = None  #: controller name (classical)
    runs: tuple[str, ...] = ()  #: run directories (learned; one per training seed)
    tiers: tuple[str, ...] = ()  #: the tiers it is scored on (empty: every benchmarked tier)


def _controllers() -> tuple[str, ...]:
    """Every registered scripted controller (the paper's four and, where present, ours)."""
    import controllers

    return tuple(getattr(controllers, "ALL_CONTROLLERS", controllers.CONTROLLERS))


def _is_run(p: Path) -> bool:
    return (p / "model.zip").is_file() and (p / "config.yaml").is_file()


def parse_policy(item: str | Path | PolicySpec) -> PolicySpec:
    """A :class:`PolicySpec` from a controller name, a run directory, a directory of runs
    (one method, its runs = training seeds) or ``"label=run_a,run_b"``; a suffix
    ``@Tier[+Tier]`` scores it on those tiers only (e.g. an expensive ``MPC@Hard``).

    Raises:
        ValueError: the item is none of these (names the valid controllers).
    """
    if isinstance(item, PolicySpec):
        return item
    text = str(item)
    if "@" in text and not Path(text).exists():
        base, _, only = text.rpartition("@")
        tiers = tuple(resolve_tier(t)[0] for t in only.split("+") if t)
        if not tiers:
            raise ValueError(f"policy={text!r} is invalid: give tiers after '@', e.g. MPC@Hard or MPC@Hard+Extreme")
        return dataclasses.replace(parse_policy(base), tiers=tiers)
    if text in _controllers():
        return PolicySpec(label=text, kind="classical", controller=text)
    label = None
    paths = [text]
    if "=" in text and not Path(text).exists():
        label, rest = text.split("=", 1)
        paths = [p for p in rest.split(",") if p]
    runs: list[str] = []
    for ptext in paths:
        p = Path(ptext)
        if _is_run(p):
            runs.append(str(p))
        elif p.is_dir() and any(_is_run(c) for c in p.iterdir()):
            runs.extend(str(c) for c in sorted(p.iterdir()) if _is_run(c))
            label = label or p.name
        else:
            raise ValueError(f"policy={ptext!r} is invalid: must be a controller name {list(_controllers())}, a run "
                             f"directory (with model.zip and config.yaml), a directory of runs, or label=run,run")
    if not runs:
        raise ValueError(f"policy={text!r} names no runs")
    if label is None:
        from agents.train import load_agent

        label = load_agent(runs[0]).name if len(runs) == 1 else Path(runs[0]).parent.name
    return PolicySpec(label=label, kind="learned", runs=tuple(runs))


class _ObsPrefix:
    """Feed a policy the first ``width`` observation fields (a v0-trained agent on a v1 env:
    the v1 layout starts with the 16 v0 fields)."""

    def __init__(self, policy: Any, width: int) -> None:
        self.policy, self.width = policy, int(width)
        self.name = getattr(policy, "name", type(policy).__name__)

    def predict(self, observation: Any, state: Any = None, episode_start: Any = None,
                deterministic: bool = True) -> tuple[np.ndarray, Any]:
        obs = np.asarray(observation)[..., : self.width]
        return self.policy.predict(obs, state=state, episode_start=episode_start, deterministic=deterministic)


def _agent_obs_width(agent: Any) -> int:
    """Width of the raw env observation an agent was trained on."""
    from auv_follow_env.layout import OBS_DIM

    try:
        probe = gym.make(agent.env_id, **(agent.env_kwargs or {}))
        width = int(probe.observation_space.shape[0])
        probe.close()
        return width
    except (gym.error.Error, ValueError, TypeError):
        return OBS_DIM


class IncompatiblePolicy(ValueError):
    """A policy that cannot run on a tier (e.g. an agent trained on the 20-field v1
    observation, on a 16-field v0 scenario)."""


def build_policy(spec: PolicySpec, run: str | None, env_id: str, task_spec: Any, obs_width: int) -> Any:
    """The policy object (SB3 ``predict`` protocol over raw observations of ``env_id``) of one
    run of ``spec`` (or of its controller)."""
    if spec.kind == "classical":
        from controllers import make_controller

        return make_controller(spec.controller, task_spec)
    from agents.train import load_agent

    agent = load_agent(run, name=spec.label)
    width = _agent_obs_width(agent)
    if width > obs_width:
        raise IncompatiblePolicy(f"policy={spec.label!r} (run {run}) was trained on {width}-wide observations and "
                                 f"cannot run on {env_id} ({obs_width} fields)")
    policy = agent.raw_policy(env_id if width == obs_width else agent.env_id, {}) if agent.mode == "residual" \
        else agent
    return _ObsPrefix(policy, width) if width < obs_width else policy


# --- evaluation --------------------------------------------------------------------------

def _condition_columns(env_id: str, seeds: Sequence[int], task_spec: Any) -> pd.DataFrame:
    """The condition each test seed draws (from the env's ``info`` at reset for v1 tiers; the
    scenario's constants for v0), one row per seed, columns ``cond_*``."""
    rows = []
    env = gym.make(env_id)
    for s in seeds:
        _, info = env.reset(seed=int(s))
        cond = info.get("condition")
        row: dict[str, Any] = {"seed": int(s)}
        if isinstance(cond, Mapping) or dataclasses.is_dataclass(cond):
            items = dataclasses.asdict(cond).items() if dataclasses.is_dataclass(cond) else cond.items()
            for k, v in items:
                if isinstance(v, (int, float, np.integer, np.floating, bool, str)):
                    row[f"cond_{k}"] = v
        else:
            row.update({"cond_latency_s": task_spec.delay_s, "cond_update_period_s": task_spec.dt,
                        "cond_loss_prob": 0.0})
        rows.append(row)
    env.close()
    return pd.DataFrame(rows)


def _max_distance(env_id: str) -> float:
    env = gym.make(env_id)
    cfg = getattr(env.unwrapped, "config", None)
    env.close()
    return float(getattr(cfg, "max_distance_m", math.nan))


#: the code that decides an episode's numbers (the cache key includes its git hashes)
_EPISODE_CODE = ("auv_follow_env", "controllers", "agents/residual.py", "agents/train.py", "agents/batched_obs.py",
                 "agents/batched_ppo.py")


def _code_fingerprint() -> str | None:
    """Git hashes of :data:`_EPISODE_CODE` at HEAD, or None if any of it differs from HEAD
    (then nothing is cached)."""
    import subprocess

    root = Path(__file__).resolve().parent.parent
    try:
        dirty = subprocess.run(["git", "status", "--porcelain", "--", *_EPISODE_CODE], cwd=root, capture_output=True,
                               text=True, timeout=30)
        if dirty.returncode != 0 or dirty.stdout.strip():
            return None
        out = subprocess.run(["git", "rev-parse", *[f"HEAD:{p}" for p in _EPISODE_CODE]], cwd=root,
                             capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip().replace("\n", ",") if out.returncode == 0 else None


def _entry_key(spec: PolicySpec, run: str | None, env_id: str, seeds: Sequence[int], code: str) -> str:
    import hashlib

    h = hashlib.sha256()
    h.update(json.dumps({"env_id": env_id, "seeds": [int(x) for x in seeds], "kind": spec.kind,
                         "controller": spec.controller, "label": spec.label, "code": code,
                         "numpy": np.__version__}).encode())
    if run is not None:
        for f in ("model.zip", "vecnormalize.json", "vecnormalize.pkl", "config.yaml"):
            fp = Path(run) / f
            if fp.is_file():
                h.update(fp.read_bytes())
    return h.hexdigest()[:32]


def evaluate_tier(policies: Sequence[PolicySpec], tier: str, seeds: Sequence[int] | None = None, *,
                  batched: bool = True, progress: bool = True, skip_incompatible: bool = True,
                  cache_dir: str | Path | None = None) -> pd.DataFrame:
    """Per-episode rows of every run of every policy on one tier's seeds.

    A policy that cannot run on the tier (:class:`IncompatiblePolicy`, e.g. a v1-trained
    agent on a v0 scenario) is left out with a warning (``skip_incompatible``) or raises.

    With ``cache_dir``, each run's episodes are stored under a key of (env id, seeds, policy,
    the run's model files, the git hashes of the episode code) and reused on a later call;
    nothing is cached while that code differs from the git HEAD. Episodes are deterministic,
    so a cached and a fresh evaluation agree.

    All runs share one native vector env (:func:`controllers.evaluation.evaluate_batched`)
    unless ``batched`` is False (one single-env episode at a time, same numbers).

    Returns:
        columns tier, env_id, policy, kind, run, seed, steps, terminated, return, the
        ``true_*`` / ``own_*`` metrics, ``cond_*`` (the drawn condition) and
        ``fail_error_m`` (the loss threshold used for terminated episodes).
    """
    from controllers.evaluation import evaluate, evaluate_batched

    name, env_id = resolve_tier(tier)
    seeds = list(tier_test_seeds(name) if seeds is None else seeds)
    probe = gym.make(env_id)
    task_spec = probe.unwrapped.task_spec
    obs_width = int(probe.observation_space.shape[0])
    probe.close()
    entries, objs = [], []
    for spec in policies:
        if spec.tiers and name not in spec.tiers:
            continue
        try:
            built = [(run, build_policy(spec, run, env_id, task_spec, obs_width)) for run in (spec.runs or (None,))]
        except IncompatiblePolicy as exc:
            if not skip_incompatible:
                raise
            warnings.warn(f"{name}: {exc}; {spec.label!r} is left out of this tier", stacklevel=2)
            continue
        entries.extend((spec, run) for run, _ in built)
        objs.extend(obj for _, obj in built)
    if not entries:
        raise ValueError(f"tier={tier!r}: none of the policies can run on {env_id}")
    labels = [spec.label for spec, _ in entries]
    code = _code_fingerprint() if cache_dir is not None else None
    keys = [_entry_key(spec, run, env_id, seeds, code) if code else None for spec, run in entries]
    cached: dict[int, pd.DataFrame] = {}
    if code:
        for i, k in enumerate(keys):
            f = Path(cache_dir) / f"{k}.parquet"
            if f.is_file():
                cached[i] = pd.read_parquet(f)
    todo = [i for i in range(len(entries)) if i not in cached]
    fresh: dict[int, pd.DataFrame] = {}
    if todo and batched:
        out = evaluate_batched([objs[i] for i in todo], env_id, seeds, policy_names=[labels[i] for i in todo],
                               progress=progress)
        fresh = {i: out.iloc[j * len(seeds):(j + 1) * len(seeds)].reset_index(drop=True) for j, i in enumerate(todo)}
    elif todo:
        fresh = {i: evaluate(objs[i], env_id, seeds, policy_name=labels[i], progress=progress) for i in todo}
    if code:
        Path(cache_dir).mkdir(parents=True, exist_ok=True)
        for i, d in fresh.items():
            d.to_parquet(Path(cache_dir) / f"{keys[i]}.parquet", index=False)
    df = pd.concat([cached[i] if i in cached else fresh[i] for i in range(len(entries))], ignore_index=True)
    df.insert(0, "env_id", env_id)
    df.insert(0, "tier", name)
    df.insert(df.columns.get_loc("policy") + 1, "kind", np.repeat([s.kind for s, _ in entries], len(seeds)))
    df.insert(df.columns.get_loc("kind") + 1, "run",
              np.repeat([Path(r).name if r else s.controller for s, r in entries], len(seeds)))
    df["fail_error_m"] = _max_distance(env_id)
    return df.merge(_condition_columns(env_id, seeds, task_spec), on="seed", how="left")


def scores(episodes: pd.DataFrame, metric: str) -> pd.Series:
    """The per-episode score of ``metric``: the metric, or the loss threshold for an episode
    that terminated (or has no sample in the window)."""
    if metric not in episodes:
        raise ValueError(f"metric={metric!r} is not a column: valid metrics are {list(ERROR_METRICS)}")
    s = episodes[metric].astype(float)
    fail = episodes["terminated"].astype(bool) | ~np.isfinite(s)
    if metric in ERROR_METRICS and "fail_error_m" in episodes:
        s = s.where(~fail, episodes["fail_error_m"].astype(float))
    return s


def leaderboard(episodes: pd.DataFrame, *, metrics: Sequence[str] = LEADERBOARD_METRICS,
                n_resamples: int = DEFAULT_RESAMPLES, seed: int = DEFAULT_BOOTSTRAP_SEED,
                confidence: float = 0.95, progress: bool = False) -> pd.DataFrame:
    """Aggregate a per-episode table into the leaderboard, one row per (tier, policy).

    Args:
        episodes: rows with columns tier, policy, kind ("classical" / "learned"), run,
            terminated and ``metrics`` (e.g. from :func:`evaluate_tier`).
        metrics: error columns to aggregate (lower is better); the first ranks the classical
            baselines and is the one the probability of improvement is computed on.
        n_resamples, seed, confidence: bootstrap settings.

    Returns:
        columns tier, policy, kind, runs, episodes, for each metric ``<m>_iqm``,
        ``<m>_iqm_lo``, ``<m>_iqm_hi``, ``<m>_mean``, ``<m>_mean_lo``, ``<m>_mean_hi``;
        ``termination_rate``, ``best_classical``, ``<m0>_iqm_change_pct`` (vs the best
        classical baseline), ``poi``, ``poi_lo``, ``poi_hi``; ``run_iqm_min`` /
        ``run_iqm_max`` (spread of the per-run IQMs of ``metrics[0]``).
    """
    need = {"tier", "policy", "kind", "run", "terminated", *metrics}
    missing = sorted(need - set(episodes.columns))
    if missing:
        raise ValueError(f"episodes lacks columns {missing}: give a table from evaluate_tier")
    if not metrics:
        raise ValueError("metrics is empty: give at least one metric column")
    m0 = metrics[0]
    rows = []
    groups = list(episodes.groupby(["tier", "policy"], sort=False))
    for (tier, pol), d in tqdm(groups, desc="leaderboard", disable=not progress, leave=False):
        d = d.sort_values(["run", "seed"], kind="stable")  # strata aligned by test seed
        row: dict[str, Any] = {"tier": tier, "policy": pol, "kind": d["kind"].iloc[0],
                               "runs": int(d["run"].nunique()), "episodes": len(d)}
        for m in metrics:
            sc = scores(d, m)
            strata = [sc[d["run"] == r].to_numpy() for r in d["run"].unique()]
            for stat in ("iqm", "mean"):
                est, lo, hi = stratified_bootstrap_ci(strata, stat, n_resamples=n_resamples, seed=seed,
                                                      confidence=confidence)
                row[f"{m}_{stat}"], row[f"{m}_{stat}_lo"], row[f"{m}_{stat}_hi"] = est, lo, hi
        per_run = [float(iqm(scores(d[d["run"] == r], m0).to_numpy())) for r in d["run"].unique()]
        row["run_iqm_min"], row["run_iqm_max"] = min(per_run), max(per_run)
        row["termination_rate"] = float(d["terminated"].astype(bool).mean())
        rows.append(row)
    board = pd.DataFrame(rows)
    board["best_classical"] = None
    for c in (f"{m0}_iqm_change_pct", "poi", "poi_lo", "poi_hi"):
        board[c] = np.nan
    for tier, idx in board.groupby("tier", sort=False).groups.items():
        sub = board.loc[idx]
        classical = sub[sub["kind"] == "classical"]
        if classical.empty:
            continue
        best = classical.loc[classical[f"{m0}_iqm"].idxmin(), "policy"]
        board.loc[idx, "best_classical"] = best
        board.loc[idx, f"{m0}_iqm_change_pct"] = 100.0 * (
            sub[f"{m0}_iqm"] / float(classical.loc[classical["policy"] == best, f"{m0}_iqm"].iloc[0]) - 1.0)
        ep_t = episodes[episodes["tier"] == tier]
        y = scores(ep_t[ep_t["policy"] == best], m0).to_numpy()
        for i in idx:
            x = scores(ep_t[ep_t["policy"] == board.at[i, "policy"]], m0).to_numpy()
            board.loc[i, ["poi", "poi_lo", "poi_hi"]] = probability_of_improvement(
                x, y, n_resamples=max(200, n_resamples // 5), seed=seed, confidence=confidence)
    return board


def goal_check(board: pd.DataFrame, tier: str = "Hard", metric: str = "true_steady_mean",
               reduction: float = 0.30) -> dict[str, Any]:
    """Is the best learned policy's IQM at least ``reduction`` below the best classical
    baseline's, with non-overlapping CIs, on ``tier``? Returns the numbers and the verdict."""
    sub = board[board["tier"] == tier]
    learned, classical = sub[sub["kind"] == "learned"], sub[sub["kind"] == "classical"]
    if learned.empty or classical.empty:
        return {"tier": tier, "met": None, "reason": "needs both a learned and a classical policy on this tier"}
    c = classical.loc[classical[f"{metric}_iqm"].idxmin()]
    lrn = learned.loc[learned[f"{metric}_iqm"].idxmin()]
    change = float(lrn[f"{metric}_iqm"] / c[f"{metric}_iqm"] - 1.0)
    separated = bool(lrn[f"{metric}_iqm_hi"] < c[f"{metric}_iqm_lo"])
    return {"tier": tier, "metric": metric, "best_learned": lrn["policy"], "best_classical": c["policy"],
            "learned_iqm": float(lrn[f"{metric}_iqm"]),
            "learned_ci": (float(lrn[f"{metric}_iqm_lo"]), float(lrn[f"{metric}_iqm_hi"])),
            "classical_iqm": float(c[f"{metric}_iqm"]),
            "classical_ci": (float(c[f"{metric}_iqm_lo"]), float(c[f"{metric}_iqm_hi"])),
            "change_pct": 100.0 * change, "cis_separated": separated,
            "met": bool(change <= -reduction and separated)}


# --- provenance and output ---------------------------------------------------------------

def provenance(config: Mapping[str, Any]) -> dict[str, Any]:
    """The configuration and the versions / git commit a result was made with."""
    import scipy

    from agents.train import versions

    v = versions()
    v.update({"pandas": pd.__version__, "scipy": scipy.__version__, "python_impl": platform.python_implementation()})
    return {"config": json.loads(json.dumps(config, default=str)), "versions": v}


@dataclass
class BenchmarkResult:
    """What :func:`benchmark` returns (and writes)."""

    episodes: pd.DataFrame
    leaderboard: pd.DataFrame
    provenance: dict[str, Any]
    files: dict[str, Path] = field(default_factory=dict)


def _fmt_ci(est: float, lo: float, hi: float, digits: int = 4) -> str:
    if not np.isfinite(est):
        return "-"
    return f"{est:.{digits}f} [{lo:.{digits}f}, {hi:.{digits}f}]"


def leaderboard_markdown(board: pd.DataFrame, prov: Mapping[str, Any] | None = None,
                         metrics: Sequence[str] = LEADERBOARD_METRICS) -> str:
    """The leaderboard as Markdown: one table per tier (errors in m, 95 % CIs in brackets)."""
    lines = ["# Leaderboard", "",
             "True-reference tracking error [m] (eq. (65)), steady state t >= 10 s and full run: IQM and mean "
             "over the tier's test episodes with 95 % stratified-bootstrap CIs (strata: training runs); "
             "P(better) = probability that an episode has a lower steady-state error than one of the tier's best "
             "classical baseline (rliable's probability of improvement); a terminated episode scores the loss "
             "threshold.", ""]
    m0 = metrics[0]
    for tier, sub in board.groupby("tier", sort=False):
        best = sub["best_classical"].iloc[0]
        lines += [f"## {tier}" + (f" (best classical: {best})" if best else ""), ""]
        head = ["policy", "kind", "runs x episodes"]
        for m in metrics:
            short = m.replace("true_", "").replace("_mean", "")
            head += [f"{short} IQM", f"{short} mean"]
        head += ["vs best classical (IQM)", "P(better) vs best classical", "terminated"]
        lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        for _, r in sub.sort_values(f"{m0}_iqm").iterrows():
            cells = [f"**{r['policy']}**" if r["policy"] == best else str(r["policy"]), r["kind"],
                     f"{r['runs']} x {r['episodes'] // max(r['runs'], 1)}"]
            for m in metrics:
                cells += [_fmt_ci(r[f"{m}_iqm"], r[f"{m}_iqm_lo"], r[f"{m}_iqm_hi"]),
                          _fmt_ci(r[f"{m}_mean"], r[f"{m}_mean_lo"], r[f"{m}_mean_hi"])]
            chg = r.get(f"{m0}_iqm_change_pct")
            cells.append("-" if chg is None or not np.isfinite(chg) else f"{chg:+.1f} %")
            cells.append(_fmt_ci(r["poi"], r["poi_lo"], r["poi_hi"], 2))
            cells.append(f"{100 * r['termination_rate']:.0f} %")
            lines.append("| " + " | ".join(cells) + " |")
        lines.append("")
    if prov is not None:
        cfg = prov.get("config", {})
        lines += ["## Provenance", "", "```json", json.dumps(prov, indent=1, default=str), "```", ""]
        if "command" in cfg:
            lines[-5:-5] = [f"Reproduce: `{cfg['command']}`", ""]
    return "\n".join(lines)


def plot_leaderboard(board: pd.DataFrame, path: str | Path, metric: str = "true_steady_mean",
                     prov: Mapping[str, Any] | None = None) -> None:
    """One panel per tier: the IQM of ``metric`` per policy with its 95 % CI (log scale)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker  # noqa: F401  (matplotlib.ticker below)

    tiers = list(dict.fromkeys(board["tier"]))
    n_pol = board.groupby("tier").size().max()
    fig, axes = plt.subplots(1, len(tiers), figsize=(3.6 * len(tiers) + 1.5, 0.35 * n_pol + 1.6), squeeze=False)
    for ax, tier in zip(axes[0], tiers, strict=True):
        sub = board[board["tier"] == tier].sort_values(f"{metric}_iqm", ascending=False)
        y = np.arange(len(sub))
        est = sub[f"{metric}_iqm"].to_numpy()
        err = np.vstack([est - sub[f"{metric}_iqm_lo"].to_numpy(), sub[f"{metric}_iqm_hi"].to_numpy() - est])
        colors = ["C1" if k == "classical" else "C0" for k in sub["kind"]]
        ax.barh(y, est, xerr=err, color=colors, capsize=3)
        ax.set_yticks(y, sub["policy"], fontsize=8)
        ax.set_xscale("log")
        # labelled ticks at 1, 2, 5 x 10^k; no minor labels (they overlap on short ranges)
        ax.xaxis.set_major_locator(matplotlib.ticker.LogLocator(base=10.0, subs=(1.0, 2.0, 5.0)))
        ax.xaxis.set_major_formatter(matplotlib.ticker.FuncFormatter(lambda v, _: f"{v:g}"))
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.tick_params(axis="x", labelsize=8)
        ax.set_title(tier)
        ax.set_xlabel(f"IQM {metric.replace('true_', '')} [m]")
    fig.suptitle("true-reference error, IQM with 95 % CI (orange: classical, blue: learned)", fontsize=9)
    fig.tight_layout()
    meta = {"Description": json.dumps(prov, default=str)} if prov is not None else None
    fig.savefig(path, dpi=120, metadata=meta)
    plt.close(fig)


def _write_csv(df: pd.DataFrame, path: Path, prov: Mapping[str, Any]) -> None:
    with open(path, "w") as f:
        f.write("# provenance: " + json.dumps(prov, default=str) + "\n")
        df.to_csv(f, index=False)


def _write_parquet(df: pd.DataFrame, path: Path, prov: Mapping[str, Any]) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    table = pa.Table.from_pandas(df, preserve_index=False)
    meta = dict(table.schema.metadata or {})
    meta[b"auv_follow_provenance"] = json.dumps(prov, default=str).encode()
    pq.write_table(table.replace_schema_metadata(meta), path)


def load_result(out_dir: str | Path) -> BenchmarkResult:
    """Read a benchmark written by :func:`benchmark` back (episodes, leaderboard, provenance)."""
    out = Path(out_dir)
    if not (out / "episodes.parquet").is_file():
        raise FileNotFoundError(f"{out}/episodes.parquet does not exist: run `auv-follow benchmark --out {out}`")
    episodes = pd.read_parquet(out / "episodes.parquet")
    board = pd.read_csv(out / "leaderboard.csv", comment="#")
    prov = json.loads((out / "benchmark.json").read_text())
    return BenchmarkResult(episodes, board, prov, {})


def benchmark(policies: Iterable[str | Path | PolicySpec] | None = None, tiers: Iterable[str] = ("S4",), *,
              seeds: Mapping[str, Sequence[int]] | Sequence[int] | None = None, out_dir: str | Path | None = None,
              n_resamples: int = DEFAULT_RESAMPLES, bootstrap_seed: int = DEFAULT_BOOTSTRAP_SEED,
              batched: bool = True, progress: bool = True, command: str | None = None,
              cache_dir: str | Path | None = None) -> BenchmarkResult:
    """Score ``policies`` on ``tiers`` and build the leaderboard.

    Args:
        policies: controller names, run directories, directories of runs, ``label=run,run``
            or ``"classical"`` (every registered scripted controller; the default).
        tiers: tier names or ids (``"S4"``, ``"Hard"``, ``"AUVFollow-Hard-v1"``).
        seeds: override the published test seeds (one list for all tiers, or per tier); for
            quick looks only - the leaderboard protocol is the published seeds.
        out_dir: if given, write ``episodes.parquet``, ``leaderboard.csv``, ``leaderboard.md``,
            ``leaderboard.png`` and ``benchmark.json`` there (each records the provenance).
        n_resamples, bootstrap_seed: bootstrap settings (fixed seed: reruns agree).
        batched: evaluate through the native vector env.
        command: the command line to record (the CLI fills it in).
        cache_dir: reuse the episodes of runs evaluated before (see :func:`evaluate_tier`).

    Raises:
        ValueError: unknown tier or policy, bad seeds.
    """
    items: list[Any] = []
    for p in (list(policies) if policies is not None else [CLASSICAL]):
        items.extend(_controllers() if p == CLASSICAL else [p])
    specs = [parse_policy(p) for p in items]
    if not specs:
        raise ValueError("policies is empty: give at least one controller name or run directory")
    labels = [s.label for s in specs]
    dup = sorted({x for x in labels if labels.count(x) > 1})
    if dup:
        raise ValueError(f"policies has duplicate labels {dup}: give each method once (use label=run,run)")
    tiers = [resolve_tier(t)[0] for t in tiers]
    if not tiers:
        raise ValueError(f"tiers is empty: give at least one of {available_tiers()}")
    seed_map: dict[str, list[int]] = {}
    for t in tiers:
        if seeds is None:
            seed_map[t] = tier_test_seeds(t)
        elif isinstance(seeds, Mapping):
            seed_map[t] = list(seeds[t]) if t in seeds else tier_test_seeds(t)
        else:
            seed_map[t] = list(seeds)
    frames = [evaluate_tier(specs, t, seed_map[t], batched=batched, progress=progress, cache_dir=cache_dir)
              for t in tqdm(tiers, desc="tiers", disable=not progress)]
    episodes = pd.concat(frames, ignore_index=True)
    board = leaderboard(episodes, n_resamples=n_resamples, seed=bootstrap_seed, progress=progress)
    config = {"command": command, "tiers": {t: resolve_tier(t)[1] for t in tiers}, "seeds": seed_map,
              "policies": [dataclasses.asdict(s) for s in specs], "metrics": list(LEADERBOARD_METRICS),
              "n_resamples": n_resamples, "bootstrap_seed": bootstrap_seed, "confidence": 0.95,
              "batched": batched, "published_seeds": seeds is None,
              "cache_dir": None if cache_dir is None else str(cache_dir)}
    prov = provenance(config)
    result = BenchmarkResult(episodes, board, prov)
    if out_dir is not None:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        files = {"episodes": out / "episodes.parquet", "leaderboard_csv": out / "leaderboard.csv",
                 "leaderboard_md": out / "leaderboard.md", "leaderboard_png": out / "leaderboard.png",
                 "provenance": out / "benchmark.json"}
        _write_parquet(episodes, files["episodes"], prov)
        _write_csv(board, files["leaderboard_csv"], prov)
        files["leaderboard_md"].write_text(leaderboard_markdown(board, prov) + "\n")
        plot_leaderboard(board, files["leaderboard_png"], prov=prov)
        files["provenance"].write_text(json.dumps(prov, indent=1, default=str) + "\n")
        result.files = files
    return result
