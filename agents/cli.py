"""``auv-follow``: train, evaluate and compare agents on AUVFollow.

Examples::

    auv-follow train --algo ppo --env AUVFollow-S4-v0 --mode residual --timesteps 2000000 --max-minutes 20
    auv-follow train --algo sac --mode scratch --timesteps 100000 --env-kwarg disturbance=L1
    auv-follow train --algo ppo --resume runs/<run>/checkpoints/model_500000_steps.zip --timesteps 3000000
    auv-follow evaluate runs/<run> --seeds 1000-1009
    auv-follow compare runs/<run-a> runs/<run-b> --seeds 1000-1009 --out results/tmp/compare

Every setting is checked before any work starts or any directory is created; a bad one ends
with a one-line error naming the argument (exit code 2). Ctrl-C during training saves the
model and its statistics and exits with code 130.

Trust: run directories and model files from others must be trusted like code. Evaluation
reads the observation statistics from plain JSON (``vecnormalize.json``), but an SB3
``model.zip`` can hold pickled objects, and ``--resume`` unpickles ``vecnormalize.pkl``.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import yaml

import auv_follow_env
from agents._cli_errors import _check_writable, _Refused
from agents.training.config import ALGOS, MAX_N_ENVS, MODES, ConfigError, TrainConfig, TrainingInterrupted
from agents.training.history import DEFAULT_CONTROLLER, DEFAULT_HISTORY_LEN, DEFAULT_HISTORY_STRIDE, DEFAULT_SCALE
from auv_follow_env._signals import exit_code, stop_name, stop_on_signals

__all__ = ["main", "build_parser"]

#: every registered id: the paper's v0 scenarios and the v1 acoustic-link tiers
ENV_CHOICES: tuple[str, ...] = auv_follow_env.ENV_IDS + auv_follow_env.ENV_IDS_V1

#: TrainConfig field -> command-line flag (for errors found after parsing)
FLAGS: dict[str, str] = {
    "algo": "--algo", "env_id": "--env", "env_kwargs": "--env-kwarg", "mode": "--mode", "controller": "--controller",
    "scale": "--scale", "include_base_action": "--no-base-action", "history_len": "--history-len",
    "history_stride": "--history-stride", "total_timesteps": "--timesteps", "max_minutes": "--max-minutes",
    "seed": "--seed", "n_envs": "--n-envs", "vec": "--vec", "out_dir": "--out", "run_name": "--run-name",
    "checkpoint_freq": "--checkpoint-freq", "eval_freq": "--eval-freq", "eval_episodes": "--eval-episodes",
    "eval_seed": "--eval-seed", "resume_from": "--resume", "hyperparams_file": "--hyperparams",
    "hyperparams": "--hp", "verbose": "--verbose", "observation": "--obs"}

#: where ``auv-follow benchmark`` writes without --out (ignored by git, like experiments/outputs.py's scratch)
SCRATCH_BENCH = "results/tmp/benchmark"

_TRUST = ("Run directories and model files from others must be trusted like code: an SB3 model.zip can hold "
          "pickled objects (and --resume unpickles vecnormalize.pkl). Evaluation reads the observation statistics "
          "only from vecnormalize.json.")


class _Formatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """Keeps the description's line breaks and shows every argument's default (not for on/off
    flags such as ``--no-progress``, where "default: True" would read as the flag's state, nor
    where the help text already says the default)."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        if action.nargs == 0 or "(default" in (action.help or ""):
            return action.help
        return super()._get_help_string(action)


def _integer(text: str, lo: int, hi: float = math.inf) -> int:
    try:
        f = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if not math.isfinite(f) or not f.is_integer() or not lo <= f <= hi:
        bound = f">= {lo}" if hi == math.inf else f"in [{lo}, {hi:g}]"
        raise argparse.ArgumentTypeError(f"{text!r} is invalid: must be an integer {bound}")
    return int(f)


def _positive_int(text: str) -> int:
    return _integer(text, 1)


def _nonneg_int(text: str) -> int:
    return _integer(text, 0)


def _n_envs(text: str) -> int:
    return _integer(text, 1, MAX_N_ENVS)


def _positive_float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not (math.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"{text!r} is invalid: must be a finite number > 0")
    return v


MAX_SEEDS = 100_000  #: bound of the number of seeds of one --seeds argument
MAX_SEED = 2**63 - 1  #: largest seed (the result tables store 64-bit integers; controllers.evaluation.MAX_SEED)


def _seeds(text: str) -> list[int]:
    """``"1000-1009"``, ``"1,2,5"`` or ``"7"``."""
    out: list[int] = []
    try:
        for part in text.split(","):
            if "-" in part.strip()[1:]:
                a, b = part.split("-")
                a, b = int(a), int(b)
                if b - a >= MAX_SEEDS:
                    raise argparse.ArgumentTypeError(f"{text!r} gives more than {MAX_SEEDS} seeds")
                out.extend(range(a, b + 1))
            else:
                out.append(int(part))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a seed list: use e.g. 1000-1009 or 1,2,3") from None
    if not out or min(out) < 0 or len(out) > MAX_SEEDS:
        raise argparse.ArgumentTypeError(f"{text!r} gives no seeds or a negative one: use e.g. 1000-1009 or 1,2,3")
    if max(out) > MAX_SEED:
        raise argparse.ArgumentTypeError(f"{text!r} has seed {max(out)}: seeds must be in [0, 2**63 - 1] "
                                         f"(= {MAX_SEED})")
    if len(set(out)) != len(out):
        seen: set[int] = set()
        rep = sorted({x for x in out if x in seen or seen.add(x)})
        raise argparse.ArgumentTypeError(f"{text!r} repeats seed(s) {rep[:10]}: a seed list is a set of episodes, "
                                         "give each seed once")
    return out


def key_value(text: str) -> tuple[str, Any]:
    """An argparse type: ``KEY=VALUE`` -> (key, the value read as YAML: ``.inf``, ``1e-3``, ``[1, 2]``)."""
    if "=" not in text:
        raise argparse.ArgumentTypeError(f"{text!r} is not key=value")
    k, v = text.split("=", 1)
    if not k.strip():
        raise argparse.ArgumentTypeError(f"{text!r} has an empty key")
    try:
        return k.strip(), yaml.safe_load(v)
    except yaml.YAMLError as exc:
        raise argparse.ArgumentTypeError(f"{text!r}: the value is not valid YAML ({' '.join(str(exc).split())})") \
            from None


def build_parser() -> argparse.ArgumentParser:
    from controllers import ALL_CONTROLLERS

    p = argparse.ArgumentParser(prog="auv-follow", description=__doc__, formatter_class=_Formatter)
    sub = p.add_subparsers(dest="command", required=True)

    t = sub.add_parser("train", help="train a PPO/SAC/TD3 agent (from scratch or residual)", formatter_class=_Formatter,
                       description="Train a PPO/SAC/TD3 agent on AUVFollow, from scratch or as a residual on a "
                                   "controller; everything is checked before the run directory is created.",
                       epilog=_TRUST)
    t.add_argument("--algo", choices=ALGOS, default="bppo",
                   help="algorithm (bppo: the batched PPO of agents/training/batched_ppo.py on the native vector env)")
    t.add_argument("--env", dest="env_id", choices=ENV_CHOICES, default="AUVFollow-S4-v0", help="env id")
    t.add_argument("--env-kwarg", dest="env_kwargs", type=key_value, action="append", default=[],
                   metavar="KEY=VALUE", help="scenario override for gym.make (repeatable), e.g. disturbance=L1")
    t.add_argument("--mode", choices=MODES, default="residual", help="residual on a controller, or from scratch")
    t.add_argument("--controller", choices=ALL_CONTROLLERS, default=DEFAULT_CONTROLLER,
                   help="base controller of a residual agent (the paper's four, or ours: PROPOSED_KF, "
                        "PROPOSED_KF_DOB, MPC)")
    t.add_argument("--scale", type=_positive_float, default=DEFAULT_SCALE,
                   help="residual authority as a fraction of the force limits")
    t.add_argument("--history-len", type=_nonneg_int, default=None,
                   help=f"lagged delayed-target velocity differences in a residual agent's observation "
                        f"(None: {DEFAULT_HISTORY_LEN} for residual agents on v0 ids, else 0)")
    t.add_argument("--obs", dest="observation", choices=("raw", "estimator"), default=None,
                   help="agent observation: the env's fields, or with the estimator block (agents/README.md; "
                        "None: estimator for --algo bppo on v1 ids, else raw)")
    t.add_argument("--history-stride", type=_positive_int, default=DEFAULT_HISTORY_STRIDE,
                   help="steps between the lagged samples")
    t.add_argument("--no-base-action", dest="include_base_action", action="store_false",
                   help="leave the base action out of a residual agent's observation")
    t.add_argument("--timesteps", dest="total_timesteps", type=_positive_int, default=None,
                   help="total env steps (None: n_timesteps of the hyperparameter YAML)")
    t.add_argument("--max-minutes", type=_positive_float, default=None, help="wall-clock budget [min]")
    t.add_argument("--seed", type=_nonneg_int, default=0, help="seed of the model and the training envs")
    t.add_argument("--n-envs", type=_n_envs, default=None, help="training envs (None: the YAML's n_envs)")
    t.add_argument("--vec", choices=("dummy", "native"), default="dummy",
                   help="training VecEnv: SB3 DummyVecEnv of single envs, or the native batched env "
                        "(one kernel call for all envs; scratch mode only)")
    t.add_argument("--out", dest="out_dir", default="runs", help="parent directory of the run directory")
    t.add_argument("--run-name", default=None,
                   help="run directory name, one path component (None: <algo>-<env>-<mode>-seed<k>-<timestamp>)")
    t.add_argument("--checkpoint-freq", type=_nonneg_int, default=None,
                   help="env steps between checkpoints (0: none; None: 100000, bppo 5000000)")
    t.add_argument("--eval-freq", type=_nonneg_int, default=None,
                   help="env steps between evaluations (0: none; None: 50000, bppo 1000000)")
    t.add_argument("--eval-episodes", type=_positive_int, default=3,
                   help="episodes per evaluation and of the final score")
    t.add_argument("--eval-seed", type=_nonneg_int, default=TrainConfig.eval_seed,
                   help="first seed of the learning-curve episodes (held out from the training envs' seeds)")
    t.add_argument("--resume", dest="resume_from", default=None,
                   help="checkpoint/model .zip to continue (trusted files only: its vecnormalize .pkl is unpickled)")
    t.add_argument("--hyperparams", dest="hyperparams_file", default=None,
                   help="rl-zoo3-format YAML file (None: agents/training/hyperparams/<algo>.yml)")
    t.add_argument("--hp", dest="hyperparams", type=key_value, action="append", default=[], metavar="KEY=VALUE",
                   help="override a hyperparameter (repeatable), e.g. learning_rate=1e-4")
    t.add_argument("--no-progress", dest="progress_bar", action="store_false", help="no progress output")
    t.add_argument("--no-tensorboard", dest="tensorboard", action="store_false", help="no TensorBoard logs")
    t.add_argument("--no-final-eval", dest="final_eval", action="store_false",
                   help="skip the final score (eval-episodes episodes from eval-seed)")
    t.add_argument("-v", "--verbose", type=int, choices=(0, 1, 2), default=0, help="SB3 verbosity")

    e = sub.add_parser("evaluate", help="evaluate a saved agent on test seeds", formatter_class=_Formatter,
                       description="Evaluate a saved agent on test seeds (one row per episode).", epilog=_TRUST)
    e.add_argument("model", help="run directory or model .zip")
    e.add_argument("--env", dest="env_id", choices=ENV_CHOICES, default=None,
                   help="env id (None: the one the agent was trained on)")
    e.add_argument("--seeds", type=_seeds, default=None,
                   help="test seeds, e.g. 1000-1009 or 1,2 (default: the first 10 published test seeds of the env: "
                        "a v1 tier's own, 1000-1009 for the paper's scenarios)")
    e.add_argument("--out", default=None, help="CSV file for the per-episode metrics")
    e.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bars")

    c = sub.add_parser("compare", help="agents and scripted controllers in one table and plot",
                       formatter_class=_Formatter, epilog=_TRUST,
                       description="Agents and the scripted controllers on the same env and seeds: "
                                   "<name>.csv, <name>_summary.csv, <name>.md and <name>.png in --out.")
    c.add_argument("models", nargs="*", help="run directories or model .zip files")
    c.add_argument("--env", dest="env_id", choices=ENV_CHOICES, default=None,
                   help="env id (default: the one the agents were trained on, AUVFollow-S4-v0 without agents)")
    c.add_argument("--env-kwarg", dest="env_kwargs", type=key_value, action="append", default=[],
                   metavar="KEY=VALUE", help="scenario override for every policy (repeatable)")
    c.add_argument("--seeds", type=_seeds, default=None,
                   help="test seeds, e.g. 1000-1009 or 1,2 (default: the first 10 published test seeds of the env)")
    c.add_argument("--controllers", nargs="*", choices=ALL_CONTROLLERS, default=list(ALL_CONTROLLERS),
                   help="scripted controllers to include (default: the paper's four and ours)")
    c.add_argument("--out", default="results/tmp/compare", help="directory for the outputs (created if needed)")
    c.add_argument("--name", default="compare", help="file name stem of the outputs")
    c.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bars")
    _add_benchmark_commands(sub)
    from agents.data_commands import add_data_commands

    add_data_commands(sub, _Formatter, ENV_CHOICES, _seeds)
    return p


def _load(path: str, flag: str):
    from agents.training.loading import load_agent

    try:
        return load_agent(path)
    except (FileNotFoundError, ValueError) as exc:
        raise _Refused(flag, str(exc)) from None


def _train(args: argparse.Namespace) -> None:
    from agents.training.config import TrainingFailed
    from agents.training.runner import train

    kw = vars(args).copy()
    kw.pop("command")
    kw["env_kwargs"] = dict(kw["env_kwargs"])
    kw["hyperparams"] = dict(kw["hyperparams"])
    _check_writable(Path(kw["out_dir"]), "--out", want_dir=True)  # before any work, as for the other commands
    tier = auv_follow_env.ALL_TIERS.get(kw["env_id"][len("AUVFollow-"):].rsplit("-", 1)[0])
    if tier is not None and tier.out_of_distribution:
        print(f"auv-follow train: warning: {kw['env_id']} is for out-of-distribution testing only; train on "
              "Easy/Medium/Hard and score on it", file=sys.stderr)
    try:
        run = train(TrainConfig(**kw))
    except ConfigError as exc:
        raise _Refused(FLAGS.get(exc.field, exc.field), str(exc)) from None
    except TrainingFailed as exc:  # diverged or a write failed: one line, exit code 1
        print(f"auv-follow train: error: {' '.join(str(exc).split())}", file=sys.stderr)
        raise SystemExit(1) from None
    print(f"run directory: {run}")


def _evaluate(args: argparse.Namespace) -> None:
    from agents.training.loading import evaluate_agent

    if args.out:
        _check_writable(Path(args.out), "--out", want_dir=False)
    from agents.benchmark.protocol import default_test_seeds

    agent = _load(args.model, "model")
    seeds = args.seeds if args.seeds is not None else default_test_seeds(args.env_id or agent.env_id)
    df = evaluate_agent(agent, seeds, env_id=args.env_id, progress=args.progress)
    cols = ["policy", "seed", "true_steady_mean", "true_steady_rmse", "true_full_mean", "return"]
    print(df[cols].to_string(index=False))
    print(f"mean true steady-state mean error: {df['true_steady_mean'].mean():.4f} m")
    if args.out:
        _write_csv_atomic(df, Path(args.out))
        print(f"wrote {args.out}")


def _write_csv_atomic(df: Any, path: Path) -> None:
    """``df.to_csv(path)`` through a temporary file beside it and a rename: a failed or
    interrupted write leaves the previous file (and no temporary one)."""
    import tempfile

    from agents.benchmark.outputs import OutputWriteError

    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".partial", dir=path.parent)
        with os.fdopen(fd, "w") as f:
            df.to_csv(f, index=False)
        mask = os.umask(0)
        os.umask(mask)
        os.chmod(tmp, 0o666 & ~mask)  # as a plain open would create it (mkstemp makes it private)
        os.replace(tmp, path)
        tmp = None
    except OSError as exc:
        raise OutputWriteError(f"cannot write {path} ({exc.strerror or exc}): the previous file is kept") from exc
    finally:
        if tmp is not None:
            Path(tmp).unlink(missing_ok=True)


def _compare(args: argparse.Namespace) -> None:
    from agents.benchmark.compare import compare, summary_markdown

    out = Path(args.out)
    _check_writable(out, "--out", want_dir=True)
    if not args.name or "/" in args.name or args.name in (".", ".."):
        raise _Refused("--name", f"{args.name!r} is invalid: must be a file name stem without '/'")
    from agents.benchmark.protocol import default_test_seeds

    agents = [_load(m, "models") for m in args.models]
    if args.env_id is None:
        envs = sorted({a.env_id for a in agents})
        if len(envs) > 1:
            raise _Refused("--env", f"the agents were trained on different envs {envs}: give the env to compare on")
        args.env_id = envs[0] if envs else "AUVFollow-S4-v0"
    if args.seeds is None:
        args.seeds = default_test_seeds(args.env_id)
    try:
        _, summary = compare(agents, args.env_id, args.seeds, controllers=args.controllers,
                             env_kwargs=dict(args.env_kwargs) or None, out_dir=out, name=args.name,
                             progress=args.progress)
    except ConfigError as exc:
        raise _Refused(FLAGS.get(exc.field, exc.field), str(exc)) from None
    print(summary_markdown(summary, args.env_id, args.seeds))
    print(f"wrote {', '.join(args.name + s for s in ('.csv', '_summary.csv', '.md', '.png'))} in {out}/")


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``auv-follow`` console script."""
    parser = build_parser()
    args = parser.parse_args(argv)
    with stop_on_signals():  # SIGTERM and SIGHUP take Ctrl-C's path: save, keep, resume
        if getattr(args, "handler", None) is not None:  # benchmark, report, sweep
            return _run_handler(args, parser)
        return _run_training_command(args)


def _run_training_command(args: argparse.Namespace) -> int:
    try:
        {"train": _train, "evaluate": _evaluate, "compare": _compare}[args.command](args)
    except _Refused as exc:
        flag, msg = exc.args
        print(f"auv-follow {args.command}: error: argument {flag}: {msg}", file=sys.stderr)
        raise SystemExit(2) from None
    except TrainingInterrupted as exc:
        print(f"auv-follow train: interrupted{stop_name()}; run directory: {exc.run} (continue it with the "
              f"same command and --resume {Path(exc.run) / 'model.zip'})", file=sys.stderr)
        return exit_code()
    except OSError as exc:  # a write failed (full disk, read-only file system)
        print(f"auv-follow {args.command}: error: {_os_error_text(exc)}", file=sys.stderr)
        raise SystemExit(1) from None
    except KeyboardInterrupt as exc:
        print(f"auv-follow {args.command}: interrupted{stop_name(exc)}", file=sys.stderr)
        return exit_code(exc)
    return 0


# --- benchmark, report, sweep --------------------------------------------------

def _add_benchmark_commands(sub: Any) -> None:
    """The ``benchmark``, ``report`` and ``sweep`` subcommands (each sets ``handler``)."""
    from agents.benchmark.stats import DEFAULT_RESAMPLES, MAX_RESAMPLES

    def _resamples(text: str) -> int:
        return _integer(text, 1, MAX_RESAMPLES)

    b = sub.add_parser("benchmark", help="score policies on the tiers' test seeds: per-episode table + leaderboard",
                       formatter_class=_Formatter, epilog=_TRUST,
                       description="Score policies on the tiers' published test seeds and write the per-episode "
                                   "table, the leaderboard (.md/.csv/.png), one recorded episode per tier and policy "
                                   "(traces.parquet) and benchmark.json (docs/benchmark.md). Costs: scripted "
                                   "controllers and agents are quick; MPC (a batched QP per step) about a minute "
                                   "per tier of 100 seeds. "
                                   "Quick look: --tiers Hard --policies PID PROPOSED --seeds 3000000-3000009.")
    b.add_argument("--policies", nargs="+", default=None, metavar="POLICY",
                   help="controller names, 'classical' (every scripted controller, MPC included: slow), run "
                        "directories, directories of runs, label=run,run, or [label=]module:Class (your own "
                        "controller); NAME@Tier scores it on that tier only (default: classical)")
    b.add_argument("--tiers", nargs="+", default=["S4"], metavar="TIER",
                   help="S1..S4 (paper scenarios) and/or Easy, Medium, Hard, Extreme (v1 tiers), Leader-Easy, "
                        "Leader-Medium, Leader-Hard (targets with manoeuvre modes)")
    b.add_argument("--seeds", type=_seeds, default=None,
                   help="override the published test seeds (quick looks only), e.g. 3000000-3000009 "
                        "(default: each tier's 100 published test seeds)")
    b.add_argument("--out", default=None,
                   help=f"output directory (default: {SCRATCH_BENCH}, ignored by git; the committed leaderboard in "
                        "results/benchmark is rewritten only when you give --out results/benchmark)")
    b.add_argument("--resamples", type=_resamples, default=DEFAULT_RESAMPLES,
                   help=f"bootstrap resamples, at most {MAX_RESAMPLES}", metavar="N")
    b.add_argument("--bootstrap-seed", type=_nonneg_int, default=0, help="seed of the bootstrap resampling")
    b.add_argument("--unbatched", dest="batched", action="store_false",
                   help="one single-env episode at a time instead of one native vector env")
    b.add_argument("--cache", dest="cache_dir", default=None,
                   help="directory of per-run episode caches, reused while the episode code equals git HEAD "
                        "(default: no cache)")
    b.add_argument("--floors", action="store_true",
                   help="add each tier's floors as reference rows and 'gap closed' columns (agents/benchmark/"
                        "floors.py, docs/floors.md): a v1 tier's control and Kalman floors (a minute per tier), a "
                        "Leader tier's control and oracle-parameter floors (a few minutes) and its tier-prior floor "
                        "(about 25-30 minutes per tier; --cache keeps it)")
    b.add_argument("--address", default=None,
                   help="run the episodes on the Ray cluster at this address (host:port of its head, or 'local' "
                        "for a new Ray instance on this machine) as (tier, policy, seed chunk) cells; every node "
                        "needs this checkout installed (default: in this process)")
    b.add_argument("--chunk", type=_positive_int, default=None,
                   help="seeds per cell with --address (default: 25, four cells per tier and policy)")
    b.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bars")
    b.set_defaults(handler=_cmd_benchmark)

    lb = sub.add_parser("leaderboard", help="recompute a benchmark folder's leaderboard from its stored episodes",
                        formatter_class=_Formatter,
                        description="Recompute the leaderboard (leaderboard.csv/.md/.png, benchmark.json) of a folder "
                                    "written by `auv-follow benchmark` from its episodes.parquet, with the folder's "
                                    "bootstrap settings: no episode runs. For a new statistic on the stored episodes; "
                                    "the provenance keeps the episodes' own and records the rebuild.")
    lb.add_argument("--bench", required=True, help="directory written by `auv-follow benchmark`")
    lb.add_argument("--tier-prior-floor", nargs="+", default=[], metavar="TIER",
                    help="first compute the tier-prior floor of these Leader tiers of the folder (a follower who "
                         "knows the tier's published ranges, not the episode's draws; docs/floors.md) on the "
                         "folder's seeds and add it as reference rows: about 25 minutes per tier of 100 seeds on "
                         "2 cores")
    lb.add_argument("--add-policies", nargs="+", default=[], metavar="POLICY",
                    help="first score these policies (as benchmark --policies takes them; NAME@Tier for one tier) "
                         "on the folder's tiers and seeds and add them (a label the folder holds is scored again "
                         "and replaced): a new row without running the others again")
    lb.add_argument("--cache", dest="cache_dir", default=None,
                    help="directory of the particle floors' and the policies' episode caches, reused while their "
                         "code and inputs are unchanged (default: no cache)")
    lb.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bars")
    lb.set_defaults(handler=_cmd_leaderboard)

    r = sub.add_parser("report", help="one self-contained HTML page from a benchmark directory",
                       formatter_class=_Formatter,
                       description="One self-contained HTML page (plotly inline) from a benchmark directory, built "
                                   "from its stored tables alone: it never loads a model file.")
    r.add_argument("--bench", default="results/benchmark", help="directory written by `auv-follow benchmark`")
    r.add_argument("--out", default=None, help="HTML file (default: <bench>/report.html)")
    r.add_argument("--replay-policy", default=None, help="policy label of the episode replay (default: best)")
    r.add_argument("--replay-tier", default=None, help="tier of the replay and the time plots (default: Hard or "
                                                       "the last tier)")
    r.add_argument("--replay-seed", type=int, default=None, help="test seed of the replay (default: the first)")
    r.set_defaults(handler=_cmd_report)

    s = sub.add_parser("sweep", help="Ray Tune sweep: algorithm x hyperparameters x training seed x tier",
                       formatter_class=_Formatter,
                       description="A Ray Tune sweep over algorithm x hyperparameters x training seed x tier "
                                   "(docs/benchmark.md); resumable: run the same command again after a crash or "
                                   "Ctrl-C. Options override the --config file's keys only when given.")
    s.add_argument("--config", default=None, help="YAML search space (default: a small built-in grid)")
    s.add_argument("--name", default=None,
                   help="experiment name, one path component: the folder inside --storage and the resume key "
                        "(default: the config's name, else auv-follow-sweep)")
    s.add_argument("--storage", default=None,
                   help="directory of the Ray Tune experiment (default: the config's storage, else "
                        "results/tmp/sweeps, ignored by git)")
    s.add_argument("--address", default=None, help="existing Ray cluster (default: RAY_ADDRESS or local Ray)")
    s.add_argument("--timesteps", type=_positive_int, default=None,
                   help="env steps per trial (default: the config's, else 20000)")
    s.add_argument("--chunks", type=_positive_int, default=None,
                   help="reports (and checkpoints) per trial (default: the config's, else 2)")
    s.add_argument("--num-samples", type=_positive_int, default=None,
                   help="samples of the search space (default: the config's, else 1)")
    s.add_argument("--cpus-per-trial", type=_positive_float, default=None,
                   help="CPUs Tune reserves per trial (default: the config's, else 1)")
    s.add_argument("--no-resume", dest="resume", action="store_const", const=False, default=None,
                   help="start afresh even if the experiment can be resumed (default: resume)")
    s.set_defaults(handler=_cmd_sweep)


def _cmd_benchmark(args: argparse.Namespace) -> None:
    import shlex

    from agents.benchmark.leaderboard import benchmark_summary
    from agents.benchmark.run import benchmark, resolve_tiers

    try:
        resolve_tiers(args.tiers)
    except ValueError as exc:
        raise _Refused("--tiers", str(exc)) from None
    if args.out is None:
        args.out = SCRATCH_BENCH
        print(f"writing to {SCRATCH_BENCH} (ignored by git); give --out to choose the place", file=sys.stderr)
    _check_writable(Path(args.out), "--out", want_dir=True)
    if args.cache_dir is not None:
        _check_writable(Path(args.cache_dir), "--cache", want_dir=True)
    if args.chunk is not None and args.address is None:
        raise _Refused("--chunk", "cells are for --address: give the cluster's address too")
    from agents.benchmark.cluster import ClusterUnavailable

    try:
        res = benchmark(args.policies, args.tiers, seeds=args.seeds, out_dir=args.out, n_resamples=args.resamples,
                        bootstrap_seed=args.bootstrap_seed, batched=args.batched, progress=args.progress,
                        cache_dir=args.cache_dir, floors=args.floors, address=args.address, chunk=args.chunk,
                        command="auv-follow " + shlex.join(sys.argv[1:]) if sys.argv[1:2] == ["benchmark"] else None)
    except ClusterUnavailable as exc:
        raise _Refused("--address", str(exc)) from None
    print(benchmark_summary(res.leaderboard, res.files))


def _cmd_leaderboard(args: argparse.Namespace) -> None:
    import shlex

    from agents.benchmark.leaderboard import benchmark_summary
    from agents.benchmark.run import rebuild_leaderboard

    _check_writable(Path(args.bench), "--bench", want_dir=True)
    if args.cache_dir is not None:
        _check_writable(Path(args.cache_dir), "--cache", want_dir=True)
    try:
        res = rebuild_leaderboard(args.bench, progress=args.progress, tier_prior_floor=args.tier_prior_floor,
                                  cache_dir=args.cache_dir, add_policies=args.add_policies,
                                  command="auv-follow " + shlex.join(sys.argv[1:])
                                  if sys.argv[1:2] == ["leaderboard"] else None)
    except ValueError as exc:
        for key, flag in (("tier_prior_floor", "--tier-prior-floor"), ("add_policies", "--add-policies")):
            if key in str(exc):
                raise _Refused(flag, str(exc).replace(f"{key}=", "").replace(f"{key}: ", "")) from None
        raise
    print(benchmark_summary(res.leaderboard, res.files))


def _cmd_report(args: argparse.Namespace) -> None:
    from agents.benchmark.report import write_report

    if args.out is not None:
        _check_writable(Path(args.out), "--out", want_dir=False)
    path = write_report(args.bench, args.out, replay_policy=args.replay_policy, replay_tier=args.replay_tier,
                        replay_seed=args.replay_seed)
    print(f"report: {path}")


def _cmd_sweep(args: argparse.Namespace) -> None:
    from agents.benchmark.sweep import SweepConfig, SweepFailed, SweepUnavailable, sweep

    try:
        cfg = SweepConfig.from_args(args)
    except TypeError as exc:  # a YAML value of the wrong type reaching the dataclass
        raise _Refused("--config", str(exc)) from None
    try:
        best = sweep(cfg)
    except SweepUnavailable as exc:  # the sweep extra is not installed
        print(f"auv-follow sweep: error: {exc}", file=sys.stderr)
        raise SystemExit(1) from None
    except SweepFailed as exc:
        print(f"auv-follow sweep: error: {exc}", file=sys.stderr)
        raise SystemExit(1) from None
    print(best.to_string() if hasattr(best, "to_string") else best)
    if best.attrs.get("errors"):
        print(f"auv-follow sweep: {best.attrs['errors']} trial(s) failed: run the same command again to resume them",
              file=sys.stderr)
        raise SystemExit(1)


def _os_error_text(exc: OSError) -> str:
    """One line for a failed file operation: the message, or the reason and the file."""
    from agents.benchmark.outputs import OutputWriteError

    if isinstance(exc, OutputWriteError) or not exc.strerror:
        return " ".join(str(exc).split())
    name = f": {exc.filename}" if exc.filename else ""
    return f"{exc.strerror}{name}"


def _run_handler(args: argparse.Namespace, parser: argparse.ArgumentParser) -> int:
    """Run benchmark / report / sweep: a refusal is one line naming the argument or file (exit
    code 2); Ctrl-C prints one line and returns 130 (nothing half-written is left in place)."""
    try:
        args.handler(args)
    except _Refused as exc:
        flag, msg = exc.args
        print(f"auv-follow {args.command}: error: argument {flag}: {msg}", file=sys.stderr)
        raise SystemExit(2) from None
    except (ValueError, FileNotFoundError, IsADirectoryError, NotADirectoryError, PermissionError) as exc:
        msg = " ".join(str(exc).split())
        print(f"auv-follow {args.command}: error: {msg}", file=sys.stderr)
        raise SystemExit(2) from None
    except OSError as exc:  # a write failed (full disk, read-only file system): nothing half-written is kept
        print(f"auv-follow {args.command}: error: {_os_error_text(exc)}", file=sys.stderr)
        raise SystemExit(1) from None
    except KeyboardInterrupt as exc:
        # benchmark and report replace their files as one set (agents.benchmark.replace_set, report's rename)
        tail = "run the same command again to resume" if args.command == "sweep" else "nothing half-written was kept"
        print(f"auv-follow {args.command}: interrupted{stop_name(exc)} ({tail})", file=sys.stderr)
        return exit_code(exc)
    except MemoryError:
        print(f"auv-follow {args.command}: error: out of memory: use fewer seeds or policies", file=sys.stderr)
        raise SystemExit(2) from None
    return 0


if __name__ == "__main__":
    sys.exit(main())
