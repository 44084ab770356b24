"""The paper's published numbers (Tables 2-7) and its quantitative claims, as data and checks.

Used by ``experiments/reproduce_paper.py``. The CSVs are copied from ``shared/paper``
into ``experiments/data`` so the package is self-contained.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

DATA = Path(__file__).resolve().parent / "data"
SCENARIOS = ("S1", "S2", "S3", "S4")
CONTROLLERS = ("PID", "ROBUST_ONLY", "PRED_ONLY", "PROPOSED")
WINDOWS = ("full", "steady")
METRICS = ("mean", "rmse", "max")


def paper_results() -> pd.DataFrame:
    """Tables 4-7 in long form: scenario, window, metric, controller, value [m]."""
    wide = pd.read_csv(DATA / "paper_results.csv")
    return wide.melt(id_vars=["scenario", "window", "metric"], var_name="controller", value_name="value")


def lookup(df: pd.DataFrame, scenario: str, controller: str, window: str, metric: str) -> float:
    sel = df[(df.scenario == scenario) & (df.controller == controller) & (df.window == window)
             & (df.metric == metric)]
    return float(sel.value.iloc[0])


@dataclass(frozen=True)
class Claim:
    """A quantitative statement of Section 4.3 / the conclusions and how to check it."""

    id: str
    where: str
    text: str
    check: Callable[[pd.DataFrame], tuple[bool, str]]


def _reduction(df, sc, a, b, window, metric) -> float:
    """Percentage by which controller a is below controller b."""
    va, vb = lookup(df, sc, a, window, metric), lookup(df, sc, b, window, metric)
    return 100.0 * (1.0 - va / vb)


def _smallest(window: str, metric: str, who: str):
    def check(df):
        bits, ok = [], True
        for sc in SCENARIOS:
            vals = {c: lookup(df, sc, c, window, metric) for c in CONTROLLERS}
            best = min(vals, key=vals.get)
            ok &= best == who
            bits.append(f"{sc}: best {best} ({vals[best]:.3f}; {who} {vals[who]:.3f})")
        return ok, "; ".join(bits)
    return check


def _steady_all_three(df):
    bits, ok = [], True
    for sc in SCENARIOS:
        wins = [m for m in METRICS
                if min(CONTROLLERS, key=lambda c, m=m: lookup(df, sc, c, "steady", m)) == "PROPOSED"]
        ok &= len(wins) == 3
        bits.append(f"{sc}: PROPOSED best on {len(wins)}/3 ({', '.join(wins) or 'none'})")
    return ok, "; ".join(bits)


PUBLISHED_FULL_MEAN_REDUCTIONS = {  # Sec. 4.3 text: vs PID, ROBUST_ONLY, PRED_ONLY [%]
    "S1": (76.8, 29.6, 47.2), "S2": (80.0, 43.4, 72.7), "S3": (79.2, 34.5, 74.1), "S4": (73.9, 44.3, 68.3)}
PUBLISHED_STEADY_RMSE_REDUCTION = {"S1": 33.0, "S2": 54.0, "S3": 46.0, "S4": 50.0}  # vs ROBUST_ONLY [%]


def _full_mean_reductions(df):
    bits, ok = [], True
    for sc in SCENARIOS:
        red = [_reduction(df, sc, "PROPOSED", c, "full", "mean") for c in ("PID", "ROBUST_ONLY", "PRED_ONLY")]
        ok &= all(r > 0 for r in red)
        pub = PUBLISHED_FULL_MEAN_REDUCTIONS[sc]
        bits.append(f"{sc}: " + ", ".join(f"{r:+.1f}% (paper {p:.1f}%)" for r, p in zip(red, pub, strict=True)))
    return ok, "; ".join(bits)


def _steady_rmse_reduction(df):
    bits, ok = [], True
    for sc in SCENARIOS:
        r = _reduction(df, sc, "PROPOSED", "ROBUST_ONLY", "steady", "rmse")
        ok &= r >= 33.0
        bits.append(f"{sc}: {r:+.1f}% (paper {PUBLISHED_STEADY_RMSE_REDUCTION[sc]:.0f}%)")
    return ok, "; ".join(bits)


def _pid_deteriorates_most(df):
    parts, ok = [], True
    for window in WINDOWS:
        inc = {c: lookup(df, "S4", c, window, "mean") - lookup(df, "S1", c, window, "mean") for c in CONTROLLERS}
        worst = max(inc, key=inc.get)
        ok &= worst == "PID"
        parts.append(f"{window}-run mean S1->S4: " + ", ".join(f"{c} {v:+.3f} m" for c, v in inc.items())
                     + f" (largest: {worst})")
    return ok, "; ".join(parts)


def _pid_s2_steady_above_full(df):
    s, f = lookup(df, "S2", "PID", "steady", "mean"), lookup(df, "S2", "PID", "full", "mean")
    return s > f, f"PID S2 steady mean {s:.3f} m vs full-run mean {f:.3f} m"


CLAIMS: tuple[Claim, ...] = (
    Claim("C1", "Abstract; Sec. 4.3; Conclusions",
          "PROPOSED achieves the smallest (full-run) mean tracking error in all scenarios",
          _smallest("full", "mean", "PROPOSED")),
    Claim("C2", "Sec. 4.3 per scenario",
          "PROPOSED's full-run mean error is below PID, ROBUST_ONLY and PRED_ONLY by the stated percentages",
          _full_mean_reductions),
    Claim("C3", "Sec. 4.3 (second trend)", "ROBUST_ONLY has the smallest full-run RMSE in every scenario",
          _smallest("full", "rmse", "ROBUST_ONLY")),
    Claim("C4", "Sec. 4.3 (third trend)",
          "PROPOSED has the smallest steady-state mean, RMSE and max error in all four scenarios",
          _steady_all_three),
    Claim("C5", "Sec. 4.3 (third trend)",
          "PROPOSED's steady-state RMSE is 33-54% lower than ROBUST_ONLY's (checked: >= 33% in each scenario)",
          _steady_rmse_reduction),
    Claim("C6", "Sec. 4.3 (first trend); Conclusions",
          "From S1 to S4 PID deteriorates most (largest rise of the mean error, full run and steady state)",
          _pid_deteriorates_most),
    Claim("C7", "Sec. 4.3, S2", "PID's steady-state mean error exceeds its full-run mean in S2",
          _pid_s2_steady_above_full),
)


def paper_consistency() -> pd.DataFrame:
    """Rows of Tables 4-7 that violate RMSE^2 <= max * mean (true of any sample set)."""
    wide = pd.read_csv(DATA / "paper_results.csv")
    out = []
    for (sc, win), g in wide.groupby(["scenario", "window"]):
        vals = g.set_index("metric")
        for c in CONTROLLERS:
            mean, rmse, mx = (float(vals.loc[m, c]) for m in METRICS)
            if rmse ** 2 > mx * mean + 1e-12:
                out.append({"scenario": sc, "window": win, "controller": c, "rmse^2": rmse ** 2,
                            "max*mean": mx * mean})
    return pd.DataFrame(out)


def t_quantile_975(dof: int) -> float:
    """Two-sided 95% Student-t quantile (standard table values; normal beyond 30 dof)."""
    table = (12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228, 2.201, 2.179,
             2.160, 2.145, 2.131, 2.120, 2.110, 2.101, 2.093, 2.086, 2.080, 2.074, 2.069, 2.064,
             2.060, 2.056, 2.052, 2.048, 2.045, 2.042)
    if dof < 1:
        return float("nan")
    return table[dof - 1] if dof <= 30 else 1.96 + 2.4 / dof  # 1.96 + ~g1(z)/dof expansion


def mean_ci(x: np.ndarray) -> tuple[float, float]:
    """(mean, half-width of the 95% confidence interval) over seeds."""
    x = np.asarray(x, dtype=float)
    n = x.size
    if n < 2:
        return float(x.mean()), float("nan")
    return float(x.mean()), t_quantile_975(n - 1) * float(x.std(ddof=1)) / np.sqrt(n)
