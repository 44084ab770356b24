"""RL baselines that generalise: train on a v1 tier's training
distribution, never on its test seeds, on a wall-clock budget per run.

    python experiments/train_tiers.py --method ppo-scratch --seed 0 --minutes 12
    python experiments/train_tiers.py --method recurrentppo-scratch --seed 0 --minutes 12
    python experiments/train_tiers.py --method ppo-residual --seed 0 --minutes 12 --controller PROPOSED_KF_DOB
    python experiments/train_tiers.py --stage curves            # learning curves of every run

Runs go to ``results/benchmark/runs/<method>/<algo>-<tier>-<mode>-seed<k>/``. Training env i of
a run starts from seed ``seed + i`` (each later episode continues its own generator and draws
a new condition from the tier's distribution); the EvalCallback uses seed 500. Both are
checked against the tier's test-seed limit (``auv_follow_env.check_training_seeds``): every
published test seed is >= 1 000 000. The leaderboard then scores the runs of a method as one
policy (its runs are the strata) with ``auv-follow benchmark``.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np

METHODS = {  # method -> (algo, mode, vec)
    "ppo-scratch": ("ppo", "scratch", "native"),
    "recurrentppo-scratch": ("recurrentppo", "scratch", "native"),
    "ppo-residual": ("ppo", "residual", "dummy"),
}


@dataclass
class Args:
    stage: str = "train"  #: train (one run) | curves (learning-curve figure of every run)
    method: str = "ppo-scratch"  #: one of METHODS
    tier: str = "Hard"  #: training distribution (a v1 tier)
    seed: int = 0  #: training seed (envs seed + i)
    minutes: float = 12.0  #: wall-clock budget [min]
    max_timesteps: int = 50_000_000  #: step cap (the wall clock stops first)
    controller: str = "PROPOSED"  #: base controller of a residual agent
    out: str = "results/benchmark/runs"  #: parent of the method directories
    eval_freq: int = 100_000  #: env steps between EvalCallback evaluations (learning curve)


def parse(argv: list[str] | None = None) -> Args:
    d = Args()
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--stage", choices=["train", "curves"], default=d.stage)
    p.add_argument("--method", choices=list(METHODS), default=d.method)
    p.add_argument("--tier", default=d.tier)
    p.add_argument("--seed", type=int, default=d.seed)
    p.add_argument("--minutes", type=float, default=d.minutes)
    p.add_argument("--max-timesteps", type=int, default=d.max_timesteps)
    p.add_argument("--controller", default=d.controller)
    p.add_argument("--out", default=d.out)
    p.add_argument("--eval-freq", type=int, default=d.eval_freq)
    return Args(**vars(p.parse_args(argv)))


def train_one(args: Args) -> Path:
    from agents.benchmark.protocol import resolve_tier
    from agents.training.config import TrainConfig
    from agents.training.runner import train

    algo, mode, vec = METHODS[args.method]
    _, env_id = resolve_tier(args.tier)
    cfg = TrainConfig(algo=algo, env_id=env_id, mode=mode, vec=vec, controller=args.controller,
                      total_timesteps=args.max_timesteps, max_minutes=args.minutes, seed=args.seed,
                      out_dir=str(Path(args.out) / args.method), run_name=f"{algo}-{args.tier}-{mode}-seed{args.seed}",
                      checkpoint_freq=0, eval_freq=args.eval_freq, eval_episodes=3, tensorboard=False)
    run = train(cfg)
    print(f"{args.method} seed {args.seed}: {run}")
    return run


def plot_curves(root: str | Path, path: str | Path) -> None:
    """EvalCallback mean return (3 episodes at seed 500) against env steps, one panel per method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    methods = sorted(p for p in Path(root).iterdir() if p.is_dir())
    fig, axes = plt.subplots(1, max(len(methods), 1), figsize=(4.5 * max(len(methods), 1), 3.5), squeeze=False)
    for ax, m in zip(axes[0], methods, strict=False):
        for run in sorted(m.iterdir()):
            f = run / "eval" / "evaluations.npz"
            if f.is_file():
                d = np.load(f)
                ax.plot(d["timesteps"], d["results"].mean(axis=1), marker=".", label=run.name.split("-")[-1])
        ax.set_title(m.name)
        ax.set_xlabel("env steps")
        ax.set_ylabel("eval return (3 episodes)")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    args = parse(argv)
    if args.stage == "train":
        train_one(args)
    else:
        out = Path(args.out).parent / "learning_curves.png"
        plot_curves(args.out, out)
        print(out)


if __name__ == "__main__":
    main()
