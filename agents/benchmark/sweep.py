"""Sweeps on Ray Tune: algorithm x hyperparameters x training seed x tier, each trial calling
the project's :func:`agents.training.train`.

A trial trains in ``chunks`` pieces (``train(..., resume_from=<previous model>)`` continues the
step count and the VecNormalize statistics); after each piece it evaluates the agent on the
tier's **validation seeds** (:data:`VALIDATION_SEEDS`, disjoint from every published test
seed: asserted) and reports the metrics to Tune together with a checkpoint (the run
directory: ``model.zip``, ``vecnormalize.pkl``, ``config.yaml``). A restored trial continues
from its last checkpoint, so a sweep interrupted by a crash or Ctrl-C resumes where it stopped
when run again with the same ``name`` and ``storage`` (``Tuner.restore``, unfinished and
errored trials resumed).

Ray runs locally by default (``ray.init`` on this machine's CPUs); ``address`` (or the
``RAY_ADDRESS`` environment variable) connects to an existing cluster instead, unchanged -
every node then needs this package installed (``pip install -e .[sweep]``) and a shared
``storage`` path (or a URI Ray can write, e.g. a bucket).

Search-space file (YAML)::

    grid:                 # every combination (tune.grid_search)
      algo: [ppo, recurrentppo]
      mode: [scratch]
      tier: [Medium]
      seed: [0, 1, 2]
      hp.learning_rate: [3.0e-4, 1.0e-4]
    search:               # sampled num_samples times per grid point
      hp.gamma: {uniform: [0.95, 0.99]}
    timesteps: 200000     # env steps per trial
    chunks: 4             # reports / checkpoints per trial
    n_envs: 8

The best trials feed the benchmark: each result row has ``run_dir`` (the trial's final run),
e.g. ``auv-follow benchmark --policies best=<run_dir>``.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import signal
import threading
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import yaml

from auv_follow_env._files import check_size
from auv_follow_env._signals import STOP_SIGNALS, SignalStop, record_stop

__all__ = ["SweepConfig", "SweepFailed", "SweepUnavailable", "sweep", "run_trial", "VALIDATION_SEEDS", "DEFAULT_GRID",
           "param_space"]

#: validation seeds of every tier (our choice: 900-919; test seeds are published separately
#: and checked to be disjoint, training envs start at seed + i for small seeds)
VALIDATION_SEEDS: tuple[int, ...] = tuple(range(900, 920))
#: the default grid (small: one algorithm, two seeds)
DEFAULT_GRID: dict[str, list[Any]] = {"algo": ["ppo"], "mode": ["scratch"], "tier": ["S4"], "seed": [0, 1]}
_TRIAL_KEYS = ("algo", "mode", "tier", "seed", "controller", "scale")
_SAMPLERS = ("uniform", "loguniform", "choice", "randint")


@dataclass
class SweepConfig:
    """One sweep (everything Tune needs; written to ``<storage>/<name>/sweep.yaml``)."""

    grid: dict[str, list[Any]] = field(default_factory=lambda: dict(DEFAULT_GRID))  #: grid_search axes
    search: dict[str, dict[str, list[Any]]] = field(default_factory=dict)  #: sampled axes
    timesteps: int = 20_000  #: env steps per trial
    chunks: int = 2  #: reports (and checkpoints) per trial
    n_envs: int = 4  #: training envs per trial
    num_samples: int = 1  #: samples of the search space per grid point
    validation_seeds: list[int] = field(default_factory=lambda: list(VALIDATION_SEEDS))  #: evaluation seeds
    name: str = "auv-follow-sweep"  #: experiment name (the resume key)
    storage: str = "results/tmp/sweeps"  #: parent directory of the experiment (default: ignored by git)
    address: str | None = None  #: Ray cluster address (None: RAY_ADDRESS, else local Ray)
    cpus_per_trial: float = 1.0  #: Tune resources per trial
    max_failures: int = 0  #: automatic retries of a failed trial (from its last checkpoint)
    resume: bool = True  #: restore the experiment if it exists
    verbose: int = 1  #: Tune verbosity (1: the progress table)
    fail_once_marker: str | None = None  #: testing: a trial fails once after its first report while this file exists

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first invalid field."""
        from agents.benchmark.protocol import resolve_tier
        from agents.training.config import ALGOS, MODES

        name = self.name
        if not isinstance(name, str) or not name.strip() or name in (".", "..") or any(
                c in name for c in ("/", "\\", "\0")) or name != name.strip():
            raise ValueError(f"name={name!r} is invalid: must be one path component (no '/', '\\', '.' or '..'), "
                             f"the experiment folder inside storage")
        if not isinstance(self.storage, str) or not self.storage:
            raise ValueError(f"storage={self.storage!r} is invalid: must be a directory or a URI")
        for fname in ("grid", "search"):
            if not isinstance(getattr(self, fname), dict):
                raise ValueError(f"{fname}={getattr(self, fname)!r} is invalid: must be a mapping")
        for k, v in self.grid.items():
            if not isinstance(v, list) or not v:
                raise ValueError(f"grid[{k!r}]={v!r} is invalid: must be a non-empty list")
            if not (k in _TRIAL_KEYS or k.startswith("hp.")):
                raise ValueError(f"grid key {k!r} is unknown: valid keys are {list(_TRIAL_KEYS)} and hp.<name>")
        for a in self.grid.get("algo", ["ppo"]):
            if a not in ALGOS:
                raise ValueError(f"grid['algo'] has {a!r}: valid algorithms are {list(ALGOS)}")
        for m in self.grid.get("mode", ["scratch"]):
            if m not in MODES:
                raise ValueError(f"grid['mode'] has {m!r}: valid modes are {list(MODES)}")
        for t in self.grid.get("tier", ["S4"]):
            resolve_tier(t)
            _check_validation_seeds(self.validation_seeds, t)
        for k, spec in self.search.items():
            if not (isinstance(spec, dict) and len(spec) == 1 and next(iter(spec)) in _SAMPLERS):
                raise ValueError(f"search[{k!r}]={spec!r} is invalid: must be one of {{sampler: args}} with sampler "
                                 f"in {list(_SAMPLERS)}")
        for name, lo, hi in (("timesteps", 1, 10**12), ("chunks", 1, 10_000), ("n_envs", 1, 4096),
                             ("num_samples", 1, 100_000), ("max_failures", 0, 1000)):
            v = getattr(self, name)
            if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)) or not lo <= v <= hi:
                raise ValueError(f"{name}={v!r} is invalid: must be an integer in [{lo}, {hi}]")
            setattr(self, name, int(v))
        if self.timesteps < self.chunks:
            raise ValueError(f"timesteps={self.timesteps} is invalid: must be >= chunks={self.chunks}")
        c = self.cpus_per_trial
        if isinstance(c, (bool, np.bool_)) or not isinstance(c, (int, float, np.integer, np.floating)) or not (
                math.isfinite(c) and 0 < c <= 1024):
            raise ValueError(f"cpus_per_trial={c!r} is invalid: must be a number in (0, 1024]")
        self.cpus_per_trial = float(c)

    @classmethod
    def from_file(cls, path: str | Path, **overrides: Any) -> SweepConfig:
        p = Path(path)
        if not p.is_file():
            raise FileNotFoundError(f"sweep config {p} does not exist")
        try:
            data = yaml.safe_load(check_size(p, "text").read_text()) or {}
        except (yaml.YAMLError, UnicodeDecodeError) as exc:
            raise ValueError(f"sweep config {p} is not valid YAML: {' '.join(str(exc).split())[:200]}") from None
        if not isinstance(data, dict):
            raise ValueError(f"sweep config {p} is invalid: must be a mapping of keys "
                             f"{sorted(cls.__dataclass_fields__)}")
        unknown = sorted(set(data) - {f for f in cls.__dataclass_fields__})
        if unknown:
            raise ValueError(f"sweep config {p} has unknown keys {unknown}: valid keys are "
                             f"{sorted(cls.__dataclass_fields__)}")
        data.update({k: v for k, v in overrides.items() if v is not None})
        return cls(**data)

    @classmethod
    def from_args(cls, args: Any) -> SweepConfig:
        """From the ``auv-follow sweep`` arguments."""
        over = {"name": args.name, "storage": args.storage, "address": args.address, "timesteps": args.timesteps,
                "chunks": args.chunks, "num_samples": args.num_samples, "cpus_per_trial": args.cpus_per_trial,
                "resume": args.resume}
        if args.config:
            return cls.from_file(args.config, **over)
        return cls(**{k: v for k, v in over.items() if v is not None})


def _check_validation_seeds(seeds: list[int], tier: str) -> None:
    from agents.benchmark.protocol import tier_test_seeds

    clash = sorted(set(int(s) for s in seeds) & set(tier_test_seeds(tier)))
    if clash:
        raise ValueError(f"validation_seeds={clash[:5]}... overlap the published test seeds of tier {tier!r}: "
                         f"sweeps must never select on test seeds")


def param_space(cfg: SweepConfig) -> dict[str, Any]:
    """Tune's ``param_space``: grid axes as ``tune.grid_search``, search axes as samplers,
    and the fixed settings."""
    from ray import tune

    space: dict[str, Any] = {k: tune.grid_search(list(v)) for k, v in cfg.grid.items()}
    for k, spec in cfg.search.items():
        (kind, arg), = spec.items()
        space[k] = tune.choice(arg) if kind == "choice" else getattr(tune, kind)(*arg)
    space["_fixed"] = {"timesteps": cfg.timesteps, "chunks": cfg.chunks, "n_envs": cfg.n_envs,
                       "validation_seeds": list(cfg.validation_seeds), "fail_once_marker": cfg.fail_once_marker,
                       "cpus_per_trial": cfg.cpus_per_trial}
    return space


def _validation_metrics(run: Path, tier: str, seeds: list[int]) -> dict[str, float]:
    from agents.benchmark.evaluation import evaluate_tier
    from agents.benchmark.leaderboard import scores
    from agents.benchmark.policies import PolicySpec
    from agents.benchmark.stats import iqm

    spec = PolicySpec(label="trial", kind="learned", runs=(str(run),))
    df = evaluate_tier([spec], tier, seeds, progress=False)
    sc = scores(df, "true_steady_mean").to_numpy()
    return {"val_true_steady_mean_iqm": float(iqm(sc)), "val_true_steady_mean_mean": float(np.mean(sc)),
            "val_true_full_mean_iqm": float(iqm(scores(df, "true_full_mean").to_numpy())),
            "val_termination_rate": float(df["terminated"].mean()), "val_return_mean": float(df["return"].mean())}


def _claim(marker: Path) -> bool:
    """Delete ``marker``; True for the one caller that did (trials race for it)."""
    try:
        marker.unlink()
    except FileNotFoundError:
        return False
    return True


def run_trial(config: dict[str, Any]) -> None:
    """Tune's function trainable: train in chunks with :func:`agents.training.train`, evaluate on
    the validation seeds, report with a checkpoint; resumes from Tune's checkpoint."""
    import tempfile

    from ray import tune

    from agents.benchmark.protocol import resolve_tier
    from agents.training.config import ConfigError, TrainConfig
    from agents.training.runner import train

    fixed = config["_fixed"]
    tier = config.get("tier", "S4")
    _, env_id = resolve_tier(tier)
    hp = {k[3:]: v for k, v in config.items() if k.startswith("hp.")}
    if config.get("algo", "ppo") == "bppo":  # torch's threads within the trial's share of the cores
        hp.setdefault("torch_threads", max(1, int(fixed.get("cpus_per_trial", 1))))
    chunks, total = int(fixed["chunks"]), int(fixed["timesteps"])
    work = Path(tempfile.mkdtemp(prefix="auv-sweep-"))
    start_chunk, model, resumed_from = 0, None, -1
    ckpt = tune.get_checkpoint()
    if ckpt is not None:
        with ckpt.as_directory() as d:
            state = json.loads((Path(d) / "trial_state.json").read_text())
            shutil.copytree(d, work / "restored")
        start_chunk, model, resumed_from = state["chunk"] + 1, work / "restored" / "model.zip", state["chunk"]
    extra = {k: config[k] for k in ("controller", "scale") if k in config}
    for i in range(start_chunk, chunks):
        cfg = TrainConfig(algo=config.get("algo", "ppo"), env_id=env_id, mode=config.get("mode", "scratch"),
                          seed=int(config.get("seed", 0)), n_envs=int(fixed["n_envs"]),
                          total_timesteps=max(1, round(total * (i + 1) / chunks)), hyperparams=hp,
                          resume_from=str(model) if model is not None else None, out_dir=str(work),
                          run_name=f"chunk{i}", checkpoint_freq=0, eval_freq=0, progress_bar=False,
                          tensorboard=False, **extra)
        try:
            run = train(cfg)
        except ConfigError as exc:  # its two-argument constructor does not survive Ray's pickling
            raise ValueError(f"trial {config.get('algo', 'ppo')}/{tier}/seed {config.get('seed', 0)}: {exc}") from None
        model = run / "model.zip"
        with open(run / "config.yaml") as f:
            steps = int(yaml.safe_load(f)["result"]["num_timesteps"])
        metrics = _validation_metrics(run, tier, list(fixed["validation_seeds"]))
        (run / "trial_state.json").write_text(json.dumps({"chunk": i, "timesteps": steps}))
        metrics.update({"timesteps": steps, "chunk": i, "resumed_from_chunk": resumed_from,
                        "env_id": env_id, "run_dir": str(run)})
        tune.report(metrics, checkpoint=tune.Checkpoint.from_directory(str(run)))
        if fixed.get("fail_once_marker") and i == 0 and _claim(Path(fixed["fail_once_marker"])):
            raise RuntimeError("injected failure (fail_once_marker): run the sweep again to resume it")
    shutil.rmtree(work, ignore_errors=True)  # everything kept is in Tune's checkpoints


#: SweepConfig fields that do not change what a sweep trains (a resume may differ in them)
_RUN_ONLY_FIELDS = ("name", "storage", "address", "resume", "verbose", "fail_once_marker", "cpus_per_trial",
                    "max_failures")


def _settings(cfg: SweepConfig) -> dict[str, Any]:
    return json.loads(json.dumps(asdict(cfg), default=str))


def _write_settings(cfg: SweepConfig, exp: Path) -> None:
    tmp = exp / "sweep.yaml.tmp"
    tmp.write_text(yaml.safe_dump(_settings(cfg), sort_keys=False))
    os.replace(tmp, exp / "sweep.yaml")


def _check_same_settings(cfg: SweepConfig, exp: Path) -> None:
    """Refuse to resume ``exp`` with settings that change what is trained: a restored
    experiment keeps the search space and budgets it was started with."""
    path = check_size(exp / "sweep.yaml", "text")
    if not path.is_file():
        raise ValueError(f"sweep {cfg.name!r} in {exp.parent} exists but has no sweep.yaml recording its settings: "
                         "give --no-resume to start it afresh, or another --name")
    try:
        old = yaml.safe_load(path.read_text()) or {}
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path} is not valid YAML ({' '.join(str(exc).split())[:200]})") from None
    new = _settings(cfg)
    changed = [k for k in new if k not in _RUN_ONLY_FIELDS and old.get(k) != new[k]] if isinstance(old, dict) else ["*"]
    if changed:
        what = "; ".join(f"{k}: {old.get(k)!r} then, {new[k]!r} now" for k in changed[:4]) if changed != ["*"] else (
            f"{path} is not a mapping")
        raise ValueError(f"sweep {cfg.name!r} in {exp.parent} was started with other settings ({what}): resuming it "
                         "would train and print the old ones; give --no-resume to start it afresh, or another --name")


@contextlib.contextmanager
def _stop_tune_gracefully() -> Iterator[list[int]]:
    """Ctrl-C, SIGTERM and SIGHUP during ``Tuner.fit`` ask Tune to save its state and return (its
    SIGUSR1 path; Ray's own SIGTERM handler would abort the driver); a second signal raises at once.
    Yields the list of stop signals received."""
    stops: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        yield stops
        return

    def handler(signum, frame) -> None:  # noqa: ARG001 - a signal handler's signature
        record_stop(signum)
        stops.append(signum)
        if len(stops) > 1:
            raise SignalStop(signum) if signum != signal.SIGINT else KeyboardInterrupt()
        os.kill(os.getpid(), signal.SIGUSR1)

    before = os.environ.get("TUNE_DISABLE_SIGINT_HANDLER")
    os.environ["TUNE_DISABLE_SIGINT_HANDLER"] = "1"  # ours forwards it
    previous = {sig: signal.signal(sig, handler) for sig in STOP_SIGNALS if signal.getsignal(sig) is not signal.SIG_IGN}
    try:
        yield stops
    finally:
        for sig, h in previous.items():
            signal.signal(sig, h)
        if before is None:
            os.environ.pop("TUNE_DISABLE_SIGINT_HANDLER", None)
        else:
            os.environ["TUNE_DISABLE_SIGINT_HANDLER"] = before


def _init_ray(address: str | None) -> None:
    import ray

    if ray.is_initialized():
        return
    address = address or os.environ.get("RAY_ADDRESS")
    if address:
        ray.init(address=address, log_to_driver=False)
    else:
        # ("local": a new local instance, never one a `ray start` on this host left running)
        ray.init(address="local", num_cpus=os.cpu_count() or 1, include_dashboard=False, log_to_driver=False)


def sweep(cfg: SweepConfig) -> pd.DataFrame:
    """Run (or resume) the sweep and return one row per trial, best first (lowest validation
    IQM steady-state error); also written to ``<storage>/<name>/trials.csv``.

    ``df.attrs["errors"]`` is the number of trials that errored (the CLI exits with code 1 then).

    Raises:
        ValueError: invalid configuration (names the field).
        SweepFailed: every trial failed.
        SweepUnavailable: Ray Tune is not installed.
    """
    cfg.validate()
    try:
        from ray import tune
    except ImportError:
        raise SweepUnavailable('Ray Tune is not installed: pip install -e ".[sweep]"') from None

    storage = cfg.storage if "://" in cfg.storage else str(Path(cfg.storage).resolve())
    exp = Path(storage) / cfg.name
    restore = cfg.resume and tune.Tuner.can_restore(str(exp))
    if restore:
        _check_same_settings(cfg, exp)
    _init_ray(cfg.address)
    trainable = tune.with_resources(run_trial, {"cpu": cfg.cpus_per_trial})
    if "://" not in storage:  # what was asked, for a later resume to compare (also rewritten at the end)
        exp.mkdir(parents=True, exist_ok=True)
        _write_settings(cfg, exp)
    if restore:
        tuner = tune.Tuner.restore(str(exp), trainable, resume_unfinished=True, resume_errored=True)
    else:
        run_config = tune.RunConfig(
            name=cfg.name, storage_path=storage, verbose=cfg.verbose,
            checkpoint_config=tune.CheckpointConfig(num_to_keep=2),
            failure_config=tune.FailureConfig(max_failures=cfg.max_failures))
        tuner = tune.Tuner(trainable, param_space=param_space(cfg),
                           tune_config=tune.TuneConfig(num_samples=cfg.num_samples),
                           run_config=run_config)
    with _stop_tune_gracefully() as stops:
        results = tuner.fit()
    if stops:  # Tune saved its state and returned: the experiment is unfinished, resumable
        raise SignalStop(stops[0]) if stops[0] != signal.SIGINT else KeyboardInterrupt()
    errors = [r.error for r in results if r.error is not None]
    if len(errors) == len(results):
        first = " ".join(str(errors[0]).split())[-400:] if errors else "no trials ran"
        raise SweepFailed(f"all {len(results)} trial(s) of sweep {cfg.name!r} failed; the last lines of the first "
                          f"error: {first}")
    df = results.get_dataframe()
    # the trial's last checkpoint is a complete run directory (model.zip, vecnormalize.pkl,
    # config.yaml): what `auv-follow benchmark --policies` takes
    ckpt_dirs = {r.metrics.get("trial_id"): (r.checkpoint.path if r.checkpoint is not None else None)
                 for r in results}
    df["run_dir"] = df["trial_id"].map(ckpt_dirs)
    keep = [c for c in df.columns if c.startswith(("config/", "val_")) and not c.startswith("config/_fixed")]
    keep += [c for c in ("timesteps", "chunk", "resumed_from_chunk", "training_iteration", "run_dir", "trial_id",
                         "env_id") if c in df]
    df = df[keep].rename(columns=lambda c: c.replace("config/", ""))
    if "val_true_steady_mean_iqm" in df:
        df = df.sort_values("val_true_steady_mean_iqm").reset_index(drop=True)
    if "://" not in storage:
        exp.mkdir(parents=True, exist_ok=True)
        df.to_csv(exp / "trials.csv", index=False)
        _write_settings(cfg, exp)
    df.attrs["errors"] = len(errors)
    if errors:
        print(f"{len(errors)} trial(s) errored; run the same command again to resume them: {errors[0]}")
    return df


class SweepFailed(RuntimeError):
    """Every trial of a sweep failed (the message has the first error)."""


class SweepUnavailable(ImportError):
    """Ray Tune, the ``sweep`` extra, is not installed (the message says how to install it)."""
