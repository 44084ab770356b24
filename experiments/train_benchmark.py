"""Benchmark: a residual agent on top of PROPOSED vs the paper's controllers and a
from-scratch agent, in AUVFollow-S4-v0, on a wall-clock training budget.

Stages (run one training at a time on a 2-core machine)::

    python experiments/train_benchmark.py --stage residual   # <= --minutes of training
    python experiments/train_benchmark.py --stage scratch    # same algorithm, no base controller
    python experiments/train_benchmark.py --stage report     # evaluate + write results/agents/

``--stage all`` runs the three in sequence. Runs go to ``results/agents/runs/<name>/``;
the report evaluates the most recent residual and scratch runs (or ``--residual-run`` /
``--scratch-run``) together with PID, ROBUST_ONLY, PRED_ONLY and PROPOSED on the held-out
test seeds, and writes ``benchmark.md``, ``benchmark.csv`` (summary), ``benchmark_episodes.csv``,
``benchmark.png`` and ``learning_curves.png``.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from agents.benchmark.compare import compare, plot_learning_curves, summary_markdown
from agents.training.config import TrainConfig
from agents.training.loading import load_agent
from agents.training.rundir import versions
from agents.training.runner import train
from experiments.outputs import output_path


@dataclass
class Args:
    stage: str = "all"  #: residual | scratch | report | all
    algo: str = "ppo"  #: algorithm for both agents
    env_id: str = "AUVFollow-S4-v0"  #: benchmark scenario
    minutes: float = 20.0  #: wall-clock training budget per agent [min]
    scratch_minutes: float | None = None  #: budget of the from-scratch agent (None: --minutes)
    max_timesteps: int = 20_000_000  #: step cap (the wall clock normally stops first)
    residual_seed: int = 0  #: training seed of the residual agent (training envs: seed + i)
    scratch_seed: int = 1  #: training seed of the from-scratch agent
    test_seeds: list[int] = field(default_factory=lambda: list(range(1000, 1010)))  #: held-out seeds
    out: str = "results/agents"  #: report directory (runs in <out>/runs)
    residual_run: str | None = None  #: run directory to report (default: newest residual run)
    scratch_run: str | None = None  #: run directory to report (default: newest scratch run)
    progress: bool = True  #: progress bars


def parse(argv: list[str] | None = None) -> Args:
    d = Args()
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--stage", choices=["residual", "scratch", "report", "all"], default=d.stage)
    p.add_argument("--algo", choices=["ppo", "sac", "td3"], default=d.algo)
    p.add_argument("--env-id", default=d.env_id)
    p.add_argument("--minutes", type=float, default=d.minutes)
    p.add_argument("--scratch-minutes", type=float, default=None)
    p.add_argument("--max-timesteps", type=int, default=d.max_timesteps)
    p.add_argument("--residual-seed", type=int, default=d.residual_seed)
    p.add_argument("--scratch-seed", type=int, default=d.scratch_seed)
    p.add_argument("--test-seeds", type=int, nargs="+", default=d.test_seeds)
    p.add_argument("--out", default=None,
                   help="report directory, runs in <out>/runs (default: results/agents; results/tmp/agents with "
                        "non-default settings)")
    p.add_argument("--residual-run", default=None)
    p.add_argument("--scratch-run", default=None)
    p.add_argument("--no-progress", dest="progress", action="store_false")
    a = p.parse_args(argv)
    a.out = str(output_path(a, p, Path(d.out), ignore=("progress", "stage")))
    return Args(**vars(a))


def _train(args: Args, mode: str) -> Path:
    minutes = args.minutes if mode == "residual" or args.scratch_minutes is None else args.scratch_minutes
    cfg = TrainConfig(algo=args.algo, env_id=args.env_id, mode=mode, total_timesteps=args.max_timesteps,
                      max_minutes=minutes, seed=args.residual_seed if mode == "residual" else args.scratch_seed,
                      out_dir=str(Path(args.out) / "runs"), checkpoint_freq=500_000, eval_freq=200_000,
                      eval_episodes=3, progress_bar=args.progress)
    run = train(cfg)
    print(f"{mode}: {run}")
    return run


def _newest(args: Args, mode: str) -> Path | None:
    runs = sorted((Path(args.out) / "runs").glob(f"{args.algo}-{args.env_id}-{mode}-seed*"),
                  key=lambda p: p.stat().st_mtime)
    runs = [r for r in runs if (r / "model.zip").is_file()]
    return runs[-1] if runs else None


def report(args: Args) -> None:
    out = Path(args.out)
    runs = {"residual": Path(args.residual_run) if args.residual_run else _newest(args, "residual"),
            "scratch": Path(args.scratch_run) if args.scratch_run else _newest(args, "scratch")}
    runs = {k: v for k, v in runs.items() if v is not None}
    agents = [load_agent(r) for r in runs.values()]
    episodes, summary = compare(agents, args.env_id, args.test_seeds, progress=args.progress)
    out.mkdir(parents=True, exist_ok=True)
    episodes.to_csv(out / "benchmark_episodes.csv", index=False)
    summary.to_csv(out / "benchmark.csv")
    from agents.benchmark.compare import plot_summary

    plot_summary(episodes, out / "benchmark.png", title=f"{args.env_id}, test seeds {args.test_seeds[0]}-"
                 f"{args.test_seeds[-1]}")
    proposed_return = float(episodes.loc[episodes.policy == "PROPOSED", "return"].mean())
    plot_learning_curves({f"{k} ({agents[i].name})": r for i, (k, r) in enumerate(runs.items())},
                         out / "learning_curves.png", baseline={"PROPOSED (test seeds)": proposed_return})
    lines = ["# Residual RL benchmark (AUVFollow-S4-v0)", "",
             summary_markdown(summary, args.env_id, args.test_seeds), ""]
    if "residual" in runs and "PROPOSED" in summary.index:
        res_name = agents[0].name
        chg = float(summary.loc[res_name, "true_steady_mean_change_pct"])
        goal = "met" if chg <= -30.0 else "NOT met"
        lines += [f"Goal (>= 30 % lower steady-state mean true error than PROPOSED): **{goal}** ({chg:+.1f} %).",
                  ""]
    if "residual" in runs:
        lines += _transfer(args, load_agent(runs["residual"]))
    lines += ["## Training runs", "", "| run | algo | mode | seed | steps | wall clock (s) | steps/s |",
              "|---|---|---|---|---|---|---|"]
    for k, r in runs.items():
        cfg = yaml.safe_load(open(r / "config.yaml"))
        res = cfg.get("result", {})
        lines.append(f"| {r.name} | {cfg['run']['algo']} | {k} | {cfg['run']['seed']} | {res.get('num_timesteps')} | "
                     f"{res.get('wall_clock_s')} | {res.get('steps_per_s')} |")
        if cfg.get("residual"):
            lines.append(f"|  residual settings | {cfg['residual']} ||||||")
    v = versions()
    lines += ["", "## Reproduce", "", "```",
              f"python experiments/train_benchmark.py --stage residual --minutes {args.minutes}",
              f"python experiments/train_benchmark.py --stage scratch --minutes {args.minutes}"
              + (f" --scratch-minutes {args.scratch_minutes}" if args.scratch_minutes else ""),
              "python experiments/train_benchmark.py --stage report", "```", "",
              f"Training seeds: residual {args.residual_seed}, scratch {args.scratch_seed} (training env i "
              f"is seeded seed + i, later episodes continue its generator); EvalCallback seed 500; held-out test "
              f"seeds {args.test_seeds}. Hyperparameters: agents/training/hyperparams/{args.algo}.yml "
              "(resolved copy in "
              "each run's config.yaml).", "",
              "Versions: " + ", ".join(f"{k} {val}" for k, val in v.items()), "",
              "![benchmark](benchmark.png)", "", "![learning curves](learning_curves.png)", ""]
    (out / "benchmark.md").write_text("\n".join(lines))
    print("\n".join(lines[:len(summary) + 6]))


#: out-of-distribution checks of the S4-trained residual agent: (label, env id, overrides)
TRANSFER_CASES = (("S4, delay 1.0 s", "AUVFollow-S4-v0", {"delay_s": 1.0}),
                  ("S4, disturbance L1", "AUVFollow-S4-v0", {"disturbance": "L1"}),
                  ("S3 (tau 1.5 s, other manoeuvre periods)", "AUVFollow-S3-v0", {}))


def _transfer(args: Args, agent) -> list[str]:
    """The residual agent outside its training scenario, against PROPOSED (same seeds)."""
    seeds = args.test_seeds[:5]
    lines = ["## Outside the training scenario", "",
             f"The residual agent trained on {args.env_id}, evaluated unchanged elsewhere (test seeds {seeds}); "
             "steady-state mean error to the true reference [m].", "",
             "| case | PROPOSED | residual agent | change (%) |", "|---|---|---|---|"]
    for label, env_id, kw in TRANSFER_CASES:
        _, s = compare([agent], env_id, seeds, controllers=["PROPOSED"], env_kwargs=kw or None,
                       progress=False)
        p, r = s.loc["PROPOSED", "true_steady_mean"], s.loc[agent.name, "true_steady_mean"]
        lines.append(f"| {label} | {p:.4f} | {r:.4f} | {100 * (r / p - 1):+.1f} |")
    return lines + [""]


def main(argv: list[str] | None = None) -> None:
    args = parse(argv)
    if args.stage in ("residual", "all"):
        _train(args, "residual")
    if args.stage in ("scratch", "all"):
        _train(args, "scratch")
    if args.stage in ("report", "all"):
        report(args)


if __name__ == "__main__":
    main()
