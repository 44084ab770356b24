"""``auv-follow``: train, evaluate and compare agents on AUVFollow.

Examples::

    auv-follow train --algo ppo --env AUVFollow-S4-v0 --mode residual --timesteps 2000000 --max-minutes 20
    auv-follow train --algo sac --mode scratch --timesteps 100000 --env-kwarg disturbance=L1
    auv-follow train --algo ppo --resume runs/<run>/checkpoints/model_500000_steps.zip --timesteps 3000000
    auv-follow evaluate runs/<run> --seeds 1000-1009
    auv-follow compare runs/<run-a> runs/<run-b> --seeds 1000-1009 --out results/compare
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import yaml

import auv_follow_env
from agents.residual import DEFAULT_CONTROLLER, DEFAULT_HISTORY_LEN, DEFAULT_HISTORY_STRIDE, DEFAULT_SCALE
from agents.train import ALGOS, MODES, TrainConfig

__all__ = ["main", "build_parser"]


def _positive_int(text: str) -> int:
    try:
        v = int(float(text))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if v <= 0 or v != float(text):
        raise argparse.ArgumentTypeError(f"{text!r} is invalid: must be a positive integer")
    return v


def _positive_float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not v > 0:
        raise argparse.ArgumentTypeError(f"{text!r} is invalid: must be > 0")
    return v


def _seeds(text: str) -> list[int]:
    """``"1000-1009"``, ``"1,2,5"`` or ``"7"``."""
    out: list[int] = []
    try:
        for part in text.split(","):
            if "-" in part.strip()[1:]:
                a, b = part.split("-")
                out.extend(range(int(a), int(b) + 1))
            else:
                out.append(int(part))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a seed list: use e.g. 1000-1009 or 1,2,3") from None
    if not out or min(out) < 0:
        raise argparse.ArgumentTypeError(f"{text!r} gives no non-negative seeds")
    return out


def _key_value(text: str) -> tuple[str, Any]:
    if "=" not in text:
        raise argparse.ArgumentTypeError(f"{text!r} is not key=value")
    k, v = text.split("=", 1)
    return k.strip(), yaml.safe_load(v)


def build_parser() -> argparse.ArgumentParser:
    from controllers import ALL_CONTROLLERS

    p = argparse.ArgumentParser(prog="auv-follow", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="command", required=True)

    t = sub.add_parser("train", help="train a PPO/SAC/TD3 agent (from scratch or residual)")
    t.add_argument("--algo", choices=ALGOS, default="ppo")
    t.add_argument("--env", dest="env_id", choices=auv_follow_env.ENV_IDS, default="AUVFollow-S4-v0")
    t.add_argument("--env-kwarg", dest="env_kwargs", type=_key_value, action="append", default=[],
                   metavar="KEY=VALUE", help="scenario override for gym.make (repeatable), e.g. disturbance=L1")
    t.add_argument("--mode", choices=MODES, default="residual")
    t.add_argument("--controller", choices=ALL_CONTROLLERS, default=DEFAULT_CONTROLLER,
                   help="base controller of a residual agent (the paper's four, or ours: PROPOSED_KF, "
                        "PROPOSED_KF_DOB, MPC)")
    t.add_argument("--scale", type=_positive_float, default=DEFAULT_SCALE,
                   help="residual authority as a fraction of the force limits")
    t.add_argument("--history-len", type=int, default=DEFAULT_HISTORY_LEN)
    t.add_argument("--history-stride", type=_positive_int, default=DEFAULT_HISTORY_STRIDE)
    t.add_argument("--no-base-action", dest="include_base_action", action="store_false")
    t.add_argument("--timesteps", dest="total_timesteps", type=_positive_int, default=None,
                   help="total env steps (default: n_timesteps of the hyperparameter YAML)")
    t.add_argument("--max-minutes", type=_positive_float, default=None, help="wall-clock budget [min]")
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--n-envs", type=_positive_int, default=None)
    t.add_argument("--vec", choices=("dummy", "native"), default="dummy",
                   help="training VecEnv: SB3 DummyVecEnv of single envs, or the native batched env "
                        "(one kernel call for all envs; scratch mode only)")
    t.add_argument("--out", dest="out_dir", default="runs", help="parent directory of the run directory")
    t.add_argument("--run-name", default=None)
    t.add_argument("--checkpoint-freq", type=int, default=100_000, help="env steps between checkpoints (0: none)")
    t.add_argument("--eval-freq", type=int, default=50_000, help="env steps between evaluations (0: none)")
    t.add_argument("--eval-episodes", type=_positive_int, default=3)
    t.add_argument("--resume", dest="resume_from", default=None, help="checkpoint/model .zip to continue")
    t.add_argument("--hyperparams", dest="hyperparams_file", default=None, help="rl-zoo3-format YAML file")
    t.add_argument("--hp", dest="hyperparams", type=_key_value, action="append", default=[], metavar="KEY=VALUE",
                   help="override a hyperparameter (repeatable), e.g. learning_rate=1e-4")
    t.add_argument("--no-progress", dest="progress_bar", action="store_false")
    t.add_argument("--no-tensorboard", dest="tensorboard", action="store_false")
    t.add_argument("-v", "--verbose", type=int, default=0)

    e = sub.add_parser("evaluate", help="evaluate a saved agent on test seeds")
    e.add_argument("model", help="run directory or model .zip")
    e.add_argument("--env", dest="env_id", choices=auv_follow_env.ENV_IDS, default=None,
                   help="env id (default: the one the agent was trained on)")
    e.add_argument("--seeds", type=_seeds, default=list(range(1000, 1010)))
    e.add_argument("--out", default=None, help="CSV file for the per-episode metrics")
    e.add_argument("--no-progress", dest="progress", action="store_false")

    c = sub.add_parser("compare", help="agents and scripted controllers in one table and plot")
    c.add_argument("models", nargs="*", help="run directories or model .zip files")
    c.add_argument("--env", dest="env_id", choices=auv_follow_env.ENV_IDS, default="AUVFollow-S4-v0")
    c.add_argument("--env-kwarg", dest="env_kwargs", type=_key_value, action="append", default=[],
                   metavar="KEY=VALUE")
    c.add_argument("--seeds", type=_seeds, default=list(range(1000, 1010)))
    c.add_argument("--controllers", nargs="*", choices=ALL_CONTROLLERS, default=list(ALL_CONTROLLERS),
                   help="scripted controllers to include (default: the paper's four and ours)")
    c.add_argument("--out", default="results/compare", help="directory for compare.csv/.md/.png")
    c.add_argument("--name", default="compare")
    c.add_argument("--no-progress", dest="progress", action="store_false")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``auv-follow`` console script."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        if args.command == "train":
            from agents.train import train

            kw = vars(args).copy()
            kw.pop("command")
            kw["env_kwargs"] = dict(kw["env_kwargs"])
            kw["hyperparams"] = dict(kw["hyperparams"])
            kw["tensorboard"] = kw["tensorboard"]
            run = train(TrainConfig(**kw))
            print(f"run directory: {run}")
        elif args.command == "evaluate":
            from agents.train import evaluate_agent, load_agent

            agent = load_agent(args.model)
            df = evaluate_agent(agent, args.seeds, env_id=args.env_id, progress=args.progress)
            cols = ["policy", "seed", "true_steady_mean", "true_steady_rmse", "true_full_mean", "return"]
            print(df[cols].to_string(index=False))
            print(f"mean true steady-state mean error: {df['true_steady_mean'].mean():.4f} m")
            if args.out:
                Path(args.out).parent.mkdir(parents=True, exist_ok=True)
                df.to_csv(args.out, index=False)
        else:
            from agents.compare import compare, summary_markdown

            _, summary = compare(args.models, args.env_id, args.seeds, controllers=args.controllers,
                                 env_kwargs=dict(args.env_kwargs) or None, out_dir=args.out, name=args.name,
                                 progress=args.progress)
            print(summary_markdown(summary, args.env_id, args.seeds))
    except (ValueError, FileNotFoundError) as exc:
        parser.error(str(exc))
    return 0


if __name__ == "__main__":
    sys.exit(main())
