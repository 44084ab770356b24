"""Benchmark: the MPC (thrusters in its model, batched ADMM) against the previous MPC
(CasADi, one problem per env) on the same episodes of AUVFollow-Hard-v1, in one run.

    python -m experiments.bench_mpc [--envs 100] [--old-steps 40]

The new MPC runs N = ``--envs`` Hard envs (seeds ``--seed`` .. ``--seed + N - 1``, training
seeds) through the native vector env for whole episodes (1200 steps); the previous MPC runs
the same N envs from the same reset for the first ``--old-steps`` steps only (at its speed
whole episodes would take about half an hour), and the new MPC's figures over those first
steps are given beside its figures for the whole episodes. Per controller: the solve time per
env-step (the MPC's own part: linearisation and QP; median and 99th percentile over the
control steps, for the batch: the batched solve's wall time divided by N), the wall time per
env-step of the whole loop (env, estimator, observer, MPC) and the episodes/s it gives
(measured for the new MPC; for the previous one extrapolated from its first steps, and
marked so). Constraint satisfaction of the fixed-iteration ADMM: how far its solution was
outside its constraints before the final clip (max and share of env-steps above 1e-3, in
units of the force limit); the commands sent are always within the force and rate limits
(the final clip to the first step's exact bounds; tests/test_mpc.py).

The machine is shared (2 cores, other jobs): the load average is printed with the table.
Writes results/bench_mpc.md.
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

import gymnasium as gym
import numpy as np

import auv_follow_env  # noqa: F401
from controllers.mpc import CasadiMPCController, MPCController
from experiments.outputs import output_path, write_report


def _loop(venv, policy, seeds: list[int], steps: int) -> tuple[float, list[float], np.ndarray, np.ndarray]:
    """Run ``steps`` control steps from a reset; returns the loop's wall time, the solve time
    per env-step of each call, the true errors (steps, N) and ADMM's constraint violation
    (steps, N) (empty for the previous MPC)."""
    obs, _ = venv.reset(seed=seeds)
    start = np.ones(len(seeds), dtype=bool)
    errs, viol = [], []
    policy.solve_times.clear()
    t0 = time.perf_counter()
    for _ in range(steps):
        a, _ = policy.predict(obs, episode_start=start)
        start[:] = False
        if getattr(policy, "last_violation", None) is not None:
            viol.append(policy.last_violation.copy())
        obs, rew, term, trunc, _ = venv.step(a)
        errs.append(-np.asarray(rew))
    return time.perf_counter() - t0, list(policy.solve_times), np.asarray(errs), np.asarray(viol)


def main(argv: list[str] | None = None) -> str:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--envs", type=int, default=100, help="Hard envs in the batch")
    p.add_argument("--seed", type=int, default=500, help="first seed (training seeds: < 1,000,000)")
    p.add_argument("--old-steps", type=int, default=40, help="control steps the previous MPC runs")
    p.add_argument("--episode-s", type=float, default=None, help="episode length [s] (default 60; smoke tests)")
    p.add_argument("--out", type=Path, default=None,
                   help="Markdown output (default: results/bench_mpc.md; results/tmp/ with non-default settings)")
    a = p.parse_args(argv)
    for name in ("envs", "old_steps"):
        if getattr(a, name) < 1:
            p.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(a, name)}")
    if not 0 <= a.seed < 1_000_000:
        p.error(f"--seed must be a training seed in [0, 1000000), got {a.seed}")
    if a.episode_s is not None and not a.episode_s > 0:
        p.error(f"--episode-s must be > 0, got {a.episode_s}")
    a.out = output_path(a, p, Path("results/bench_mpc.md"))
    kw = {"episode_s": a.episode_s, "steady_start_s": a.episode_s / 2} if a.episode_s is not None else {}
    env_id = "AUVFollow-Hard-v1"
    seeds = list(range(a.seed, a.seed + a.envs))
    venv = gym.make_vec(env_id, num_envs=a.envs, **kw)
    spec = venv.unwrapped.task_spec if hasattr(venv, "unwrapped") else venv.task_spec
    T = spec.n_steps
    old_steps = min(a.old_steps, T)

    new = MPCController(spec)
    _loop(venv, new, seeds, 2)  # numba compile / cache load, outside the timing
    wall_new, st_new, err_new, viol = _loop(venv, new, seeds, T)
    old = CasadiMPCController(spec)
    wall_old, st_old, _, _ = _loop(venv, old, seeds, old_steps)
    venv.close()
    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3

    from agents.benchmark.stats import iqm

    steady = int(round(spec.steady_start_s / spec.dt))
    score = float(iqm(err_new[steady:].mean(axis=0)))
    ms_new, ms_new_first = 1e3 * np.asarray(st_new), 1e3 * np.asarray(st_new[:old_steps])
    ms_old = 1e3 * np.asarray(st_old)
    per_new = wall_new / (T * a.envs)
    per_old = wall_old / (old_steps * a.envs)
    rows = [
        ("MPC (thrusters in the model, batched ADMM), whole episodes", ms_new, f"{1e3 * per_new:.3f}",
         f"{a.envs / wall_new:.3f}"),
        (f"MPC (thrusters in the model, batched ADMM), first {old_steps} steps", ms_new_first, "-", "-"),
        (f"previous MPC (CasADi osqp per env, no actuator), first {old_steps} steps", ms_old, f"{1e3 * per_old:.3f}",
         f"{1.0 / (per_old * T):.4f} (extrapolated from its first {old_steps} steps)"),
    ]
    lines = ["# MPC solve time per control step", "",
             f"`python -m experiments.bench_mpc{'' if argv is None else ' ' + ' '.join(argv)}`: {env_id}, "
             f"N = {a.envs} envs batched (seeds {seeds[0]}-{seeds[-1]}), {T} steps per episode; "
             f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores shared with other jobs "
             f"(load average at the end {load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f}).", "",
             "Solve = the MPC's own part of one env-step (batched: the batch's solve / N). Env-step = the whole "
             "loop per env-step (env, estimator, observer, MPC). Episodes/s at N envs in one batch.", "",
             "| controller | solve median [ms] | solve p99 [ms] | env-step mean [ms] | episodes/s |",
             "|---|---|---|---|---|"]
    for label, ms, per, eps in rows:
        lines.append(f"| {label} | {np.median(ms):.3f} | {np.percentile(ms, 99):.3f} | {per} | {eps} |")
    speed = np.median(ms_old) / np.median(ms_new_first)
    lines += ["",
              f"Solve median over the same first {old_steps} steps: previous / new = {speed:.1f}x. "
              f"100 Hard episodes with the new MPC at this run's rate: {100 * T * per_new / 60:.1f} min "
              f"(the previous MPC: {100 * T * per_old / 60:.0f} min).", "",
              f"ADMM ({new.config.admm_iterations} iterations, warm-started) before the final clip: solution "
              f"outside its constraints by at most {viol.max():.2e} (force-limit units); env-steps with a violation "
              f"> 1e-3: {np.mean(viol > 1e-3):.2%}. The commands sent are always inside the force and rate limits.",
              "",
              f"The new MPC's steady-state true-reference error on these episodes (training seeds): IQM "
              f"{score:.4f} m.", ""]
    text = "\n".join(lines)
    return write_report(a.out, text)


if __name__ == "__main__":
    main()
