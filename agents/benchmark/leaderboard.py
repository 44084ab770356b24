"""The leaderboard: per (tier, policy) IQM and mean with stratified-bootstrap CIs, termination
rate, probability of improvement and paired differences; its Markdown table, summary and PNG."""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from tqdm.auto import tqdm

import auv_follow_env  # noqa: F401  (registers the ids)
from agents.benchmark.protocol import ERROR_METRICS, LEADERBOARD_METRICS, check_labels
from agents.benchmark.stats import (
    DEFAULT_BOOTSTRAP_SEED,
    DEFAULT_RESAMPLES,
    iqm,
    probability_of_improvement,
    stratified_bootstrap_ci,
)


def scores(episodes: pd.DataFrame, metric: str) -> pd.Series:
    """The per-episode score of ``metric``: the metric, or the loss threshold for an episode
    that terminated (or has no sample in the window)."""
    if metric not in episodes:
        raise ValueError(f"metric={metric!r} is not a column: valid metrics are {list(ERROR_METRICS)}")
    s = episodes[metric].astype(float)
    fail = episodes["terminated"].astype(bool) | ~np.isfinite(s)
    if metric in ERROR_METRICS and "fail_error_m" in episodes:
        s = s.where(~fail, episodes["fail_error_m"].astype(float))
    return s


def paired_difference(episodes: pd.DataFrame, tier: str, policy: str, other: str, metric: str = "true_steady_mean",
                      *, n_resamples: int = DEFAULT_RESAMPLES, seed: int = DEFAULT_BOOTSTRAP_SEED,
                      confidence: float = 0.95) -> tuple[float, float, float]:
    """Mean over the test seeds of ``policy``'s score minus ``other``'s on the same seed (a
    method's runs averaged per seed first), with a percentile bootstrap CI over seeds [m];
    negative: ``policy`` is better. Seeds that only one of them has are left out.

    Raises:
        ValueError: a policy has no episodes on ``tier``.
    """
    ep = episodes[episodes["tier"] == tier]
    a, b = _per_seed(ep, policy, metric, tier)[0].align(_per_seed(ep, other, metric, tier)[0], join="inner")
    return _boot_ci((a - b).to_numpy(), np.mean, n_resamples, seed, confidence)


#: suffixes of the robust paired columns (:func:`robust_paired_difference`) after a prefix such as ``paired_diff``
ROBUST_SUFFIXES = ("_kept", "_kept_lo", "_kept_hi", "_kept_seeds", "_median", "_median_lo", "_median_hi")


def _per_seed(ep: pd.DataFrame, name: str, metric: str, tier: str) -> tuple[pd.Series, pd.Series]:
    d = ep[ep["policy"] == name]
    if d.empty:
        raise ValueError(f"policy={name!r} has no episodes on tier {tier!r}")
    score = pd.Series(scores(d, metric).to_numpy(), index=d["seed"].to_numpy()).groupby(level=0).mean()
    lost = pd.Series(d["terminated"].astype(bool).to_numpy(), index=d["seed"].to_numpy()).groupby(level=0).any()
    return score, lost


def _boot_ci(x: np.ndarray, stat: Any, n_resamples: int, seed: int, confidence: float) -> tuple[float, float, float]:
    if x.size == 0:
        return math.nan, math.nan, math.nan
    est = float(stat(x))
    if x.size == 1 or np.all(x == x[0]):
        return est, float(x[0]), float(x[0])
    rng = np.random.default_rng(seed)
    boot = stat(x[rng.integers(0, x.size, (n_resamples, x.size))], axis=1)
    q = 100 * (1 - confidence) / 2
    return est, float(np.percentile(boot, q)), float(np.percentile(boot, 100 - q))


def robust_paired_difference(episodes: pd.DataFrame, tier: str, policy: str, other: str,
                             metric: str = "true_steady_mean", *, n_resamples: int = DEFAULT_RESAMPLES,
                             seed: int = DEFAULT_BOOTSTRAP_SEED, confidence: float = 0.95,
                             prefix: str = "paired_diff") -> dict[str, float]:
    """Two paired statistics that a few lost targets cannot dominate (a lost target scores the loss
    threshold, 20 m, against errors of tenths of a metre), on the seeds both policies have [m]:

    * ``<prefix>_kept``: the mean of ``policy - other`` over the seeds where neither lost the target
      (no run of either terminated), with a bootstrap CI over those seeds; ``<prefix>_kept_seeds``: how
      many they are;
    * ``<prefix>_median``: the median of ``policy - other`` over all the common seeds (a lost target
      counts as one large difference, not as its size), with a bootstrap CI.

    Raises:
        ValueError: a policy has no episodes on ``tier``.
    """
    ep = episodes[episodes["tier"] == tier]
    (a, lost_a), (b, lost_b) = _per_seed(ep, policy, metric, tier), _per_seed(ep, other, metric, tier)
    a, b = a.align(b, join="inner")
    lost = (lost_a.reindex(a.index) | lost_b.reindex(a.index)).to_numpy()
    diff = (a - b).to_numpy()
    kept = _boot_ci(diff[~lost], np.mean, n_resamples, seed, confidence)
    median = _boot_ci(diff, np.median, n_resamples, seed, confidence)
    return dict(zip((prefix + s for s in ROBUST_SUFFIXES), (*kept, float((~lost).sum()), *median), strict=True))


def leaderboard(episodes: pd.DataFrame, *, metrics: Sequence[str] = LEADERBOARD_METRICS,
                n_resamples: int = DEFAULT_RESAMPLES, seed: int = DEFAULT_BOOTSTRAP_SEED,
                confidence: float = 0.95, progress: bool = False,
                bases: Mapping[str, str] | None = None, observations: Mapping[str, str] | None = None,
                filtered: Mapping[str, str] | None = None) -> pd.DataFrame:
    """Aggregate a per-episode table into the leaderboard, one row per (tier, policy).

    Args:
        episodes: rows with columns tier, policy, kind ("classical" / "learned"), run,
            terminated and ``metrics`` (e.g. from :func:`evaluate_tier`).
        metrics: error columns to aggregate (lower is better); the first ranks the classical
            baselines and is the one the probability of improvement is computed on.
        n_resamples, seed, confidence: bootstrap settings.
        bases: residual methods' base controllers (``{policy: base policy}``, see
            :func:`residual_bases`): adds ``base`` and the paired difference against it
            (``paired_diff_base``, ``_lo``, ``_hi``) where the base was scored on the tier.
        observations: residual methods' observation (``{policy: "raw" | "estimator"}``, see
            :func:`~agents.benchmark.policies.residual_observations`): the column ``observation``.
        filtered: residual methods whose observation carries a target filter their base lacks
            (``{policy: the same law on that filter}``, see
            :func:`~agents.benchmark.policies.filtered_laws`): adds ``filtered_law`` and the paired
            difference against it (``paired_diff_filtered``, ``_lo``, ``_hi``).

    Returns:
        columns tier, policy, kind, runs, episodes, for each metric ``<m>_iqm``,
        ``<m>_iqm_lo``, ``<m>_iqm_hi``, ``<m>_mean``, ``<m>_mean_lo``, ``<m>_mean_hi``;
        ``termination_rate``, ``best_classical``, ``<m0>_iqm_change_pct`` (vs the best
        classical baseline), ``poi``, ``poi_lo``, ``poi_hi``; ``run_iqm_min`` /
        ``run_iqm_max`` (spread of the per-run IQMs of ``metrics[0]``); ``paired_diff``,
        ``paired_diff_lo``, ``paired_diff_hi`` (:func:`paired_difference` of ``metrics[0]`` against
        the best classical baseline, same seeds, in m) and its robust companions ``paired_diff_kept``
        (+ ``_lo``, ``_hi``, ``_seeds``: seeds where neither lost the target) and ``paired_diff_median``
        (+ ``_lo``, ``_hi``) (:func:`robust_paired_difference`; the same after ``paired_diff_base`` and
        ``paired_diff_filtered``); ``lost_targets`` (terminated episodes); with reference rows
        (``kind="reference"``, the floors of :mod:`agents.benchmark.floors`) also ``gap_closed``.
    """
    need = {"tier", "policy", "kind", "run", "terminated", *metrics}
    missing = sorted(need - set(episodes.columns))
    if missing:
        raise ValueError(f"episodes lacks columns {missing}: give a table from evaluate_tier")
    check_labels(sorted(set(episodes.loc[episodes["kind"] != "reference", "policy"].astype(str))))
    kinds = episodes.groupby(["tier", "policy"], sort=False)["kind"].nunique()
    if (kinds > 1).any():
        (tier_, pol_), = kinds[kinds > 1].index[:1]
        raise ValueError(f"episodes has policy {pol_!r} on tier {tier_!r} with several kinds "
                         f"{sorted(set(episodes.loc[episodes['policy'] == pol_, 'kind']))}: one label per policy")
    dup = episodes.duplicated(["tier", "policy", "run", "seed"]) if "seed" in episodes else None
    if dup is not None and dup.any():
        r = episodes[dup].iloc[0]
        raise ValueError(f"episodes has seed {r['seed']} of policy {r['policy']!r} (run {r['run']!r}) on tier "
                         f"{r['tier']!r} more than once: a seed list is a set of episodes")
    if not metrics:
        raise ValueError("metrics is empty: give at least one metric column")
    m0 = metrics[0]
    rows = []
    groups = list(episodes.groupby(["tier", "policy"], sort=False))
    for (tier, pol), d in tqdm(groups, desc="leaderboard", disable=not progress, leave=False):
        d = d.sort_values(["run", "seed"], kind="stable")  # strata aligned by test seed
        row: dict[str, Any] = {"tier": tier, "policy": pol, "kind": d["kind"].iloc[0],
                               "runs": int(d["run"].nunique()), "episodes": len(d)}
        for m in metrics:
            sc = scores(d, m)
            strata = [sc[d["run"] == r].to_numpy() for r in d["run"].unique()]
            for stat in ("iqm", "mean"):
                est, lo, hi = stratified_bootstrap_ci(strata, stat, n_resamples=n_resamples, seed=seed,
                                                      confidence=confidence)
                row[f"{m}_{stat}"], row[f"{m}_{stat}_lo"], row[f"{m}_{stat}_hi"] = est, lo, hi
        per_run = [float(iqm(scores(d[d["run"] == r], m0).to_numpy())) for r in d["run"].unique()]
        row["run_iqm_min"], row["run_iqm_max"] = min(per_run), max(per_run)
        row["termination_rate"] = float(d["terminated"].astype(bool).mean())
        row["lost_targets"] = int(d["terminated"].astype(bool).sum())
        rows.append(row)
    board = pd.DataFrame(rows)
    board["best_classical"] = None
    for c in (f"{m0}_iqm_change_pct", "poi", "poi_lo", "poi_hi", "paired_diff", "paired_diff_lo", "paired_diff_hi",
              *("paired_diff" + x for x in ROBUST_SUFFIXES)):
        board[c] = np.nan
    for tier, idx in board.groupby("tier", sort=False).groups.items():
        sub = board.loc[idx]
        classical = sub[sub["kind"] == "classical"]
        if classical.empty:
            continue
        best = classical.loc[classical[f"{m0}_iqm"].idxmin(), "policy"]
        board.loc[idx, "best_classical"] = best
        board.loc[idx, f"{m0}_iqm_change_pct"] = 100.0 * (
            sub[f"{m0}_iqm"] / float(classical.loc[classical["policy"] == best, f"{m0}_iqm"].iloc[0]) - 1.0)
        ep_t = episodes[episodes["tier"] == tier]
        y = scores(ep_t[ep_t["policy"] == best], m0).to_numpy()
        for i in idx:
            x = scores(ep_t[ep_t["policy"] == board.at[i, "policy"]], m0).to_numpy()
            board.loc[i, ["poi", "poi_lo", "poi_hi"]] = probability_of_improvement(
                x, y, n_resamples=max(200, n_resamples // 5), seed=seed, confidence=confidence)
            if board.at[i, "kind"] != "reference":
                board.loc[i, ["paired_diff", "paired_diff_lo", "paired_diff_hi"]] = paired_difference(
                    ep_t, tier, board.at[i, "policy"], best, m0, n_resamples=n_resamples, seed=seed,
                    confidence=confidence)
                for c, v in robust_paired_difference(ep_t, tier, board.at[i, "policy"], best, m0,
                                                     n_resamples=n_resamples, seed=seed,
                                                     confidence=confidence).items():
                    board.at[i, c] = v
    board["observation"] = [str((observations or {}).get(p, "")) for p in board["policy"]]
    for col, table in (("base", bases), ("filtered_law", filtered)):
        key = "paired_diff_" + ("base" if col == "base" else "filtered")
        board[col] = ""
        for c in (key, f"{key}_lo", f"{key}_hi", *(key + x for x in ROBUST_SUFFIXES)):
            board[c] = math.nan
        for i in board.index:
            other = (table or {}).get(board.at[i, "policy"])
            ep_t = episodes[episodes["tier"] == board.at[i, "tier"]]
            if other and (ep_t["policy"] == other).any():
                board.at[i, col] = other
                board.loc[i, [key, f"{key}_lo", f"{key}_hi"]] = paired_difference(
                    ep_t, board.at[i, "tier"], board.at[i, "policy"], other, m0, n_resamples=n_resamples,
                    seed=seed, confidence=confidence)
                for c, v in robust_paired_difference(ep_t, board.at[i, "tier"], board.at[i, "policy"], other, m0,
                                                     n_resamples=n_resamples, seed=seed, confidence=confidence,
                                                     prefix=key).items():
                    board.at[i, c] = v
    if (board["kind"] == "reference").any():  # floors (agents/benchmark/floors.py): their gap column
        from agents.benchmark.floors import add_gap_closed

        board = add_gap_closed(board, m0)
    return board


def goal_check(board: pd.DataFrame, tier: str = "Hard", metric: str = "true_steady_mean",
               reduction: float = 0.30) -> dict[str, Any]:
    """Is the best learned policy's IQM at least ``reduction`` below the best classical
    baseline's, with non-overlapping CIs, on ``tier``? Returns the numbers and the verdict."""
    sub = board[board["tier"] == tier]
    learned, classical = sub[sub["kind"] == "learned"], sub[sub["kind"] == "classical"]
    if learned.empty or classical.empty:
        return {"tier": tier, "met": None, "reason": "needs both a learned and a classical policy on this tier"}
    c = classical.loc[classical[f"{metric}_iqm"].idxmin()]
    lrn = learned.loc[learned[f"{metric}_iqm"].idxmin()]
    change = float(lrn[f"{metric}_iqm"] / c[f"{metric}_iqm"] - 1.0)
    separated = bool(lrn[f"{metric}_iqm_hi"] < c[f"{metric}_iqm_lo"])  # apart, the learned one below
    apart = separated or bool(lrn[f"{metric}_iqm_lo"] > c[f"{metric}_iqm_hi"])
    return {"tier": tier, "metric": metric, "best_learned": lrn["policy"], "best_classical": c["policy"],
            "learned_iqm": float(lrn[f"{metric}_iqm"]),
            "learned_ci": (float(lrn[f"{metric}_iqm_lo"]), float(lrn[f"{metric}_iqm_hi"])),
            "classical_iqm": float(c[f"{metric}_iqm"]),
            "classical_ci": (float(c[f"{metric}_iqm_lo"]), float(c[f"{metric}_iqm_hi"])),
            "change_pct": 100.0 * change, "cis_separated": separated, "cis_apart": apart,
            "met": bool(change <= -reduction and separated)}


def _learned_words(g: Mapping[str, Any]) -> str:
    """The best learned policy against the best classical one, in numbers only."""
    apart = g.get("cis_apart", g["cis_separated"])
    return (f"best learned {g['best_learned']}: {g['change_pct']:+.1f} % against the best classical "
            f"{g['best_classical']}, 95 % CIs {'apart' if apart else 'overlap'}")


def benchmark_summary(board: pd.DataFrame, files: Mapping[str, Path] | None = None, *, top: int = 5,
                      metric: str = "true_steady_mean") -> str:
    """A few lines for the terminal: per tier the ``top`` policies by the IQM of ``metric``
    (label, IQM with its 95 % CI, kind), the floors (reference rows) on one line, the best
    learned policy's change against the best classical one where the tier has both, and where
    the full files are."""
    def one_line(x: Any, width: int = 48) -> str:
        text = " ".join(str(x).split())
        return text if len(text) <= width else text[: width - 3] + "..."

    def ci(r: Any) -> str:
        return _fmt_ci(r[f"{metric}_iqm"], r[f"{metric}_iqm_lo"], r[f"{metric}_iqm_hi"])

    lines = []
    for tier, sub in board.groupby("tier", sort=False):
        sub = sub.sort_values(f"{metric}_iqm", kind="stable")
        refs, comp = sub[sub["kind"] == "reference"], sub[sub["kind"] != "reference"]
        best = sub["best_classical"].iloc[0] if "best_classical" in sub else None
        head = f"{one_line(tier)}: {len(comp)} policies by {metric.replace('true_', '')} error IQM [95 % CI] in m"
        lines.append(head + (f"; best classical {one_line(best)}" if isinstance(best, str) and best else ""))
        shown = comp.head(top)
        width = max((len(one_line(p)) for p in shown["policy"]), default=0)
        for rank, (_, r) in enumerate(shown.iterrows(), 1):
            lines.append(f"  {rank}. {one_line(r['policy']):<{width}}  {ci(r)}  ({one_line(r['kind'], 12)})")
        if len(comp) > top:
            lines.append(f"  ... {len(comp) - top} more in the full table")
        if len(refs):
            lines.append("  floors: " + ", ".join(f"{one_line(r['policy'])} {ci(r)}" for _, r in refs.iterrows()))
        g = goal_check(board, str(tier), metric)
        if g["met"] is not None:
            lines.append("  " + _learned_words(g))
    if files:
        md = files.get("leaderboard_md")
        rest = [Path(p).name for k, p in files.items() if k != "leaderboard_md"]
        lines.append(f"full table: {md}" + (f" (and {', '.join(rest)} beside it)" if rest else "")
                     if md is not None else f"written: {', '.join(str(p) for p in files.values())}")
    return "\n".join(lines)


def _fmt_ci(est: float, lo: float, hi: float, digits: int = 4) -> str:
    if not np.isfinite(est):
        return "-"
    return f"{est:.{digits}f} [{lo:.{digits}f}, {hi:.{digits}f}]"


def _md(value: Any) -> str:
    """A value as Markdown table text: HTML special characters as entities (a Markdown viewer
    renders raw HTML), ``|`` escaped and line breaks removed."""
    import html

    return html.escape(" ".join(str(value).split()), quote=False).replace("|", "\\|")


def _robust_text(r: Mapping[str, Any], prefix: str) -> str:
    """"neither lost <ci> (<n> seeds); median <ci>" from a board row, or "-"."""
    kept = r.get(f"{prefix}_kept")
    if kept is None or not np.isfinite(r.get(f"{prefix}_median", math.nan)):
        return "-"
    text = "-" if not np.isfinite(kept) else _fmt_ci(kept, r[f"{prefix}_kept_lo"], r[f"{prefix}_kept_hi"])
    return (f"neither lost {text} ({int(r[f'{prefix}_kept_seeds'])} seeds); median "
            f"{_fmt_ci(r[f'{prefix}_median'], r[f'{prefix}_median_lo'], r[f'{prefix}_median_hi'])}")


def leaderboard_markdown(board: pd.DataFrame, prov: Mapping[str, Any] | None = None,
                         metrics: Sequence[str] = LEADERBOARD_METRICS) -> str:
    """The leaderboard as Markdown: one table per tier (errors in m, 95 % CIs in brackets)."""
    from agents.benchmark.floors import INFORMATION_FLOOR

    lines = ["# Leaderboard", "",
             "True-reference tracking error [m] (eq. (65)), steady state t >= 10 s and full run: IQM and mean "
             "over the tier's test episodes with 95 % stratified-bootstrap CIs (strata: training runs); "
             "P(better) = probability that an episode has a lower steady-state error than one of the tier's best "
             "classical baseline (rliable's probability of improvement, unpaired); paired diff = mean over the "
             "test seeds of (this policy's steady-state error - the best classical's on the same seed), runs "
             "averaged per seed, with a 95 % bootstrap CI over seeds (negative: better); robust paired diff = "
             "the same mean over the seeds where neither lost the target (no run terminated; their number in "
             "brackets) and the paired median over all seeds, each with its 95 % bootstrap CI: a lost target "
             "scores 20 m and can make a paired mean by itself; for a residual agent the "
             "same against its own base controller (obs: what its observation carries: raw = the env's fields "
             "and the base action, estimator = also a target filter's estimate), and, where that filter is one "
             "its base lacks, against the same law on that filter; a terminated episode scores the loss "
             "threshold" + ("; gap closed = (best generic classical IQM - this IQM) / (best generic classical IQM - "
                            "floor IQM), against the floor named in the column's head: the tier-prior floor (a "
                            "follower who knows the tier's published ranges, not the episode's draws) where it "
                            "converged, else the oracle-parameter floor (knows each episode's drawn parameters: a "
                            "bound no follower reaches); generic: not a model-aware controller (which knows a Leader "
                            "tier's generator)" if "gap_closed" in board and board["gap_closed"].notna().any()
                            else "") + ".", ""]
    m0 = metrics[0]
    for tier, sub in board.groupby("tier", sort=False):
        best = sub["best_classical"].iloc[0]
        lines += [f"## {_md(tier)}" + (f" (best classical: {_md(best)})" if best else ""), ""]
        head = ["policy", "kind", "runs x episodes"]
        for m in metrics:
            short = m.replace("true_", "").replace("_mean", "")
            head += [f"{short} IQM", f"{short} mean"]
        robust = "paired_diff_kept" in sub and sub["paired_diff_kept"].notna().any()
        head += ["vs best classical (IQM)", "paired diff vs best classical [m]"]
        head += ["robust paired diff vs best classical [m]"] if robust else []
        head += ["P(better) vs best classical", "terminated" + (" (lost targets)" if "lost_targets" in sub else "")]
        has_base = "base" in sub and (sub["base"].fillna("") != "").any()
        head += ["paired diff vs its base [m]"] if has_base else []
        has_filtered = "filtered_law" in sub and (sub["filtered_law"].fillna("") != "").any()
        head += ["paired diff vs its base's law on its observation's filter [m]"] if has_filtered else []
        gap = "gap_closed" in sub and sub["gap_closed"].notna().any()  # floors present (agents/benchmark/floors.py)
        gap_floor = str(sub["gap_floor"].iloc[0]) if gap and "gap_floor" in sub else ""
        both = gap and bool(gap_floor) and gap_floor != INFORMATION_FLOOR and sub["gap_closed_oracle"].notna().any()
        head += [f"gap closed ({gap_floor})" if gap_floor else "gap closed"] if gap else []
        head += [f"gap closed ({INFORMATION_FLOOR})"] if both else []
        lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        for _, r in sub.sort_values(f"{m0}_iqm").iterrows():
            cells = [f"**{_md(r['policy'])}**" if r["policy"] == best else _md(r["policy"]), _md(r["kind"]),
                     f"{r['runs']} x {r['episodes'] // max(r['runs'], 1)}"]
            for m in metrics:
                cells += [_fmt_ci(r[f"{m}_iqm"], r[f"{m}_iqm_lo"], r[f"{m}_iqm_hi"]),
                          _fmt_ci(r[f"{m}_mean"], r[f"{m}_mean_lo"], r[f"{m}_mean_hi"])]
            chg = r.get(f"{m0}_iqm_change_pct")
            cells.append("-" if chg is None or not np.isfinite(chg) else f"{chg:+.1f} %")
            pdiff = r.get("paired_diff")
            cells.append("-" if pdiff is None or not np.isfinite(pdiff) or r["policy"] == best else
                         _fmt_ci(pdiff, r["paired_diff_lo"], r["paired_diff_hi"]))
            if robust:
                cells.append("-" if r["policy"] == best else _robust_text(r, "paired_diff"))
            cells.append(_fmt_ci(r["poi"], r["poi_lo"], r["poi_hi"], 2))
            lost = f" ({int(r['lost_targets'])})" if "lost_targets" in r and np.isfinite(r["lost_targets"]) else ""
            cells.append(f"{100 * r['termination_rate']:.0f} %{lost}")
            if has_base:
                ci = _fmt_ci(r["paired_diff_base"], r["paired_diff_base_lo"], r["paired_diff_base_hi"])
                obs = f"; obs {_md(r['observation'])}" if r.get("observation") else ""
                rob = _robust_text(r, "paired_diff_base")
                rob = f"; robust: {rob}" if rob != "-" else ""
                cells.append(f"{ci} (base {_md(r['base'])}{obs}{rob})" if r.get("base") else "-")
            if has_filtered:
                ci = _fmt_ci(r["paired_diff_filtered"], r["paired_diff_filtered_lo"], r["paired_diff_filtered_hi"])
                cells.append(f"{ci} ({_md(r['filtered_law'])})" if r.get("filtered_law") else "-")
            if gap:
                cells.append("-" if not np.isfinite(r["gap_closed"]) else f"{r['gap_closed']:.2f}")
            if both:
                cells.append("-" if not np.isfinite(r["gap_closed_oracle"]) else f"{r['gap_closed_oracle']:.2f}")
            lines.append("| " + " | ".join(cells) + " |")
        lines.append("")
    if prov is not None:
        cfg = prov.get("config", {})
        import re

        text = json.dumps(prov, indent=1, default=str)
        fence = "`" * max(3, 1 + max((len(m) for m in re.findall("`+", text)), default=0))  # longer than any run
        lines += ["## Provenance", "", fence + "json", text, fence, ""]
        if "command" in cfg:
            cmd = str(cfg["command"])
            tick = "`" * (1 + max((len(m) for m in re.findall("`+", cmd)), default=0))
            pad = " " if len(tick) > 1 else ""
            lines[-5:-5] = [f"Reproduce: {tick}{pad}{cmd}{pad}{tick}", ""]
    return "\n".join(lines)


def plot_leaderboard(board: pd.DataFrame, path: str | Path, metric: str = "true_steady_mean",
                     prov: Mapping[str, Any] | None = None) -> None:
    """One panel per tier, stacked (the policy names need the width): the IQM of ``metric`` per
    policy with its 95 % CI (log scale)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker  # noqa: F401  (matplotlib.ticker below)

    tiers = list(dict.fromkeys(board["tier"]))
    sizes = [int((board["tier"] == t).sum()) for t in tiers]
    fig, axes = plt.subplots(len(tiers), 1, figsize=(10.0, 0.24 * sum(sizes) + 1.1 * len(tiers) + 0.6),
                             squeeze=False, gridspec_kw={"height_ratios": sizes})
    for ax, tier in zip(axes[:, 0], tiers, strict=True):
        sub = board[board["tier"] == tier].sort_values(f"{metric}_iqm", ascending=False)
        y = np.arange(len(sub))
        est = sub[f"{metric}_iqm"].to_numpy()
        err = np.vstack([est - sub[f"{metric}_iqm_lo"].to_numpy(), sub[f"{metric}_iqm_hi"].to_numpy() - est])
        colors = ["C1" if k == "classical" else "0.6" if k == "reference" else "C0" for k in sub["kind"]]
        ax.barh(y, est, xerr=err, color=colors, capsize=3)
        ax.set_yticks(y, sub["policy"], fontsize=8)
        ax.set_xscale("log")
        # labelled ticks at 1, 2, 5 x 10^k; no minor labels (they overlap on short ranges)
        lo = float(np.nanmin(sub[f"{metric}_iqm_lo"].to_numpy()))
        hi = float(np.nanmax(sub[f"{metric}_iqm_hi"].to_numpy()))
        decades = math.log10(hi / lo) if lo > 0 and hi > lo else 0.0
        subs = (1.0,) if decades > 1.5 else (1.0, 2.0, 5.0)  # 1-2-5 labels run together over wide ranges
        ax.xaxis.set_major_locator(matplotlib.ticker.LogLocator(base=10.0, subs=subs))
        ax.xaxis.set_major_formatter(matplotlib.ticker.FuncFormatter(lambda v, _: f"{v:g}"))
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.tick_params(axis="x", labelsize=8)
        ax.set_title(tier)
        ax.set_xlabel(f"IQM {metric.replace('true_', '')} [m]")
    grey = ", grey: floors (references)" if (board["kind"] == "reference").any() else ""
    fig.suptitle(f"true-reference error, IQM with 95 % CI (orange: classical, blue: learned{grey})", fontsize=9)
    fig.tight_layout(rect=(0.0, 0.0, 1.0, 1.0 - 0.4 / fig.get_figheight()))  # room for the title
    meta = {"Description": json.dumps(prov, default=str)} if prov is not None else None
    fig.savefig(path, dpi=120, metadata=meta)
    plt.close(fig)
