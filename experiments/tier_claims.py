"""Measure what docs/tiers.md and the README say about the v1 tiers' links.

For every tier, PROPOSED follows the target on the tier's test seeds (the link does not depend
on the follower except through range-dependent fix noise) and per episode we record: the share
of sends lost (``info["link_stats"]``: i.i.d. loss and bursts together), the age of the newest
packet (observation field ``packet_age``: mean and max over t in [0, 60) s), the age of each
fix when it arrives (``packet_age`` on steps with ``new_packet``), and the longest time without
an arrival. It also lists the drawn or fixed fields where Extreme's values are not outside
Hard's. Nothing is tuned here: it measures.

Usage: ``python -m experiments.tier_claims [--seeds N] [--out PATH]`` (default: the 100 test
seeds of each tier, ``results/tier_claims.md``; other settings write to ``results/tmp/``).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import gymnasium as gym
import numpy as np

import auv_follow_env  # noqa: F401
from auv_follow_env.layout import OBS_INDEX_V1
from auv_follow_env.tiers import TIERS
from controllers import make_controller
from experiments.outputs import output_path, write_report

ROOT = Path(__file__).resolve().parents[1]
COMMITTED = ROOT / "results" / "tier_claims.md"


def measure(tier: str, seeds: list[int]) -> dict[str, np.ndarray]:
    """Per-episode link figures of ``tier`` on ``seeds`` (arrays, one entry per episode; the
    arrival ages pooled over all episodes)."""
    env = gym.make(f"AUVFollow-{tier}-v1")
    pol = make_controller("PROPOSED", env.unwrapped.task_spec)
    ia, inew, ihas = OBS_INDEX_V1["packet_age"], OBS_INDEX_V1["new_packet"], OBS_INDEX_V1["has_packet"]
    out: dict[str, list] = {"lost": [], "age_mean": [], "age_max": [], "gap_max": [], "arrival_age": [],
                            "no_packet": []}
    for s in seeds:
        obs, _ = env.reset(seed=s)
        pol.reset()
        ages, arrivals, times = [], [], []
        while True:
            action, _ = pol.predict(obs)
            obs, _, term, trunc, info = env.step(action)
            # before the first arrival the age is undefined (the field is 0): count it as the time so far
            ages.append(float(obs[ia]) if obs[ihas] > 0.5 else float(info["time"]))
            times.append(float(info["time"]))
            if obs[inew] > 0.5:
                arrivals.append(len(ages) - 1)
            if term or trunc:
                break
        st = info["link_stats"]
        out["lost"].append(st["lost"] / max(st["sent"], 1))
        out["age_mean"].append(float(np.mean(ages)))
        out["age_max"].append(float(np.max(ages)))
        t = np.asarray(times)
        edges = np.concatenate([[0.0], t[arrivals], [t[-1]]])
        out["gap_max"].append(float(np.max(np.diff(edges))))
        out["arrival_age"].extend(ages[k] for k in arrivals)
        out["no_packet"].append(not arrivals)
    env.close()
    return {k: np.asarray(v) for k, v in out.items()}


def overlaps(a: str = "Hard", b: str = "Extreme") -> list[str]:
    """Fields (fixed or drawn) where tier ``b``'s interval is not entirely outside ``a``'s."""
    def span(t, k):
        v = t.ranges.get(k, t.fixed.get(k))
        return None if v is None or isinstance(v, str) else (tuple(map(float, v)) if isinstance(v, tuple)
                                                              else (float(v), float(v)))
    ta, tb = TIERS[a], TIERS[b]
    out = []
    for k in sorted(set(ta.ranges) | set(tb.ranges)):
        sa, sb = span(ta, k), span(tb, k)
        if sa is not None and sb is not None and not (sb[0] > sa[1] or sb[1] < sa[0]):
            touch = sb[0] == sa[1] or sb[1] == sa[0]
            out.append(f"{k}: {a} {sa}, {b} {sb}" + (" (they share an end value)" if touch else " (overlap)"))
    return out


def report(n_seeds: int) -> str:
    lines = ["# Link figures of the v1 tiers (measured)", "",
             f"`python -m experiments.tier_claims` (PROPOSED follows; the first {n_seeds} test seeds of each tier). "
             "Per episode: share of sends lost (i.i.d. loss and bursts), mean and max age of the newest packet, "
             "longest time without an arrival (from t = 0; before the first arrival the age is the time "
             "since t = 0); fix age at arrival pooled over the episodes. Ranges are min-max over the "
             "episodes (5th-95th percentile in brackets).", "",
             "| tier | sends lost [%] | mean packet age [s] | max packet age [s] | longest gap without a fix [s] | "
             "fix age at arrival [s] | episodes without any fix |", "|---|---|---|---|---|---|---|"]

    def rng(x: np.ndarray, scale: float = 1.0, fmt: str = ".1f") -> str:
        x = scale * x
        p5, p95 = np.percentile(x, [5, 95])
        return f"{x.min():{fmt}}-{x.max():{fmt}} ({p5:{fmt}}-{p95:{fmt}})"

    for name, t in TIERS.items():
        m = measure(name, list(t.test_seeds[:n_seeds]))
        mean_age = f"{rng(m['age_mean'])} (mean {m['age_mean'].mean():.1f})"
        lines.append(f"| {name} | {rng(m['lost'], 100, '.0f')} | {mean_age} "
                     f"| {rng(m['age_max'])} | {rng(m['gap_max'])} | {rng(m['arrival_age'])} "
                     f"| {int(m['no_packet'].sum())} of {len(m['no_packet'])} |")
    lines += ["", "Fields where Extreme is not outside Hard's values:", ""]
    lines += [f"- {x}" for x in overlaps()] or ["- none"]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.tier_claims", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", type=int, default=100, help="test seeds per tier (the first N)")
    p.add_argument("--out", type=Path, default=None, help=f"Markdown output (default: {COMMITTED})")
    args = p.parse_args(argv)
    if not 1 <= args.seeds <= 100:
        p.error(f"argument --seeds: {args.seeds} is invalid: must be in [1, 100]")
    write_report(output_path(args, p, COMMITTED), report(args.seeds))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
