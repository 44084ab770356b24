"""How much a policy moves its thrusters: mean |dF| per control step beside its tracking error.

    python -m experiments.smoothness --tier Easy --seeds 100 \\
        --policies PROPOSED_KF_DOB MPC "PPO scratch=results/benchmark/runs/bppo4-Easy-scratch-s0"
    python -m experiments.smoothness --tier Hard --env-kwarg thruster_rate=.inf ...   # an ablated tier

For each policy (a controller name, or ``label=run[,run...]`` as ``auv-follow benchmark`` takes
them) and each of the tier's first ``--seeds`` published test seeds, one episode on the vector
env (every policy and seed in one batch): per step the commanded force F = clip(a, -1, 1) * F_max
[N, N, N m]; reported per policy are the mean over episodes of mean |F_u|, mean |dF_u| per step
(dF_k = F_k - F_{k-1} within an episode), the same for sway and yaw, and the steady-state true
tracking error (the leaderboard's metric, its mean over the episodes). ``--env-kwarg KEY=VALUE``
(repeatable, the value read as YAML) changes the tier's env for every policy, e.g. an ablation of
its thrusters (the controllers are then built for the changed task). Writes a Markdown table
to ``--out`` (default ``results/tmp/smoothness.md``; ``results/smoothness.md`` is the committed
one, written with the defaults of ``docs/benchmark.md``'s table).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
from tqdm.auto import tqdm

import auv_follow_env  # noqa: F401  (registers the ids)
from agents.benchmark.policies import build_policy, parse_policy
from agents.benchmark.protocol import resolve_tier, tier_test_seeds
from agents.cli import key_value


def measure(policy, env_id: str, seeds: list[int], progress: bool = True,
            env_kwargs: dict | None = None) -> dict[str, float]:
    """Roll ``policy`` (SB3 ``predict`` protocol over a batch) on one episode per seed at once
    (``env_kwargs``: overrides of the env, as ``gym.make`` takes them)."""
    n = len(seeds)
    venv = gym.make_vec(env_id, num_envs=n, vectorization_mode="vector_entry_point", **(env_kwargs or {}))
    spec = venv.unwrapped.task_spec if hasattr(venv, "unwrapped") else venv.task_spec
    limits = np.asarray(spec.force_limits, dtype=np.float64)
    obs, _ = venv.reset(seed=seeds)
    if hasattr(policy, "reset"):
        policy.reset()
    alive = np.ones(n, dtype=bool)
    start = np.ones(n, dtype=bool)
    prev = np.zeros((n, 3))
    f_sum, df_sum, steps, df_steps = np.zeros((n, 3)), np.zeros((n, 3)), np.zeros(n), np.zeros(n)
    err_sum, err_n = np.zeros(n), np.zeros(n)
    spin_sum = np.zeros(n)  # |yaw rate| [rad/s] (observation field 2)
    t0 = float(spec.steady_start_s) if hasattr(spec, "steady_start_s") else 10.0
    for k in tqdm(range(int(spec.n_steps)), desc=f"{n} episodes", disable=not progress, leave=False, mininterval=2):
        action, _ = policy.predict(obs, episode_start=start, deterministic=True)
        force = np.clip(np.asarray(action, dtype=np.float64).reshape(n, 3), -1.0, 1.0) * limits
        live = alive.copy()
        f_sum[live] += np.abs(force[live])
        spin_sum[live] += np.abs(np.asarray(obs, dtype=np.float64)[live, 2])
        steps[live] += 1
        if k > 0:
            df_sum[live] += np.abs(force[live] - prev[live])
            df_steps[live] += 1
        prev = force
        obs, _, term, trunc, info = venv.step(action)
        t = (k + 1) * float(spec.dt)
        if t >= t0:
            err = np.asarray(info["tracking_error"], dtype=np.float64)
            err_sum[live] += err[live]
            err_n[live] += 1
        alive &= ~(term | trunc)
        start = np.zeros(n, dtype=bool)
        if not alive.any():
            break
    venv.close()
    f = f_sum / np.maximum(steps, 1)[:, None]
    df = df_sum / np.maximum(df_steps, 1)[:, None]
    out = {f"F_{a}": float(f[:, i].mean()) for i, a in enumerate("uvr")}
    out.update({f"dF_{a}": float(df[:, i].mean()) for i, a in enumerate("uvr")})
    out["steady_mean"] = float(np.mean(err_sum / np.maximum(err_n, 1)))
    out["yaw_rate"] = float(np.mean(spin_sum / np.maximum(steps, 1)))
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--tier", default="Easy")
    p.add_argument("--seeds", type=int, default=100, help="the tier's first K published test seeds")
    p.add_argument("--policies", nargs="+", required=True)
    p.add_argument("--env-kwarg", dest="env_kwargs", action="append", default=[],
                   metavar="KEY=VALUE", help="an override of the tier's env for every policy (repeatable; YAML value)")
    p.add_argument("--out", default="results/tmp/smoothness.md")
    a = p.parse_args(argv)
    name, env_id = resolve_tier(a.tier)
    seeds = list(tier_test_seeds(name))[: a.seeds]
    try:
        kw = dict(key_value(t) for t in a.env_kwargs)
    except argparse.ArgumentTypeError as exc:
        p.error(f"--env-kwarg: {exc}")
    try:
        probe = gym.make(env_id, **kw)
    except (TypeError, ValueError) as exc:
        p.error(f"--env-kwarg {kw} is refused by {env_id}: {exc}")
    task_spec, width = probe.unwrapped.task_spec, int(probe.observation_space.shape[0])
    probe.close()
    rows = []
    for item in a.policies:
        spec = parse_policy(item)
        runs = list(spec.runs) or [None]
        per_run = [measure(build_policy(spec, r, env_id, task_spec, width), env_id, seeds, env_kwargs=kw) for r in runs]
        row = {k: float(np.mean([m[k] for m in per_run])) for k in per_run[0]}
        rows.append((spec.label, len(runs), row))
        print(f"{spec.label}: steady error {row['steady_mean']:.4f} m, |dF_u| {row['dF_u']:.2f} N/step, "
              f"|F_u| {row['F_u']:.2f} N, |r| {row['yaw_rate']:.3f} rad/s", file=sys.stderr)
    changed = "".join(f" --env-kwarg {t}" for t in a.env_kwargs)
    lines = [f"# Thruster activity on {name} ({env_id}{', changed: ' + str(kw) if kw else ''})", "",
             f"Reproduce: `python -m experiments.smoothness --tier {name} --seeds {a.seeds}{changed} --policies "
             + " ".join(f"'{x}'" for x in a.policies) + "`", "",
             f"The tier's first {a.seeds} published test seeds, one deterministic episode each; a learned method's "
             "numbers are the mean over its runs. |dF| = mean over steps of |F_k - F_(k-1)| (commanded force, "
             "N or N m per 0.05 s step); |F| = mean commanded magnitude; steady error = mean over episodes of "
             "the steady-state (t >= 10 s) true tracking error [m]; |r| = mean yaw rate magnitude [rad/s] (the "
             "env scores position only: a policy that spins is not penalised by the score).", "",
             "| policy | runs | steady error [m] | mean abs dF_u [N/step] | mean abs dF_v [N/step] | "
             "mean abs dF_r [N m/step] | mean abs F_u [N] | mean abs F_v [N] | mean abs F_r [N m] | mean abs r "
             "[rad/s] |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for label, k, r in rows:
        lines.append(f"| {label} | {k} | {r['steady_mean']:.4f} | {r['dF_u']:.2f} | {r['dF_v']:.2f} | "
                     f"{r['dF_r']:.3f} | {r['F_u']:.2f} | {r['F_v']:.2f} | {r['F_r']:.3f} | {r['yaw_rate']:.3f} |")
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines) + "\n")
    print(f"wrote {out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
