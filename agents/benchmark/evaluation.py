"""Evaluation of policies on a tier's seeds (batched) with the per-episode cache, keyed by the
code and package versions that decide an episode's numbers."""

from __future__ import annotations

import json
import warnings
from collections.abc import Sequence
from pathlib import Path

import gymnasium as gym
import numpy as np
import pandas as pd

import auv_follow_env  # noqa: F401  (registers the ids)
from agents.benchmark.policies import IncompatiblePolicy, PolicySpec, _import_external, build_policy
from agents.benchmark.protocol import (
    _condition_columns,
    _max_distance,
    check_labels,
    check_seed_list,
    resolve_tier,
    tier_test_seeds,
)

#: the code that decides an episode's numbers (the cache key includes its git hashes)
_EPISODE_CODE = ("auv_follow_env", "controllers", "agents/training", "agents/benchmark/protocol.py",
                 "agents/benchmark/policies.py", "agents/benchmark/evaluation.py")


#: packages whose version can change an episode's numbers (part of the cache key)
_EPISODE_PACKAGES = ("numpy", "numba", "gymnasium", "torch", "stable_baselines3", "sb3_contrib", "casadi", "scipy")


def _code_fingerprint() -> str | None:
    """Git hashes of :data:`_EPISODE_CODE` at HEAD, or None if any of it differs from HEAD
    (then nothing is cached)."""
    import subprocess

    root = Path(__file__).resolve().parents[2]
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
