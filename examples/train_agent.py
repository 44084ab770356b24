"""Train a batched-PPO agent (``algo="bppo"``) with a budget you choose, then score it.

    python examples/train_agent.py                      # 200,000 steps on AUVFollow-Easy-v1
    python examples/train_agent.py --timesteps 4096     # a smoke test: a few seconds

The run directory (model, observation statistics, config.yaml) goes to ``--out`` (default:
a new temporary folder); ``auv-follow evaluate <run>`` and ``auv-follow benchmark`` take it too.
Training and evaluation use training-range seeds only (below 1,000,000): the tiers' test seeds
are for the leaderboard.
"""

from __future__ import annotations

import argparse
import tempfile

from agents.training.config import TrainConfig
from agents.training.loading import evaluate_agent, load_agent
from agents.training.runner import train


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env-id", default="AUVFollow-Easy-v1")
    parser.add_argument("--timesteps", type=int, default=200_000, help="env steps to train (budget)")
    parser.add_argument("--out", default=None, help="folder for the run directory (default: a temporary one)")
    args = parser.parse_args(argv)
    out = args.out if args.out is not None else tempfile.mkdtemp(prefix="auv-follow-runs-")
    cfg = TrainConfig(algo="bppo", env_id=args.env_id, mode="scratch", total_timesteps=args.timesteps, seed=0,
                      n_envs=64, hyperparams={"n_steps": 32}, out_dir=out, eval_freq=0, checkpoint_freq=0,
                      final_eval=False, progress_bar=False, tensorboard=False)
    run_dir = train(cfg)                                 # refuses bad settings before creating anything
    agent = load_agent(run_dir)
    df = evaluate_agent(agent, seeds=[500, 501], progress=False)
    print(f"run directory: {run_dir}")
    print(df[["policy", "seed", "true_steady_mean"]].to_string(index=False))


if __name__ == "__main__":
    main()
