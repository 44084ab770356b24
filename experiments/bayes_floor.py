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

from agents.benchmark.bayes_floor import DEFAULT_CHILDREN, DEFAULT_PARTICLES
from agents.benchmark.floors import leader_floor
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
    ap.add_argument("--check-seeds", type=int, default=40,
                    help="the doubling check runs 2N on the first K test seeds (default %(default)s)")
    ap.add_argument("--cache", type=Path, default=CACHE)
    ap.add_argument("--out", type=Path, default=ROOT / "results")
    a = ap.parse_args(argv)
    rows, per = [], {}
    res: dict[tuple[str, int], tuple[pd.DataFrame, float]] = {}
    for n in (a.particles, 2 * a.particles):  # every tier at N first: the leaderboard's floor rows
        for tier in a.tiers:
            seeds = list(LEADER_TIERS[tier].test_seeds)
            if n != a.particles:
                seeds = seeds[:a.check_seeds]
            t0 = time.perf_counter()
            df = leader_floor(tier, seeds, particles=n, children=a.children, cache_dir=str(a.cache), progress=True)
            res[tier, n] = (df, (time.perf_counter() - t0) / len(df))
    for tier in a.tiers:
        (full, t1), (d2, t2) = res[tier, a.particles], res[tier, 2 * a.particles]
        d1 = full[full["seed"].isin(d2["seed"])]  # N on the check's episodes (the same filter seeds)
        s1, s2 = _summary(d1), _summary(d2)
        per[tier] = (full, d2, d1)
        s0 = _summary(full)
        rows.append({"tier": tier, "floor IQM, N, 100 episodes [m]": s0["iqm"],
                     "floor mean, N, 100 episodes [m]": s0["mean"], "realised IQM, N [m]": s0["realised_iqm"],
                     "realised mean, N [m]": s0["realised_mean"], "N": a.particles,
                     "check episodes": len(d2), "floor IQM, N [m]": s1["iqm"], "floor IQM, 2N [m]": s2["iqm"],
                     "IQM change": s2["iqm"] / s1["iqm"] - 1.0, "floor mean, N [m]": s1["mean"],
                     "floor mean, 2N [m]": s2["mean"], "mean change": s2["mean"] / s1["mean"] - 1.0,
                     "realised IQM, 2N [m]": s2["realised_iqm"], "realised / expected (IQM, 2N)":
                     s2["realised_iqm"] / s2["iqm"], "median ESS / N (2N)": s2["median_ess"],
                     "dropped packets": s2["dropped"], "s per episode, N": t1, "s per episode, 2N": t2})
    table = pd.DataFrame(rows)
    a.out.mkdir(parents=True, exist_ok=True)
    md = ["# The Leader tiers' information floor: convergence", "",
          "`python -m experiments.bayes_floor` (published test seeds, 100 per tier; steady-state window; the floor is "
          "the posterior's expected distance to its spatial median, per episode; realised: the median's distance to "
          "the true reference point; IQM and mean over episodes).", "",
          f"Particles kept between fixes: N on all 100 episodes (the leaderboard's floor rows), and for the doubling "
          f"check N and 2N on the first {a.check_seeds} (the same episodes and filter seeds), each particle weighted "
          f"with {a.children} continuations at a fix. Times are per episode on this machine, with other jobs "
          "running (the N rows may come from the cache: then near zero).", "",
          _markdown(table), ""]
    (a.out / "bayes_floor.md").write_text("\n".join(md))
    _plot(per, a.particles, a.out / "bayes_floor.png")
    print("\n".join(md))
    return 0


def _markdown(table: pd.DataFrame) -> str:
    """One column per tier, one row per quantity."""
    t = table.set_index("tier")
    lines = ["| quantity | " + " | ".join(t.index) + " |", "|---|" + "---|" * len(t.index)]
    for q in t.columns:
        cells = []
        for v in t[q]:
            if "change" in q:
                cells.append(f"{v:+.2%}")
            elif isinstance(v, (float, np.floating)):
                cells.append(f"{v:.4g}")
            else:
                cells.append(str(v))
        lines.append(f"| {q} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _plot(per: dict, n: int, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import NullFormatter

    fig, ax = plt.subplots(2, len(per), figsize=(5.0 * len(per), 8.4), squeeze=False)
    for c, (tier, (d1, d2, d1c)) in enumerate(per.items()):
        x = d1c.set_index("seed").loc[d2["seed"], "expected_steady_mean"].to_numpy()
        y = d2["expected_steady_mean"].to_numpy()
        a0 = ax[0, c]
        a0.plot(x, y, ".", alpha=0.7)
        lo, hi = np.nanmin([np.nanmin(x), np.nanmin(y)]), np.nanmax([np.nanmax(x), np.nanmax(y)])
        a0.plot([lo, hi], [lo, hi], "k-", lw=0.8)
        a0.set(title=f"{tier}: floor per episode, N and 2N", xlabel=f"N = {n} [m]", ylabel=f"2N = {2 * n} [m]")
        a1 = ax[1, c]
        a1.loglog(d1["expected_steady_mean"], d1["realised_steady_mean"], ".", alpha=0.7)
        e = d1["expected_steady_mean"]
        a1.plot([e.min(), e.max()], [e.min(), e.max()], "k-", lw=0.8)
        a1.set(title=f"{tier}: realised vs expected, N", xlabel="expected (the floor) [m]",
               ylabel="realised: the median's error [m]")
    for a_ in ax.ravel():
        a_.xaxis.set_minor_formatter(NullFormatter())
        a_.yaxis.set_minor_formatter(NullFormatter())
        a_.grid(alpha=0.3, which="both")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
