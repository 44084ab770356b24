""":func:`benchmark`: policies x tiers on the published test seeds, written as one set of files."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from tqdm.auto import tqdm

import auv_follow_env  # noqa: F401  (registers the ids)
from agents.benchmark.evaluation import evaluate_tier
from agents.benchmark.leaderboard import leaderboard
from agents.benchmark.outputs import BenchmarkResult, provenance, write_outputs
from agents.benchmark.policies import (
    PolicySpec,
    _controllers,
    filtered_laws,
    parse_policy,
    residual_bases,
    residual_observations,
)
from agents.benchmark.protocol import (
    CLASSICAL,
    LEADER_TIERS,
    LEADERBOARD_METRICS,
    V1_TIERS,
    available_tiers,
    check_labels,
    check_seed_list,
    resolve_tier,
    tier_test_seeds,
)
from agents.benchmark.stats import DEFAULT_BOOTSTRAP_SEED, DEFAULT_RESAMPLES, MAX_RESAMPLES
from agents.benchmark.traces import replay_traces


def resolve_tiers(tiers: Iterable[str] | str) -> list[str]:
    """Tier names for tier names or ids, each at most once.

    Raises:
        ValueError: an unknown tier, or one given twice (by name or id).
    """
    given = [tiers] if isinstance(tiers, str) else list(tiers)
    names = [resolve_tier(t)[0] for t in given]
    seen: dict[str, str] = {}
    for g, n in zip(given, names, strict=True):
        if n in seen:
            also = f" (as {seen[n]!r} and {g!r})" if seen[n] != g else ""
            raise ValueError(f"tiers={given!r} names tier {n!r} twice{also}: give each tier once")
        seen[n] = g
    return names


def benchmark(policies: Iterable[str | Path | PolicySpec] | None = None, tiers: Iterable[str] = ("S4",), *,
              seeds: Mapping[str, Sequence[int]] | Sequence[int] | None = None, out_dir: str | Path | None = None,
              n_resamples: int = DEFAULT_RESAMPLES, bootstrap_seed: int = DEFAULT_BOOTSTRAP_SEED,
              batched: bool = True, progress: bool = True, command: str | None = None,
              cache_dir: str | Path | None = None, floors: bool = False, address: str | None = None,
              chunk: int | None = None) -> BenchmarkResult:
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
        floors: add each v1 and Leader tier's control and information floors as reference rows
            (``kind="reference"``, :func:`agents.benchmark.floors.floor_episodes`) and the leaderboard's
            ``gap_closed`` column.
        address: run the episodes on the Ray cluster there ("local": a new Ray instance on this
            machine) as (tier, policy, seed chunk) cells and one floors cell per tier
            (:mod:`agents.benchmark.cluster`); the tables are those of the local run. Default: in
            this process.
        chunk: seeds per cell with ``address`` (default :data:`agents.benchmark.cluster.DEFAULT_CHUNK`).

    Raises:
        ValueError: unknown tier or policy, a reserved label, repeated seeds or seeds outside
            [0, 2**63 - 1], ``n_resamples`` outside [1, :data:`MAX_RESAMPLES`]; all before any
            episode runs.
        OutputWriteError: the files could not be written into ``out_dir`` (its previous files
            are kept).
    """
    import controllers as ctl

    tiers = resolve_tiers(tiers)
    leader = "+".join(t for t in tiers if t in LEADER_TIERS)
    items: list[Any] = []
    for p in (list(policies) if policies is not None else [CLASSICAL]):
        if p != CLASSICAL:
            items.append(p)
            continue
        for name in _controllers():  # a model-aware controller: on the Leader tiers benchmarked only
            if name not in ctl.MODEL_AWARE_CONTROLLERS:
                items.append(name)
            elif leader:
                items.append(f"{name}@{leader}")
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
    if chunk is not None and (isinstance(chunk, bool) or not isinstance(chunk, (int, np.integer)) or
                              not 1 <= chunk <= 100_000):
        raise ValueError(f"chunk={chunk!r} is invalid: seeds per cell, an integer in [1, 100000]")
    floor_tiers = [t for t in tiers if t in V1_TIERS + LEADER_TIERS] if floors else []
    if address is not None:
        from agents.benchmark.cluster import DEFAULT_CHUNK, run_on_ray

        frames, floor_frames = run_on_ray(specs, seed_map, address, chunk=chunk or DEFAULT_CHUNK, batched=batched,
                                          floor_tiers=floor_tiers, cache_dir=cache_dir, progress=progress)
        _check_cluster_tiers(frames, specs, tiers)
        frames += floor_frames
    else:
        frames = [evaluate_tier(specs, t, seed_map[t], batched=batched, progress=progress, cache_dir=cache_dir)
                  for t in tqdm(tiers, desc="tiers", disable=not progress)]
        if floors:  # reference rows, not competitors (agents/benchmark/floors.py)
            from agents.benchmark.floors import floor_episodes

            frames += [floor_episodes(t, seed_map[t], progress=progress, cache_dir=cache_dir) for t in floor_tiers]
    episodes = pd.concat(frames, ignore_index=True)
    board = leaderboard(episodes, n_resamples=n_resamples, seed=bootstrap_seed, progress=progress,
                        bases=residual_bases(specs),
                        observations=residual_observations(specs), filtered=filtered_laws(specs))
    config = {"command": command, "tiers": {t: resolve_tier(t)[1] for t in tiers}, "seeds": seed_map,
              "policies": [dataclasses.asdict(s) for s in specs], "metrics": list(LEADERBOARD_METRICS),
              "n_resamples": n_resamples, "bootstrap_seed": bootstrap_seed, "confidence": 0.95,
              "batched": batched, "published_seeds": seeds is None, "floors": floors,
              "cache_dir": None if cache_dir is None else str(cache_dir), "address": address,
              "chunk": (chunk or _default_chunk()) if address is not None else None}
    prov = provenance(config)
    result = BenchmarkResult(episodes, board, prov)
    if out_dir is not None:
        traces = replay_traces(specs, seed_map, progress=progress)
        result.files = write_outputs(Path(out_dir), episodes, board, prov, traces)
    return result


def _default_chunk() -> int:
    from agents.benchmark.cluster import DEFAULT_CHUNK

    return DEFAULT_CHUNK


def _check_cluster_tiers(frames: list[pd.DataFrame], specs: Sequence[PolicySpec], tiers: Sequence[str]) -> None:
    """As the local run: a tier no policy could run on is an error, a policy left out of a tier a warning."""
    import warnings

    got = {f["tier"].iloc[0]: set(f["policy"]) for f in frames}
    for t in tiers:
        wanted = [s.label for s in specs if not s.tiers or t in s.tiers]
        if not wanted:
            continue
        if t not in got:
            raise ValueError(f"tier={t!r}: none of the policies can run on {resolve_tier(t)[1]}")
        for label in wanted:
            if label not in got[t]:
                warnings.warn(f"{t}: {label!r} cannot run on {resolve_tier(t)[1]} and is left out of this tier",
                              stacklevel=3)


def rebuild_leaderboard(out_dir: str | Path, *, command: str | None = None, progress: bool = True,
                        tier_prior_floor: Sequence[str] = (), cache_dir: str | Path | None = None,
                        add_policies: Sequence[str] = (), batched: bool = True) -> BenchmarkResult:
    """Recompute the leaderboard of a benchmark folder from its stored episodes (no episode runs) with
    the folder's bootstrap settings and each row's base / observation / filtered law, and write the
    set again (atomically). The provenance keeps the episodes' own and adds ``rebuilt``: the command,
    the versions of this computation and what changed.

    Args:
        tier_prior_floor: Leader tiers of the folder whose tier-prior floor
            (:func:`agents.benchmark.floors.particle_floor_rows` with ``knows="tier"``, on the folder's
            seeds of the tier; about 25 minutes per tier of 100 seeds on 2 cores) is computed and
            added as reference rows first, replacing any the folder holds.
        cache_dir: the particle floors' cache (:func:`agents.benchmark.floors.leader_floor`) and
            the policies' episode cache (:func:`evaluate_tier`).
        add_policies: policies as :func:`benchmark` takes them (``NAME@Tier`` for one tier) scored
            on the folder's seeds of its tiers and added (a label the folder holds is scored
            again and replaced), with their replay traces; the provenance lists them.
        batched: evaluate the added policies through the native vector env.

    Raises:
        ValueError: the folder is not a complete, consistent benchmark (:func:`load_result`), or a
            ``tier_prior_floor`` tier is not a Leader tier of the folder.
    """
    from agents.benchmark.outputs import load_result

    out = Path(out_dir)
    res = load_result(out)
    cfg = res.provenance.get("config", {})
    old = res.leaderboard
    added = _add_tier_prior_rows(res, list(tier_prior_floor), cache_dir, progress)
    new_specs = _add_policy_rows(res, list(add_policies), cache_dir, batched, progress)

    def column(name: str) -> dict[str, str]:
        if name not in old:
            return {}
        return {str(p): str(v) for p, v in zip(old["policy"], old[name], strict=True)
                if isinstance(v, str) and v}

    board = leaderboard(res.episodes, n_resamples=int(cfg.get("n_resamples", DEFAULT_RESAMPLES)),
                        seed=int(cfg.get("bootstrap_seed", DEFAULT_BOOTSTRAP_SEED)), progress=progress,
                        bases={**column("base"), **residual_bases(new_specs)},
                        observations={**column("observation"), **residual_observations(new_specs)},
                        filtered={**column("filtered_law"), **filtered_laws(new_specs)})
    prov = {k: v for k, v in res.provenance.items() if k != "rebuilt"}
    done = ([f"the tier-prior floor's reference rows added for {', '.join(added)}"] if added else []) + \
        ([f"policies scored and added: {', '.join(s.label for s in new_specs)}"] if new_specs else [])
    what = ("; ".join(done) + " (the other episodes unchanged), then the leaderboard recomputed" if done else
            "the leaderboard recomputed from the stored episodes (episodes unchanged)")
    earlier = res.provenance.get("rebuilt", {})
    prov["rebuilt"] = {"command": command, "versions": provenance({})["versions"], "what": what}
    rows = {**earlier.get("added_rows", {}), **{t: TIER_PRIOR_ROWS for t in added}}
    if rows:  # rows added by this or an earlier rebuild
        prov["rebuilt"]["added_rows"] = rows
    pols = {**earlier.get("added_policies", {}),
            **{s.label: {"spec": dataclasses.asdict(s), "command": command} for s in new_specs}}
    if pols:
        prov["rebuilt"]["added_policies"] = pols
    if res.traces is None:
        raise ValueError(f"{out}: no traces.parquet: run the benchmark again to write a complete set")
    result = BenchmarkResult(res.episodes, board, prov)
    result.files = write_outputs(out, res.episodes, board, prov, res.traces)
    return result


#: what :func:`rebuild_leaderboard`'s ``tier_prior_floor`` adds, as its provenance says
TIER_PRIOR_ROWS = "tier-prior floor (agents.benchmark.floors.particle_floor_rows, knows='tier')"


def _add_tier_prior_rows(res: Any, tiers: list[str], cache_dir: str | Path | None, progress: bool) -> list[str]:
    """Replace the tier-prior floor rows of ``tiers`` in ``res.episodes`` by fresh ones (in place)."""
    if not tiers:
        return []
    from agents.benchmark.floors import TIER_PRIOR_FLOOR, particle_floor_rows
    from auv_follow_env.tiers import LEADER_TIERS

    ep = res.episodes
    have = list(dict.fromkeys(ep["tier"]))
    for t in tiers:
        if t not in LEADER_TIERS or t not in have:
            raise ValueError(f"tier_prior_floor={tiers!r} is invalid: {t!r} is not one of the folder's Leader tiers "
                             f"{[x for x in have if x in LEADER_TIERS]}")
    frames = [ep[~((ep["policy"] == TIER_PRIOR_FLOOR) & ep["tier"].isin(tiers))]]
    for t in dict.fromkeys(tiers):
        frames.append(particle_floor_rows(t, _folder_seeds(res, t), "tier", cache_dir=cache_dir, progress=progress))
    res.episodes = pd.concat(frames, ignore_index=True)
    return list(dict.fromkeys(tiers))


def _add_policy_rows(res: Any, policies: list[str], cache_dir: str | Path | None, batched: bool,
                     progress: bool) -> list[PolicySpec]:
    """Score ``policies`` on the folder's tiers and seeds; replace their rows and traces in ``res``."""
    if not policies:
        return []
    specs = [parse_policy(p) for p in policies]
    labels = [s.label for s in specs]
    dup = sorted({x for x in labels if labels.count(x) > 1})
    if dup:
        raise ValueError(f"add_policies has duplicate labels {dup}: give each method once")
    check_labels(labels)
    ep = res.episodes
    tiers = list(dict.fromkeys(ep["tier"]))
    seed_map = {t: _folder_seeds(res, t) for t in tiers}
    for s in specs:
        unknown = [t for t in s.tiers if t not in tiers]
        if unknown:
            raise ValueError(f"add_policies: {s.label!r} names tiers {unknown} the folder does not hold {tiers}")
    frames = [evaluate_tier(specs, t, seed_map[t], batched=batched, progress=progress, cache_dir=cache_dir)
              for t in tqdm(tiers, desc="tiers", disable=not progress) if any(not s.tiers or t in s.tiers
                                                                            for s in specs)]
    frames = [f for f in frames if len(f)]
    if not frames:
        raise ValueError(f"add_policies: none of {labels} can run on the folder's tiers {tiers}")
    res.episodes = pd.concat([ep[~ep["policy"].isin(labels)], *frames], ignore_index=True)
    traces = replay_traces(specs, {t: seed_map[t] for t in tiers}, progress=progress)
    if res.traces is not None:
        res.traces = pd.concat([res.traces[~res.traces["policy"].isin(labels)], traces], ignore_index=True)
    return specs


def _folder_seeds(res: Any, tier: str) -> list[int]:
    """A benchmark folder's seeds of a tier: its configuration's, else those of its episode rows."""
    seeds = res.provenance.get("config", {}).get("seeds", {}).get(tier)
    if seeds is None:
        ep = res.episodes
        seeds = sorted(set(map(int, ep.loc[(ep["tier"] == tier) & (ep["kind"] != "reference"), "seed"])))
    return [int(x) for x in seeds]
