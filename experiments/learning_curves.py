"""Learning curves of the batched-PPO runs (``--algo bppo``) against the classical baselines
and the floors on the same evaluation seeds.

    python -m experiments.learning_curves                    # results/benchmark/runs/bppo-* -> PNG + MD
    python -m experiments.learning_curves --runs runs/my-run --out results/tmp/curves.png

Each run's ``eval.csv`` holds, every million steps, the steady-state (t >= 10 s) true-reference
error over its fixed evaluation seeds (990,000-990,031 by default, 500-531 for runs made before
those were held out). On each run's own seeds and tier this script scores the best classical
controllers (PROPOSED_KF_DOB and MPC; on a Leader tier also the generic PROPOSED_IMM_DOB) and
computes the oracle-parameter floor (agents/benchmark/floors.py: the Kalman floor on the v1 tiers, the
Bayes particle floor on the Leader tiers, cached in results/tmp/bench-cache), and draws them as
horizontal lines: a curve that flattens above them has converged to something worse; one still
falling was stopped early.
Writes the PNG and a Markdown table (final IQM per run, steps, wall-clock minutes). Runs trained
with ``env_kwargs`` (ablations on a changed env, e.g. results/spin_ablation_hard.md's) are skipped:
the id's references are not theirs.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from experiments.outputs import output_path, write_report

RUNS = Path("results/benchmark/runs")
OUT = Path("results/benchmark/learning_curves_bppo.png")
BASELINES = ("PROPOSED_KF_DOB", "MPC")
#: where the Leader tiers' particle floors are cached (the leaderboard's --cache: computed once per seed set)
FLOOR_CACHE = Path("results/tmp/bench-cache")


def _iqm(x: np.ndarray) -> float:
    x = np.sort(np.asarray(x, dtype=float))
    n = len(x)
    lo, hi = int(np.floor(0.25 * n)), int(np.ceil(0.75 * n))
    return float(x[lo:hi].mean())


def _runs(paths: list[Path]) -> list[Path]:
    out = []
    for p in paths:
        if (p / "eval.csv").is_file():
            out.append(p)
        elif p.is_dir():
            out += sorted(q for q in p.iterdir() if (q / "eval.csv").is_file() and q.name.startswith("bppo"))
    return out


def references(env_id: str, seeds: list[int]) -> dict[str, float]:
    """IQM of the steady-state error of the best classical controllers and the oracle-parameter floor's
    expected error on ``seeds`` (training-range seeds only)."""
    import gymnasium as gym

    from agents.benchmark import floors
    from auv_follow_env.tiers import LEADER_TIERS, TIERS, check_training_seeds
    from controllers import make_controller
    from controllers.evaluation import evaluate_batched

    check_training_seeds(seeds, name="evaluation seeds")
    spec = gym.make(env_id).unwrapped.task_spec
    tier = env_id[len("AUVFollow-"):].rsplit("-", 1)[0]
    names = BASELINES if tier in TIERS else BASELINES + ("PROPOSED_IMM_DOB",)  # a Leader tier: the generic IMM too
    df = evaluate_batched([make_controller(n, spec) for n in names], env_id, seeds=seeds, progress=False)
    out = {n: _iqm(df.loc[df["policy"] == n, "true_steady_mean"].to_numpy()) for n in names}
    if tier in TIERS:
        inf = floors.information_floor(tier, seeds)
    elif tier in LEADER_TIERS:  # the Bayes floor (particle filter under the true generator), cached
        inf = floors.leader_floor(tier, seeds, cache_dir=FLOOR_CACHE, progress=True)
    else:
        return out
    out["oracle-parameter floor"] = _iqm(inf["expected_steady_mean"].dropna().to_numpy())
    return out


def with_parent_curve(run_dir: Path, run: dict, ev: pd.DataFrame) -> pd.DataFrame:
    """A resumed run's curve preceded by the run it was resumed from (``run.resume_from``: a
    model in another run directory, looked up beside this one by name), so a fine-tune is drawn
    from step 0; the rows of the parent before the resume point."""
    src = run.get("resume_from")
    if not src:
        return ev
    parent = run_dir.parent / Path(str(src)).parent.name
    if Path(str(src)).parent.name == "checkpoints" or not (parent / "eval.csv").is_file():
        return ev
    before = pd.read_csv(parent / "eval.csv")
    before = before[before["steps"] < ev["steps"].min()] if len(ev) else before
    return pd.concat([before, ev], ignore_index=True)


def method_name(run_name: str) -> str:
    """A run's method: its directory name without the training-seed suffix ``-s<k>``
    (``bppo-Easy-scratch-priv-s2`` -> ``bppo-Easy-scratch-priv``)."""
    import re

    return re.sub(r"-s\d+$", "", run_name)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--runs", type=Path, nargs="+", default=[RUNS], help="run directories or folders of runs "
                   "(default %(default)s)")
    p.add_argument("--out", type=Path, default=None, help=f"PNG output (default {OUT}; the .md beside it)")
    args = p.parse_args(argv)
    runs = _runs(args.runs)
    if not runs:
        print(f"--runs: no bppo run directory with an eval.csv under {[str(r) for r in args.runs]}", file=sys.stderr)
        return 2
    out = output_path(args, p, OUT)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    info = []
    for r in runs:
        cfg = yaml.safe_load((r / "config.yaml").read_text())
        run = cfg.get("run", {})
        if run.get("env_kwargs"):  # (an ablation on a changed env: the id's references would not be its own)
            print(f"skipped {r.name}: trained on {run.get('env_id')} with env_kwargs {run['env_kwargs']}",
                  file=sys.stderr)
            continue
        ev = with_parent_curve(r, run, pd.read_csv(r / "eval.csv"))
        seeds = cfg.get("eval_seeds", [500, 531])
        info.append({"run": r, "env": run.get("env_id"), "mode": run.get("mode"), "cfg": cfg, "eval": ev,
                     "seeds": list(range(int(seeds[0]), int(seeds[-1]) + 1))})
    if not info:
        print("--runs: every run was trained on a changed env (env_kwargs): nothing to draw", file=sys.stderr)
        return 2
    envs = list(dict.fromkeys(i["env"] for i in info))
    fig, axes = plt.subplots(len(envs), 1, figsize=(10.0, 4.6 * len(envs)), squeeze=False)
    axes = axes.T
    lines = ["# Learning curves of the batched-PPO runs", "",
             f"`python -m experiments.learning_curves` ({__doc__.splitlines()[0]})", "",
             "Steady-state true-reference error, IQM over each run's evaluation seeds (training range); the "
             "references are scored on the same seeds.", "",
             "| run | env | mode | observation | steps | wall clock [min] | first IQM [m] | final IQM [m] "
             "| best classical on these seeds [m] | oracle-parameter floor [m] |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for ax, env in zip(axes[0], envs, strict=True):
        mine = [i for i in info if i["env"] == env]
        # references on each run's own evaluation seeds (runs of different versions use different ones)
        ref_sets = {tuple(i["seeds"]): references(env, i["seeds"]) for i in mine}
        groups: dict[str, list[dict]] = {}
        for i in mine:
            groups.setdefault(method_name(i["run"].name), []).append(i)
        for k, (method, members) in enumerate(groups.items()):
            color = plt.get_cmap("tab20")(k % 20) if len(groups) > 10 else f"C{k % 10}"
            curves = []
            for i in members:
                ev = i["eval"]
                y = ev["true_steady_iqm_m"].replace(np.inf, np.nan)
                ax.plot(ev["steps"] / 1e6, y, color=color, lw=0.8, alpha=0.45)
                curves.append(pd.Series(y.to_numpy(), index=ev["steps"].to_numpy()))
            if len(curves) > 1:  # the median over training seeds where they all have a point
                both = pd.concat(curves, axis=1).dropna()
                ax.plot(both.index / 1e6, both.median(axis=1), color=color, lw=2.0, marker="o", ms=3,
                        label=f"{method} (median of {len(curves)} seeds)")
            else:
                ax.plot(curves[0].index / 1e6, curves[0].to_numpy(), color=color, lw=2.0, marker="o", ms=3,
                        label=f"{method} (1 seed)")
        for i in mine:
            ev = i["eval"]
            y = ev["true_steady_iqm_m"].replace(np.inf, np.nan)
            label = i["run"].name
            cfg = i["cfg"]
            refs = ref_sets[tuple(i["seeds"])]
            best = min(v for n, v in refs.items() if n != "oracle-parameter floor")
            floor = f"{refs['oracle-parameter floor']:.4f}" if "oracle-parameter floor" in refs else "-"
            lines.append(f"| {label} | {env} | {i['mode']} | {cfg.get('run', {}).get('observation', '-')} "
                         f"| {int(cfg.get('steps_done', ev['steps'].iloc[-1])):,} "
                         f"| {float(cfg.get('train_seconds', 0.0)) / 60:.0f} | {y.iloc[0]:.4f} | {y.iloc[-1]:.4f} "
                         f"| {best:.4f} | {floor} |")
        styles = {"PROPOSED_KF_DOB": ("k", "--"), "MPC": ("k", "-."), "oracle-parameter floor": ("0.45", ":"),
                  "PROPOSED_IMM_DOB": ("0.3", (0, (1, 1)))}
        for seeds, refs in ref_sets.items():
            where = f", seeds {seeds[0]}-{seeds[-1]}" if len(ref_sets) > 1 else ""
            for name, v in refs.items():
                c, ls = styles[name]
                ax.axhline(v, color=c, ls=ls, lw=1.2, label=f"{name} {v:.4f} m{where}")
        ax.set_yscale("log")
        ax.set_xlabel("training env steps [millions]")
        ax.set_ylabel("steady-state error, IQM over eval seeds [m]")
        ax.set_title(env, fontsize=10)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5))
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110, bbox_inches="tight")
    plt.close(fig)
    write_report(out.with_suffix(".md"), "\n".join(lines) + f"\n\n![curves]({out.name})\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
