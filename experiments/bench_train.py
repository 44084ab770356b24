"""Training throughput, side by side in one process: env-steps per second of

* SB3 PPO on Pendulum-v1 with 8 envs (agents/training/hyperparams/ppo.yml's Pendulum-v1 section:
  n_steps 512, batch 256, 10 epochs, 1 torch thread), the reference;
* SB3 PPO (ppo.yml's default section, 8 DummyVecEnv envs) on AUVFollow-Hard-v1: from scratch,
  and residual on PROPOSED_KF_DOB with the per-env residual wrapper and the v0-era history;
* the batched path (``auv-follow train``'s default algorithm ``bppo``, agents/training/batched_ppo.py,
  with the CLI defaults of agents/training/hyperparams/bppo.yml: 512 envs, estimator observation,
  2 torch threads) from scratch on AUVFollow-Easy-v1 and AUVFollow-Hard-v1, and residual on
  PROPOSED_KF_DOB on AUVFollow-Hard-v1.

Each configuration is trained by :func:`agents.training.train` (the code ``auv-follow train``
runs) with evaluation, checkpoints, TensorBoard and the final score off; the rate is the run's
own ``steps_per_s`` (env steps over the training loop's wall clock, updates included), the
median of ``--repeats`` interleaved repetitions, after one untimed warm-up of every configuration
(numba compiles its kernels once). CPU-seconds are the process's (time.process_time) over the
whole ``train`` call. For the bppo rows the report also splits the wall clock (the run's
``result.phase_seconds``): physics (vector env), filter and observer, base controller, policy
forward, PPO update, other. Writes ``results/bench_train.md``.

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

HARD, EASY = "AUVFollow-Hard-v1", "AUVFollow-Easy-v1"
PEND = "SB3 PPO, Pendulum-v1, 8 envs"
SCRATCH_EASY = "bppo (CLI defaults), Easy-v1, scratch"
RESIDUAL_HARD = "bppo (CLI defaults), Hard-v1, residual PROPOSED_KF_DOB"
#: label -> TrainConfig overrides
CONFIGS: dict[str, dict] = {
    PEND: dict(algo="ppo", env_id="Pendulum-v1", mode="scratch", n_envs=8),
    "SB3 PPO, Hard-v1, scratch": dict(algo="ppo", env_id=HARD, mode="scratch"),
    "SB3 PPO, Hard-v1, residual PROPOSED_KF_DOB": dict(algo="ppo", env_id=HARD, mode="residual",
                                                       controller="PROPOSED_KF_DOB", history_len=4),
    SCRATCH_EASY: dict(algo="bppo", env_id=EASY, mode="scratch"),
    "bppo (CLI defaults), Hard-v1, scratch": dict(algo="bppo", env_id=HARD, mode="scratch"),
    RESIDUAL_HARD: dict(algo="bppo", env_id=HARD, mode="residual", controller="PROPOSED_KF_DOB"),
}
PHASES = ("physics", "filter_observer", "base_controller", "policy_forward", "update", "other")


def run_one(overrides: dict, timesteps: int, out: Path) -> dict:
    from agents.training.config import TrainConfig
    from agents.training.runner import train

    cfg = TrainConfig(**overrides, total_timesteps=timesteps, out_dir=str(out), checkpoint_freq=0, eval_freq=0,
                      progress_bar=False, tensorboard=False, final_eval=False)
    c0, w0 = time.process_time(), time.perf_counter()
    run = train(cfg)
    cpu, wall = time.process_time() - c0, time.perf_counter() - w0
    conf = yaml.safe_load((Path(run) / "config.yaml").read_text())
    res = conf["result"]
    return {"steps": int(res["num_timesteps"]), "steps_per_s": float(res["steps_per_s"]), "cpu_s": cpu,
            "wall_s": wall, "n_envs": conf["run"]["n_envs"],
            "torch_threads": (conf.get("threads") or {}).get("torch", 1),
            **{f"phase_{k}": float(v) for k, v in (res.get("phase_seconds") or {}).items()}}


def main(argv: list[str] | None = None) -> dict:
    import stable_baselines3
    import torch

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sb3-timesteps", type=int, default=16_384, help="env steps per SB3 run")
    p.add_argument("--bppo-timesteps", type=int, default=98_304, help="env steps per bppo run (6 updates)")
    p.add_argument("--repeats", type=int, default=3, help="interleaved repetitions; the median is reported")
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
    fields = ("steps_per_s", "cpu_s", "wall_s", "steps") + tuple(f"phase_{k}" for k in PHASES)
    med = {k: {f: float(np.median([r[f] for r in v])) for f in fields if f in v[0]} for k, v in runs.items()}
    pend = med[PEND]["steps_per_s"]
    load = os.getloadavg()[0]
    lines = ["# Training throughput: SB3 PPO and the batched trainer (bppo)", "",
             "One process, every configuration trained by `agents.training.train` (evaluation, checkpoints, "
             "TensorBoard off); env steps per second of the training loop (rollouts and updates), median of "
             f"{a.repeats} interleaved repetitions after an untimed warm-up; CPU-s per 1k steps from "
             "`time.process_time` over the whole call (setup included).", "",
             "| configuration | n_envs | torch threads | env steps | env-steps/s | x SB3 Pendulum "
             "| CPU-s per 1k steps |",
             "|---|---|---|---|---|---|---|"]
    for k in CONFIGS:
        r = runs[k][0]
        lines.append(f"| {k} | {r['n_envs']} | {r['torch_threads']} | {med[k]['steps']:.0f} | "
                     f"{med[k]['steps_per_s']:.0f} | {med[k]['steps_per_s'] / pend:.1f}x | "
                     f"{1000 * med[k]['cpu_s'] / med[k]['steps']:.3f} |")
    lines += ["", "Where the bppo runs' wall clock goes (`result.phase_seconds`, share of the training loop):", "",
              "| configuration | " + " | ".join(p.replace("_", " ") for p in PHASES) + " |",
              "|---|" + "---|" * len(PHASES)]
    for k, c in CONFIGS.items():
        if c["algo"] == "bppo":
            tot = sum(med[k][f"phase_{p}"] for p in PHASES)
            lines.append(f"| {k} | " + " | ".join(f"{100 * med[k][f'phase_{p}'] / tot:.0f} %" for p in PHASES) + " |")
    ratios = {k: med[k]["steps_per_s"] / pend for k in CONFIGS}
    lines += ["", "| goal | measured | goal |", "|---|---|---|",
              f"| bppo scratch on Easy | {med[SCRATCH_EASY]['steps_per_s']:,.0f} env-steps/s, "
              f"{ratios[SCRATCH_EASY]:.1f}x SB3 Pendulum | >= 150,000 and >= 25x |",
              f"| bppo residual PROPOSED_KF_DOB on Hard | {med[RESIDUAL_HARD]['steps_per_s']:,.0f} env-steps/s | "
              ">= 100,000 |", "",
              "Threads: SB3 on 1 torch thread (agents.train sets it), bppo on `torch_threads` (bppo.yml: 2) with the "
              "vector env on numba's serial kernel (`parallel=False`). "
              f"1-min load average at the end: {load:.1f} on {os.cpu_count()} CPUs (other jobs share the machine: "
              "compare rows of one run, not across runs).", "",
              f"python {platform.python_version()}, torch {torch.__version__}, stable-baselines3 "
              f"{stable_baselines3.__version__}, numpy {np.__version__}, {platform.machine()}.", "",
              "Reproduce: `python -m experiments.bench_train`", ""]
    write_report(Path(a.out), "\n".join(lines))
    return {"median": med, "ratios": ratios}


if __name__ == "__main__":
    main()
