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


def _cmd_trace(args: argparse.Namespace) -> None:
    import gymnasium as gym
    import numpy as np

    from agents.cli import _check_writable, _Refused
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
