"""The Leader tiers' information floor and its convergence: the particle floor
(:mod:`agents.benchmark.bayes_floor`) with N and 2N particles on the same episodes.

    python -m experiments.bayes_floor                    # the three Leader tiers, published test seeds
    python -m experiments.bayes_floor --tiers Leader-Hard --particles 4096

Writes ``results/bayes_floor.md`` (per tier: the floor's IQM and mean for N and 2N with their
relative change, the realised error of the filter's median, the effective sample size at the
fixes, the cost per episode) and ``results/bayes_floor.png`` (per episode: 2N against N, and the
realised against the expected error). The N-particle rows are cached where the leaderboard's
floor rows look for them (``--cache``), so the leaderboard reuses them.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import pandas as pd

from agents.benchmark.bayes_floor import DEFAULT_CHILDREN, DEFAULT_PARTICLES, leader_floor
from agents.benchmark.stats import iqm
from auv_follow_env.tiers import LEADER_TIERS

ROOT = Path(__file__).resolve().parents[1]
CACHE = ROOT / "results" / "tmp" / "bench-cache"


def _summary(df: pd.DataFrame) -> dict[str, float]:
    ex, re = df["expected_steady_mean"].to_numpy(), df["realised_steady_mean"].to_numpy()
    return {"iqm": iqm(ex), "mean": float(np.nanmean(ex)), "realised_iqm": iqm(re),
            "realised_mean": float(np.nanmean(re)), "median_ess": float(df["median_ess_share"].median()),
            "min_ess": float(df["min_ess_share"].min()), "dropped": int(df["dropped"].sum())}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tiers", nargs="+", default=list(LEADER_TIERS), choices=list(LEADER_TIERS))
    ap.add_argument("--particles", type=int, default=DEFAULT_PARTICLES, help="N (the check runs N and 2N)")
    ap.add_argument("--children", type=int, default=DEFAULT_CHILDREN)
    ap.add_argument("--cache", type=Path, default=CACHE)
    ap.add_argument("--out", type=Path, default=ROOT / "results")
    a = ap.parse_args(argv)
    rows, per = [], {}
    res: dict[tuple[str, int], tuple[pd.DataFrame, float]] = {}
    for n in (a.particles, 2 * a.particles):  # every tier at N first: the leaderboard's floor rows
        for tier in a.tiers:
            t0 = time.perf_counter()
            df = leader_floor(tier, particles=n, children=a.children, cache_dir=str(a.cache), progress=True)
            res[tier, n] = (df, (time.perf_counter() - t0) / len(df))
    for tier in a.tiers:
        (d1, t1), (d2, t2) = res[tier, a.particles], res[tier, 2 * a.particles]
        s1, s2 = _summary(d1), _summary(d2)
        per[tier] = (d1, d2)
        rows.append({"tier": tier, "N": a.particles, "floor IQM, N [m]": s1["iqm"], "floor IQM, 2N [m]": s2["iqm"],
                     "IQM change": s2["iqm"] / s1["iqm"] - 1.0, "floor mean, N [m]": s1["mean"],
                     "floor mean, 2N [m]": s2["mean"], "mean change": s2["mean"] / s1["mean"] - 1.0,
                     "realised IQM, 2N [m]": s2["realised_iqm"], "realised / expected (IQM, 2N)":
                     s2["realised_iqm"] / s2["iqm"], "median ESS / N (2N)": s2["median_ess"],
                     "dropped packets": s2["dropped"], "s per episode, N": t1, "s per episode, 2N": t2})
    table = pd.DataFrame(rows)
    a.out.mkdir(parents=True, exist_ok=True)
    md = ["# The Leader tiers' information floor: convergence", "",
          "`python -m experiments.bayes_floor` (published test seeds, 100 per tier; steady-state window; the floor is "
          "the posterior's expected distance to its spatial median, per episode; IQM and mean over episodes).", "",
          f"Particles kept between fixes N and 2N, each weighted with {a.children} continuations at a fix. Times are "
          "per episode on this machine (cold caches: the N rows may come from the cache).", "",
          _markdown(table), ""]
    (a.out / "bayes_floor.md").write_text("\n".join(md))
    _plot(per, a.particles, a.out / "bayes_floor.png")
    print("\n".join(md))
    return 0


def _markdown(table: pd.DataFrame) -> str:
    def cell(v: object) -> str:
        if isinstance(v, (float, np.floating)):
            return f"{v:.4g}"
        return str(v)

    lines = ["| " + " | ".join(table.columns) + " |", "|" + "---|" * len(table.columns)]
    for _, r in table.iterrows():
        lines.append("| " + " | ".join(f"{r[c]:+.2%}" if "change" in c else cell(r[c]) for c in table.columns) + " |")
    return "\n".join(lines)


def _plot(per: dict, n: int, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(2, len(per), figsize=(4.2 * len(per), 8), squeeze=False)
    for c, (tier, (d1, d2)) in enumerate(per.items()):
        x, y = d1["expected_steady_mean"], d2["expected_steady_mean"]
        a0 = ax[0, c]
        a0.loglog(x, y, ".", alpha=0.7)
        lo, hi = np.nanmin([x.min(), y.min()]), np.nanmax([x.max(), y.max()])
        a0.plot([lo, hi], [lo, hi], "k-", lw=0.8)
        a0.set(title=f"{tier}: floor per episode", xlabel=f"N = {n} [m]", ylabel=f"2N = {2 * n} [m]")
        a1 = ax[1, c]
        a1.loglog(d2["expected_steady_mean"], d2["realised_steady_mean"], ".", alpha=0.7)
        e = d2["expected_steady_mean"]
        a1.plot([e.min(), e.max()], [e.min(), e.max()], "k-", lw=0.8)
        a1.set(title=f"{tier}: realised vs expected (2N)", xlabel="expected (the floor) [m]",
               ylabel="realised: the median's error [m]")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
