"""DIAGNOSTIC ONLY - not the paper's controller and not a valid follower.

docs/paper_notes.md ("What the reproduction finds", item 4): feeding the feedforward (26) and the
yaw-rate command (29) with the *present*, undelayed target velocity instead of the delayed
one (13) may explain the paper's published steady-state numbers. A real follower does not
have that velocity, so this variant needs information the environment only gives in
``info`` (for evaluation). It exists to show what would change a result, never as a
baseline: ``experiments/reproduce_paper.py --diagnostic`` reports it separately.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from auv_follow_env.layout import OBS_DIM, decode
from auv_follow_env.params import TaskSpec
from controllers.hierarchical import Gains, HierarchicalController, inner_loop, outer_loop

__all__ = ["AppendPresentTargetVelocity", "PresentFeedforwardController"]


class AppendPresentTargetVelocity(gym.Wrapper):
    """Appends the present target velocity (u_t, v_t, r_t) from ``info`` to the observation.

    DIAGNOSTIC ONLY: this leaks the true present target state to the policy.
    """

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self.observation_space = spaces.Box(-np.inf, np.inf, (OBS_DIM + 3,), np.float32)

    def _augment(self, obs, info):
        return np.concatenate([obs, np.asarray(info["true_target"][3:6], dtype=np.float32)])

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        return self._augment(obs, info), info

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        return self._augment(obs, info), reward, terminated, truncated, info


class PresentFeedforwardController(HierarchicalController):
    """PROPOSED with eqs. (26) and (29) fed by the present target velocity (DIAGNOSTIC ONLY).

    Prediction (14) and the reference (21) are unchanged (they use the delayed velocity);
    only the feedforward velocity and r_hat in (29) use the present velocity, read from the
    three extra entries appended by :class:`AppendPresentTargetVelocity`.
    """

    obs_dims = (OBS_DIM + 3,)

    def __init__(self, spec: TaskSpec, gains: Gains | None = None) -> None:
        super().__init__(spec, prediction=True, robust=True, gains=gains,
                         name="DIAGNOSTIC_PRESENT_FF")

    def reference(self, observation) -> np.ndarray:
        return super().reference(np.atleast_2d(observation)[:, :OBS_DIM])

    def forces(self, obs: np.ndarray, reset_mask: np.ndarray) -> np.ndarray:
        o = decode(obs[:, :OBS_DIM])
        pred, ref = self._generate(o)
        pred = (pred[0], pred[1], pred[2], obs[:, OBS_DIM], obs[:, OBS_DIM + 1], obs[:, OBS_DIM + 2])
        desired = outer_loop(ref, pred, self.spec.p_d, self.gains)
        d = np.stack(desired, axis=-1)
        if reset_mask.any() or self._diff.prev is None:
            self._diff.reset(reset_mask, d)
        d_dot = self._diff(d)
        F = inner_loop(o, desired, (d_dot[:, 0], d_dot[:, 1], d_dot[:, 2]), self.spec.nominal, self.gains, True)
        return np.stack(F, axis=-1)
