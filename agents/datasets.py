"""Minari datasets of a policy's episodes on a tier (``auv-follow dataset``; docs/data.md).

A dataset holds, per episode, Minari's observations, actions, rewards, terminations and
truncations, and infos with the true tracking error and the link flags at every step (the reset
included); each episode's metadata carries its seed (Minari's own ``seed`` field) and the drawn
condition (``condition``: every v1 field). The dataset's ``ref_min_score`` and ``ref_max_score``
are the mean returns of PID and of the tier's best classical controller on the tier's published
test seeds, where a trained agent is scored, so that ``minari.get_normalized_score`` reads 0 at
PID and 1 at the best classical. ``recover_environment()`` makes the env with its keywords.

Minari is an optional dependency (the ``data`` extra, installed by the dev set-up); it is imported
only here.
"""

from __future__ import annotations

import os
import re
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from tqdm.auto import tqdm

from auv_follow_env.layout import OBS_INDEX_V1

__all__ = ["DatasetUnavailable", "write_dataset", "reference_scores", "best_classical", "check_dataset_id",
           "check_dataset_seeds", "DATASET_ID", "DEFAULT_TRAIN_SEEDS"]

#: Minari's id convention ``namespace/name-vN`` (minari.dataset.minari_dataset.DATASET_ID_RE with the
#: namespace and the version required; a namespace has two characters or more and may be nested)
DATASET_ID = re.compile(r"^[-_\w][-_\w/]*[-_\w]+/[-_\w]+?-v\d+$")
#: the seeds a dataset holds unless told otherwise (training seeds: below every test seed)
DEFAULT_TRAIN_SEEDS = tuple(range(100))
#: when the committed leaderboard does not name a tier's best classical controller
_FALLBACK_BEST = {"v0": "PROPOSED", "v1": "PROPOSED_KF_DOB"}
_LEADERBOARD = Path(__file__).resolve().parents[1] / "results" / "benchmark" / "leaderboard.csv"
_LINK_INFOS = ("packet_age", "since_arrival", "new_packet", "has_packet")


class DatasetUnavailable(RuntimeError):
    """Minari is not installed (``pip install -e '.[data]'``)."""


def _minari() -> Any:
    try:
        import minari
    except ImportError as exc:
        raise DatasetUnavailable("auv-follow dataset needs Minari: pip install -e '.[data]' (Python >= 3.11; "
                                 "the dev set-up, bash scripts/setup.sh, installs it)") from exc
    return minari


def check_dataset_id(dataset_id: str) -> str:
    """``dataset_id`` if it follows Minari's ``namespace/name-vN`` and is not in Minari's store yet,
    else a ValueError saying which."""
    if not isinstance(dataset_id, str) or not DATASET_ID.match(dataset_id):
        raise ValueError(f"dataset id {dataset_id!r} is invalid: a Minari dataset id is NAMESPACE/NAME-vN, e.g. "
                         f"auv-follow/hard-proposed_kf_dob-v0")
    if dataset_id in _minari().list_local_datasets():
        root = os.environ.get("MINARI_DATASETS_PATH", "~/.minari/datasets")
        raise ValueError(f"dataset id {dataset_id!r} exists in {root}: choose another version (-vN) or delete it with "
                         f"minari.delete_dataset({dataset_id!r})")
    return dataset_id


def check_dataset_seeds(tier: str, seeds: Sequence[int], allow_test_seeds: bool) -> list[int]:
    """``seeds`` as a list; without ``allow_test_seeds`` a ValueError if any is a published test seed
    of ``tier`` or at or above :data:`auv_follow_env.tiers.TRAIN_SEED_LIMIT`."""
    from agents.benchmark.protocol import tier_test_seeds
    from auv_follow_env.tiers import TRAIN_SEED_LIMIT

    seeds = [int(s) for s in seeds]
    if not allow_test_seeds:
        test = set(tier_test_seeds(tier))
        bad = [s for s in seeds if s in test or s >= TRAIN_SEED_LIMIT]
        if bad:
            shown = f"{bad[:5]}{', ...' if len(bad) > 5 else ''}"
            raise ValueError(f"{len(bad)} of the seeds are test seeds of {tier} ({shown}): "
                             f"a dataset is training data, and training on test seeds leaks them; use seeds below "
                             f"{TRAIN_SEED_LIMIT:,} that are not the tier's test seeds, or --allow-test-seeds for an "
                             f"analysis dataset that no agent trains on")
    return seeds


def best_classical(tier: str) -> str:
    """The tier's best classical controller on the committed leaderboard (results/benchmark), or the
    suite's default filtered controller where the board has no such row."""
    from agents.benchmark.protocol import resolve_tier

    name, env_id = resolve_tier(tier)
    if _LEADERBOARD.is_file():
        import pandas as pd

        board = pd.read_csv(_LEADERBOARD, usecols=["tier", "best_classical"])
        rows = board.loc[board["tier"] == name, "best_classical"].dropna()
        if len(rows):
            return str(rows.iloc[0])
    return _FALLBACK_BEST["v1" if env_id.endswith("-v1") else "v0"]


def reference_scores(tier: str, *, best: str | None = None, episodes: int = 100,
                     progress: bool = True) -> dict[str, Any]:
    """Mean returns of PID (``ref_min_score``) and of the best classical controller
    (``ref_max_score``) over the first ``episodes`` published test seeds of ``tier``, on the
    native vector env (:func:`controllers.evaluation.evaluate_batched`)."""
    from agents.benchmark.protocol import resolve_tier, tier_test_seeds
    from controllers import make_controller
    from controllers.evaluation import evaluate_batched

    name, env_id = resolve_tier(tier)
    best = best or best_classical(name)
    seeds = tier_test_seeds(name)[:episodes]
    spec = gym.make(env_id).unwrapped.task_spec
    names = ["PID"] if best == "PID" else ["PID", best]
    rows = evaluate_batched([make_controller(n, spec) for n in names], env_id, seeds, policy_names=names,
                            progress=progress)
    means = rows.groupby("policy")["return"].mean()
    return {"ref_min_score": float(means["PID"]), "ref_max_score": float(means[best]), "best": best,
            "episodes": len(seeds)}


def _link_infos(obs: np.ndarray, info: dict, v1: bool) -> dict[str, float]:
    """One step's infos, of the same structure at every step: the true tracking error, the time and,
    on v1, the link flags (as in the observation)."""
    out = {"tracking_error": float(info["tracking_error"]), "time": float(info["time"])}
    if v1:
        for key in _LINK_INFOS:
            out[key] = float(obs[OBS_INDEX_V1[key]])
    return out


def _condition_json(cond: dict) -> dict:
    return {k: (list(v) if isinstance(v, tuple) else v.item() if isinstance(v, np.generic) else v)
            for k, v in cond.items()}


def write_dataset(dataset_id: str, tier: str, policy: Any, label: str, seeds: Sequence[int], *,
                  refs: dict[str, Any], description: str | None = None, progress: bool = True,
                  author: str | None = None) -> Any:
    """Record ``policy``'s episodes on ``tier`` for ``seeds`` as the Minari dataset ``dataset_id``
    in Minari's store (``MINARI_DATASETS_PATH``, default ``~/.minari/datasets``); returns the
    :class:`minari.MinariDataset`.

    Raises:
        ValueError: an invalid id, or one that exists in the store already.
        DatasetUnavailable: Minari is not installed.
    """
    from agents.benchmark.protocol import resolve_tier

    minari = _minari()
    from minari.data_collector import EpisodeBuffer

    check_dataset_id(dataset_id)
    name, env_id = resolve_tier(tier)
    env = gym.make(env_id)
    v1 = env_id.endswith("-v1")
    predict = _predictor(policy)
    buffers, metadata = [], []
    bar = tqdm(total=len(seeds), desc=f"{label} on {name}", unit="episode", disable=not progress, file=sys.stderr)
    try:
        for i, seed in enumerate(seeds):
            obs, info = env.reset(seed=int(seed))
            if hasattr(policy, "reset"):
                policy.reset()
            observations, actions, rewards, terms, truncs = [obs], [], [], [], []
            infos = [_link_infos(obs, info, v1)]
            metadata.append({"condition": _condition_json(info["condition"]) if v1 else {"scenario": name},
                             "env_id": env_id, "tier": name, "policy": label})
            done = False
            while not done:
                action = np.asarray(predict(obs), dtype=np.float32)
                obs, reward, term, trunc, info = env.step(action)
                observations.append(obs)
                actions.append(action)
                rewards.append(float(reward))
                terms.append(bool(term))
                truncs.append(bool(trunc))
                infos.append(_link_infos(obs, info, v1))
                done = term or trunc
            buffers.append(EpisodeBuffer(
                id=i, seed=int(seed), observations=np.asarray(observations, dtype=np.float32),
                actions=np.asarray(actions, dtype=np.float32), rewards=rewards, terminations=terms,
                truncations=truncs,
                infos={k: [row[k] for row in infos] for k in infos[0]}))  # (lists: minari 0.5.4 misreads 1-D arrays)
            bar.update()
    finally:
        bar.close()
    text = description or (f"{label} following the target on {env_id} (tier {name}), {len(seeds)} episodes "
                           f"(seeds {_seed_range(seeds)}); infos: the true tracking error and the time"
                           + (" and the link flags" if v1 else "")
                           + f"; ref scores: mean returns of PID and {refs['best']} on the tier's first "
                             f"{refs['episodes']} published test seeds.")
    dataset = minari.create_dataset_from_buffers(
        dataset_id, buffers, env=env, algorithm_name=label, author=author or "auv-follow",
        code_permalink="auv-follow (this repository): agents/datasets.py", ref_min_score=refs["ref_min_score"],
        ref_max_score=refs["ref_max_score"], description=text,
        eval_env=env_id, author_email="", data_format="arrow")  # (arrow: pyarrow is ours already; hdf5 needs h5py)
    dataset.storage.update_episode_metadata(metadata, list(range(len(metadata))))
    return dataset


def _seed_range(seeds: Sequence[int]) -> str:
    s = list(seeds)
    return f"{s[0]}-{s[-1]}" if s == list(range(s[0], s[0] + len(s))) else ", ".join(map(str, s[:10])) + (
        ", ..." if len(s) > 10 else "")


def _predictor(policy: Any) -> Any:
    """obs -> action for a policy with the SB3 ``predict`` protocol (deterministic where it has the flag)."""
    if _takes_deterministic(policy):
        return lambda obs: policy.predict(obs, deterministic=True)[0]
    return lambda obs: policy.predict(obs)[0]


def _takes_deterministic(policy: Any) -> bool:
    import inspect

    try:
        return "deterministic" in inspect.signature(policy.predict).parameters
    except (TypeError, ValueError):
        return False
