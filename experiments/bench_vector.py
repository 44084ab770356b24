"""Speed of the native vector env against SyncVectorEnv, CartPole's native vector env and
the bare physics kernel, in env-steps per second.

    python -m experiments.bench_vector                    # N = 1, 64, 1024, 4096; ~1 s per cell
    python -m experiments.bench_vector --budget 0.2 --sizes 1 64

For each N: (a) ``AUVFollowVectorEnv`` (``gym.make_vec(..., "vector_entry_point")``),
(b) ``SyncVectorEnv`` of the single env (``gym.make_vec(..., "sync")``, with Gymnasium's
default wrappers), (c) ``gym.make_vec("CartPole-v1", ..., "vector_entry_point")`` and
(d) ``dynamics.integrate`` alone (follower + target RK4, no delay line, observation,
reward or Python). Actions are sampled before timing and cycled. Every cell runs a warm-up
step (numba compiles once, cached on disk), then doubles its step count until ``--budget``
seconds have passed (at least one timed step: a few steps for SyncVectorEnv at N = 4096).
Writes the Markdown table and the goal ratios at the largest N to ``--out``.
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import gymnasium as gym
import numba
import numpy as np

import auv_follow_env  # noqa: F401  (registers the ids)
from auv_follow_env import dynamics as dyn
from auv_follow_env.sim import BatchSim
from experiments.outputs import output_path


@dataclass
class Args:
    env_id: str = "AUVFollow-S4-v0"  #: the AUVFollow id benchmarked
    tier_id: str = "AUVFollow-Hard-v1"  #: the v1 id timed beside it (native, single-threaded)
    sizes: list[int] = field(default_factory=lambda: [1, 64, 1024, 4096])  #: numbers of envs N
    budget: float = 1.0  #: seconds of timed stepping per cell (after one warm-up step)
    max_sync_envs: int = 4096  #: skip SyncVectorEnv above this N (building it is slow)
    out: Path = Path("results/bench_vector.md")  #: Markdown output
    seed: int = 0  #: seed of the envs and of the pre-sampled actions
    parallel: bool = True  #: also time the native env with parallel=True (numba threads; off in the env by default)


#: goals at the largest N: (label, numerator column, denominator column, minimum ratio)
GOALS = (("native / SyncVectorEnv", "native", "sync", 50.0),
         ("native / CartPole native", "native", "cartpole", 0.5),
         ("native / bare kernel (>= 0.5 means step <= 2x kernel)", "native", "kernel", 0.5),
         ("v1 tier native / v0 native", "tier", "native", 0.7))
COLUMNS = {"native": "AUVFollow native", "sync": "AUVFollow SyncVectorEnv",
           "cartpole": "CartPole-v1 native", "kernel": "bare kernel (integrate)",
           "parallel": "AUVFollow native, parallel=True", "tier": "v1 tier native"}


def parse_args(argv: list[str] | None = None) -> Args:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--env-id", default=Args.env_id, help="AUVFollow id (default %(default)s)")
    p.add_argument("--tier-id", default=Args.tier_id, help="v1 id timed beside it (default %(default)s)")
    p.add_argument("--sizes", type=int, nargs="+", default=Args().sizes, help="numbers of envs")
    p.add_argument("--budget", type=float, default=Args.budget, help="timed seconds per cell")
    p.add_argument("--max-sync-envs", type=int, default=Args.max_sync_envs,
                   help="largest N for SyncVectorEnv (default %(default)s)")
    p.add_argument("--out", type=Path, default=None,
                   help="Markdown output file (default: results/bench_vector.md; results/tmp/ with non-default "
                        "settings)")
    p.add_argument("--seed", type=int, default=Args.seed, help="seed of envs and actions")
    p.add_argument("--no-parallel", dest="parallel", action="store_false",
                   help="skip the parallel=True column (numba threads)")
    a = p.parse_args(argv)
    if a.budget <= 0 or any(n < 1 for n in a.sizes):
        p.error("--budget must be > 0 and --sizes >= 1")
    a.out = output_path(a, p, Args.out)
    return Args(**vars(a))


def rate(step: Callable[[int], object], n_envs: int, budget: float) -> float:
    """Env-steps per second of ``step(j)`` (j = step counter), doubling the count until ``budget`` s."""
    step(0)  # warm-up (compilation, lazy allocation)
    count, j = 1, 1
    while True:
        t0 = time.perf_counter()
        for _ in range(count):
            step(j)
            j += 1
        elapsed = time.perf_counter() - t0
        if elapsed >= budget:
            return count * n_envs / elapsed
        count = max(count * 2, int(count * 1.2 * budget / max(elapsed, 1e-9)))


def _cycle(batches: np.ndarray) -> Callable[[int], np.ndarray]:
    k = len(batches)
    return lambda j: batches[j % k]


def bench_size(args: Args, n: int, rng: np.random.Generator) -> dict[str, float]:
    """One row: env-steps/s of each method at N = n."""
    k = 8  # distinct pre-sampled action batches, cycled
    acts = rng.uniform(-1.0, 1.0, (k, n, 3)).astype(np.float32)
    act = _cycle(acts)
    row: dict[str, float] = {}

    venv = gym.make_vec(args.env_id, num_envs=n, vectorization_mode="vector_entry_point")
    venv.reset(seed=args.seed)
    row["native"] = rate(lambda j: venv.step(act(j)), n, args.budget)
    venv.close()

    tenv = gym.make_vec(args.tier_id, num_envs=n, vectorization_mode="vector_entry_point")
    tenv.reset(seed=args.seed)
    row["tier"] = rate(lambda j: tenv.step(act(j)), n, args.budget)
    tenv.close()

    if n <= args.max_sync_envs:
        senv = gym.make_vec(args.env_id, num_envs=n, vectorization_mode="sync")
        senv.reset(seed=args.seed)
        row["sync"] = rate(lambda j: senv.step(act(j)), n, args.budget)
        senv.close()
    else:
        row["sync"] = float("nan")

    cenv = gym.make_vec("CartPole-v1", num_envs=n, vectorization_mode="vector_entry_point")
    cenv.reset(seed=args.seed)
    cacts = _cycle(rng.integers(0, 2, (k, n)))
    row["cartpole"] = rate(lambda j: cenv.step(cacts(j)), n, args.budget)
    cenv.close()

    sim = BatchSim(venv.unwrapped.config, n)
    sim.reset(np.arange(n), [np.random.default_rng(args.seed + i) for i in range(n)])
    forces = _cycle(acts.astype(np.float64) * np.asarray(venv.unwrapped.config.force_limits))
    t0 = np.zeros(n)
    row["kernel"] = rate(lambda j: dyn.integrate(sim.state, sim.params, sim.cfg, t0, forces(j)), n, args.budget)

    row["parallel"] = float("nan")
    if args.parallel:
        penv = gym.make_vec(args.env_id, num_envs=n, vectorization_mode="vector_entry_point", parallel=True)
        penv.reset(seed=args.seed)
        row["parallel"] = rate(lambda j: penv.step(act(j)), n, args.budget)
        penv.close()
    return row


def fmt(x: float) -> str:
    if not np.isfinite(x):
        return "-"
    return f"{x / 1e6:.2f} M" if x >= 1e6 else f"{x / 1e3:.1f} k"


def report(args: Args, rows: dict[int, dict[str, float]], load: str) -> str:
    lines = [f"# Vector env speed: {args.env_id} (and {args.tier_id}), env-steps/s", "",
             f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, Python "
             f"{platform.python_version()}, numpy {np.__version__}, numba {numba.__version__}, gymnasium "
             f"{gym.__version__}; {args.budget} s per cell after a warm-up step; load average before the run "
             f"{load}; columns (a)-(d) single-threaded, the last on {numba.get_num_threads()} numba threads.", "",
             "| N | " + " | ".join(COLUMNS.values()) + " | native us/env-step |",
             "|---|" + "---|" * (len(COLUMNS) + 1)]
    for n, row in rows.items():
        lines.append(f"| {n} | " + " | ".join(fmt(row[c]) for c in COLUMNS)
                     + f" | {1e6 / row['native']:.3f} |")
    n = max(rows)
    row = rows[n]
    lines += ["", f"Goals at N = {n}:", ""]
    for label, a, b, goal in GOALS:
        r = row[a] / row[b]
        verdict = "met" if r >= goal else ("n/a" if not np.isfinite(r) else "MISSED")
        lines.append(f"- {label}: {r:.2f} (goal >= {goal}): {verdict}")
    lines += ["", f"Ceiling for any single-threaded shell over this physics at N = {n}: the bare kernel alone "
              f"is {row['kernel'] / row['sync']:.1f}x SyncVectorEnv and {row['kernel'] / row['cartpole']:.3f}x "
              f"CartPole native; the native env reaches {row['native'] / row['kernel']:.2f} of the kernel's rate "
              f"(it also runs the delay line, observation, reward and info)."]
    return "\n".join(lines) + "\n"


def _load() -> str:
    try:
        return ", ".join(f"{x:.2f}" for x in os.getloadavg())
    except OSError:
        return "unknown"


def main(argv: list[str] | None = None) -> str:
    args = parse_args(argv)
    load = _load()
    rng = np.random.default_rng(args.seed)
    rows = {}
    for n in args.sizes:
        rows[n] = bench_size(args, n, rng)
        print(f"N={n}: " + ", ".join(f"{c} {fmt(v)}" for c, v in rows[n].items()), flush=True)
    text = report(args, rows, load)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(text)
    return text


if __name__ == "__main__":
    main()
