"""Your controller on the leaderboard (docs/benchmark.md):
auv-follow benchmark --tiers Hard --policies PROPOSED mine=examples.user_controller:GoToReference

or, from the repository root, ``python examples/user_controller.py --seeds 10`` (the same through
the library: the first ``--seeds`` published Hard test seeds; nothing is written)."""
import argparse

import numpy as np


class GoToReference:
    """Push toward the delayed reference point (body frame), damp the own velocity, turn to the target's heading."""

    def __init__(self, task_spec):  # built once per tier with the env's task spec
        self.limits = np.asarray(task_spec.force_limits, dtype=np.float64)

    def reset(self):  # called before each episode (optional)
        pass

    def predict(self, observation, state=None, episode_start=None, deterministic=True):
        obs = np.asarray(observation, dtype=np.float64)  # (n_envs, obs_dim) or (obs_dim,)
        u, v, r = obs[..., 0], obs[..., 1], obs[..., 2]
        dx, dy, dpsi = obs[..., 12], obs[..., 13], np.arctan2(obs[..., 8], obs[..., 7])
        force = np.stack([40.0 * dx - 20.0 * u, 40.0 * dy - 20.0 * v, 8.0 * dpsi - 3.0 * r], axis=-1)
        return np.clip(force / self.limits, -1.0, 1.0).astype(np.float32), state  # action in [-1, 1]


def main(argv=None):
    parser = argparse.ArgumentParser(description="score GoToReference beside PROPOSED on the Hard tier")
    parser.add_argument("--seeds", type=int, default=100, help="how many of the tier's 100 test seeds")
    args = parser.parse_args(argv)
    if not 1 <= args.seeds <= 100:
        parser.error(f"--seeds {args.seeds}: must be in [1, 100]")
    from agents.benchmark.run import benchmark
    from auv_follow_env import TIERS

    res = benchmark(["PROPOSED", "mine=examples.user_controller:GoToReference"], tiers=["Hard"],
                    seeds=TIERS["Hard"].test_seeds[:args.seeds], progress=False)
    print(res.leaderboard[["tier", "policy", "kind", "true_steady_mean_iqm"]].to_string(index=False))


if __name__ == "__main__":
    main()
