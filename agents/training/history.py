"""The residual agent's settings (defaults, bounds, their check) and the finite-difference history
of the delayed target's velocities."""

from __future__ import annotations

import numpy as np

from auv_follow_env.layout import OBS_DIM, obs_slice
from controllers import ALL_CONTROLLERS

_TARGET_VEL = obs_slice("target_u", "target_r")


#: defaults, written once (used by the wrapper, the CLI and the benchmark)
DEFAULT_CONTROLLER = "PROPOSED"


DEFAULT_SCALE = 0.2  # residual authority: 0.2 of the force limits (30 N surge/sway, 6 N m yaw)


DEFAULT_HISTORY_LEN = 4  # number of lagged samples of the delayed target velocity


DEFAULT_HISTORY_STRIDE = 10  # steps between lagged samples (0.5 s at dt = 0.05 s)


MAX_HISTORY_LEN = 100  # bound of history_len (features: 3 per lag)


MAX_HISTORY_STEPS = 10_000  # bound of the memory history_len * history_stride (500 s at dt = 0.05 s)


def residual_obs_dim(include_base_action: bool = True, history_len: int = DEFAULT_HISTORY_LEN,
                     obs_dim: int = OBS_DIM) -> int:
    """Width of the wrapped observation (``obs_dim``: the env's, 16 for v0, 20 for v1)."""
    return obs_dim + (3 if include_base_action else 0) + 3 * history_len


def _check(controller: str, scale: float, history_len: int, history_stride: int) -> None:
    if controller not in ALL_CONTROLLERS:
        raise ValueError(f"controller={controller!r} is unknown: valid controllers are {list(ALL_CONTROLLERS)}")
    if isinstance(scale, bool) or not isinstance(scale, (int, float, np.integer, np.floating)) or not (
            np.isfinite(scale) and scale > 0):
        raise ValueError(f"scale={scale!r} is invalid: must be a finite number > 0 (fraction of the force limits)")
    if isinstance(history_len, bool) or not isinstance(history_len, (int, np.integer)) or history_len < 0:
        raise ValueError(f"history_len={history_len!r} is invalid: must be an integer >= 0")
    if isinstance(history_stride, bool) or not isinstance(history_stride, (int, np.integer)) or history_stride < 1:
        raise ValueError(f"history_stride={history_stride!r} is invalid: must be an integer >= 1")
    if history_len > MAX_HISTORY_LEN:
        raise ValueError(f"history_len={history_len!r} is invalid: must be at most {MAX_HISTORY_LEN}")
    if history_len * history_stride > MAX_HISTORY_STEPS:
        raise ValueError(f"history_stride={history_stride!r} is invalid: history_len * history_stride = "
                         f"{history_len * history_stride} steps of memory; at most {MAX_HISTORY_STEPS} allowed")


class DelayedTargetHistory:
    """Batched finite-difference accelerations of the delayed target (the history features).

    For each env, keeps the last ``history_len * history_stride + 1`` samples of
    (target_u, target_v, target_r) and returns, for j = 1..history_len,
    ``(x_k - x_{k - j stride}) / (j stride dt)``; samples before an episode's start are its
    first sample.
    """

    def __init__(self, history_len: int, history_stride: int, dt: float) -> None:
        self.history_len, self.history_stride, self.dt = int(history_len), int(history_stride), float(dt)
        self._len = self.history_len * self.history_stride + 1
        self._buf: np.ndarray | None = None
        self._k: np.ndarray | None = None

    def __call__(self, obs: np.ndarray, start: np.ndarray) -> np.ndarray:
        """Features (N, 3 history_len) for observations (N, OBS_DIM); ``start`` (N,) marks
        the envs whose episode begins at this observation."""
        n = obs.shape[0]
        vel = np.asarray(obs[:, _TARGET_VEL], dtype=np.float64)
        if self._buf is None or self._buf.shape[1] != n:
            self._buf = np.zeros((self._len, n, 3))
            self._k = np.zeros(n, dtype=np.int64)
            start = np.ones(n, dtype=bool)
        if np.any(start):
            self._buf[:, start] = vel[start]
            self._k[start] = 0
        idx = np.arange(n)
        self._buf[self._k % self._len, idx] = vel
        feats = [(vel - self._buf[(self._k - j * self.history_stride) % self._len, idx]) / (j * self.history_stride
                                                                                           * self.dt)
                 for j in range(1, self.history_len + 1)]
        self._k += 1
        if not feats:
            return np.zeros((n, 0), dtype=np.float32)
        return np.concatenate(feats, axis=1).astype(np.float32)
