"""The learned estimator of a Leader tier (agents/training/learned_estimator.py): trains its runs
(one per training seed; an existing run is kept unless ``--retrain``), draws their learning curves,
and scores the estimate open loop against the generic filters (linear OU0, IMM) and the
model-aware particle filter on the same recorded episodes.

Training data: episodes on training seeds 100,000 + 10,000 x seed + [0, 4096) under
PROPOSED_IMM_DOB; validation (the curves): seeds 900,000-900,255. Open-loop scoring, as
experiments/leader_estimators.py: episodes recorded under PROPOSED_KF_DOB on the check seeds
(100-163, training seeds that no run trained on) and on the tier's published test seeds (scoring
only: nothing is chosen there, every setting was fixed before), each estimator run over the
same observations; per episode the mean error of the present reference point over t >= 10 s, IQM
over episodes (95 % bootstrap CI), paired ratios against the IMM. The closed-loop scores (the
estimator feeding the tracking law) are the leaderboard's rows "Learned estimator ...".

    python -m experiments.learned_estimator --tier Leader-Hard --prefix le2 --epochs 40   # the leaderboard's runs
    python -m experiments.learned_estimator --tier Leader-Medium                           # (le1: 20 epochs)
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

from agents.training.learned_estimator import EstimatorSettings
from auv_follow_env.tiers import LEADER_TIERS
from experiments.outputs import output_path, write_report

RUNS = Path("results/benchmark/runs")


def run_name(tier: str, seed: int, prefix: str = "le1") -> str:
    return f"{prefix}-{tier.replace('-', '')}-s{seed}"


def _curves_png(runs: list[Path], tier: str, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import pandas as pd

    fig, ax = plt.subplots(figsize=(7.2, 3.8))
    imm = None
    for r in runs:
        c = pd.read_csv(r / "curve.csv")
        ax.plot(c["epoch"], c["val_m"], marker="o", ms=3, label=f"learned, {r.name}")
        imm = float(c["val_imm_m"].iloc[0])
    if imm is not None:
        ax.axhline(imm, color="k", ls="--", lw=1, label="IMM alone (generic, the start)")
    ax.set_xlabel("epoch (passes over 4,096 training episodes)")
    ax.set_ylabel("validation error of the reference point [m]")
    ax.set_title(f"{tier}: learned estimator, validation seeds 900,000-900,255")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> str:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--tier", default="Leader-Hard", choices=list(LEADER_TIERS))
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="training seeds (0-9), one run each")
    p.add_argument("--runs-dir", default=str(RUNS), help="where the runs are (default %(default)s)")
    p.add_argument("--retrain", action="store_true", help="train again even where a run exists")
    p.add_argument("--epochs", type=int, default=EstimatorSettings.epochs,
                   help="passes over the training episodes for runs trained here (default %(default)s)")
    p.add_argument("--prefix", default="le1", help="run names: PREFIX-<tier>-s<seed> (default %(default)s)")
    p.add_argument("--out", default=None, help="Markdown output (default: results/learned_estimator_<tier>.md)")
    p.add_argument("--progress", action=argparse.BooleanOptionalAction, default=True)
    a = p.parse_args(argv)
    tag = a.tier.replace("-", "_").lower()
    out = output_path(a, p, Path(f"results/learned_estimator_{tag}.md"), ignore=("progress", "tier"))
    from agents.training.learned_estimator import LearnedEstimator, train_estimator
    from controllers import LEADER_IMM
    from experiments import leader_estimators as le

    env_id = LEADER_TIERS[a.tier].env_id
    runs = []
    for s in a.seeds:
        run = Path(a.runs_dir) / run_name(a.tier, s, a.prefix)
        if a.retrain or not (run / "model.zip").is_file():
            train_estimator(env_id, run, seed=s, settings=EstimatorSettings(epochs=a.epochs), progress=a.progress)
        runs.append(run)
    png = out.with_suffix(".png")
    _curves_png(runs, a.tier, png)

    import torch

    weights = [torch.load(str(r / "model.zip"), map_location="cpu", weights_only=True) for r in runs]
    t0 = time.perf_counter()
    rows = []
    test = tuple(LEADER_TIERS[a.tier].test_seeds)
    for name, seeds, scoring in (("check", le.CHECK_SEEDS, False), ("test", test, True)):
        data = le.record(a.tier, seeds, scoring=scoring)
        base = le.EstimatorConfig.for_spec(data["spec"])
        imm_cfg = dataclasses.replace(base, model="IMM", **LEADER_IMM.get(a.tier, {}))
        lin = le.episode_errors(base, data)
        imm = le.episode_errors(imm_cfg, data)
        pf = le.pf_errors(a.tier, data, le.PF_PARTICLES)
        learned = [le.episode_errors(LearnedEstimator(data["spec"], w), data) for w in weights]
        gap = le.iqm(imm) - le.iqm(pf)
        row = [f"{name} {seeds[0]}-{seeds[-1]}"]
        for e in (lin, imm, pf):
            lo, hi = le.boot_iqm(e)
            row.append(f"{le.iqm(e):.3f} ({lo:.3f}-{hi:.3f})")
        for e in learned:
            r, lo, hi = le.ratio_ci(e, imm)
            share = (le.iqm(imm) - le.iqm(e)) / gap if gap > 0 else float("nan")
            gs = f"gap share {share:.2f}" if share == share else "no gap (the particle filter is worse than the IMM)"
            row.append(f"{le.iqm(e):.3f}; {100 * r:+.0f} % ({100 * lo:+.0f} to {100 * hi:+.0f}) vs IMM; {gs}")
        rows.append("| " + " | ".join(row) + " |")
    lines = [f"# Learned estimator on {a.tier}", "",
             f"Reproduce: `python -m experiments.learned_estimator --tier {a.tier}"
             + (f" --prefix {a.prefix} --epochs {a.epochs}" if a.prefix != "le1" else "") +
             "` (method in its docstring; "
             f"{time.perf_counter() - t0:.0f} s of scoring here). Learning curves: `{png.name}`.", "",
             "Open-loop error of the present reference point [m] (per episode the mean over t >= 10 s; IQM over "
             "episodes, 95 % bootstrap CI). Learned: IQM; its paired IQM ratio against the IMM (the generic filter it "
             "corrects) with a bootstrap CI; gap share = (IMM - learned) / (IMM - particle filter), "
             "the share of the generic-to-model-aware gap it closes (the particle filter: the model-aware "
             f"classical, N = {le.PF_PARTICLES}, not a Bayes floor; where it is worse than the IMM the share is "
             "meaningless).", "",
             "| episodes | linear (OU0) | IMM (generic) | particle filter (model-aware) | "
             + " | ".join(f"learned, {r.name}" for r in runs) + " |",
             "|" + "---|" * (4 + len(runs))] + rows
    lines += ["", "Runs: " + ", ".join(f"`{r}`" for r in runs) + ". Their settings and data seeds: each run's "
              "`config.yaml`."]
    return write_report(out, "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
