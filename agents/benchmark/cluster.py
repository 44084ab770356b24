"""The benchmark's episodes on a Ray cluster (``auv-follow benchmark --address``).

The work is cut into **cells**: (tier, policy, chunk of seeds) for the policies, and one cell per
tier for its floors (the control floor picks the best controller over all of the tier's seeds, so
its seeds stay together). Each cell is one Ray task that runs :func:`~agents.benchmark.evaluation.evaluate_tier`
(or :func:`~agents.benchmark.floors.floor_episodes`) on a worker; the driver gathers the rows in
the order a local run writes them, so the tables built from them are the same. Every episode is its
own seed's arithmetic, so on one host a cell's rows equal the local run's (tests/test_cluster.py).

Workers must run the same code: each cell returns a digest of the episode code's source files
(:data:`~agents.benchmark.evaluation._EPISODE_CODE`) and the driver refuses rows computed by other
code. Every node needs this project installed (``pip install -e .`` of the same checkout, or a
Ray ``runtime_env``); ``--cache`` must then be a directory every worker can write.
"""

from __future__ import annotations

import hashlib
import os
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import pandas as pd
from tqdm.auto import tqdm

from agents.benchmark.policies import PolicySpec

__all__ = ["ClusterUnavailable", "DEFAULT_CHUNK", "code_digest", "cells", "check_reachable", "run_on_ray"]

#: seeds per (tier, policy) cell unless told otherwise: 4 cells for a tier's 100 test seeds
DEFAULT_CHUNK = 25
_ROOT = Path(__file__).resolve().parents[2]


class ClusterUnavailable(RuntimeError):
    """Ray is not installed or the cluster cannot be reached."""


def code_digest() -> str:
    """SHA-256 over the episode code's Python sources (path and bytes, in a fixed order)."""
    from agents.benchmark.evaluation import _EPISODE_CODE

    h = hashlib.sha256()
    for entry in _EPISODE_CODE:
        p = _ROOT / entry
        files = sorted(p.rglob("*.py")) if p.is_dir() else [p]
        for f in files:
            h.update(str(f.relative_to(_ROOT)).encode())
            h.update(f.read_bytes())
    return h.hexdigest()


def cells(specs: Sequence[PolicySpec], seed_map: Mapping[str, Sequence[int]], chunk: int,
          floor_tiers: Sequence[str] = ()) -> list[tuple]:
    """The cells, in the order the local run produces their rows: per tier, per policy, per chunk
    of seeds (``("policy", tier, policy index, spec, seeds)``), then the floors' tiers
    (``("floors", tier, seeds)``)."""
    out: list[tuple] = []
    for tier, seeds in seed_map.items():
        for i, spec in enumerate(specs):
            if spec.tiers and tier not in spec.tiers:
                continue
            for a in range(0, len(seeds), chunk):
                out.append(("policy", tier, i, spec, list(seeds[a:a + chunk])))
    out += [("floors", tier, list(seed_map[tier])) for tier in floor_tiers]
    return out


def _run_cell(cell: tuple, batched: bool, cache_dir: str | None) -> tuple[pd.DataFrame | None, str]:
    """One cell on a worker: its rows (None: the policy cannot run on the tier) and the worker's
    code digest."""
    import warnings

    from agents.benchmark.evaluation import evaluate_tier
    from agents.benchmark.floors import floor_episodes

    if cell[0] == "floors":
        return floor_episodes(cell[1], cell[2], progress=False, cache_dir=cache_dir), code_digest()
    _, tier, _, spec, seeds = cell
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # (the driver warns once for a policy left out of a tier)
        try:
            rows = evaluate_tier([spec], tier, seeds, batched=batched, progress=False, cache_dir=cache_dir)
        except ValueError as exc:
            if "none of the policies can run" in str(exc):
                return None, code_digest()
            raise
    return rows, code_digest()


def _ray() -> Any:
    try:
        import ray
    except ImportError as exc:
        raise ClusterUnavailable("--address needs Ray: pip install -e '.[sweep]' (the dev set-up installs it)") \
            from exc
    return ray


def check_reachable(address: str, timeout_s: float = 5.0) -> None:
    """Refuse an address whose head does not accept a TCP connection within ``timeout_s`` (Ray itself
    retries for minutes); "local" and "auto" pass.

    Raises:
        ClusterUnavailable: malformed, or nothing listens there.
    """
    import socket

    if address in ("local", "auto"):
        return
    hostport = address.removeprefix("ray://")
    host, _, port = hostport.rpartition(":")
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ClusterUnavailable(f"{address!r} is not a Ray address: give HOST:PORT of the head (e.g. "
                                 f"10.0.0.5:6379, as `ray start --head` prints it), or 'local'")
    try:
        socket.create_connection((host, int(port)), timeout=timeout_s).close()
    except OSError as exc:
        raise ClusterUnavailable(f"cannot connect to a Ray cluster at {address!r}: nothing accepted a connection "
                                 f"within {timeout_s:g} s ({exc.strerror or type(exc).__name__}); is its head "
                                 f"running (`ray start --head`)?") from None


def run_on_ray(specs: Sequence[PolicySpec], seed_map: Mapping[str, Sequence[int]], address: str, *,
               chunk: int = DEFAULT_CHUNK, batched: bool = True, floor_tiers: Sequence[str] = (),
               cache_dir: str | Path | None = None, progress: bool = True) -> tuple[list[pd.DataFrame],
                                                                                     list[pd.DataFrame]]:
    """Run every cell as a Ray task on the cluster at ``address`` ("local": a new Ray instance on
    this machine) and return (the policies' rows per tier, the floors' rows per tier), in the local
    run's order.

    Raises:
        ClusterUnavailable: Ray is missing or the cluster cannot be reached.
        ValueError: a worker runs other code; a cell's own error (a user's controller that fails,
            a run that cannot be loaded), raised as on a local run.
    """
    ray = _ray()
    started = False
    if not ray.is_initialized():
        check_reachable(address)
        try:
            if address == "local":
                ray.init(address="local", num_cpus=os.cpu_count() or 1, include_dashboard=False,
                         log_to_driver=False)
            else:
                ray.init(address=address, log_to_driver=False)
        except (ConnectionError, RuntimeError, ValueError) as exc:
            first = " ".join(str(exc).split())[:300]
            hint = ("; a cluster with token authentication (the default of `ray start --head`) needs "
                    "RAY_AUTH_MODE=token here and its token (~/.ray/auth_token or RAY_AUTH_TOKEN)"
                    if "RAY_AUTH_MODE" not in os.environ else "")
            raise ClusterUnavailable(f"cannot connect to a Ray cluster at {address!r} ({first}){hint}") from None
        started = True
    try:
        todo = cells(specs, seed_map, chunk, floor_tiers)
        task = ray.remote(num_cpus=1)(_run_cell)
        cache = None if cache_dir is None else str(cache_dir)
        refs = [task.remote(c, batched, cache) for c in todo]
        index = {r: i for i, r in enumerate(refs)}
        results: list[Any] = [None] * len(refs)
        mine = code_digest()
        pending = list(refs)
        with tqdm(total=len(refs), desc=f"cells on {address}", unit="cell", disable=not progress,
                  file=sys.stderr) as bar:
            while pending:
                done, pending = ray.wait(pending, num_returns=1)
                try:
                    rows, digest = ray.get(done[0])
                except ray.exceptions.RayTaskError as exc:
                    cause = getattr(exc, "cause", None)
                    if isinstance(cause, (ValueError, OSError)):
                        raise cause from None
                    raise
                if digest != mine:
                    cell = todo[index[done[0]]]
                    raise ValueError(f"a Ray worker ran {cell[0]} cell {cell[1]} with other episode code (digest "
                                     f"{digest[:12]} against this checkout's {mine[:12]}): install the same "
                                     f"checkout on every node")
                results[index[done[0]]] = rows
                bar.update()
    finally:
        if started:
            ray.shutdown()
    policy_frames: dict[str, list[pd.DataFrame]] = {t: [] for t in seed_map}
    floor_frames = []
    for cell, rows in zip(todo, results, strict=True):
        if cell[0] == "floors":
            floor_frames.append(rows)
        elif rows is not None:
            policy_frames[cell[1]].append(rows.assign(_spec=cell[2]))
    return [_local_order(frames, seed_map[t]) for t, frames in policy_frames.items() if frames], floor_frames


def _local_order(frames: list[pd.DataFrame], seeds: Sequence[int]) -> pd.DataFrame:
    """One tier's cell rows in the local run's order: by policy, then run, then the seeds' order."""
    df = pd.concat(frames, ignore_index=True)
    pos = {s: i for i, s in enumerate(seeds)}
    # a policy's runs in the order its cells list them (each cell: every run, one after the other)
    run_pos = df.groupby("_spec", sort=False)["run"].transform(lambda r: r.map({x: i for i, x in
                                                                                enumerate(dict.fromkeys(r))}))
    df = df.assign(_run=run_pos, _seed=df["seed"].map(pos))
    df = df.sort_values(["_spec", "_run", "_seed"], kind="stable")
    return df.drop(columns=["_spec", "_run", "_seed"]).reset_index(drop=True)
