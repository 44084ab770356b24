"""Training throughput, side by side in one process: env-steps per second of

* SB3 PPO on Pendulum-v1 with 8 envs (agents/training/hyperparams/ppo.yml's Pendulum-v1 section);
* today's default PPO config on AUVFollow-Hard-v1 (SB3 PPO, 8 DummyVecEnv envs, ppo.yml's
  default section): from scratch, and residual on PROPOSED_KF_DOB with the per-env
  residual wrapper and the v0-era history (history_len 4, as in earlier versions);
* the batched path (``--algo bppo``, agents/training/batched_ppo.py) with the CLI defaults
  (agents/training/hyperparams/bppo.yml: 512 envs, estimator observation on v1): from scratch, and
  residual on PROPOSED_KF_DOB.

Each configuration is trained by :func:`agents.training.train` (the code ``python -m agents.cli
train`` runs) with evaluation, checkpoints, TensorBoard and the final score off; the rate is
the run's own ``steps_per_s`` (env steps over the training loop's wall clock, updates
included), the median of ``--repeats`` interleaved repetitions, after one untimed warm-up
of every configuration (numba compiles its kernels once). CPU-seconds are the process's
(time.process_time) over the whole ``train`` call. Writes ``results/bench_train.md``.

    python -m experiments.bench_train
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

from experiments.outputs import output_path, write_report

HARD = "AUVFollow-Hard-v1"
#: label -> (TrainConfig overrides, timesteps key)
CONFIGS: dict[str, dict] = {
    "SB3 PPO, Pendulum-v1, 8 envs": dict(algo="ppo", env_id="Pendulum-v1", mode="scratch", n_envs=8),
    "today's default PPO, Hard-v1, scratch": dict(algo="ppo", env_id=HARD, mode="scratch"),
    "today's default PPO, Hard-v1, residual PROPOSED_KF_DOB": dict(algo="ppo", env_id=HARD, mode="residual",
                                                                   controller="PROPOSED_KF_DOB", history_len=4),
    "bppo (CLI defaults), Hard-v1, scratch": dict(algo="bppo", env_id=HARD, mode="scratch"),
    "bppo (CLI defaults), Hard-v1, residual PROPOSED_KF_DOB": dict(algo="bppo", env_id=HARD, mode="residual",
                                                                   controller="PROPOSED_KF_DOB"),
}


def run_one(overrides: dict, timesteps: int, out: Path) -> dict:
    from agents.training.config import TrainConfig
    from agents.training.runner import train

    cfg = TrainConfig(**overrides, total_timesteps=timesteps, out_dir=str(out), checkpoint_freq=0, eval_freq=0,
                      progress_bar=False, tensorboard=False, final_eval=False)
    c0, w0 = time.process_time(), time.perf_counter()
    run = train(cfg)
    cpu, wall = time.process_time() - c0, time.perf_counter() - w0
    res = yaml.safe_load((Path(run) / "config.yaml").read_text())["result"]
    return {"steps": int(res["num_timesteps"]), "steps_per_s": float(res["steps_per_s"]), "cpu_s": cpu,
            "wall_s": wall, "n_envs": yaml.safe_load((Path(run) / "config.yaml").read_text())["run"]["n_envs"]}


def main(argv: list[str] | None = None) -> dict:
    import stable_baselines3
    import torch

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sb3-timesteps", type=int, default=16_384, help="env steps per SB3 run")
    p.add_argument("--bppo-timesteps", type=int, default=98_304, help="env steps per bppo run (6 updates)")
    p.add_argument("--repeats", type=int, default=2, help="interleaved repetitions; the median is reported")
    p.add_argument("--out", default=None,
                   help="Markdown output (default: results/bench_train.md; results/tmp/ with other settings)")
    a = p.parse_args(argv)
    a.out = output_path(a, p, Path("results/bench_train.md"))
    for name in ("sb3_timesteps", "bppo_timesteps", "repeats"):
        if getattr(a, name) <= 0:
            p.error(f"--{name.replace('_', '-')}={getattr(a, name)} is invalid: must be positive")
    steps = {k: (a.bppo_timesteps if c["algo"] == "bppo" else a.sb3_timesteps) for k, c in CONFIGS.items()}
    runs: dict[str, list[dict]] = {k: [] for k in CONFIGS}
    with tempfile.TemporaryDirectory(prefix="bench-train-") as tmp:
        for c in CONFIGS.values():  # warm-up: compile the kernels, load torch
            run_one(c, 2048 if c["algo"] != "bppo" else 16_384, Path(tmp) / "warmup")
        for _ in range(a.repeats):
            for k, c in CONFIGS.items():
                runs[k].append(run_one(c, steps[k], Path(tmp) / "runs"))
    med = {k: {f: float(np.median([r[f] for r in v])) for f in ("steps_per_s", "cpu_s", "wall_s", "steps")}
           for k, v in runs.items()}
    keys = list(CONFIGS)
    pend, old_s, old_r, new_s, new_r = (med[k]["steps_per_s"] for k in keys)
    ratios = {"scratch": new_s / old_s, "residual": new_r / old_r, "residual_vs_pendulum": new_r / pend}
    load = os.getloadavg()[0]
    lines = ["# Training throughput: today's PPO vs the batched path (bppo)", "",
             "One process, every configuration trained by `agents.training.train` (evaluation, checkpoints, "
             "TensorBoard off); env steps per second of the training loop (rollouts and updates), median of "
             f"{a.repeats} interleaved repetitions after an untimed warm-up; CPU-s per 1k steps from "
             "`time.process_time` over the whole call (setup included).", "",
             "| configuration | n_envs | env steps | env-steps/s | CPU-s per 1k steps |", "|---|---|---|---|---|"]
    for k in keys:
        n = runs[k][0]["n_envs"]
        lines.append(f"| {k} | {n} | {med[k]['steps']:.0f} | {med[k]['steps_per_s']:.0f} | "
                     f"{1000 * med[k]['cpu_s'] / med[k]['steps']:.3f} |")
    lines += ["", "| ratio | measured | goal |", "|---|---|---|",
              f"| bppo scratch / today's default scratch | {ratios['scratch']:.1f}x | >= 5x |",
              f"| bppo residual / today's default residual (PROPOSED_KF_DOB) | {ratios['residual']:.1f}x | >= 10x |",
              "| bppo residual (CLI defaults) / SB3 PPO on Pendulum-v1, 8 envs | "
              f"{ratios['residual_vs_pendulum']:.2f}x | >= 3x |", "",
              "Threads: torch 1 thread in every configuration (agents.train sets it; bppo's `torch_threads` = 1), "
              "the vector env on numba's serial kernel (`parallel=False`) in bppo. "
              f"1-min load average at the end: {load:.1f} on {os.cpu_count()} CPUs (other jobs share the machine: "
              "compare rows of one run, not across runs).", "",
              f"python {platform.python_version()}, torch {torch.__version__}, stable-baselines3 "
              f"{stable_baselines3.__version__}, numpy {np.__version__}, {platform.machine()}.", "",
              "Reproduce: `python -m experiments.bench_train`", ""]
    write_report(Path(a.out), "\n".join(lines))
    return {"median": med, "ratios": ratios}


if __name__ == "__main__":
    main()
