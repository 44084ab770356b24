"""Benchmark: the MPC's solve time per control step (median, 99th percentile, max), for the
default settings and a few alternatives, on S4 through the single env (one solve per step,
what a leaderboard episode costs), with the tracking error each setting reaches.

    python -m experiments.bench_mpc [--episodes 3]

Requirement (issue 11): median < 10 ms and p99 < 50 ms per step on this machine (2 cores,
shared). The QP-solution column counts steps whose QP solution broke the force bounds by
more than 1e-6 (before the controller's safety clip). Writes results/bench_mpc.md.
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from dataclasses import replace
from pathlib import Path

import gymnasium as gym
import numpy as np

import auv_follow_env  # noqa: F401
from controllers.evaluation import evaluate
from controllers.mpc import MPCConfig, MPCController
from experiments.outputs import output_path, write_report

DEFAULT = MPCConfig()
VARIANTS: tuple[tuple[str, MPCConfig], ...] = (
    ("default: osqp, 2 SQP iterations, 20 intervals of 0.15 s", DEFAULT),
    ("real-time iteration: osqp, 1 SQP iteration", replace(DEFAULT, sqp_iterations=1)),
    ("longer: osqp, 2 iterations, 30 intervals of 0.15 s (4.5 s)", replace(DEFAULT, intervals=30, horizon_s=4.5)),
    ("qrqp, 2 SQP iterations", replace(DEFAULT, qp_solver="qrqp")),
)


class _BoundCheck:
    """Counts the steps whose QP solution broke the force bounds (before the safety clip)."""

    def __init__(self, mpc: MPCController) -> None:
        self.mpc, self.bad, self.steps = mpc, 0, 0
        self._forces = mpc.forces
        mpc.forces = self  # type: ignore[method-assign]

    def __call__(self, obs, mask):
        F = self._forces(obs, mask)
        self.steps += 1
        self.bad += int(np.any(np.abs(self.mpc.last_solution) > 1.0 + 1e-6))
        return F


def main(argv: list[str] | None = None) -> str:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--episodes", type=int, default=3, help="S4 episodes (seeds 0..N-1) per setting")
    p.add_argument("--out", type=Path, default=None,
                   help="Markdown output (default: results/bench_mpc.md; results/tmp/ with non-default settings)")
    p.add_argument("--episode-s", type=float, default=None, help="episode length [s] (default 60; smoke tests)")
    a = p.parse_args(argv)
    if a.episodes < 1:
        p.error(f"--episodes must be >= 1, got {a.episodes}")
    if a.episode_s is not None and not a.episode_s > 0:
        p.error(f"--episode-s must be > 0, got {a.episode_s}")
    a.out = output_path(a, p, Path("results/bench_mpc.md"))
    kw = {"episode_s": a.episode_s, "steady_start_s": min(10.0, a.episode_s / 2)} if a.episode_s is not None else {}
    spec = gym.make("AUVFollow-S4-v0", **kw).unwrapped.task_spec
    rows = []
    for label, cfg in VARIANTS:
        mpc = MPCController(spec, cfg)
        check = _BoundCheck(mpc)
        t0 = time.perf_counter()
        df = evaluate(mpc, "AUVFollow-S4-v0", range(a.episodes), env_kwargs=kw, progress=False)
        wall = time.perf_counter() - t0
        ms = 1e3 * np.asarray(mpc.solve_times)
        rows.append((label, np.median(ms), np.percentile(ms, 99), ms.max(), wall / (a.episodes * spec.n_steps) * 1e3,
                     df["true_steady_mean"].mean(), check.bad, check.steps))
        print(rows[-1], flush=True)
    lines = ["# MPC solve time per control step", "",
             f"`python -m experiments.bench_mpc --episodes {a.episodes}`: AUVFollow-S4-v0, seeds 0-{a.episodes - 1}, "
             f"single env, {a.episodes * spec.n_steps} steps per setting; "
             f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores (shared with other jobs).", "",
             "Solve = estimator-independent part: the SQP iterations of one env-step (QP data + QP solve). "
             "Env-step = everything per env-step through `evaluate` (env, estimator, observer, MPC).", "",
             "| setting | solve median [ms] | solve p99 [ms] | solve max [ms] | env-step mean [ms] | "
             "steady mean error [m] | steps with QP solution outside the force bounds |",
             "|---|---|---|---|---|---|---|"]
    for label, med, p99, mx, per, err, bad, steps in rows:
        lines.append(f"| {label} | {med:.2f} | {p99:.2f} | {mx:.1f} | {per:.2f} | {err:.4f} | {bad} / {steps} |")
    lines += ["", "Requirement: median < 10 ms, p99 < 50 ms per step (real time at 20 Hz).", ""]
    text = "\n".join(lines)
    return write_report(a.out, text)


if __name__ == "__main__":
    main()
