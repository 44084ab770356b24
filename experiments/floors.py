"""Floors per tier: how much is possible on each acoustic-link tier.

    python -m experiments.floors                    # Easy, Medium, Hard, Extreme; 100 test seeds each
    python -m experiments.floors --tiers Hard --seeds 10   # a quick look (writes to results/tmp/floors)

For every published test episode of each tier (library: :mod:`agents.benchmark.floors`):

* the **control floor**: every classical controller (``controllers.ALL_CONTROLLERS`` except
  MPC, see ``agents.benchmark.floors.SLOW_CONTROLLERS``) on the same episode with a perfect link (the
  present target every step, no latency, loss or noise; thruster lag and rate limit on); the
  floor is the controller with the lowest IQM;
* the **information floor**: the expected error of the optimal estimate of the present
  reference point from the packets the follower received (a Kalman filter with the episode's
  true target and noise parameters, linearised about the true trajectory, on the actual packet
  timing; docs/benchmark.md, "Floors"), and the realised error of an extended Kalman filter
  with the same parameters on the same packets.

Writes ``results/floors/floors.csv`` (one row per episode) and ``results/floors/floors.md``
(IQM with 95 % stratified-bootstrap CIs, ``agents.benchmark``'s statistics).
"""

from __future__ import annotations

import argparse
import shlex
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
from tqdm.auto import tqdm

from agents.benchmark import floors
from agents.benchmark.stats import stratified_bootstrap_ci
from auv_follow_env.tiers import TIERS
from experiments.outputs import output_path, write_report

DEFAULT_TIERS = ("Easy", "Medium", "Hard", "Extreme")
COMMITTED = Path("results/floors")


@dataclass
class Args:
    tiers: list[str] = field(default_factory=lambda: list(DEFAULT_TIERS))  #: v1 tiers
    seeds: int = 100  #: the first N published test seeds of each tier
    follower: str = floors.DEFAULT_FOLLOWER  #: controller that plays the real-link episodes
    out: Path | None = None  #: output directory (default results/floors, or results/tmp/floors)
    progress: bool = True  #: progress bars


def parse_args(argv: list[str] | None = None) -> tuple[Args, Path]:
    import controllers

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--tiers", nargs="+", choices=list(TIERS), default=list(DEFAULT_TIERS))
    p.add_argument("--seeds", type=int, default=Args.seeds, help="first N published test seeds per tier (2-100)")
    p.add_argument("--follower", choices=list(controllers.ALL_CONTROLLERS), default=Args.follower)
    p.add_argument("--out", type=Path, default=None)
    p.add_argument("--no-progress", dest="progress", action="store_false")
    a = p.parse_args(argv)
    if not 2 <= a.seeds <= 100:
        p.error(f"--seeds must be in [2, 100] (a CI needs two episodes; each tier publishes 100), got {a.seeds}")
    out = output_path(a, p, COMMITTED)
    a.out = out
    return Args(**vars(a)), out


def _ci(x: np.ndarray, stat: str = "iqm") -> str:
    est, lo, hi = stratified_bootstrap_ci([np.asarray(x, dtype=np.float64)], stat)
    return f"{est:.4f} [{lo:.4f}, {hi:.4f}]"


def run(args: Args) -> tuple[pd.DataFrame, pd.DataFrame]:
    """(per-episode floors, per-episode perfect-link scores of every controller)."""
    rows, perfect = [], []
    for tier in tqdm(args.tiers, desc="tiers", disable=not args.progress):
        seeds = list(TIERS[tier].test_seeds[:args.seeds])
        cf = floors.control_floor(tier, seeds, progress=args.progress)
        rec = floors.record_episodes(tier, seeds, args.follower, progress=args.progress)
        inf = floors.information_floor(tier, recording=rec)
        inf["estimator_steady_mean"] = floors.estimator_error(rec)  # the tier's TargetEstimator (ours)
        eps = cf.episodes.assign(tier=tier)
        perfect.append(eps[["tier", "policy", "seed", "terminated", "true_steady_mean", "true_full_mean"]])
        best = cf.scores.set_index("seed")
        real = rec["episodes"].set_index("seed")
        df = inf.assign(tier=tier, control_floor_controller=cf.best,
                        control_floor_steady_mean=best.loc[inf["seed"], "true_steady_mean"].to_numpy(),
                        control_floor_full_mean=best.loc[inf["seed"], "true_full_mean"].to_numpy(),
                        follower=args.follower,
                        follower_steady_mean=real.loc[inf["seed"], "true_steady_mean"].where(
                            ~real.loc[inf["seed"], "terminated"], floors._max_distance()).to_numpy(),
                        follower_terminated=real.loc[inf["seed"], "terminated"].to_numpy())
        rows.append(df)
    table = pd.concat(rows, ignore_index=True)
    first = ["tier", "seed", "control_floor_controller", "control_floor_steady_mean", "expected_steady_mean",
             "realised_steady_mean", "follower", "follower_steady_mean"]
    table = table[first + [c for c in table.columns if c not in first]]
    return table, pd.concat(perfect, ignore_index=True)


def report(table: pd.DataFrame, perfect: pd.DataFrame, args: Args, command: str) -> str:
    lines = ["# Floors per tier", "",
             f"Reproduce: `{command}` (library: `agents/benchmark/floors.py`; "
             "derivation: docs/benchmark.md, \"Floors\").", "",
             f"Steady-state (t >= 10 s) true-reference error [m] per episode, IQM [95 % stratified-bootstrap CI] "
             f"over the first {args.seeds} published test seeds of each tier. *Control floor*: the best classical "
             "controller on the same episodes with a perfect link (the present target every step; thruster lag and "
             "rate limit on). *Information floor*: expected error of the optimal estimate of the present reference "
             "point from the packets received (Kalman filter with the true parameters, linearised about the true "
             "trajectory). *Realised*: an extended Kalman filter with the true parameters on the same packets. "
             f"*Follower*: {args.follower} on the real link (whose packets the floor uses). *Estimator*: the "
             "tier's own target estimator (`controllers.estimator`, OU0, which does not know the episode's "
             "parameters) on the same packets, with the floor's conventions "
             "(`agents.benchmark.floors.estimator_error`); "
             "\"estimator / floor\" compares the sums over the episodes like \"realised / floor\".", "",
             "| tier | control floor (controller) | information floor | realised (EKF) | realised / floor | "
             "estimator | estimator / floor | "
             f"{args.follower} (real link) | heading std > {floors.WIDE_HEADING_RAD} rad | turn rate clipped "
             "| steps w/o packet |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    notes = []
    for tier, d in table.groupby("tier", sort=False):
        ood = " (OOD)" if TIERS[tier].out_of_distribution else ""
        ok = d["expected_steady_mean"].notna()
        ratio = float(d.loc[ok, "realised_steady_mean"].sum() / d.loc[ok, "expected_steady_mean"].sum())
        both = ok & d["estimator_steady_mean"].notna()
        e_ratio = float(d.loc[both, "estimator_steady_mean"].sum() / d.loc[both, "expected_steady_mean"].sum())
        clipped = float(d["clipped_turn_share"].mean())
        wide = float(d.loc[ok, "wide_heading_share"].mean())
        lines.append(f"| {tier}{ood} | {_ci(d['control_floor_steady_mean'])} ({d['control_floor_controller'].iloc[0]}) "
                     f"| {_ci(d.loc[ok, 'expected_steady_mean'])} | {_ci(d.loc[ok, 'realised_steady_mean'])} "
                     f"| {ratio:.2f} | {_ci(d.loc[both, 'estimator_steady_mean'])} | {e_ratio:.3f} "
                     f"| {_ci(d['follower_steady_mean'])} | {100 * wide:.1f} % | {100 * clipped:.1f} % "
                     f"| {int(d['steady_steps_without_packet'].sum())} |")
        if clipped > 0.005 or wide > 0.05 or abs(ratio - 1.0) > 0.1:
            notes.append(f"- **{tier}**: the linear bound is approximate: the heading posterior std exceeds "
                         f"{floors.WIDE_HEADING_RAD} rad on {100 * wide:.1f} % of the steady-state steps, the turn "
                         f"rate sits at its clip on {100 * clipped:.1f} % of the steps, and the EKF's realised error "
                         f"is {ratio:.2f} x the linearised expectation.")
        missing = d.loc[~ok, "seed"].tolist()
        if missing:
            notes.append(f"- **{tier}**: no packet arrived in the steady-state window of seed(s) {missing}: no floor "
                         "there (left out of the IQM).")
    lines += ["", "\"realised / floor\": the EKF's realised error summed over the episodes over the linearised "
              "expected error summed the same way (1 where the linear-Gaussian model holds); \"heading std\": share "
              "of steady-state steps whose heading posterior std exceeds that value (the small-angle linearisation "
              "strains); \"turn rate clipped\": share of steps with |r_t| at target_yaw_rate_max, where the linear "
              "model's Gaussian turn rate is wrong; \"steps w/o packet\": steady-state steps before any packet "
              "arrived (left out of the floor's mean). A terminated follower scores the loss threshold (20 m).", ""]
    if notes:
        lines += ["Where the linear bound breaks down:", "", *notes, ""]
    lines += ["Means over the same episodes [95 % CI] (the floor is an expectation per episode: a method's realised "
              "errors scatter about their own expectations, so its IQM can fall below the floor's IQM while its mean "
              "cannot fall below the floor's mean by more than the sampling error):", "",
              "| tier | control floor | information floor | realised (EKF) | follower (real link) |",
              "|---|---|---|---|---|"]
    for tier, d in table.groupby("tier", sort=False):
        ok = d["expected_steady_mean"].notna()
        lines.append(f"| {tier} | {_ci(d['control_floor_steady_mean'], 'mean')} "
                     f"| {_ci(d.loc[ok, 'expected_steady_mean'], 'mean')} "
                     f"| {_ci(d.loc[ok, 'realised_steady_mean'], 'mean')} | {_ci(d['follower_steady_mean'], 'mean')} |")
    lines += ["", "## Every classical controller on the perfect link", "",
              "Steady-state IQM [95 % CI]; the lowest per tier is its control floor.", ""]
    tiers = list(dict.fromkeys(perfect["tier"]))
    lines += ["| controller | " + " | ".join(tiers) + " |", "|---|" + "---|" * len(tiers)]
    for pol in dict.fromkeys(perfect["policy"]):
        cells = []
        for tier in tiers:
            d = perfect[(perfect["tier"] == tier) & (perfect["policy"] == pol)]
            sc = d["true_steady_mean"].where(~d["terminated"], 20.0)
            cells.append(_ci(sc))
        lines.append(f"| {pol} | " + " | ".join(cells) + " |")
    lines.append("")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    args, out = parse_args(argv)
    given = [a for a in (argv if argv is not None else sys.argv[1:]) if a != "--no-progress"]
    command = "python -m experiments.floors" + (" " + shlex.join(given) if given else "")
    table, perfect = run(args)
    out.mkdir(parents=True, exist_ok=True)
    table.to_csv(out / "floors.csv", index=False, float_format="%.10g")
    write_report(out / "floors.md", report(table, perfect, args, command))


if __name__ == "__main__":
    main()
