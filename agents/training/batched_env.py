"""The batched training env: the native AUVFollow vector env behind an
:class:`~agents.training.batched_obs.ObservationBuilder` (residual or from scratch, raw or estimator
observation), for :mod:`agents.training.batched_ppo`.

One ``step`` is one kernel call for the N envs plus one call of the base controller (and
estimator / observer) on the whole batch: nothing runs per env in Python.

**Autoreset** follows the vector env (Gymnasium's ``NEXT_STEP``): on the step after env i
ended, its action is ignored, its reward is 0 and its observation is the new episode's first.
So the last observation of an episode is returned like any other (the trainer bootstraps a
truncated episode from it) and the transition out of it is a dummy, flagged by
``prev_done`` (the trainer drops it from the loss).

**Random phases.** With ``random_phase=True`` each env's *first* episode is truncated after a
uniformly drawn number of steps in [1, episode length] (drawn from ``seed``), so the batch does
not reset in step (all envs ending together would make every rollout look alike and end all
episodes in one update). A truncated step is an ordinary time-limit truncation (bootstrapped);
the env is then reset on the next step like an autoreset. No warm-up steps are spent.

**Threads.** ``parallel`` is passed to the vector env (default ``False``: the serial kernel;
training shares the cores with torch, and numba's threaded kernel inside a trainer cost 7.8x
the CPU of the serial one when we measured it).
"""

from __future__ import annotations

import time
from typing import Any

import gymnasium as gym
import numpy as np

import auv_follow_env  # noqa: F401  (registers the ids)
from agents.training.batched_obs import ObservationBuilder

__all__ = ["BatchedTrainEnv"]


class BatchedTrainEnv:
    """N AUVFollow envs with the agent's observation and action (module docstring).

    Args:
        env_id: an AUVFollow id.
        num_envs: N.
        seed: env i draws its episodes from generator ``seed + i``; also seeds the random phases.
        env_kwargs: overrides for ``gym.make_vec``.
        builder: keyword arguments of :class:`ObservationBuilder` (mode, controller, scale, ...).
        random_phase: truncate each env's first episode at a random length.
        parallel: the vector env's ``parallel`` (None: automatic; False: serial kernel).
    """

    def __init__(self, env_id: str, num_envs: int, seed: int = 0, env_kwargs: dict[str, Any] | None = None,
                 builder: dict[str, Any] | None = None, random_phase: bool = True,
                 parallel: bool | None = False) -> None:
        if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)) or num_envs < 1:
            raise ValueError(f"num_envs={num_envs!r} is invalid: must be an integer >= 1")
        self.venv = gym.make_vec(env_id, num_envs=int(num_envs), vectorization_mode="vector_entry_point",
                                 parallel=parallel, **(env_kwargs or {}))
        self.env_id = env_id
        self.num_envs = int(num_envs)
        self.spec = self.venv.unwrapped.task_spec if hasattr(self.venv, "unwrapped") else self.venv.task_spec
        self.builder = ObservationBuilder(self.spec, **(builder or {}))
        self.obs_dim = self.builder.dim
        self.seed = int(seed)
        self.random_phase = bool(random_phase)
        self.n_steps = int(self.spec.n_steps)
        self._rng = np.random.default_rng([self.seed, 0x5EED])
        self._cut_at = np.full(self.num_envs, np.iinfo(np.int64).max)
        self._len = np.zeros(self.num_envs, dtype=np.int64)
        self._pending = np.zeros(self.num_envs, dtype=bool)  # cut last step: reset on this one
        self._done = np.zeros(self.num_envs, dtype=bool)  # ended last step (any reason)
        self._ret = np.zeros(self.num_envs)
        self.raw: np.ndarray | None = None
        self.last_action: np.ndarray | None = None
        self.info: dict[str, Any] = {}
        self.physics_seconds = 0.0  #: wall-clock seconds in the vector env's step and reset (the kernel and the link)

    def reset(self) -> np.ndarray:
        raw, info = self.venv.reset(seed=self.seed)
        n = self.num_envs
        if self.random_phase:
            self._cut_at = self._rng.integers(1, self.n_steps + 1, size=n)
        self._len[:] = 0
        self._pending[:] = False
        self._done[:] = False
        self._ret[:] = 0.0
        self.raw, self.info = raw, info
        return self.builder.observe(raw, np.ones(n, dtype=bool))

    def step(self, actions: Any):
        """Returns (obs (N, D) float32, reward (N,), terminated (N,), truncated (N,), info) where
        ``info["prev_done"]`` marks the envs whose *previous* observation was an episode's last
        (this transition is the autoreset, a dummy) and, on steps where episodes ended naturally,
        ``info["episodes"]`` = (returns, lengths, episode_metrics dict) of those envs."""
        a = self.builder.act(actions)
        self.last_action = a  #: (N, 3) the env action of this step, in [-1, 1]
        t0 = time.perf_counter()
        raw, rew, term, trunc, info = self.venv.step(np.ascontiguousarray(a))
        prev_done = self._done.copy()
        pend = self._pending
        if pend.any():  # envs cut last step start their next episode now (their action was ignored)
            raw, rinfo = self.venv.reset(options={"reset_mask": pend.copy()})
            rew = rew.copy()
            rew[pend] = 0.0
            term = term & ~pend
            trunc = trunc & ~pend
            for key in ("true_reference", "follower_pose", "true_target"):
                if key in rinfo:  # the reset's arrays hold every env's present values (the new episodes' first)
                    info[key] = rinfo[key]
        self.physics_seconds += time.perf_counter() - t0
        start = prev_done
        self._len[start] = 0
        self._len[~start] += 1
        self._ret[start] = 0.0
        self._ret += rew
        natural = term | trunc
        cut = (self._len >= self._cut_at) & ~natural & ~start
        if cut.any():
            self._cut_at[cut] = np.iinfo(np.int64).max  # only the first episode is cut
        trunc = trunc | cut
        done = natural | cut
        out: dict[str, Any] = {"prev_done": prev_done}
        if natural.any():
            idx = np.flatnonzero(natural)
            metrics = info.get("episode_metrics", {})
            out["episodes"] = (self._ret[idx].copy(), self._len[idx].copy(),
                               {k: np.asarray(v)[idx] for k, v in metrics.items() if not k.startswith("_")})
        out["true_reference"] = info.get("true_reference")
        out["follower_pose"] = info.get("follower_pose")
        self._pending = cut
        self._done = done
        self.raw, self.info = raw, info
        feats = self.builder.observe(raw, start)
        return feats, rew, term, trunc, out

    def close(self) -> None:
        self.venv.close()
