"""The protocol's fixed parts: tiers and their env ids, published test seeds, seed lists, the
scored metrics, reserved labels and the per-episode condition columns."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
import pandas as pd

import auv_follow_env  # noqa: F401  (registers the ids)

V0_TIERS: tuple[str, ...] = ("S1", "S2", "S3", "S4")


V1_TIERS: tuple[str, ...] = ("Easy", "Medium", "Hard", "Extreme")


#: the Leader tiers (targets with hidden manoeuvre modes; ids AUVFollow-Leader-<level>-v1). Their
#: floors are not today's linear ones (the Bayes floor under the mode generator is not built yet)
LEADER_TIERS: tuple[str, ...] = ("Leader-Easy", "Leader-Medium", "Leader-Hard")


#: test seeds of the paper scenarios (our choice: 100 seeds; training uses seeds < 1000 and the
#: EvalCallback seed 500, so these are held out)
V0_TEST_SEEDS: tuple[int, ...] = tuple(range(1000, 1100))


#: per-episode columns aggregated by the leaderboard (true reference, eq. (65))
LEADERBOARD_METRICS: tuple[str, ...] = ("true_steady_mean", "true_full_mean")


#: every error metric (replaced by the loss threshold for terminated episodes)
ERROR_METRICS: tuple[str, ...] = tuple(f"true_{w}_{s}" for w in ("full", "steady") for s in ("mean", "rmse", "max"))


#: policy token standing for every registered scripted controller
CLASSICAL = "classical"


#: leaderboard labels of the floors' reference rows (agents/benchmark/floors.py): no policy may take them
RESERVED_LABELS: tuple[str, ...] = ("control floor", "oracle-parameter floor", "information floor")


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


def _v1_registered(tier: str) -> bool:
    return f"AUVFollow-{tier}-v1" in gym.registry


def available_tiers() -> list[str]:
    """The tier names this installation can score (v1 tiers appear once registered)."""
    return list(V0_TIERS) + [t for t in V1_TIERS + LEADER_TIERS if _v1_registered(t)]


def resolve_tier(tier: str) -> tuple[str, str]:
    """``(name, env_id)`` for a tier name (``"S4"``, ``"Hard"``) or its env id.

    Raises:
        ValueError: unknown or unregistered tier (lists the available ones).
    """
    if not isinstance(tier, str):
        raise ValueError(f"tier={tier!r} is invalid: must be a tier name, one of {available_tiers()}")
    name = tier
    if tier.startswith("AUVFollow-") and tier.count("-") in (2, 3):
        name = tier[len("AUVFollow-"):].rsplit("-", 1)[0]
    if name in V0_TIERS:
        return name, f"AUVFollow-{name}-v0"
    if name in V1_TIERS + LEADER_TIERS and _v1_registered(name):
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
        tiers = getattr(mod, "ALL_TIERS", None) or getattr(mod, "TIERS", None)
        if isinstance(tiers, Mapping):
            for key in (name, env_id):
                t = tiers.get(key)
                if t is not None and getattr(t, "test_seeds", None) is not None:
                    return [int(s) for s in t.test_seeds]
    return None


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
