"""Agents and the paper's scripted controllers in one table and one plot, on identical seeds.

Both references are reported: ``true_*`` (the present target's reference, the task's
metric, what the env rewards) and ``own_*`` (the reference a scripted controller generated
itself; NaN for agents, which generate none).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pandas as pd

from agents.training.config import check_env_id
from agents.training.loading import Agent, load_agent

__all__ = ["compare", "summarize", "plot_summary", "plot_learning_curves", "SUMMARY_METRICS"]

#: columns summarised per policy (mean and std over seeds)
SUMMARY_METRICS: tuple[str, ...] = ("true_steady_mean", "true_steady_rmse", "true_steady_max", "true_full_mean",
                                    "true_full_rmse", "own_steady_mean", "own_steady_rmse")


def compare(agents: Sequence[Agent | str | Path] = (), env_id: str = "AUVFollow-S4-v0",
            seeds: Iterable[int] = range(1000, 1010), *, controllers: Sequence[str] | None = None,
            env_kwargs: dict[str, Any] | None = None, reference: str = "PROPOSED",
            out_dir: str | Path | None = None, name: str = "compare",
            progress: bool = True) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Evaluate agents and scripted controllers on the same env and seeds.

    Args:
        agents: loaded agents or run directories / model files.
        env_id: registered AUVFollow id (agents trained elsewhere are evaluated here too).
        seeds: test seeds (use seeds the agents were not trained on).
        controllers: scripted controllers to include (default: the paper's four and ours,
            ``controllers.ALL_CONTROLLERS``).
        env_kwargs: scenario overrides for every policy.
        reference: the policy the ``*_change_pct`` columns compare against.
        out_dir: if given, write ``<name>.csv`` (per-episode rows), ``<name>_summary.csv``,
            ``<name>.md`` and ``<name>.png`` there.

    Returns:
        (per-episode metrics, per-policy summary).

    Raises:
        ValueError: unknown env id or controller name, a broken run directory, or an ``out_dir``
            that is a file; all checked before any episode runs.
        FileNotFoundError: an agent path without a model (see :func:`agents.training.load_agent`).
    """
    from controllers import ALL_CONTROLLERS, make_controller
    from controllers.evaluation import evaluate

    check_env_id(env_id)
    names = list(ALL_CONTROLLERS if controllers is None else controllers)
    for n in names:
        if n not in ALL_CONTROLLERS:
            raise ValueError(f"controller={n!r} is unknown: valid controllers are {list(ALL_CONTROLLERS)}")
    from agents.benchmark.protocol import check_seed_list

    seeds = check_seed_list(seeds)  # distinct: a repeated seed would count an episode twice in the means
    loaded = [a if isinstance(a, Agent) else load_agent(a) for a in agents]  # every path checked before any work
    labels = names + [a.name for a in loaded]
    dup = sorted({x for x in labels if labels.count(x) > 1})
    if dup:
        raise ValueError(f"policy names {dup} occur more than once (an agent named like a controller, or two agents "
                         "of one name): their episodes would be merged in the summary; rename a run directory")
    if out_dir is not None and Path(out_dir).exists() and not Path(out_dir).is_dir():
        raise ValueError(f"out_dir={str(out_dir)!r} is invalid: it exists and is not a directory")
    probe = gym.make(env_id, **(env_kwargs or {}))
    spec = probe.unwrapped.task_spec
    probe.close()
    frames = [evaluate(make_controller(n, spec), env_id, seeds, env_kwargs=env_kwargs, policy_name=n,
                       progress=progress) for n in names]
    for agent in loaded:
        frames.append(evaluate(agent, env_id, seeds, env_kwargs=env_kwargs, env_wrapper=agent.env_wrapper,
                               policy_name=agent.name, progress=progress))
    per_episode = pd.concat(frames, ignore_index=True)
    summary = summarize(per_episode, reference=reference)
    if out_dir is not None:
        _write_outputs(Path(out_dir), name, per_episode, summary, env_id, seeds)
    return per_episode, summary


def _write_outputs(out: Path, name: str, per_episode: pd.DataFrame, summary: pd.DataFrame, env_id: str,
                   seeds: Sequence[int]) -> None:
    """The four files, written into a temporary folder inside ``out`` and moved into place as
    one set (:func:`agents.benchmark.replace_set`): a failure or Ctrl-C leaves the previous set.

    Raises:
        agents.benchmark.OutputWriteError: a file could not be written (nothing in ``out`` changed).
    """
    import shutil
    import tempfile

    from agents.benchmark.outputs import OutputWriteError, replace_set

    try:
        out.mkdir(parents=True, exist_ok=True)
        stage = Path(tempfile.mkdtemp(prefix=f".{name}-partial-", dir=out))
    except OSError as exc:
        raise OutputWriteError(f"cannot write into {out} ({exc.strerror or exc})") from exc
    files = [f"{name}.csv", f"{name}_summary.csv", f"{name}.md", f"{name}.png"]
    try:
        try:
            per_episode.to_csv(stage / files[0], index=False)
            summary.to_csv(stage / files[1])
            (stage / files[2]).write_text(summary_markdown(summary, env_id, seeds) + "\n")
            plot_summary(per_episode, stage / files[3], title=f"{env_id}, seeds {seeds[0]}-{seeds[-1]}")
        except OSError as exc:
            raise OutputWriteError(f"cannot write into {out} ({exc.strerror or exc}): its previous files are "
                                   "kept") from exc
        replace_set(stage, out, files)
    finally:
        shutil.rmtree(stage, ignore_errors=True)


def summarize(per_episode: pd.DataFrame, reference: str | None = "PROPOSED") -> pd.DataFrame:
    """Mean and std over seeds per policy (in order of appearance), and the change of the mean
    true/own steady-state mean error relative to ``reference`` [%]."""
    order = list(dict.fromkeys(per_episode["policy"]))
    cols = [c for c in SUMMARY_METRICS if c in per_episode]
    g = per_episode.groupby("policy", sort=False)
    summary = g[cols].mean().loc[order]
    for c in ("true_steady_mean", "true_steady_rmse"):
        summary[f"{c}_std"] = g[c].std(ddof=1).loc[order]
    summary["episodes"] = g.size().loc[order]
    summary["terminated"] = g["terminated"].sum().loc[order]
    if reference is not None and reference in summary.index:
        for c in ("true_steady_mean", "true_steady_rmse"):
            summary[f"{c}_change_pct"] = 100.0 * (summary[c] / summary.loc[reference, c] - 1.0)
    return summary


def summary_markdown(summary: pd.DataFrame, env_id: str, seeds: Sequence[int]) -> str:
    """The summary as a Markdown table (errors in m, changes in %)."""
    cols = ["true_steady_mean", "true_steady_mean_std", "true_steady_mean_change_pct", "true_steady_rmse",
            "true_steady_max", "true_full_mean", "own_steady_mean", "terminated"]
    cols = [c for c in cols if c in summary]
    head = "| policy | " + " | ".join(cols) + " |"
    sep = "|---" * (len(cols) + 1) + "|"
    lines = [f"{env_id}, {len(seeds)} test seeds ({seeds[0]}-{seeds[-1]}); errors in m, changes in %; "
             "own_* is NaN for agents (they generate no reference of their own).", "", head, sep]
    for pol, row in summary.iterrows():
        cells = []
        for c in cols:
            v = row[c]
            cells.append("nan" if pd.isna(v) else (f"{v:+.1f}" if c.endswith("_pct") else
                                                  (f"{int(v)}" if c == "terminated" else f"{v:.4f}")))
        lines.append(f"| {pol} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot_summary(per_episode: pd.DataFrame, path: str | Path, title: str = "") -> None:
    """One figure: steady-state mean error to the true reference per policy (bars: mean over
    seeds; dots: seeds), and the own-reference value where defined."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    order = list(dict.fromkeys(per_episode["policy"]))
    fig, ax = plt.subplots(figsize=(max(6.0, 1.3 * len(order)), 4.0))
    x = np.arange(len(order))
    for i, pol in enumerate(order):
        d = per_episode[per_episode["policy"] == pol]
        ax.bar(i - 0.2, d["true_steady_mean"].mean(), 0.4, color="C0", label="true reference" if i == 0 else None)
        ax.plot(np.full(len(d), i - 0.2), d["true_steady_mean"], "k.", ms=3)
        own = d["own_steady_mean"].mean()
        if np.isfinite(own):
            ax.bar(i + 0.2, own, 0.4, color="C1", label="own reference" if i == 0 else None)
    ax.set_xticks(x, order, rotation=20, ha="right")
    ax.set_ylabel("steady-state mean error (t >= 10 s) [m]")
    ax.set_yscale("log")
    ax.set_title(title)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_learning_curves(runs: dict[str, str | Path], path: str | Path, baseline: dict[str, float] | None = None,
                         window: int = 50) -> None:
    """Learning curves of runs: training episode return (Monitor logs, moving average over
    ``window`` episodes) and EvalCallback mean return, against environment steps.
    ``baseline``: horizontal lines (name -> return), e.g. PROPOSED's mean return."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from stable_baselines3.common.monitor import load_results

    fig, axes = plt.subplots(1, len(runs), figsize=(6.0 * len(runs), 4.0), squeeze=False)
    for ax, (label, run) in zip(axes[0], runs.items(), strict=True):
        run = Path(run)
        mon = load_results(str(run / "monitor"))
        if len(mon):
            steps = np.cumsum(mon["l"].to_numpy())
            ax.plot(steps, mon["r"].rolling(window, min_periods=1).mean(), label=f"training (avg {window} ep.)")
        ev = run / "eval" / "evaluations.npz"
        if ev.is_file():
            d = np.load(ev)
            ax.plot(d["timesteps"], d["results"].mean(axis=1), "o-", ms=3, label="evaluation (deterministic)")
        for name, value in (baseline or {}).items():
            ax.axhline(value, ls="--", lw=1, color="gray")
            ax.annotate(name, (0.01, value), xycoords=("axes fraction", "data"), fontsize=8, va="bottom")
        ax.set_xlabel("environment steps")
        ax.set_ylabel("episode return (-sum of distances) [m], symlog")
        ax.set_yscale("symlog", linthresh=10.0)
        ax.set_title(label)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
