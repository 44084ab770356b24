"""``auv-follow trace`` and ``auv-follow dataset``: data out of the benchmark (link traces, Minari
datasets). Registered by :func:`agents.cli.build_parser`; errors take the CLI's one-line path."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

__all__ = ["add_data_commands", "one_policy"]

#: the policy a trace is recorded with unless --policy says otherwise
DEFAULT_TRACE_POLICY = "PROPOSED_KF_DOB"


def one_policy(text: str, env_id: str) -> tuple[Any, str]:
    """(policy object with the SB3 ``predict`` protocol, its label) of a policy as the benchmark
    names it: a controller name, a run directory (a directory of runs: its first run) or
    ``[label=]module:Class``."""
    import gymnasium as gym

    from agents.benchmark.policies import build_policy, parse_policy

    spec = parse_policy(text)
    env = gym.make(env_id)
    try:
        width = int(env.observation_space.shape[0])
        policy = build_policy(spec, spec.runs[0] if spec.runs else None, env_id, env.unwrapped.task_spec, width)
    finally:
        env.close()
    if len(spec.runs) > 1:
        print(f"{spec.label}: {len(spec.runs)} runs; using the first, {spec.runs[0]}", file=sys.stderr)
    return policy, spec.label


def add_data_commands(sub: Any, formatter: type, env_choices: tuple[str, ...], seed_type: Any) -> None:
    """The ``trace`` and ``dataset`` subcommands (each sets ``handler``)."""
    v1 = tuple(e for e in env_choices if e.endswith("-v1"))
    t = sub.add_parser("trace", help="write the link trace of a simulated v1 episode (CSV or Parquet)",
                       formatter_class=formatter,
                       description="Run one episode of a v1 env and write its link trace: per packet sent from "
                                   "t = 0 on, its send time, arrival time (empty: lost) and the fix's error "
                                   "(docs/link_traces.md). Replay it with gym.make(ENV, link_trace=FILE); the same "
                                   "seed and policy give the same episode. Edit it, or convert a modem's log to the "
                                   "same columns, to run the benchmark's tasks on a recorded link.")
    t.add_argument("--env", required=True, choices=v1, metavar="ENV", help=f"a v1 id: {', '.join(v1)}")
    t.add_argument("--seed", required=True, type=seed_type, help="the episode's seed")
    t.add_argument("--out", required=True, help="trace file: .csv or .parquet (overwritten if it exists)")
    t.add_argument("--policy", default=DEFAULT_TRACE_POLICY,
                   help="the follower's policy, named as in `benchmark --policies` (the fix errors grow with "
                        "range, so they depend on the follower's path; send times, latencies and losses do not)")
    t.set_defaults(handler=_cmd_trace)

    d = sub.add_parser("dataset", help="write a Minari dataset of a policy's episodes on a tier",
                       formatter_class=formatter,
                       description="Record a policy's episodes on a tier as a Minari dataset in Minari's store "
                                   "(MINARI_DATASETS_PATH, default ~/.minari/datasets) and print its id: "
                                   "observations, actions, rewards, terminations, truncations; infos with the true "
                                   "tracking error and the link flags; each episode's seed and drawn condition in "
                                   "its metadata; ref_min_score / ref_max_score from PID and the tier's best "
                                   "classical controller on its test seeds (docs/data.md). Load it with "
                                   "minari.load_dataset(ID); dataset.recover_environment() makes the env.")
    d.add_argument("--tier", required=True, help="S1..S4, Easy, Medium, Hard, Extreme, Leader-Easy, Leader-Medium, "
                                                 "Leader-Hard")
    d.add_argument("--policy", required=True,
                   help="a controller name, a run directory or [label=]module:Class, as in `benchmark --policies`")
    d.add_argument("--id", dest="dataset_id", required=True,
                   help="the dataset's Minari id, NAMESPACE/NAME-vN (e.g. auv-follow/hard-kf-v0)")
    d.add_argument("--seeds", type=seed_type, default=None,
                   help="episode seeds, e.g. 0-99 (default: training seeds 0-99)")
    d.add_argument("--allow-test-seeds", action="store_true",
                   help="allow the tier's published test seeds in --seeds. Offline training or imitation on test "
                        "seeds leaks them: the agent's test score then measures what it memorised, not how it "
                        "follows. Only for analysis datasets that no agent trains on")
    d.add_argument("--ref-episodes", type=_ref_episodes, default=100,
                   help="test seeds (the tier's first N) on which the reference scores are measured")
    d.add_argument("--ref-max", default=None, metavar="CONTROLLER",
                   help="the controller of ref_max_score (default: the tier's best classical on the committed "
                        "leaderboard)")
    d.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bars")
    d.set_defaults(handler=_cmd_dataset)


def _ref_episodes(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if not 1 <= n <= 100:
        raise argparse.ArgumentTypeError(f"{text!r} is invalid: must be an integer in [1, 100] (a tier has 100 "
                                         f"test seeds)")
    return n


def _cmd_dataset(args: argparse.Namespace) -> None:
    import os

    from agents._cli_errors import _Refused
    from agents.benchmark.policies import _controllers
    from agents.benchmark.protocol import resolve_tier
    from agents.datasets import (
        DEFAULT_TRAIN_SEEDS,
        DatasetUnavailable,
        check_dataset_id,
        check_dataset_seeds,
        reference_scores,
        write_dataset,
    )

    try:
        name, env_id = resolve_tier(args.tier)
    except ValueError as exc:
        raise _Refused("--tier", str(exc)) from None
    try:
        check_dataset_id(args.dataset_id)
    except DatasetUnavailable as exc:
        raise SystemExit(f"auv-follow dataset: error: {exc}") from None
    except ValueError as exc:
        raise _Refused("--id", str(exc)) from None
    try:
        seeds = check_dataset_seeds(name, args.seeds or list(DEFAULT_TRAIN_SEEDS), args.allow_test_seeds)
    except ValueError as exc:
        raise _Refused("--seeds", str(exc)) from None
    if args.ref_max is not None and args.ref_max not in _controllers():
        raise _Refused("--ref-max", f"{args.ref_max!r} is not a controller: one of {list(_controllers())}")
    policy, label = one_policy(args.policy, env_id)
    refs = reference_scores(name, best=args.ref_max, episodes=args.ref_episodes, progress=args.progress)
    ds = write_dataset(args.dataset_id, name, policy, label, seeds, refs=refs, progress=args.progress)
    root = os.environ.get("MINARI_DATASETS_PATH", "~/.minari/datasets")
    print(f"dataset: {args.dataset_id} ({ds.total_episodes} episodes, {ds.total_steps} steps of {label} on {env_id}; "
          f"ref scores {refs['ref_min_score']:.1f} (PID) and {refs['ref_max_score']:.1f} ({refs['best']})) in {root}")
    print(f"load it with: minari.load_dataset({args.dataset_id!r})")


def _cmd_trace(args: argparse.Namespace) -> None:
    import gymnasium as gym
    import numpy as np

    from agents._cli_errors import _check_writable, _Refused
    from auv_follow_env.link_trace import _kind, record_link_trace

    if len(args.seed) != 1:
        raise _Refused("--seed", f"{len(args.seed)} seeds given: a trace is one episode, give one seed")
    out = Path(args.out)
    try:
        _kind(out, "--out")
    except ValueError as exc:
        raise _Refused("--out", str(exc)) from None
    _check_writable(out, "--out", want_dir=False)
    policy, label = one_policy(args.policy, args.env)
    env = gym.make(args.env)
    trace = record_link_trace(env, policy, args.seed[0])
    trace.write(out)
    lat = trace.arrival_time - trace.send_time
    arrived = ~np.isnan(lat)
    mean = f"{np.mean(lat[arrived]):.2f} s" if arrived.any() else "-"
    print(f"trace: {out} ({args.env}, seed {args.seed[0]}, {label}): {len(trace)} packets, {int((~arrived).sum())} "
          f"lost, mean latency {mean}")
