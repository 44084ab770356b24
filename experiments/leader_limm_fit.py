"""The model-aware IMM of the Leader tiers (controllers/_leader_imm.py: the tier's own mode set,
shares, durations and lags), its settings fitted on training seeds exactly as the generic IMM's
were (experiments/leader_estimators.py): episodes recorded under PROPOSED_KF_DOB, each estimator
run open loop over them; score the IQM over episodes of the present reference point's error (per
episode the mean over t >= 10 s). The grid: the noise intensities on speed, heading and turn rate,
a scale of the modes' leaving rates (``sojourn_scale``: 1 is the tier's mean durations) and the
sojourns' Gamma shape (4: the generator's; 1: exponential sojourns, a Markov chain). Best on
fitting seeds 0-63, re-scored on check seeds 100-163 beside the generic IMM
(controllers.LEADER_IMM) and the linear filter, with the paired difference's bootstrap CI; nothing
here sees a test seed. Writes results/leader_limm_fit.md; the chosen settings are
controllers.LEADER_LIMM (a test checks they are this table's).

    python -m experiments.leader_limm_fit
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from itertools import product
from pathlib import Path

import numpy as np

from auv_follow_env.tiers import LEADER_TIERS
from controllers import LEADER_IMM
from controllers.estimator import EstimatorConfig
from experiments.leader_estimators import CHECK_SEEDS, FIT_SEEDS, boot_iqm, episode_errors, iqm, record
from experiments.outputs import output_path, write_report

#: (q_u [m^2/s^3], q_h [rad^2/s], q_r [rad^2/s^3], sojourn_scale [-], Gamma shape [-])
GRID = list(product([1e-3, 1e-2], [1e-3, 1e-2, 3e-2], [1e-4, 1e-3], [0.1, 0.25, 0.5, 1.0], [1, 4]))


def limm_config(base: EstimatorConfig, q_u: float, q_h: float, q_r: float, sojourn: float,
                shape: int) -> EstimatorConfig:
    return dataclasses.replace(base, model="LEADER_IMM", limm_q_u=q_u, limm_q_h=q_h, limm_q_r=q_r,
                               limm_sojourn=sojourn, limm_shape=shape)


def paired(a: np.ndarray, b: np.ndarray, reps: int = 2000, seed: int = 1) -> tuple[float, float, float]:
    """Mean of the paired differences a - b over episodes and its bootstrap 95 % CI."""
    d = (a - b)[np.isfinite(a - b)]
    rng = np.random.default_rng(seed)
    boots = [np.mean(d[rng.integers(0, len(d), len(d))]) for _ in range(reps)]
    return float(np.mean(d)), float(np.percentile(boots, 2.5)), float(np.percentile(boots, 97.5))


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--tiers", nargs="+", default=list(LEADER_TIERS), choices=list(LEADER_TIERS))
    p.add_argument("--out", default=None, help="Markdown output (default: results/leader_limm_fit.md)")
    a = p.parse_args(argv)
    a.out = output_path(a, p, Path("results/leader_limm_fit.md"))
    chosen: dict[str, dict] = {}
    lines = ["# The model-aware IMM of the Leader tiers, fitted on training seeds", "",
             "Reproduce: `python -m experiments.leader_limm_fit` (method in its docstring). Error of the estimated "
             "present reference point [m], per episode the mean over t >= 10 s, IQM over episodes (95 % bootstrap "
             f"CI). Fitting seeds {FIT_SEEDS[0]}-{FIT_SEEDS[-1]}, check seeds {CHECK_SEEDS[0]}-{CHECK_SEEDS[-1]} "
             "(training seeds; every test seed is >= 1,000,000). Generic IMM: `controllers.LEADER_IMM`; linear: "
             "the tiers' OU0 filter with the leader's moments.", "",
             "| tier | model-aware IMM, fit seeds (best of grid) | generic IMM, fit seeds | model-aware IMM, check "
             "seeds | generic IMM, check seeds | linear, check seeds | model-aware - generic, check seeds (paired "
             "mean [95 % CI]) | setting (q_u, q_h, q_r, sojourn scale, shape) |",
             "|---|---|---|---|---|---|---|---|"]
    t0 = time.perf_counter()
    for tier in a.tiers:
        fit, check = record(tier, FIT_SEEDS), record(tier, CHECK_SEEDS)
        base = EstimatorConfig.for_spec(fit["spec"])
        generic = dataclasses.replace(base, model="IMM", **LEADER_IMM[tier])
        scores = [iqm(episode_errors(limm_config(base, *g), fit)) for g in GRID]
        best = GRID[int(np.argmin(scores))]
        chosen[tier] = {"limm_q_u": best[0], "limm_q_h": best[1], "limm_q_r": best[2], "limm_sojourn": best[3],
                        "limm_shape": best[4]}
        gen_fit = episode_errors(generic, fit)
        mine, gen, lin = (episode_errors(limm_config(base, *best), check), episode_errors(generic, check),
                          episode_errors(base, check))

        def fmt(x: np.ndarray) -> str:
            lo, hi = boot_iqm(x)
            return f"{iqm(x):.4f} [{lo:.4f}, {hi:.4f}]"

        d, lo, hi = paired(mine, gen)
        lines.append(f"| {tier} | {min(scores):.4f} | {iqm(gen_fit):.4f} | {fmt(mine)} | {fmt(gen)} | {fmt(lin)} | "
                     f"{d:+.4f} m [{lo:+.4f}, {hi:+.4f}] | {', '.join(f'{v:g}' for v in best)} |")
        print(f"{tier}: done ({time.perf_counter() - t0:.0f} s)", flush=True)
    lines += ["", "The chosen settings (`controllers.LEADER_LIMM`, used by PROPOSED_LIMM_DOB on these tiers):", "",
              "```json", json.dumps(chosen, indent=1, sort_keys=True), "```", ""]
    write_report(Path(a.out), "\n".join(lines))
    return chosen


if __name__ == "__main__":
    main()
