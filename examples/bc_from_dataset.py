"""Behaviour cloning from a Minari dataset of PROPOSED_KF_DOB, scored on the tier's test seeds.

    python examples/bc_from_dataset.py                      # Easy: 50 episodes, 30 epochs, 20 test seeds
    python examples/bc_from_dataset.py --tier Hard --episodes 100 --epochs 50 --test-seeds 100

1. ``auv-follow dataset`` records PROPOSED_KF_DOB on training seeds 0..N-1 (skipped if the id is in
   Minari's store already; MINARI_DATASETS_PATH, default ~/.minari/datasets).
2. An MLP (obs -> action, tanh output) is fitted to the dataset's (observation, action) pairs.
3. The clone, the expert and PID are scored on the tier's first published test seeds, which the
   clone never saw, with the true steady-state error and Minari's normalised score (0 = PID,
   1 = the tier's best classical controller).

A memoryless clone sees one observation; the expert carries a Kalman filter over the packets, so
the clone has less to go on than what it imitates.
"""

from __future__ import annotations

import argparse

import gymnasium as gym
import minari
import numpy as np
import torch
from torch import nn

import auv_follow_env  # noqa: F401
from agents.benchmark.protocol import resolve_tier, tier_test_seeds
from agents.cli import main as auv_follow
from controllers import make_controller
from controllers.evaluation import evaluate_batched


class Clone:
    """The fitted MLP with the SB3 ``predict`` protocol (a batch of observations or one)."""

    def __init__(self, net: nn.Module, spec) -> None:
        self.net, self.task_spec, self.name = net, spec, "BC clone"

    def predict(self, obs, state=None, episode_start=None, deterministic=True):
        with torch.no_grad():
            a = self.net(torch.as_tensor(np.asarray(obs, dtype=np.float32))).numpy()
        return a, None


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--tier", default="Easy")
    p.add_argument("--episodes", type=int, default=50, help="training episodes in the dataset (seeds 0..N-1)")
    p.add_argument("--epochs", type=int, default=30)
    p.add_argument("--test-seeds", type=int, default=20, help="the tier's first N published test seeds")
    args = p.parse_args()
    for flag in ("episodes", "epochs", "test_seeds"):
        if getattr(args, flag) < 1:
            p.error(f"--{flag.replace('_', '-')} {getattr(args, flag)}: must be at least 1")
    name, env_id = resolve_tier(args.tier)
    dataset_id = f"auv-follow-examples/{name.lower()}-proposed_kf_dob-{args.episodes}-v0"
    if dataset_id not in minari.list_local_datasets():
        auv_follow(["dataset", "--tier", name, "--policy", "PROPOSED_KF_DOB", "--seeds", f"0-{args.episodes - 1}",
                    "--id", dataset_id, "--ref-episodes", str(args.test_seeds)])
    ds = minari.load_dataset(dataset_id)
    obs = np.concatenate([ep.observations[:-1] for ep in ds.iterate_episodes()])
    act = np.concatenate([ep.actions for ep in ds.iterate_episodes()])
    print(f"{dataset_id}: {len(obs)} (observation, action) pairs from {ds.total_episodes} episodes")

    torch.manual_seed(0)
    net = nn.Sequential(nn.Linear(obs.shape[1], 256), nn.Tanh(), nn.Linear(256, 256), nn.Tanh(),
                        nn.Linear(256, act.shape[1]), nn.Tanh())
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    x, y = torch.as_tensor(obs), torch.as_tensor(act)
    gen = torch.Generator().manual_seed(0)
    for epoch in range(args.epochs):
        perm = torch.randperm(len(x), generator=gen)
        total = 0.0
        for i in range(0, len(x), 512):
            idx = perm[i:i + 512]
            loss = nn.functional.mse_loss(net(x[idx]), y[idx])
            opt.zero_grad()
            loss.backward()
            opt.step()
            total += float(loss.detach()) * len(idx)
        if epoch in (0, args.epochs - 1) or (epoch + 1) % 10 == 0:
            print(f"epoch {epoch + 1:3d}: action MSE {total / len(x):.5f}")

    spec = gym.make(env_id).unwrapped.task_spec
    seeds = tier_test_seeds(name)[:args.test_seeds]
    policies = [Clone(net, spec), make_controller("PROPOSED_KF_DOB", spec), make_controller("PID", spec)]
    names = ["BC clone", "PROPOSED_KF_DOB (expert)", "PID"]
    rows = evaluate_batched(policies, env_id, seeds, policy_names=names, progress=False)
    score = rows.groupby("policy", sort=False).agg(steady=("true_steady_mean", "mean"), ret=("return", "mean"),
                                                   lost=("terminated", "sum"))
    print(f"\n{env_id}, {len(seeds)} test seeds (never in the dataset)")
    print(f"{'policy':28s} {'steady error [m]':>16s} {'normalised score':>17s} {'lost':>5s}")
    for label, r in score.iterrows():
        norm = float(minari.get_normalized_score(ds, np.array([r["ret"]]))[0])
        print(f"{label:28s} {r['steady']:16.3f} {norm:17.3f} {int(r['lost']):5d}")


if __name__ == "__main__":
    main()
