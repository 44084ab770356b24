"""The generic IMM fitted on the learned estimator's own data and loss: is the learned
estimator's win one of learning, or of fitting on more data with the right loss?

    python -m experiments.imm_same_data                 # Leader-Medium and Leader-Hard, about 3 minutes

A learned filter's win over a classical one is fair only against the classical filter fitted to
the same data with the same loss: tuning the Kalman filter on the same loss has reversed
published wins. The generic IMM of PROPOSED_IMM_DOB was fitted on 64 episodes recorded under
PROPOSED_KF_DOB by the IQM of the per-episode steady-window mean (experiments/leader_estimators.py,
``controllers.LEADER_IMM``). The learned estimator (agents/training/learned_estimator.py) was
trained on 4,096 episodes under PROPOSED_IMM_DOB (training seeds 100,000 + 10,000 x run seed +
[0, 4096); here run seed 0's) with the mean Euclidean error of the present reference point over
every step where the IMM has a fix and the episode runs.

Here the IMM's four settings (q_u, q_r, q_h, tau_s; the values of leader_estimators.py's grid,
each axis widened by two values beyond both ends: :data:`AXES`) are fitted by that loss on those
4,096 episodes, by coordinate descent from the committed setting: each pass tries every value of
one setting with the others held, keeps the best, and the passes stop when one changes nothing.
The fitted IMM is then scored with the same loss on the learned estimator's validation
episodes (900,000-900,255), beside the committed IMM and the committed learned-estimator runs'
own validation error (their ``config.yaml``). Nothing here sees a test seed. Writes results/imm_same_data.md.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import yaml

from agents.training.learned_estimator import N_FEATURES, record_episodes
from auv_follow_env.layout import OBS_DIM_V1
from auv_follow_env.tiers import LEADER_TIERS
from controllers import LEADER_IMM
from controllers.estimator import EstimatorConfig, TargetEstimator
from controllers.hierarchical import reference_point
from experiments.leader_estimators import GRID, imm_config
from experiments.outputs import output_path, write_report

TIERS = ("Leader-Medium", "Leader-Hard")
TRAIN_FIRST, N_TRAIN = 100_000, 4096  #: run seed 0's training episodes
VAL_FIRST, N_VAL = 900_000, 256
RUNS = Path("results/benchmark/runs")
LEARNED = {"Leader-Medium": "le1-LeaderMedium", "Leader-Hard": "le2-LeaderHard"}
#: each setting's values, in the order (q_u, q_r, q_h, tau_s): leader_estimators.GRID's axes, each
#: widened by two values beyond both ends (a fit that stops at an end of its grid has not fitted)
AXES = ((1e-4, 3e-4, *sorted({g[0] for g in GRID}), 0.3, 1.0),
        (1e-5, 3e-5, *sorted({g[1] for g in GRID}), 0.1, 0.3),
        (1e-6, 1e-5, *sorted({g[2] for g in GRID}), 1e-2, 1e-1),
        (1.0, 2.0, *sorted({g[3] for g in GRID}), 100.0, 300.0))
KEYS = ("imm_q_u", "imm_q_r", "imm_q_h", "imm_tau_s")


def loss(config: EstimatorConfig, data: dict, spec) -> float:
    """The learned estimator's loss of an IMM setting on recorded episodes: the mean error [m]
    of the present reference point over the masked steps (the IMM has a fix, the episode runs)."""
    X, Y, M = data["X"], data["Y"], data["M"]
    truth = X[..., OBS_DIM_V1:OBS_DIM_V1 + 2].astype(np.float64) + Y  # the default IMM's point + its error
    est = TargetEstimator(spec, config)
    T, n = M.shape
    tot, cnt = 0.0, 0
    for k in range(T):
        e = est.step(X[k, :, :OBS_DIM_V1].astype(np.float64), np.full(n, k == 0), with_cov=False)
        xr, yr, _ = reference_point(e.rel_x, e.rel_y, e.rel_psi, spec.p_d, spec.psi_d)
        ok = M[k] & e.valid
        err = np.hypot(xr - truth[k, :, 0], yr - truth[k, :, 1])
        tot += float(err[ok].sum())
        cnt += int(ok.sum())
    return tot / max(cnt, 1)


def fit(tier: str, train: dict, spec, log) -> tuple[tuple[float, ...], float, int]:
    base = EstimatorConfig.for_spec(spec)
    start = tuple(LEADER_IMM[tier][k] for k in KEYS)
    seen: dict[tuple[float, ...], float] = {}

    def score(g: tuple[float, ...]) -> float:
        if g not in seen:
            seen[g] = loss(imm_config(base, *g), train, spec)
            log(f"{tier} {g}: {seen[g]:.4f}")
        return seen[g]

    best = start
    score(best)
    changed = True
    while changed:
        changed = False
        for i, values in enumerate(AXES):
            for v in values:
                g = best[:i] + (v,) + best[i + 1:]
                if score(g) < score(best):
                    best, changed = g, True
    return best, seen[best], len(seen)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--tiers", nargs="+", default=list(TIERS), choices=list(TIERS))
    p.add_argument("--out", default=None, help="Markdown output (default: results/imm_same_data.md)")
    a = p.parse_args(argv)
    out = output_path(a, p, Path("results/imm_same_data.md"))
    t0 = time.perf_counter()

    def log(msg: str) -> None:
        print(f"[{time.perf_counter() - t0:6.0f} s] {msg}", flush=True)

    rows = []
    for tier in a.tiers:
        env_id = LEADER_TIERS[tier].env_id
        train = record_episodes(env_id, TRAIN_FIRST, N_TRAIN)
        assert train["X"].shape[-1] == N_FEATURES
        import gymnasium as gym

        probe = gym.make(env_id)
        spec = probe.unwrapped.task_spec
        probe.close()
        best, train_loss, tried = fit(tier, train, spec, log)
        del train
        val = record_episodes(env_id, VAL_FIRST, N_VAL)
        base = EstimatorConfig.for_spec(spec)
        committed = tuple(LEADER_IMM[tier][k] for k in KEYS)
        v_committed = loss(imm_config(base, *committed), val, spec)
        v_fitted = loss(imm_config(base, *best), val, spec)
        learned = []
        for r in sorted(RUNS.glob(f"{LEARNED[tier]}-s*")):
            cfg = yaml.safe_load((r / "config.yaml").read_text())
            learned.append((r.name, float(cfg["result"]["val_m"]), float(cfg["result"]["val_imm_m"])))
        lv = np.array([x[1] for x in learned])
        rows.append(f"| {tier} | {committed} | {v_committed:.4f} | {best} ({tried} settings tried; training loss "
                    f"{train_loss:.4f}) | {v_fitted:.4f} | {lv.min():.4f}-{lv.max():.4f} ({len(lv)} runs) | "
                    f"{(v_committed - v_fitted) / max(v_committed - lv.mean(), 1e-12):.2f} |")
        log(f"{tier}: committed {v_committed:.4f}, fitted {v_fitted:.4f}, learned {lv.mean():.4f} "
            f"(its record of the IMM: {np.mean([x[2] for x in learned]):.4f})")
    lines = ["# The generic IMM fitted on the learned estimator's data and loss", "",
             "Reproduce: `python -m experiments.imm_same_data` (method in its docstring). Loss: the mean error [m] "
             "of the present reference point over every step where the IMM has a fix and the episode runs, "
             f"fitted on the learned estimator's {N_TRAIN:,} training episodes (seeds {TRAIN_FIRST:,}-"
             f"{TRAIN_FIRST + N_TRAIN - 1:,}, under PROPOSED_IMM_DOB), scored on its {N_VAL} validation episodes "
             f"({VAL_FIRST:,}-{VAL_FIRST + N_VAL - 1:,}). Settings (q_u, q_r, q_h, tau_s).", "",
             "| tier | committed IMM setting | its validation loss | IMM fitted on the same data and loss "
             "| its validation loss | learned estimator runs, validation loss | share of the learned gain the "
             "fit takes |", "|---|---|---|---|---|---|---|", *rows, "",
             f"Wall clock: {time.perf_counter() - t0:.0f} s.", ""]
    write_report(out, "\n".join(lines))


if __name__ == "__main__":
    main()
