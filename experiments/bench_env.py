"""Speed of the single AUVFollow env through ``gym.make``, beside Gymnasium's Pendulum-v1.

Measures, in one run:

* steady-state steps/s of ``gym.make(id)`` (all default wrappers) with pre-sampled random
  actions, for AUVFollow-S4-v0 and Pendulum-v1, repeated ``--repeats`` times interleaved
  (best and median reported; the env is reset whenever an episode ends, and resets count
  towards the time);
* the first-call cost (import + make + reset + first step) in a fresh interpreter, once
  with an empty numba cache (``NUMBA_CACHE_DIR`` set to a new temporary directory, so every
  kernel is compiled) and once more with that now-warm cache.

Writes a Markdown table to ``results/bench_env.md`` and prints it.

    python experiments/bench_env.py --steps 200000
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import gymnasium as gym
import numpy as np

import auv_follow_env  # noqa: F401  (registers the ids)
from experiments.outputs import output_path, write_report

ENVS = ("AUVFollow-S4-v0", "AUVFollow-Hard-v1", "Pendulum-v1")
ROOT = Path(__file__).resolve().parents[1]

_FIRST_CALL = r"""
import json, time
t0 = time.perf_counter()
import gymnasium as gym
t1 = time.perf_counter()
import auv_follow_env  # noqa: F401
t2 = time.perf_counter()
env = gym.make("AUVFollow-S4-v0")
obs, _ = env.reset(seed=0)
t3 = time.perf_counter()
env.step(env.action_space.sample())
t4 = time.perf_counter()
env.step(env.action_space.sample())
t5 = time.perf_counter()
print(json.dumps({"import_gymnasium": t1 - t0, "import_env": t2 - t1, "make_reset": t3 - t2,
                  "first_step": t4 - t3, "second_step": t5 - t4, "total": t4 - t0}))
"""


def steps_per_second(env_id: str, actions: np.ndarray, seed: int = 0) -> tuple[float, int]:
    """(steps/s, episodes ended) of ``gym.make(env_id)`` over the given actions (resetting at
    episode ends)."""
    env = gym.make(env_id)
    env.reset(seed=seed)
    env.step(actions[0])  # warm-up: first step (and any lazy compile) outside the timing
    env.reset(seed=seed)
    step, reset = env.step, env.reset
    ends = 0
    t0 = time.perf_counter()
    for a in actions:
        _, _, term, trunc, _ = step(a)
        if term or trunc:
            ends += 1
            reset()
    dt = time.perf_counter() - t0
    env.close()
    return len(actions) / dt, ends


def first_call(cache_dir: str) -> dict[str, float]:
    """Run the first-call snippet in a fresh interpreter with NUMBA_CACHE_DIR=cache_dir."""
    env = {**os.environ, "NUMBA_CACHE_DIR": cache_dir}
    t0 = time.perf_counter()
    out = subprocess.run([sys.executable, "-c", _FIRST_CALL], capture_output=True, text=True,
                         env=env, check=True, cwd=str(ROOT))
    wall = time.perf_counter() - t0
    res = json.loads(out.stdout.strip().splitlines()[-1])
    res["process_wall"] = wall
    return res


def main(argv: list[str] | None = None) -> str:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=200_000, help="steps per measurement (default 200000)")
    ap.add_argument("--repeats", type=int, default=3, help="interleaved repetitions (default 3)")
    ap.add_argument("--out", type=Path, default=None,
                    help="Markdown output (default: results/bench_env.md; results/tmp/ with non-default settings)")
    args = ap.parse_args(argv)
    args.out = output_path(args, ap, ROOT / "results" / "bench_env.md")
    if args.steps < 1 or args.repeats < 1:
        ap.error("--steps and --repeats must be >= 1")

    rng = np.random.default_rng(0)
    actions = {}
    for env_id in ENVS:
        space = gym.make(env_id).action_space
        actions[env_id] = rng.uniform(space.low, space.high, (args.steps, *space.shape)).astype(space.dtype)

    load = ", ".join(f"{x:.2f}" for x in os.getloadavg())
    rates: dict[str, list[float]] = {e: [] for e in ENVS}
    episodes: dict[str, int] = {}
    for rep in range(args.repeats):
        for env_id in ENVS:
            r, episodes[env_id] = steps_per_second(env_id, actions[env_id])
            rates[env_id].append(r)
            print(f"  repeat {rep + 1}/{args.repeats}  {env_id:18s} {r:12,.0f} steps/s", flush=True)

    with tempfile.TemporaryDirectory(prefix="numba-cache-") as cache:
        cold = first_call(cache)
        warm = first_call(cache)

    auv, hard, pend = rates["AUVFollow-S4-v0"], rates["AUVFollow-Hard-v1"], rates["Pendulum-v1"]
    ratio_hard = statistics.median(hard) / statistics.median(pend)
    lines = [
        "# Single-env speed: AUVFollow-S4-v0 and AUVFollow-Hard-v1 vs Pendulum-v1",
        "",
        f"`python experiments/bench_env.py --steps {args.steps} --repeats {args.repeats}`; "
        f"Python {platform.python_version()}, numpy {np.__version__}, gymnasium {gym.__version__}, "
        f"numba {__import__('numba').__version__}, {platform.machine()}, {os.cpu_count()} CPUs; load average "
        f"(1, 5, 15 min) before the run {load}, after it {', '.join(f'{x:.2f}' for x in os.getloadavg())}.",
        "",
        "Through `gym.make` (Pendulum-v1: TimeLimit, OrderEnforcing, PassiveEnvChecker; AUVFollow: "
        "OrderEnforcing, PassiveEnvChecker - it truncates itself at episode_s), pre-sampled random",
        f"actions, {args.steps:,} steps per measurement, {args.repeats} repeats interleaved; resets at",
        "episode ends are included in the time (random thrust drives the AUV follower more than",
        "20 m from the reference, so many of its episodes end by termination before 1200 steps).",
        "",
        "| env | best steps/s | median steps/s | all runs | episodes ended per run |",
        "| --- | ---: | ---: | --- | ---: |",
    ]
    for env_id in ENVS:
        r = rates[env_id]
        lines.append(f"| {env_id} | {max(r):,.0f} | {statistics.median(r):,.0f} | "
                     + ", ".join(f"{x:,.0f}" for x in r) + f" | {episodes[env_id]:,} |")
    lines += [
        "",
        f"AUVFollow-S4-v0 / Pendulum-v1 (median): {statistics.median(auv) / statistics.median(pend):.2f}",
        "",
        f"AUVFollow-Hard-v1 / Pendulum-v1 (median): {ratio_hard:.2f} (goal >= 2): "
        f"{'met' if ratio_hard >= 2 else 'MISSED'}",
        "",
        "First call in a fresh interpreter (AUVFollow-S4-v0; seconds):",
        "",
        "| numba cache | import gymnasium | import auv_follow_env | make + reset | first step | "
        "second step | total to first step | process wall |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for name, res in (("cold (empty NUMBA_CACHE_DIR: compile)", cold), ("warm (same dir, second run)", warm)):
        lines.append(f"| {name} | {res['import_gymnasium']:.3f} | {res['import_env']:.3f} | "
                     f"{res['make_reset']:.3f} | {res['first_step']:.3f} | {res['second_step'] * 1e3:.3f} ms | "
                     f"{res['total']:.3f} | {res['process_wall']:.3f} |")
    table = "\n".join(lines) + "\n"
    print()
    write_report(args.out, table)
    return table


if __name__ == "__main__":
    main()
