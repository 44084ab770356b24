"""Does spinning pay? A physical check of the learned policies' spin (docs/benchmark.md, "The
longer from-scratch runs spin").

PROPOSED_KF_DOB computes its surge and sway forces in the body frame from the current heading at
every step, so it tracks whatever the hull's heading does. Here its yaw moment is replaced by a
constant share of the limit (0: no yaw control; 1: the limit, a steady spin as the learned
policies hold it) while the surge and sway law is unchanged, and the steady-state true tracking
error (eq. (65)) is compared with the law's own yaw control on the same training seeds (500-563,
never a test seed; a diagnostic, nothing is chosen). The mean |r| of each setting is measured on
the same seeds over the steady window.

Reading: if a spin made the position easier to hold (through the hull's damping or its Coriolis
terms), the spinning law would track better; if the heading does not matter to the position
metric, "no yaw control" tracks as the law does.

    python -m experiments.spin_cost
"""

from __future__ import annotations

import argparse
from pathlib import Path

import gymnasium as gym
import numpy as np

import auv_follow_env  # noqa: F401
from auv_follow_env.layout import decode
from controllers import make_controller
from controllers.evaluation import evaluate_batched
from experiments.outputs import output_path, write_report

SEEDS = tuple(range(500, 564))
SHARES = (None, 0.0, 0.25, 1.0)  #: the yaw moment's share of its limit (None: the law's own)


class YawOverride:
    """PROPOSED_KF_DOB with its yaw action replaced by ``share`` (of the limit; None keeps it)."""

    def __init__(self, spec, share: float | None) -> None:
        self.base = make_controller("PROPOSED_KF_DOB", spec)
        self.share = share
        self.name = "PROPOSED_KF_DOB" if share is None else f"PROPOSED_KF_DOB, yaw moment {share:g} of its limit"

    def predict(self, observation, state=None, episode_start=None, deterministic=True):
        act, state = self.base.predict(observation, state, episode_start, deterministic)
        if self.share is not None:
            act = np.array(act, copy=True)
            act[..., 2] = self.share
        return act, state

    def reference(self, observation):
        return self.base.reference(observation)

    def reset(self) -> None:
        self.base.reset()


def mean_yaw_rate(env_id: str, share: float | None, seeds: tuple[int, ...], steady_s: float) -> float:
    """Mean |r| [rad/s] of the follower over t >= steady_s, one episode per seed."""
    n = len(seeds)
    venv = gym.make_vec(env_id, num_envs=n, vectorization_mode="vector_entry_point")
    spec = venv.unwrapped.task_spec
    pol = YawOverride(spec, share)
    obs, _ = venv.reset(seed=list(seeds))
    start = np.ones(n, dtype=bool)
    alive = np.ones(n, dtype=bool)
    tot = cnt = 0.0
    for k in range(int(spec.n_steps)):
        a, _ = pol.predict(obs, episode_start=start)
        start[:] = False
        obs, _, term, trunc, _ = venv.step(a)
        alive &= ~(term | trunc)
        if k * spec.dt >= steady_s:
            r = np.abs(decode(np.asarray(obs, dtype=np.float64))["r"])
            tot += float(r[alive].sum())
            cnt += int(alive.sum())
    venv.close()
    return tot / max(cnt, 1)


def main(argv: list[str] | None = None) -> str:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--tiers", nargs="+", default=["Easy", "Medium", "Hard"])
    p.add_argument("--out", default=None, help="Markdown output (default: results/spin_cost.md)")
    a = p.parse_args(argv)
    a.out = output_path(a, p, Path("results/spin_cost.md"))
    lines = ["# Does spinning pay? PROPOSED_KF_DOB with its yaw moment replaced", "",
             "Reproduce: `python -m experiments.spin_cost` (method in its docstring). Training seeds "
             f"{SEEDS[0]}-{SEEDS[-1]}, one episode each; steady-state true tracking error [m] (eq. (65)): IQM "
             "and mean over episodes; mean |r| of the follower over the steady window.", "",
             "| tier | yaw moment | steady error IQM [m] | steady error mean [m] | mean abs r [rad/s] |",
             "|---|---|---|---|---|"]
    for tier in a.tiers:
        env_id = f"AUVFollow-{tier}-v1"
        spec = gym.make(env_id).unwrapped.task_spec
        for share in SHARES:
            df = evaluate_batched([YawOverride(spec, share)], env_id, SEEDS, progress=False)
            x = np.sort(df["true_steady_mean"].to_numpy())
            q = len(x) // 4
            r = mean_yaw_rate(env_id, share, SEEDS, float(spec.steady_start_s))
            label = "the law's own" if share is None else f"{share:g} of the limit"
            lines.append(f"| {tier} | {label} | {x[q:len(x) - q].mean():.4f} | {x.mean():.4f} | {r:.3f} |")
            print(lines[-1], flush=True)
    lines.append("")
    return write_report(Path(a.out), "\n".join(lines))


if __name__ == "__main__":
    main()
