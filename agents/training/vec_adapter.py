"""The native batched AUVFollow env as a Stable-Baselines3 ``VecEnv``.

SB3 expects its own vector-env protocol: an env that finishes is reset in the same step, its
last observation is in ``infos[i]["terminal_observation"]``, and time-limit truncation is
flagged by ``infos[i]["TimeLimit.truncated"]``. Gymnasium 1.x vector envs (and
:class:`~auv_follow_env.vector_env.AUVFollowVectorEnv`) instead reset on the *next* step.
:class:`NativeVecEnv` bridges the two: after a step it resets the envs that ended at once
(``reset(options={"reset_mask": ...})``), so SB3 trains on N envs stepped by one kernel call.
It also reports ``infos[i]["episode"] = {"r", "l", "t"}`` like SB3's ``Monitor``, so the usual
``rollout/ep_rew_mean`` logging works without per-env wrappers.

Env ``i`` seeded ``seed`` draws its episodes from generator ``seed + i``, exactly like
``make_vec_env(..., seed=seed)`` with single envs, so both give the same episodes.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.vec_env.base_vec_env import VecEnv

import auv_follow_env  # noqa: F401  (registers the ids)

__all__ = ["NativeVecEnv"]


class NativeVecEnv(VecEnv):
    """``num_envs`` AUVFollow envs in one native vector env, behind SB3's ``VecEnv`` API.

    Args:
        env_id: an AUVFollow id.
        num_envs: number of envs (>= 1).
        seed: seed of env 0 (env i gets seed + i); None draws fresh entropy.
        env_kwargs: overrides passed to ``gym.make_vec`` (scenario, disturbance, delay_s, ...).
    """

    def __init__(self, env_id: str = "AUVFollow-S4-v0", num_envs: int = 8, seed: int | None = 0,
                 env_kwargs: dict[str, Any] | None = None) -> None:
        valid = list(auv_follow_env.ENV_IDS) + list(getattr(auv_follow_env, "ENV_IDS_V1", ()))
        if env_id not in valid:
            raise ValueError(f"env_id={env_id!r} is unknown: valid ids are {valid}")
        if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)) or num_envs < 1:
            raise ValueError(f"num_envs={num_envs!r} is invalid: must be an integer >= 1")
        self.venv = gym.make_vec(env_id, num_envs=int(num_envs), vectorization_mode="vector_entry_point",
                                 **(env_kwargs or {}))
        self.env_id = env_id
        self.task_spec = self.venv.task_spec
        self.render_mode = None
        super().__init__(int(num_envs), self.venv.single_observation_space, self.venv.single_action_space)
        self._seed = seed
        self._actions: np.ndarray | None = None
        self._ret = np.zeros(self.num_envs)
        self._len = np.zeros(self.num_envs, dtype=np.int64)
        self._t0 = time.time()

    # --- SB3 VecEnv API --------------------------------------------------------------------
    def reset(self) -> np.ndarray:
        seed = self._seeds if any(s is not None for s in self._seeds) else self._seed
        obs, _ = self.venv.reset(seed=seed)
        self._seeds = [None] * self.num_envs
        self._seed = None  # later resets continue each env's own generator
        self._ret[:] = 0.0
        self._len[:] = 0
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = np.asarray(actions, dtype=np.float32).reshape(self.num_envs, -1)

    def step_wait(self):
        obs, rew, term, trunc, _ = self.venv.step(self._actions)
        done = term | trunc
        self._ret += rew
        self._len += 1
        infos: list[dict[str, Any]] = [{} for _ in range(self.num_envs)]
        if done.any():
            idx = np.flatnonzero(done)
            elapsed = round(time.time() - self._t0, 6)
            for i in idx:
                infos[i]["terminal_observation"] = obs[i].copy()
                infos[i]["TimeLimit.truncated"] = bool(trunc[i] and not term[i])
                infos[i]["episode"] = {"r": float(self._ret[i]), "l": int(self._len[i]), "t": elapsed}
            new_obs, _ = self.venv.reset(options={"reset_mask": done})
            obs = obs.copy()
            obs[idx] = new_obs[idx]
            self._ret[idx] = 0.0
            self._len[idx] = 0
        return obs, rew.astype(np.float32), done, infos

    def close(self) -> None:
        self.venv.close()

    def seed(self, seed: int | None = None) -> Sequence[None | int]:
        self._seeds = [None if seed is None else seed + i for i in range(self.num_envs)]
        return self._seeds

    def get_attr(self, attr_name: str, indices=None) -> list[Any]:
        return [getattr(self, attr_name) for _ in self._get_indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices=None) -> None:
        setattr(self, attr_name, value)

    def env_method(self, method_name: str, *method_args, indices=None, **method_kwargs) -> list[Any]:
        raise NotImplementedError(f"NativeVecEnv has no per-env objects to call {method_name!r} on")

    def env_is_wrapped(self, wrapper_class: type[gym.Wrapper], indices=None) -> list[bool]:
        return [False for _ in self._get_indices(indices)]

    def get_images(self) -> Sequence[np.ndarray | None]:
        return [None for _ in range(self.num_envs)]
