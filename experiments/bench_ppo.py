"""Speed benchmark: SB3 PPO training throughput on AUVFollow-S4-v0 vs Gymnasium's Pendulum-v1.

Same PPO settings for both envs (SB3 defaults, rollout of 2048 samples: n_steps = 2048 //
n_envs), DummyVecEnv with 8 envs and with 1 env, ``--timesteps`` each, torch on one thread,
same process. Throughput = timesteps / wall clock of ``model.learn`` (collection and
updates), median of ``--repeats`` interleaved runs. Goal: AUVFollow >= 0.9 x Pendulum.
Also reports raw env stepping (random actions through ``gym.make``) for context. Writes ``results/bench_ppo.md``.

    python experiments/bench_ppo.py --timesteps 20000
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import gymnasium as gym
import numpy as np

import auv_follow_env  # noqa: F401  (registers the ids)
from experiments.outputs import output_path, write_report

ENVS = ("AUVFollow-S4-v0", "Pendulum-v1")


def ppo_throughput(env_id: str, n_envs: int, timesteps: int, seed: int = 0) -> float:
    """PPO timesteps per second of ``learn`` on ``n_envs`` DummyVecEnv copies of ``env_id``."""
    from stable_baselines3 import PPO
    from stable_baselines3.common.env_util import make_vec_env

    venv = make_vec_env(env_id, n_envs=n_envs, seed=seed)
    model = PPO("MlpPolicy", venv, n_steps=2048 // n_envs, batch_size=64, n_epochs=10, seed=seed, device="cpu")
    t0 = time.perf_counter()
    model.learn(total_timesteps=timesteps)
    dt = time.perf_counter() - t0
    steps = model.num_timesteps
    venv.close()
    return steps / dt


def env_step_us(env_id: str, steps: int = 20_000) -> float:
    """Microseconds per ``env.step`` with random actions through ``gym.make``."""
    env = gym.make(env_id)
    env.reset(seed=0)
    actions = [env.action_space.sample() for _ in range(1000)]
    t0 = time.perf_counter()
    for i in range(steps):
        _, _, term, trunc, _ = env.step(actions[i % 1000])
        if term or trunc:
            env.reset()
    return 1e6 * (time.perf_counter() - t0) / steps


def main(argv: list[str] | None = None) -> dict:
    import stable_baselines3
    import torch

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--timesteps", type=int, default=20_000, help="PPO timesteps per (env, n_envs) run")
    p.add_argument("--n-envs", type=int, nargs="+", default=[8, 1])
    p.add_argument("--repeats", type=int, default=3, help="interleaved repetitions; the median is reported")
    p.add_argument("--out", default=None,
                   help="Markdown output (default: results/bench_ppo.md; results/tmp/ with non-default settings)")
    a = p.parse_args(argv)
    a.out = output_path(a, p, Path("results/bench_ppo.md"))
    if a.timesteps <= 0:
        p.error(f"--timesteps={a.timesteps} is invalid: must be positive")
    if a.repeats <= 0:
        p.error(f"--repeats={a.repeats} is invalid: must be positive")
    torch.set_num_threads(1)
    rows = []
    for n in a.n_envs:
        runs = {e: [] for e in ENVS}
        for _ in range(a.repeats):  # interleaved, so drifts in machine load hit both envs alike
            for e in ENVS:
                runs[e].append(ppo_throughput(e, n, a.timesteps))
        fps = {e: float(np.median(v)) for e, v in runs.items()}
        rows.append((n, fps[ENVS[0]], fps[ENVS[1]], fps[ENVS[0]] / fps[ENVS[1]]))
    raw = {e: env_step_us(e) for e in ENVS}
    lines = ["# PPO training throughput: AUVFollow-S4-v0 vs Pendulum-v1", "",
             f"SB3 PPO (MlpPolicy, rollout 2048 samples, batch 64, 10 epochs), DummyVecEnv, {a.timesteps} "
             f"timesteps per run, median of {a.repeats} interleaved runs, torch 1 thread, same process. "
             "Goal: ratio >= 0.9.", "",
             "| n_envs | AUVFollow-S4-v0 (steps/s) | Pendulum-v1 (steps/s) | ratio |", "|---|---|---|---|"]
    lines += [f"| {n} | {x:.0f} | {y:.0f} | {r:.2f} |" for n, x, y, r in rows]
    lines += ["", "Raw `env.step` through `gym.make` (random actions): "
              + ", ".join(f"{e} {us:.1f} us" for e, us in raw.items()), "",
              f"python {platform.python_version()}, torch {torch.__version__}, stable-baselines3 "
              f"{stable_baselines3.__version__}, gymnasium {gym.__version__}, numpy {np.__version__}, "
              f"{platform.machine()}.", "",
              f"Reproduce: `python experiments/bench_ppo.py --timesteps {a.timesteps}`", ""]
    write_report(Path(a.out), "\n".join(lines))
    return {"rows": rows, "raw_us": raw}


if __name__ == "__main__":
    main()
