"""Evaluate the paper's controllers on a scenario and print one row per policy.

    python examples/evaluate_controller.py                 # 20 seeds of AUVFollow-S4-v0
    python examples/evaluate_controller.py --seeds 4 --env-id AUVFollow-Hard-v1

All policies run in one batch through the native vector env (``evaluate_batched``); the
score is the steady-state (t >= 10 s) distance to the true reference point [m].
"""

from __future__ import annotations

import argparse

import gymnasium as gym

import auv_follow_env  # noqa: F401  (registers the ids)
from controllers import CONTROLLERS, make_controller
from controllers.evaluation import evaluate_batched


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env-id", default="AUVFollow-S4-v0", help="a registered AUVFollow id")
    parser.add_argument("--seeds", type=int, default=20, help="number of seeds, from 0 (training range)")
    args = parser.parse_args(argv)
    if args.seeds < 1:
        parser.error(f"--seeds {args.seeds}: must be at least 1")
    env = gym.make(args.env_id)                         # the env's task spec builds matching controllers
    spec = env.unwrapped.task_spec
    env.close()
    policies = [make_controller(name, spec) for name in CONTROLLERS]
    df = evaluate_batched(policies, args.env_id, seeds=range(args.seeds), progress=False)
    table = df.groupby("policy", sort=False)[["true_steady_mean", "own_steady_mean"]].mean()
    print(f"{args.env_id}, {args.seeds} seeds, steady-state mean error [m]:")
    print(table.round(4).to_string())


if __name__ == "__main__":
    main()
