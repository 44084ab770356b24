"""Your controller on the leaderboard (docs/benchmark.md):
auv-follow benchmark --tiers Hard --policies PROPOSED mine=examples.user_controller:GoToReference"""
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
