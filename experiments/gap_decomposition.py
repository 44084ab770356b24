"""Where the gap goes, per Leader tier: each estimator's error in estimation alone against its
controller's error in closed loop, on the tier's 100 published test seeds (scoring only).

    python -m experiments.gap_decomposition                  # the three Leader tiers, about 10 minutes

* **Estimation alone**: the episodes are recorded once per tier under PROPOSED_KF_DOB (the follower
  the floors' recordings use, agents/benchmark/floors.py), and each controller's own estimator (the
  object its ``make_controller`` holds, or the learned estimator's three runs) runs open loop over
  the recorded observations: per episode the mean error of the estimated present reference point
  over the steady window, the IQM over episodes (experiments/leader_estimators.py).
* **Closed loop**: the same controller's steady-state true-reference error on the same seeds, from the
  committed leaderboard (results/benchmark; a lost target scores 20 m there).
* **Tracking cost** = closed loop / estimation alone: how much a follower loses tracking that estimate
  (1.0 would be a perfect tracker of a perfect copy of the estimate).

The floors are shown beside, from the leaderboard: the tier-prior floor (its realised error; a
follower who knows the tier's published ranges, on the tiers where it converged) and the
oracle-parameter floor (named "information floor" before 2026-12-07: a filter that knows each
episode's drawn parameters, which no follower reaches; its expected error).
Writes results/gap_decomposition.md.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd

from experiments import leader_estimators as le
from experiments.outputs import output_path, write_report

#: the Leader tiers' controllers and, per tier, the committed learned-estimator runs (the leaderboard's rows)
CONTROLLERS = ("PROPOSED_KF_DOB", "PROPOSED_IMM_DOB", "PROPOSED_LIMM_DOB", "PROPOSED_PF_DOB")
ESTIMATOR_NAMES = {"PROPOSED_KF_DOB": "linear (OU0)", "PROPOSED_IMM_DOB": "generic IMM",
                   "PROPOSED_LIMM_DOB": "model-aware IMM", "PROPOSED_PF_DOB": "model-aware particle filter"}
LEARNED = {"Leader-Medium": "le1-LeaderMedium", "Leader-Hard": "le2-LeaderHard"}
RUNS = Path("results/benchmark/runs")
BOARD = Path("results/benchmark/leaderboard.csv")
#: the floors' leaderboard rows (agents/benchmark/floors.py) and what each knows
FLOORS = (("tier-prior floor", "tier-prior floor (knows the tier's published ranges)"),
          ("oracle-parameter floor", "oracle-parameter floor (knows the episode's draws)"))


def _learned_label(board: pd.DataFrame, tier: str) -> str | None:
    rows = board[(board["tier"] == tier) & board["policy"].str.startswith("Learned estimator on PROPOSED_IMM_DOB")]
    return None if rows.empty else str(rows["policy"].iloc[0])


def _fmt(x: np.ndarray) -> str:
    lo, hi = le.boot_iqm(x)
    return f"{le.iqm(x):.3f} [{lo:.3f}, {hi:.3f}]"


def tier_rows(tier: str, board: pd.DataFrame, progress: bool) -> list[str]:
    import torch

    from agents.training.learned_estimator import LearnedEstimator
    from auv_follow_env import LEADER_TIERS
    from controllers import make_controller

    data = le.record(tier, tuple(LEADER_TIERS[tier].test_seeds), scoring=True)
    spec = data["spec"]
    sub = board[board["tier"] == tier].set_index("policy")
    floor_rows = [(sub.loc[n], what) for n, what in FLOORS if n in sub.index]
    rows = []
    for name in CONTROLLERS:
        if name not in sub.index:
            continue
        est = make_controller(name, spec).estimator
        alone = le.episode_errors(est, data)
        closed = sub.loc[name]
        rows.append((ESTIMATOR_NAMES[name], name, alone, closed))
        if progress:
            print(f"{tier} {name}: alone {le.iqm(alone):.3f}, closed {closed['true_steady_mean_iqm']:.3f}", flush=True)
    label = _learned_label(board, tier)
    if tier in LEARNED and label is not None:
        runs = sorted(RUNS.glob(f"{LEARNED[tier]}-s*"))
        errs = [le.episode_errors(LearnedEstimator(spec, torch.load(str(r / "model.zip"), map_location="cpu",
                                                                      weights_only=True)), data) for r in runs]
        rows.append((f"learned estimator ({len(runs)} runs, on the generic IMM)", label, np.concatenate(errs),
                     sub.loc[label]))
    out = []
    for est_name, ctrl, alone, closed in rows:
        c = closed["true_steady_mean_iqm"]
        out.append(f"| {tier} | {est_name} | {ctrl if len(ctrl) < 40 else 'learned estimator row'} | {_fmt(alone)} | "
                   f"{c:.3f} [{closed['true_steady_mean_iqm_lo']:.3f}, {closed['true_steady_mean_iqm_hi']:.3f}] | "
                   f"{c / le.iqm(alone):.2f}x | {int(closed['lost_targets'])} |")
    for floor, what in floor_rows:
        out.append(f"| {tier} | {what} | - | "
                   f"{floor['true_steady_mean_iqm']:.3f} [{floor['true_steady_mean_iqm_lo']:.3f}, "
                   f"{floor['true_steady_mean_iqm_hi']:.3f}] | - | - | - |")
    return out


def main(argv: list[str] | None = None) -> str:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--tiers", nargs="+", default=["Leader-Easy", "Leader-Medium", "Leader-Hard"])
    p.add_argument("--out", default=None, help="Markdown file (default results/gap_decomposition.md)")
    p.add_argument("--no-progress", dest="progress", action="store_false")
    a = p.parse_args(argv)
    out = output_path(a, p, Path("results/gap_decomposition.md"))
    board = pd.read_csv(BOARD)
    lines = ["# Where the gap goes: estimation alone against closed loop", "",
             "Each Leader tier's 100 published test seeds (scoring only). Estimation alone: the controller's own "
             "estimator run open loop over episodes recorded under PROPOSED_KF_DOB, the error of its present "
             "reference point, IQM over episodes of the per-episode steady-window mean [m] with a 95 % bootstrap "
             "CI. Closed loop: that controller's steady-state true-reference error on the same seeds (the "
             "committed leaderboard, a lost target scoring 20 m). Tracking cost: closed / alone.", "",
             "| tier | estimator | controller | estimation alone [m] | closed loop [m] | tracking cost | "
             "lost targets (closed loop) |", "|---|---|---|---|---|---|---|"]
    for tier in a.tiers:
        lines += tier_rows(tier, board, a.progress)
    lines += ["", "Command: `python -m experiments.gap_decomposition" + (" " + " ".join(argv) if argv else "") + "`",
              ""]
    return write_report(out, "\n".join(lines))


if __name__ == "__main__":
    main()
