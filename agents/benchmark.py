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

import contextlib
import dataclasses
import json
import math
import platform
import re
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
           "resolve_tier", "tier_test_seeds", "default_test_seeds", "parse_policy", "iqm", "stratified_bootstrap_ci",
           "probability_of_improvement", "evaluate_tier", "leaderboard", "benchmark", "provenance",
           "leaderboard_markdown", "plot_leaderboard", "goal_check", "load_result", "check_seed_list",
           "check_labels", "benchmark_summary", "RESERVED_LABELS", "MAX_RESAMPLES"]

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
#: most bootstrap resamples accepted (a million take minutes per row; more only waits longer)
MAX_RESAMPLES = 1_000_000
#: policy token standing for every registered scripted controller
CLASSICAL = "classical"
DEFAULT_BOOTSTRAP_SEED = 0
#: leaderboard labels of the floors' reference rows (agents/floors.py): no policy may take them
RESERVED_LABELS: tuple[str, ...] = ("control floor", "information floor")


def _label_key(label: str) -> str:
    return " ".join(str(label).split()).casefold()


def check_labels(labels: Sequence[str]) -> None:
    """Refuse a policy label that is one of :data:`RESERVED_LABELS` (compared without regard to
    case or repeated spaces: the floors' rows would take the policy's episodes into theirs)."""
    reserved = {_label_key(r) for r in RESERVED_LABELS}
    bad = [x for x in labels if _label_key(x) in reserved]
    if bad:
        raise ValueError(f"policy label {bad[0]!r} is reserved for the floors' reference rows "
                         f"{list(RESERVED_LABELS)}: give the policy another label (label=module:Class)")


def check_seed_list(seeds: Any, name: str = "seeds") -> list[int]:
    """``seeds`` as a list of distinct integers in [0, 2**63 - 1] (a seed list is a set of
    episodes: a repeated seed would count one episode several times in every aggregate).

    Raises:
        ValueError: not a sequence of integers, empty, out of range or with a repeated seed
            (names them).
    """
    from controllers.evaluation import MAX_SEED

    if isinstance(seeds, (str, bytes)) or not isinstance(seeds, Iterable):
        raise ValueError(f"{name}={seeds!r} is invalid: give a list of integers, e.g. [3000000, 3000001]")
    out: list[int] = []
    for x in seeds:
        if isinstance(x, bool) or not isinstance(x, (int, np.integer)):
            raise ValueError(f"{name} contains {x!r}: seeds must be integers in [0, 2**63 - 1]")
        if not 0 <= int(x) <= MAX_SEED:
            raise ValueError(f"{name} contains {int(x)}: seeds must be integers in [0, 2**63 - 1] "
                             f"(the tables store 64-bit integers)")
        out.append(int(x))
    if not out:
        raise ValueError(f"{name} is empty: give at least one seed")
    if len(set(out)) != len(out):
        seen: set[int] = set()
        rep = sorted({x for x in out if x in seen or seen.add(x)})
        raise ValueError(f"{name} repeats {rep[:10]}{' ...' if len(rep) > 10 else ''}: a seed list is a set of "
                         f"episodes (a repeated seed would count one episode several times): give each seed once")
    return out


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


def default_test_seeds(env_id: str, n: int = 10) -> list[int]:
    """The seeds ``evaluate`` / ``compare`` use when none are given: the first ``n`` published
    test seeds of the env's family - a v1 tier's own (:func:`tier_test_seeds`), and
    :data:`V0_TEST_SEEDS` for the paper's scenarios and the custom ids ``AUVFollow-v0`` /
    ``AUVFollow-v1`` (held out from every seed the training code uses)."""
    try:
        name, _ = resolve_tier(env_id)
    except ValueError:
        return list(V0_TEST_SEEDS[:n])
    return tier_test_seeds(name)[:n]


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
    kind: str  #: "classical" (scripted controller), "learned" or "external" (a user's ``module:Class``)
    controller: str | None = None  #: controller name (classical) or ``module:Class`` (external)
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
    (one method, its runs = training seeds), ``"label=run_a,run_b"`` or a user's controller
    class ``"[label=]module.path:ClassName"`` (:func:`_import_external`); a suffix
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
    ext = _EXTERNAL.match(text)
    if ext is not None and not Path(text).exists():
        target = ext.group("target")
        _import_external(target)  # refuses an unknown module or class now, naming it
        return PolicySpec(label=ext.group("label") or target.rsplit(":", 1)[1], kind="external", controller=target)
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
    for r in runs:
        _check_complete_run(Path(r), text)
    if label is None:
        from agents.train import load_agent

        label = load_agent(runs[0]).name if len(runs) == 1 else Path(runs[0]).parent.name
    return PolicySpec(label=label, kind="learned", runs=tuple(runs))


#: ``[label=]module.path:ClassName`` - a user's controller class (see :func:`_import_external`)
_EXTERNAL = re.compile(r"^(?:(?P<label>[^=]+)=)?(?P<target>[A-Za-z_][\w.]*:[A-Za-z_]\w*)$")


def _import_external(target: str) -> type:
    """The class ``module.path:ClassName`` (the current directory is searched too, so a file
    next to you works with the console script). Its protocol: ``Class(task_spec)`` builds the
    policy for one tier; ``predict(observation, state=None, episode_start=None,
    deterministic=True) -> (action, state)`` takes a batch ``(n_envs, obs_dim)`` and returns
    actions in [-1, 1] of shape ``(n_envs, 3)`` (where the benchmark has one observation - the
    unbatched evaluation, the replay episode - it passes a batch of one: :class:`_BatchProtocol`);
    an optional ``reset()`` is called at the start of the episodes. Importing runs the module:
    name only code you trust (building a report never imports it).

    Raises:
        ValueError: the module cannot be imported (or raises while it is), or has no such class
            with a ``predict``.
    """
    import importlib
    import os
    import sys

    module, _, cls_name = target.partition(":")
    cwd = os.getcwd()
    added = cwd not in sys.path
    if added:
        sys.path.append(cwd)
    try:
        mod = importlib.import_module(module)
    except ImportError as exc:
        raise ValueError(f"policy={target!r} is invalid: module {module!r} cannot be imported ({exc}); give "
                         "module.path:ClassName of an installed module or one under the current directory") from None
    except Exception as exc:  # noqa: BLE001 (importing runs the user's module: it can raise anything)
        text = " ".join(str(exc).split())[:300]
        raise ValueError(f"policy={target!r}: importing module {module!r} raised {type(exc).__name__}"
                         + (f": {text}" if text else "")) from exc
    finally:
        if added:
            sys.path.remove(cwd)
    cls = getattr(mod, cls_name, None)
    if not isinstance(cls, type) or not callable(getattr(cls, "predict", None)):
        raise ValueError(f"policy={target!r} is invalid: {module} has no class {cls_name!r} with a predict method "
                         "(see docs/benchmark.md, 'Your own controller')")
    return cls


def _check_complete_run(run: Path, policy: str) -> None:
    """Refuse a run whose training did not finish: ``config.yaml`` records ``result.interrupted:
    true`` (Ctrl-C or a signal) or has no ``result`` (still training, or killed)."""
    import yaml

    cfg_path = run / "config.yaml"
    try:
        cfg = yaml.safe_load(cfg_path.read_text())
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise ValueError(f"policy={policy!r}: {cfg_path} is not readable YAML ({type(exc).__name__})") from None
    result = cfg.get("result") if isinstance(cfg, dict) else None
    if not isinstance(result, dict):
        raise ValueError(f"policy={policy!r}: run {run} has no 'result' in {cfg_path} (training still running or "
                         "killed): only finished runs can be benchmarked")
    if result.get("interrupted"):
        steps = result.get("num_timesteps")
        total = (cfg.get("run") or {}).get("total_timesteps") if isinstance(cfg.get("run"), dict) else None
        raise ValueError(f"policy={policy!r}: run {run} is an interrupted training run (result.interrupted: true in "
                         f"{cfg_path}, {steps} of {total} steps): finish it with `auv-follow train --resume` or "
                         "leave it out")


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


class _BatchProtocol:
    """A user's controller as docs/benchmark.md describes it: ``predict`` always gets a batch
    ``(n_envs, obs_dim)`` and returns ``(n_envs, 3)``. A single observation (the unbatched
    evaluation, the replay episode of ``traces.parquet``) is passed as a batch of one and the
    action of that one env returned; the optional ``reset()`` is called at the start of each
    episode (``episode_start`` all true)."""

    def __init__(self, policy: Any, label: str) -> None:
        self.policy, self.name = policy, label
        if callable(getattr(policy, "reference", None)):
            self.reference = policy.reference

    def predict(self, observation: Any, state: Any = None, episode_start: Any = None,
                deterministic: bool = True) -> tuple[Any, Any]:
        obs = np.asarray(observation)
        single = obs.ndim == 1
        start = episode_start
        if single:
            obs = obs[None]
            if start is not None:
                start = np.asarray(start, dtype=bool).reshape(-1)[:1]
        if start is not None and np.all(start) and callable(getattr(self.policy, "reset", None)):
            try:
                self.policy.reset()
            except Exception as exc:  # noqa: BLE001 (a user's code can raise anything)
                raise RuntimeError(f"reset() raised {type(exc).__name__}: {exc}") from exc
        out = self.policy.predict(obs, state=state, episode_start=start, deterministic=deterministic)
        if not single or not isinstance(out, tuple) or len(out) != 2:
            return out
        from controllers.evaluation import BadAction

        action = np.asarray(out[0]) if not isinstance(out[0], np.ndarray) else out[0]
        if action.shape != (1, 3):
            raise BadAction(f"its action for a batch of one observation, shape (1, {obs.shape[1]}), has shape "
                            f"{action.shape}: expected (1, 3) (docs/benchmark.md, 'Your own controller')")
        return action[0], out[1]


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
    if spec.kind == "external":
        cls = _import_external(spec.controller)
        try:
            obj = cls(task_spec)
        except Exception as exc:  # noqa: BLE001 (a user's constructor can raise anything)
            text = " ".join(str(exc).split())[:300]
            raise ValueError(f"policy {spec.label!r} on {env_id}: {spec.controller}(task_spec) raised "
                             f"{type(exc).__name__}" + (f": {text}" if text else "")) from exc
        return _BatchProtocol(obj, spec.label)
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
_EPISODE_CODE = ("auv_follow_env", "controllers", "agents/residual.py", "agents/train.py", "agents/benchmark.py",
                 "agents/obs_stats.py", "agents/batched_obs.py", "agents/batched_ppo.py")
#: packages whose version can change an episode's numbers (part of the cache key)
_EPISODE_PACKAGES = ("numpy", "numba", "gymnasium", "torch", "stable_baselines3", "sb3_contrib", "casadi", "scipy")


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


def _package_versions() -> dict[str, str | None]:
    """Installed versions of :data:`_EPISODE_PACKAGES` (None: not installed)."""
    from importlib import metadata

    out: dict[str, str | None] = {}
    for name in _EPISODE_PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = None
    return out


#: columns every cached episode table must have
_CACHE_COLUMNS = ("policy", "seed", "steps", "terminated", "return", "true_full_mean", "true_steady_mean")


def _read_cache_entry(path: Path, label: str, seeds: Sequence[int]) -> pd.DataFrame | None:
    """A cached episode table if it is complete and consistent (one row per seed, in order, of
    this policy; finite errors for every episode that was not terminated), else None (with a
    warning: the entry is recomputed and rewritten)."""
    try:
        d = pd.read_parquet(path)
    except Exception as exc:  # noqa: BLE001 (pyarrow raises many kinds for a broken file)
        warnings.warn(f"cache entry {path} is unreadable ({type(exc).__name__}): recomputing it", stacklevel=3)
        return None
    problem = None
    missing = [c for c in _CACHE_COLUMNS if c not in d.columns]
    if missing:
        problem = f"lacks columns {missing}"
    elif len(d) != len(seeds) or [int(x) for x in d["seed"]] != [int(x) for x in seeds]:
        problem = f"has seeds {d['seed'].tolist()[:5]}... ({len(d)} rows), expected {len(seeds)} seeds"
    elif set(d["policy"].astype(str)) != {label}:
        problem = f"is of policy {sorted(set(d['policy'].astype(str)))}, expected {label!r}"
    else:
        ok = d["terminated"].astype(bool) | np.isfinite(d["true_full_mean"].astype(float))
        if not ok.all() or not np.isfinite(d["steps"].astype(float)).all():
            problem = "has non-finite errors for episodes that were not terminated"
    if problem is not None:
        warnings.warn(f"cache entry {path} {problem}: recomputing it", stacklevel=3)
        return None
    return d


def _write_atomic_parquet(d: pd.DataFrame, path: Path) -> None:
    """Write ``d`` to ``path`` via a temporary file and a rename (never a half-written file)."""
    import os
    import tempfile

    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        d.to_parquet(tmp, index=False)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _external_fingerprint(target: str) -> str | None:
    """A hash of the source of a user's ``module:Class``: every loaded module of its top-level
    package (or the module alone), and the module that defines the class; None if a file cannot
    be read (then its episodes are not cached). Code it imports from other packages is not
    covered: clear the cache after editing that."""
    import hashlib
    import sys

    cls = _import_external(target)
    module = target.partition(":")[0]
    names = {module, getattr(cls, "__module__", module)}
    tops = {n.split(".")[0] for n in names}
    names |= {n for n in list(sys.modules) if n.split(".")[0] in tops}
    h = hashlib.sha256(target.encode())
    for n in sorted(names):
        mod = sys.modules.get(n)
        path = getattr(mod, "__file__", None) if mod is not None else None
        if not path:
            if n in (module, cls.__module__):
                return None
            continue  # a namespace package has no file
        try:
            h.update(n.encode() + b"\0" + Path(path).read_bytes())
        except OSError:
            return None
    return h.hexdigest()


def _entry_key(spec: PolicySpec, run: str | None, env_id: str, seeds: Sequence[int], code: str) -> str | None:
    """The cache key of one run's episodes (None: not cacheable)."""
    import hashlib

    h = hashlib.sha256()
    h.update(json.dumps({"env_id": env_id, "seeds": [int(x) for x in seeds], "kind": spec.kind,
                         "controller": spec.controller, "label": spec.label, "code": code,
                         "versions": _package_versions()}).encode())
    if spec.kind == "external":
        source = _external_fingerprint(spec.controller)
        if source is None:
            warnings.warn(f"policy {spec.label!r}: the source of {spec.controller} cannot be read, so its episodes "
                          "are not cached", stacklevel=3)
            return None
        h.update(source.encode())
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
    the run's model files, the git hashes of the episode code, and for a user's
    ``module:Class`` the source of its package: :func:`_external_fingerprint`) and reused on a
    later call; nothing is cached while that code differs from the git HEAD, and a cache that
    cannot be written is skipped with a warning. Episodes are deterministic, so a cached and a
    fresh evaluation agree.

    All runs share one native vector env (:func:`controllers.evaluation.evaluate_batched`)
    unless ``batched`` is False (one single-env episode at a time, same numbers).

    Returns:
        columns tier, env_id, policy, kind, run, seed, steps, terminated, return, the
        ``true_*`` / ``own_*`` metrics, ``cond_*`` (the drawn condition) and
        ``fail_error_m`` (the loss threshold used for terminated episodes).

    Raises:
        ValueError: repeated or out-of-range seeds, a reserved label (:data:`RESERVED_LABELS`),
            no policy that can run on the tier; a user's controller that fails
            (:class:`controllers.evaluation.PolicyError`, naming it, the env, the seed and the step).
    """
    from controllers.evaluation import evaluate, evaluate_batched

    name, env_id = resolve_tier(tier)
    seeds = tier_test_seeds(name) if seeds is None else check_seed_list(seeds, f"seeds of tier {name}")
    check_labels([p.label for p in policies])
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
            if k is None:
                continue
            f = Path(cache_dir) / f"{k}.parquet"
            if f.is_file():
                d = _read_cache_entry(f, labels[i], seeds)
                if d is not None:
                    cached[i] = d
    todo = [i for i in range(len(entries)) if i not in cached]
    fresh: dict[int, pd.DataFrame] = {}
    if todo and batched:
        out = evaluate_batched([objs[i] for i in todo], env_id, seeds, policy_names=[labels[i] for i in todo],
                               progress=progress)
        fresh = {i: out.iloc[j * len(seeds):(j + 1) * len(seeds)].reset_index(drop=True) for j, i in enumerate(todo)}
    elif todo:
        fresh = {i: evaluate(objs[i], env_id, seeds, policy_name=labels[i], progress=progress) for i in todo}
    if code:
        for i, d in fresh.items():
            if keys[i] is None:
                continue
            try:
                _write_atomic_parquet(d, Path(cache_dir) / f"{keys[i]}.parquet")
            except OSError as exc:  # the cache only saves time: go on without it
                warnings.warn(f"cache_dir={str(cache_dir)!r}: cannot store episodes there "
                              f"({exc.strerror or type(exc).__name__}); continuing without the cache", stacklevel=2)
                break
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


def paired_difference(episodes: pd.DataFrame, tier: str, policy: str, other: str, metric: str = "true_steady_mean",
                      *, n_resamples: int = DEFAULT_RESAMPLES, seed: int = DEFAULT_BOOTSTRAP_SEED,
                      confidence: float = 0.95) -> tuple[float, float, float]:
    """Mean over the test seeds of ``policy``'s score minus ``other``'s on the same seed (a
    method's runs averaged per seed first), with a percentile bootstrap CI over seeds [m];
    negative: ``policy`` is better. Seeds that only one of them has are left out.

    Raises:
        ValueError: a policy has no episodes on ``tier``.
    """
    ep = episodes[episodes["tier"] == tier]
    per_seed = []
    for name in (policy, other):
        d = ep[ep["policy"] == name]
        if d.empty:
            raise ValueError(f"policy={name!r} has no episodes on tier {tier!r}")
        per_seed.append(pd.Series(scores(d, metric).to_numpy(), index=d["seed"].to_numpy()).groupby(level=0).mean())
    a, b = per_seed[0].align(per_seed[1], join="inner")
    diff = (a - b).to_numpy()
    if diff.size == 0:
        return math.nan, math.nan, math.nan
    if diff.size == 1 or np.all(diff == diff[0]):
        return float(diff.mean()), float(diff[0]), float(diff[0])
    rng = np.random.default_rng(seed)
    boot = diff[rng.integers(0, diff.size, (n_resamples, diff.size))].mean(axis=1)
    q = 100 * (1 - confidence) / 2
    return float(diff.mean()), float(np.percentile(boot, q)), float(np.percentile(boot, 100 - q))


def leaderboard(episodes: pd.DataFrame, *, metrics: Sequence[str] = LEADERBOARD_METRICS,
                n_resamples: int = DEFAULT_RESAMPLES, seed: int = DEFAULT_BOOTSTRAP_SEED,
                confidence: float = 0.95, progress: bool = False,
                bases: Mapping[str, str] | None = None) -> pd.DataFrame:
    """Aggregate a per-episode table into the leaderboard, one row per (tier, policy).

    Args:
        episodes: rows with columns tier, policy, kind ("classical" / "learned"), run,
            terminated and ``metrics`` (e.g. from :func:`evaluate_tier`).
        metrics: error columns to aggregate (lower is better); the first ranks the classical
            baselines and is the one the probability of improvement is computed on.
        n_resamples, seed, confidence: bootstrap settings.
        bases: residual methods' base controllers (``{policy: base policy}``, see
            :func:`residual_bases`): adds ``base`` and the paired difference against it
            (``paired_diff_base``, ``_lo``, ``_hi``) where the base was scored on the tier.

    Returns:
        columns tier, policy, kind, runs, episodes, for each metric ``<m>_iqm``,
        ``<m>_iqm_lo``, ``<m>_iqm_hi``, ``<m>_mean``, ``<m>_mean_lo``, ``<m>_mean_hi``;
        ``termination_rate``, ``best_classical``, ``<m0>_iqm_change_pct`` (vs the best
        classical baseline), ``poi``, ``poi_lo``, ``poi_hi``; ``run_iqm_min`` /
        ``run_iqm_max`` (spread of the per-run IQMs of ``metrics[0]``); ``paired_diff``,
        ``paired_diff_lo``, ``paired_diff_hi`` (:func:`paired_difference` of ``metrics[0]`` against
        the best classical baseline, same seeds, in m); with reference rows
        (``kind="reference"``, the floors of :mod:`agents.floors`) also ``gap_closed``.
    """
    need = {"tier", "policy", "kind", "run", "terminated", *metrics}
    missing = sorted(need - set(episodes.columns))
    if missing:
        raise ValueError(f"episodes lacks columns {missing}: give a table from evaluate_tier")
    check_labels(sorted(set(episodes.loc[episodes["kind"] != "reference", "policy"].astype(str))))
    kinds = episodes.groupby(["tier", "policy"], sort=False)["kind"].nunique()
    if (kinds > 1).any():
        (tier_, pol_), = kinds[kinds > 1].index[:1]
        raise ValueError(f"episodes has policy {pol_!r} on tier {tier_!r} with several kinds "
                         f"{sorted(set(episodes.loc[episodes['policy'] == pol_, 'kind']))}: one label per policy")
    dup = episodes.duplicated(["tier", "policy", "run", "seed"]) if "seed" in episodes else None
    if dup is not None and dup.any():
        r = episodes[dup].iloc[0]
        raise ValueError(f"episodes has seed {r['seed']} of policy {r['policy']!r} (run {r['run']!r}) on tier "
                         f"{r['tier']!r} more than once: a seed list is a set of episodes")
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
    for c in (f"{m0}_iqm_change_pct", "poi", "poi_lo", "poi_hi", "paired_diff", "paired_diff_lo", "paired_diff_hi"):
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
            if board.at[i, "kind"] != "reference":
                board.loc[i, ["paired_diff", "paired_diff_lo", "paired_diff_hi"]] = paired_difference(
                    ep_t, tier, board.at[i, "policy"], best, m0, n_resamples=n_resamples, seed=seed,
                    confidence=confidence)
    board["base"] = ""
    for c in ("paired_diff_base", "paired_diff_base_lo", "paired_diff_base_hi"):
        board[c] = math.nan
    for i in board.index:
        base = (bases or {}).get(board.at[i, "policy"])
        ep_t = episodes[episodes["tier"] == board.at[i, "tier"]]
        if base and (ep_t["policy"] == base).any():
            board.at[i, "base"] = base
            board.loc[i, ["paired_diff_base", "paired_diff_base_lo", "paired_diff_base_hi"]] = paired_difference(
                ep_t, board.at[i, "tier"], board.at[i, "policy"], base, m0, n_resamples=n_resamples, seed=seed,
                confidence=confidence)
    if (board["kind"] == "reference").any():  # floors (agents/floors.py): their gap column
        from agents.floors import add_gap_closed

        board = add_gap_closed(board, m0)
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


def _goal_words(g: Mapping[str, Any]) -> str:
    return (f"goal (best learned >= 30 % below the best classical, CIs apart): {'met' if g['met'] else 'not met'}, "
            f"{g['best_learned']} {g['change_pct']:+.1f} % vs {g['best_classical']}, "
            f"CIs {'apart' if g['cis_separated'] else 'overlap'}")


def benchmark_summary(board: pd.DataFrame, files: Mapping[str, Path] | None = None, *, top: int = 5,
                      metric: str = "true_steady_mean") -> str:
    """A few lines for the terminal: per tier the ``top`` policies by the IQM of ``metric``
    (label, IQM with its 95 % CI, kind), the floors (reference rows) on one line, the goal
    check in words where the tier has a learned and a classical policy, and where the full
    files are."""
    def one_line(x: Any, width: int = 48) -> str:
        text = " ".join(str(x).split())
        return text if len(text) <= width else text[: width - 3] + "..."

    def ci(r: Any) -> str:
        return _fmt_ci(r[f"{metric}_iqm"], r[f"{metric}_iqm_lo"], r[f"{metric}_iqm_hi"])

    lines = []
    for tier, sub in board.groupby("tier", sort=False):
        sub = sub.sort_values(f"{metric}_iqm", kind="stable")
        refs, comp = sub[sub["kind"] == "reference"], sub[sub["kind"] != "reference"]
        best = sub["best_classical"].iloc[0] if "best_classical" in sub else None
        head = f"{one_line(tier)}: {len(comp)} policies by {metric.replace('true_', '')} error IQM [95 % CI] in m"
        lines.append(head + (f"; best classical {one_line(best)}" if isinstance(best, str) and best else ""))
        shown = comp.head(top)
        width = max((len(one_line(p)) for p in shown["policy"]), default=0)
        for rank, (_, r) in enumerate(shown.iterrows(), 1):
            lines.append(f"  {rank}. {one_line(r['policy']):<{width}}  {ci(r)}  ({one_line(r['kind'], 12)})")
        if len(comp) > top:
            lines.append(f"  ... {len(comp) - top} more in the full table")
        if len(refs):
            lines.append("  floors: " + ", ".join(f"{one_line(r['policy'])} {ci(r)}" for _, r in refs.iterrows()))
        g = goal_check(board, str(tier), metric)
        if g["met"] is not None:
            lines.append("  " + _goal_words(g))
    if files:
        md = files.get("leaderboard_md")
        rest = [Path(p).name for k, p in files.items() if k != "leaderboard_md"]
        lines.append(f"full table: {md}" + (f" (and {', '.join(rest)} beside it)" if rest else "")
                     if md is not None else f"written: {', '.join(str(p) for p in files.values())}")
    return "\n".join(lines)


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
    traces: pd.DataFrame | None = None  #: per-step replay episodes (see :func:`replay_traces`)


def _fmt_ci(est: float, lo: float, hi: float, digits: int = 4) -> str:
    if not np.isfinite(est):
        return "-"
    return f"{est:.{digits}f} [{lo:.{digits}f}, {hi:.{digits}f}]"


def _md(value: Any) -> str:
    """A value as Markdown table text: HTML special characters as entities (a Markdown viewer
    renders raw HTML), ``|`` escaped and line breaks removed."""
    import html

    return html.escape(" ".join(str(value).split()), quote=False).replace("|", "\\|")


def leaderboard_markdown(board: pd.DataFrame, prov: Mapping[str, Any] | None = None,
                         metrics: Sequence[str] = LEADERBOARD_METRICS) -> str:
    """The leaderboard as Markdown: one table per tier (errors in m, 95 % CIs in brackets)."""
    lines = ["# Leaderboard", "",
             "True-reference tracking error [m] (eq. (65)), steady state t >= 10 s and full run: IQM and mean "
             "over the tier's test episodes with 95 % stratified-bootstrap CIs (strata: training runs); "
             "P(better) = probability that an episode has a lower steady-state error than one of the tier's best "
             "classical baseline (rliable's probability of improvement, unpaired); paired diff = mean over the "
             "test seeds of (this policy's steady-state error - the best classical's on the same seed), runs "
             "averaged per seed, with a 95 % bootstrap CI over seeds (negative: better); for a residual agent the "
             "same against its own base controller; a terminated episode scores the loss threshold.", ""]
    m0 = metrics[0]
    for tier, sub in board.groupby("tier", sort=False):
        best = sub["best_classical"].iloc[0]
        lines += [f"## {_md(tier)}" + (f" (best classical: {_md(best)})" if best else ""), ""]
        head = ["policy", "kind", "runs x episodes"]
        for m in metrics:
            short = m.replace("true_", "").replace("_mean", "")
            head += [f"{short} IQM", f"{short} mean"]
        head += ["vs best classical (IQM)", "paired diff vs best classical [m]", "P(better) vs best classical",
                 "terminated"]
        has_base = "base" in sub and (sub["base"].fillna("") != "").any()
        head += ["paired diff vs its base [m]"] if has_base else []
        gap = "gap_closed" in sub and sub["gap_closed"].notna().any()  # floors present (agents/floors.py)
        head += ["gap closed"] if gap else []
        lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        for _, r in sub.sort_values(f"{m0}_iqm").iterrows():
            cells = [f"**{_md(r['policy'])}**" if r["policy"] == best else _md(r["policy"]), _md(r["kind"]),
                     f"{r['runs']} x {r['episodes'] // max(r['runs'], 1)}"]
            for m in metrics:
                cells += [_fmt_ci(r[f"{m}_iqm"], r[f"{m}_iqm_lo"], r[f"{m}_iqm_hi"]),
                          _fmt_ci(r[f"{m}_mean"], r[f"{m}_mean_lo"], r[f"{m}_mean_hi"])]
            chg = r.get(f"{m0}_iqm_change_pct")
            cells.append("-" if chg is None or not np.isfinite(chg) else f"{chg:+.1f} %")
            pdiff = r.get("paired_diff")
            cells.append("-" if pdiff is None or not np.isfinite(pdiff) or r["policy"] == best else
                         _fmt_ci(pdiff, r["paired_diff_lo"], r["paired_diff_hi"]))
            cells.append(_fmt_ci(r["poi"], r["poi_lo"], r["poi_hi"], 2))
            cells.append(f"{100 * r['termination_rate']:.0f} %")
            if has_base:
                ci = _fmt_ci(r["paired_diff_base"], r["paired_diff_base_lo"], r["paired_diff_base_hi"])
                cells.append(f"{ci} (base {_md(r['base'])})" if r.get("base") else "-")
            if gap:
                cells.append("-" if not np.isfinite(r["gap_closed"]) else f"{r['gap_closed']:.2f}")
            lines.append("| " + " | ".join(cells) + " |")
        lines.append("")
    if prov is not None:
        cfg = prov.get("config", {})
        import re

        text = json.dumps(prov, indent=1, default=str)
        fence = "`" * max(3, 1 + max((len(m) for m in re.findall("`+", text)), default=0))  # longer than any run
        lines += ["## Provenance", "", fence + "json", text, fence, ""]
        if "command" in cfg:
            cmd = str(cfg["command"])
            tick = "`" * (1 + max((len(m) for m in re.findall("`+", cmd)), default=0))
            pad = " " if len(tick) > 1 else ""
            lines[-5:-5] = [f"Reproduce: {tick}{pad}{cmd}{pad}{tick}", ""]
    return "\n".join(lines)


def plot_leaderboard(board: pd.DataFrame, path: str | Path, metric: str = "true_steady_mean",
                     prov: Mapping[str, Any] | None = None) -> None:
    """One panel per tier, stacked (the policy names need the width): the IQM of ``metric`` per
    policy with its 95 % CI (log scale)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker  # noqa: F401  (matplotlib.ticker below)

    tiers = list(dict.fromkeys(board["tier"]))
    sizes = [int((board["tier"] == t).sum()) for t in tiers]
    fig, axes = plt.subplots(len(tiers), 1, figsize=(10.0, 0.24 * sum(sizes) + 1.1 * len(tiers) + 0.6),
                             squeeze=False, gridspec_kw={"height_ratios": sizes})
    for ax, tier in zip(axes[:, 0], tiers, strict=True):
        sub = board[board["tier"] == tier].sort_values(f"{metric}_iqm", ascending=False)
        y = np.arange(len(sub))
        est = sub[f"{metric}_iqm"].to_numpy()
        err = np.vstack([est - sub[f"{metric}_iqm_lo"].to_numpy(), sub[f"{metric}_iqm_hi"].to_numpy() - est])
        colors = ["C1" if k == "classical" else "0.6" if k == "reference" else "C0" for k in sub["kind"]]
        ax.barh(y, est, xerr=err, color=colors, capsize=3)
        ax.set_yticks(y, sub["policy"], fontsize=8)
        ax.set_xscale("log")
        # labelled ticks at 1, 2, 5 x 10^k; no minor labels (they overlap on short ranges)
        lo = float(np.nanmin(sub[f"{metric}_iqm_lo"].to_numpy()))
        hi = float(np.nanmax(sub[f"{metric}_iqm_hi"].to_numpy()))
        decades = math.log10(hi / lo) if lo > 0 and hi > lo else 0.0
        subs = (1.0,) if decades > 1.5 else (1.0, 2.0, 5.0)  # 1-2-5 labels run together over wide ranges
        ax.xaxis.set_major_locator(matplotlib.ticker.LogLocator(base=10.0, subs=subs))
        ax.xaxis.set_major_formatter(matplotlib.ticker.FuncFormatter(lambda v, _: f"{v:g}"))
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.tick_params(axis="x", labelsize=8)
        ax.set_title(tier)
        ax.set_xlabel(f"IQM {metric.replace('true_', '')} [m]")
    grey = ", grey: floors (references)" if (board["kind"] == "reference").any() else ""
    fig.suptitle(f"true-reference error, IQM with 95 % CI (orange: classical, blue: learned{grey})", fontsize=9)
    fig.tight_layout(rect=(0.0, 0.0, 1.0, 1.0 - 0.4 / fig.get_figheight()))  # room for the title
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


#: the files :func:`benchmark` writes (key -> file name); each records the run's provenance
OUTPUT_FILES: dict[str, str] = {"episodes": "episodes.parquet", "leaderboard_csv": "leaderboard.csv",
                                "leaderboard_md": "leaderboard.md", "leaderboard_png": "leaderboard.png",
                                "traces": "traces.parquet", "provenance": "benchmark.json"}


def replay_traces(specs: Sequence[PolicySpec], seed_map: Mapping[str, Sequence[int]], *,
                  progress: bool = False) -> pd.DataFrame:
    """Per-step traces of one episode per (tier, policy): the tier's first seed, the policy's
    first run (what ``auv-follow report`` plots: it never loads a model itself)."""
    from agents.report import rollout_episode

    frames = []
    for tier, seeds in tqdm(list(seed_map.items()), desc="traces", disable=not progress, leave=False):
        name, env_id = resolve_tier(tier)
        probe = gym.make(env_id)
        task_spec, width = probe.unwrapped.task_spec, int(probe.observation_space.shape[0])
        probe.close()
        for spec in specs:
            if spec.tiers and name not in spec.tiers:
                continue
            try:
                pol = build_policy(spec, spec.runs[0] if spec.runs else None, env_id, task_spec, width)
            except IncompatiblePolicy:
                continue
            try:
                df = rollout_episode(pol, env_id, int(seeds[0]))
            except Exception as exc:  # noqa: BLE001 (a user's controller can raise anything)
                text = " ".join(str(exc).split())[:300]
                raise ValueError(f"policy {spec.label!r} on {name} ({env_id}), seed {int(seeds[0])}: recording its "
                                 f"replay episode (traces.parquet) failed: {type(exc).__name__}"
                                 + (f": {text}" if text else "")) from exc
            df.insert(0, "seed", int(seeds[0]))
            df.insert(0, "policy", spec.label)
            df.insert(0, "tier", name)
            frames.append(df)
    if not frames:
        return pd.DataFrame(columns=["tier", "policy", "seed"])
    out = pd.concat(frames, ignore_index=True)
    floats = [c for c in out.columns if out[c].dtype == np.float64]
    return out.astype({c: np.float32 for c in floats})  # plotted only: half the file size


class OutputWriteError(OSError):
    """A set of output files could not be written (full disk, no permission); the previous
    files in the folder are kept (the message names the folder and the reason)."""


@contextlib.contextmanager
def _sigint_deferred():
    """Hold back SIGINT (Ctrl-C) inside the block: it is delivered when the block ends (main
    thread on POSIX; elsewhere the block runs as it is)."""
    import signal
    import threading

    block = hasattr(signal, "pthread_sigmask") and threading.current_thread() is threading.main_thread()
    if block:
        old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        if block:
            signal.pthread_sigmask(signal.SIG_SETMASK, old)


def replace_set(stage: Path, out: Path, names: Sequence[str]) -> dict[str, Path]:
    """Move the files ``names`` from ``stage`` into ``out`` as one set: the files of the same
    names already in ``out`` are moved aside first and put back if any move fails or is
    interrupted, so ``out`` holds either the previous set or the complete new one, never a mix.
    Ctrl-C is held back while the files move. ``stage`` must be on the file system of ``out``.

    Returns:
        ``{name: out / name}``.

    Raises:
        OutputWriteError: a move failed (the previous set is back in place; if even that
            failed, the message says where the previous files are).
    """
    import os
    import shutil
    import tempfile

    aside = Path(tempfile.mkdtemp(prefix=".benchmark-previous-", dir=out))
    moved: list[str] = []
    placed: list[str] = []
    with _sigint_deferred():
        try:
            for name in names:
                if os.path.lexists(out / name):
                    os.replace(out / name, aside / name)
                    moved.append(name)
            for name in names:
                os.replace(stage / name, out / name)
                placed.append(name)
        except BaseException as exc:
            lost = []
            for name in placed:
                try:
                    os.replace(out / name, stage / name)
                except OSError:
                    lost.append(name)
            for name in moved:
                try:
                    os.replace(aside / name, out / name)
                except OSError:
                    lost.append(name)
            if lost:
                raise OutputWriteError(f"{out}: writing the new files failed ({_first_line(exc)}) and putting the "
                                       f"previous ones back failed too: they are in {aside}") from exc
            shutil.rmtree(aside, ignore_errors=True)
            if isinstance(exc, OSError):
                raise OutputWriteError(f"cannot write into {out} ({exc.strerror or _first_line(exc)}): its previous "
                                       "files are kept") from exc
            raise
    shutil.rmtree(aside, ignore_errors=True)
    return {name: out / name for name in names}


def write_outputs(out: Path, episodes: pd.DataFrame, board: pd.DataFrame, prov: Mapping[str, Any],
                  traces: pd.DataFrame) -> dict[str, Path]:
    """Write the benchmark files into ``out``: all of them into a temporary folder inside
    ``out`` first, then moved into place as one set (:func:`replace_set`: an interruption or a
    failure at any point leaves the previous files, all of them; :func:`load_result` refuses a
    folder whose files disagree).

    Raises:
        OutputWriteError: a file could not be written (full disk, no permission): nothing in
            ``out`` was changed.
    """
    import shutil
    import tempfile

    created = not out.exists()
    try:
        out.mkdir(parents=True, exist_ok=True)
        stage = Path(tempfile.mkdtemp(prefix=".benchmark-partial-", dir=out))
    except OSError as exc:
        raise OutputWriteError(f"cannot write into {out} ({exc.strerror or _first_line(exc)})") from exc
    ok = False
    try:
        staged = {k: stage / name for k, name in OUTPUT_FILES.items()}
        try:
            _write_parquet(episodes, staged["episodes"], prov)
            _write_csv(board, staged["leaderboard_csv"], prov)
            staged["leaderboard_md"].write_text(leaderboard_markdown(board, prov) + "\n")
            plot_leaderboard(board, staged["leaderboard_png"], prov=prov)
            _write_parquet(traces, staged["traces"], prov)
            staged["provenance"].write_text(json.dumps(prov, indent=1, default=str) + "\n")
        except OSError as exc:
            raise OutputWriteError(f"cannot write into {out} ({exc.strerror or _first_line(exc)}): its previous "
                                   "files are kept") from exc
        placed = replace_set(stage, out, list(OUTPUT_FILES.values()))
        ok = True
        return {k: placed[name] for k, name in OUTPUT_FILES.items()}
    finally:
        shutil.rmtree(stage, ignore_errors=True)
        if created and not ok:
            with contextlib.suppress(OSError):
                out.rmdir()  # the folder this call made, if it is still empty


def _prov_key(prov: Any) -> str:
    return json.dumps(prov, sort_keys=True, default=str)


def load_result(out_dir: str | Path) -> BenchmarkResult:
    """Read a benchmark written by :func:`benchmark` back (episodes, leaderboard, provenance,
    and the replay traces if present).

    Raises:
        FileNotFoundError: a file of the benchmark is missing (names it).
        ValueError: a file is corrupt, or the files come from different runs (names them).
    """
    import pyarrow.parquet as pq

    out = Path(out_dir)
    for name in ("episodes.parquet", "leaderboard.csv", "benchmark.json"):
        if not (out / name).is_file():
            raise FileNotFoundError(f"{out / name} does not exist: run `auv-follow benchmark --out {out}`")
    try:
        prov = json.loads((out / "benchmark.json").read_text())
        if not isinstance(prov, dict) or not isinstance(prov.get("config"), dict):
            raise ValueError("expected a mapping with a 'config' section")
    except (UnicodeDecodeError, ValueError) as exc:
        raise ValueError(f"{out / 'benchmark.json'} is not a benchmark provenance file: {_first_line(exc)}") from None
    stamps: dict[str, Any] = {}

    def parquet(name: str) -> pd.DataFrame:
        try:
            table = pq.read_table(out / name)
        except Exception as exc:  # noqa: BLE001 (pyarrow raises many kinds for a broken file)
            raise ValueError(f"{out / name} is not a readable parquet file: {_first_line(exc)}") from None
        meta = (table.schema.metadata or {}).get(b"auv_follow_provenance")
        stamps[name] = json.loads(meta) if meta else None
        return table.to_pandas()

    episodes = parquet("episodes.parquet")
    try:
        with open(out / "leaderboard.csv") as f:
            first = f.readline()
            stamps["leaderboard.csv"] = (json.loads(first[len("# provenance: "):])
                                         if first.startswith("# provenance: ") else None)
        board = pd.read_csv(out / "leaderboard.csv", comment="#")
    except (UnicodeDecodeError, ValueError, pd.errors.ParserError) as exc:
        raise ValueError(f"{out / 'leaderboard.csv'} is not a leaderboard CSV: {_first_line(exc)}") from None
    traces = parquet("traces.parquet") if (out / "traces.parquet").is_file() else None
    want = _prov_key(prov)
    mixed = sorted(name for name, st in stamps.items() if st is not None and _prov_key(st) != want)
    if mixed:
        raise ValueError(f"{', '.join(str(out / m) for m in mixed)} and {out / 'benchmark.json'} are from different "
                         f"benchmark runs (their provenance differs): run the benchmark again")
    need = {"tier", "policy", "kind", "true_steady_mean_iqm", "true_steady_mean_iqm_lo", "true_steady_mean_iqm_hi"}
    if not need <= set(board.columns):
        raise ValueError(f"{out / 'leaderboard.csv'} lacks columns {sorted(need - set(board.columns))}")
    lacks = sorted({"tier", "policy", "seed"} - set(episodes.columns))
    if lacks:
        raise ValueError(f"{out / 'episodes.parquet'} lacks columns {lacks}")
    res = BenchmarkResult(episodes, board, prov, {})
    res.traces = traces
    return res


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return (text[0] if text else type(exc).__name__)[:200]


def residual_bases(specs: Iterable[PolicySpec]) -> dict[str, str]:
    """``{label: base controller}`` of the learned methods whose runs are residual agents on one
    base controller (read from each run's ``config.yaml``); methods mixing bases are left out."""
    import yaml

    out: dict[str, str] = {}
    for s in specs:
        if s.kind != "learned" or not s.runs:
            continue
        found = set()
        for r in s.runs:
            try:
                cfg = yaml.safe_load((Path(r) / "config.yaml").read_text()) or {}
            except (OSError, yaml.YAMLError):
                found.add(None)
                continue
            run = cfg.get("run", {}) if isinstance(cfg, dict) else {}
            found.add(run.get("controller") if run.get("mode") == "residual" else None)
        if len(found) == 1 and None not in found:
            out[s.label] = str(found.pop())
    return out


def benchmark(policies: Iterable[str | Path | PolicySpec] | None = None, tiers: Iterable[str] = ("S4",), *,
              seeds: Mapping[str, Sequence[int]] | Sequence[int] | None = None, out_dir: str | Path | None = None,
              n_resamples: int = DEFAULT_RESAMPLES, bootstrap_seed: int = DEFAULT_BOOTSTRAP_SEED,
              batched: bool = True, progress: bool = True, command: str | None = None,
              cache_dir: str | Path | None = None, floors: bool = False) -> BenchmarkResult:
    """Score ``policies`` on ``tiers`` and build the leaderboard.

    Args:
        policies: controller names, run directories, directories of runs, ``label=run,run``
            or ``"classical"`` (every registered scripted controller; the default).
        tiers: tier names or ids (``"S4"``, ``"Hard"``, ``"AUVFollow-Hard-v1"``).
        seeds: override the published test seeds (one list for all tiers, or per tier); for
            quick looks only - the leaderboard protocol is the published seeds.
        out_dir: if given, write ``episodes.parquet``, ``leaderboard.csv``, ``leaderboard.md``,
            ``leaderboard.png``, ``traces.parquet`` (one replay episode per tier and policy, for
            the report) and ``benchmark.json`` there (each records the provenance; written to
            a temporary folder first, see :func:`write_outputs`).
        n_resamples, bootstrap_seed: bootstrap settings (fixed seed: reruns agree).
        batched: evaluate through the native vector env.
        command: the command line to record (the CLI fills it in).
        cache_dir: reuse the episodes of runs evaluated before (see :func:`evaluate_tier`).
        floors: add each v1 tier's control and information floors as reference rows
            (``kind="reference"``, :func:`agents.floors.floor_episodes`) and the leaderboard's
            ``gap_closed`` column.

    Raises:
        ValueError: unknown tier or policy, a reserved label, repeated seeds or seeds outside
            [0, 2**63 - 1], ``n_resamples`` outside [1, :data:`MAX_RESAMPLES`]; all before any
            episode runs.
        OutputWriteError: the files could not be written into ``out_dir`` (its previous files
            are kept).
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
    check_labels(labels)
    if isinstance(n_resamples, bool) or not isinstance(n_resamples, (int, np.integer)) or \
            not 1 <= n_resamples <= MAX_RESAMPLES:
        raise ValueError(f"n_resamples={n_resamples!r} is invalid: must be an integer in [1, {MAX_RESAMPLES}]")
    if isinstance(bootstrap_seed, bool) or not isinstance(bootstrap_seed, (int, np.integer)) or bootstrap_seed < 0:
        raise ValueError(f"bootstrap_seed={bootstrap_seed!r} is invalid: must be an integer >= 0")
    tiers = [resolve_tier(t)[0] for t in ([tiers] if isinstance(tiers, str) else tiers)]
    if not tiers:
        raise ValueError(f"tiers is empty: give at least one of {available_tiers()}")
    seed_map: dict[str, list[int]] = {}
    for t in tiers:
        if seeds is None:
            seed_map[t] = tier_test_seeds(t)
        elif isinstance(seeds, Mapping):
            seed_map[t] = check_seed_list(seeds[t], f"seeds[{t!r}]") if t in seeds else tier_test_seeds(t)
        else:
            seed_map[t] = check_seed_list(seeds)
    frames = [evaluate_tier(specs, t, seed_map[t], batched=batched, progress=progress, cache_dir=cache_dir)
              for t in tqdm(tiers, desc="tiers", disable=not progress)]
    if floors:  # reference rows, not competitors (agents/floors.py)
        from agents.floors import floor_episodes

        frames += [floor_episodes(t, seed_map[t], progress=progress) for t in tiers if t in V1_TIERS]
    episodes = pd.concat(frames, ignore_index=True)
    board = leaderboard(episodes, n_resamples=n_resamples, seed=bootstrap_seed, progress=progress,
                        bases=residual_bases(specs))
    config = {"command": command, "tiers": {t: resolve_tier(t)[1] for t in tiers}, "seeds": seed_map,
              "policies": [dataclasses.asdict(s) for s in specs], "metrics": list(LEADERBOARD_METRICS),
              "n_resamples": n_resamples, "bootstrap_seed": bootstrap_seed, "confidence": 0.95,
              "batched": batched, "published_seeds": seeds is None, "floors": floors,
              "cache_dir": None if cache_dir is None else str(cache_dir)}
    prov = provenance(config)
    result = BenchmarkResult(episodes, board, prov)
    if out_dir is not None:
        traces = replay_traces(specs, seed_map, progress=progress)
        result.files = write_outputs(Path(out_dir), episodes, board, prov, traces)
    return result
